"""Configuration fields that carry their help text, so a name and its meaning are spelled once.

``learner`` builds its command-line options from the fields of :class:`TPSRConfig`,
:class:`PCAConfig` and :class:`FQIConfig`, and every node builds its ROS parameters (and
``--help``) from its parameter dataclass, all through :func:`option`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import numpy as np

from tpsr_ros.core.errors import ConfigError

__all__ = ["check_positive_int", "config_dict", "config_from_dict", "option"]


def option(
    default: Any,
    help: str,
    *,
    choices: Sequence[Any] | None = None,
    cli: str | None = None,
    minimum: float | None = None,
    maximum: float | None = None,
    positive: bool = False,
) -> Any:
    """Dataclass field with its help, e.g. ``rate: float = option(10.0, "steps per second")``.

    ``choices``, ``minimum``/``maximum`` (inclusive) and ``positive`` restrict the value
    (checked by the config's ``__post_init__`` or the node's parameter parser, and shown in
    help and in ROS parameter descriptors); ``cli`` overrides the generated
    ``--option-name``. Lists become tuples, so frozen dataclasses stay hashable.
    """
    metadata: dict[str, Any] = {"help": help}
    if choices is not None:
        metadata["choices"] = tuple(choices)
    if minimum is not None or maximum is not None:
        metadata["range"] = (minimum, maximum)
    if positive:
        metadata["positive"] = True
    if cli is not None:
        metadata["cli"] = cli
    if isinstance(default, list):
        default = tuple(default)
    return dataclasses.field(default=default, metadata=metadata)


def check_positive_int(value: Any, what: str) -> None:
    """Refuse anything but a positive integer (a bool is not one), naming ``what``."""
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ConfigError(f"{what} must be a positive integer, not {value!r}")


def config_dict(config: Any) -> dict[str, Any]:
    """A frozen configuration dataclass's parameters as a JSON-serialisable dict."""
    return {
        k: (v.item() if isinstance(v, np.generic) else v)
        for k, v in dataclasses.asdict(config).items()
    }


def config_from_dict(cls: Any, values: dict[str, Any], what: str) -> Any:
    """``cls(**values)``; names ``cls`` does not have are refused, naming ``what``."""
    if unknown := sorted(set(values) - {f.name for f in dataclasses.fields(cls)}):
        raise ConfigError(f"unknown {what} parameters {unknown}")
    return cls(**values)
