"""The filter node on the in-process bus: faults are counted and never stop it, and the states
it publishes after every recovery equal offline tracking of the same steps; resets, backwards
jumps, the command for b_*, diagnostics and the start-up refusals.

Helpers here (a small fitted model, a random-weight policy for it) are also imported by
tests/test_msgs_doc.py and tests/test_filter_node_lockstep.py.
"""

from __future__ import annotations

import atexit
import io
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest

from learner.cli import main as learner_main
from sim_node import SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.core.actions import ACTIONS
from tpsr_ros.core.episodes import track_trajectory
from tpsr_ros.core.errors import TpsrError
from tpsr_ros.core.fqi import QFunction
from tpsr_ros.core.tpsr import TPSRModel
from tpsr_ros.filter_node import FilterNode, FilterNodeParams, load_inputs
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader, BagWriter
from tpsr_ros.io.model_io import load_model, model_fingerprint, read_metadata, save_model
from tpsr_ros.io.policy import Policy, save_policy
from tpsr_ros.io.trajectory import read_trajectory
from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions, parse_ros_args
from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE, ERROR, OK, WARN, status_values
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

S = 10**9
SMALL = ["--obs-centers", "40", "--ht-centers", "80", "--rank", "3"]
DOC = Path(__file__).resolve().parent.parent / "msgs_doc" / "filter_node.md"


# -- helpers shared with other test modules ----------------------------------------------


_FITTED: dict[tuple[int, int], Path] = {}
"""The bag and model of each (steps, seed) fitted in this process, in a directory of its own."""


def fit_small_model(tmp: Path, *, steps: int = 900, seed: int = 3) -> Path:
    """A small TPSR fitted on a generated full-environment bag (about a second).

    The bag and the fit are seeded, so they are made once per process and copied into
    ``tmp`` for every later test that asks for the same (steps, seed): byte for byte what
    generating and fitting again would write."""
    if (steps, seed) not in _FITTED:
        made = Path(tempfile.mkdtemp(prefix=f"small_model_{steps}_{seed}_"))
        atexit.register(shutil.rmtree, made, ignore_errors=True)
        generate_bag(made / "train", SimConfig(environment="full"), steps, seed=seed)
        assert learner_main(["fit", str(made / "train"), "-o", str(made / "model.npz"),
                             *SMALL]) == 0  # fmt: skip
        _FITTED[steps, seed] = made
    made = _FITTED[steps, seed]
    shutil.copytree(made / "train", tmp / f"train_{seed}")
    model = tmp / f"model_{seed}.npz"
    shutil.copyfile(made / "model.npz", model)
    return model


def random_policy(
    model_path: Path,
    out: Path,
    *,
    fingerprint: str | None = None,
    state_dim: int | None = None,
    representation: str = "tpsr",
    environment: str | None = "full",
    seed: int = 0,
) -> Path:
    """A greedy policy with random Q weights over the model's states (for plumbing tests)."""
    model = load_model(model_path)
    r = state_dim or model.state_dim
    rng = np.random.default_rng(seed)
    q = QFunction(np.zeros(r), np.ones(r), rng.normal(size=(8, r)), 1.0, rng.normal(size=(8, 25)))
    policy = Policy(
        q,
        representation,
        fingerprint or model_fingerprint(model),
        environment,
        metadata={"model_path": str(model_path)},
    )
    save_policy(policy, out)
    return out


def scaled_model(model_path: Path, out: Path, actions, factor: float) -> Path:
    """The model with ``B[a]`` multiplied by ``factor`` for ``actions``: updates overflow."""
    model = load_model(model_path)
    arrays = model.to_arrays()
    arrays["B"] = arrays["B"].copy()
    for a in actions:
        arrays["B"][a] *= factor
    broken = TPSRModel.from_arrays(arrays, model.parameters(), model.summary())
    save_model(broken, out, training=read_metadata(model_path)["training"])
    return out


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("filter")
    model = fit_small_model(tmp)
    policy = random_policy(model, tmp / "policy.npz")
    feed = tmp / "feed"
    generate_bag(feed, SimConfig(environment="full"), 40, seed=11)
    with BagReader(feed) as reader:
        msgs = {t: {} for t in ("/camera/image_raw", "/action")}
        for bag_msg in reader.messages(list(msgs)):
            msg = bag_msg.decode()
            msgs[bag_msg.topic][m.stamp_of(msg)] = msg
    return {
        "tmp": tmp,
        "model": model,
        "policy": policy,
        "images": msgs["/camera/image_raw"],
        "actions": msgs["/action"],
    }


