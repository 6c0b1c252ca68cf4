"""``learner closed-loop POLICY --environment E``: the standard evaluation over the nodes.

The headless protocol of :mod:`learner.evaluate`, run by the real nodes as separate
processes over the DDS backend (a fresh ``ROS_DOMAIN_ID``, loopback only unless
``CYCLONEDDS_URI`` says otherwise):

1. ``python -m sim_node --ros-args -p mode:=command -p environment:=E -p seed:=2026
   -p episode_steps:=50`` (and, with ``--record BAG``, ``python -m tpsr_ros.record``);
2. an in-process driver node waits for the simulator's start-up reset, publishes
   ``/sim/reset`` to the first start position and waits for its ``/sim/episode_start``;
3. ``python -m tpsr_ros.filter_node --ros-args -p model:=M -p policy:=P`` starts only now,
   so the latched episode start it receives is the first trial's (the start-up reset must
   not be followed by a step, as in the headless protocol); it commands the first step
   from ``b_*``, and from then on sim and filter run in lockstep;
4. per trial the driver sums the 50 rewards on ``/reward`` (stamps t_r+1 .. t_r+50 after
   the reset at t_r), waits until the simulator has *ignored* the filter's 51st command
   (its debug log line; only then can the next reset not be overtaken by that command),
   and resets to the next start.

Lockstep, reliable QoS and waiting for matched endpoints make the run deterministic: its
trial rewards and score equal ``learner evaluate``'s exactly. The filter holds its first
command until ``/cmd_vel`` and ``/tpsr/state`` have every subscriber (``wait_for_subscribers``),
and, when recording, the simulator holds its start-up reset until the recorder subscribes
to each of its topics, so the recorder misses nothing of the trials (the start-up reset's
latched ``/sim/episode_start`` can still be replaced by the first trial's before the
recorder's reader matches: the driver's own subscription already satisfies that gate).
Processes are stopped with SIGINT (filter, simulator, then the recorder, which closes the
bag), killed if they do not exit, on success, error, timeout and Ctrl-C alike; on Linux
they also get SIGTERM if this process dies.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from learner.evaluate import EVALUATION_SEED, START_POSITIONS, STEPS, Evaluation, Trial
from sim_node import Environment
from tpsr_ros.core.errors import ModelFormatError, TpsrError
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import check_bag_path_free
from tpsr_ros.io.filter_inputs import load_filter_inputs
from tpsr_ros.io.policy import TRUE_POSITION, load_policy
from tpsr_ros.runtime import (
    LATCHED_QOS,
    Durability,
    History,
    Node,
    NodeOptions,
    QoSProfile,
    Reliability,
)

__all__ = [
    "RECORDED_TOPICS",
    "ClosedLoopError",
    "ClosedLoopResult",
    "format_trial",
    "register",
    "run",
    "run_closed_loop",
]

RECORDED_TOPICS = (
    "/camera/image_raw",
    "/action",
    "/ground_truth/pose",
    "/reward",
    "/clock",
    "/sim/episode_start",
    "/sim/reset",
    "/tpsr/state",
    "/cmd_vel",
    "/diagnostics",
)
_SIM_TOPICS = RECORDED_TOPICS[:7]
KEEP_ALL_QOS = QoSProfile(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_ALL, 0)
_IGNORED = "/cmd_vel ignored: episode_steps"
_READY = "spinning until SIGINT/SIGTERM"
# Run a node module so that it gets SIGTERM if this (parent) process dies (Linux prctl
# PR_SET_PDEATHSIG), then exactly as `python -m MODULE ARGS...`.
_LAUNCH = """\
import ctypes, os, runpy, signal, sys
from tpsr_ros.core.units import NS_PER_S as _NS
try:
    ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)
except Exception:
    pass
if os.getppid() != int(sys.argv[1]):
    sys.exit(1)
