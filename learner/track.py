"""``learner track MODEL BAG... -o STATES.csv|.npz [--mcap VIEW_BAG]``: the states a model
tracks over bags, offline, and what the filter node's view shows of them.

The reference the filter node is held to: replaying the bags through it publishes exactly
these states on ``/tpsr/state`` (msgs_doc/filter_node.md). Bags are read as the model's
training bags were (:func:`learner.inputs.read_for_model`: the model's step grid for robot
models, exact-stamp pairing for simulator models) and tracked with the model's parameters
(Algorithm 4), restarting at every gap.

``.csv``: a header line, then one row per tracked step in step order, columns
``stamp_ns,b0,...,b{r-1}`` (then ``x,y`` where the bags carry a pose, and
``cos_heading,sin_heading`` where the robot turns), every number written to round-trip
exactly (17 significant digits). ``.npz`` (no pickles): ``stamp_ns`` ``(T,)``, ``states``
``(T, r)``, ``recovered`` ``(T,)`` and, with a pose, ``positions`` ``(T, 2)`` or ``(T, 4)``.

``--mcap VIEW_BAG``: a new rosbag2 MCAP bag with the bags' camera messages (as recorded)
and, per tracked step, what the filter node publishes on ``/tpsr/state``,
``/tpsr/predicted_image``, ``/tpsr/state_markers`` and ``/tpsr/decoded_pose`` (with
``--policy``: the predicted image after the greedy action, and the actions' values), byte
for byte, so one Foxglove layout shows the live robot and the recording.
"""

from __future__ import annotations

import argparse
import heapq
import io
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from learner.fit import add_topic_options
from learner.inputs import (
    far_commands_line,
    read_for_model,
    recorded_topic,
    require_given_topics,
    topics_from_args,
)
from tpsr_ros.cli import positive_int
from tpsr_ros.core.episodes import Trajectory, track_trajectory
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.online import SWAP_STATES, track_with_swap
from tpsr_ros.core.state_model import Track
from tpsr_ros.core.units import STEP_NS
from tpsr_ros.io import messages as m
from tpsr_ros.io.atomic import atomic_file
from tpsr_ros.io.bag import BagReader, BagWriter, check_bag_path_free
from tpsr_ros.io.filter_inputs import check_policy
from tpsr_ros.io.model_io import ModelFile, check_output_path, open_model
from tpsr_ros.io.policy import Policy, load_policy
from tpsr_ros.io.view_messages import (
    DECODED_POSE_TOPIC,
    MARKERS_TYPE,
    PREDICTED_IMAGE_TOPIC,
    STATE_MARKERS_TOPIC,
    ViewSettings,
    view_messages,
)
from tpsr_ros.runtime.transport import pad_cdr

__all__ = ["register", "run", "write_states"]

FORMATS = (".csv", ".npz")


def register(subparsers: Any) -> None:
    """Add the ``track`` subcommand."""
    doc = "write the states a model tracks over bags (the filter node's reference)"
    parser = subparsers.add_parser(
        "track", help=doc, description=doc[0].upper() + doc[1:] + ". " + __doc__.split("\n\n")[2]
    )
    parser.add_argument("model", type=Path, metavar="MODEL", help="model file (.npz)")
    parser.add_argument("bags", nargs="+", type=Path, metavar="BAG", help="rosbag2 MCAP bag(s)")
    parser.add_argument(
        "-o", "--output", type=Path, metavar="STATES",
        help="states file to write: .csv or .npz",
    )  # fmt: skip
    parser.add_argument(
        "--mcap", type=Path, metavar="VIEW_BAG",
        help="also write a new MCAP bag of the camera and the filter node's view topics",
    )  # fmt: skip
    parser.add_argument(
        "--policy", type=Path, metavar="POLICY",
        help="with --mcap: the model's policy (predicted images after its greedy action, and "
        "its action values), as the filter node has it",
    )  # fmt: skip
    parser.add_argument(
        "--view-trail", type=positive_int, default=ViewSettings.trail, metavar="N",
        help="with --mcap: states in the markers' trail (the filter node's view_trail; "
        "default %(default)s)",
    )  # fmt: skip
    swap = parser.add_argument_group(
        "a model swap (the filter node's, offline: msgs_doc/filter_node.md, Model swaps)"
    )
    swap.add_argument(
        "--swap-at", type=int, metavar="STAMP_NS",
        help="track with --swap-model from the first step stamped at or after STAMP_NS",
    )  # fmt: skip
    swap.add_argument("--swap-model", type=Path, metavar="MODEL", help="the model swapped in")
    swap.add_argument(
        "--swap-state", choices=SWAP_STATES, default="replay",
        help="its state: the last --swap-replay-steps re-filtered, or b_* (default %(default)s)",
    )  # fmt: skip
    swap.add_argument(
        "--swap-replay-steps", type=positive_int, default=20, metavar="N",
        help="steps re-filtered at the swap (default %(default)s)",
    )  # fmt: skip
    parser.add_argument("--force", action="store_true", help="overwrite an existing STATES")
    add_topic_options(parser.add_argument_group("topics"))
    parser.set_defaults(run=run)