def offline_track(model: Path, images: dict, actions: dict, stamps, tmp: Path):
    """Offline tracking (read_trajectory + track_trajectory) of exactly these steps."""
    bag = tmp / f"expected_{time.monotonic_ns()}"
    with BagWriter(bag) as writer:
        writer.add_topic("/camera/image_raw", m.IMAGE_TYPE)
        writer.add_topic("/action", m.ACTION_TYPE)
        for s in sorted(stamps):
            writer.write_message("/camera/image_raw", s, images[s])
            writer.write_message("/action", s, actions[s])
    trajectory = read_trajectory([bag])
    return trajectory.stamps, track_trajectory(load_model(model), trajectory)


def offline_states(model: Path, images: dict, actions: dict, stamps, tmp: Path) -> dict:
    """Stamp -> state of :func:`offline_track`."""
    stamps, track = offline_track(model, images, actions, stamps, tmp)
    return {int(s): track.states[i] for i, s in enumerate(stamps)}


class Harness:
    """A filter node, a feeder publishing its inputs, and a probe of its outputs."""

    def __init__(self, model: Path, policy: Path | None = None, *params: str) -> None:
        self.bus = InprocBus()
        self.feeder = Node(NodeOptions(name="feeder"), transport=InprocTransport("/f", self.bus))
        self.pubs = {
            "/camera/image_raw": self.feeder.create_publisher("/camera/image_raw", m.IMAGE_TYPE),
            "/action": self.feeder.create_publisher("/action", m.ACTION_TYPE),
            "/sim/episode_start": self.feeder.create_publisher(
                "/sim/episode_start", m.POSE_TYPE, LATCHED_QOS
            ),
            "/clock": self.feeder.create_publisher("/clock", m.CLOCK_TYPE),
        }
        self.states: list[tuple[int, np.ndarray]] = []
        self.commands: list[tuple[float, float]] = []
        self.diagnostics: list = []
        self.feeder.create_subscription(
            "/tpsr/state",
            m.STATE_TYPE,
            lambda x: self.states.append((m.stamp_of(x), m.state_to_array(x))),
        )
        self.feeder.create_subscription(
            "/cmd_vel", m.TWIST_TYPE, lambda x: self.commands.append(m.twist_to_xy(x))
        )
        self.feeder.create_subscription(
            "/diagnostics", DIAGNOSTICS_TYPE, lambda x: self.diagnostics.append(x)
        )
        args = ["-p", f"model:={model}"]
        if policy is not None:
            args += ["-p", f"policy:={policy}"]
        for p in params:
            args += ["-p", p]
        options = NodeOptions.for_node(FilterNode, parse_ros_args(args))
        self.node = FilterNode(options, transport=InprocTransport("/tpsr_filter", self.bus))
        self.log = io.StringIO()
        self.node.logger.stream = self.log
        if policy is not None:  # the first command waits for its subscriber + settle time
            deadline = time.monotonic() + 10
            while not self.node.commands_ready and time.monotonic() < deadline:
                self.node.spin_once(0.01)
            assert self.node.commands_ready

    def send(self, topic: str, msg, raw: bytes | None = None) -> None:
        pub = self.pubs[topic]
        if raw is not None:
            pub.publish_raw(raw)
        else:
            pub.publish(msg)
        self.node.spin_once(0.0)
        self.feeder.spin_once(0.0)

    def step(self, images: dict, actions: dict, s: int) -> None:
        self.send("/camera/image_raw", images[s])
        self.send("/action", actions[s])

    def values(self) -> dict:
        return self.node.diagnostics_values()

    def close(self) -> None:
        self.node.close()
        self.feeder.close()


def _image(msg, **changes):
    fields = {
        k: getattr(msg, k)
        for k in ("header", "height", "width", "encoding", "is_bigendian", "step", "data")
    }
    fields.update(changes)
    return type(msg)(**fields)


def _header(msg, frame):
    return type(msg.header)(stamp=msg.header.stamp, frame_id=frame)


