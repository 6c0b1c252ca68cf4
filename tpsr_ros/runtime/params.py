"""Node parameters declared once, as the fields of a frozen dataclass.

Each field is a parameter: its name, its type (``bool``, ``int``, ``float``, ``str`` or a
``tuple[...]`` of those), its default and its help (``param(default, "meaning")``). The
same declaration drives ``--help``, type checking of ``-p`` and ``--params-file`` values,
the rclpy backend's ``declare_parameter`` calls and the msgs_doc check.

Types follow ROS: ``-p seed:=3.5`` for an integer parameter is an error, ``-p rate:=50``
for a double is accepted (an integer is promoted to a double, never the reverse). The
dataclass's ``__post_init__`` validates values (ranges, choices); its ``ConfigError``
becomes a usage error.
"""

from __future__ import annotations

import dataclasses
import re
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.fields import option as param
from tpsr_ros.io.safe_yaml import YamlInputError, load_yaml
from tpsr_ros.runtime.ros_args import ParamOverride, ParamsFile, RosArgs, UsageError

__all__ = [
    "STANDARD_PARAMETERS",
    "USE_SIM_TIME",
    "NoParameters",
    "ParamSpec",
    "format_parameter_help",
    "load_params_file",
    "param",
    "param_specs",
    "resolve_parameters",
    "resolve_standard_parameters",
]

_ROS_TYPES = {bool: "bool", int: "integer", float: "double", str: "string"}

MAX_PARAMS_FILE_BYTES = 2**20


@dataclass(frozen=True)
class NoParameters:
    """A node without parameters."""


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter."""

    name: str
    py_type: Any
    default: Any
    help: str
    choices: tuple[Any, ...] | None = None
    range: tuple[float | None, float | None] | None = None  # inclusive; None: open
    positive: bool = False

    @property
    def constraints(self) -> str:
        """The allowed values in words (help, ROS ``additional_constraints``); "" if any."""
        if self.choices is not None:
            return "one of: " + ", ".join(format_value(c) for c in self.choices)
        low, high = self.range or (None, None)
        words = ["> 0"] if self.positive else []
        if low is not None and high is not None:
            words.append(f"from {format_value(low)} to {format_value(high)}")
        elif low is not None:
            words.append(f">= {format_value(low)}")
        elif high is not None:
            words.append(f"<= {format_value(high)}")
        return ", ".join(words)

    def violation(self, value: Any) -> str | None:
        """Why ``value`` (of the right type) is not allowed, or None."""
        if self.choices is not None:
            allowed = ", ".join(format_value(c) for c in self.choices)
            return None if value in self.choices else f"is not one of {allowed}"
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            low, high = self.range or (None, None)
            if (
                (self.positive and not value > 0)
                or (low is not None and not value >= low)
                or (high is not None and not value <= high)
            ):
                return "must be " + self.constraints
        return None

    @property
    def element_type(self) -> type | None:
        """Element type of a list parameter, else ``None``."""
        if typing.get_origin(self.py_type) is tuple:
            return typing.get_args(self.py_type)[0]  # type: ignore[no-any-return]
        return None

    @property
    def ros_type(self) -> str:
        """ROS parameter type name: bool, integer, double, string, double_array..."""
        element = self.element_type
        if element is not None:
            return f"{_ROS_TYPES[element]}_array"
        return _ROS_TYPES[self.py_type]

    def format_default(self) -> str:
        """Default as it would be written after ``:=``."""
        return format_value(self.default)


def format_value(value: Any) -> str:
    """A parameter value in ``-p`` syntax (YAML flow style)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (tuple, list)):
        return "[" + ", ".join(format_value(v) for v in value) + "]"
    if isinstance(value, float):
        return repr(value)
    return str(value)


def _check_type(annotation: Any, where: str) -> Any:
    if annotation in _ROS_TYPES:
        return annotation
    if typing.get_origin(annotation) is tuple:
        args = typing.get_args(annotation)
        if len(args) == 2 and args[1] is Ellipsis and args[0] in _ROS_TYPES:
            return annotation
    raise TypeError(f"{where}: parameter type {annotation!r} is not bool/int/float/str/tuple")


