"""msgs_doc/ says exactly what the nodes declare: parameters, options, endpoints, QoS.

Each page (format in msgs_doc/README.md) names its node class; the node is constructed on
the in-process bus (with its default parameters, or by a factory below) in the namespace
``/doc_ns`` and its parameters, command-line options, publishers and subscriptions are
compared with the page's tables: a relative topic (``camera/image_raw``) must resolve into
the namespace, an absolute one (``/diagnostics``) must not. Rows whose topic is ``*`` are
dynamic and not checked.
"""

from __future__ import annotations

import argparse
import importlib
import re
from collections.abc import Callable
from pathlib import Path

import pytest

from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagWriter
from tpsr_ros.io.qos import parse_qos_text
from tpsr_ros.runtime import Node, NodeOptions, RosArgs, parse_ros_args
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport
from tpsr_ros.runtime.params import param_specs

DOC = Path(__file__).resolve().parent.parent / "msgs_doc"
NAMESPACE = "/doc_ns"


def _cells(line: str) -> list[str]:
    return [c.strip() for c in line.strip().strip("|").split("|")]


def _unquote(text: str) -> str:
    return text.strip().strip("`")


def sections(text: str) -> dict[str, list[str]]:
    """Lines of each ``## Heading`` section (and the preamble under '')."""
    out: dict[str, list[str]] = {"": []}
    current = ""
    for line in text.splitlines():
        if line.startswith("## "):
            current = line[3:].strip()
            out[current] = []
        else:
            out[current].append(line)
    return out


def table(lines: list[str], header: list[str]) -> list[list[str]] | None:
    """Rows of the first table with ``header``; None if the section says None."""
    rows: list[list[str]] = []
    found = False
    for line in lines:
        if not line.strip().startswith("|"):
            if found:
                break
            continue
        cells = _cells(line)
        if not found:
            if [c.lower() for c in cells] == header:
                found = True
            continue
        if set("".join(cells)) <= set("-: "):
            continue
        rows.append(cells)
    if not found:
        if any(line.strip().startswith("None") for line in lines):
            return None
        raise AssertionError(f"no table with header {header} and no 'None'")
    return rows


def header_rows(lines: list[str]) -> dict[str, str]:
    return {
        _cells(line)[0]: _unquote(_cells(line)[1])
        for line in lines
        if line.startswith("|") and len(_cells(line)) == 2 and _cells(line)[0]
    }


def index_pages() -> list[str]:
    text = (DOC / "README.md").read_text()
    rows = table(sections(text)["Nodes"], ["node", "page", "command"])
    assert rows
    return [re.search(r"\(([^)]+\.md)\)", row[1]).group(1) for row in rows]


# -- node factories: nodes that need more than their default parameters -----------------


def _recorder(tmp: Path, bus: InprocBus, ros_args: RosArgs) -> tuple[Node, set[str]]:
    from tpsr_ros.record import RecorderNode

    args = RecorderNode.argument_parser("record").parse_args(["-o", str(tmp / "bag")])
    node = RecorderNode(NodeOptions.for_node(RecorderNode, ros_args, args=args),
                        transport=InprocTransport("/rec", bus))
    return node, set()


def _player(tmp: Path, bus: InprocBus, ros_args: RosArgs) -> tuple[Node, set[str]]:
    from tpsr_ros.play import PlayerNode

    bag = tmp / "in"
    with BagWriter(bag) as writer:
        writer.add_topic("/action", m.ACTION_TYPE)
        writer.write_message("/action", 1, m.twist_stamped_msg(1, 0.0, 0.0))
    args = PlayerNode.argument_parser("play").parse_args([str(bag)])
    node = PlayerNode(NodeOptions.for_node(PlayerNode, ros_args, args=args),
                      transport=InprocTransport("/play", bus))
    return node, {"/action"}  # the bag's topics are the dynamic '*' rows


def _filter(tmp: Path, bus: InprocBus, ros_args: RosArgs) -> tuple[Node, set[str]]:
    from test_filter_node import fit_small_model, random_policy

    from tpsr_ros.filter_node import FilterNode

    model = fit_small_model(tmp)
    policy = random_policy(model, tmp / "policy.npz")  # with a policy: /cmd_vel exists too
    options = NodeOptions.for_node(FilterNode, ros_args, model=str(model), policy=str(policy))
    return FilterNode(options, transport=InprocTransport("/filter", bus)), set()


def _view(tmp: Path, bus: InprocBus, ros_args: RosArgs) -> tuple[Node, set[str]]:
    from tpsr_ros.view import ViewNode

    options = NodeOptions.for_node(ViewNode, ros_args, port=0)  # not the default 8765
    return ViewNode(options, transport=InprocTransport("/view", bus)), set()


def _learner(tmp: Path, bus: InprocBus, ros_args: RosArgs) -> tuple[Node, set[str]]:
    from tpsr_ros.learner_node import LearnerNode

    options = NodeOptions.for_node(LearnerNode, ros_args, output=str(tmp / "live"))
    return LearnerNode(options, transport=InprocTransport("/learner", bus)), set()


