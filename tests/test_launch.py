"""launch/closed_loop.launch.xml: it names real executables, nodes and parameters (every
node's command line parses as the node itself parses it), the launcher refuses what it
cannot run in one line, and ``python -m tpsr_ros.launch`` runs the closed loop from it.
"""

from __future__ import annotations

import ast
import itertools
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from sim_node.node import SimNode
from tpsr_ros.filter_node import FilterNode
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.launch import EXECUTABLES, LaunchError, parse_launch
from tpsr_ros.play import PlayerNode
from tpsr_ros.record import RecorderNode
from tpsr_ros.runtime import parse_node_args
from tpsr_ros.runtime.params import param_specs

ROOT = Path(__file__).resolve().parent.parent
LAUNCH = ROOT / "launch" / "closed_loop.launch.xml"
NODE_CLASSES = {"sim_node": SimNode, "filter_node": FilterNode, "record": RecorderNode,
                "play": PlayerNode}
LOOPBACK = (
    "<CycloneDDS><Domain id='any'><General><Interfaces>"
    "<NetworkInterface address='127.0.0.1' multicast='true'/>"
    "</Interfaces></General></Domain></CycloneDDS>"
)
_COUNTER = itertools.count()


def test_the_executables_are_the_ones_colcon_installs():
    tree = ast.parse((ROOT / "setup.py").read_text())
    (nodes,) = [
        ast.literal_eval(n.value) for n in tree.body
        if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", None) == "NODES"
    ]
    assert {k: v.split(":")[0].removesuffix(".__main__") for k, v in nodes.items()} == EXECUTABLES
    assert set(NODE_CLASSES) == set(EXECUTABLES)


def test_the_closed_loop_launch_file_names_real_nodes_and_parameters(tmp_path):
    nodes = parse_launch(LAUNCH, {"model": "m.npz", "policy": "p.npz",
                                  "bag": str(tmp_path / "bag")})
    assert [n.executable for n in nodes] == ["record", "sim_node", "filter_node"]
    for node in nodes:
        cls = NODE_CLASSES[node.executable]
        assert node.name == cls.default_name
        known = {s.name for s in param_specs(cls.Params)}
        assert {k for k, _ in node.params} <= known, node.name
        # the node's own parser accepts the whole command line: names, types, choices
        command = node.command()
        assert command[:2] == ["-m", EXECUTABLES[node.executable]]
        options = parse_node_args(cls, command[2:], "prog")
        assert options is not None and options.name == node.name
        for key, value in node.params:
            assert str(getattr(options.params, key)) == value
    sim = parse_node_args(SimNode, nodes[1].command()[2:], "prog").params
    assert (sim.mode, sim.seed, sim.episode_steps, sim.environment) == ("command", 2026, 50, "full")
    recorder = parse_node_args(RecorderNode, nodes[0].command()[2:], "prog")
    assert recorder.args.output == tmp_path / "bag"
    assert "/tpsr/state" in recorder.args.topics and "/camera/image_raw" in recorder.args.topics


@pytest.mark.parametrize(
    "overrides, text, message",
    [
        ({}, None, "argument 'model' is required"),
        ({"model": "m", "policy": "p", "sed": "1"}, None, "has no argument(s) sed"),
        ({}, "<launch><group/></launch>", "<group>: unsupported element"),
        ({}, "<launch><node pkg='turtlesim' exec='turtlesim_node'/></launch>",
         "turtlesim/turtlesim_node is not one of this package's executables"),
        ({}, "<launch><node pkg='tpsr_ros' exec='sim_node' respawn='true'/></launch>",
         "unsupported attribute(s) respawn"),
        ({}, "<launch><node pkg='tpsr_ros' exec='sim_node' name='$(var x)'/></launch>",
         "$(var x) has no value"),
        ({}, "<launch>", "cannot read launch file"),
    ],
)
def test_what_the_launcher_cannot_run_is_refused_in_one_line(tmp_path, overrides, text, message):
    path = LAUNCH
    if text is not None:
        path = tmp_path / "x.launch.xml"
        path.write_text(text)
    with pytest.raises(LaunchError) as info:
        parse_launch(path, overrides)
    assert message in str(info.value) and "\n" not in str(info.value)


@pytest.mark.slow
def test_the_launch_file_runs_the_closed_loop(tmp_path):
    from test_filter_node import fit_small_model, random_policy

    model = fit_small_model(tmp_path)
    policy = random_policy(model, tmp_path / "policy.npz")
    bag = tmp_path / "bag"
    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str((os.getpid() * 19 + 11 * next(_COUNTER)) % 200 + 20),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "CYCLONEDDS_URI": LOOPBACK,
        "PYTHONUNBUFFERED": "1",
    }
    log = tmp_path / "launch.log"
    with log.open("wb") as sink:
        proc = subprocess.Popen(
            [sys.executable, "-m", "tpsr_ros.launch", str(LAUNCH), f"model:={model}",
             f"policy:={policy}", f"bag:={bag}", "episode_steps:=5", "log_level:=debug"],
            stdout=sink, stderr=subprocess.STDOUT, env=env,
        )
    try:
        deadline = time.monotonic() + 90
        while "/cmd_vel ignored: episode_steps (5) reached" not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.1)
        time.sleep(0.5)  # the recorder receives the last step's messages
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        code = proc.wait(60)
    text = log.read_text()
    assert code == 0, text
    for name in ("tpsr_recorder", "sim_node", "tpsr_filter"):
        assert f"[{name}] " in text
    with BagReader(bag) as reader:
        counts = reader.message_counts
        states = [m.stamp_of(x.decode()) for x in reader.messages(["/tpsr/state"])]
    assert counts["/camera/image_raw"] == counts["/action"] == 5
    assert states == [k * 10**9 for k in range(1, 6)]
    # one command per step and the ignored 6th (the first may precede the recorder's match)
    assert counts["/cmd_vel"] in (5, 6)