def assert_states_equal(published, expected):
    assert [s for s, _ in published] == sorted(expected)
    for stamp, state in published:
        np.testing.assert_allclose(state, expected[stamp], rtol=0, atol=1e-12)


# -- faults ---------------------------------------------------------------------------------


@pytest.mark.slow
def test_faults_are_counted_and_states_after_recovery_equal_offline_tracking(small):
    images, actions = small["images"], small["actions"]
    t = {k: k * S for k in range(1, 41)}
    assert set(t.values()) <= set(images)
    h = Harness(small["model"])
    try:
        for k in range(1, 6):
            h.step(images, actions, t[k])
        h.send("/action", actions[t[6]])  # image 6 lost
        for k in range(7, 10):
            h.step(images, actions, t[k])
        corrupted = _image(images[t[10]], data=np.asarray(images[t[10]].data)[:700])
        h.send("/camera/image_raw", corrupted)  # bad data length
        h.send("/action", actions[t[10]])
        h.step(images, actions, t[11])
        h.send("/camera/image_raw", images[t[12]])
        h.send("/camera/image_raw", images[t[12]])  # duplicate while buffered
        h.send("/action", actions[t[12]])
        h.step(images, actions, t[12])  # duplicates of a processed step
        h.send("/camera/image_raw", images[t[14]])
        h.send("/camera/image_raw", images[t[13]])  # out of order, still used
        h.send("/action", actions[t[13]])
        h.send("/action", actions[t[14]])
        h.step(images, actions, t[16])
        h.step(images, actions, t[15])  # too late: step 16 was processed
        bad = images[t[17]]
        h.send("/camera/image_raw", _image(bad, encoding="bgr8"))
        h.send("/camera/image_raw", _image(bad, encoding="bgr8"))  # same warning: throttled
        h.send(
            "/camera/image_raw",
            _image(bad, height=8, width=8, step=24, data=np.asarray(bad.data)[:192]),
        )
        h.send("/camera/image_raw", _image(bad, header=_header(bad, "map")))
        h.send("/camera/image_raw", None, raw=b"\x00\x01\x00\x00not an image at all")
        h.send("/action", m.twist_stamped_msg(t[17], float("nan"), 0.0))
        h.send("/action", m.twist_stamped_msg(t[17], 3.0, 0.0, frame_id="odom"))
        for k in range(17, 21):
            h.step(images, actions, t[k])

        used = [1, 2, 3, 4, 5, 7, 8, 9, 11, 12, 13, 14, 16, 17, 18, 19, 20]
        expected = offline_states(
            small["model"], images, actions, [t[k] for k in used], small["tmp"]
        )
        assert_states_equal(h.states, expected)
        v = h.values()
        assert {
            k: v[k]
            for k in (
                "steps",
                "dropped",
                "duplicates",
                "late",
                "out_of_order",
                "gaps",
                "recoveries",
                "time_jumps",
                "errors",
            )
        } == {
            "steps": 17,
            "dropped": 2,
            "duplicates": 3,
            "late": 2,
            "out_of_order": 3,
            "gaps": 3,
            "recoveries": 0,
            "time_jumps": 0,
            "errors": 0,
        }
        assert {
            k: v[f"rejected_{k}"]
            for k in ("data", "encoding", "size", "frame", "undecodable", "action")
        } == {
            "data": 1,
            "encoding": 2,
            "size": 1,
            "frame": 2,
            "undecodable": 1,
            "action": 1,
        }
        log = h.log.getvalue()
        # throttled: one warning per topic (the first rejection on each)
        assert log.count("/camera/image_raw: rejected (") == 1
        assert log.count("/action: rejected (") == 1
        assert "/camera/image_raw: rejected (data)" in log
        h.node.publish_diagnostics()
        h.feeder.spin_once(0.0)
        status = h.diagnostics[-1].status[0]
        assert status.level == WARN and "rejected_encoding" in status.message
        h.step(images, actions, t[21])  # still running
        assert h.states[-1][0] == t[21]
    finally:
        h.close()