FACTORIES: dict[str, Callable[[Path, InprocBus, RosArgs], tuple[Node, set[str]]]] = {
    "tpsr_ros.record:RecorderNode": _recorder,
    "tpsr_ros.play:PlayerNode": _player,
    "tpsr_ros.filter_node:FilterNode": _filter,
    "tpsr_ros.view:ViewNode": _view,
    "tpsr_ros.learner_node:LearnerNode": _learner,
}


def _node_class(spec: str) -> type[Node]:
    module, name = spec.split(":")
    cls = getattr(importlib.import_module(module), name)
    assert issubclass(cls, Node)
    return cls


def _construct(spec: str, tmp: Path) -> tuple[Node, set[str]]:
    bus = InprocBus()
    ros_args = parse_ros_args(["-r", f"__ns:={NAMESPACE}"])
    if spec in FACTORIES:
        return FACTORIES[spec](tmp, bus, ros_args)
    cls = _node_class(spec)
    options = NodeOptions.for_node(cls, ros_args)
    return cls(options, transport=InprocTransport("/doc", bus)), set()


def _in_namespace(topic: str) -> str:
    return topic if topic.startswith("/") else f"{NAMESPACE}/{topic}"


def test_index_lists_every_page_and_every_page_exists():
    pages = index_pages()
    on_disk = sorted(p.name for p in DOC.glob("*.md") if p.name != "README.md")
    assert sorted(pages) == on_disk


@pytest.mark.parametrize("page", index_pages())
def test_page_matches_the_node(page, tmp_path):
    parts = sections((DOC / page).read_text())
    head = header_rows(parts[""])
    for key in ("command", "node name", "node class"):
        assert head.get(key), f"{page}: header row {key!r} missing"
    cls = _node_class(head["node class"])
    assert cls.default_name == head["node name"]

    # parameters: names (in order), ROS types and defaults exactly as declared
    rows = table(parts["Parameters"], ["name", "type", "default", "meaning"]) or []
    documented = [(_unquote(r[0]), r[1], _unquote(r[2])) for r in rows]
    declared = [(s.name, s.ros_type, s.format_default()) for s in param_specs(cls.Params)]
    assert documented == declared, page
    assert all(r[3] for r in rows), f"{page}: a parameter has no meaning"

    # command-line options: the node's own argparse options
    parser = cls.argument_parser("prog")
    actions = [a for a in parser._actions if not isinstance(a, argparse._HelpAction)]
    if "Command-line options" in parts:
        rows = table(parts["Command-line options"], ["option", "type", "default", "meaning"])
        documented_options = {
            tuple(_unquote(o) for o in r[0].split(",")): r[2] for r in rows or []
        }
        declared_options = {
            tuple(a.option_strings) or (a.dest,): a for a in actions
        }
        assert set(documented_options) == set(declared_options), page
        for names, default in documented_options.items():
            action = declared_options[names]
            if action.required or action.nargs in ("*", "+") or action.option_strings == []:
                continue
            if action.default is None:  # no default of its own (e.g. a parameter's)
                continue
            if isinstance(action, argparse._StoreTrueAction):
                assert default == "off", (page, names)
            else:
                assert _unquote(default) == str(action.default), (page, names)
    else:
        assert actions == [], f"{page}: options exist but are not documented"

    # endpoints: every non-dynamic row, exactly
    node, dynamic = _construct(head["node class"], tmp_path)
    assert node.namespace == NAMESPACE
    try:
        for kind, heading in (("publisher", "Publishers"), ("subscription", "Subscriptions")):
            rows = table(parts[heading], ["topic", "type", "qos", "meaning"]) or []
            documented_endpoints = {
                (_in_namespace(_unquote(r[0])), _unquote(r[1]), parse_qos_text(r[2]))
                for r in rows if _unquote(r[0]) != "*"
            }
            assert all(r[3] for r in rows), f"{page}: an endpoint has no meaning"
            declared_endpoints = {
                (e.topic, e.msgtype, e.qos)
                for e in node.endpoints()
                if e.kind == kind and e.topic not in dynamic
            }
            assert documented_endpoints == declared_endpoints, (page, kind)
        assert "Services" in parts, f"{page}: no Services section"
    finally:
        node.close()


def test_the_sim_node_page_documents_the_reset_protocol():
    text = (DOC / "sim_node.md").read_text()
    for needle in ("t_{k+1}", "t_{k+2}", "/sim/episode_start", "transient-local",
                   "never jumps back"):
        assert needle in text


def test_the_reward_types_are_those_learner_policy_reads():
    from tpsr_ros.io.reward_messages import REWARD_TYPES

    text = (DOC / "README.md").read_text()
    rows = table(sections(text)["Rewards from a robot"], ["type", "reward", "time"])
    assert rows is not None
    assert [_unquote(row[0]) for row in rows] == list(REWARD_TYPES)
