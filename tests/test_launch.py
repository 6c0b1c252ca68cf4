"""launch/closed_loop.launch.xml: it names real executables, nodes and parameters (every
node's command line parses as the node itself parses it), the launcher refuses what it
cannot run in one line, and ``python -m tpsr_ros.launch`` runs the closed loop from it
(itself started by the runtime launcher, its progress watched in the graph).
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

import pytest
from graph_support import LOOPBACK, fresh_domain

from sim_node.node import SimNode
from tpsr_ros.filter_node import FilterNode
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.launch import EXECUTABLES, LaunchError, parse_launch
from tpsr_ros.learner_node import LearnerNode
from tpsr_ros.play import PlayerNode
from tpsr_ros.record import RecorderNode
from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions, parse_node_args
from tpsr_ros.runtime.backend import choose_backend, open_transport
from tpsr_ros.runtime.diagnostics import DIAGNOSTICS_TYPE, status_values
from tpsr_ros.runtime.launcher import Launch, NodeProcess
from tpsr_ros.runtime.params import param_specs
from tpsr_ros.view import ViewNode

ROOT = Path(__file__).resolve().parent.parent
LAUNCH = ROOT / "launch" / "closed_loop.launch.xml"
NODE_CLASSES = {"sim_node": SimNode, "filter_node": FilterNode, "record": RecorderNode,
                "play": PlayerNode, "view": ViewNode, "learner_node": LearnerNode}
LEARN_ONLINE = ROOT / "launch" / "learn_online.launch.xml"


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


def test_view_true_adds_the_view_node_and_the_recorder_records_the_view_topics(tmp_path):
    args = {"model": "m.npz", "policy": "p.npz", "bag": str(tmp_path / "bag")}
    nodes = parse_launch(LAUNCH, {**args, "view": "true", "view_port": "0"})
    assert [n.executable for n in nodes] == ["record", "sim_node", "filter_node", "view"]
    view = parse_node_args(ViewNode, nodes[-1].command()[2:], "prog")
    assert view is not None and view.name == ViewNode.default_name and view.params.port == 0
    recorder = parse_node_args(RecorderNode, nodes[0].command()[2:], "prog")
    assert {"/tpsr/predicted_image", "/tpsr/state_markers", "/tpsr/decoded_pose"} <= set(
        recorder.args.topics
    )
    assert [n.executable for n in parse_launch(LAUNCH, {**args, "view": "False"})] == [
        "record", "sim_node", "filter_node"
    ]


@pytest.mark.parametrize(
    "attributes, runs",
    [("if='true'", True), ("if='1'", True), ("if='TRUE'", True), ("if='false'", False),
     ("if='0'", False), ("unless='true'", False), ("unless='false'", True),
     ("if='true' unless='true'", False), ("if='$(var on)'", True)],
)
def test_if_and_unless_select_nodes_as_ros2_launch_does(tmp_path, attributes, runs):
    path = tmp_path / "x.launch.xml"
    path.write_text("<launch><arg name='on' default='true'/>"
                    f"<node pkg='tpsr_ros' exec='view' {attributes}/></launch>")
    assert [n.executable for n in parse_launch(path, {})] == (["view"] if runs else [])


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
        ({}, "<launch><node pkg='tpsr_ros' exec='view' if='yes'/></launch>",
         "condition 'yes' is not true, false, 1 or 0"),
        ({}, "<launch><node pkg='turtlesim' exec='turtlesim_node' if='false'/></launch>",
         "turtlesim/turtlesim_node is not one of this package's executables"),
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
def _graph_probe(monkeypatch, name: str, domain_seed: int) -> Node:
    """A node on the default middleware in a fresh local domain, which the launched nodes
    (children of this process) share."""
    monkeypatch.delenv("TPSR_TRANSPORT", raising=False)
    backend, _ = choose_backend()
    for key, value in {
        "ROS_DOMAIN_ID": str(fresh_domain(domain_seed)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "CYCLONEDDS_URI": LOOPBACK,
        "PYTHONUNBUFFERED": "1",
    }.items():
        monkeypatch.setenv(key, value)
    return Node(NodeOptions(name=name), transport=open_transport(backend, name, "/"))


def test_the_learn_online_launch_file_names_real_nodes_and_parameters(tmp_path):
    nodes = parse_launch(LEARN_ONLINE, {"output": str(tmp_path / "live"), "steps": "500"})
    assert [n.executable for n in nodes] == ["learner_node", "filter_node", "sim_node"]
    parsed = {}
    for node in nodes:
        cls = NODE_CLASSES[node.executable]
        options = parse_node_args(cls, node.command()[2:], "prog")
        assert options is not None and options.name == cls.default_name
        parsed[node.executable] = options.params
    assert parsed["learner_node"].output == str(tmp_path / "live")
    assert parsed["learner_node"].environment == parsed["sim_node"].environment == "full"
    assert parsed["filter_node"].wait_for_model and not parsed["filter_node"].model
    assert (parsed["sim_node"].mode, parsed["sim_node"].steps) == ("explore", 500)


@pytest.mark.slow
def test_the_learn_online_launch_file_learns_and_the_filter_swaps(tmp_path, monkeypatch):
    """The simulator explores, the learner node announces versions, the filter node starts
    with the first and acknowledges the next on /tpsr/model_info (seen in the graph)."""
    import json

    output = tmp_path / "live"
    probe = _graph_probe(monkeypatch, "learn_probe", 23)
    infos: list[dict] = []
    probe.create_subscription(
        "/tpsr/model_info", "std_msgs/msg/String",
        lambda msg: infos.append(json.loads(msg.data)), LATCHED_QOS,
    )  # fmt: skip
    try:
        # the refit worker runs at the lowest priority: on a machine busy with other tests
        # its refits wait for idle cores. The simulator runs until stopped at the launch
        # file's 50 steps/s: a faster one would only keep the cores busy (its steps and the
        # filter's) while the refits wait (at 150 steps/s a refit took 2.5 s, not 0.5 s)
        with Launch(tmp_path, spin=probe.spin_once, timeout_s=300) as launch:
            proc = launch.start("launch", "tpsr_ros.launch", [
                str(LEARN_ONLINE), f"output:={output}", "warmup_steps:=300", "refit_steps:=100",
            ])  # fmt: skip
            launch.wait("the filter node's acknowledgement of version 2",
                        lambda: any(i.get("version") == 2 for i in infos))  # fmt: skip
            code = proc.stop(timeout_s=60)
    finally:
        probe.close()
    text = proc.text()
    assert code == 0, text
    assert "[tpsr_learner] " in text and "v1: " in text, text[-6000:]
    assert "no model yet: waiting" in text
    assert infos[-1]["swaps"] >= 1 and infos[-1]["version"] >= 2
    assert (output / "model.npz").is_file() and (output / "policy.npz").is_file()


@pytest.mark.slow
def test_the_launch_file_runs_the_closed_loop(tmp_path, monkeypatch):
    """The launch file's closed loop runs its episode; its end is seen in the graph.

    A probe on the nodes' default middleware waits for the filter's ``/diagnostics``
    report of the 5 steps and its 6th command (the one the simulator ignores), not for a
    log line. The report repeats every second, so a probe that discovers the nodes only
    after the fast lockstep episode still sees it (a volatile ``/sim/cmd_ignored`` sent
    before the probe matched would be lost; the launch file gives the probe no gate).
    """
    from test_filter_node import fit_small_model, random_policy

    model = fit_small_model(tmp_path)
    policy = random_policy(model, tmp_path / "policy.npz")
    bag = tmp_path / "bag"
    probe = _graph_probe(monkeypatch, "launch_probe", 19)
    reports: list[dict[str, str]] = []
    recorded: list[dict[str, str]] = []
    probe.create_subscription(
        "/diagnostics", DIAGNOSTICS_TYPE,
        lambda msg: [
            (reports if s.name.startswith("tpsr_filter:") else recorded).append(status_values(s))
            for s in msg.status
            if s.name.startswith(("tpsr_filter:", "tpsr_recorder:"))
        ],
    )

    def episode_done() -> bool:
        return any(r.get("steps") == "5" and r.get("commands") == "6" for r in reports)

    def episode_recorded() -> bool:
        topics = ("/camera/image_raw", "/action", "/tpsr/state")
        return any(all(r.get(f"{t} recorded") == "5" for t in topics) for r in recorded)

    try:
        with Launch(tmp_path, spin=probe.spin_once, timeout_s=90) as launch:
            proc = launch.start("launch", "tpsr_ros.launch", [
                str(LAUNCH), f"model:={model}", f"policy:={policy}", f"bag:={bag}",
                "episode_steps:=5", "log_level:=debug",
            ])  # fmt: skip
            launch.wait("the filter's report of 5 steps and 6 commands", episode_done)
            launch.wait("the recorder's report of the 5 steps", episode_recorded)
            code = proc.stop(timeout_s=60)
    finally:
        probe.close()
    text = proc.text()
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


@pytest.mark.slow
def test_a_node_process_passes_each_output_line_to_a_callback_and_its_log(tmp_path):
    """The runtime launcher's pipe mode (how ``tpsr_ros.launch`` prefixes node output)."""
    expected = subprocess.run(
        [sys.executable, "-m", "sim_node", "--help"], capture_output=True, text=True, timeout=60
    ).stdout.splitlines()
    lines: list[str] = []
    proc = NodeProcess("help", "sim_node", ["--help"], log_path=tmp_path / "help.log",
                       on_output=lines.append)
    assert proc.wait(60) == 0
    assert lines == expected and len(expected) > 3
    assert proc.text().splitlines() == expected
    quiet: list[str] = []
    unlogged = NodeProcess("bad", "sim_node", ["--ros-args", "-p", "mode:=fly"],
                           on_output=quiet.append)
    assert unlogged.wait(60) == 2
    assert len(quiet) == 1 and "parameter 'mode'" in quiet[0]
    assert unlogged.log_path is None and unlogged.tail(1) == quiet[0]