module = sys.argv[2]
sys.argv = [module] + sys.argv[3:]
runpy.run_module(module, run_name="__main__", alter_sys=True)
"""


class ClosedLoopError(TpsrError):
    """The closed loop could not run to the end (a node failed, a wait timed out)."""


@dataclass(frozen=True)
class ClosedLoopResult:
    """Trials, score and what the driver saw.

    Attributes:
        evaluation: the trials and their score, as :func:`learner.evaluate.evaluate` returns.
        states: stamp (ns) -> state published on ``/tpsr/state``.
        bag: the recorded bag, if any.
        log_dir: where the nodes' logs are (None if they were in a removed temporary dir).
        seconds: wall time of the whole run.

    """

    evaluation: Evaluation
    states: dict[int, np.ndarray] = field(repr=False)
    bag: Path | None
    log_dir: Path | None
    seconds: float


def format_trial(index: int, trial: Trial) -> str:
    """One trial as ``learner evaluate`` prints it."""
    goal = f"goal zone at step {trial.goal_step}" if trial.goal_step else "goal zone not reached"
    return (
        f"trial {index + 1:2d}: start ({trial.start[0]:4.1f}, {trial.start[1]:4.1f})  "
        f"reward {trial.reward:7.1f}  {goal}, {trial.wall_contacts} wall contacts"
    )


# -- child processes ----------------------------------------------------------------------


class _Child:
    """A node process; its output is copied to a log file and kept for waiting on lines."""

    def __init__(
        self, name: str, module: str, args: Sequence[str], env: dict[str, str], log_dir: Path
    ) -> None:
        self.name = name
        self.command = ["python", "-m", module, *args]
        self.log_path = log_dir / f"{name}.log"
        self._lines: list[str] = []
        self._lock = threading.Lock()
        self._log = self.log_path.open("w", encoding="utf-8")
        self.popen = subprocess.Popen(
            [sys.executable, "-c", _LAUNCH, str(os.getpid()), module, *args],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            env=env,
            text=True,
            errors="replace",
        )
        self._reader = threading.Thread(target=self._read, name=f"{name}-log", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        assert self.popen.stdout is not None
        for line in self.popen.stdout:
            with self._lock:
                self._lines.append(line.rstrip("\n"))
                self._log.write(line)
                self._log.flush()

    def count(self, needle: str) -> int:
        """Lines so far containing ``needle``."""
        with self._lock:
            return sum(needle in line for line in self._lines)

    def tail(self, n: int = 8) -> str:
        """Return the last ``n`` lines of output."""
        with self._lock:
            return "\n".join(self._lines[-n:])

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, timeout_s: float = 20.0) -> int | None:
        """SIGINT, wait; SIGKILL if it does not exit. Returns the exit code."""
        if self.popen.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.popen.send_signal(signal.SIGINT)
            try:
                self.popen.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.popen.kill()
                self.popen.wait(10)
        self._reader.join(5)
        with self._lock:
            self._log.close()
        return self.popen.returncode


# -- the driver ---------------------------------------------------------------------------


def _pick_domain() -> int:
    return random.SystemRandom().randrange(1, 233)


@contextlib.contextmanager
def _environment(overrides: dict[str, str]) -> Iterator[None]:
    saved = {k: os.environ.get(k) for k in overrides}
    os.environ.update(overrides)
    try:
        yield
    finally:
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


class _Driver:
    """The in-process node that resets the simulator and collects rewards and states."""

    def __init__(self, domain_id: int) -> None:
        from tpsr_ros.runtime.dds import DdsTransport

        transport = DdsTransport("closed_loop_driver", domain_id=domain_id)
        self.node = Node(NodeOptions(name="closed_loop_driver"), transport=transport)
        self.episode_starts: list[tuple[int, float, float]] = []
        self.rewards: list[tuple[int, m.RewardSample]] = []
        self.states: dict[int, np.ndarray] = {}
        self.node.create_subscription(
            "/sim/episode_start", m.POSE_TYPE, self._on_start, LATCHED_QOS
        )
        # keep-all: lockstep runs hundreds of steps per second; a keep-last reader of a
        # descheduled driver would lose rewards
        self.reward_sub = self.node.create_subscription(
            "/reward",
            m.REWARD_TYPE,
            lambda msg: self.rewards.append((m.stamp_of(msg), m.reward_to_sample(msg))),
            KEEP_ALL_QOS,
        )
        self.node.create_subscription(
            "/tpsr/state",
            m.STATE_TYPE,
            lambda msg: self.states.__setitem__(m.stamp_of(msg), m.state_to_array(msg)),
            KEEP_ALL_QOS,
        )
        self.reset_pub = self.node.create_publisher("/sim/reset", m.POSE_TYPE)

    def _on_start(self, msg: Any) -> None:
        x, y = m.pose_to_xy(msg)
        self.episode_starts.append((m.stamp_of(msg), x, y))

    def graph_is_empty(self) -> bool:
        """No other simulator or filter is publishing in this domain."""
        theirs = set(RECORDED_TOPICS) - {"/sim/reset"}  # /sim/reset is our own publisher
        return not any(e.topic in theirs for e in self.node.transport.publishers())

    def close(self) -> None:
        self.node.close()


@dataclass
class _Run:
    children: dict[str, _Child]
    timeout_s: float

    def wait(self, what: str, condition: Callable[[], bool], driver: _Driver) -> None:
        """Spin the driver until ``condition()``; fail if a node exits or on timeout."""
        deadline = time.monotonic() + self.timeout_s
        while not condition():
            for child in self.children.values():
                if not child.alive():
                    raise ClosedLoopError(
                        f"{child.name} exited with status {child.popen.returncode} while "
                        f"waiting for {what}: {child.tail(3)!r}"
                    )
            if time.monotonic() > deadline:
                raise ClosedLoopError(f"timed out after {self.timeout_s:g} s waiting for {what}")
            driver.node.spin_once(0.02)


def _run_trial(
    run: _Run,
    driver: _Driver,
    sim: _Child,
    index: int,
    start: tuple[float, float],
    steps: int,
    on_reset: Callable[[], None] | None,
    on_step: Callable[[int], None] | None,
) -> Trial:
    """Reset to ``start``, collect the trial's rewards, wait until the sim ignored step N+1."""
    name = f"trial {index + 1}"
    before = len(driver.episode_starts)
    driver.reset_pub.publish(m.pose_msg(0, float(start[0]), float(start[1])))
    run.wait(f"the episode start of {name}", lambda: len(driver.episode_starts) > before, driver)
    reset_stamp, x, y = driver.episode_starts[-1]
    if abs(x - start[0]) > 1e-9 or abs(y - start[1]) > 1e-9:
        raise ClosedLoopError(f"{name}: the simulator started at ({x}, {y}), not {tuple(start)}")
    if on_reset is not None:
        on_reset()
    wanted = [reset_stamp + k * _NS for k in range(1, steps + 1)]
    seen = 0

    def rewards() -> list[m.RewardSample]:
        got = dict(driver.rewards)
        return [got[s] for s in wanted if s in got]

    def complete() -> bool:
        nonlocal seen
        count = len(rewards())
        if on_step is not None and count > seen:
            on_step(count - seen)
        seen = count
        return count == steps

    run.wait(f"the {steps} rewards of {name}", complete, driver)
    run.wait(
        f"the simulator to ignore the command after step {steps} of {name}",
        lambda: sim.count(_IGNORED) >= index + 1,
        driver,
    )
    run.wait(
        f"the {steps} states of {name}", lambda: all(s in driver.states for s in wanted), driver
    )
    samples = rewards()
    return Trial(
        (float(start[0]), float(start[1])),
        float(sum(s.reward for s in samples)),
        next((k + 1 for k, s in enumerate(samples) if s.goal_zone), None),
        int(sum(s.wall_contact for s in samples)),
    )