def param_specs(cls: type) -> tuple[ParamSpec, ...]:
    """The parameters declared by dataclass ``cls`` (in field order)."""
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    hints = typing.get_type_hints(cls)
    specs = []
    for f in dataclasses.fields(cls):
        if f.default is dataclasses.MISSING:
            raise TypeError(f"parameter {cls.__name__}.{f.name} needs a default")
        py_type = _check_type(hints[f.name], f"{cls.__name__}.{f.name}")
        specs.append(
            ParamSpec(
                f.name,
                py_type,
                f.default,
                f.metadata.get("help", ""),
                f.metadata.get("choices"),
                f.metadata.get("range"),
                bool(f.metadata.get("positive", False)),
            )
        )
    return tuple(specs)


def _type_word(value: Any) -> str:
    if isinstance(value, bool):
        return "bool"
    if isinstance(value, int):
        return "integer"
    if isinstance(value, float):
        return "double"
    if isinstance(value, str):
        return "string"
    if isinstance(value, (list, tuple)):
        return "list"
    return type(value).__name__


def _coerce_scalar(py_type: type, value: Any) -> Any:
    if py_type is bool:
        return value if isinstance(value, bool) else None
    if py_type is int:
        return value if isinstance(value, int) and not isinstance(value, bool) else None
    if py_type is float:
        if isinstance(value, bool):
            return None
        return float(value) if isinstance(value, (int, float)) else None
    return value if isinstance(value, str) else None


def coerce(spec: ParamSpec, value: Any, source: str) -> Any:
    """``value`` converted to the declared type of ``spec``, or a UsageError naming both."""
    article = "an" if spec.ros_type[0] in "aeiou" else "a"

    def mismatch(shown: str) -> UsageError:
        return UsageError(
            f"parameter {spec.name!r} ({source}) expects {article} {spec.ros_type}, got {shown}"
        )

    element = spec.element_type
    if element is not None:
        if not isinstance(value, (list, tuple)):
            raise mismatch(f"{_type_word(value)} {format_value(value)}")
        items = [_coerce_scalar(element, v) for v in value]
        if any(v is None for v in items):
            raise mismatch(format_value(value))
        result: Any = tuple(items)
    else:
        result = _coerce_scalar(spec.py_type, value)
        if result is None:
            raise mismatch(f"{_type_word(value)} {format_value(value)}")
    if (reason := spec.violation(result)) is not None:
        raise UsageError(f"parameter {spec.name!r} ({source}): {format_value(result)} {reason}")
    return result


def _flatten(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, dict):
            flat.update(_flatten(value, name + "."))
        else:
            flat[name] = value
    return flat


def _node_sections(tree: Any, path: str, where: str) -> list[tuple[str, dict[str, Any]]]:
    if not isinstance(tree, dict):
        raise UsageError(
            f"{where}: {path or 'the top level'} is not a mapping with a ros__parameters section"
        )
    sections: list[tuple[str, dict[str, Any]]] = []
    for key, value in tree.items():
        key = str(key)
        if key == "ros__parameters":
            if not isinstance(value, dict):
                raise UsageError(f"{where}: ros__parameters of {path!r} is not a mapping")
            sections.append((path, _flatten(value)))
        else:
            sub = key if key.startswith("/") else f"{path}/{key}"
            sections.extend(_node_sections(value, sub, where))
    return sections


def _pattern(name: str) -> re.Pattern[str]:
    name = name if name.startswith("/") else "/" + name
    parts = []
    for token in name.strip("/").split("/"):
        if token == "**":
            parts.append("(?:/[^/]+)*")
        elif token == "*":
            parts.append("/[^/]+")
        else:
            parts.append("/" + re.escape(token))
    return re.compile("^" + "".join(parts) + "$")


