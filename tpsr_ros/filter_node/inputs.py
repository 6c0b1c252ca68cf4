"""The filter node's inputs without ROS: decoded messages to observations and action indices.

Each function takes a message already decoded by the node (any object with the message's
fields) and returns what offline tracking reads from the same message in a bag, bit for
bit, or raises :class:`Rejected` with the reason it is counted under
(:data:`REJECT_REASONS`) and a sentence for the log.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from tpsr_ros.core.actions import PLANAR, ActionGrid
from tpsr_ros.core.codebook import ActionCodebook
from tpsr_ros.core.episodes import DEFAULT_ACTION_TOLERANCE, image_to_observation
from tpsr_ros.core.errors import EncodingError, MessageError, TpsrError
from tpsr_ros.core.images import Preprocessing, preprocess_images
from tpsr_ros.io.images import decode_image
from tpsr_ros.io.message_fields import image_to_array, twist_components

__all__ = [
    "REJECT_REASONS",
    "Frame",
    "Rejected",
    "action_index",
    "robot_command",
    "simulator_action",
    "simulator_image",
]

REJECT_REASONS = ("undecodable", "encoding", "size", "data", "frame", "action")
"""Why a message was rejected, one counter each on ``/diagnostics``."""

ACTION_CACHE_SIZE = 1024
"""Distinct commands whose action index :func:`simulator_action` remembers."""


class Rejected(Exception):
    """A message the node cannot use: ``reason`` is one of :data:`REJECT_REASONS`."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


def simulator_image(msg: Any, shape: tuple[int, int], frame: str) -> np.ndarray:
    """The observation of a simulator camera image (rgb8 of ``shape``, frame ``frame``)."""
    if msg.encoding != "rgb8":
        raise Rejected("encoding", f"encoding {msg.encoding!r} is not rgb8")
    if (int(msg.height), int(msg.width)) != shape or int(msg.step) != 3 * int(msg.width):
        raise Rejected(
            "size",
            f"image is {msg.height}x{msg.width} (step {msg.step}), expected "
            f"{shape[0]}x{shape[1]} (step {3 * shape[1]})",
        )
    if len(msg.data) != shape[0] * shape[1] * 3:
        raise Rejected(
            "data", f"image holds {len(msg.data)} bytes, expected {shape[0] * shape[1] * 3}"
        )
    if frame and msg.header.frame_id != frame:
        raise Rejected("frame", f"frame {msg.header.frame_id!r} is not {frame!r}")
    return image_to_observation(image_to_array(msg, shape=shape))


def simulator_action(
    msg: Any, frame: str, cache: dict[tuple[float, ...], int], grid: ActionGrid = PLANAR
) -> int:
    """The action index of an executed action (``TwistStamped``) on the simulator's
    ``grid``, as offline tracking maps it.

    ``cache`` remembers the index of up to :data:`ACTION_CACHE_SIZE` commands.
    """
    if frame and msg.header.frame_id != frame:
        raise Rejected("frame", f"frame {msg.header.frame_id!r} is not {frame!r}")
    try:
        command = tuple(twist_components(msg, grid.components).tolist())
    except TpsrError as exc:
        raise Rejected("action", str(exc)) from None
    return action_index(command, cache, grid)


def action_index(
    command: tuple[float, ...], cache: dict[tuple[float, ...], int], grid: ActionGrid
) -> int:
    """The grid index of a (finite) command, remembered in ``cache``."""
    index = cache.get(command)
    if index is None:
        try:
            index = int(grid.indices(np.array([command]), DEFAULT_ACTION_TOLERANCE)[0])
        except TpsrError as exc:
            raise Rejected("action", str(exc)) from None
        if len(cache) < ACTION_CACHE_SIZE:
            cache[command] = index
    return index


def robot_command(msg: Any, codebook: ActionCodebook) -> tuple[int, float, np.ndarray]:
    """A robot command's nearest code, its distance to it (the offline assignment) and the
    command's components."""
    try:
        values = twist_components(msg, codebook.components)
        index, distance = codebook.assign(values[None])
    except TpsrError as exc:
        raise Rejected("action", str(exc)) from None
    return int(index[0]), float(distance[0]), values


class Frame:
    """A robot camera image as a step holds it: decoded to its observation on first use.

    Only the images a step takes are decoded (one per step, as offline): a camera faster
    than the step grid costs no decoding for the frames in between, which the step grid
    drops undecoded. The message is dropped once decoded.
    """

    __slots__ = ("_msg", "_msgtype", "_preprocessing", "detail", "observation", "reason")

    def __init__(self, msg: Any, msgtype: str, preprocessing: Preprocessing) -> None:
        self._msg, self._msgtype, self._preprocessing = msg, msgtype, preprocessing
        self.observation: np.ndarray | None = None
        self.reason, self.detail = "data", "not decoded"

    def reduce(self) -> np.ndarray | None:
        """The observation (the offline one, bit for bit), decoding the message if not yet;
        None when it cannot be decoded (``reason`` and ``detail`` say why)."""
        if self._msg is None:
            return self.observation
        try:
            pixels = decode_image(self._msg, self._msgtype)
            self.observation = preprocess_images(pixels[None], self._preprocessing)[0]
        except MessageError as exc:
            self.detail = str(exc)
            self.reason = "encoding" if isinstance(exc, EncodingError) else "data"
        self._msg = None
        return self.observation
