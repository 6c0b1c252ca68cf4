"""``python -m tpsr_ros.launch FILE [name:=value ...]``: run a ROS 2 XML launch file.

The same file ``ros2 launch tpsr_ros FILE`` reads (after ``colcon build``). This reads the
subset of ROS 2's XML launch format our launch files use, and refuses anything else with a
one-line error:

- ``<launch>`` holding ``<arg name= default= description=>`` and ``<node>`` elements;
- ``<node pkg="tpsr_ros" exec= name= namespace= args= ros_args= output=>`` with
  ``<param name= value=>`` and ``<remap from= to=>`` children;
- ``$(var NAME)`` in any attribute value.

Each node runs as ``python -m MODULE ARGS --ros-args -r __node:=NAME [-r __ns:=NS]
-p NAME:=VALUE -r FROM:=TO ROS_ARGS`` (the module of each executable is in
:data:`EXECUTABLES`). Output is prefixed with ``[name]``. Ctrl-C (SIGINT) or SIGTERM stops
every node with SIGINT, in reverse order of start; when one node exits with an error, the
others are stopped and the launcher exits with that status.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import threading
import time
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from tpsr_ros.cli import ArgumentParser
from tpsr_ros.core.errors import TpsrError

__all__ = ["EXECUTABLES", "LaunchError", "LaunchedNode", "main", "parse_launch"]

PROG = "python -m tpsr_ros.launch"
PACKAGE = "tpsr_ros"
EXECUTABLES = {
    "sim_node": "sim_node",
    "filter_node": "tpsr_ros.filter_node",
    "record": "tpsr_ros.record",
    "play": "tpsr_ros.play",
}
"""Executables of the colcon package (``lib/tpsr_ros/<exec>``) and the module each runs."""

_VAR = re.compile(r"\$\(var ([A-Za-z_][A-Za-z0-9_]*)\)")
_NODE_ATTRS = {"pkg", "exec", "name", "namespace", "args", "ros_args", "output"}


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
            nodes.append(
                LaunchedNode(
                    name=a.get("name", a["exec"]),
                    executable=a["exec"],
                    namespace=a.get("namespace", ""),
                    args=tuple(a.get("args", "").split()),
                    params=tuple(params),
                    remaps=tuple(remaps),
                    ros_args=tuple(a.get("ros_args", "").split()),
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


class _Running:
    """The node processes; their output prefixed with the node name."""

    def __init__(self, nodes: Sequence[LaunchedNode]) -> None:
        self.procs: list[tuple[LaunchedNode, subprocess.Popen[bytes]]] = []
        self.lock = threading.Lock()
        for node in nodes:
            popen = subprocess.Popen(
                [sys.executable, *node.command()],
                stdout=subprocess.PIPE,
                stderr=subprocess.STDOUT,
                env={**os.environ, "PYTHONUNBUFFERED": "1"},
            )
            self.procs.append((node, popen))
            threading.Thread(target=self._copy, args=(node.name, popen), daemon=True).start()
            print(
                f"[{PROG}] started {node.name} (pid {popen.pid}): "
                f"python {' '.join(node.command())}",
                flush=True,
            )

    def _copy(self, name: str, popen: subprocess.Popen[bytes]) -> None:
        assert popen.stdout is not None
        for raw in popen.stdout:
            line = raw.decode(errors="replace").rstrip("\n")
            with self.lock:
                print(f"[{name}] {line}", flush=True)

    def failed(self) -> tuple[str, int] | None:
        for node, popen in self.procs:
            code = popen.poll()
            if code is not None and code != 0:
                return node.name, code
        return None

    def all_exited(self) -> bool:
        return all(popen.poll() is not None for _, popen in self.procs)

    def stop(self, timeout_s: float = 20.0) -> None:
        for _, popen in reversed(self.procs):
            if popen.poll() is None:
                popen.send_signal(signal.SIGINT)
        deadline = time.monotonic() + timeout_s
        for _, popen in reversed(self.procs):
            try:
                popen.wait(max(0.1, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                popen.kill()
                popen.wait(5)


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
    except LaunchError as exc:
        parser.exit(2, f"{PROG}: error: {exc}\n")
    stop = threading.Event()

    def handler(signum: int, frame: object) -> None:
        stop.set()

    signal.signal(signal.SIGINT, handler)
    signal.signal(signal.SIGTERM, handler)
    running = _Running(nodes)
    code = 0
    try:
        while not stop.wait(0.1):
            failed = running.failed()
            if failed is not None:
                print(f"[{PROG}] {failed[0]} exited with status {failed[1]}; stopping", flush=True)
                code = 1
                break
            if running.all_exited():
                break
    finally:
        running.stop()
    sys.exit(code)


if __name__ == "__main__":
    main()
