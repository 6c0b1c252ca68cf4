"""``CONFIG.yaml``: TPSR fit parameters, written by ``learner tune``, read by ``learner fit``.

The file is a YAML mapping with a ``tpsr`` section (any fields of
:class:`~tpsr_ros.core.tpsr.TPSRConfig`; missing ones keep their defaults), an optional
``input`` section (the topics and robot-bag options the data were read with, so that
``learner fit BAG --config FILE`` needs no other option; an option given on the command line
wins) and an optional ``tune`` section (what the tuner measured and tried; read by people,
ignored by ``fit``).
It is read with the bounded safe loader (:func:`tpsr_ros.io.safe_yaml.load_yaml`), every
name and value validated by ``TPSRConfig`` itself, and each problem is one ``ConfigError``
line naming the file. Writing goes to a temporary file and an atomic rename.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.io.atomic import atomic_file
from tpsr_ros.io.model_io import check_output_path
from tpsr_ros.io.safe_yaml import YamlInputError, load_yaml

__all__ = [
    "INPUT_KEYS",
    "SECTIONS",
    "changed_parameters",
    "describe",
    "read_fit_config",
    "read_fit_file",
    "read_fit_inputs",
    "write_fit_config",
]

SECTIONS = ("tpsr", "input", "tune")
"""Top-level keys of a config file; ``tune`` is informational."""
TOPIC_KEYS = ("image_topic", "action_topic", "pose_topic", "reward_topic", "pose_frame")
SECONDS_KEYS = ("step_period", "step_offset", "image_timeout", "command_timeout")
INPUT_KEYS = (*TOPIC_KEYS, *SECONDS_KEYS, "image_size", "grey", "components", "actions")
"""Keys of the ``input`` section: the ``learner fit`` options of the same names."""

MAX_CONFIG_BYTES = 2**20


def changed_parameters(config: TPSRConfig) -> dict[str, Any]:
    """The parameters of ``config`` that differ from the guide's defaults."""
    default = TPSRConfig()
    return {
        f.name: getattr(config, f.name)
        for f in dataclasses.fields(config)
        if getattr(config, f.name) != getattr(default, f.name)
    }


def describe(config: TPSRConfig) -> str:
    """``rank=8 sigma_ht=2.19 ...``: what differs from the guide's defaults."""
    parts = [
        f"{name}={value:.3g}" if isinstance(value, float) else f"{name}={value}"
        for name, value in changed_parameters(config).items()
    ]
    return " ".join(parts) or "the guide's defaults"


def _load(path: Path) -> dict[str, Any]:
    """The config file's mapping, its sections checked."""
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise ConfigError(f"cannot read config file {str(path)!r}: {exc.strerror}") from None
    try:
        content = load_yaml(data, f"config file {str(path)!r}", max_bytes=MAX_CONFIG_BYTES)
    except YamlInputError as exc:
        raise ConfigError(str(exc)) from None
    if not isinstance(content, dict):
        raise ConfigError(f"config file {str(path)!r}: expected a mapping with a 'tpsr' section")
    if unknown := sorted(map(str, set(content) - set(SECTIONS))):
        raise ConfigError(
            f"config file {str(path)!r}: unknown section(s) {unknown}; expected {list(SECTIONS)}"
        )
    return content


def read_fit_file(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """``(tpsr values, input values)`` of the config file at ``path``, read once."""
    content = _load(path)
    return read_fit_config(path, content), read_fit_inputs(path, content)


def read_fit_config(path: Path, content: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``tpsr`` values of the config file at ``path`` (or of its ``content``, when read
    already), validated (a ``ConfigError`` else)."""
    values = (_load(path) if content is None else content).get("tpsr")
    if not isinstance(values, dict) or not values:
        raise ConfigError(f"config file {str(path)!r}: 'tpsr' must be a mapping of parameters")
    known = {f.name for f in dataclasses.fields(TPSRConfig)}
    if unknown := sorted(map(str, set(values) - known)):
        raise ConfigError(
            f"config file {str(path)!r}: unknown TPSR parameter(s) {unknown}; "
            f"expected some of {sorted(known)}"
        )
    try:
        TPSRConfig(**values)
    except ConfigError as exc:
        raise ConfigError(f"config file {str(path)!r}: {exc}") from None
    return dict(values)


def _valid_input(key: str, value: Any) -> bool:
    if key in TOPIC_KEYS:
        return isinstance(value, str) and 0 < len(value) < 256
    if key in SECONDS_KEYS:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if key == "image_size":
        return (
            isinstance(value, list)
            and len(value) == 2
            and all(isinstance(v, int) and not isinstance(v, bool) and 0 < v <= 4096 for v in value)
        )
    if key == "grey":
        return isinstance(value, bool)
    if key == "components":
        return (
            isinstance(value, list)
            and 0 < len(value) <= 6
            and all(isinstance(c, str) for c in value)
        )
    return isinstance(value, int) and not isinstance(value, bool) and 0 < value <= 10_000


def read_fit_inputs(path: Path, content: dict[str, Any] | None = None) -> dict[str, Any]:
    """The ``input`` values of the config file (empty without the section), types checked;
    ``learner fit`` validates them further as it validates its options."""
    section = (_load(path) if content is None else content).get("input", {})
    if not isinstance(section, dict):
        raise ConfigError(f"config file {str(path)!r}: 'input' must be a mapping")
    if unknown := sorted(map(str, set(section) - set(INPUT_KEYS))):
        raise ConfigError(
            f"config file {str(path)!r}: unknown input option(s) {unknown}; expected some of "
            f"{list(INPUT_KEYS)}"
        )
    for key, value in section.items():
        if not _valid_input(key, value):
            raise ConfigError(f"config file {str(path)!r}: input {key} {value!r} is not valid")
    values = dict(section)
    if "image_size" in values:
        values["image_size"] = tuple(values["image_size"])
    if "components" in values:
        values["components"] = tuple(values["components"])
    return values


def write_fit_config(
    path: Path,
    tpsr: TPSRConfig,
    tune: Mapping[str, Any],
    *,
    inputs: Mapping[str, Any] | None = None,
    header: str = "",
    force: bool = False,
) -> None:
    """Write ``tpsr`` (every field), the ``input`` options and the ``tune`` record
    atomically, ``header`` as comments."""
    path = check_output_path(path, force=force)
    content: dict[str, Any] = {"tpsr": tpsr.to_dict()}
    if inputs:
        content["input"] = {
            k: list(v) if isinstance(v, tuple) else v for k, v in inputs.items() if v is not None
        }
    content["tune"] = dict(tune)
    body = yaml.safe_dump(content, sort_keys=False, default_flow_style=None)
    comments = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    with atomic_file(path, "w") as handle:
        handle.write(comments + body)