def run_closed_loop(
    policy_path: Path | str,
    environment: Environment | str,
    *,
    model_path: Path | str | None = None,
    record: Path | str | None = None,
    log_dir: Path | str | None = None,
    seed: int = EVALUATION_SEED,
    starts: Sequence[tuple[float, float]] = START_POSITIONS,
    steps: int = STEPS,
    timeout_s: float = 60.0,
    domain_id: int | None = None,
    on_trial: Callable[[int, Trial], None] | None = None,
    on_step: Callable[[int], None] | None = None,
    say: Callable[[str], None] | None = None,
) -> ClosedLoopResult:
    """Run the standard protocol with the simulator and filter nodes as processes.

    ``on_step(n)`` is called with the number of new rewards as they arrive (for progress
    bars), ``on_trial`` after each trial, ``say`` with stage lines.
    """
    started = time.monotonic()
    say = say or (lambda text: None)
    environment = Environment(environment).value
    policy_path = Path(policy_path).resolve()
    policy = load_policy(policy_path)
    if policy.representation == TRUE_POSITION:
        raise ModelFormatError(
            f"{policy_path} is a true-position policy; the filter node drives only from a "
            "model's states"
        )
    policy.check_environment(environment)
    model_path = policy.model_path(model_path).resolve()
    # the filter node's own start-up checks, here, before any process starts
    load_filter_inputs(str(model_path), str(policy_path))
    if record is not None:
        record = Path(record).resolve()
        check_bag_path_free(record)
    if steps < 1 or not starts:
        raise ModelFormatError("the closed loop needs at least one start and one step")
    keep_logs = log_dir is not None
    logs = (
        Path(log_dir) if log_dir is not None else Path(tempfile.mkdtemp(prefix="tpsr-closed-loop-"))
    )
    logs.mkdir(parents=True, exist_ok=True)

    network: dict[str, str] = {}
    if not os.environ.get("CYCLONEDDS_URI") and not os.environ.get("ROS_AUTOMATIC_DISCOVERY_RANGE"):
        network["ROS_AUTOMATIC_DISCOVERY_RANGE"] = "LOCALHOST"
    children: dict[str, _Child] = {}
    driver: _Driver | None = None
    ok = False
    try:
        # a domain nobody else is using right now (other runs, tests, robots)
        for _ in range(8):
            domain = domain_id if domain_id is not None else _pick_domain()
            with _environment(network):
                driver = _Driver(domain)
            driver.node.spin(timeout_s=0.5)
            if driver.graph_is_empty() or domain_id is not None:
                break
            say(f"ROS_DOMAIN_ID {domain} is in use; trying another")
            driver.close()
            driver = None
        if driver is None:
            raise ClosedLoopError("found no free ROS_DOMAIN_ID")
        env = {
            **os.environ,
            **network,
            "ROS_DOMAIN_ID": str(domain),
            "TPSR_TRANSPORT": "dds",
            "PYTHONUNBUFFERED": "1",
        }
        run = _Run(children, timeout_s)
        say(f"DDS domain {domain}; node logs in {logs}")

        if record is not None:
            say(f"recording to {record}")
            children["recorder"] = _Child(
                "recorder", "tpsr_ros.record", ["-o", str(record), *RECORDED_TOPICS], env, logs
            )
        sim_args = [
            "--ros-args",
            "-p",
            "mode:=command",
            "-p",
            f"environment:={environment}",
            "-p",
            f"seed:={seed}",
            "-p",
            f"episode_steps:={steps}",
            "--log-level",
            "debug",
        ]
        if record is not None:  # the recorder gets everything, the start-up reset included
            sim_args[1:1] = ["-p", "wait_for_subscribers:=1"]
        say("starting " + " ".join(["python -m sim_node", *sim_args]))
        sim = children["sim_node"] = _Child("sim_node", "sim_node", sim_args, env, logs)
        run.wait("the simulator's start-up reset", lambda: len(driver.episode_starts) >= 1, driver)
        run.wait(
            "the simulator to subscribe /sim/reset and publish /reward",
            lambda: (
                driver.reset_pub.get_subscription_count() >= 1
                and driver.reward_sub.get_publisher_count() >= 1
            ),
            driver,
        )
        if record is not None:
            recorder = children["recorder"]
            run.wait(
                "the recorder to subscribe the simulator's topics",
                lambda: (
                    all(recorder.count(f"subscribed to {t} ") for t in _SIM_TOPICS)
                    and driver.reset_pub.get_subscription_count() >= 2
                ),
                driver,
            )

        filter_args = [
            "--ros-args",
            "-p",
            f"model:={model_path}",
            "-p",
            f"policy:={policy_path}",
            "-p",
            f"wait_for_subscribers:={2 if record is not None else 1}",
        ]
        trials: list[Trial] = []
        for index, start in enumerate(starts):
            on_reset = None
            if index == 0:

                def on_reset() -> None:
                    say("starting " + " ".join(["python -m tpsr_ros.filter_node", *filter_args]))
                    children["tpsr_filter"] = _Child(
                        "tpsr_filter", "tpsr_ros.filter_node", filter_args, env, logs
                    )

            trial = _run_trial(run, driver, sim, index, start, steps, on_reset, on_step)
            trials.append(trial)
            if on_trial is not None:
                on_trial(index, trial)
        evaluation = Evaluation(tuple(trials))
        states = dict(driver.states)
        ok = True
    finally:
        for name in ("tpsr_filter", "sim_node", "recorder"):  # the recorder last: it drains
            if name in children:
                children[name].stop()
        if driver is not None:
            driver.close()
        if not ok or keep_logs:
            if not ok:
                say(f"node logs kept in {logs}")
        else:
            for child in children.values():
                child.log_path.unlink(missing_ok=True)
            with contextlib.suppress(OSError):
                logs.rmdir()
    if record is not None and children["recorder"].popen.returncode != 0:
        raise ClosedLoopError(
            f"the recorder exited with status {children['recorder'].popen.returncode}"
        )
    return ClosedLoopResult(
        evaluation, states, record, logs if keep_logs else None, time.monotonic() - started
    )


