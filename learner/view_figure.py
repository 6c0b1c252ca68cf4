"""``learner view-figure VIEW_BAG -o PNG``: one picture of what the view shows at one step.

Drawn from the messages themselves (a bag written by ``learner track --mcap``, or a
recording of the filter node's view topics), so the picture is what Foxglove or RViz would
show: the camera image at step k, the image the model predicted at step k for step k + 1
next to the image that came, the state among the training states (the markers, on their
first two coordinates) and, where the bag has them, the decoded pose against the true one.
"""

from __future__ import annotations

import argparse
import itertools
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io import messages as m
from tpsr_ros.io.atomic import atomic_file
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.model_io import check_output_path
from tpsr_ros.io.view_messages import (
    DECODED_POSE_TOPIC,
    PREDICTED_IMAGE_TOPIC,
    STATE_MARKERS_TOPIC,
)

__all__ = ["register", "run"]

CAMERA_TOPIC = "/camera/image_raw"
TRUE_POSE_TOPIC = "/ground_truth/pose"
DEFAULT_STEP = 25
"""The step drawn by default: half-way into the standard evaluation's first episode (50
steps), the trail formed and the robot on its way (or the middle of a shorter bag)."""


@dataclass
class _Recorded:
    """The view bag's messages by stamp."""

    camera: dict[int, bytes] = field(default_factory=dict)
    """The camera's CDR by stamp, decoded only for the two frames drawn (a robot's camera
    may be large)."""
    predicted: dict[int, np.ndarray] = field(default_factory=dict)
    markers: dict[int, dict[str, Any]] = field(default_factory=dict)
    cloud: np.ndarray | None = None
    decoded: dict[int, tuple[float, float]] = field(default_factory=dict)
    true: dict[int, tuple[float, float]] = field(default_factory=dict)


def _read(path: Path, camera_topic: str) -> _Recorded:
    recorded = _Recorded()
    topics = [camera_topic, "/" + PREDICTED_IMAGE_TOPIC, "/" + STATE_MARKERS_TOPIC,
              "/" + DECODED_POSE_TOPIC, TRUE_POSE_TOPIC]  # fmt: skip
    with BagReader(path) as reader:
        types = reader.topics_with_messages
        if "/" + STATE_MARKERS_TOPIC not in types or "/" + PREDICTED_IMAGE_TOPIC not in types:
            raise ConfigError(
                f"{path} has no view topics: write one with `learner track MODEL BAG --mcap "
                "VIEW_BAG`, or record the filter node's tpsr/ topics"
            )
        for topic, _, data in reader.raw_messages([t for t in topics if t in types]):
            if topic == camera_topic:
                if types[topic] == m.IMAGE_TYPE:
                    recorded.camera[m.header_stamp_ns(data)] = bytes(data)
                continue
            msg = m.deserialize(data, types[topic])
            stamp = m.stamp_of(msg) if topic != "/" + STATE_MARKERS_TOPIC else None
            if topic == "/" + PREDICTED_IMAGE_TOPIC:
                recorded.predicted[stamp] = m.image_to_array(msg)
            elif topic == "/" + STATE_MARKERS_TOPIC:
                _take_markers(recorded, msg)
            elif topic in ("/" + DECODED_POSE_TOPIC, TRUE_POSE_TOPIC):
                where = recorded.decoded if topic != TRUE_POSE_TOPIC else recorded.true
                where[stamp] = (msg.pose.position.x, msg.pose.position.y)
    return recorded


def _frame(data: bytes) -> np.ndarray:
    """A camera message's pixels."""
    return m.image_to_array(m.deserialize(data, m.IMAGE_TYPE))


def _points(marker: Any) -> np.ndarray:
    return np.array([[p.x, p.y, p.z] for p in marker.points]).reshape(-1, 3)


def _take_markers(recorded: _Recorded, msg: Any) -> None:
    by_ns = {marker.ns: marker for marker in msg.markers}
    if "training_states" in by_ns:
        recorded.cloud = _points(by_ns["training_states"])
        return
    stamp = m.stamp_of(by_ns["state"])
    recorded.markers[stamp] = {
        "trail": _points(by_ns["trail"]),
        "state": np.array([by_ns["state"].pose.position.x, by_ns["state"].pose.position.y]),
        "actions": _points(by_ns["action_values"]) if "action_values" in by_ns else None,
        "colors": (
            [(c.r, c.g, c.b) for c in by_ns["action_values"].colors]
            if "action_values" in by_ns else None
        ),
    }


