"""``learner closed-loop POLICY --environment E``: the standard evaluation over the nodes.

The headless protocol of :mod:`learner.evaluate`, run by the real nodes as separate
processes over the middleware the nodes choose by default (rclpy when importable, else
the Cyclone DDS backend; ``--transport`` or ``TPSR_TRANSPORT`` picks one), in a fresh
``ROS_DOMAIN_ID``, loopback only unless ``ROS_AUTOMATIC_DISCOVERY_RANGE`` or
``CYCLONEDDS_URI`` says otherwise:

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
   (announced on ``/sim/cmd_ignored``; only then can the next reset not be overtaken by
   that command), and resets to the next start.

A model learned from robot bags (``learner fit --step-period 1``) runs the same protocol:
the simulator renders its robot camera's size (``-p image_size:=N``) on the model's camera
topic (``-r camera/image_raw:=TOPIC``) and snaps each code's command to its nearest
action, and the filter node runs with ``-p lockstep:=true``: each image is one step on the
model's grid (at the first grid time at or after its stamp) with the node's own last
command, which its grid rules could not close in lockstep (they wait for an image after the
step, which the simulator sends only once the step is answered). What the simulator cannot
play (another step period, a compressed or non-square camera, a command it does not have)
is refused in one line before any process starts (:mod:`learner.sim_robot`).

Lockstep, reliable QoS and waiting for matched endpoints make the run deterministic: its
trial rewards and score equal ``learner evaluate``'s exactly. The filter holds its first
command until ``/cmd_vel`` and ``/tpsr/state`` have every subscriber (``wait_for_subscribers``),
and, when recording, the simulator holds its start-up reset until the recorder subscribes
to each of its topics (``wait_for_subscribers:=2``: the driver subscribes them all too), so
the recorder misses nothing of the trials. Every wait is a condition on the graph
(matched endpoints, messages received), never on log text. The processes are started and
stopped by :class:`tpsr_ros.runtime.launcher.Launch`: SIGINT (filter, simulator, then the
recorder, which closes the bag), killed if they do not exit, on success, error, timeout
and Ctrl-C alike; on Linux they also get SIGTERM if this process dies.
"""

from __future__ import annotations

import contextlib
import os
import random
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from learner.evaluate import (
    EVALUATION_SEED,
    START_POSITIONS,
    STEPS,
    Evaluation,
    Trial,
    path_end,
    start_heading,
)
from learner.inputs import require_camera
from learner.sim_robot import SimulatedRobot, simulated_robot
from sim_node import Environment, SimConfig
from sim_node.topics import CMD_IGNORED_TOPIC
from tpsr_ros.core.errors import ModelFormatError, TpsrError
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import check_bag_path_free
from tpsr_ros.io.filter_inputs import filter_inputs, input_topics
from tpsr_ros.io.model_io import open_model
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
from tpsr_ros.runtime.backend import choose_backend, open_transport
from tpsr_ros.runtime.dds import LAST_SAFE_DOMAIN_ID
from tpsr_ros.runtime.launcher import Launch, LaunchError, environ_overrides

__all__ = [
    "RECORDED_TOPICS",
    "ClosedLoopError",
    "ClosedLoopResult",
    "format_trial",
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
    "/tpsr/predicted_image",
    "/tpsr/state_markers",
    "/tpsr/decoded_pose",
    "/cmd_vel",
    "/diagnostics",
)
_WATCHED_TOPICS = {
    "/camera/image_raw": m.IMAGE_TYPE,
    "/action": m.ACTION_TYPE,
    "/clock": m.CLOCK_TYPE,
}
"""The simulator's topics the driver does not otherwise read (see :class:`_Driver`)."""
KEEP_ALL_QOS = QoSProfile(Reliability.RELIABLE, Durability.VOLATILE, History.KEEP_ALL, 0)


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


# -- the driver ---------------------------------------------------------------------------


def _pick_domain() -> int:
    """A random domain id in 1..101 (0 is every ROS 2 system's default)."""
    return random.SystemRandom().randrange(1, LAST_SAFE_DOMAIN_ID + 1)


