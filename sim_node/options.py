"""Command-line options the simulator commands share: the camera's vertical extent, and the
``drive`` robot's field of view and turn rate."""

from __future__ import annotations

import argparse
from typing import Any

from sim_node.config import (
    DEFAULT_VERTICAL_HALF_EXTENT,
    MAX_VERTICAL_HALF_EXTENT,
    STRIP_VERTICAL_HALF_EXTENT,
    check_vertical_half_extent,
)
from tpsr_ros.core.actions import DEFAULT_TURN_RATE_DEG, MAX_TURN_RATE_DEG
from tpsr_ros.core.errors import ConfigError

__all__ = [
    "add_drive_options",
    "add_vertical_half_extent_option",
    "field_of_view",
    "turn_rate",
    "vertical_half_extent",
]


def _number(text: str, low: float, high: float, what: str) -> float:
    """argparse type helper: ``text`` as a number in ``(low, high]``."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not low < value <= high:
        raise argparse.ArgumentTypeError(f"{what} must be in ({low:g}, {high:g}], got {value:g}")
    return value


def field_of_view(text: str) -> float:
    """argparse type: a horizontal field of view in degrees, (0, 360]."""
    return _number(text, 0.0, 360.0, "the field of view (degrees)")


def turn_rate(text: str) -> float:
    """argparse type: the ``drive`` robot's turn rate in degrees per step."""
    return _number(text, 0.0, MAX_TURN_RATE_DEG, "the turn rate (degrees per step)")


def add_drive_options(parser: Any) -> None:
    """``--field-of-view DEG`` and ``--turn-rate DEG``."""
    parser.add_argument(
        "--field-of-view",
        type=field_of_view,
        default=None,
        metavar="DEG",
        help="horizontal field of view in degrees, (0, 360] (default: the environment's, "
        "300; 60 in partial and partial-strip)",
    )
    parser.add_argument(
        "--turn-rate",
        type=turn_rate,
        default=DEFAULT_TURN_RATE_DEG,
        metavar="DEG",
        help=f"drive: turn rate of the turning actions in degrees per 1 s step, (0, "
        f"{MAX_TURN_RATE_DEG:g}] (default {DEFAULT_TURN_RATE_DEG:g})",
    )


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
