"""Recorder, player, bag_info and bag_recover: real processes over DDS (and rclpy if present).

Each test gets its own ROS_DOMAIN_ID (derived from the pid) and restricts Cyclone DDS to
the loopback interface with CYCLONEDDS_URI, so parallel runs and other machines never
cross-talk. Processes are started with the launcher (tpsr_ros.runtime.launcher); waiting
is on conditions (subscriptions matched in the graph, messages received, process exits,
file contents), never on log lines, except the 5 s recording window the acceptance test
asks for.
"""

import contextlib
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from graph_support import BACKENDS, LOOPBACK, fresh_domain

from sim_node.topics import SimTopics
from tpsr_ros.core.errors import BagError
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader, BagWriter
from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions
from tpsr_ros.runtime.backend import open_transport
from tpsr_ros.runtime.launcher import Launch, NodeProcess

S = 10**9
STEP_TOPICS = ("/camera/image_raw", "/action", "/ground_truth/pose", "/reward")






@pytest.fixture
def graph_env():
    pytest.importorskip("cyclonedds")
    domain = fresh_domain(11)
    return {
        **os.environ,
        "ROS_DOMAIN_ID": str(domain),
        "CYCLONEDDS_URI": LOOPBACK,
        "TPSR_TRANSPORT": "dds",
        "PYTHONUNBUFFERED": "1",
    }


def start_recorder(tmp: Path, env: dict[str, str], bag: Path, *topics: str, name="rec"):
    """The recorder; the nodes it records wait for its subscriptions (wait_for_subscribers)."""
    args = ["-o", str(bag), *topics, "--ros-args", "--log-level", "debug"]
    return NodeProcess(name, "tpsr_ros.record", args, log_path=tmp / f"{name}.log", env=env)


def start_sim(tmp: Path, env: dict[str, str], *params: str, name="sim"):
    args = ["--ros-args", "--log-level", "debug"]
    for p in params:
        args += ["-p", p]
    return NodeProcess(name, "sim_node", args, log_path=tmp / f"{name}.log", env=env)


@contextlib.contextmanager
def probe_node(env: dict[str, str]):
    """A node in this process on the test's domain and backend, to watch the graph."""
    keys = ("ROS_DOMAIN_ID", "CYCLONEDDS_URI")
    saved = {key: os.environ.get(key) for key in keys}
    os.environ.update({key: env[key] for key in keys if key in env})
    node = None
    try:
        transport = open_transport(env["TPSR_TRANSPORT"], "probe", "/")
        node = Node(NodeOptions(name="probe"), transport=transport)
        yield node
    finally:
        if node is not None:
            node.close()
        for key, value in saved.items():
            if value is None:
                os.environ.pop(key, None)
            else:
                os.environ[key] = value


def published_steps(log: str) -> int:
    line = next(x for x in log.splitlines() if "published" in x and "steps and" in x)
    return int(line.split("published ")[1].split(" steps")[0])


def decoded(bag: Path, topic: str) -> list:
    with BagReader(bag) as reader:
        return [msg.decode() for msg in reader.messages([topic])]


def payloads(bag: Path) -> dict[str, list[bytes]]:
    with BagReader(bag) as reader:
        out: dict[str, list[bytes]] = {t: [] for t in reader.topics}
        for msg in reader.messages():
            out[msg.topic].append(msg.data)
    return out