class _Driver:
    """The in-process node that resets the simulator and collects rewards, poses and states.

    With ``watch_all`` it also subscribes the simulator's other step topics (and drops
    what it gets), so that ``wait_for_subscribers:=2`` holds the simulator's start-up
    reset until a recorder has subscribed every one of them as well.
    """

    def __init__(
        self, backend: str, *, watch_all: bool, image_topic: str = "/camera/image_raw"
    ) -> None:
        # the transport reads ROS_DOMAIN_ID (and the discovery range) from the environment
        transport = open_transport(backend, "closed_loop_driver", "/")
        self.node = Node(NodeOptions(name="closed_loop_driver"), transport=transport)
        self.episode_starts: list[tuple[int, float, float]] = []
        self.rewards: list[tuple[int, m.RewardSample]] = []
        self.states: dict[int, np.ndarray] = {}
        self.positions: dict[int, tuple[float, float]] = {}
        self.ended_episodes = 0
        """``/sim/cmd_ignored`` messages for ``episode_steps``: commands after an episode's end."""
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
        self.node.create_subscription(
            "/ground_truth/pose",
            m.POSE_TYPE,
            lambda msg: self.positions.__setitem__(m.stamp_of(msg), m.pose_to_xy(msg)),
            KEEP_ALL_QOS,
        )
        self.node.create_subscription(
            CMD_IGNORED_TOPIC, m.HEADER_TYPE, self._on_ignored, KEEP_ALL_QOS
        )
        if watch_all:
            for topic, msgtype in _WATCHED_TOPICS.items():
                topic = image_topic if topic == "/camera/image_raw" else topic
                self.node.create_subscription(topic, msgtype, lambda data: None, raw=True)
        self.reset_pub = self.node.create_publisher("/sim/reset", m.POSE_TYPE)

    def _on_start(self, msg: Any) -> None:
        x, y = m.pose_to_xy(msg)
        self.episode_starts.append((m.stamp_of(msg), x, y))

    def _on_ignored(self, msg: Any) -> None:
        if msg.frame_id == "episode_steps":
            self.ended_episodes += 1

    def graph_is_empty(self) -> bool:
        """No other simulator or filter is publishing in this domain."""
        theirs = set(RECORDED_TOPICS) - {"/sim/reset"}  # /sim/reset is our own publisher
        return not any(e.topic in theirs for e in self.node.transport.publishers())

    def close(self) -> None:
        self.node.close()


def _run_trial(
    launch: Launch,
    driver: _Driver,
    index: int,
    start: tuple[float, float],
    steps: int,
    on_reset: Callable[[], None] | None,
    on_step: Callable[[int], None] | None,
    heading: float | None = None,
    state_stamp: Callable[[int], int] = lambda stamp: stamp,
) -> Trial:
    """One trial of the standard protocol (guide 4.1): reset, N lockstep steps, their reward.

    Reset to ``start`` (turned to ``heading``, if any), collect the rewards r_1 .. r_N
    stamped after the reset, wait until the simulator announced on ``/sim/cmd_ignored`` that
    it ignored the filter's command N+1 (only then can the next reset not be overtaken by
    it) and for the N states (``state_stamp``: the filter's stamp of the step stamped
    so by the simulator; a robot model's grid time).
    """
    name = f"trial {index + 1}"
    before = len(driver.episode_starts)
    driver.reset_pub.publish(m.pose_msg(0, float(start[0]), float(start[1]), heading=heading))
    launch.wait(f"the episode start of {name}", lambda: len(driver.episode_starts) > before)
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

    launch.wait(f"the {steps} rewards of {name}", complete)
    launch.wait(
        f"the simulator to ignore the command after step {steps} of {name}",
        lambda: driver.ended_episodes >= index + 1,
    )
    stamps = [state_stamp(s) for s in wanted]
    launch.wait(f"the {steps} states of {name}", lambda: all(s in driver.states for s in stamps))
    launch.wait(f"the {steps} poses of {name}", lambda: all(s in driver.positions for s in wanted))
    samples = rewards()
    path = np.array([(x, y), *(driver.positions[s] for s in wanted)])
    return Trial(
        (float(start[0]), float(start[1])),
        float(sum(s.reward for s in samples)),
        next((k + 1 for k, s in enumerate(samples) if s.goal_zone), None),
        int(sum(s.wall_contact for s in samples)),
        *path_end(path),
    )


def _check_inputs(
    policy_path: Path | str,
    environment: str,
    model_path: Path | str | None,
    vertical_half_extent: float | None = None,
    camera_size: int | None = None,
) -> tuple[Path, Path, SimulatedRobot | None]:
    """Refuse what the filter node or the simulator would refuse, before any process starts.

    Returns the resolved policy and model paths, and for a model learned on a step grid how
    the simulator plays its robot.
    """
    policy_path = Path(policy_path).resolve()
    policy = load_policy(policy_path)
    if policy.representation == TRUE_POSITION:
        raise ModelFormatError(
            f"{policy_path} is a true-position policy; the filter node drives only from a "
            "model's states"
        )
    policy.check_environment(environment)
    model = policy.model_path(model_path).resolve()
    camera = SimConfig(environment=environment, vertical_half_extent=vertical_half_extent)
    # once: the filter node opens it again in its process
    model_file = open_model(model)
    robot = None
    if model_file.spec is not None:
        robot = simulated_robot(model_file, camera, camera_size)
    require_camera(model_file, camera.vertical_extent)
    image, action = ("/" + t for t in input_topics(model_file) or ("camera/image_raw", "action"))
    filter_inputs(
        model_file, (policy, str(policy_path)), image_topic=image, action_topic=action
    )
    return policy_path, model, robot


