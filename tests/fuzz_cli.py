"""The hostile-input acceptance run: mutate what users hand us and run it as they would.

    python tests/fuzz_cli.py --minutes 15 [--seed S] [--out DIR]     (make fuzz-cli)
    python tests/fuzz_cli.py --seed S --case N                        (rerun one case)

Each case mutates one input of a known-good set (a small simulated bag: its ``.mcap`` bytes,
its chunks' contents behind valid CRCs, its messages inside a valid file, its
``metadata.yaml``; a model and a policy ``.npz``: bytes, the JSON metadata, ``.npy`` headers,
array contents, compression bombs; ``-p name:=value`` values; params files) and runs one
real entry point on it as a subprocess, the way a user would: ``learner fit|plot|policy|
evaluate|info``, ``tpsr_ros.play``, ``tpsr_ros.bag_info``, ``tpsr_ros.bag_recover``, and the
filter, simulator, player and recorder nodes (in-process transport; started, and stopped
with SIGINT once they log that they run). Every run has a 2 GiB address-space cap and a 20 s
limit. Outcomes:

- ``error``: a non-zero exit whose last stderr line is ``<prog>: error: <one line>``;
- ``success``: exit 0 (a node: it started and stopped cleanly on SIGINT);
- failures: ``traceback``, ``over-memory`` (an allocation failed under the cap),
  ``hang`` (20 s), ``signal`` (killed by a signal), ``unclear`` (non-zero exit with no
  error line), ``destroyed`` (``bag_recover`` changed or removed an input it did not keep).
  A run past 20 s is rerun once: a hang must reproduce; one that does not (the machine is
  shared: a niced run can be starved) is counted and listed as ``slow``. A hung process
  gets SIGABRT before SIGKILL, so Python's faulthandler shows where each thread was.

Cases are drawn from ``numpy.random.default_rng([seed, case])``, so ``--seed S --case N``
reruns one exactly; every failure's input, command and stderr are saved under
``OUT/failures/<case>/``. Exit status 1 when any case failed.
"""

from __future__ import annotations

import argparse
import dataclasses
import io
import json
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import time
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
sys.path.insert(0, str(HERE))
sys.path.insert(0, str(ROOT))

from fuzz_mutators import (  # noqa: E402
    HOSTILE_SCALARS,
    mutate_mcap,
    mutate_npz,
    mutate_yaml,
    pick,
    rewrite_messages,
)
from test_fuzz import mutate  # noqa: E402  (the byte-level mutator the CI fuzz suite uses)

PY = sys.executable
SPLIT_BAG = HERE / "data" / "rosbag2" / "multiple_files"
MEMORY_CAP = 2 * 2**30
TIMEOUT_S = 20.0
FAILURES = ("traceback", "over-memory", "hang", "signal", "unclear", "destroyed")
_ALLOCATION = re.compile(
    r"MemoryError|Unable to allocate|Cannot allocate memory|bad_alloc|out of memory"
)
_ERROR_LINE = re.compile(r"^\S.*: (error: .+|interrupted)$")
_LOG_LINE = re.compile(r"^\[(INFO|WARN|ERROR|DEBUG)\] \[")

# hostile scalars for YAML values and -p values (rcl parses -p values as YAML 1.2 scalars)
# -- the known-good inputs ----------------------------------------------------------------


@dataclass(frozen=True)
class Fixtures:
    """Valid inputs every case starts from (built once per run, deterministically)."""

    root: Path
    bag: Path
    model: Path
    policy: Path
    bomb_member: Path  # a deflated .npy of 1.5 GiB of zeros (about 1.5 MB)


def _run_quiet(argv: list[str], cwd: Path) -> None:
    result = subprocess.run(argv, cwd=cwd, capture_output=True, text=True, env=_env())
    if result.returncode != 0:
        raise SystemExit(f"fixture step failed: {' '.join(argv)}\n{result.stderr}")


def _env() -> dict[str, str]:
    return {
        **os.environ,
        "PYTHONPATH": str(ROOT),
        "TPSR_TRANSPORT": "inproc",
        "PYTHONWARNINGS": "default",
        "PYTHONFAULTHANDLER": "1",
        "OMP_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
        "MPLBACKEND": "Agg",
    }