def test_a_nan_producing_model_is_recovered_and_counted(small):
    images, actions = small["images"], small["actions"]
    stamps = [k * S for k in range(1, 31)]
    used_actions = [
        int(np.argmin(np.abs(ACTIONS - m.twist_to_xy(actions[s])).sum(1))) for s in stamps
    ]
    worst = max(set(used_actions), key=used_actions.count)
    broken = scaled_model(small["model"], small["tmp"] / "broken.npz", [worst], 1e300)
    h = Harness(broken)
    try:
        for s in stamps:
            h.step(images, actions, s)
        offline_stamps, track = offline_track(broken, images, actions, stamps, small["tmp"])
        assert_states_equal(h.states, dict(zip(offline_stamps.tolist(), track.states, strict=True)))
        assert all(np.isfinite(state).all() for _, state in h.states)
        recoveries = h.values()["recoveries"]
        assert recoveries == int(track.recovered.sum()) >= used_actions.count(worst) > 0
        h.node.publish_diagnostics()
        h.feeder.spin_once(0.0)
        assert h.diagnostics[-1].status[0].level == WARN
    finally:
        h.close()
    # every update degenerate: ERROR after ten in a row, and the node still publishes
    hopeless = scaled_model(small["model"], small["tmp"] / "hopeless.npz", range(25), 1e300)
    h = Harness(hopeless)
    try:
        for s in stamps[:12]:
            h.step(images, actions, s)
        assert len(h.states) == 12 and h.values()["recoveries"] == 12
        h.node.publish_diagnostics()
        h.feeder.spin_once(0.0)
        assert h.diagnostics[-1].status[0].level == ERROR
    finally:
        h.close()


def test_resets_jumps_and_the_command_for_b_star(small):
    images, actions = small["images"], small["actions"]
    t = {k: k * S for k in range(1, 41)}
    policy_file = small["policy"]
    from tpsr_ros.io.policy import load_policy

    policy = load_policy(policy_file)
    model = load_model(small["model"])
    h = Harness(small["model"], policy_file)
    try:
        for k in range(1, 11):
            h.step(images, actions, t[k])
        assert len(h.commands) == 10
        h.send("/sim/episode_start", m.pose_msg(t[11], 10.0, 10.0))  # a reset at t_11
        assert h.values()["resets"] == 1 and len(h.commands) == 11
        assert tuple(h.commands[-1]) == tuple(ACTIONS[policy.action(model.initial_state())])
        for k in range(12, 16):
            h.step(images, actions, t[k])
        h.send("/sim/episode_start", m.pose_msg(t[13], 10.0, 10.0))  # stale: ignored
        assert h.values()["stale_resets"] == 1 and len(h.commands) == 15
        for k in range(1, 6):  # time jumps back (a bag replayed in a loop)
            h.step(images, actions, t[k])
        for k in range(6, 21):
            h.step(images, actions, t[k])
        h.send("/clock", m.clock_msg(t[2]))  # /clock jumps back: re-init and command
        assert h.values()["time_jumps"] == 2 and len(h.commands) == 15 + 20 + 1
        h.step(images, actions, t[3])

        first = offline_states(
            small["model"], images, actions, [t[k] for k in range(1, 11)], small["tmp"]
        )
        second = offline_states(
            small["model"], images, actions, [t[k] for k in range(12, 16)], small["tmp"]
        )
        loop = offline_states(
            small["model"], images, actions, [t[k] for k in range(1, 21)], small["tmp"]
        )
        alone = offline_states(small["model"], images, actions, [t[3]], small["tmp"])
        got = h.states
        assert [s for s, _ in got] == (
            [t[k] for k in range(1, 11)]
            + [t[k] for k in range(12, 16)]
            + [t[k] for k in range(1, 21)]
            + [t[3]]
        )
        # after the reset, the loop and the /clock jump, segments start from b_*
        expected = [*first.values(), *second.values(), *loop.values(), *alone.values()]
        for (_, state), want in zip(got, expected, strict=True):
            np.testing.assert_allclose(state, want, rtol=0, atol=1e-12)
        # every command is the greedy action of the state just published (or of b_*)
        assert h.commands[:10] == [tuple(ACTIONS[policy.action(x)]) for _, x in got[:10]]
    finally:
        h.close()


