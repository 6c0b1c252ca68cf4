"""The simulator's images and executed actions from their CDR bytes, for the filter node.

Apart from :mod:`tpsr_ros.filter_node.inputs` (which takes messages already decoded and
imports no bag library): reading a message at the offsets of its learnt layout, as offline
tracking reads a bag, needs the CDR decoders of :mod:`tpsr_ros.io.cdr_fields`.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from typing import Any

import numpy as np

from tpsr_ros.core.actions import ActionGrid
from tpsr_ros.core.errors import MessageError
from tpsr_ros.core.images import Preprocessing, preprocess_images
from tpsr_ros.filter_node.inputs import (
    Rejected,
    action_index,
    simulator_action,
    simulator_image,
)
from tpsr_ros.io.cdr_fields import ImageDecoder, TwistDecoder
from tpsr_ros.io.message_fields import stamp_of
from tpsr_ros.io.messages import ACTION_TYPE, IMAGE_TYPE, deserialize

__all__ = ["SimulatorInputs"]


class SimulatorInputs:
    """Simulator images and executed actions from their CDR bytes: ``(stamp, observation)``
    and ``(stamp, action index)``, or :class:`Rejected` (``undecodable`` when the bytes are
    not a message).

    A message laid out byte for byte as the last valid one of its input but for its stamp
    and values (the same frame, encoding and size) is read at that one's offsets, as
    offline tracking reads a bag (:mod:`tpsr_ros.io.cdr_fields`): it would pass the same
    checks. Any other is deserialised and checked by :func:`simulator_image` or
    :func:`simulator_action`, and its layout learnt.
    """

    def __init__(
        self, shape: tuple[int, int], image_frame: str, action_frame: str, grid: ActionGrid
    ) -> None:
        self.shape, self.image_frame, self.action_frame, self.grid = (
            shape, image_frame, action_frame, grid,
        )  # fmt: skip
        self._images = ImageDecoder(shape)
        self._preprocessing = Preprocessing(*shape)  # image_to_observation's, made once
        self._actions = TwistDecoder(grid.components)
        self._indices: dict[tuple[float, ...], int] = {}

    def image(self, data: bytes) -> tuple[int, np.ndarray]:
        """Stamp and observation of an image message."""
        known = self._images.decode_known(data)
        if known is not None:
            stamp, pixels = known
            rgb = np.frombuffer(pixels, dtype=np.uint8).reshape(1, *self.shape, 3)
            return stamp, preprocess_images(rgb, self._preprocessing)[0]
        msg = _deserialize(data, IMAGE_TYPE)
        observation = simulator_image(msg, self.shape, self.image_frame)
        _learn(self._images.decode, data)
        return stamp_of(msg), observation

    def action(self, data: bytes) -> tuple[int, int]:
        """Stamp and action index of an executed action message."""
        known = self._actions.decode_known(data)
        if known is not None:
            stamp, command = known
            return stamp, action_index(command, self._indices, self.grid)
        msg = _deserialize(data, ACTION_TYPE)
        index = simulator_action(msg, self.action_frame, self._indices, self.grid)
        _learn(self._actions.decode, data)
        return stamp_of(msg), index


def _deserialize(data: bytes, msgtype: str) -> Any:
    try:
        return deserialize(data, msgtype)
    except MessageError as exc:
        raise Rejected("undecodable", str(exc)) from None


def _learn(decode: Callable[[bytes], Any], data: bytes) -> None:
    """Learn the layout of a message that passed the checks (a stamp that is no time, which
    only the layout's fast read refuses, leaves it to the checks again)."""
    with contextlib.suppress(MessageError):
        decode(data)
