"""Model swaps of a running filter node: at a step boundary, the state re-filtered or
restarted, equal bit for bit to `learner track --swap-at`; refused models leave the old one
running; every swap acknowledged on tpsr/model_info."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_filter_node import Harness, S, fit_small_model, random_policy, small  # noqa: F401

from learner.cli import main as learner_main
from tpsr_ros.core.online import OnlineTracker
from tpsr_ros.io.model_io import load_model, open_model
from tpsr_ros.runtime import LATCHED_QOS

STRING = "std_msgs/msg/String"


@pytest.fixture(scope="module")
def second(small, tmp_path_factory):  # noqa: F811
    """Another model of the same inputs (another training run), and a policy for it."""
    tmp = tmp_path_factory.mktemp("swap")
    model = fit_small_model(tmp, seed=4)
    return {"model": model, "policy": random_policy(model, tmp / "policy.npz", seed=1)}


def _run(h: Harness, small, first: int, last: int) -> None:  # noqa: F811
    for k in range(first, last + 1):
        h.step(small["images"], small["actions"], k * S)


def _infos(h: Harness) -> list[dict]:
    infos: list[dict] = []
    h.feeder.create_subscription(
        "/tpsr/model_info", STRING, lambda msg: infos.append(json.loads(msg.data)), LATCHED_QOS
    )
    h.feeder.spin_once(0.0)
    return infos


def _offline(small, second, tmp_path, state: str) -> np.ndarray:  # noqa: F811
    out = tmp_path / f"swap_{state}.npz"
    assert learner_main([
        "track", str(small["model"]), str(small["tmp"] / "feed"), "-o", str(out),
        "--swap-at", str(21 * S), "--swap-model", str(second["model"]), "--swap-state", state,
        "--swap-replay-steps", "5",
    ]) == 0  # fmt: skip
    with np.load(out, allow_pickle=False) as archive:
        return archive["states"]


@pytest.mark.parametrize("state", ["replay", "restart"])
def test_a_swap_between_steps_equals_learner_track_swap_at(small, second, tmp_path, state):  # noqa: F811
    h = Harness(small["model"], None, f"swap_state:={state}", "swap_replay_steps:=5")
    infos = _infos(h)
    try:
        _run(h, small, 1, 20)
        assert h.node.on_parameter_change("model", str(second["model"])) is None
        _run(h, small, 21, 40)
        h.feeder.spin_once(0.0)
        values = h.values()
    finally:
        h.close()
    assert [stamp for stamp, _ in h.states] == [k * S for k in range(1, 41)]  # no step missed
    expected = _offline(small, second, tmp_path, state)
    np.testing.assert_array_equal(np.array([s for _, s in h.states]), expected)
    new = open_model(second["model"]).fingerprint
    assert values["model_swaps"] == 1 and values["model"] == new[:12]
    assert infos[-1]["fingerprint"] == new and infos[-1]["first_stamp_ns"] == 21 * S
    assert infos[0]["fingerprint"] != new and infos[0]["swaps"] == 0


def test_the_replayed_state_is_the_new_model_over_the_last_steps(small, second):  # noqa: F811
    first, new = load_model(small["model"]), load_model(second["model"])
    tracker = OnlineTracker(first)
    obs = np.random.default_rng(0).random((8, first.obs_size))
    steps = [(k * S, k % 3, obs[k]) for k in range(8)]
    for step in steps[:6]:
        tracker.step(*step)
    tracker.swap(new, steps[3:6])
    assert tracker.steps == 6  # the replayed steps are not counted again
    expected = new.track(np.array([a for _, a, _ in steps[3:7]]), obs[3:7]).states[-1]
    np.testing.assert_array_equal(tracker.step(*steps[6]).state, expected)


def test_an_announced_update_swaps_and_a_bad_one_leaves_the_old_model(small, second, tmp_path):  # noqa: F811
    h = Harness(small["model"], small["policy"])
    infos = _infos(h)
    update = h.feeder.create_publisher("/tpsr/model_update", STRING, LATCHED_QOS)
    try:
        _run(h, small, 1, 10)
        corrupt = tmp_path / "corrupt.npz"
        corrupt.write_bytes(b"not a model")
        for text in ("not json", json.dumps({"path": str(corrupt)}),
                     json.dumps({"path": str(second["model"]), "fingerprint": "0000"})):
            update.publish(_string(text))
            h.node.spin_once(0.0)
        assert h.values()["model_swaps_refused"] == 3 and h.values()["model_swaps"] == 0
        _run(h, small, 11, 15)  # the old model keeps tracking and commanding
        commands_before = len(h.commands)
        announced = {"path": str(second["model"]), "version": 7,
                     "fingerprint": open_model(second["model"]).fingerprint[:12]}
        update.publish(_string(json.dumps(announced)))
        h.node.spin_once(0.0)
        _run(h, small, 16, 20)
        log = h.log.getvalue()
        assert h.values()["model_swaps"] == 1 and h.values()["model_version"] == 7
        assert h.node.policy is None and "tracking without commanding" in log
        assert len(h.commands) == commands_before  # its policy was for the old model
        assert h.node.on_parameter_change("policy", str(second["policy"])) is None
        _run(h, small, 21, 22)
        assert len(h.commands) == commands_before + 2
        h.feeder.spin_once(0.0)
    finally:
        h.close()
    assert [s for s, _ in h.states] == [k * S for k in range(1, 23)]
    assert infos[-1]["version"] == 7 and infos[-1]["first_stamp_ns"] == 16 * S


def _string(text: str):
    from tpsr_ros.filter_node.swap import string_msg

    return string_msg(text)


def test_models_for_other_inputs_are_refused_with_the_reason(small, tmp_path):  # noqa: F811
    from test_filter_node import SMALL

    from sim_node import SimConfig
    from sim_node.generate import generate_bag

    generate_bag(tmp_path / "drive", SimConfig(environment="drive"), 900, seed=0)
    drive = tmp_path / "drive.npz"
    assert learner_main(["fit", str(tmp_path / "drive"), "-o", str(drive), *SMALL]) == 0
    h = Harness(small["model"])
    try:
        _run(h, small, 1, 3)
        reason = h.node.on_parameter_change("model", str(drive))
        assert reason is not None and "other inputs" in reason, reason
        assert "does not exist" in h.node.on_parameter_change("model", str(tmp_path / "x.npz"))
        assert h.node.on_parameter_change("model", "") == "model cannot be empty"
        _run(h, small, 4, 5)
        assert h.values()["model_swaps_refused"] == 2 and h.values()["model_swaps"] == 0
        assert h.values()["model"] == open_model(small["model"]).fingerprint[:12]
    finally:
        h.close()
    assert [s for s, _ in h.states] == [k * S for k in range(1, 6)]


def test_replay_and_restart_give_different_states_after_the_swap(small, second, tmp_path):  # noqa: F811
    replayed, restarted = (_offline(small, second, tmp_path, s) for s in ("replay", "restart"))
    np.testing.assert_array_equal(replayed[:20], restarted[:20])
    assert not np.array_equal(replayed[20], restarted[20])


def test_a_waiting_node_starts_with_the_model_set_and_refuses_a_bad_one(small, tmp_path):  # noqa: F811
    """wait_for_model: ``/diagnostics`` says it waits (STALE); ``ros2 param set ... model``
    starts it, checked as at start-up."""
    from tpsr_ros.filter_node import FilterNode
    from tpsr_ros.runtime import Node, NodeOptions, parse_ros_args
    from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE
    from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

    bus = InprocBus()
    options = NodeOptions.for_node(
        FilterNode, parse_ros_args(["-p", "wait_for_model:=true", "-p", "diagnostics_period:=0.02"])
    )
    node = FilterNode(options, transport=InprocTransport("/tpsr_filter", bus))
    probe = Node(NodeOptions(name="probe"), transport=InprocTransport("/probe", bus))
    reports: list = []
    probe.create_subscription("/diagnostics", DIAGNOSTICS_TYPE, reports.append)
    try:
        while not reports:
            node.spin_once(0.02)
            probe.spin_once(0.0)
        (status,) = reports[-1].status
        assert status.level == 3 and "waiting for one on /tpsr/model_update" in status.message
        assert not hasattr(node, "inputs")
        corrupt = tmp_path / "corrupt.npz"
        corrupt.write_bytes(b"not a model")
        assert "not a readable model file" in node.on_parameter_change("model", str(corrupt))
        assert not hasattr(node, "inputs")
        assert node.on_parameter_change("model", str(small["model"])) is None
        assert node.inputs.fingerprint == open_model(small["model"]).fingerprint
        assert node.swaps == 0 and node.params.model == str(small["model"])
        reports.clear()
        while not reports:
            node.spin_once(0.02)
            probe.spin_once(0.0)
        assert reports[-1].status[0].level != 3  # the tracking report, no longer waiting
    finally:
        probe.close()
        node.close()
