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
from collections import deque
from dataclasses import dataclass
from typing import Any

import numpy as np

from tpsr_ros.core.actions import environment_grid
from tpsr_ros.core.view_readout import ViewReadout
from tpsr_ros.io import messages as m
from tpsr_ros.io.filter_inputs import model_image_shape
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
MARKER_TYPE = "visualization_msgs/msg/Marker"
VIEW_FRAME = "tpsr"

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


def _point(xyz: np.ndarray) -> Any:
    return m.jazzy_typestore().types["geometry_msgs/msg/Point"](
        x=float(xyz[0]), y=float(xyz[1]), z=float(xyz[2])
    )


def _color(r: float, g: float, b: float, a: float = 1.0) -> Any:
    return m.jazzy_typestore().types["std_msgs/msg/ColorRGBA"](r=r, g=g, b=b, a=a)



def _marker(
    stamp_ns: int, ns: str, marker_id: int, kind: int, *,
    scale: tuple[float, float, float], color: Any, points: list[Any] | None = None,
    colors: list[Any] | None = None, position: np.ndarray | None = None,
) -> Any:  # fmt: skip
    """One ``visualization_msgs/msg/Marker`` in the view frame (lifetime 0: until replaced)."""
    t = m.jazzy_typestore().types
    where = np.zeros(3) if position is None else position
    pose = t["geometry_msgs/msg/Pose"](
        position=_point(where),
        orientation=t["geometry_msgs/msg/Quaternion"](x=0.0, y=0.0, z=0.0, w=1.0),
    )
    return t[MARKER_TYPE](
        header=m.header_msg(stamp_ns, VIEW_FRAME),
        ns=ns,
        id=marker_id,
        type=kind,
        action=_ADD,
        pose=pose,
        scale=t["geometry_msgs/msg/Vector3"](x=scale[0], y=scale[1], z=scale[2]),
        color=color,
        lifetime=t["builtin_interfaces/msg/Duration"](sec=0, nanosec=0),
        frame_locked=False,
        points=points or [],
        colors=colors or [],
        texture_resource="",
        texture=t["sensor_msgs/msg/CompressedImage"](
            header=m.header_msg(0, ""), format="", data=np.zeros(0, dtype=np.uint8)
        ),
        uv_coordinates=[],
        text="",
        mesh_resource="",
        mesh_file=t["visualization_msgs/msg/MeshFile"](
            filename="", data=np.zeros(0, dtype=np.uint8)
        ),
        mesh_use_embedded_materials=False,
    )


def _marker_array(markers: list[Any]) -> bytes:
    msg = m.jazzy_typestore().types[MARKERS_TYPE](markers=markers)
    return m.serialize(msg, MARKERS_TYPE)


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
        self._trail: deque[Any] = deque(maxlen=self.settings.trail)
        self._steps = 0
        self._previous: np.ndarray | None = None  # the last prediction, in [0, 1]
        self._green, self._grey = _color(0.1, 0.8, 0.2), _color(0.5, 0.5, 0.5, 0.6)
        cloud = _marker(
            0, "training_states", 0, _POINTS, scale=(0.02, 0.02, 0.0),
            color=_color(0.6, 0.6, 0.6, 0.5), points=[_point(p) for p in view.points],
        )  # fmt: skip
        self.cloud = _marker_array([cloud])
        """The training states' message (constant: built once)."""

    def step(self, stamp_ns: int, state: np.ndarray, observation: np.ndarray,
             q_values: np.ndarray | None = None) -> ViewStep:  # fmt: skip
        """The messages of one tracked step (``q_values``: the policy's, per action)."""
        error = None
        if self._previous is not None:
            error = float(np.sqrt(np.mean((self._previous - observation) ** 2)) * 255.0)
        greedy = None if q_values is None else int(np.argmax(q_values))
        predicted = np.clip(self.view.predicted_observation(state, greedy), 0.0, 1.0)
        self._previous = predicted
        pixels = np.rint(predicted * 255.0).astype(np.uint8).reshape(self._pixels_shape)
        if pixels.shape[2] == 1:
            pixels = np.repeat(pixels, 3, axis=2)
        image = m.serialize(m.image_msg(stamp_ns, pixels, self.image_frame), m.IMAGE_TYPE)
        markers = self._markers(stamp_ns, state, q_values)
        if self._steps % self.settings.cloud_every == 0:
            markers = (self.cloud, *markers)
        self._steps += 1
        return ViewStep(image, markers, self._pose(stamp_ns, state), error)

    def _markers(
        self, stamp_ns: int, state: np.ndarray, q_values: np.ndarray | None
    ) -> tuple[bytes]:
        here = self.view.view_point(state)
        self._trail.append(_point(here))
        markers = [
            _marker(stamp_ns, "trail", 0, _LINE_STRIP, scale=(0.02, 0.0, 0.0),
                    color=_color(0.2, 0.6, 1.0, 0.8), points=list(self._trail)),
            _marker(stamp_ns, "state", 0, _SPHERE, scale=(0.12, 0.12, 0.12),
                    color=_color(1.0, 0.5, 0.0), position=here),
        ]  # fmt: skip
        if q_values is not None:
            markers.append(self._action_values(stamp_ns, here, q_values))
        return (_marker_array(markers),)

    def _action_values(self, stamp_ns: int, here: np.ndarray, q_values: np.ndarray) -> Any:
        """One line per action from the current state along its command, of length rising
        with its Q-value from 0.05 to 0.5; the greedy action's green, the others grey."""
        values = np.asarray(q_values, dtype=np.float64)
        low, high = float(values.min()), float(values.max())
        lengths = 0.05 + 0.45 * (values - low) / (high - low if high > low else 1.0)
        tips = here + lengths[:, None] * self._directions
        greedy = int(np.argmax(values))
        points, colors = [], []
        for action, tip in enumerate(tips):
            color = self._green if action == greedy else self._grey
            points += [_point(here), _point(tip)]
            colors += [color, color]
        return _marker(
            stamp_ns, "action_values", 0, _LINE_LIST, scale=(0.015, 0.0, 0.0),
            color=self._green, points=points, colors=colors,
        )  # fmt: skip

    def _pose(self, stamp_ns: int, state: np.ndarray) -> bytes | None:
        pose = self.view.decoded_pose(state)
        if pose is None:
            return None
        heading = None
        if pose.shape[0] == 4:  # cos, sin of the heading: its angle, whatever their norm
            heading = math.atan2(float(pose[3]), float(pose[2]))
        msg = m.pose_msg(stamp_ns, pose[0], pose[1], self.view.pose_frame, heading)
        return m.serialize(msg, m.POSE_TYPE)


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
