"""sim_node as a node (in-process bus): explore, command lockstep, the reset protocol, CLI."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
from graph_support import LOOPBACK, fresh_domain

from sim_node.node import SimNode
from tpsr_ros.core.actions import ACTIONS
from tpsr_ros.io import messages as m
from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions, parse_ros_args
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

STEP_TOPICS = ("/camera/image_raw", "/action", "/ground_truth/pose", "/reward", "/clock")
S = 10**9


class Probe:
    """A second node that records everything the simulator publishes."""

    def __init__(self, bus: InprocBus) -> None:
        self.node = Node(NodeOptions(name="probe"), transport=InprocTransport("/probe", bus))
        self.got: dict[str, list] = {t: [] for t in (*STEP_TOPICS, "/sim/episode_start")}
        for topic, msgtype in [
            ("/camera/image_raw", m.IMAGE_TYPE), ("/action", m.ACTION_TYPE),
            ("/ground_truth/pose", m.POSE_TYPE), ("/reward", m.REWARD_TYPE),
            ("/clock", m.CLOCK_TYPE),
        ]:
            self.node.create_subscription(topic, msgtype, self.got[topic].append)
        self.node.create_subscription(
            "/sim/episode_start", m.POSE_TYPE, self.got["/sim/episode_start"].append, LATCHED_QOS
        )
        self.cmd = self.node.create_publisher("/cmd_vel", m.TWIST_TYPE)
        self.reset = self.node.create_publisher("/sim/reset", m.POSE_TYPE)

    def stamps(self, topic: str) -> list[int]:
        return [m.stamp_of(x) for x in self.got[topic]]


def start_sim(bus: InprocBus, *ros_args: str) -> SimNode:
    options = NodeOptions.for_node(SimNode, parse_ros_args(list(ros_args)))
    return SimNode(options, transport=InprocTransport("/sim_node", bus))


def spin_both(sim, probe, until, timeout=10.0):
    import time

    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        sim.spin_once(0.005)
        probe.node.spin_once(0.0)
        if until():
            return True
    return until()


def test_explore_publishes_paired_steps_with_consecutive_stamps():
    bus = InprocBus()
    probe = Probe(bus)
    sim = start_sim(bus, "-p", "rate:=200", "-p", "steps:=20", "-p", "seed:=3")
    assert spin_both(sim, probe, lambda: len(probe.got["/reward"]) == 20)
    sim.spin(timeout_s=0.05)  # no step after `steps`
    probe.node.spin_once(0.0)
    assert sim.steps_published == 20 and len(probe.got["/camera/image_raw"]) == 20
    # reset at t_0, steps at t_1..t_20; images, actions, poses, rewards share the stamps
    assert probe.stamps("/sim/episode_start") == [0]
    for topic in ("/camera/image_raw", "/action", "/ground_truth/pose", "/reward"):
        assert probe.stamps(topic) == [k * S for k in range(1, 21)]
    assert probe.stamps("/clock") == [k * S for k in range(0, 21)]
    for action in probe.got["/action"]:
        assert tuple(m.twist_to_xy(action)) in {tuple(a) for a in ACTIONS}
    image = m.image_to_array(probe.got["/camera/image_raw"][0], frame_id="camera")
    assert image.shape == (16, 16, 3)
    sim.close()


def test_explore_matches_the_environment_rollout_for_the_same_seed():
    from sim_node import RobotEnv, SimConfig

    bus = InprocBus()
    probe = Probe(bus)
    sim = start_sim(bus, "-p", "rate:=500", "-p", "steps:=5", "-p", "seed:=11",
                    "-p", "environment:=partial")
    assert spin_both(sim, probe, lambda: len(probe.got["/reward"]) == 5)
    env = RobotEnv(SimConfig(environment="partial"), seed=11)
    env.reset()
    for k in range(5):
        image, reward, _, _, info = env.step(env.sample_action())
        assert np.array_equal(m.image_to_array(probe.got["/camera/image_raw"][k]), image)
        assert m.reward_to_sample(probe.got["/reward"][k]).reward == reward
        assert m.pose_to_xy(probe.got["/ground_truth/pose"][k]) == pytest.approx(
            tuple(info["position"]))
    sim.close()


def test_command_mode_is_lockstep_and_snaps_to_the_25_actions(capsys):
    bus = InprocBus()
    probe = Probe(bus)
    sim = start_sim(bus, "-p", "mode:=command")
    assert spin_both(sim, probe, lambda: probe.got["/sim/episode_start"])
    for vx, vy in [(2.6, -5.1), (0.4, 0.0), (float("nan"), 0.0), (40.0, 0.0), (6.0, 6.0)]:
        probe.cmd.publish(m.twist_msg(vx, vy))
    assert spin_both(sim, probe, lambda: len(probe.got["/action"]) == 3)
    sim.spin(timeout_s=0.05)
    probe.node.spin_once(0.0)
    actions = [m.twist_to_xy(a) for a in probe.got["/action"]]
    assert actions == [(3.0, -6.0), (0.0, 0.0), (6.0, 6.0)]  # nan and 40 m/s rejected
    assert probe.stamps("/action") == [1 * S, 2 * S, 3 * S]
    err = capsys.readouterr().err
    assert err.count("/cmd_vel rejected") == 2
    sim.close()


def test_reset_protocol_time_never_goes_back_and_images_stay_paired(capsys):
    bus = InprocBus()
    probe = Probe(bus)
    sim = start_sim(bus, "-p", "mode:=command")
    assert spin_both(sim, probe, lambda: probe.got["/sim/episode_start"])
    probe.cmd.publish(m.twist_msg(3.0, 0.0))  # step at t_1
    assert spin_both(sim, probe, lambda: len(probe.got["/action"]) == 1)
    probe.reset.publish(m.pose_msg(0, 10.0, 12.0))  # reset at t_2
    assert spin_both(sim, probe, lambda: len(probe.got["/sim/episode_start"]) == 2)
    probe.cmd.publish(m.twist_msg(0.0, 0.0))  # next step at t_3
    assert spin_both(sim, probe, lambda: len(probe.got["/action"]) == 2)
    starts = probe.got["/sim/episode_start"]
    assert [m.stamp_of(s) for s in starts] == [0, 2 * S]
    assert m.pose_to_xy(starts[1]) == (10.0, 12.0)
    assert starts[1].header.frame_id == "map"
    assert probe.stamps("/action") == probe.stamps("/camera/image_raw") == [1 * S, 3 * S]
    assert probe.stamps("/clock") == [0, 1 * S, 2 * S, 3 * S]
    # a standing-still step right after the reset starts where the reset put the robot
    assert m.pose_to_xy(probe.got["/ground_truth/pose"][1]) == pytest.approx((10.0, 12.0))
    # bad resets are rejected with a warning and take no time
    probe.reset.publish(m.pose_msg(0, 100.0, 5.0))
    bad_frame = m.pose_msg(0, 5.0, 5.0, frame_id="odom")
    probe.reset.publish(bad_frame)
    sim.spin(timeout_s=0.05)
    assert sim.resets == 2 and sim.last_stamp_ns == 3 * S
    err = capsys.readouterr().err
    assert "outside the room" in err and "is not 'map'" in err
    # a late joiner still gets the latest episode start (transient local, depth 1)
    late = Node(NodeOptions(name="late"), transport=InprocTransport("/late", bus))
    latched = []
    late.create_subscription("/sim/episode_start", m.POSE_TYPE, latched.append, LATCHED_QOS)
    late.spin_once(0.0)
    assert [m.stamp_of(x) for x in latched] == [2 * S]
    sim.close()
    assert "published 2 steps and 2 resets" in capsys.readouterr().err


def test_wait_for_subscribers_holds_the_first_reset():
    bus = InprocBus()
    sim = start_sim(bus, "-p", "wait_for_subscribers:=1", "-p", "rate:=100")
    sim.spin(timeout_s=0.1)
    assert not sim.started and sim.steps_published == 0
    probe = Probe(bus)
    assert spin_both(sim, probe, lambda: len(probe.got["/action"]) >= 3)
    assert probe.stamps("/clock")[0] == 0 and probe.stamps("/action")[0] == S
    sim.close()


def test_node_declares_documented_endpoints():
    sim = start_sim(InprocBus(), "-p", "mode:=command")
    kinds = {(e.kind, e.topic, e.msgtype) for e in sim.endpoints()}
    assert ("subscription", "/cmd_vel", m.TWIST_TYPE) in kinds
    assert ("publisher", "/sim/episode_start", m.POSE_TYPE) in kinds
    sim.close()


def _cli(*args: str, **env: str) -> subprocess.CompletedProcess[str]:
    import os

    return subprocess.run(
        [sys.executable, "-m", "sim_node", *args],
        capture_output=True, text=True, timeout=60,
        env={**os.environ, "TPSR_TRANSPORT": "inproc", **env},
    )


def test_help_lists_parameters():
    result = _cli("--help")
    assert result.returncode == 0
    for needle in ("environment", "seed", "mode", "rate", "steps", "double", "integer",
                   "--ros-args", "-r FROM:=TO"):
        assert needle in result.stdout


@pytest.mark.parametrize(
    "args, fragment",
    [
        (["--ros-args", "-p", "bogus:=1"], "unknown parameter 'bogus'"),
        (["--ros-args", "-p", "seed:=abc"], "expects an integer"),
        (["--ros-args", "-p", "rate:=0"], "parameter 'rate' (-p): 0.0 must be > 0"),
        (["--ros-args", "-p", "environment:=moon"], "moon is not one of full"),
        (["--ros-args", "--frobnicate"], "unknown ROS argument"),
        (["--ros-args", "-p", "seed"], "not of the form name:=value"),
        (["extra"], "unrecognized arguments"),
    ],
)
def test_bad_command_lines_exit_2_with_one_line(args, fragment, capsys):
    from tpsr_ros.runtime import run_node

    with pytest.raises(SystemExit) as info:
        run_node(SimNode, prog="python -m sim_node", argv=args)
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert fragment in err
    assert err.strip().count("\n") == 0


def test_bad_parameter_message_is_one_line_on_stderr():
    result = _cli("--ros-args", "-p", "mode:=fly")
    assert result.returncode == 2
    assert result.stderr.strip().count("\n") == 0
    assert result.stderr.startswith("python -m sim_node: error: parameter 'mode'")


def test_ignored_commands_are_announced_on_the_graph():
    bus = InprocBus()
    probe = Probe(bus)
    ignored: list = []
    probe.node.create_subscription("/sim/cmd_ignored", m.HEADER_TYPE, ignored.append)
    sim = start_sim(bus, "-p", "mode:=command", "-p", "episode_steps:=2")
    assert spin_both(sim, probe, lambda: len(probe.got["/sim/episode_start"]) == 1)
    for _ in range(3):  # two steps, then the third command is past the episode's end
        probe.cmd.publish(m.twist_msg(3.0, 0.0))
        spin_both(sim, probe, lambda: False, timeout=0.05)
    assert spin_both(sim, probe, lambda: len(ignored) == 1)
    assert len(probe.got["/reward"]) == 2 and sim.ignored_commands == 1
    sim.close()
    assert ignored[0].frame_id == "episode_steps" and ignored[0].stamp.sec == 2  # t_2


@pytest.mark.slow
def test_sigterm_stops_the_node_gracefully_and_logs_the_count(tmp_path, monkeypatch):
    """SIGTERM once the node is spinning: a /clock message seen in the graph, not a log line."""
    import os
    import signal

    pytest.importorskip("cyclonedds")
    from tpsr_ros.runtime.dds import DdsTransport
    from tpsr_ros.runtime.launcher import Launch

    domain = fresh_domain(37)  # one this process has not configured (one config per domain)
    monkeypatch.setenv("ROS_DOMAIN_ID", str(domain))
    monkeypatch.setenv("CYCLONEDDS_URI", LOOPBACK)
    probe = Node(NodeOptions(name="probe"), transport=DdsTransport("probe"))
    clocks: list = []
    probe.create_subscription("/clock", m.CLOCK_TYPE, clocks.append)
    env = {**os.environ, "TPSR_TRANSPORT": "dds"}
    try:
        with Launch(tmp_path, env=env, spin=probe.spin_once, timeout_s=30) as launch:
            sim = launch.start(
                "sim", "sim_node", ["--ros-args", "-p", "rate:=100", "--log-level", "debug"]
            )
            launch.wait("the running node's /clock", lambda: len(clocks) >= 2)
            assert sim.stop(sig=signal.SIGTERM) == 0
    finally:
        probe.close()
    err = sim.text()
    assert "published" in err and "steps and 1 resets" in err
