"""``python -m <node>`` (and ``ros2 run tpsr_ros <node>``) for a :class:`~.node.Node`.

:func:`run_node` parses ROS 2's command line (``--ros-args -p/-r/--params-file/
--log-level``; ``--help`` lists the parameters), opens the transport chosen by
``TPSR_TRANSPORT``, installs SIGINT/SIGTERM handlers that stop :meth:`Node.spin`
gracefully, and closes the node (which waits for reliable data to be acknowledged).
Usage errors exit with status 2, runtime errors with 1, each as one line on stderr that
names the program as the user started it.
"""

from __future__ import annotations

import signal
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import NoReturn

from tpsr_ros.cli import ArgumentParser
from tpsr_ros.core.errors import TpsrError
from tpsr_ros.runtime.node import Node, NodeOptions
from tpsr_ros.runtime.params import format_parameter_help
from tpsr_ros.runtime.ros_args import UsageError, parse_ros_args, split_ros_args

__all__ = ["ROS_ARGS_HELP", "parse_node_args", "program_name", "run_node"]

ROS_ARGS_HELP = """\
ROS arguments (after --ros-args):
  -p NAME:=VALUE          set a parameter (YAML value: 3, 3.0, true, text, [1, 2])
  --params-file FILE      ROS 2 parameters file (node_name: ros__parameters: {...})
  -r FROM:=TO             remap a topic; -r __node:=NAME renames the node,
                          -r __ns:=/NS sets its namespace
  --log-level LEVEL       debug, info, warn, error or fatal (or LOGGER:=LEVEL)
Middleware: TPSR_TRANSPORT=rclpy|dds|inproc (default: rclpy if importable, else dds);
ROS_DOMAIN_ID selects the DDS domain.
"""



def _help_text(node_cls: type[Node], parser: ArgumentParser) -> str:
    return (
        parser.format_help().rstrip()
        + "\n\n"
        + format_parameter_help(node_cls.Params)
        + "\n"
        + ROS_ARGS_HELP
    )


def parse_node_args(
    node_cls: type[Node], argv: Sequence[str], prog: str
) -> NodeOptions | None:
    """Parse a node's command line; None after printing ``--help``.

    Raises UsageError for a bad ``--ros-args`` section or parameter; the node's own
    options are parsed by its ``argument_parser`` (which exits 2 on errors).
    """
    own, ros_tokens, _ = split_ros_args(argv)
    parser = node_cls.argument_parser(prog)
    if "-h" in own or "--help" in own:
        sys.stdout.write(_help_text(node_cls, parser))
        return None
    args = parser.parse_args(own)
    ros_args = parse_ros_args(ros_tokens)
    return NodeOptions.for_node(node_cls, ros_args, args=args)


class _Signals:
    """SIGINT/SIGTERM from the node's construction on: the first asks the node to shut down
    gracefully (one that arrives while the node is being built, after it has started to
    log, is kept and asked once it exists), a second one while it still spins or is being
    built stops waiting (KeyboardInterrupt); once the node is closing, further signals are
    ignored, as closing is bounded (a terminal's Ctrl-C under ``ros2 launch`` arrives
    twice, from the terminal and from launch)."""

    def __init__(self) -> None:
        self.node: Node | None = None
        self.closing = False
        self.pending: int | None = None  # a signal that came before the node existed
        self._previous: dict[int, object] = {}

    def install(self) -> None:
        """Take SIGINT and SIGTERM (before the node is built: it may log, and be seen
        running, before its constructor returns)."""
        for signum in (signal.SIGINT, signal.SIGTERM):
            self._previous[signum] = signal.signal(signum, self.handle)

    def attach(self, node: Node) -> None:
        """The node exists: a signal that came while it was built asks it to shut down."""
        self.node = node
        if self.pending is not None:
            node.request_shutdown(f"{signal.Signals(self.pending).name} received while starting")

    def close(self) -> None:
        """The node is closing: later signals are ignored, SIGINT even while Python exits
        (Python puts back the default handler of its own, which would kill the process).
        When no node was built (its start was refused), the caller's handlers are put back,
        for the children it starts later too."""
        self.closing = True
        if self.node is not None:
            signal.signal(signal.SIGINT, signal.SIG_IGN)
            return
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)  # type: ignore[arg-type]

    def handle(self, signum: int, frame: object) -> None:
        if self.closing:
            return
        if self.node is None:
            if self.pending is None:  # asked once the node exists
                self.pending = signum
                return
            self.closing = True  # a second signal while the node is built: stop waiting
            raise KeyboardInterrupt
        if not self.node.ok():  # second signal: stop waiting for a graceful exit
            self.closing = True  # and ignore the ones after it
            raise KeyboardInterrupt
        self.node.request_shutdown(f"{signal.Signals(signum).name} received")


def program_name(default: str, argv0: str) -> str:
    """How the user started the node, for help and errors: ``python -m ...`` (``default``),
    or ``ros2 run tpsr_ros NODE`` for the executables colcon installs in lib/tpsr_ros/."""
    path = Path(argv0)
    if not argv0 or path.suffix == ".py":  # python -m sim_node runs sim_node/__main__.py
        return default
    if path.parent.name == "tpsr_ros" and path.parent.parent.name == "lib":
        return f"ros2 run tpsr_ros {path.name}"
    return path.name


def run_node(node_cls: type[Node], *, prog: str, argv: Sequence[str] | None = None) -> NoReturn:
    """Parse the command line, run the node until SIGINT/SIGTERM, close it and exit."""
    if argv is None:
        prog = program_name(prog, sys.argv[0])
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        options = parse_node_args(node_cls, argv, prog)
    except UsageError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        sys.exit(2)
    if options is None:
        sys.exit(0)
    signals = _Signals()
    node: Node | None = None
    try:
        prepared = node_cls.preflight(options)
        signals.install()
        node = node_cls(options, prepared=prepared)
        signals.attach(node)
        node.logger.debug(f"{node.transport.kind} transport ready; spinning until SIGINT/SIGTERM")
        node.spin()
        code = getattr(node, "exit_code", 0)
    except UsageError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        code = 2
    except TpsrError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        print(f"{prog}: interrupted", file=sys.stderr)
        code = 130
    finally:
        signals.close()
        if node is not None:
            try:
                node.close()
            except TpsrError as exc:
                print(f"{prog}: error: {exc}", file=sys.stderr)
                code = 1
            except KeyboardInterrupt:  # a signal before the handlers were installed
                code = 130
    sys.exit(code)
