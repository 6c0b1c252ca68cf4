"""``python -m tpsr_ros.launch FILE [name:=value ...]``: run a ROS 2 XML launch file.

The same file ``ros2 launch tpsr_ros FILE`` reads (after ``colcon build``). This reads the
subset of ROS 2's XML launch format our launch files use, and refuses anything else with a
one-line error:

- ``<launch>`` holding ``<arg name= default= description=>`` and ``<node>`` elements;
- ``<node pkg="tpsr_ros" exec= name= namespace= args= ros_args= output= on_exit= if=
  unless=>`` with ``<param name= value=>`` and ``<remap from= to=>`` children
  (``on_exit="shutdown"``: when the node exits, for any reason, every node is stopped;
  ``if``/``unless``: the node runs only when the value is, or is not, true, read as ROS 2
  launch reads a condition: ``true``/``1`` or ``false``/``0``, any case);
- ``$(var NAME)`` in any attribute value.

Each node runs as ``python -m MODULE ARGS --ros-args -r __node:=NAME [-r __ns:=NS]
-p NAME:=VALUE -r FROM:=TO ROS_ARGS`` (the module of each executable is in
:data:`EXECUTABLES`), started by :class:`tpsr_ros.runtime.launcher.Launch` (so a node gets
SIGTERM if the launcher dies). Output is prefixed with ``[name]``. Ctrl-C (SIGINT) or
SIGTERM stops every node with SIGINT, in reverse order of start; when one node exits with
an error, the others are stopped and the launcher exits with status 1. A recorder's
output bag that already exists is refused before any node starts.
"""

from __future__ import annotations

import re
import signal
import sys
import threading
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from tpsr_ros.cli import ArgumentParser
from tpsr_ros.core.errors import TpsrError
from tpsr_ros.runtime.launcher import Launch

__all__ = ["EXECUTABLES", "LaunchError", "LaunchedNode", "main", "parse_launch"]

PROG = "python -m tpsr_ros.launch"
PACKAGE = "tpsr_ros"
EXECUTABLES = {
    "sim_node": "sim_node",
    "filter_node": "tpsr_ros.filter_node",
    "learner_node": "tpsr_ros.learner_node",
    "record": "tpsr_ros.record",
    "play": "tpsr_ros.play",
    "view": "tpsr_ros.view",
}
"""Executables of the colcon package (``lib/tpsr_ros/<exec>``) and the module each runs."""

_VAR = re.compile(r"\$\(var ([A-Za-z_][A-Za-z0-9_]*)\)")
_NODE_ATTRS = {
    "pkg", "exec", "name", "namespace", "args", "ros_args", "output", "on_exit", "if", "unless",
}  # fmt: skip
_CONDITION_VALUES = {"true": True, "1": True, "false": False, "0": False}


class LaunchError(TpsrError):
    """A launch file this launcher cannot run (unknown element, missing arg...)."""


@dataclass(frozen=True)
class LaunchedNode:
    """One ``<node>`` of a launch file, with every ``$(var)`` substituted."""

    name: str
    executable: str
    namespace: str
    args: tuple[str, ...]
    params: tuple[tuple[str, str], ...]
    remaps: tuple[tuple[str, str], ...]
    ros_args: tuple[str, ...]
    on_exit: str = ""

    @property
    def module(self) -> str:
        """The Python module ``python -m`` runs for this executable."""
        return EXECUTABLES[self.executable]

    def command(self) -> list[str]:
        """Return the node's ``python -m`` command line (without the interpreter)."""
        ros = ["--ros-args", "-r", f"__node:={self.name}"]
        if self.namespace:
            ros += ["-r", f"__ns:={self.namespace}"]
        for key, value in self.params:
            ros += ["-p", f"{key}:={value}"]
        for source, target in self.remaps:
            ros += ["-r", f"{source}:={target}"]
        return ["-m", self.module, *self.args, *ros, *self.ros_args]


def _attrs(element: ET.Element, allowed: set[str], required: set[str], where: str) -> None:
    unknown = set(element.attrib) - allowed
    if unknown:
        raise LaunchError(f"{where}: unsupported attribute(s) {', '.join(sorted(unknown))}")
    missing = required - set(element.attrib)
    if missing:
        raise LaunchError(f"{where}: missing attribute(s) {', '.join(sorted(missing))}")


def _condition(value: str, where: str) -> bool:
    """Read a condition as ROS 2 launch does (``true``/``1``, ``false``/``0``, any case)."""
    try:
        return _CONDITION_VALUES[value.strip().lower()]
    except KeyError:
        raise LaunchError(f"{where}: condition {value!r} is not true, false, 1 or 0") from None


def _runs(attributes: dict[str, str], where: str) -> bool:
    """Whether a node's ``if``/``unless`` attributes (substituted) let it run."""
    if "if" in attributes and not _condition(attributes["if"], f"{where} if"):
        return False
    return not ("unless" in attributes and _condition(attributes["unless"], f"{where} unless"))


