"""Learning on the robot: the learner node beside a running simulator, and its refit times.

1. Live (node processes on the default middleware): ``sim_node`` exploring ``full`` for
   ``LEARN_STEPS`` steps (default 6000) at ``LEARN_RATE`` steps/s (default 50), the learner
   node (warm-up 1000 steps, a refit every 1000), a filter node waiting for its first
   version (``wait_for_model``) and a recorder of the simulator's step topics and
   ``/tpsr/state``. Figures: the versions announced and their steps, refit times, the
   last policy's score by the standard evaluation (``learner evaluate``), whether
   ``learner fit RECORDING --init-from DIR/model.npz`` is the last version (max abs
   difference of the arrays), and the filter node's swaps and any gap in the stamps of
   ``/tpsr/state`` after its first version.
2. Refit times at 6000, 12000 and 24000 steps (target at 24000: <= 1 s for the model from
   the sums): one refit on the first version's basis as the learner node runs it
   (``tpsr_ros.learner_node.refits.refit``): at its default (two passes over every step),
   and with ``forgetting`` 0.9995 continuing the statistics of the refit 1000 steps before;
   the TPSR fit alone, the solve of the sums alone, and the whole refit with its fitted-Q
   policy and files; median of 3.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

STEPS = int(os.environ.get("LEARN_STEPS", "6000"))
RATE = float(os.environ.get("LEARN_RATE", "50"))
WARMUP, REFIT = 1000, 1000
SIZES = (6000, 12000, 24000)
FORGETTING = 0.9995


def live_run(tmp: Path) -> None:
    from learner.cli import main as learner_main
    from tpsr_ros.io import messages as m
    from tpsr_ros.io.bag import BagReader
    from tpsr_ros.io.model_io import open_model
    from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions
    from tpsr_ros.runtime.backend import choose_backend, open_transport
    from tpsr_ros.runtime.launcher import Launch

    output, recording = tmp / "live", tmp / "recording"
    os.environ.setdefault("ROS_DOMAIN_ID", "61")
    backend, _ = choose_backend()
    transport = open_transport(backend, "bench_probe", "/")
    probe = Node(NodeOptions(name="bench_probe"), transport=transport)
    updates: list[dict] = []
    infos: list[dict] = []
    probe.create_subscription("/tpsr/model_update", "std_msgs/msg/String",
                              lambda x: updates.append(json.loads(x.data)), LATCHED_QOS)
    probe.create_subscription("/tpsr/model_info", "std_msgs/msg/String",
                              lambda x: infos.append(json.loads(x.data)), LATCHED_QOS)
    expected = 1 + (STEPS - WARMUP) // REFIT
    start = time.monotonic()
    try:
        with Launch(tmp / "logs", spin=probe.spin_once, timeout_s=STEPS / RATE + 300) as launch:
            learner = launch.start("learner", "tpsr_ros.learner_node", [
                "--ros-args", "-p", f"output:={output}", "-p", "environment:=full",
                "-p", f"warmup_steps:={WARMUP}", "-p", f"refit_steps:={REFIT}",
            ])
            filt = launch.start("filter", "tpsr_ros.filter_node", [
                "--ros-args", "-p", "wait_for_model:=true", "-p", "jump_threshold:=60.0",
            ])
            launch.wait("the learner's subscriptions", lambda: "learning from" in learner.text())
            launch.wait("the filter waiting", lambda: "waiting for one" in filt.text())
            recorder = launch.start("record", "tpsr_ros.record", [
                "-o", str(recording), "/camera/image_raw", "/action", "/ground_truth/pose",
                "/reward", "/clock", "/sim/episode_start", "/tpsr/state",
            ])
            time.sleep(2.0)  # the learner and the recorder discover each other's peers
            sim = launch.start("sim", "sim_node", [
                "--ros-args", "-p", "mode:=explore", "-p", "environment:=full",
                "-p", f"rate:={RATE:g}", "-p", f"steps:={STEPS}", "-p", "wait_for_subscribers:=1",
            ])
            launch.wait("the simulator's last step", lambda: "explore finished" in sim.text())
            # steps lost to discovery at the start leave the last due point unreached
            settled = time.monotonic() + 30
            launch.wait(f"{expected} versions (or 30 s after the last step)",
                        lambda: len(updates) >= expected or time.monotonic() > settled)
            last_version = updates[-1]["version"] if updates else None
            launch.wait("the filter's acknowledgement of the last version",
                        lambda: any(i.get("version") == last_version for i in infos))
            recorder.stop(timeout_s=30)
    finally:
        probe.close()
    elapsed = time.monotonic() - start
    print(f"   {len(updates)} versions in {elapsed:.0f} s: steps "
          f"{[u['steps'] for u in updates]}", flush=True)
    last = updates[-1]
    quiet = contextlib.redirect_stderr(io.StringIO())
    with contextlib.redirect_stdout(io.StringIO()) as out, quiet:
        learner_main(["evaluate", last["policy"], "--environment", "full"])
    score = float(out.getvalue().strip().splitlines()[-1].split(":")[1])
    offline = tmp / "offline.npz"
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        learner_main(["fit", str(recording), "--init-from", str(output / "model.npz"),
                      "-o", str(offline)])
    a, b = open_model(offline).model.to_arrays(), open_model(last["path"]).model.to_arrays()
    difference = max(float(np.abs(a[k] - b[k]).max()) for k in a)
    with BagReader(recording) as reader:
        steps = reader.message_counts.get("/camera/image_raw", 0)
        stamps = np.array([m.stamp_of(x.decode()) for x in reader.messages(["/tpsr/state"])])
    gaps = int(np.count_nonzero(np.diff(stamps) != 10**9)) if stamps.size > 1 else -1
    swaps = max((i.get("swaps", 0) for i in infos), default=0)
    print(f"last version v{last['version']} ({last['steps']} steps): score {score:.1f} by "
          f"learner evaluate (target >= 460); recording {steps} steps; learner fit "
          f"--init-from on it: max abs difference {difference:.3g} (target <= 1e-9); filter "
          f"node: {swaps} swaps, {stamps.size} states, {gaps} gaps in their stamps", flush=True)


def refit_times(tmp: Path) -> None:
    from sim_node import SimConfig
    from sim_node.generate import generate_bag
    from tpsr_ros.io.trajectory import LiveSteps
    from tpsr_ros.learner_node.refits import RefitRequest, refit

    bag = tmp / "steps"
    generate_bag(bag, SimConfig(environment="full"), max(SIZES), seed=5)
    live = LiveSteps.of_bag(bag, "full")
    first = refit(RefitRequest(live.chunk(WARMUP), 1, tmp / "out", "best"))
    for size in SIZES:
        before = refit(RefitRequest(live.chunk(size - REFIT), 2, tmp / "out", "best",
                                    basis_model=first.model, forgetting=FORGETTING))  # fmt: skip
        fits, two_pass, totals, solves = [], [], [], []
        for run in range(3):
            result = refit(RefitRequest(live.chunk(size), 3 + run, tmp / "out", "best",
                                        basis_model=first.model, forgetting=FORGETTING,
                                        previous=before.summed))  # fmt: skip
            fits.append(result.fit_seconds)
            start = time.perf_counter()
            result.summed.statistics.solve()
            solves.append(time.perf_counter() - start)
            default = refit(RefitRequest(live.chunk(size), 3 + run, tmp / "out", "best",
                                         basis_model=first.model))  # fmt: skip
            two_pass.append(default.fit_seconds)
            totals.append(default.total_seconds)
        fit = statistics.median(fits)
        met = "met" if fit <= 1 else "NOT met"
        verdict = f" (target <= 1 s: {met})" if size == max(SIZES) else ""
        print(f"refit of {size} steps on the first version's basis: TPSR fit at the default "
              f"(two passes) median {statistics.median(two_pass):.2f} s, with the fitted-Q "
              f"policy and the files {statistics.median(totals):.2f} s; with forgetting "
              f"{FORGETTING} from the sums (the last {REFIT} steps added) "
              f"{fit:.2f} s{verdict}, the solve alone {statistics.median(solves) * 1e3:.1f} ms",
              flush=True)  # fmt: skip


def main() -> None:
    with tempfile.TemporaryDirectory(prefix="bench_learn_online_") as tmpdir:
        tmp = Path(tmpdir)
        if not os.environ.get("LEARN_LIVE_ONLY"):
            refit_times(tmp)
        try:
            live_run(tmp)
        except Exception:
            for log in sorted((tmp / "logs").glob("*")):
                print(f"--- {log.name}\n{log.read_text()[-3000:]}")
            raise


if __name__ == "__main__":
    main()