@pytest.mark.slow
@pytest.mark.parametrize("backend", BACKENDS)
def test_sim_recorded_for_5_s_then_replayed_into_a_second_recording(
    tmp_path, graph_env, backend
):
    env = {**graph_env, "TPSR_TRANSPORT": backend}
    bag1, bag2 = tmp_path / "run", tmp_path / "replay"
    with probe_node(env) as probe:
        # the probe subscribes every topic of the sim too, so wait_for_subscribers:=2 (the
        # probe and the recorder) holds the start-up reset until the recorder has them all
        starts: list = []
        probe.create_subscription("/sim/episode_start", m.POSE_TYPE, starts.append, LATCHED_QOS)
        for topic, msgtype in SimTopics().types().items():
            probe.create_subscription(topic, msgtype, lambda data: None, raw=True)
        launch = Launch(tmp_path, env=env, spin=probe.spin_once, timeout_s=30)
        with launch:
            recorder = launch.start(
                "rec", "tpsr_ros.record", ["-o", str(bag1), "--ros-args", "--log-level", "debug"]
            )
            sim = launch.start("sim", "sim_node", [
                "--ros-args", "--log-level", "debug",
                "-p", "rate:=50", "-p", "mode:=explore", "-p", "wait_for_subscribers:=2",
            ])
            launch.wait("the simulator's start-up reset", lambda: len(starts) >= 1)
            time.sleep(5.0)  # the acceptance test: record the running sim for 5 s
            assert sim.stop() == 0
            steps = published_steps(sim.text())
            assert recorder.stop() == 0
    assert steps >= 100, sim.text()

    with BagReader(bag1) as reader:
        counts = reader.message_counts
    assert {t: counts[t] for t in STEP_TOPICS} == dict.fromkeys(STEP_TOPICS, steps)
    assert counts["/clock"] == steps + 1  # the reset at t_0 has a clock tick too
    assert counts["/sim/episode_start"] == 1
    images = {m.stamp_of(x): x for x in decoded(bag1, "/camera/image_raw")}
    actions = {m.stamp_of(x): x for x in decoded(bag1, "/action")}
    assert sorted(images) == [k * S for k in range(1, steps + 1)]  # consecutive stamps
    assert images.keys() == actions.keys()  # images and actions paired by stamp
    assert all(len(x.data) == 768 and x.encoding == "rgb8" for x in images.values())

    # play it back (5x faster) while a second recorder runs: identical payloads
    recorder2 = start_recorder(tmp_path, env, bag2, name="rec2")
    player = NodeProcess(
        "play", "tpsr_ros.play", [str(bag1), "--rate", "5", "--wait-for-subscribers", "1"],
        log_path=tmp_path / "play.log", env=env,
    )
    try:
        assert player.popen.wait(60) == 0, player.text()
        assert f"played {sum(counts.values())} messages" in player.text()
        assert recorder2.stop() == 0
    finally:
        player.kill()
        recorder2.kill()
    original, replayed = payloads(bag1), payloads(bag2)
    assert replayed.keys() == original.keys()
    for topic in original:
        assert replayed[topic] == original[topic], topic