def test_a_swapped_policy_chooses_every_later_command(small):
    images, actions = small["images"], small["actions"]
    from tpsr_ros.io.policy import load_policy

    other = random_policy(small["model"], small["tmp"] / "other_policy.npz", seed=1)
    before, after = load_policy(small["policy"]), load_policy(other)
    h = Harness(small["model"], small["policy"])
    try:
        for k in range(1, 6):
            h.step(images, actions, k * S)
        assert h.node.on_parameter_change("policy", str(other)) is None
        for k in range(6, 21):
            h.step(images, actions, k * S)
        states = [x for _, x in h.states]
        greedy = [before.action(x) for x in states[:5]] + [after.action(x) for x in states[5:]]
        assert h.commands == [tuple(ACTIONS[a]) for a in greedy]
        assert greedy[5:] != [before.action(x) for x in states[5:]]  # the swap shows
    finally:
        h.close()


def test_an_added_observer_takes_every_tracked_step_restart_and_swap(small):
    from tpsr_ros.filter_node.observers import StepObserver, Tracked
    from tpsr_ros.filter_node.swap import ModelUpdate

    class Recorder(StepObserver):  # what a learner consuming the node's steps would see
        def __init__(self) -> None:
            self.steps: list[tuple[int, int, np.ndarray, bool]] = []
            self.new_segments: list[bool] = []
            self.events: list[str] = []

        def observe(self, tracked: Tracked) -> None:
            step = tracked.step
            self.steps.append((step.stamp, step.action, tracked.info.state, tracked.q_values
                               is not None))  # fmt: skip
            self.new_segments.append(tracked.new_segment)

        def restarted(self, state: np.ndarray) -> None:
            self.events.append(f"restart {len(self.steps)}")

        def swapped(self, inputs) -> None:
            self.events.append(f"swap {len(self.steps)} {inputs.fingerprint[:12]}")

    images, actions = small["images"], small["actions"]
    h = Harness(small["model"], small["policy"])
    try:
        recorder = Recorder()
        h.node.observers.append(recorder)
        for k in range(1, 6):
            h.step(images, actions, k * S)
        h.send("/sim/episode_start", m.pose_msg(6 * S, 10.0, 10.0))
        for k in range(7, 10):
            h.step(images, actions, k * S)
        assert h.node.swap_model(ModelUpdate(str(small["model"]))) is None
        h.step(images, actions, 10 * S)
        h.step(images, actions, 2 * S)  # time jumps back 8 s: this step starts a segment
        fingerprint = h.node.inputs.fingerprint[:12]
        assert recorder.events == ["restart 5", f"swap 8 {fingerprint}"]
        assert [(s, a) for s, a, _, _ in recorder.steps] == [
            (k * S, actions_index(actions[k * S])) for k in (1, 2, 3, 4, 5, 7, 8, 9, 10, 2)
        ]
        assert recorder.new_segments == [False] * 9 + [True]
        assert [stamp for stamp, _, _ in h.node.replay.steps()] == [2 * S]  # a swap replays it
        assert [stamp for stamp, _ in h.states] == [s for s, _, _, _ in recorder.steps]
        for (_, published), (_, _, state, with_values) in zip(h.states, recorder.steps,
                                                            strict=True):  # fmt: skip
            assert published.tobytes() == np.asarray(state, dtype=float).tobytes()
            assert with_values  # the command's Q-values, left for later observers
    finally:
        h.close()


def actions_index(msg) -> int:
    """The index of an action message's (vx, vy) among the 25 actions."""
    vx, vy = msg.twist.linear.x, msg.twist.linear.y
    return next(i for i, (ax, ay) in enumerate(ACTIONS) if (ax, ay) == (vx, vy))


def test_a_late_joiner_gets_the_latched_episode_start(small):
    bus = InprocBus()
    feeder = Node(NodeOptions(name="sim"), transport=InprocTransport("/sim", bus))
    feeder.create_publisher("/sim/episode_start", m.POSE_TYPE, LATCHED_QOS).publish(
        m.pose_msg(7 * S, 5.0, 5.0)
    )
    commands = []
    feeder.create_subscription("/cmd_vel", m.TWIST_TYPE, commands.append)
    options = NodeOptions.for_node(
        FilterNode,
        parse_ros_args(["-p", f"model:={small['model']}", "-p", f"policy:={small['policy']}"]),
    )
    node = FilterNode(options, transport=InprocTransport("/f", bus))
    node.logger.stream = io.StringIO()
    try:
        deadline = time.monotonic() + 10
        while not commands and time.monotonic() < deadline:
            node.spin_once(0.01)
            feeder.spin_once(0.0)
        assert len(commands) == 1 and node.resets == 1
        assert node.source.last_stamp == 7 * S
    finally:
        node.close()
        feeder.close()