POSE_COLUMNS = ("x", "y", "cos_heading", "sin_heading")
"""CSV columns of the ground truth: the position, and the heading of a robot that turns."""


def write_states(
    path: Path,
    stamps: np.ndarray,
    states: np.ndarray,
    recovered: np.ndarray,
    positions: np.ndarray | None,
) -> None:
    """Write the states as ``.csv`` or ``.npz`` (module docstring), atomically."""
    if path.suffix == ".npz":
        arrays = {"stamp_ns": stamps, "states": states, "recovered": recovered}
        if positions is not None:
            arrays["positions"] = positions
        buffer = io.BytesIO()
        np.savez(buffer, **arrays)
        with atomic_file(path, "wb") as handle:
            handle.write(buffer.getvalue())
        return
    columns = ["stamp_ns", *(f"b{i}" for i in range(states.shape[1]))]
    values = [states]
    if positions is not None:
        columns += list(POSE_COLUMNS[: positions.shape[1]])
        values.append(positions)
    table = np.concatenate(values, axis=1)
    with atomic_file(path, "w") as handle:
        handle.write(",".join(columns) + "\n")
        for stamp, row in zip(stamps.tolist(), table, strict=True):
            handle.write(f"{stamp}," + ",".join(format(v, ".17g") for v in row) + "\n")


def run(args: argparse.Namespace) -> int:
    """Read, track, write; say how many steps and restarts."""
    if args.output is None and args.mcap is None:
        raise ConfigError("give -o STATES (.csv or .npz), --mcap VIEW_BAG, or both")
    if (args.swap_at is None) != (args.swap_model is None):
        raise ConfigError("a swap needs both --swap-at STAMP_NS and --swap-model MODEL")
    if args.swap_at is not None and args.mcap is not None:
        raise ConfigError("--mcap writes one model's view: drop --swap-at or --mcap")
    if args.policy is not None and args.mcap is None:
        raise ConfigError("--policy shapes the view topics only: add --mcap VIEW_BAG")
    if args.output is not None and args.output.suffix not in FORMATS:
        raise ConfigError(f"--output {str(args.output)!r}: write a .csv or .npz file")
    output = None if args.output is None else check_output_path(args.output, force=args.force)
    if args.mcap is not None:
        check_bag_path_free(args.mcap)
    require_given_topics(args.bags, args)
    model_file = open_model(args.model)
    policy = None
    if args.policy is not None:
        policy = load_policy(args.policy)
        check_policy(policy, model_file, str(args.policy))
    if args.mcap is not None and model_file.view is None:
        raise ConfigError(
            f"model {str(args.model)!r} has no viewer read-outs (written before them): refit "
            "it with `learner fit` to write the view topics"
        )
    trajectory = read_for_model(model_file, args.bags, args)
    if args.swap_at is not None:
        tracked = _swapped(args, model_file, trajectory)
    else:
        tracked = track_trajectory(model_file.model, trajectory)
    if model_file.spec is not None:  # a robot model: the filter node's far_commands
        print(f"learner track: {far_commands_line(trajectory, model_file.spec)}", file=sys.stderr)
    positions = trajectory.positions
    has_pose = positions is not None and bool(np.isfinite(positions).any())
    written = []
    if output is not None:
        write_states(
            output,
            np.asarray(trajectory.stamps, dtype=np.int64),
            tracked.states,
            np.asarray(tracked.recovered, dtype=bool),
            positions if has_pose else None,
        )
        written.append(str(output))
    if args.mcap is not None:
        spec, topics = model_file.spec, topics_from_args(args)
        copied = [spec.image_topic if spec is not None else topics.image]
        pose_topic = getattr(args, "pose_topic", None) or (
            recorded_topic(model_file.metadata, "pose") if spec is not None else topics.pose
        )
        if pose_topic:
            copied.append(pose_topic)
        write_view_bag(
            args.mcap, model_file, args.bags, copied, trajectory, tracked, policy,
            ViewSettings(trail=args.view_trail),
        )  # fmt: skip
        written.append(f"{args.mcap} (the camera, the ground truth and the view topics)")
    print(
        f"wrote {' and '.join(written)}: {len(trajectory)} steps in "
        f"{len(trajectory.segment_bounds())} segment(s), {int(np.sum(tracked.recovered))} "
        "normaliser recoveries",
        file=sys.stderr,
    )
    return 0