def parse_launch(path: Path | str, overrides: dict[str, str] | None = None) -> list[LaunchedNode]:
    """Return the nodes of launch file ``path``, ``overrides`` giving ``<arg>`` values."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except (OSError, ET.ParseError) as exc:
        raise LaunchError(f"cannot read launch file {str(path)!r}: {exc}") from None
    if root.tag != "launch":
        raise LaunchError(f"{path}: the root element is <{root.tag}>, not <launch>")
    overrides = dict(overrides or {})
    values: dict[str, str] = {}
    declared: set[str] = set()

    def sub(text: str, where: str) -> str:
        def one(match: re.Match[str]) -> str:
            name = match.group(1)
            if name not in values:
                raise LaunchError(f"{where}: $(var {name}) has no value (declare an <arg>)")
            return values[name]

        return _VAR.sub(one, text)

    nodes = []
    for element in root:
        where = f"{path.name}:<{element.tag}>"
        if element.tag == "arg":
            _attrs(element, {"name", "default", "description"}, {"name"}, where)
            name = element.attrib["name"]
            declared.add(name)
            if name in overrides:
                values[name] = overrides[name]
            elif "default" in element.attrib:
                values[name] = sub(element.attrib["default"], where)
            else:
                raise LaunchError(f"{path.name}: argument {name!r} is required ({name}:=VALUE)")
        elif element.tag == "node":
            _attrs(element, _NODE_ATTRS, {"pkg", "exec"}, where)
            a = {k: sub(v, where) for k, v in element.attrib.items()}
            runs = _runs(a, where)  # a node left out is still checked
            if a.get("on_exit", "shutdown") != "shutdown":
                raise LaunchError(f"{where}: on_exit {a['on_exit']!r}: only 'shutdown' is read")
            if a["pkg"] != PACKAGE or a["exec"] not in EXECUTABLES:
                raise LaunchError(
                    f"{where}: {a['pkg']}/{a['exec']} is not one of this package's executables "
                    f"({', '.join(f'{PACKAGE}/{e}' for e in EXECUTABLES)})"
                )
            params, remaps = [], []
            for child in element:
                inner = f"{where}<{child.tag}>"
                if child.tag == "param":
                    _attrs(child, {"name", "value"}, {"name", "value"}, inner)
                    params.append((child.attrib["name"], sub(child.attrib["value"], inner)))
                elif child.tag == "remap":
                    _attrs(child, {"from", "to"}, {"from", "to"}, inner)
                    source, target = child.attrib["from"], child.attrib["to"]
                    remaps.append((sub(source, inner), sub(target, inner)))
                else:
                    raise LaunchError(f"{inner}: unsupported element")
            if runs:
                nodes.append(
                    LaunchedNode(
                        name=a.get("name", a["exec"]),
                        executable=a["exec"],
                        namespace=a.get("namespace", ""),
                        args=tuple(a.get("args", "").split()),
                        params=tuple(params),
                        remaps=tuple(remaps),
                        ros_args=tuple(a.get("ros_args", "").split()),
                        on_exit=a.get("on_exit", ""),
                    )
                )
        else:
            raise LaunchError(f"{where}: unsupported element")
    unknown = set(overrides) - declared
    if unknown:
        raise LaunchError(
            f"{path.name} has no argument(s) {', '.join(sorted(unknown))}; it declares "
            f"{', '.join(sorted(declared)) or 'none'}"
        )
    return nodes


def _check_outputs(nodes: Sequence[LaunchedNode]) -> None:
    """Refuse a recorder output bag that exists, before any node starts (a half-started
    loop would wait for a recorder that never records)."""
    for node in nodes:
        if node.executable != "record":
            continue
        args = list(node.args)
        for flag in ("-o", "--output"):
            if flag in args[:-1] and Path(args[args.index(flag) + 1]).exists():
                raise LaunchError(
                    f"{node.name}: output bag {args[args.index(flag) + 1]!r} already exists; "
                    "remove it or give another (bag:=NEW_DIR)"
                )


def _start_nodes(nodes: Sequence[LaunchedNode]) -> Launch:
    """Start every node through the runtime launcher, its output prefixed with ``[name]``.

    The nodes get SIGTERM if this launcher dies; stopping goes in reverse order of start.
    """
    lock = threading.Lock()

    def echo(name: str, line: str) -> None:
        with lock:
            print(f"[{name}] {line}", flush=True)

    launch = Launch(None, on_output=echo)
    for node in nodes:
        command = node.command()
        process = launch.start(node.name, node.module, command[2:])
        with lock:
            print(
                f"[{PROG}] started {node.name} (pid {process.pid}): python {' '.join(command)}",
                flush=True,
            )
    return launch


def main(argv: list[str] | None = None) -> None:
    """Run a launch file until Ctrl-C or until a node fails."""
    parser = ArgumentParser(prog=PROG, description=__doc__.splitlines()[0])
    parser.add_argument("file", type=Path, help="ROS 2 XML launch file")
    parser.add_argument("arguments", nargs="*", metavar="NAME:=VALUE", help="launch arguments")
    args = parser.parse_args(argv)
    overrides = {}
    for item in args.arguments:
        if ":=" not in item:
            parser.error(f"launch argument {item!r} is not of the form name:=value")
        key, value = item.split(":=", 1)
        overrides[key] = value
    try:
        nodes = parse_launch(args.file, overrides)
        _check_outputs(nodes)
    except LaunchError as exc:
        parser.exit(2, f"{PROG}: error: {exc}\n")
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    launch = _start_nodes(nodes)
    shutdown_on_exit = {n.name for n in nodes if n.on_exit == "shutdown"}
    code = 0
    try:
        while not stop.wait(0.1):
            exited = launch.exited()
            failed = next(((name, c) for name, c in exited.items() if c != 0), None)
            if failed is not None:
                print(f"[{PROG}] {failed[0]} exited with status {failed[1]}; stopping", flush=True)
                code = 1
                break
            if ended := sorted(set(exited) & shutdown_on_exit):
                print(f"[{PROG}] {ended[0]} exited (on_exit shutdown); stopping", flush=True)
                break
            if len(exited) == len(launch.processes):
                break
    finally:
        launch.stop()
    sys.exit(code)


if __name__ == "__main__":
    main()