@pytest.mark.slow
def test_a_plain_cyclone_reader_receives_the_images(tmp_path, graph_env, monkeypatch):
    """An independent check: IdlStructs written by hand here, none of our code.

    (This module does not use ``from __future__ import annotations`` so that Cyclone can
    resolve the annotations of these function-local classes.)
    """
    from dataclasses import dataclass as idl_dataclass

    from cyclonedds.core import Policy, Qos
    from cyclonedds.domain import DomainParticipant
    from cyclonedds.idl import IdlStruct
    from cyclonedds.idl.annotations import final
    from cyclonedds.idl.types import int32, sequence, uint8, uint32
    from cyclonedds.sub import DataReader
    from cyclonedds.topic import Topic
    from cyclonedds.util import duration

    @final
    @idl_dataclass
    class Time_(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
        sec: int32
        nanosec: uint32

    @final
    @idl_dataclass
    class Header_(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
        stamp: Time_
        frame_id: str

    @final
    @idl_dataclass
    class Image_(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
        header: Header_
        height: uint32
        width: uint32
        encoding: str
        is_bigendian: uint8
        step: uint32
        data: sequence[uint8]

    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    participant = DomainParticipant(int(graph_env["ROS_DOMAIN_ID"]))
    topic = Topic(participant, "rt/camera/image_raw", Image_)
    reader = DataReader(participant, topic, Qos(
        Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(100)
    ))
    sim = start_sim(tmp_path, graph_env, "rate:=50", "wait_for_subscribers:=0")
    images = []
    try:
        deadline = time.monotonic() + 30
        while len(images) < 10 and time.monotonic() < deadline:
            images.extend(reader.take(N=100))
            time.sleep(0.02)
        assert sim.stop() == 0
    finally:
        sim.kill()
    assert len(images) >= 10, sim.text()
    stamps = [i.header.stamp.sec * S + i.header.stamp.nanosec for i in images]
    assert stamps == list(range(stamps[0], stamps[0] + S * len(stamps), S))
    first = images[0]
    assert (first.height, first.width, first.encoding, first.step) == (16, 16, "rgb8", 48)
    assert first.header.frame_id == "camera" and len(first.data) == 768


def _messages_in(mcap: Path, topic: str) -> int:
    """Complete messages on ``topic`` in a possibly still growing MCAP file."""
    from mcap.records import Channel, Message
    from mcap.stream_reader import StreamReader

    count, channel_ids = 0, set()
    try:
        with mcap.open("rb") as stream:
            for record in StreamReader(stream).records:
                if isinstance(record, Channel) and record.topic == topic:
                    channel_ids.add(record.id)
                elif isinstance(record, Message) and record.channel_id in channel_ids:
                    count += 1
    except Exception:
        pass
    return count


@pytest.mark.slow
def test_sigkill_leaves_a_bag_that_bag_recover_makes_readable(tmp_path, graph_env):
    bag = tmp_path / "killed"
    recorder = start_recorder(tmp_path, graph_env, bag)
    sim = start_sim(tmp_path, graph_env, "rate:=50", "wait_for_subscribers:=1")
    mcap = bag / "killed.mcap"
    try:
        deadline = time.monotonic() + 30
        while _messages_in(mcap, "/camera/image_raw") < 60 and time.monotonic() < deadline:
            time.sleep(0.1)
        flushed = _messages_in(mcap, "/camera/image_raw")
        recorder.popen.kill()  # SIGKILL: no chance to close the bag
        recorder.popen.wait(10)
        assert sim.stop() == 0
    finally:
        sim.kill()
        recorder.kill()
    assert flushed >= 60
    assert not (bag / "metadata.yaml").exists()
    with pytest.raises(BagError, match="bag_recover"):
        BagReader(bag)
    result = subprocess.run(
        [sys.executable, "-m", "tpsr_ros.bag_recover", str(bag)],
        capture_output=True, text=True, timeout=60,
    )
    assert result.returncode == 0, result.stderr
    assert "recovered" in result.stdout
    images = [m.stamp_of(x) for x in decoded(bag, "/camera/image_raw")]
    actions = [m.stamp_of(x) for x in decoded(bag, "/action")]
    assert len(images) >= flushed
    assert images == [k * S for k in range(1, len(images) + 1)]
    # a flush may split the last step: images and actions agree except at the very end
    common = min(len(images), len(actions))
    assert images[:common] == actions[:common] and abs(len(images) - len(actions)) <= 1
    info = subprocess.run(
        [sys.executable, "-m", "tpsr_ros.bag_info", str(bag)],
        capture_output=True, text=True, timeout=60,
    )
    assert info.returncode == 0 and "/camera/image_raw" in info.stdout


# -- bad input and exit paths (in process, fast) ---------------------------------------


def _run(main, argv, capsys) -> tuple[int, str]:
    with pytest.raises(SystemExit) as info:
        main(argv)
    return int(info.value.code or 0), capsys.readouterr().err


def test_recorder_refuses_existing_or_unwritable_paths(tmp_path, capsys, monkeypatch):
    from tpsr_ros import record

    monkeypatch.setenv("TPSR_TRANSPORT", "inproc")
    existing = tmp_path / "exists"
    existing.mkdir()
    handler = signal.getsignal(signal.SIGINT)
    code, err = _run(record.main, ["-o", str(existing)], capsys)
    assert code == 1 and "already exists" in err and err.count("\n") == 1
    # a refused start leaves the caller's SIGINT handler (and its later children's) alone
    assert signal.getsignal(signal.SIGINT) is handler
    code, err = _run(record.main, ["-o", str(tmp_path / "no" / "such" / "bag")], capsys)
    assert code == 1 and "does not exist" in err
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    try:
        if not os.access(locked, os.W_OK):  # root can write anywhere
            code, err = _run(record.main, ["-o", str(locked / "bag")], capsys)
            assert code == 1 and "not writable" in err
    finally:
        locked.chmod(0o700)
    code, err = _run(record.main, [], capsys)
    assert code == 2 and "-o/--output" in err


def test_player_and_info_refuse_what_is_not_a_rosbag2_mcap_bag(tmp_path, capsys):
    from tpsr_ros import bag_info, play

    plain = tmp_path / "file.txt"
    plain.write_text("hello")
    sqlite = tmp_path / "sqlite_bag"
    sqlite.mkdir()
    (sqlite / "metadata.yaml").write_text(
        "rosbag2_bagfile_information:\n  version: 5\n  storage_identifier: sqlite3\n"
    )
    for path, fragment in [
        (tmp_path / "missing", "not a rosbag2 directory"),
        (plain, "not a rosbag2 directory"),
        (sqlite, "not mcap"),
    ]:
        code, err = _run(play.main, [str(path)], capsys)
        assert code == 1 and fragment in err and err.count("\n") == 1
        with pytest.raises(SystemExit) as info:
            from tpsr_ros.cli import run_cli

            run_cli("python -m tpsr_ros.bag_info", lambda p=path: bag_info.main([str(p)]))
        assert info.value.code == 1
        err = capsys.readouterr().err
        assert fragment in err and err.count("\n") == 1
    code, err = _run(play.main, [str(tmp_path), "--rate", "0"], capsys)
    assert code == 2 and "not positive" in err


def _recorder(bus, bag: Path, *topics: str):
    from tpsr_ros.record import RecorderNode
    from tpsr_ros.runtime import NodeOptions
    from tpsr_ros.runtime.inproc import InprocTransport

    args = RecorderNode.argument_parser("record").parse_args(["-o", str(bag), *topics])
    options = NodeOptions.for_node(RecorderNode, args=args)
    return RecorderNode(options, transport=InprocTransport("/rec", bus))


def _talker(bus, name="talker"):
    from tpsr_ros.runtime import Node, NodeOptions
    from tpsr_ros.runtime.inproc import InprocTransport

    return Node(NodeOptions(name=name), transport=InprocTransport("/" + name, bus))


def test_topic_type_clash_stops_the_recorder_and_the_bag_stays_readable(tmp_path):
    from tpsr_ros.runtime.inproc import InprocBus

    bus = InprocBus()
    talker = _talker(bus)
    clock = talker.create_publisher("/x", m.CLOCK_TYPE)
    rec = _recorder(bus, tmp_path / "bag")
    assert rec.wait_for(lambda: "/x" in rec.subscribed, 5)
    clock.publish(m.clock_msg(5))
    rec.spin(timeout_s=0.05)
    _talker(bus, "other").create_publisher("/x", m.TWIST_TYPE)
    with pytest.raises(BagError, match="topic type clash: /x"):
        rec.spin(timeout_s=5)
    rec.close()
    with BagReader(tmp_path / "bag") as reader:
        assert reader.topics == {"/x": m.CLOCK_TYPE}
        assert reader.message_counts == {"/x": 1}


def test_recorder_selects_topics_adapts_qos_and_records_late_publishers(tmp_path):
    from tpsr_ros.runtime import SENSOR_DATA_QOS
    from tpsr_ros.runtime.inproc import InprocBus

    bus = InprocBus()
    talker = _talker(bus)
    scan = talker.create_publisher("/scan", m.CLOCK_TYPE, SENSOR_DATA_QOS)
    ignored = talker.create_publisher("/ignored", m.CLOCK_TYPE)
    rec = _recorder(bus, tmp_path / "bag", "/scan", "/late")
    assert rec.wait_for(lambda: "/scan" in rec.subscribed, 5)
    assert rec.planner.qos["/scan"].reliability.value == "best_effort"
    late = _talker(bus, "late").create_publisher("/late", m.POSE_TYPE)
    assert rec.wait_for(lambda: "/late" in rec.subscribed, 5)
    scan.publish(m.clock_msg(1))
    ignored.publish(m.clock_msg(2))
    late.publish(m.pose_msg(3, 1.0, 2.0))
    rec.spin(timeout_s=0.05)
    rec.close()
    with BagReader(tmp_path / "bag") as reader:
        assert reader.message_counts == {"/scan": 1, "/late": 1}
        offered = reader.qos_profiles["/scan"]
        assert offered[0].reliability.name == "BEST_EFFORT" and offered[0].depth == 5


def test_player_publishes_clock_from_header_stamps_when_the_bag_has_none(tmp_path):
    from tpsr_ros.play import PlayerNode
    from tpsr_ros.runtime import NodeOptions
    from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

    bag = tmp_path / "bag"
    with BagWriter(bag) as writer:
        writer.add_topic("/action", m.ACTION_TYPE)
        for k in range(1, 4):
            writer.write_message("/action", 100 * S + k, m.twist_stamped_msg(k * S, 3.0, 0.0))
    bus = InprocBus()
    listener = _talker(bus, "listener")
    clocks, actions = [], []
    listener.create_subscription("/clock", m.CLOCK_TYPE, clocks.append)
    listener.create_subscription("/action", m.ACTION_TYPE, actions.append)
    args = PlayerNode.argument_parser("play").parse_args([str(bag), "--rate", "100"])
    player = PlayerNode(NodeOptions.for_node(PlayerNode, args=args),
                        transport=InprocTransport("/player", bus))
    assert {(e.topic, e.msgtype) for e in player.endpoints()} == {
        ("/action", m.ACTION_TYPE), ("/clock", m.CLOCK_TYPE)
    }
    player.spin()
    player.close()
    listener.spin_once(0.0)
    assert [m.stamp_of(c) for c in clocks] == [S, 2 * S, 3 * S]
    assert [m.stamp_of(a) for a in actions] == [S, 2 * S, 3 * S]


def test_player_reports_its_lateness_when_publishing_cannot_keep_up(tmp_path, capfd):
    from tpsr_ros.play import PlayerNode
    from tpsr_ros.runtime import NodeOptions
    from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

    bag = tmp_path / "bag"
    with BagWriter(bag) as writer:  # 6 messages 10 ms apart
        writer.add_topic("/action", m.ACTION_TYPE)
        for k in range(6):
            writer.write_message("/action", S + k * 10**7, m.twist_stamped_msg(k, 1.0, 0.0))
    args = PlayerNode.argument_parser("play").parse_args([str(bag), "--no-clock"])
    player = PlayerNode(NodeOptions.for_node(PlayerNode, args=args),
                        transport=InprocTransport("/player", InprocBus()))
    handle = player.publishers["/action"]._handle
    write = handle.write

    def slow_write(data: bytes) -> None:  # a middleware that takes 30 ms per message
        time.sleep(0.03)
        write(data)

    handle.write = slow_write
    player.spin()
    player.close()
    assert len(player.lateness_ms) == 6
    p50, worst = player.lateness_ms.percentiles(50, 100)
    assert worst >= 5 * 20 - 1  # message k starts at least k x (30 - 10) ms late
    assert p50 >= 2 * 20 - 1
    line = next(x for x in capfd.readouterr().err.splitlines() if "played 6 messages" in x)
    assert f"max {worst:.1f} ms" in line and "lateness p50" in line and "p99" in line


def test_the_first_message_on_each_topic_waits_for_acknowledgement_and_the_schedule_moves_on(
    tmp_path, capfd
):
    from tpsr_ros import play
    from tpsr_ros.runtime import NodeOptions
    from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

    bag = tmp_path / "bag"
    with BagWriter(bag) as writer:  # two topics, a message every 10 ms on each
        writer.add_topic("/a", m.ACTION_TYPE)
        writer.add_topic("/b", m.ACTION_TYPE)
        for k in range(8):
            for i, topic in enumerate(("/a", "/b")):
                stamp = S + k * 10**7 + i * 5 * 10**6
                writer.write_message(topic, stamp, m.twist_stamped_msg(stamp, 1.0, 0.0))
    bus = InprocBus()
    listener = _talker(bus, "listener")
    for topic in ("/a", "/b"):
        listener.create_subscription(topic, m.ACTION_TYPE, lambda _: None)
    argv = [str(bag), "--no-clock", "--wait-for-subscribers", "1"]
    args = play.PlayerNode.argument_parser("play").parse_args(argv)
    player = play.PlayerNode(NodeOptions.for_node(play.PlayerNode, args=args),
                             transport=InprocTransport("/player", bus))  # fmt: skip
    written: dict[str, int] = {"/a": 0, "/b": 0}
    waits: list[tuple[str, int]] = []  # (topic, messages written on it when it waited)
    budgets: list[float] = []  # the timeout of each wait
    for topic, publisher in player.publishers.items():
        handle = publisher._handle
        write = handle.write

        def counted(data: bytes, topic: str = topic, write=write) -> None:
            written[topic] += 1
            write(data)

        def slow_ack(timeout_s: float, topic: str = topic) -> bool:
            waits.append((topic, written[topic]))
            budgets.append(timeout_s)
            time.sleep(0.1)  # a subscriber whose side of the match completes late
            return topic == "/a"  # /b is never acknowledged in time

        handle.write, handle.wait_for_acks = counted, slow_ack
    player.spin()
    player.close()
    assert waits == [("/a", 1), ("/b", 1)]  # once per topic, right after its first message
    # the topics share one budget: a subscriber that never answers delays the start once
    assert budgets[0] == play.FIRST_ACK_TIMEOUT_S and 4.0 < budgets[1] <= 4.9
    assert written == {"/a": 8, "/b": 8}
    # the schedule resumes after each wait: no message is due 100 ms before it is sent
    assert player.lateness_ms.percentiles(100)[0] < 60
    err = capfd.readouterr().err
    assert "/b: the first message was not acknowledged within 5 s of the start; playing on" in err
    assert "/a: the first message" not in err


def test_read_ahead_yields_in_order_raises_the_readers_error_and_stops_early():
    from tpsr_ros.play import ReadAhead

    assert list(ReadAhead(iter(range(50)), depth=4)) == list(range(50))

    def damaged():
        yield 1
        raise BagError("bag 'x': chunk 2 is damaged")

    with pytest.raises(BagError, match="chunk 2 is damaged"):
        list(ReadAhead(damaged()))
    produced = []

    def endless():
        for k in range(10**9):
            produced.append(k)
            yield k

    ahead = ReadAhead(endless(), depth=2)
    assert next(iter(ahead)) == 0
    ahead.close()
    assert not ahead._thread.is_alive() and len(produced) < 10