# -- command line -------------------------------------------------------------------------


def register(subparsers: Any) -> None:
    """Add the ``closed-loop`` subcommand."""
    doc = (
        "score a policy with the standard protocol over the nodes: sim_node and the filter "
        "node as separate processes in lockstep over DDS"
    )
    parser = subparsers.add_parser(
        "closed-loop",
        help=doc,
        description=doc[0].upper() + doc[1:] + ". Prints each trial, then `score: X`, "
        "exactly as `learner evaluate` does for the same policy.",
    )
    parser.add_argument("policy", type=Path, metavar="POLICY")
    parser.add_argument("--environment", required=True, choices=[e.value for e in Environment])
    parser.add_argument(
        "--model",
        type=Path,
        default=None,
        metavar="MODEL",
        help="the policy's model file (default: the path recorded in the policy)",
    )
    parser.add_argument(
        "--record",
        type=Path,
        default=None,
        metavar="BAG",
        help="also record every topic of the run into a new bag",
    )
    parser.add_argument(
        "--logs",
        type=Path,
        default=None,
        metavar="DIR",
        help="keep the nodes' logs in DIR (default: only when a run fails)",
    )
    parser.add_argument(
        "--seed", type=int, default=EVALUATION_SEED, help="simulator seed (default: %(default)s)"
    )
    parser.add_argument(
        "--timeout",
        type=float,
        default=60.0,
        metavar="S",
        help="longest wait for any one stage (default: %(default)s s)",
    )
    parser.add_argument(
        "--domain-id",
        type=int,
        default=None,
        metavar="N",
        help="ROS_DOMAIN_ID to use (default: a free one at random)",
    )
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Run the closed loop; print each trial, then ``score: <mean>`` as the last line."""
    if args.seed < 0:
        raise ModelFormatError(f"--seed must be >= 0, got {args.seed}")

    def show(index: int, trial: Trial) -> None:
        print(format_trial(index, trial), flush=True)

    result = run_closed_loop(
        args.policy,
        args.environment,
        model_path=args.model,
        record=args.record,
        log_dir=args.logs,
        seed=args.seed,
        timeout_s=args.timeout,
        domain_id=args.domain_id,
        on_trial=show,
        say=lambda text: print(f"learner closed-loop: {text}", file=sys.stderr, flush=True),
    )
    print(f"score: {result.evaluation.score:.1f}")
    return 0