def render(recorded: _Recorded, step: int | None, path: Path, title: str) -> int:
    """Draw the figure at the ``step``-th predicted image (default: :data:`DEFAULT_STEP`);
    return its stamp."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    stamps = sorted(recorded.predicted)
    following = dict(itertools.pairwise(stamps))
    usable = [s for s in stamps[:-1] if s in recorded.camera and following[s] in recorded.camera]
    if not usable:
        raise ConfigError("the bag has no step with its camera image and the next one")
    index = min(DEFAULT_STEP, len(usable) // 2) if step is None else step
    if not 0 <= index < len(usable):
        raise ConfigError(f"--step {index}: the bag has {len(usable)} drawable steps")
    stamp = usable[index]
    fig = plt.figure(figsize=(11, 6.2))
    grid = fig.add_gridspec(2, 3, height_ratios=[1, 1.25])
    images = (
        (_frame(recorded.camera[stamp]), f"camera, step k (t = {stamp / 1e9:g} s)"),
        (recorded.predicted[stamp], "predicted at step k for step k+1"),
        (_frame(recorded.camera[following[stamp]]), "camera, step k+1"),
    )
    for column, (image, label) in enumerate(images):
        ax = fig.add_subplot(grid[0, column])
        ax.imshow(image, interpolation="nearest")
        ax.set_title(label, fontsize=10)
        ax.set_axis_off()
    ax = fig.add_subplot(grid[1, :2])
    if recorded.cloud is not None:
        ax.plot(recorded.cloud[:, 0], recorded.cloud[:, 1], ".", color="0.75", markersize=2,
                label="training states (the map the model learned)")  # fmt: skip
    markers = recorded.markers.get(stamp)
    if markers is not None:
        trail = markers["trail"]
        ax.plot(trail[:, 0], trail[:, 1], "-", color="tab:blue", lw=1.2, label="state trail")
        ax.plot(*markers["state"], "o", color="tab:orange", markersize=9, label="state b_k",
                zorder=5)
        if markers["actions"] is not None:
            lines = markers["actions"].reshape(-1, 2, 3)
            for line, color in zip(lines, markers["colors"][::2], strict=True):
                ax.plot(line[:, 0], line[:, 1], "-", color=color, lw=1.5)
    ax.set_title("tpsr/state_markers (leading two coordinates)", fontsize=10)
    ax.legend(loc="best", fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    ax = fig.add_subplot(grid[1, 2])
    _draw_poses(ax, recorded, stamp)
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    with atomic_file(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=100)
    plt.close(fig)
    return stamp


def _draw_poses(ax: Any, recorded: _Recorded, stamp: int, last: int = 30) -> None:
    """The last ``last`` decoded poses against the true ones, up to ``stamp``."""
    ax.set_title("tpsr/decoded_pose against the true pose", fontsize=10)
    decoded = [s for s in sorted(recorded.decoded) if s <= stamp][-last:]
    if not decoded:
        ax.text(0.5, 0.5, "no pose read-out", ha="center", transform=ax.transAxes)
        return
    path = np.array([recorded.decoded[s] for s in decoded])
    ax.plot(path[:, 0], path[:, 1], ".-", color="tab:orange", label="decoded", lw=1)
    truth = np.array([recorded.true[s] for s in decoded if s in recorded.true]).reshape(-1, 2)
    if len(truth):
        ax.plot(truth[:, 0], truth[:, 1], ".-", color="k", label="true", lw=1)
    ax.legend(fontsize=8)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_aspect("equal", adjustable="datalim")


def register(subparsers: Any) -> None:
    """Add the ``view-figure`` subcommand."""
    doc = "draw what the view topics show at one step of a view bag (PNG)"
    parser = subparsers.add_parser("view-figure", help=doc, description=__doc__)
    parser.add_argument("bag", type=Path, metavar="VIEW_BAG", help="bag with the view topics")
    parser.add_argument("-o", "--output", type=Path, required=True, metavar="PNG")
    parser.add_argument(
        "--step", type=int, default=None,
        help=f"index of the step to draw (default: {DEFAULT_STEP}, or the middle of fewer)",
    )  # fmt: skip
    parser.add_argument("--camera-topic", default=CAMERA_TOPIC, metavar="TOPIC")
    parser.add_argument("--title", default="what the filter node's view shows", metavar="TEXT")
    parser.add_argument("--force", action="store_true", help="overwrite an existing PNG")
    parser.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    """Read the bag, draw, say which step."""
    output = check_output_path(args.output, force=args.force)
    recorded = _read(args.bag, args.camera_topic)
    stamp = render(recorded, args.step, output, args.title)
    print(f"wrote {output}: the step at {stamp / 1e9:g} s", file=sys.stderr)
    return 0