def _bomb_member(path: Path, n_bytes: int = 3 * 2**29) -> None:
    """A zip member body: an .npy of ``n_bytes`` zeros, deflated (raw) in constant memory."""
    header = io.BytesIO()
    np.lib.format.write_array_header_1_0(
        header, {"descr": "<f8", "fortran_order": False, "shape": (n_bytes // 8,)}
    )
    packer = zlib.compressobj(9, zlib.DEFLATED, -15)
    zeros = bytes(2**24)
    with path.open("wb") as out:
        out.write(packer.compress(header.getvalue()))
        for _ in range(n_bytes // len(zeros)):
            out.write(packer.compress(zeros))
        out.write(packer.flush())
    crc = zlib.crc32(header.getvalue())
    for _ in range(n_bytes // len(zeros)):
        crc = zlib.crc32(zeros, crc)
    meta = {"size": len(header.getvalue()) + n_bytes, "crc": crc}
    path.with_suffix(".json").write_text(json.dumps(meta))


def build_fixtures(root: Path) -> Fixtures:
    """A 800-step simulated bag, a small TPSR model fitted on it and a policy."""
    root.mkdir(parents=True, exist_ok=True)
    fixtures = Fixtures(root, root / "bag", root / "model.npz", root / "policy.npz",
                        root / "bomb.deflate")
    if not fixtures.bag.exists():
        _run_quiet([PY, "-m", "sim_node.generate", "--environment", "full", "--steps", "800",
                    "--seed", "1", "-o", str(fixtures.bag)], root)
    if not fixtures.model.exists():
        _run_quiet([PY, "-m", "learner", "fit", str(fixtures.bag), "-o", str(fixtures.model),
                    "--obs-centers", "100", "--ht-centers", "100"], root)
    if not fixtures.policy.exists():
        _run_quiet([PY, "-m", "learner", "policy", str(fixtures.model), str(fixtures.bag),
                    "-o", str(fixtures.policy)], root)
    if not fixtures.bomb_member.exists():
        _bomb_member(fixtures.bomb_member)
    return fixtures


# -- cases ----------------------------------------------------------------------------------


@dataclass
class Case:
    """One run: the command, its working directory, and what to save if it fails."""

    family: str
    argv: list[str]
    cwd: Path
    node: bool = False  # start, wait for its first log line, stop with SIGINT
    inputs: list[Path] = field(default_factory=list)
    recover_inputs: dict[str, Path] | None = None  # bag_recover: file name -> saved copy


def _copy_bag(fixtures: Fixtures, target: Path) -> Path:
    shutil.copytree(fixtures.bag, target)
    return target


def _learner_on_bag(bag: Path, fixtures: Fixtures, rng: np.random.Generator,
                    work: Path) -> list[str]:
    which = int(rng.integers(4))
    if which == 0:
        return [PY, "-m", "learner", "fit", str(bag), "-o", str(work / "out.npz"),
                "--obs-centers", "100", "--ht-centers", "100"]
    if which == 1:
        return [PY, "-m", "learner", "plot", str(fixtures.model), str(bag),
                "-o", str(work / "out.png")]
    if which == 2:
        return [PY, "-m", "learner", "policy", str(fixtures.model), str(bag),
                "-o", str(work / "out.npz")]
    return [PY, "-m", "learner", "fit", str(bag), "-o", str(work / "out.npz"),
            "--method", "pca"]


def _bag_reader_command(bag: Path, fixtures: Fixtures, rng: np.random.Generator,
                        work: Path) -> tuple[list[str], bool]:
    which = int(rng.integers(4))
    if which == 0:
        return [PY, "-m", "tpsr_ros.bag_info", str(bag)], False
    if which == 1:
        return [PY, "-m", "tpsr_ros.play", str(bag), "--rate", "1000000"], True
    return _learner_on_bag(bag, fixtures, rng, work), False


def make_case(seed: int, index: int, fixtures: Fixtures, work: Path) -> Case:
    """Case ``index`` of run ``seed``: a mutated input in ``work`` and the command to run."""
    rng = np.random.default_rng([seed, index])
    family = pick(rng, ("mcap", "chunk", "messages", "metadata", "recover", "split-recover",
                         "model", "policy", "param", "params-file"))
    work.mkdir(parents=True)
    if family == "split-recover":  # rosbag2's 3-file bag, one or two files damaged
        bag = work / "bag"
        bag.mkdir()
        files = sorted(SPLIT_BAG.glob("*.mcap"))
        for file in files:
            shutil.copy(file, bag)
        for file in {pick(rng, files) for _ in range(int(rng.integers(1, 3)))}:
            target = bag / file.name
            data = target.read_bytes()
            target.write_bytes(mutate(data, rng) if rng.integers(2) else mutate_mcap(data, rng))
        return _recover_case(family, bag, work, rng)
    if family in ("mcap", "chunk", "messages", "metadata", "recover"):
        bag = _copy_bag(fixtures, work / "bag")
        mcap = bag / "bag.mcap"
        if family == "metadata":
            meta = bag / "metadata.yaml"
            meta.write_bytes(mutate_yaml(meta.read_bytes(), rng))
            argv, node = _bag_reader_command(bag, fixtures, rng, work)
            return Case(family, argv, work, node, [bag])
        if family == "messages":
            rewrite_messages(fixtures.bag / "bag.mcap", mcap, rng)
        else:
            data = mcap.read_bytes()
            mcap.write_bytes(mutate(data, rng) if family == "mcap" and rng.integers(2)
                             else mutate_mcap(data, rng))
        if family == "recover" or rng.integers(5) == 0:
            (bag / "metadata.yaml").unlink()
            return _recover_case("recover", bag, work, rng)
        argv, node = _bag_reader_command(bag, fixtures, rng, work)
        return Case(family, argv, work, node, [bag])
    if family in ("model", "policy"):
        source = fixtures.model if family == "model" else fixtures.policy
        target = work / source.name
        target.write_bytes(mutate_npz(source.read_bytes(), rng, fixtures.bomb_member))
        which = int(rng.integers(4))
        if family == "model":
            argv = [
                [PY, "-m", "learner", "info", str(target)],
                [PY, "-m", "learner", "plot", str(target), str(fixtures.bag), "-o",
                 str(work / "out.png")],
                [PY, "-m", "learner", "evaluate", str(fixtures.policy), "--environment", "full",
                 "--model", str(target)],
                [PY, "-m", "tpsr_ros.filter_node", "--ros-args", "-p", f"model:={target}",
                 "-p", f"policy:={fixtures.policy}"],
            ][which]
        else:
            argv = [
                [PY, "-m", "learner", "evaluate", str(target), "--environment", "full",
                 "--model", str(fixtures.model)],
                [PY, "-m", "tpsr_ros.filter_node", "--ros-args", "-p",
                 f"model:={fixtures.model}", "-p", f"policy:={target}"],
            ][which % 2]
        return Case(family, argv, work, "filter_node" in argv[2], [target])
    node_module, base, params = pick(rng, _nodes(fixtures))
    if family == "param":
        name = pick(rng, (*params, "use_sim_time", "x", "qos_overrides./a.reliability"))
        value = pick(rng, HOSTILE_SCALARS) if rng.integers(3) else mutate(
            b"[1.0, 2.5]" if rng.integers(2) else b"full", rng).decode("utf-8", "replace")
        value = value.replace("\x00", "")  # a command line cannot hold NUL
        argv = [PY, "-m", node_module, *base, "-p", f"{name}:={value}"]
        return Case(family, argv, work, True, [])
    target = work / "params.yaml"
    node_name = {"sim_node": "sim_node", "tpsr_ros.filter_node": "tpsr_filter",
                 "tpsr_ros.play": "tpsr_player", "tpsr_ros.record": "tpsr_recorder"}[node_module]
    template = _params_template(node_name, params, fixtures)
    target.write_bytes(mutate_yaml(template, rng))
    argv = [PY, "-m", node_module, *base, "--params-file", str(target)]
    return Case(family, argv, work, True, [target])


def _recover_case(family: str, bag: Path, work: Path, rng: np.random.Generator) -> Case:
    """bag_recover on ``bag``; its .mcap files are saved to check nothing is destroyed."""
    saved = {}
    (work / "inputs").mkdir()
    for file in sorted(bag.glob("*.mcap")):
        saved[file.name] = work / "inputs" / file.name
        shutil.copy(file, saved[file.name])
    argv = [PY, "-m", "tpsr_ros.bag_recover", str(bag)]
    if rng.integers(3) == 0:
        argv.append("--keep-original")
    return Case(family, argv, work, False, [work / "inputs"], recover_inputs=saved)


def _nodes(fixtures: Fixtures) -> list[tuple[str, list[str], tuple[str, ...]]]:
    from sim_node.node import SimNodeParams
    from tpsr_ros.filter_node import FilterNodeParams
    from tpsr_ros.runtime.params import param_specs

    filter_params = tuple(s.name for s in param_specs(FilterNodeParams))
    sim_params = tuple(s.name for s in param_specs(SimNodeParams))
    return [
        ("sim_node", ["--ros-args", "-p", "rate:=50.0"], sim_params),
        ("tpsr_ros.filter_node", ["--ros-args", "-p", f"model:={fixtures.model}", "-p",
                                  f"policy:={fixtures.policy}"], filter_params),
        ("tpsr_ros.play", [str(fixtures.bag), "--rate", "1000000", "--ros-args"], ()),
        ("tpsr_ros.record", ["-o", "rec", "--ros-args"], ()),
    ]


def _params_template(node_name: str, params: tuple[str, ...], fixtures: Fixtures) -> bytes:
    from sim_node.node import SimNodeParams
    from tpsr_ros.filter_node import FilterNodeParams
    from tpsr_ros.runtime.params import param_specs

    specs = {s.name: s for s in (*param_specs(SimNodeParams), *param_specs(FilterNodeParams))}
    lines = ["/**:", "  ros__parameters:", "    use_sim_time: false",
             f"{node_name}:", "  ros__parameters:"]
    for name in params:
        value = {"model": str(fixtures.model), "policy": str(fixtures.policy)}.get(
            name, specs[name].default)
        value = list(value) if isinstance(value, tuple) else value
        lines.append(f"    {name}: {json.dumps(value)}")
    return ("\n".join(lines) + "\n").encode()


# -- running and judging ---------------------------------------------------------------------


def _limits() -> None:
    # a shell starts background jobs with SIGINT ignored, and a child inherits that: give
    # the node the terminal's default, or a SIGINT before its handler is installed is lost
    signal.signal(signal.SIGINT, signal.SIG_DFL)
    resource.setrlimit(resource.RLIMIT_AS, (MEMORY_CAP, MEMORY_CAP))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))


@dataclass
class Outcome:
    """How a case ended."""

    kind: str
    returncode: int | None
    stderr: str
    seconds: float
    max_rss_mb: float
    cpu_seconds: float = 0.0


def run_case(case: Case) -> Outcome:
    """Run the case's command under the caps and classify the result."""
    out_path, err_path = case.cwd / "stdout.txt", case.cwd / "stderr.txt"
    start = time.monotonic()
    with out_path.open("wb") as out, err_path.open("wb") as err:
        process = subprocess.Popen(case.argv, cwd=case.cwd, stdout=out, stderr=err,
                                   stdin=subprocess.DEVNULL, env=_env(), preexec_fn=_limits,
                                   start_new_session=True)
    status, usage, interrupted, hung = None, None, False, False
    while status is None:
        pid, raw, rusage = os.wait4(process.pid, os.WNOHANG)
        if pid:
            status, usage = raw, rusage
            break
        elapsed = time.monotonic() - start
        if elapsed > TIMEOUT_S:  # SIGABRT first: faulthandler dumps where every thread is
            hung = True
            os.killpg(process.pid, signal.SIGABRT)
            time.sleep(1.0)
            os.killpg(process.pid, signal.SIGKILL)
            _, status, usage = os.wait4(process.pid, 0)
            break
        if case.node and not interrupted and _started(out_path, err_path):
            time.sleep(0.3)
            os.killpg(process.pid, signal.SIGINT)
            interrupted = True
        time.sleep(0.01)
    process.returncode = 0  # reaped by wait4; keep Popen from waiting again
    seconds = time.monotonic() - start
    stderr = err_path.read_text(errors="replace")
    rss = usage.ru_maxrss / 1024 if usage is not None else 0.0
    cpu = usage.ru_utime + usage.ru_stime if usage is not None else 0.0
    code = os.waitstatus_to_exitcode(status)
    kind = _classify(case, code, stderr, hung, interrupted)
    return Outcome(kind, code, stderr, seconds, rss, cpu)


def _started(*paths: Path) -> bool:
    for path in paths:
        text = path.read_text(errors="replace")
        if any(_LOG_LINE.match(line) for line in text.splitlines()):
            return True
    return False


def _classify(case: Case, code: int, stderr: str, hung: bool, interrupted: bool) -> str:
    if hung:
        return "hang"
    if _ALLOCATION.search(stderr):
        return "over-memory"
    if "Traceback (most recent call last)" in stderr:
        return "traceback"
    if code < 0 and not (interrupted and code == -signal.SIGINT):
        return "signal"
    if case.recover_inputs is not None and not _recover_kept_input(case, code):
        return "destroyed"
    if code == 0 or (interrupted and code in (130, -signal.SIGINT)):
        return "success"
    lines = [line for line in stderr.splitlines() if line.strip()]
    if lines and _ERROR_LINE.match(lines[-1]):
        return "error"
    return "unclear"


def _recover_kept_input(case: Case, code: int) -> bool:
    """bag_recover kept each input file unless it verified its copy and lost only a tail."""
    assert case.recover_inputs is not None
    bag = case.cwd / "bag"
    stdout = (case.cwd / "stdout.txt").read_text(errors="replace").splitlines()
    single = len(case.recover_inputs) == 1
    for name, saved in case.recover_inputs.items():
        original = saved.read_bytes()
        current, kept = bag / name, bag / f"{name}.damaged"
        if kept.exists():
            if kept.read_bytes() != original:
                return False
        elif code != 0:
            if not current.exists() or current.read_bytes() != original:
                return False
        else:
            prefix = "lost: " if single else f"lost in {name}: "
            losses = [line.strip()[len(prefix):] for line in stdout
                      if line.strip().startswith(prefix)]
            if not current.exists() or any(
                loss != "an incomplete final record" for loss in losses
            ):
                return False
    return True


def _save_failure(out: Path, seed: int, index: int, case: Case, outcome: Outcome) -> Path:
    target = out / "failures" / f"seed{seed}-case{index}"
    if target.exists():
        shutil.rmtree(target)
    shutil.copytree(case.cwd, target, ignore=shutil.ignore_patterns("*.png"))
    (target / "README.txt").write_text(
        f"seed {seed} case {index} family {case.family}: {outcome.kind} "
        f"(exit {outcome.returncode}, {outcome.seconds:.1f} s)\n"
        f"command (cwd {case.cwd}):\n  {' '.join(case.argv)}\n"
        f"rerun: {PY} tests/fuzz_cli.py --seed {seed} --case {index}\n"
    )
    return target


def _last_lines(text: str, n: int = 3) -> str:
    lines = [line for line in text.splitlines() if line.strip()]
    return " | ".join(line[:200] for line in lines[-n:])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="tests/fuzz_cli.py", description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=15.0, help="time budget (default 15)")
    parser.add_argument("--seed", type=int, default=None, help="default: the current time")
    parser.add_argument("--case", type=int, default=None, help="run only this case")
    parser.add_argument("--out", type=Path, default=Path("fuzz_output"),
                        help="fixtures, work and failures (default ./fuzz_output)")
    args = parser.parse_args(argv)
    seed = int(time.time()) if args.seed is None else args.seed
    out = args.out.resolve()
    fixtures = build_fixtures(out / "fixtures")
    print(f"fuzz_cli: seed {seed}; budget {args.minutes} min; output {out}", flush=True)
    cases = [args.case] if args.case is not None else None
    deadline = time.monotonic() + args.minutes * 60
    counts: Counter[str] = Counter()
    families: dict[str, Counter[str]] = {}
    failures: list[str] = []
    max_rss = 0.0
    index = 0
    while (cases is None and time.monotonic() < deadline) or (cases and index < 1):
        case_id = cases[0] if cases else index
        work = out / "work" / f"{case_id}"
        shutil.rmtree(work, ignore_errors=True)
        case = make_case(seed, case_id, fixtures, work)
        outcome = run_case(case)
        note = ""
        if outcome.kind == "hang":  # a hang must reproduce: the machine is shared and loaded
            shutil.rmtree(work, ignore_errors=True)
            rerun = run_case(make_case(seed, case_id, fixtures, work))
            note = (f" (first run {outcome.cpu_seconds:.1f} s of CPU in {outcome.seconds:.0f} s;"
                    f" rerun: {rerun.kind} in {rerun.seconds:.1f} s)")
            if rerun.kind != "hang":
                outcome = dataclasses.replace(outcome, kind="slow")
        counts[outcome.kind] += 1
        families.setdefault(case.family, Counter())[outcome.kind] += 1
        max_rss = max(max_rss, outcome.max_rss_mb)
        if outcome.kind in (*FAILURES, "slow") or args.case is not None:
            saved = _save_failure(out, seed, case_id, case, outcome)
            failures.append(f"case {case_id} [{case.family}] {outcome.kind}{note}: "
                            f"{' '.join(a[:80] for a in case.argv[2:])}\n"
                            f"    {_last_lines(outcome.stderr)}\n    saved in {saved}")
        shutil.rmtree(work, ignore_errors=True)
        index += 1
    total = sum(counts.values())
    print(f"fuzz_cli: seed {seed}: {total} cases in {args.minutes} min; largest RSS "
          f"{max_rss:.0f} MB")
    for kind in ("error", "success", *FAILURES, "slow"):
        print(f"  {kind:14s} {counts.get(kind, 0)}")
    for family, outcome_counts in sorted(families.items()):
        print(f"  {family:14s} " + ", ".join(f"{k} {v}" for k, v in sorted(outcome_counts.items())))
    for line in failures:
        print(line)
    return 1 if any(counts.get(kind) for kind in FAILURES) else 0


if __name__ == "__main__":
    sys.exit(main())
