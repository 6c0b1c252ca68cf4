"""Bags -> trajectory -> episodes: pairing by stamp, segments, episode cutting, bad bags."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tpsr_ros.core.episodes import (
    image_to_observation,
    images_to_observations,
    make_episodes,
    velocities_to_actions,
)
from tpsr_ros.core.errors import BagError, DataError, MessageError
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagWriter
from tpsr_ros.io.trajectory import Topics, read_trajectory

S = 1_000_000_000
VEL = np.array([-6.0, -3.0, 0.0, 3.0, 6.0])


def image_for(step: int, size: int = 16) -> np.ndarray:
    """An image that encodes its step number in pixel (0, 0)."""
    img = np.full((size, size, 3), 7, dtype=np.uint8)
    img[0, 0] = (step % 256, step // 256, 1)
    return img


def write_bag(
    path: Path,
    steps,
    *,
    skip=(),
    image=None,
    velocity=None,
    pose=None,
    topics=None,
    shuffle_log_times=True,
) -> Path:
    """Steps ``k`` stamped ``k`` s; ``skip`` holds (topic, step) pairs left out."""
    topics = topics or Topics()
    rng = np.random.default_rng(0)
    with BagWriter(path) as writer:
        for topic, msgtype in topics.types().items():
            writer.add_topic(topic, msgtype)
        for k in steps:
            stamp = k * S
            vx, vy = velocity(k) if velocity else (VEL[k % 5], VEL[(k // 5) % 5])
            px, py = pose(k) if pose else (float(k), -float(k))
            msgs = [
                (topics.image, image(k) if image else m.image_msg(stamp, image_for(k))),
                (topics.action, m.twist_stamped_msg(stamp, vx, vy)),
                (topics.pose, m.pose_msg(stamp, px, py)),
                (
                    topics.reward,
                    m.reward_msg(stamp, m.RewardSample(float(k % 3 - 1), False, False)),
                ),
            ]
            for topic, msg in msgs:
                if (topic, k) in skip or topic in skip:
                    continue
                # log times jitter up to 0.4 s after the stamp: pairing must use header stamps
                log = stamp + (int(rng.integers(0, 400_000_000)) if shuffle_log_times else 0)
                writer.write_message(topic, log, msg)
    return path


def step_of(observation: np.ndarray) -> int:
    return round(observation[0] * 255) + 256 * round(observation[1] * 255)


def test_image_to_observation_scaling_and_order():
    img = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3) * 10
    obs = image_to_observation(img)
    assert obs.dtype == np.float64 and obs.shape == (18,)
    np.testing.assert_array_equal(obs, img.reshape(-1) / 255.0)
    assert obs[3 * 1 + 2] == img[0, 1, 2] / 255.0  # row-major (height, width, channel)
    np.testing.assert_array_equal(images_to_observations(img[None])[0], obs)
    with pytest.raises(MessageError):
        image_to_observation(img.astype(np.float32))


def test_pairing_by_header_stamp_not_log_time(tmp_path):
    bag = write_bag(tmp_path / "b", range(1, 31))
    traj = read_trajectory([bag])
    assert len(traj) == 30
    np.testing.assert_array_equal(traj.stamps, np.arange(1, 31) * S)
    np.testing.assert_array_equal([step_of(o) for o in traj.observations], np.arange(1, 31))
    k = np.arange(1, 31)
    np.testing.assert_array_equal(traj.velocities, np.c_[VEL[k % 5], VEL[(k // 5) % 5]])
    np.testing.assert_array_equal(traj.actions, 5 * (k % 5) + (k // 5) % 5)
    np.testing.assert_array_equal(traj.positions, np.c_[k, -k])
    np.testing.assert_array_equal(traj.rewards, k % 3 - 1)
    assert traj.segment_bounds() == [(0, 30)]
    assert traj.n_actions == 25 and traj.image_shape == (16, 16)
    assert traj.sources[0]["steps"] == 30 and traj.sources[0]["stamps_ns"] == [S, 30 * S]


def test_gaps_and_missing_messages_split_segments(tmp_path):
    # steps 1-10, gap, 12-20 with step 15's action missing
    bag = write_bag(tmp_path / "b", [*range(1, 11), *range(12, 21)], skip={("/action", 15)})
    traj = read_trajectory([bag])
    assert 15 not in traj.stamps // S
    assert traj.segment_bounds() == [(0, 10), (10, 13), (13, 18)]
    assert traj.sources[0]["unpaired_messages"] == 1
    episodes = make_episodes(traj, 1, 1)
    # 10 steps -> 3 episodes; 3 (12-14) -> 1; 5 (16-20) -> 1: none spans a gap
    assert len(episodes) == 5
    np.testing.assert_array_equal(episodes.stamps // S, [2, 5, 8, 13, 17])
    for i, current in enumerate(episodes.stamps // S):
        assert step_of(episodes.history[i]) == current - 1
        assert step_of(episodes.observation[i]) == current
        assert step_of(episodes.test[i]) == current + 1
    assert episodes.steps().shape == (15, 768)


def test_a_bag_boundary_ends_a_segment(tmp_path):
    a = write_bag(tmp_path / "a", range(1, 7))
    b = write_bag(tmp_path / "b", range(7, 13))
    traj = read_trajectory([a, b])
    assert traj.segment_bounds() == [(0, 6), (6, 12)]
    episodes = make_episodes(traj, 2, 1)  # span 4: one episode per bag
    np.testing.assert_array_equal(episodes.stamps // S, [3, 9])
    assert [step_of(h) for h in episodes.history[1].reshape(2, -1)] == [7, 8]
    assert len(traj.summary()["bags"]) == 2


def test_max_episodes_and_no_usable_episodes(tmp_path):
    traj = read_trajectory([write_bag(tmp_path / "b", range(1, 13))])
    assert len(make_episodes(traj, 1, 1, max_episodes=2)) == 2
    with pytest.raises(DataError, match="no usable episodes"):
        make_episodes(traj, 6, 6)


def test_missing_topic(tmp_path):
    bag = write_bag(tmp_path / "b", range(1, 5), skip={"/action"})
    with pytest.raises(BagError, match=r"no messages on topic\(s\) \['/action'\]"):
        read_trajectory([bag])
    bag2 = write_bag(tmp_path / "c", range(1, 5), skip={"/ground_truth/pose"})
    assert np.isnan(read_trajectory([bag2]).positions).all()
    with pytest.raises(BagError, match="ground_truth/pose"):
        read_trajectory([bag2], require_ground_truth=True)


def test_remapped_topics(tmp_path):
    topics = Topics(image="/cam", action="/act", pose="/pose", reward="/r")
    bag = write_bag(tmp_path / "b", range(1, 5), topics=topics)
    with pytest.raises(BagError, match="no messages on topic"):
        read_trajectory([bag])
    assert len(read_trajectory([bag], topics=topics)) == 4


def test_wrong_encoding_and_size(tmp_path):
    def bgr(k):
        msg = m.image_msg(k * S, image_for(k))
        msg.encoding = "bgr8"
        return msg

    with pytest.raises(MessageError, match="'bgr8' is not rgb8"):
        read_trajectory([write_bag(tmp_path / "a", range(1, 4), image=bgr)])
    small = write_bag(
        tmp_path / "b", range(1, 4), image=lambda k: m.image_msg(k * S, image_for(k, 8))
    )
    with pytest.raises(MessageError, match="8x8, expected 16x16"):
        read_trajectory([small])
    assert read_trajectory([small], image_shape=None).observations.shape == (3, 192)
    mixed = write_bag(
        tmp_path / "c",
        range(1, 4),
        image=lambda k: m.image_msg(k * S, image_for(k, 8 if k < 3 else 16)),
    )
    with pytest.raises(MessageError, match="16x16, expected 8x8"):
        read_trajectory([mixed], image_shape=None)


def test_non_finite_values(tmp_path):
    bag = write_bag(tmp_path / "a", range(1, 4), velocity=lambda k: (float("nan"), 0.0))
    with pytest.raises(MessageError, match="not finite"):
        read_trajectory([bag])
    bag = write_bag(tmp_path / "b", range(1, 4), pose=lambda k: (float("inf"), 0.0))
    with pytest.raises(MessageError, match="not finite"):
        read_trajectory([bag])


def test_velocities_far_from_every_action(tmp_path):
    np.testing.assert_array_equal(
        velocities_to_actions(np.array([[-6.0, 6.0], [2.6, -0.4]])), [4, 17]
    )
    bag = write_bag(tmp_path / "a", range(1, 4), velocity=lambda k: (4.5 if k == 2 else 3, 0.0))
    with pytest.raises(DataError, match="cannot be mapped") as exc:
        read_trajectory([bag])
    assert "topic '/action', the step at stamp 2000000000 ns" in str(exc.value)  # the far one


def test_wrong_topic_type_and_duplicate_stamps(tmp_path):
    path = tmp_path / "a"
    with BagWriter(path) as writer:
        writer.add_topic("/camera/image_raw", m.IMAGE_TYPE)
        writer.add_topic("/action", m.POSE_TYPE)
        writer.write_message("/camera/image_raw", S, m.image_msg(S, image_for(1)))
        writer.write_message("/action", S, m.pose_msg(S, 0, 0))
    with pytest.raises(BagError, match="has type geometry_msgs/msg/PoseStamped"):
        read_trajectory([path])
    dup = tmp_path / "dup"
    with BagWriter(dup) as writer:
        writer.add_topic("/camera/image_raw", m.IMAGE_TYPE)
        writer.add_topic("/action", m.ACTION_TYPE)
        for log in (S, S + 1):
            writer.write_message("/camera/image_raw", log, m.image_msg(S, image_for(1)))
        writer.write_message("/action", S, m.twist_stamped_msg(S, 0, 0))
    with pytest.raises(BagError, match="'/camera/image_raw', message 1: a second message with"):
        read_trajectory([dup])


def test_no_bag_or_not_a_bag(tmp_path):
    with pytest.raises(Exception, match="no bag"):
        read_trajectory([])
    with pytest.raises(BagError):
        read_trajectory([tmp_path / "missing"])
