"""A phone-like robot's bag (a jittery ~14 Hz JPEG camera, unstamped commands logged at the
frame stamps) fits with only its topics and a step period, and its replay through the
filter node gives exactly `learner track`'s states, first step included, on both backends
at half and four times its speed (slower and faster than recorded), with no image counted
lost."""

from __future__ import annotations

import numpy as np
import pytest
from graph_support import BACKENDS, LOOPBACK, fresh_domain
from replay_support import replay_states

from learner.cli import main as learner_main
from sim_node.robot_bag import COMPRESSED_TOPIC, RobotBagConfig, write_robot_bag
from tpsr_ros.io import messages as m

STEP = "0.075"


@pytest.fixture(scope="module")
def phone(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("phone")
    bag, model, states = tmp / "phone", tmp / "phone.npz", tmp / "states.npz"
    write_robot_bag(bag, RobotBagConfig(steps=12, seed=3, timeline="phone"))
    topics = ["--image-topic", COMPRESSED_TOPIC, "--action-topic", "/cmd_vel"]
    assert learner_main(["fit", str(bag), *topics, "--step-period", STEP, "-o", str(model)]) == 0
    assert learner_main(["track", str(model), str(bag), "-o", str(states)]) == 0
    with np.load(states, allow_pickle=False) as data:
        expected = dict(zip(data["stamp_ns"].tolist(), data["states"], strict=True))
    return {"bag": bag, "model": model, "expected": expected}


def test_the_phone_bag_is_tracked_in_one_segment_from_its_first_step(phone):
    from tpsr_ros.io.bag import BagReader
    from tpsr_ros.io.model_io import model_stream_spec, read_metadata

    spec = model_stream_spec(phone["model"], read_metadata(phone["model"]))
    with BagReader(phone["bag"]) as reader:
        first = min(m.stamp_of(x.decode()) for x in reader.messages([COMPRESSED_TOPIC]))
    stamps = sorted(phone["expected"])
    assert stamps[0] - first < spec.grid.step_ns  # the first grid step is tracked
    assert np.all(np.diff(stamps) == spec.grid.step_ns)  # no gap: the jitter is not silence
    assert (spec.preprocessing.width, spec.preprocessing.height) == (16, 6)  # 256x96 kept


@pytest.mark.slow
@pytest.mark.parametrize(
    ("backend", "rates"),
    [  # either side of real time on one backend, faster than real time on the other
        pytest.param(b.values[0], ("0.5", "4") if b.values[0] == "dds" else ("4",), marks=b.marks)
        for b in BACKENDS
    ],
)
def test_a_replay_at_any_rate_gives_learner_tracks_states(
    phone, backend, rates, tmp_path, monkeypatch
):
    monkeypatch.setenv("ROS_DOMAIN_ID", str(fresh_domain(41)))
    monkeypatch.setenv("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST")
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    monkeypatch.setenv("TPSR_TRANSPORT", backend)
    expected = phone["expected"]
    for rate in rates:
        states, log = replay_states(
            phone["model"], phone["bag"], [COMPRESSED_TOPIC, "/cmd_vel"], rate, len(expected),
            tmp_path / rate,
        )
        assert [s for s, _ in states] == sorted(expected), (rate, log)
        for stamp, state in states:
            assert np.array_equal(state, expected[stamp]), (rate, stamp)
        assert f"tracked {len(expected)} steps" in log and "lost_images" not in log, log