def _join_free_domain(
    domain_id: int | None,
    network: dict[str, str],
    backend: str,
    watch_all: bool,
    say: Callable[[str], None],
    image_topic: str = "/camera/image_raw",
) -> tuple[_Driver, int]:
    """Start the driver node in a ROS domain nobody else uses right now (runs, tests, robots)."""
    for _ in range(8):
        domain = domain_id if domain_id is not None else _pick_domain()
        try:
            with environ_overrides({**network, "ROS_DOMAIN_ID": str(domain)}):
                driver = _Driver(backend, watch_all=watch_all, image_topic=image_topic)
        except TpsrError as exc:
            if domain_id is not None:
                raise
            say(f"cannot join ROS_DOMAIN_ID {domain} ({exc}); trying another")
            continue
        driver.node.spin(timeout_s=0.5)
        if driver.graph_is_empty() or domain_id is not None:
            return driver, domain
        say(f"ROS_DOMAIN_ID {domain} is in use; trying another")
        driver.close()
    raise ClosedLoopError("found no free ROS_DOMAIN_ID")


def _start_simulator(
    launch: Launch,
    driver: _Driver,
    *,
    environment: str,
    vertical_half_extent: float | None,
    seed: int,
    steps: int,
    record: Path | None,
    say: Callable[[str], None],
    robot: SimulatedRobot | None = None,
) -> None:
    """Start the recorder (if any) and the simulator; wait until both are in the graph.

    The simulator in command mode with ``episode_steps:=N`` (lockstep, one step per
    ``/cmd_vel``); when recording, ``wait_for_subscribers:=2`` (the driver and the
    recorder) holds its start-up reset until the recorder subscribes each of its topics.
    """
    if record is not None:
        say(f"recording to {record}")
        launch.start("recorder", "tpsr_ros.record", ["-o", str(record), *_recorded(robot)])
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
    if vertical_half_extent is not None:  # else the environment's
        sim_args[1:1] = ["-p", f"vertical_half_extent:={float(vertical_half_extent)!r}"]
    if record is not None:  # the recorder gets everything, the start-up reset included
        sim_args[1:1] = ["-p", "wait_for_subscribers:=2"]
    if robot is not None:  # the robot's camera, on the model's camera topic
        sim_args[1:1] = ["-p", f"image_size:={robot.camera_size}"]
        sim_args += ["-r", f"camera/image_raw:={robot.image_topic}"]
    say("starting " + " ".join(["python -m sim_node", *sim_args]))
    launch.start("sim_node", "sim_node", sim_args)
    launch.wait("the simulator's start-up reset", lambda: len(driver.episode_starts) >= 1)
    readers = 1 if record is None else 2  # the simulator's /sim/reset, and the recorder's
    launch.wait(
        "the simulator to subscribe /sim/reset and publish /reward"
        + ("" if record is None else ", and the recorder to subscribe /sim/reset"),
        lambda: (
            driver.reset_pub.get_subscription_count() >= readers
            and driver.reward_sub.get_publisher_count() >= 1
        ),
    )


def _recorded(robot: SimulatedRobot | None) -> list[str]:
    """The topics to record: the simulator's camera on the model's camera topic."""
    if robot is None:
        return list(RECORDED_TOPICS)
    return [robot.image_topic if t == "/camera/image_raw" else t for t in RECORDED_TOPICS]


def _filter_args(
    model_path: Path,
    policy_path: Path,
    record: Path | None,
    lockstep: bool = False,
    view: bool = False,
) -> list[str]:
    """Build the filter node's command line: the first command waits until its readers match
    (the driver's, the recorder's, the view's; ``lockstep``: one step per image, for a model
    learned on a step grid)."""
    readers = 1 + (record is not None) + view
    return [
        "--ros-args",
        "-p",
        f"model:={model_path}",
        "-p",
        f"policy:={policy_path}",
        "-p",
        f"wait_for_subscribers:={readers}",
        *(["-p", "lockstep:=true"] if lockstep else []),
    ]


def _tidy_logs(
    logs: Path, statuses: dict[str, int], *, ok: bool, keep: bool, say: Callable[[str], None]
) -> None:
    """Remove the nodes' logs after a successful run unless asked to keep them."""
    if not ok:
        say(f"node logs kept in {logs}")
    if ok and not keep:
        for name in statuses:
            (logs / f"{name}.log").unlink(missing_ok=True)
        with contextlib.suppress(OSError):
            logs.rmdir()


