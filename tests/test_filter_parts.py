"""The filter node's ROS-free parts: the health ledger, the two step sources, the simulator
inputs read from CDR bytes and the state messages written as CDR bytes."""

from __future__ import annotations

import numpy as np
import pytest

from tpsr_ros.core.actions import PLANAR
from tpsr_ros.core.episodes import image_to_observation
from tpsr_ros.core.errors import MessageError
from tpsr_ros.core.resample import GridConfig, resample_grid
from tpsr_ros.filter_node.health import ERROR, OK, STALE, WARN, HealthLedger, Throttle
from tpsr_ros.filter_node.inputs import Rejected
from tpsr_ros.filter_node.simulator_inputs import SimulatorInputs
from tpsr_ros.filter_node.stepping import ExactPairing, GridStepping
from tpsr_ros.io import messages as m

S = 10**9
TOPICS = {"image": "/camera/image_raw", "action": "/action"}


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_throttle_lets_one_warning_through_per_period_and_counts_the_rest() -> None:
    clock = FakeClock()
    throttle = Throttle(5.0, clock)
    key = ("/camera/image_raw", "rejected")
    assert throttle(key) and not throttle(key) and not throttle(key)
    assert throttle(("/action", "rejected"))  # another key is not held back
    clock.now += 5.0
    assert throttle(key) and throttle.take_suppressed(key) == 2
    assert throttle.take_suppressed(key) == 0


def test_ledger_rates_silence_and_levels() -> None:
    clock = FakeClock()
    ledger = HealthLedger(input_timeout_s=3.0, clock=clock)
    assert ledger.assess({}, 0, TOPICS) == (OK, "waiting for paired images and actions")
    for k in range(11):  # 10 Hz on both inputs for one second
        ledger.arrived("image")
        ledger.arrived("action")
        clock.now += 0.1 if k < 10 else 0.0
    values = ledger.input_values(TOPICS)
    assert values["image_rate_hz"] == pytest.approx(10.0) and values["action_age_s"] == 0.0
    assert ledger.assess({"dropped": 0}, 11, TOPICS) == (OK, "tracking")
    ledger.reported({"dropped": 0}, 11)
    assert ledger.assess({"dropped": 2}, 12, TOPICS) == (WARN, "since the last report: dropped")
    clock.now += 4.0
    ledger.arrived("action")
    level, message = ledger.assess({"dropped": 0}, 12, TOPICS)
    assert level == WARN and message.startswith("/camera/image_raw silent for 4.")
    clock.now += 4.0
    level, message = ledger.assess({}, 12, TOPICS)
    assert level == STALE and "no /camera/image_raw, no /action" in message


def test_ledger_errors_on_a_run_of_recoveries_or_when_everything_is_rejected() -> None:
    ledger = HealthLedger(3.0, clock=FakeClock())
    for _ in range(10):
        ledger.update(recovered=True)
    assert ledger.assess({}, 10, TOPICS)[0] == ERROR
    ledger.update(recovered=False)
    assert ledger.assess({}, 11, TOPICS)[0] == OK
    ledger.reported({"rejected_size": 0}, 11)
    ledger.reject("size")
    level, message = ledger.assess({"rejected_size": 1}, 11, TOPICS)
    assert level == ERROR and "every message rejected (1" in message


def test_exact_pairing_pairs_by_stamp_in_any_order_and_counts_lost_steps() -> None:
    source = ExactPairing(S, queue_size=10, jump_threshold_ns=5 * S)
    assert source.add_action(1 * S, 3).steps == []
    (step,) = source.add_image(1 * S, "o1").steps
    assert (step.stamp, step.action, step.image) == (1 * S, 3, "o1")
    assert source.add_image(4 * S, "o4").steps == []  # steps 2 and 3 lost on the camera
    (step,) = source.add_action(4 * S, 7).steps
    assert step.image == "o4"
    counts = source.counts()
    assert counts["lost_images"] == 2 and counts["lost_actions"] == 2
    assert source.add_image(4 * S, "again").problem == "duplicate"
    assert source.add_image(3 * S, "late").problem == "late"
    jumped = source.add_image(2 * S, "o2")  # 2 s back is no jump (threshold 5 s): late
    assert not jumped.jumped and jumped.problem == "late"
    assert source.clock(0) is False
    assert source.add_action(0, 1).problem == "late"
    assert source.episode_start(10 * S) and not source.episode_start(9 * S)  # then stale
    assert source.add_action(1 * S, 2).jumped  # 9 s before the episode start: time jumped