@pytest.mark.slow
def test_when_a_node_fails_the_others_are_stopped_and_the_launcher_exits_1(tmp_path):
    text = (
        "<launch><node pkg='tpsr_ros' exec='sim_node'/>"
        "<node pkg='tpsr_ros' exec='filter_node' name='tpsr_filter'>"
        f"<param name='model' value='{tmp_path / 'missing.npz'}'/></node></launch>"
    )
    (tmp_path / "fails.launch.xml").write_text(text)
    env = {
        **os.environ,
        "ROS_DOMAIN_ID": str(fresh_domain(29)),
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST",
        "CYCLONEDDS_URI": LOOPBACK,
    }
    runner = NodeProcess("launch", "tpsr_ros.launch", [str(tmp_path / "fails.launch.xml")],
                         log_path=tmp_path / "launch.log", env=env)
    try:
        code = runner.wait(90)
    finally:
        runner.kill()
    out = runner.text()
    assert code == 1, out
    assert "[tpsr_filter] python -m tpsr_ros.filter_node: error:" in out
    assert "[python -m tpsr_ros.launch] tpsr_filter exited with status 1; stopping" in out
    # the simulator was stopped with SIGINT and said so, its lines prefixed: with its
    # summary if it was up, else as interrupted while starting (the filter can fail first)
    stopped = ("steps and 1 resets", "[sim_node] python -m sim_node: interrupted")
    assert "[sim_node] " in out and any(line in out for line in stopped), out


def test_on_exit_shutdown_is_read_and_a_taken_bag_is_refused_before_any_node(tmp_path):
    from tpsr_ros.launch import _check_outputs

    nodes = parse_launch(ROOT / "launch" / "closed_loop.launch.xml",
                         {"model": "m.npz", "policy": "p.npz", "bag": str(tmp_path / "bag")})
    assert {n.on_exit for n in nodes} == {"shutdown"}  # any node's exit stops the loop
    _check_outputs(nodes)  # a new bag: fine
    (tmp_path / "bag").mkdir()
    with pytest.raises(LaunchError, match=r"output bag .* already exists"):
        _check_outputs(nodes)
    bad = tmp_path / "bad.launch.xml"
    bad.write_text("<launch><node pkg='tpsr_ros' exec='sim_node' on_exit='restart'/></launch>")
    with pytest.raises(LaunchError, match="only 'shutdown' is read"):
        parse_launch(bad, {})