def load_params_file(path: Path, node_fqn: str) -> list[tuple[bool, dict[str, Any]]]:
    """Sections of a ROS 2 params file that apply to node ``node_fqn`` (e.g. ``/sim_node``).

    Returns ``(wildcard, {name: value})`` pairs in file order; ``wildcard`` is True for
    sections such as ``/**`` that address every node.
    """
    where = f"--params-file {str(path)!r}"
    try:
        with Path(path).open("rb") as handle:
            data = handle.read(MAX_PARAMS_FILE_BYTES + 1)
        tree = load_yaml(data, where, max_bytes=MAX_PARAMS_FILE_BYTES, rcl_values=True)
    except OSError as exc:
        raise UsageError(f"{where}: cannot read it: {exc.strerror}") from None
    except YamlInputError as exc:
        raise UsageError(str(exc)) from None
    if tree is None:
        return []
    sections = _node_sections(tree, "", where)
    if not sections:
        raise UsageError(f"{where}: no 'ros__parameters' section found")
    return [
        ("*" in name, values) for name, values in sections if _pattern(name).match(node_fqn)
    ]


USE_SIM_TIME = ParamSpec(
    "use_sim_time", bool, False, "take the time from /clock (a simulator or a bag replay)"
)
STANDARD_PARAMETERS = {USE_SIM_TIME.name: USE_SIM_TIME}
"""Parameters every ROS 2 node has, besides its own."""


def _given_values(
    specs: dict[str, ParamSpec], ros_args: RosArgs, node_fqn: str
) -> tuple[dict[str, Any], dict[str, Any]]:
    """(node parameters, standard parameters) from params files and ``-p`` in command-line
    order; any other name is an error naming the node's parameters."""
    values: dict[str, Any] = {}
    standard: dict[str, Any] = {}

    def put(name: str, value: Any, source: str) -> None:
        if name in STANDARD_PARAMETERS:
            standard[name] = coerce(STANDARD_PARAMETERS[name], value, source)
        elif name in specs:
            values[name] = coerce(specs[name], value, source)
        else:
            listed = ", ".join([*specs, *STANDARD_PARAMETERS])
            raise UsageError(
                f"unknown parameter {name!r} ({source}); this node's parameters: {listed}"
            )

    for item in ros_args.parameters:
        if isinstance(item, ParamOverride):
            put(item.name, item.value, "-p")
        elif isinstance(item, ParamsFile):
            source = f"--params-file {item.path.name}"
            for _, section in load_params_file(item.path, node_fqn):
                for name, value in section.items():
                    put(name, value, source)
    return values, standard


def resolve_parameters(cls: type, ros_args: RosArgs, node_fqn: str) -> Any:
    """Instance of parameter dataclass ``cls`` from defaults, params files and ``-p``.

    Sources apply in command-line order (a later one wins). An unknown name is an error,
    in ``-p`` and in every params-file section that applies to this node, wildcard ones
    (``/**``, which ``ros2 launch`` writes for a node's ``<param>`` tags) included: a
    misspelt parameter never passes silently. The standard parameters
    (:data:`STANDARD_PARAMETERS`) are read by :func:`resolve_standard_parameters`.
    """
    values, _ = _given_values({s.name: s for s in param_specs(cls)}, ros_args, node_fqn)
    try:
        return cls(**values)
    except ConfigError as exc:
        raise UsageError(f"invalid parameters: {exc}") from None


def resolve_standard_parameters(cls: type, ros_args: RosArgs, node_fqn: str) -> dict[str, Any]:
    """The standard parameters (``use_sim_time``) given to a node of parameters ``cls``,
    defaults for the others."""
    _, standard = _given_values({s.name: s for s in param_specs(cls)}, ros_args, node_fqn)
    return {name: standard.get(name, spec.default) for name, spec in STANDARD_PARAMETERS.items()}


def format_parameter_help(cls: type) -> str:
    """Parameter table for ``--help``."""
    specs = param_specs(cls)
    if not specs:
        return "Parameters: none.\n"
    lines = ["Parameters (--ros-args -p name:=value):"]
    width = max(len(s.name) for s in specs)
    for s in specs:
        extra = f" ({s.constraints})" if s.constraints else ""
        lines.append(
            f"  {s.name:<{width}}  {s.ros_type:<8} default {s.format_default():<10} "
            f"{s.help}{extra}"
        )
    return "\n".join(lines) + "\n"