def test_grid_stepping_equals_offline_resampling() -> None:
    rng = np.random.default_rng(1)
    grid = GridConfig(S, S // 4, S, 2 * S)
    images = np.cumsum(rng.uniform(0.15, 0.4, size=200) * S).astype(np.int64)
    commands = np.sort(rng.uniform(0, images[-1], size=120)).astype(np.int64)
    offline = resample_grid(images, commands, grid)
    source = GridStepping(grid, jump_threshold_ns=5 * S)
    online = []
    events = sorted(
        [(t, 0, k) for k, t in enumerate(images)] + [(t, 1, k) for k, t in enumerate(commands)]
    )
    for time, kind, index in events:  # each message at its time: commands before images
        added = source.add_action(int(time), index) if kind else source.add_image(int(time), index)
        online += added.steps
    online += source.flush().steps  # the streams end: the steps before the last image
    assert [s.stamp for s in online] == offline.stamps.tolist()
    assert [s.image for s in online] == offline.image_index.tolist()
    assert [s.action for s in online] == offline.command_index.tolist()
    assert source.counts()["command_gaps"] == offline.no_command


@pytest.mark.parametrize("seed", range(5))
def test_unstamped_commands_get_their_offline_dates_in_any_handling_order(seed) -> None:
    """Commands without stamps are dated by the first image sent after them; handled in
    any order within the latency bound (a backend serving one topic before the other),
    the steps are those of the bag's order."""
    rng = np.random.default_rng(seed)
    grid = GridConfig(75 * S // 1000, 55 * S // 1000, 3 * S // 10, 3 * S // 10, phase_ns=0)
    frames = np.cumsum(rng.uniform(0.04, 0.16, 150) * S).astype(np.int64)
    images = [(int(t) + 2 * 10**6, "image", int(t), k) for k, t in enumerate(frames)]
    commands = [(int(t), "command", None, k) for k, t in enumerate(frames)]  # at frame stamps
    sent_order = sorted(images + commands)  # (sent, kind, stamp, index): as a bag logs them
    # offline: each command dated by the next image in the bag's order
    dates, pending = [], []
    for _, kind, stamp, k in sent_order:
        if kind == "command":
            pending.append(k)
        else:
            dates += [(stamp, c) for c in pending]
            pending = []
    offline = resample_grid(frames, np.array([d for d, _ in dates]), grid)
    indices = zip(offline.stamps, offline.command_index, offline.image_index, strict=True)
    expected = [(int(s), dates[c][1], int(i)) for s, c, i in indices]
    # online: each topic in its own order, the two interleaved by random delays up to 0.3 s
    arrival = {}
    for kind in ("image", "command"):
        stream = [e for e in sent_order if e[1] == kind]
        late = np.maximum.accumulate([e[0] + rng.uniform(0, 0.3 * S) for e in stream])
        arrival.update({e: t for e, t in zip(stream, late, strict=True)})
    handled = sorted(sent_order, key=arrival.__getitem__)
    source = GridStepping(grid, jump_threshold_ns=5 * S, max_latency_ns=S)
    online = []
    for sent, kind, stamp, k in handled:
        if kind == "image":
            online += source.add_image(stamp, k, sent_ns=sent).steps
        else:
            online += source.add_action(None, k, sent_ns=sent).steps
    online += source.flush().steps
    assert [(s.stamp, s.action, s.image) for s in online] == expected
    assert len(expected) > 100


def _image_cdr(stamp: int, seed: int, **changes) -> bytes:
    rgb = np.random.default_rng(seed).integers(0, 256, size=(4, 5, 3), dtype=np.uint8)
    msg = m.image_msg(stamp, rgb)
    return m.serialize(type(msg)(**{**msg.__dict__, **changes}), m.IMAGE_TYPE)


def test_simulator_inputs_read_a_learnt_layout_as_the_checks_do_and_check_anything_else():
    inputs = SimulatorInputs((4, 5), "camera", "base_link", PLANAR)
    for k in range(1, 4):  # the first is checked and learnt, the others read at its offsets
        rgb = np.random.default_rng(k).integers(0, 256, size=(4, 5, 3), dtype=np.uint8)
        stamp, observation = inputs.image(_image_cdr(k * S, k))
        assert stamp == k * S
        np.testing.assert_array_equal(observation, image_to_observation(rgb))
        action = m.serialize(m.twist_stamped_msg(k * S, 3.0, -6.0), m.ACTION_TYPE)
        assert inputs.action(action) == (k * S, PLANAR.indices(np.array([[3.0, -6.0]]))[0])
    header = m.image_msg(S, np.zeros((4, 5, 3), np.uint8)).header
    refused = {
        "frame": _image_cdr(S, 0, header=type(header)(stamp=header.stamp, frame_id="map")),
        "encoding": _image_cdr(S, 0, encoding="bgr8"),
        "data": _image_cdr(S, 0, data=np.zeros(59, np.uint8)),
        "undecodable": b"\x00\x01\x00\x00not an image",
    }
    for reason, data in refused.items():
        with pytest.raises(Rejected) as caught:
            inputs.image(data)
        assert caught.value.reason == reason
    for vx, frame, reason in ((1.5, "base_link", "action"), (3.0, "odom", "frame")):
        data = m.serialize(m.twist_stamped_msg(5 * S, vx, 0.0, frame_id=frame), m.ACTION_TYPE)
        with pytest.raises(Rejected) as caught:  # the first has the learnt layout
            inputs.action(data)
        assert caught.value.reason == reason
    assert inputs.image(_image_cdr(6 * S, 6))[0] == 6 * S  # still reading


@pytest.mark.parametrize("frame", ["", "a", "tpsr", "abcdefg"])
@pytest.mark.parametrize("size", [1, 3, 8, 16])
def test_state_messages_written_as_cdr_are_those_of_the_serialiser(size, frame):
    encode = m.StateEncoder(size, frame)
    for stamp in (0, 7, 1_500_000_002, (2**31 - 1) * S):
        state = np.random.default_rng(stamp % 97).normal(size=size)
        assert encode(stamp, state) == m.serialize(m.state_msg(stamp, state, frame), m.STATE_TYPE)
    with pytest.raises(MessageError):
        encode(0, np.zeros(size + 1))