def run_closed_loop(
    policy_path: Path | str,
    environment: Environment | str,
    *,
    vertical_half_extent: float | None = None,
    model_path: Path | str | None = None,
    record: Path | str | None = None,
    log_dir: Path | str | None = None,
    seed: int = EVALUATION_SEED,
    starts: Sequence[tuple[float, float]] = START_POSITIONS,
    steps: int = STEPS,
    timeout_s: float = 60.0,
    domain_id: int | None = None,
    transport: str | None = None,
    on_trial: Callable[[int, Trial], None] | None = None,
    on_step: Callable[[int], None] | None = None,
    say: Callable[[str], None] | None = None,
    camera_size: int | None = None,
    view_port: int | None = None,
) -> ClosedLoopResult:
    """Run the standard protocol (guide 4.1-4.2) with the simulator and filter nodes as processes.

    The steps: the filter's own refusals (:func:`_check_inputs`), a free ROS domain for the
    driver (:func:`_join_free_domain`), the recorder and simulator
    (:func:`_start_simulator`), then per start one trial (:func:`_run_trial`; the filter
    node starts at the first trial's reset). ``on_step(n)`` is called with the number of
    new rewards as they arrive (for progress bars), ``on_trial`` after each trial, ``say``
    with stage lines. ``transport`` is ``rclpy`` or ``dds`` (default: ``TPSR_TRANSPORT``,
    else rclpy if importable, else dds). ``camera_size``: the simulator's camera for a model
    learned from robot bags (default: the one the model records). ``view_port``: also run
    the view node (``python -m tpsr_ros.view``), serving the run to Foxglove on that port.
    """
    started = time.monotonic()
    say = say or (lambda text: None)
    backend, _ = choose_backend(transport)
    if backend == "inproc":
        raise ClosedLoopError(
            "the closed loop runs the nodes as processes: use the rclpy or dds transport, "
            "not inproc"
        )
    environment = Environment(environment).value
    policy_path, model_path, robot = _check_inputs(
        policy_path, environment, model_path, vertical_half_extent, camera_size
    )
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
    launch: Launch | None = None
    driver: _Driver | None = None
    statuses: dict[str, int] = {}
    ok = False
    try:
        image_topic = "/camera/image_raw" if robot is None else robot.image_topic
        driver, domain = _join_free_domain(
            domain_id, network, backend, record is not None, say, image_topic
        )
        env = {**os.environ, **network, "ROS_DOMAIN_ID": str(domain), "TPSR_TRANSPORT": backend}
        launch = Launch(logs, env=env, spin=driver.node.spin_once, timeout_s=timeout_s)
        say(f"{backend} transport, ROS_DOMAIN_ID {domain}; node logs in {logs}")
        _start_simulator(
            launch,
            driver,
            environment=environment,
            vertical_half_extent=vertical_half_extent,
            seed=seed,
            steps=steps,
            record=record,
            say=say,
            robot=robot,
        )
        if view_port is not None:
            view = launch.start("tpsr_view", "tpsr_ros.view", ["--port", str(view_port)])
            launch.wait("the view's server", lambda: "ws://" in view.text())
            say(f"Foxglove: open a connection to ws://127.0.0.1:{view_port} (msgs_doc/view.md)")
        filter_args = _filter_args(
            model_path, policy_path, record, lockstep=robot is not None, view=view_port is not None
        )
        state_stamp = (lambda stamp: stamp) if robot is None else robot.step_time

        def start_filter() -> None:
            # only after the first trial's reset, so the latched episode start it receives
            # is the first trial's; it commands the first step from b_*
            say("starting " + " ".join(["python -m tpsr_ros.filter_node", *filter_args]))
            assert launch is not None
            launch.start("tpsr_filter", "tpsr_ros.filter_node", filter_args)

        trials: list[Trial] = []
        for index, start in enumerate(starts):
            on_reset = start_filter if index == 0 else None
            heading = start_heading(environment == Environment.DRIVE.value, index)
            trials.append(
                _run_trial(
                    launch, driver, index, start, steps, on_reset, on_step, heading, state_stamp
                )
            )
            if on_trial is not None:
                on_trial(index, trials[-1])
        evaluation = Evaluation(tuple(trials))
        states = dict(driver.states)
        ok = True
    except LaunchError as exc:
        raise ClosedLoopError(str(exc)) from None
    finally:
        if launch is not None:  # filter, simulator, then the recorder: it drains last
            statuses = launch.stop()
        if driver is not None:
            driver.close()
        _tidy_logs(logs, statuses, ok=ok, keep=keep_logs, say=say)
    if record is not None and statuses.get("recorder") != 0:
        raise ClosedLoopError(f"the recorder exited with status {statuses.get('recorder')}")
    return ClosedLoopResult(
        evaluation, states, record, logs if keep_logs else None, time.monotonic() - started
    )
