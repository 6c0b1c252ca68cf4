"""Configuration fields that carry their help text, so a name and its meaning are spelled once.

``learner`` builds its command-line options from the fields of :class:`TPSRConfig`,
:class:`PCAConfig` and :class:`FQIConfig`, and every node builds its ROS parameters (and
``--help``) from its parameter dataclass, all through :func:`option`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

__all__ = ["option"]


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