def _swapped(args: argparse.Namespace, model_file: ModelFile, trajectory: Trajectory) -> Track:
    """The states of the trajectory with the swap the options ask for, as the filter node
    tracks them (:func:`~tpsr_ros.core.online.track_with_swap`)."""
    second = open_model(args.swap_model)
    if second.model.obs_size != model_file.model.obs_size or (
        second.model.n_actions != model_file.model.n_actions
    ):
        raise ConfigError(f"--swap-model {args.swap_model} reads other observations or actions")
    spec = model_file.spec
    step_ns = int(spec.grid.step_ns) if spec is not None else STEP_NS
    steps = list(
        zip(trajectory.stamps.tolist(), trajectory.actions.tolist(), trajectory.observations,
            strict=True)
    )  # fmt: skip
    replay = args.swap_replay_steps if args.swap_state == "replay" else 0
    return track_with_swap(
        model_file.model, second.model, steps, args.swap_at, step_ns=step_ns, replay_steps=replay
    )


def _view_records(
    model_file: ModelFile,
    trajectory: Trajectory,
    tracked: Track,
    policy: Policy | None,
    settings: ViewSettings,
) -> Iterator[tuple[int, int, str, bytes]]:
    """``(stamp, order, topic, cdr)`` of the view topics, step by step, as the filter node
    publishes them (the state, then the markers, the predicted image and the pose)."""
    viewer = view_messages(model_file, settings)
    assert viewer is not None
    state_cdr = m.StateEncoder(model_file.model.state_dim)
    order = 0
    for stamp, state, observation in zip(
        trajectory.stamps.tolist(), tracked.states, trajectory.observations, strict=True
    ):
        q_values = None if policy is None else policy.q.values(state)[0]
        view = viewer.step(stamp, state, observation, q_values)
        records = [("/tpsr/state", state_cdr(stamp, state))]
        records += [("/" + STATE_MARKERS_TOPIC, markers) for markers in view.markers]
        records.append(("/" + PREDICTED_IMAGE_TOPIC, view.predicted_image))
        if view.decoded_pose is not None:
            records.append(("/" + DECODED_POSE_TOPIC, view.decoded_pose))
        for topic, data in records:  # as every transport delivers them: padded to 4 bytes
            yield stamp, order, topic, pad_cdr(data)
            order += 1


def _copied_records(
    bags: list[Path], topics: list[str]
) -> Iterator[tuple[int, int, str, bytes]]:
    """``(log time, -1, topic, cdr)`` of every message on ``topics``, bag by bag."""
    for bag in bags:
        with BagReader(bag) as reader:
            present = [topic for topic in topics if topic in reader.topics_with_messages]
            for topic, log_time, data in reader.raw_messages(present):
                yield log_time, -1, topic, data


def write_view_bag(
    path: Path,
    model_file: ModelFile,
    bags: list[Path],
    copied: list[str],
    trajectory: Trajectory,
    tracked: Track,
    policy: Policy | None,
    settings: ViewSettings | None = None,
) -> None:
    """The view topics of the tracked steps and the bags' messages on ``copied`` (the
    camera first; the ground truth where a bag has it) in a new MCAP bag at ``path``, in
    time order (a camera message before the step of its stamp)."""
    types: dict[str, str] = {}
    for bag in bags:
        with BagReader(bag) as reader:
            for topic in copied:
                msgtype = reader.topics_with_messages.get(topic)
                if msgtype is not None and types.setdefault(topic, msgtype) != msgtype:
                    raise ConfigError(f"{topic} has type {msgtype} in {bag}, {types[topic]} before")
    if copied[0] not in types:
        raise ConfigError(f"the bags have no messages on the camera topic {copied[0]}")
    present = list(types)
    assert model_file.view is not None
    types |= {
        "/tpsr/state": m.STATE_TYPE,
        "/" + STATE_MARKERS_TOPIC: MARKERS_TYPE,
        "/" + PREDICTED_IMAGE_TOPIC: m.IMAGE_TYPE,
    }
    if model_file.view.pose is not None:
        types["/" + DECODED_POSE_TOPIC] = m.POSE_TYPE
    records = heapq.merge(
        _copied_records(bags, present),
        _view_records(model_file, trajectory, tracked, policy, settings or ViewSettings()),
        key=lambda record: (record[0], record[1]),
    )
    with BagWriter(path) as writer:
        for topic, msgtype in types.items():
            writer.add_topic(topic, msgtype)
        for stamp, _, topic, data in records:
            writer.write(topic, stamp, data)