# -- diagnostics ----------------------------------------------------------------------------


def test_diagnostics_report_every_documented_key(small):
    h = Harness(small["model"], small["policy"])
    try:
        h.node.publish_diagnostics()
        h.feeder.spin_once(0.0)
        status = h.diagnostics[-1].status[0]
        assert status.level == OK and status.message == "waiting for paired images and actions"
        for s in [k * S for k in range(1, 6)]:
            h.step(small["images"], small["actions"], s)
        h.node.publish_diagnostics()
        h.feeder.spin_once(0.0)
        status = h.diagnostics[-1].status[0]
        values = status_values(status)
        assert status.level == OK and status.message == "tracking"
        assert status.name == "tpsr_filter: state tracking" and status.hardware_id == "tpsr"
        assert values["steps"] == "5" and values["commands"] == "5"
        assert values["last_stamp_s"] == "5.000000000"
        assert float(values["latency_p99_ms"]) >= float(values["latency_p50_ms"]) > 0
        assert float(values["update_rate_hz"]) > 0
        documented = DOC.read_text().split("## Diagnostics")[1].split("\n## ")[0]
        for key in values:
            assert f"`{key}`" in documented, key
    finally:
        h.close()


# -- start-up checks ------------------------------------------------------------------------


def _refusal(params: FilterNodeParams, image="/camera/image_raw", action="/action") -> str:
    with pytest.raises(TpsrError) as exc:
        load_inputs(params, image, action)
    text = str(exc.value)
    assert "\n" not in text
    return text


def test_start_up_refusals(small):
    tmp, model = small["tmp"], small["model"]
    assert "no model" in _refusal(FilterNodeParams())
    other = random_policy(model, tmp / "other.npz", fingerprint="0" * 64)
    assert "trained for model 000000000000" in _refusal(
        FilterNodeParams(model=str(model), policy=str(other))
    )
    truth = random_policy(
        model,
        tmp / "truth.npz",
        fingerprint="true-position",
        representation="true-position",
        state_dim=2,
    )
    assert "true position" in _refusal(FilterNodeParams(model=str(model), policy=str(truth)))
    wide = random_policy(model, tmp / "wide.npz", state_dim=7)
    assert "7-dimensional" in _refusal(FilterNodeParams(model=str(model), policy=str(wide)))
    partial = random_policy(model, tmp / "partial.npz", environment="partial")
    assert "environment 'partial'" in _refusal(
        FilterNodeParams(model=str(model), policy=str(partial))
    )
    text = _refusal(FilterNodeParams(model=str(model)), image="/robot/camera/image_raw")
    assert "trained on /camera/image_raw and /action" in text and "check_topics" in text
    # the override, and the fully resolved names (remaps, namespace) in preflight
    load_inputs(FilterNodeParams(model=str(model), check_topics=False), "/robot/x", "/robot/y")
    ok = NodeOptions.for_node(
        FilterNode,
        parse_ros_args(["-p", f"model:={model}", "-r", "/camera/image_raw:=/camera/image_raw"]),
    )
    FilterNode.preflight(ok)
    bad = NodeOptions.for_node(
        FilterNode, parse_ros_args(["-p", f"model:={model}", "-r", "/action:=/robot/action"])
    )
    with pytest.raises(TpsrError, match="node subscribes /camera/image_raw and /robot/action"):
        FilterNode.preflight(bad)


@pytest.mark.slow
def test_the_command_line_refuses_in_one_line(small, tmp_path):
    other = random_policy(small["model"], tmp_path / "other.npz", fingerprint="f" * 64)
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "tpsr_ros.filter_node",
            "--ros-args",
            "-p",
            f"model:={small['model']}",
            "-p",
            f"policy:={other}",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env={**__import__("os").environ, "TPSR_TRANSPORT": "inproc"},
    )
    assert proc.returncode == 1
    assert re.fullmatch(r"python -m tpsr_ros\.filter_node: error: .*ffffffffffff.*\n", proc.stderr)
