"""Command-line options generated from the configuration dataclasses, and the ``--preset`` option.

Every field of :class:`~tpsr_ros.core.tpsr.TPSRConfig`, :class:`~tpsr_ros.core.fqi.FQIConfig`
and :class:`~tpsr_ros.core.pca_baseline.PCAConfig` is one option (name, help and choices
spelled once, on the field). Options default to None, so that a value resolves in this
order: given on the command line, else set by a ``--config`` file, else the preset's
(:mod:`tpsr_ros.core.presets`), else the dataclass default (the guide's).
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

from tpsr_ros.core.fqi import FQIConfig
from tpsr_ros.core.presets import DEFAULT_PRESET, PRESETS, Preset, get_preset
from tpsr_ros.core.tpsr import TPSRConfig

__all__ = ["add_config_options", "add_preset_option", "config_from_args", "preset_from_args"]

C = TypeVar("C")
Group = argparse.ArgumentParser | argparse._ArgumentGroup


def _option_name(f: dataclasses.Field[Any]) -> str:
    return str(f.metadata.get("cli") or f"--{f.name.replace('_', '-')}")


def _preset_defaults(cls: type[Any], name: str) -> str:
    """``5`` or ``8 (best), 5 (guide)``: a field's default under each preset."""
    if cls not in (TPSRConfig, FQIConfig):
        return str(getattr(cls(), name))
    values = {}
    for preset in PRESETS.values():
        config = preset.tpsr_config() if cls is TPSRConfig else preset.fqi_config()
        values[preset.name] = getattr(config, name)
        if cls is TPSRConfig and name in preset.robot_tpsr:
            values[preset.name] = f"{values[preset.name]}; {preset.robot_tpsr[name]} for robot bags"
    if len({str(v) for v in values.values()}) == 1:
        return str(next(iter(values.values())))
    return ", ".join(f"{value} ({preset})" for preset, value in values.items())


def add_config_options(parser: Group, cls: type[Any], *, config_file: bool = False) -> None:
    """One option per field of the frozen config dataclass ``cls`` (dest = field name).

    Every option defaults to None and is resolved by :func:`config_from_args`; the help
    shows the default of each preset (and says a ``--config`` file may set it when
    ``config_file``).
    """
    for f in dataclasses.fields(cls):
        source = ", or the --config file's" if config_file else ""
        kwargs: dict[str, Any] = {
            "dest": f.name,
            "default": None,
            "help": f"{f.metadata.get('help', '')} (default: {_preset_defaults(cls, f.name)}"
            f"{source})",
        }
        if isinstance(f.default, bool):
            kwargs["action"] = argparse.BooleanOptionalAction
        else:
            kwargs["type"] = type(f.default)
            if "choices" in f.metadata:
                kwargs["choices"] = f.metadata["choices"]
            else:
                kwargs["metavar"] = {int: "N", float: "X"}.get(type(f.default), "VALUE")
        parser.add_argument(_option_name(f), **kwargs)


def config_from_args(
    cls: type[C],
    args: argparse.Namespace,
    base: C | None = None,
    file_values: Mapping[str, Any] | None = None,
) -> C:
    """``cls`` from the options of :func:`add_config_options` (validated by ``cls``).

    A field takes the option given on the command line, else ``file_values``' (a
    ``--config`` file), else ``base``'s (a preset's configuration; default ``cls()``).
    """
    reference = cls() if base is None else base
    values = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        value = getattr(args, f.name)
        if value is None:
            if file_values is not None and f.name in file_values:
                value = file_values[f.name]
            else:
                value = getattr(reference, f.name)
        values[f.name] = value
    return cls(**values)


def add_preset_option(parser: Group, what: str = "fit and fitted-Q") -> None:
    """``--preset NAME``: the named settings every other option starts from."""
    parser.add_argument(
        "--preset",
        choices=sorted(PRESETS),
        default=DEFAULT_PRESET,
        help=f"named {what} settings the other options change: "
        + "; ".join(f"{p.name}: {p.summary}" for p in PRESETS.values()).replace("%", "%%")
        + " (default: %(default)s)",
    )


def preset_from_args(args: argparse.Namespace) -> Preset:
    """The preset ``--preset`` named."""
    return get_preset(args.preset)
