"""``--set NAME=VALUE``: any fit or fitted-Q parameter of an experiment, by name.

Names are the fields of :class:`~tpsr_ros.core.tpsr.TPSRConfig`,
:class:`~tpsr_ros.core.pca_baseline.PCAConfig`, :class:`~tpsr_ros.core.fqi.FQIConfig`, the
simulator's :class:`~learner.simulated.SimSettings` and the baselines that carry the past
(:class:`~tpsr_ros.core.window_baselines.StackedPCAConfig` as ``stacked``,
:class:`~tpsr_ros.core.window_baselines.WindowConfig` as ``window``), qualified as
``tpsr.rank``, ``pca.dim``, ``fqi.ridge``, ``sim.vertical_half_extent`` or ``window.k``; a
bare name (``rank``, ``sigma_ht``) is enough where only one of them has it, and ``-`` may
stand for ``_`` (``ht-centers`` as in ``learner fit --ht-centers``). Values are converted to
the field's type (integer, number, ``true``/``false``, one of the field's choices) and then
validated by the config itself, so a ``--set`` value obeys the same rules as the
command-line option of the same name. """

from __future__ import annotations

import dataclasses
import types
import typing
from collections.abc import Iterable, Mapping
from typing import Any

from learner.simulated import SimSettings
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.fqi import FQIConfig
from tpsr_ros.core.pca_baseline import PCAConfig
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.core.window_baselines import StackedPCAConfig, WindowConfig

__all__ = [
    "CONFIG_CLASSES",
    "apply_overrides",
    "convert",
    "parameter_names",
    "parse_assignment",
    "resolve",
]

CONFIG_CLASSES: Mapping[str, type] = {
    "tpsr": TPSRConfig,
    "pca": PCAConfig,
    "fqi": FQIConfig,
    "sim": SimSettings,
    "stacked": StackedPCAConfig,
    "window": WindowConfig,
}
_BOOLEANS = {"true": True, "1": True, "yes": True, "false": False, "0": False, "no": False}


def parameter_names() -> list[str]:
    """Every settable name, qualified (``tpsr.rank``, ...)."""
    return [
        f"{group}.{f.name}"
        for group, cls in CONFIG_CLASSES.items()
        for f in dataclasses.fields(cls)
    ]


def parse_assignment(text: str) -> tuple[str, str]:
    """``"NAME=VALUE"`` -> ``(NAME, VALUE)``; anything else is a ``ConfigError``."""
    name, sep, value = text.partition("=")
    if not sep or not name.strip() or not value.strip():
        raise ConfigError(f"--set takes NAME=VALUE, got {text!r}")
    return name.strip().replace("-", "_"), value.strip()


def resolve(name: str) -> tuple[str, str]:
    """``(group, field)`` for a qualified or unambiguous bare name."""
    names = parameter_names()
    if name in names:
        group, field = name.split(".", 1)
        return group, field
    matches = [n for n in names if n.split(".", 1)[1] == name]
    if len(matches) == 1:
        group, field = matches[0].split(".", 1)
        return group, field
    if matches:
        raise ConfigError(f"--set name {name!r} is ambiguous; use one of {matches}")
    raise ConfigError(f"unknown --set name {name!r}; choose from {names}")


def _convert(group: str, field: str, text: str) -> Any:
    """``text`` as a value of the field's type, or a ``ConfigError`` naming that type."""
    cls = CONFIG_CLASSES[group]
    kind = typing.get_type_hints(cls)[field]
    if isinstance(kind, types.UnionType):  # ``float | None``: None is the field's default
        kind = next(k for k in typing.get_args(kind) if k is not type(None))
    if typing.get_origin(kind) is typing.Literal:
        choices = typing.get_args(kind)
        if text not in choices:
            raise ConfigError(f"--set {group}.{field} takes one of {list(choices)}, got {text!r}")
        return text
    try:
        if kind is bool:
            return _BOOLEANS[text.lower()]
        if kind is int:
            return int(text)
        if kind is float:
            return float(text)
    except (KeyError, ValueError):
        article = {bool: "true or false", int: "an integer", float: "a number"}[kind]
        raise ConfigError(f"--set {group}.{field} takes {article}, got {text!r}") from None
    raise ConfigError(f"--set {group}.{field}: parameters of type {kind} cannot be set")


def convert(name: str, text: str) -> Any:
    """``text`` as a value of parameter ``name`` (qualified or bare), as ``--set`` reads it."""
    group, field = resolve(name.replace("-", "_"))
    return _convert(group, field, text)


def apply_overrides(configs: Mapping[str, Any], assignments: Iterable[str]) -> dict[str, Any]:
    """New ``{"tpsr": ..., "pca": ..., "fqi": ..., "sim": ..., ...}`` configs with every
    ``NAME=VALUE`` applied.

    Later assignments of the same name win. The configs validate the result; their
    ``ConfigError`` is prefixed with the assignment that caused it.
    """
    changes: dict[str, dict[str, Any]] = {group: {} for group in CONFIG_CLASSES}
    for text in assignments:
        name, value = parse_assignment(text)
        group, field = resolve(name)
        changes[group][field] = _convert(group, field, value)
    result = dict(configs)
    for group, values in changes.items():
        if not values:
            continue
        try:
            result[group] = dataclasses.replace(configs[group], **values)
        except ConfigError as exc:
            shown = " ".join(f"{group}.{k}={v}" for k, v in values.items())
            raise ConfigError(f"--set {shown}: {exc}") from None
    return result
