"""ROS 2's command line (rcl's ``--ros-args`` grammar), parsed without ROS.

    prog [own options] --ros-args [ROS arguments] [-- [own options]]

ROS arguments, in any order and repeatable (a later value wins):

- ``-p name:=value`` / ``--param``: a parameter; the value is a YAML scalar or flow list
  (``3`` is an integer, ``3.0`` a double, ``true`` a bool, ``[1, 2]`` a list);
- ``-r from:=to`` / ``--remap``: topic remapping, optionally for one node
  (``node:from:=to``); ``__node:=name`` renames the node, ``__ns:=/ns`` sets its namespace;
- ``--params-file FILE``: a ROS 2 parameters file (``node: {ros__parameters: {...}}``);
- ``--log-level LEVEL`` or ``--log-level logger:=LEVEL`` (debug, info, warn, error, fatal);
- ``-e``/``--enclave`` and the ``--enable-*``/``--disable-*-logs`` flags are accepted;
  ``--disable-stdout-logs`` silences the console logger.

Anything else inside a ``--ros-args`` section is an error (rcl: "unknown ROS arguments").
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.safe_yaml import YamlInputError, load_yaml

__all__ = [
    "LOG_LEVELS",
    "ParamOverride",
    "ParamsFile",
    "Remap",
    "RosArgs",
    "UsageError",
    "parse_ros_args",
    "parse_yaml_value",
    "split_ros_args",
]

LOG_LEVELS = ("debug", "info", "warn", "error", "fatal")

_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*$")
_TOPIC = re.compile(r"^(~|~/)?/?[A-Za-z_{}][A-Za-z0-9_{}/]*$|^/$")
_FLAGS = frozenset(
    {
        "--enable-rosout-logs",
        "--disable-rosout-logs",
        "--enable-stdout-logs",
        "--disable-stdout-logs",
        "--enable-external-lib-logs",
        "--disable-external-lib-logs",
    }
)


class UsageError(ConfigError):
    """Bad command line: unparsable ``--ros-args``, unknown or mistyped parameter.

    Entry points print it on one line and exit with status 2, like argparse.
    """


@dataclass(frozen=True)
class Remap:
    """``-r [node:]from:=to``."""

    source: str
    target: str
    node: str | None = None


@dataclass(frozen=True)
class ParamOverride:
    """``-p name:=value`` (value already parsed as YAML)."""

    name: str
    value: Any


@dataclass(frozen=True)
class ParamsFile:
    """``--params-file FILE``."""

    path: Path


@dataclass(frozen=True)
class RosArgs:
    """Everything found in the ``--ros-args`` sections of a command line."""

    parameters: tuple[ParamOverride | ParamsFile, ...] = ()
    remaps: tuple[Remap, ...] = ()
    log_levels: tuple[tuple[str | None, str], ...] = ()
    enclave: str | None = None
    flags: frozenset[str] = field(default_factory=frozenset)
    tokens: tuple[str, ...] = ()
    """The tokens as given, for rcl (logging flags, params files) on the rclpy backend."""

    def node_name(self, default: str) -> str:
        """Node name after ``-r __node:=name`` (the last one wins)."""
        name = default
        for remap in self.remaps:
            if remap.source == "__node" and remap.node in (None, default):
                name = remap.target
        return name

    def namespace(self, node: str, default: str = "/") -> str:
        """Node namespace after ``-r __ns:=/ns``."""
        namespace = default
        for remap in self.remaps:
            if remap.source == "__ns" and remap.node in (None, node):
                namespace = remap.target
        return namespace

    def topic_remaps(self, node: str) -> list[Remap]:
        """Topic remap rules that apply to ``node`` (in command-line order)."""
        return [
            r
            for r in self.remaps
            if r.source not in ("__node", "__ns") and r.node in (None, node)
        ]

    def log_level(self, logger: str, default: str = "info") -> str:
        """Level of ``logger``: a logger-specific ``--log-level`` beats the global one."""
        level = default
        for name, value in self.log_levels:
            if name is None:
                level = value
        for name, value in self.log_levels:
            if name == logger:
                level = value
        return level


def split_ros_args(argv: Sequence[str]) -> tuple[list[str], list[str], bool]:
    """Split ``argv`` into (own arguments, ROS argument tokens, whether --ros-args appeared).

    ``--ros-args`` opens a ROS section that runs to a lone ``--`` or the end; several
    sections may appear.
    """
    own: list[str] = []
    ros: list[str] = []
    seen = False
    in_ros = False
    for token in argv:
        if token == "--ros-args":
            in_ros = seen = True
        elif in_ros and token == "--":
            in_ros = False
        elif in_ros:
            ros.append(token)
        else:
            own.append(token)
    return own, ros, seen


def parse_yaml_value(text: str, what: str) -> Any:
    """A ``-p`` value parsed as one YAML scalar or flow sequence, typed as rcl does."""
    if text == "":
        return ""
    try:
        where = f"{what}: cannot parse value {text[:40]!r}"
        value = load_yaml(text, where, max_bytes=2**16, rcl_values=True)
    except YamlInputError as exc:
        raise UsageError(str(exc)) from None
    if isinstance(value, dict):
        raise UsageError(f"{what}: value {text!r} is a mapping; parameters are scalars or lists")
    if value is None:
        raise UsageError(f"{what}: value {text!r} is empty (null)")
    return value


def _split_assignment(text: str, what: str) -> tuple[str, str]:
    if ":=" not in text:
        raise UsageError(f"{what} {text!r} is not of the form name:=value")
    left, right = text.split(":=", 1)
    return left, right


def _parse_remap(text: str) -> Remap:
    left, right = _split_assignment(text, "remap rule")
    node = None
    if ":" in left:
        node, left = left.split(":", 1)
        if not _NAME.match(node) or "." in node:
            raise UsageError(f"remap rule {text!r}: {node!r} is not a node name")
    if left == "__node":
        if not re.match(r"^[A-Za-z_][A-Za-z0-9_]*$", right):
            raise UsageError(f"remap rule {text!r}: {right!r} is not a valid node name")
    elif left == "__ns":
        if not re.match(r"^(/[A-Za-z_][A-Za-z0-9_]*)*/?$", right) or not right.startswith("/"):
            raise UsageError(f"remap rule {text!r}: {right!r} is not an absolute namespace")
        right = right.rstrip("/") or "/"
    elif not _TOPIC.match(left) or not _TOPIC.match(right):
        raise UsageError(f"remap rule {text!r} does not map one topic name to another")
    return Remap(left, right, node)


def _parse_param(text: str) -> ParamOverride:
    name, value = _split_assignment(text, "parameter")
    if not _NAME.match(name):
        raise UsageError(f"parameter {text!r}: {name!r} is not a valid parameter name")
    return ParamOverride(name, parse_yaml_value(value, f"parameter {name!r}"))


def _parse_log_level(text: str) -> tuple[str | None, str]:
    name: str | None = None
    level = text
    if ":=" in text:
        name, level = text.split(":=", 1)
        if not name:
            raise UsageError(f"--log-level {text!r}: empty logger name")
    if level.lower() not in LOG_LEVELS:
        raise UsageError(
            f"--log-level {text!r}: unknown level {level!r}; choose one of {', '.join(LOG_LEVELS)}"
        )
    return name, level.lower()


def parse_ros_args(tokens: Sequence[str]) -> RosArgs:
    """Parse the tokens of the ``--ros-args`` sections; anything unknown raises UsageError."""
    parameters: list[ParamOverride | ParamsFile] = []
    remaps: list[Remap] = []
    levels: list[tuple[str | None, str]] = []
    enclave: str | None = None
    flags: set[str] = set()
    i = 0
    while i < len(tokens):
        token = tokens[i]

        def value(token: str = token, i: int = i) -> str:
            if i + 1 >= len(tokens):
                raise UsageError(f"ROS argument {token} needs a value")
            return tokens[i + 1]

        if token in ("-p", "--param"):
            parameters.append(_parse_param(value()))
            i += 2
        elif token in ("-r", "--remap"):
            remaps.append(_parse_remap(value()))
            i += 2
        elif token == "--params-file":
            path = Path(value())
            if not path.is_file():
                raise UsageError(f"--params-file {str(path)!r} does not exist or is not a file")
            parameters.append(ParamsFile(path))
            i += 2
        elif token == "--log-level":
            levels.append(_parse_log_level(value()))
            i += 2
        elif token in ("-e", "--enclave"):
            enclave = value()
            i += 2
        elif token in ("--log-config-file", "--log-file-name"):
            value()
            i += 2
        elif token in _FLAGS:
            flags.add(token)
            i += 1
        else:
            raise UsageError(f"unknown ROS argument {token!r} after --ros-args")
    return RosArgs(
        tuple(parameters), tuple(remaps), tuple(levels), enclave, frozenset(flags), tuple(tokens)
    )
