"""Bag generation: contents read back with rosbags and mcap, and bad input refused."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

import sim_node.generate as generate
from sim_node import SimConfig
from sim_node.config import Environment
from sim_node.generate import generate_bag
from tpsr_ros.core.errors import BagError


@pytest.mark.slow
@pytest.mark.parametrize(
    ("environment", "steps"),
    # the guide's size once; the rooms differ in pixels only, not in what is written
    [("full", 24000), ("partial", 3000), ("distractors", 3000)],
)
def test_a_generated_bag_reads_back_with_rosbags(tmp_path, environment, steps):
    bag = tmp_path / environment
    generate_bag(bag, SimConfig(environment=environment), steps, seed=1)
    images, actions = {}, {}
    with AnyReader([bag], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        counts = {c.topic: c.msgcount for c in reader.connections}
        assert counts == {
            "/camera/image_raw": steps, "/action": steps, "/ground_truth/pose": steps,
            "/reward": steps, "/clock": steps,
        }
        wanted = [c for c in reader.connections if c.topic in ("/camera/image_raw", "/action")]
        for connection, log_time, raw in reader.messages(connections=wanted):
            msg = reader.deserialize(raw, connection.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert stamp == log_time
            if connection.topic == "/camera/image_raw":
                assert (msg.height, msg.width, msg.encoding, msg.step) == (16, 16, "rgb8", 48)
                assert msg.header.frame_id == "camera" and len(msg.data) == 768
                images[stamp] = msg.data
            else:
                assert msg.twist.linear.x in (-6, -3, 0, 3, 6)
                assert msg.twist.linear.y in (-6, -3, 0, 3, 6)
                actions[stamp] = (msg.twist.linear.x, msg.twist.linear.y)
    assert images.keys() == actions.keys()  # paired by identical stamps
    stamps = np.array(sorted(images))
    assert len(stamps) == steps
    assert np.all(np.diff(stamps) == 10**9)  # 1 s apart
    # the MCAP file itself is valid for the independent mcap reader, with a summary
    with (bag / f"{environment}.mcap").open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None and summary.statistics.message_count == 5 * steps


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sim_node.generate", *args],
        capture_output=True, text=True, timeout=60,
    )


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--environment", "moon", "--steps", "5"], "invalid choice: 'moon'"),
        (["--environment", "full", "--steps", "0"], "0 is not positive"),
        (["--environment", "full", "--steps", "-3"], "-3 is not positive"),
        (["--environment", "full", "--steps", "x"], "'x' is not an integer"),
        (["--environment", "full", "--steps", "5", "--seed", "-1"], "-1 is negative"),
    ],
)
def test_bad_arguments_give_one_line_errors(tmp_path, args, message):
    out = tmp_path / "bag"
    result = _run(*args, "-o", str(out))
    assert result.returncode != 0
    assert result.stderr.count("\n") == 1 and message in result.stderr
    assert not out.exists()


def test_existing_output_is_never_overwritten(tmp_path):
    out = tmp_path / "bag"
    out.mkdir()
    (out / "precious.txt").write_text("keep me")
    result = _run("--environment", "full", "--steps", "5", "-o", str(out))
    assert result.returncode != 0 and "already exists" in result.stderr
    assert result.stderr.count("\n") == 1
    assert (out / "precious.txt").read_text() == "keep me"


@pytest.mark.parametrize(
    ("output", "message"),
    [("/nonexistent-dir/bag", "does not exist"), ("/proc/tpsr-bag", "cannot create bag")],
)
def test_unwritable_directory_is_named(output, message):
    result = _run("--environment", "full", "--steps", "5", "-o", output)
    assert result.returncode != 0
    assert message in result.stderr and result.stderr.count("\n") == 1
    assert not Path(output).exists()


def test_failure_midway_leaves_nothing_behind(tmp_path, monkeypatch):
    real = generate.iter_random_rollout

    def failing(*args, **kwargs):
        parts = real(*args, **kwargs)
        yield next(parts)
        raise KeyboardInterrupt

    monkeypatch.setattr(generate, "iter_random_rollout", failing)
    out = tmp_path / "bag"
    with pytest.raises(KeyboardInterrupt):
        generate_bag(out, SimConfig(), 3000, seed=0)
    assert not out.exists()


def test_generated_bag_records_its_settings(tmp_path):
    from tpsr_ros.io.bag import BagReader

    out = tmp_path / "bag"
    generate_bag(out, SimConfig(environment="partial"), 10, seed=7)
    with BagReader(out) as reader:
        assert reader.custom_data["tpsr_ros.environment"] == "partial"
        assert '"seed": 7' in reader.custom_data["tpsr_ros.generator"]
    with pytest.raises(BagError, match="already exists"):
        generate_bag(out, SimConfig(), 10, seed=7)


@pytest.mark.parametrize("environment", ["full", "distractors", "drive"])
def test_chunk_payloads_are_exactly_what_rosbags_serialises(environment):
    # the generator writes CDR built per chunk with numpy; it must be rosbags' bytes
    from sim_node.batch_cdr import chunk_payloads
    from sim_node.rollout import random_rollout
    from sim_node.topics import SimTopics, step_messages
    from tpsr_ros.io.messages import RewardSample, serialize

    config = SimConfig(environment=environment, start_time_ns=1_700_000_000_123_456_789)
    part = random_rollout(config, 400, seed=5)
    assert part.wall_contact.any() and part.goal_zone.any()  # every reward value occurs
    topics = SimTopics()
    payloads = chunk_payloads(topics, part, config)
    for i in range(len(part)):
        reward = RewardSample(float(part.rewards[i]), bool(part.wall_contact[i]),
                              bool(part.goal_zone[i]))
        heading = float(part.headings[i]) if config.drives else None
        expected = step_messages(topics, int(part.stamps_ns[i]), part.images[i],
                                 part.commands[i], part.positions[i], reward,
                                 components=config.actions.components, heading=heading)
        for topic, msgtype, msg in expected:
            assert payloads[topic][i] == serialize(msg, msgtype), (topic, i)


@pytest.mark.slow
@pytest.mark.parametrize("environment", [e.value for e in Environment])
def test_the_sample_bags_are_what_the_generator_writes(environment, tmp_path):
    """bags/ holds 3000 steps of each environment (seed 2026): the messages of today's
    simulator, rewards and all."""
    from tpsr_ros.io.bag import BagReader

    sample = Path(__file__).resolve().parents[1] / "bags" / environment
    generate_bag(tmp_path / "bag", SimConfig(environment=environment), 3000, seed=2026)
    with BagReader(sample) as committed, BagReader(tmp_path / "bag") as fresh:
        topics = sorted(fresh.topics_with_messages)
        assert sorted(committed.topics_with_messages) == topics
        assert list(committed.raw_messages(topics)) == list(fresh.raw_messages(topics))
