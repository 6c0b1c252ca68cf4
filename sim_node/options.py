"""Command-line options every simulator command shares: the camera's vertical extent."""

from __future__ import annotations

import argparse
from typing import Any

from sim_node.config import (
    DEFAULT_VERTICAL_HALF_EXTENT,
    MAX_VERTICAL_HALF_EXTENT,
    STRIP_VERTICAL_HALF_EXTENT,
    check_vertical_half_extent,
)
from tpsr_ros.core.errors import ConfigError

__all__ = ["add_vertical_half_extent_option", "vertical_half_extent"]


def vertical_half_extent(text: str) -> float:
    """argparse type: a vertical half-extent the camera can render."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    try:
        return check_vertical_half_extent(value)
    except ConfigError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def add_vertical_half_extent_option(parser: Any, what: str = "the simulator's camera") -> None:
    """``--vertical-half-extent T``: the tangent of the camera's half vertical field of view."""
    parser.add_argument(
        "--vertical-half-extent",
        type=vertical_half_extent,
        default=None,
        metavar="T",
        help=f"{what}: tangent of the half vertical field of view, in (0, "
        f"{MAX_VERTICAL_HALF_EXTENT:g}] (default: the environment's, "
        f"{DEFAULT_VERTICAL_HALF_EXTENT:g} or ±11.3°, partial-strip "
        f"{STRIP_VERTICAL_HALF_EXTENT:g}; 0.03 makes the walls fill every image row at any "
        "distance in the room)",
    )
