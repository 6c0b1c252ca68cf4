"""The view topics' messages, step by step: what the filter node publishes and what
``learner track --mcap`` writes, from one code path, so the two agree byte for byte.

For each tracked step k (stamp t_k, state b_k, observation o_k) :class:`ViewMessages` gives
the CDR bytes of

- ``tpsr/predicted_image`` (``sensor_msgs/msg/Image``, rgb8, the model's image size): the
  expected next observation from b_k after the greedy action (with Q-values) or
  action-blind (without), clipped to pixel range;
- ``tpsr/state_markers`` (``visualization_msgs/msg/MarkerArray``, frame ``tpsr``): the trail
  of the last ``trail`` states and the current state in the viewer's three coordinates
  (:meth:`~tpsr_ros.core.view_readout.ViewReadout.view_point`) and, with Q-values, one line
  per action (namespace ``action_values``, a line list) from the current state along the
  action's command, longer for higher values, the greedy one green; at step 0 and every
  ``cloud_every`` steps it is preceded by a second message holding the training states
  (namespace ``training_states``, stamp 0: "latest");
- ``tpsr/decoded_pose`` (``geometry_msgs/msg/PoseStamped``, the training poses' frame) where
  the model has a pose read-out;

and the error (pixel units, root mean square) of the previous step's predicted image
against o_k. The messages depend only on the steps given, in order.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass

import numpy as np

from tpsr_ros.core.actions import environment_grid
from tpsr_ros.core.errors import MessageError
from tpsr_ros.core.view_readout import ViewReadout
from tpsr_ros.io import messages as m
from tpsr_ros.io.filter_inputs import model_image_shape
from tpsr_ros.io.marker_cdr import MarkerArrayTemplate, MarkerData, marker_array_cdr
from tpsr_ros.io.model_io import ModelFile

__all__ = [
    "DECODED_POSE_TOPIC",
    "MARKERS_TYPE",
    "PREDICTED_IMAGE_TOPIC",
    "STATE_MARKERS_TOPIC",
    "ViewMessages",
    "ViewSettings",
    "ViewStep",
    "view_messages",
]

PREDICTED_IMAGE_TOPIC = "tpsr/predicted_image"
STATE_MARKERS_TOPIC = "tpsr/state_markers"
DECODED_POSE_TOPIC = "tpsr/decoded_pose"
MARKERS_TYPE = "visualization_msgs/msg/MarkerArray"
VIEW_FRAME = "tpsr"
_GREEN = (0.1, 0.8, 0.2, 1.0)
_GREY = (0.5, 0.5, 0.5, 0.6)

# visualization_msgs/msg/Marker constants
_SPHERE, _LINE_STRIP, _LINE_LIST, _POINTS, _ADD = 2, 4, 5, 8, 0


@dataclass(frozen=True)
class ViewSettings:
    """How much the view draws.

    Attributes:
        trail: states in the trail (the last ones).
        cloud_every: steps between repetitions of the training states' message (a viewer
            that joins late sees the map within this many steps).

    """

    trail: int = 100
    cloud_every: int = 50

    def __post_init__(self) -> None:
        if self.trail < 1 or self.cloud_every < 1:
            raise ValueError(f"view trail and cloud_every must be >= 1, got {self}")


@dataclass(frozen=True)
class ViewStep:
    """The messages of one step, as CDR bytes in publishing order per topic."""

    predicted_image: bytes
    markers: tuple[bytes, ...]
    decoded_pose: bytes | None
    image_error: float | None
    """Pixel RMS error of the previous step's predicted image against this step's image."""


def _checked(template: bytes, size: int, stamp_ns: int, expected: bytes) -> m.StampedTemplate:
    """The template encoder of a message whose last ``size`` bytes change, checked to give
    ``expected`` (the generic serialiser's bytes of a probe stamped ``stamp_ns``)."""
    encoder = m.StampedTemplate(template, size)
    if encoder(stamp_ns, expected[-size:]) != expected:
        raise MessageError("the message layout is not the one the view's encoder writes")
    return encoder


def _image_encoder(shape: tuple[int, int, int], frame_id: str) -> m.StampedTemplate:
    """rgb8 images of ``shape``: the pixels end the message."""
    zeros = np.zeros(shape, dtype=np.uint8)
    probe = np.arange(zeros.size, dtype=np.uint8).reshape(shape)
    expected = m.serialize(m.image_msg(1_500_000_002, probe, frame_id), m.IMAGE_TYPE)
    template = m.serialize(m.image_msg(0, zeros, frame_id), m.IMAGE_TYPE)
    return _checked(template, zeros.size, 1_500_000_002, expected)


def _pose_encoder(frame_id: str) -> m.StampedTemplate:
    """Poses in ``frame_id``: position and orientation, 7 float64, end the message."""
    expected = m.serialize(m.pose_msg(1_500_000_002, 1.5, -2.5, frame_id, 0.3), m.POSE_TYPE)
    template = m.serialize(m.pose_msg(0, 0, 0, frame_id), m.POSE_TYPE)
    return _checked(template, 56, 1_500_000_002, expected)


def _directions(commands: np.ndarray | None, n_actions: int) -> np.ndarray:
    """Unit-length-at-most arrow directions ``(n_actions, 3)`` from the actions' first two
    command components (the planar velocity; a turning robot's forward and turn rate)."""
    out = np.zeros((n_actions, 3))
    if commands is None or commands.size == 0:
        return out
    planar = np.zeros((n_actions, 2))
    planar[:, : min(2, commands.shape[1])] = commands[:, :2]
    largest = float(np.abs(planar).max())
    if largest > 0:
        out[:, :2] = planar / largest
    return out


class ViewMessages:
    """The view topics of a run of steps (module docstring); one instance per run."""

    def __init__(
        self,
        view: ViewReadout,
        image_shape: tuple[int, int],
        *,
        commands: np.ndarray | None = None,
        settings: ViewSettings | None = None,
        image_frame: str = "camera",
    ) -> None:
        """``image_shape`` is the observations' ``(H, W)``; ``commands`` ``(A, d)`` the
        actions' command components (arrow directions)."""
        self.view = view
        self.settings = settings or ViewSettings()
        height, width = image_shape
        channels = view.obs_size // (height * width)
        if channels not in (1, 3) or channels * height * width != view.obs_size:
            raise ValueError(
                f"observations of {view.obs_size} values are not {height}x{width} images"
            )
        self._pixels_shape = (height, width, channels)
        self.image_frame = image_frame
        self._directions = _directions(commands, view.n_actions)
        self._line_colors = np.tile(np.asarray(_GREY, dtype=np.float32), (2 * view.n_actions, 1))
        self._greedy_colors: dict[int, bytes] = {}  # the lines' colours per greedy action
        self._lines = np.empty((2 * view.n_actions, 3))  # each line's ends, start first
        self._line_starts, self._line_ends = self._lines[0::2], self._lines[1::2]
        self._template: MarkerArrayTemplate | None = None  # of the last step's markers
        # the trail twice over: the last ``trail`` points are always one contiguous slice
        self._trail = np.zeros((2 * self.settings.trail, 3))
        self._image = _image_encoder((height, width, 3), image_frame)
        self._pose_cdr = None if view.pose is None else _pose_encoder(view.pose_frame)
        self._steps = 0
        self._previous: np.ndarray | None = None  # the last prediction, in [0, 1]
        cloud = MarkerData(
            0, VIEW_FRAME, "training_states", 0, _POINTS, scale=(0.02, 0.02, 0.0),
            color=(0.6, 0.6, 0.6, 0.5), points=view.points,
        )  # fmt: skip
        self.cloud = marker_array_cdr([cloud])
        """The training states' message (constant: built once)."""

    def step(self, stamp_ns: int, state: np.ndarray, observation: np.ndarray,
             q_values: np.ndarray | None = None) -> ViewStep:  # fmt: skip
        """The messages of one tracked step (``q_values``: the policy's, per action)."""
        error = None
        if self._previous is not None:  # np.mean's sum and division, without its wrappers
            difference = self._previous - observation
            error = float(np.sqrt(np.add.reduce(difference * difference) / difference.size) * 255.0)
        greedy = None if q_values is None else int(np.asarray(q_values).argmax())
        predicted = self.view.predicted_observation(state, greedy)  # a new array: clip it
        np.minimum(np.maximum(predicted, 0.0, out=predicted), 1.0, out=predicted)
        self._previous = predicted
        pixels = np.rint(predicted * 255.0).astype(np.uint8).reshape(self._pixels_shape)
        if pixels.shape[2] == 1:
            pixels = np.repeat(pixels, 3, axis=2)
        image = self._image(stamp_ns, pixels.tobytes())
        markers = self._markers(stamp_ns, state, q_values, greedy)
        if self._steps % self.settings.cloud_every == 0:
            markers = (self.cloud, *markers)
        self._steps += 1
        return ViewStep(image, markers, self._pose(stamp_ns, state), error)

    def _markers(
        self, stamp_ns: int, state: np.ndarray, q_values: np.ndarray | None, greedy: int | None
    ) -> tuple[bytes]:
        here = self.view.view_point(state)
        length = self.settings.trail
        slot = self._steps % length
        self._trail[slot] = self._trail[slot + length] = here
        first = slot + 1 if self._steps >= length else 0
        trail = self._trail[first : slot + 1] if first == 0 else self._trail[first : first + length]
        lines = colors = None
        if q_values is not None and greedy is not None:
            lines, colors = self._action_values(here, q_values, greedy)
        # the same markers but for stamps, positions and values: a template's bytes
        template = self._template
        shape = ((len(trail), 0), (0, 0)) + (() if lines is None else ((len(lines),) * 2,))
        if template is None or template.shape != shape:  # the trail grows, or values come
            template = self._template = MarkerArrayTemplate(self._marker_shapes(trail, lines))
        if lines is None:
            return (template(stamp_ns, [None, here], [trail, None], [None, None]),)
        return (template(stamp_ns, [None, here, None], [trail, None, lines], [None, None, colors]),)

    def _marker_shapes(self, trail: np.ndarray, lines: np.ndarray | None) -> list[MarkerData]:
        """The markers of a step (trail, state and, with Q-values, the action lines), with
        values that the template's users write over."""
        zeros = np.zeros((len(trail), 3))
        markers = [
            MarkerData(0, VIEW_FRAME, "trail", 0, _LINE_STRIP, scale=(0.02, 0.0, 0.0),
                       color=(0.2, 0.6, 1.0, 0.8), points=zeros),
            MarkerData(0, VIEW_FRAME, "state", 0, _SPHERE, scale=(0.12, 0.12, 0.12),
                       color=(1.0, 0.5, 0.0, 1.0)),
        ]  # fmt: skip
        if lines is not None:
            values = MarkerData(
                0, VIEW_FRAME, "action_values", 0, _LINE_LIST, scale=(0.015, 0.0, 0.0),
                color=_GREEN, points=np.zeros((len(lines), 3)),
                colors=np.zeros((len(lines), 4), dtype=np.float32),
            )  # fmt: skip
            markers.append(values)
        return markers

    def _action_values(
        self, here: np.ndarray, q_values: np.ndarray, greedy: int
    ) -> tuple[np.ndarray, bytes]:
        """One line per action from the current state along its command, of length rising
        with its Q-value from 0.05 to 0.5; the greedy action (``q_values``' argmax) green,
        the others grey: the lines' points and the bytes of their colours."""
        values = np.asarray(q_values, dtype=np.float64)
        low, high = float(np.minimum.reduce(values)), float(np.maximum.reduce(values))
        lengths = 0.05 + 0.45 * (values - low) / (high - low if high > low else 1.0)
        self._line_starts[...] = here  # written into a message before the next step
        ends = np.multiply(lengths[:, None], self._directions, out=self._line_ends)
        ends += here
        colors = self._greedy_colors.get(greedy)
        if colors is None:
            line_colors = self._line_colors.copy()
            line_colors[2 * greedy : 2 * greedy + 2] = _GREEN
            colors = self._greedy_colors[greedy] = np.ascontiguousarray(
                line_colors, dtype="<f4"
            ).tobytes()
        return self._lines, colors

    def _pose(self, stamp_ns: int, state: np.ndarray) -> bytes | None:
        pose = self.view.decoded_pose(state)
        if pose is None or self._pose_cdr is None:
            return None
        heading = None
        if pose.shape[0] == 4:  # cos, sin of the heading: its angle, whatever their norm
            heading = math.atan2(float(pose[3]), float(pose[2]))
        z, w = m.heading_quaternion(heading)
        values = (float(pose[0]), float(pose[1]), 0.0, 0.0, 0.0, z, w)
        return self._pose_cdr(stamp_ns, struct.pack("<7d", *values))


def view_messages(
    model_file: ModelFile, settings: ViewSettings | None = None
) -> ViewMessages | None:
    """The view messages of a model file's steps, its actions' commands giving the arrows'
    directions; None for a model without the viewer's read-outs."""
    if model_file.view is None:
        return None
    if model_file.spec is None:
        codes = environment_grid(model_file.environment).codes
    else:
        codes = model_file.spec.codebook.codes
    return ViewMessages(
        model_file.view, model_image_shape(model_file), commands=codes, settings=settings
    )
