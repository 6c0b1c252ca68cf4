"""``CONFIG.yaml``: TPSR fit parameters, written by ``learner tune``, read by ``learner fit``.

The file is a YAML mapping with a ``tpsr`` section (any fields of
:class:`~tpsr_ros.core.tpsr.TPSRConfig`; missing ones keep their defaults) and an optional
``tune`` section (what the tuner measured and tried; read by people, ignored by ``fit``).
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

__all__ = ["SECTIONS", "changed_parameters", "describe", "read_fit_config", "write_fit_config"]

SECTIONS = ("tpsr", "tune")
"""Top-level keys of a config file; ``tune`` is informational."""

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


def read_fit_config(path: Path) -> dict[str, Any]:
    """The ``tpsr`` values of the config file at ``path``, validated (a ``ConfigError`` else)."""
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
    values = content.get("tpsr")
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


def write_fit_config(
    path: Path,
    tpsr: TPSRConfig,
    tune: Mapping[str, Any],
    *,
    header: str = "",
    force: bool = False,
) -> None:
    """Write ``tpsr`` (every field) and the ``tune`` record atomically, ``header`` as comments."""
    path = check_output_path(path, force=force)
    body = yaml.safe_dump(
        {"tpsr": tpsr.to_dict(), "tune": dict(tune)}, sort_keys=False, default_flow_style=None
    )
    comments = "".join(f"# {line}\n" if line else "#\n" for line in header.splitlines())
    with atomic_file(path, "w") as handle:
        handle.write(comments + body)
