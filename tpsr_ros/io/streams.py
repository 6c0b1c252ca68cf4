"""What a model reads from a robot, and reading it from bags onto the step grid.

A :class:`StreamSpec` is everything a model learned with ``learner fit --step-period``
remembers about its inputs (stored in the model metadata under ``"input"``): camera topic
and type, the preprocessing (:mod:`tpsr_ros.core.images`), command topic and type, the
action codebook (:mod:`tpsr_ros.core.codebook`) and the step grid
(:mod:`tpsr_ros.core.resample`). ``learner plot``, ``learner policy`` and the filter node
take it from the model; a bag or stream that does not fit it is refused with the reason.

:func:`read_stream_trajectory` reads bags with a spec: images (``Image`` in any supported
encoding or ``CompressedImage``; time = header stamp, or log time where the stamp is zero),
commands (``TwistStamped``: header stamp; unstamped: the stamp of the next image in the
bag's order), optional ground truth (``PoseStamped``, ``Odometry``,
``TransformStamped``, ``PoseWithCovarianceStamped``, or ``tf2_msgs/TFMessage`` (``/tf``:
the transforms whose child frame is ``pose_frame``); interpolated at the step times) and
reward (``Float32``, ``Float64``, ``Bool`` or the simulator's ``JointState``:
:mod:`tpsr_ros.io.reward_messages`; a step earns the sum of the rewards timed within it,
0 if none, :func:`tpsr_ros.core.rewards.step_reward_sums`; NaN throughout where the bag
has no reward topic).
:func:`fit_stream_spec` first makes the spec from the training bags (camera period,
constant command components, k-means codebook). Both read each bag's timed streams
(:func:`read_bag_streams`: stamps and commands, images not decoded); ``learner fit`` reads
them once and gives them to both.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.core.codebook import (
    COMPONENTS,
    DEFAULT_COMPONENTS,
    sim_codebook,
)
from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import ConfigError, DataError, MessageError
from tpsr_ros.core.images import Preprocessing
from tpsr_ros.core.resample import GridConfig, choose_phase, resample_grid
from tpsr_ros.core.rewards import step_reward_sums
from tpsr_ros.core.units import NS_PER_S
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.bag_streams import (
    DEFAULT_POSE_FRAME,
    POSE_TYPES,
    TF_TYPE,
    BagStreams,
    pose_planar,
    read_bag_streams,
    where,
)
from tpsr_ros.io.cdr_fields import RawImageDecoder
from tpsr_ros.io.images import IMAGE_TYPE, decode_image
from tpsr_ros.io.images import image_observations as _observations
from tpsr_ros.io.messages import (
    deserialize,
)
from tpsr_ros.io.stream_defaults import (
    check_image_size,
    default_action_count,
    default_image_size,
    grid_step_count,
    supported_codebook,
)
from tpsr_ros.io.stream_spec import COMMAND_TYPES, TWIST_TYPE, StreamSpec

__all__ = [
    "COMMAND_TYPES",
    "DEFAULT_POSE_FRAME",
    "POSE_TYPES",
    "TF_TYPE",
    "BagStreams",
    "FitOptions",
    "StreamSpec",
    "fit_stream_spec",
    "read_bag_streams",
    "read_stream_trajectory",
]

MIN_FRESH_FRACTION = 0.5
"""Fewer grid steps with a new image than this fraction: the step period is refused."""
CHUNK_IMAGES = 512
TIMEOUT_PERCENTILE = 95
"""The default image and command timeouts are at least twice this percentile of the
camera's and the commands' intervals: a jittery stream's long intervals are not silences."""


@dataclass(frozen=True)
class FitOptions:
    """What ``learner fit`` is told about the streams of robot bags."""

    step_period: float = field(metadata={"help": "s between steps"})
    image_size: tuple[int, int] | None = None
    """(height, width) of the observations; None: 16 px on the camera's longer side."""
    grey: bool | None = None
    """Grey observations; None: grey for a grey camera, colour otherwise."""
    components: tuple[str, ...] = DEFAULT_COMPONENTS
    actions: int | None = None
    """K of the k-means codebook; None: the simulator's 25 pairs for simulator bags, else one
    action per 60 steps (2 to 25) that the data support."""
    image_timeout: float | None = None
    """s; default: one step period, or twice the camera's 95th-percentile frame interval if
    longer (a jittery camera's long intervals are not silences)."""
    command_timeout: float | None = None
    """s; default: two step periods, or twice the commands' 95th-percentile interval if
    longer."""
    step_offset: float | None = None
    """s; step times are ``step_offset + k * step_period``; None: chosen from the data."""
    seed: int = 0

    def __post_init__(self) -> None:
        for name in ("step_period", "image_timeout", "command_timeout"):
            value = getattr(self, name)
            if value is not None and not (np.isfinite(value) and 1e-6 <= value <= 1e5):
                raise ConfigError(f"{name.replace('_', '-')} must be in [1e-6, 1e5] s, not {value}")
        if bad := [c for c in self.components if c not in COMPONENTS]:
            raise ConfigError(f"command components {bad} are not among {list(COMPONENTS)}")
        if not self.components or len(set(self.components)) != len(self.components):
            raise ConfigError(f"command components {list(self.components)} are empty or repeat")
        if self.actions is not None and not 1 <= self.actions <= 10_000:
            raise ConfigError(f"--actions must be 1..10000, not {self.actions}")
        if self.step_offset is not None and not np.isfinite(self.step_offset):
            raise ConfigError(f"--step-offset must be a finite number of s, not {self.step_offset}")


def _check_given(
    streams: Sequence[BagStreams],
    bags: Sequence[Path | str],
    components: Sequence[str],
    *,
    exact: bool,
) -> None:
    """Refuse streams not read from ``bags`` with ``components`` (``exact``) or more of them."""
    wanted = tuple(components)
    fits = (lambda got: got == wanted) if exact else (lambda got: set(wanted) <= set(got))
    if [s.path for s in streams] != [Path(b) for b in bags] or not all(
        fits(s.components) for s in streams
    ):
        raise ConfigError("the streams given were not read from these bags with these options")


def _poses_at(streams: BagStreams, at: np.ndarray) -> np.ndarray:
    """Ground truth ``(x, y, cos yaw, sin yaw)`` interpolated at ``at`` (NaN where none);
    only the poses around each time are decoded."""
    times = streams.pose_times
    if times.size == 0 or streams.pose_topic is None:
        return np.full((at.size, 4), np.nan)
    if streams.pose_values is not None:
        values = streams.pose_values
    else:
        after = np.clip(np.searchsorted(times, at, side="left"), 0, times.size - 1)
        needed = np.unique(np.concatenate([after, np.maximum(after - 1, 0)]))
        values = np.empty((needed.size, 4))
        for row, index in enumerate(needed.tolist()):
            try:
                msg = deserialize(streams.pose_data[index], streams.pose_type)
                values[row] = pose_planar(msg, streams.pose_type)
            except MessageError as exc:
                raise MessageError(
                    f"bag {str(streams.path)!r}, topic {streams.pose_topic!r}: {exc}"
                ) from None
        times = times[needed]
    return _interpolate(times, values, at)


def _planar_unless_turning(poses: np.ndarray) -> np.ndarray:
    """``poses`` ``(T, 4)`` as the learner's positions: ``(x, y)`` alone unless the robot
    turns (the heading's cosine or sine varies over the steps with a pose)."""
    known = poses[np.isfinite(poses).all(axis=1)]
    turns = known.size > 0 and float(np.ptp(known[:, 2:], axis=0).max()) > HEADING_TOLERANCE
    return poses if turns else poses[:, :2]


def _decode_images(
    path: Path, topic: str, msgtype: str, numbers: np.ndarray, preprocessing: Preprocessing
) -> np.ndarray:
    """Observations of the messages ``numbers`` (sorted message indices) of ``topic``.

    A message several steps share (no new image between them) is decoded once.
    """
    unique, inverse = np.unique(numbers, return_inverse=True)
    out = np.empty((unique.size, preprocessing.size))
    wanted = {int(n): i for i, n in enumerate(unique.tolist())}
    batch: list[np.ndarray] = []
    rows: list[int] = []

    def flush() -> None:
        out[rows] = _observations(batch, preprocessing)
        batch.clear()
        rows.clear()

    raw = RawImageDecoder() if msgtype == IMAGE_TYPE else None  # pixels straight from CDR
    with BagReader(path) as reader:
        for index, (_, _, data) in enumerate(reader.raw_messages([topic])):
            if index not in wanted:
                continue
            try:
                if raw is not None:
                    pixels = raw.decode(data)[1]
                else:
                    pixels = decode_image(deserialize(data, msgtype), msgtype)
                if pixels.shape[2] == 1 and not preprocessing.grey:
                    raise MessageError("a grey image cannot give the model's colour observations")
            except MessageError as exc:
                raise MessageError(f"{where(path, topic, index)}: {exc}") from None
            batch.append(pixels)
            rows.append(wanted[index])
            if len(batch) >= CHUNK_IMAGES:
                flush()
    if batch:
        flush()
    return out[inverse.reshape(-1)]


HEADING_TOLERANCE = 1e-6
"""Spread of a heading's cosine or sine below which the robot never turned."""


def _interpolate(times: np.ndarray, values: np.ndarray, at: np.ndarray) -> np.ndarray:
    """Linear interpolation per column; NaN outside the recorded times."""
    out = np.full((at.size, values.shape[1]), np.nan)
    if times.size == 0:
        return out
    inside = (at >= times[0]) & (at <= times[-1])
    for column in range(values.shape[1]):
        out[inside, column] = np.interp(at[inside], times, values[:, column])
    return out


def _step_rewards(streams: BagStreams, at: np.ndarray, step_ns: int) -> np.ndarray:
    """Each step's summed reward (:func:`~tpsr_ros.core.rewards.step_reward_sums`); NaN
    everywhere when the bag has no reward topic (unknown, not zero)."""
    if streams.reward_topic is None:
        return np.full(at.size, np.nan)
    return step_reward_sums(streams.reward_times, streams.rewards, at, step_ns)


# -- the spec of the training bags --------------------------------------------------------


def fit_stream_spec(
    bags: Sequence[Path | str],
    options: FitOptions,
    *,
    image_topic: str,
    action_topic: str,
    streams: Sequence[BagStreams] | None = None,
) -> StreamSpec:
    """The spec learned from the training bags: camera period, grid phase, components,
    codebook and observation size (defaults sized to the data: :mod:`.stream_defaults`).

    ``streams``: the bags' streams already read with ``options.components`` (else read here).
    """
    if streams is None:
        streams = read_bag_streams(
            bags, image_topic=image_topic, action_topic=action_topic,
            components=options.components,
        )  # fmt: skip
    else:
        _check_given(streams, bags, options.components, exact=True)
    types = {(s.image_type, s.action_type) for s in streams}
    if len(types) > 1:
        raise DataError(f"the bags carry different camera or command types: {sorted(types)}")
    gaps = np.concatenate([np.diff(s.image_times) for s in streams])
    if gaps.size == 0:
        raise DataError(f"the bags hold fewer than two images on {image_topic!r}")
    step_ns = round(options.step_period * NS_PER_S)
    if options.step_offset is None:
        phase = _phase_from_data(streams, step_ns)
    else:
        phase = round(options.step_offset * NS_PER_S) % step_ns
    grid = GridConfig(
        step_ns=step_ns,
        camera_period_ns=int(np.median(gaps)),
        image_timeout_ns=(
            round(options.image_timeout * NS_PER_S)
            if options.image_timeout is not None
            else max(step_ns, 2 * _interval_percentile([s.image_times for s in streams]))
        ),
        command_timeout_ns=(
            round(options.command_timeout * NS_PER_S)
            if options.command_timeout is not None
            else max(2 * step_ns, 2 * _interval_percentile([s.command_times for s in streams]))
        ),
        phase_ns=phase,
    )
    commands = np.concatenate([s.commands for s in streams])
    varying = tuple(c for i, c in enumerate(options.components) if np.ptp(commands[:, i]) > 0)
    if not varying:
        raise DataError(
            f"every command component {list(options.components)} on {action_topic!r} is "
            "constant: there is nothing to learn actions from"
        )
    columns = [options.components.index(c) for c in varying]
    environment = {s.environment for s in streams}
    if len(environment) > 1 and "drive" in environment:
        raise DataError(
            f"the bags come from different simulator environments {sorted(map(str, environment))}"
            ": drive's actions are not the others'"
        )
    if options.actions is None and None not in environment:
        codebook = sim_codebook(next(iter(environment)))
    else:
        default = options.actions is None
        count = (
            default_action_count(grid_step_count(streams, grid))
            if options.actions is None
            else options.actions
        )
        codebook = supported_codebook(
            streams, grid, varying, columns, count, options.seed, reduce=default
        )
    first = streams[0]
    shape = _first_pixels(first, image_topic).shape
    grey = shape[2] == 1 if options.grey is None else options.grey
    if options.image_size is None:
        height, width = default_image_size(shape[:2])
    else:
        check_image_size(options.image_size, shape[:2])
        height, width = options.image_size
    return StreamSpec(
        image_topic=image_topic,
        image_type=first.image_type,
        action_topic=action_topic,
        action_type=first.action_type,
        preprocessing=Preprocessing(height, width, bool(grey)),
        codebook=codebook,
        grid=grid,
    )


def _interval_percentile(times: Sequence[np.ndarray]) -> int:
    """The :data:`TIMEOUT_PERCENTILE` of the intervals of each bag's ``times`` (0 if none)."""
    gaps = np.concatenate([np.diff(t) for t in times])
    return int(np.percentile(gaps, TIMEOUT_PERCENTILE)) if gaps.size else 0


def _phase_from_data(streams: Sequence[BagStreams], step_ns: int) -> int:
    """:func:`~tpsr_ros.core.resample.choose_phase` over image stamps and command times; an
    unstamped command spans from its log time to the image that dates it."""
    starts, spans = [], []
    for bag in streams:
        starts.append(bag.image_times)
        spans.append(np.zeros(bag.image_times.size))
        unstamped = bag.action_type == TWIST_TYPE
        logs = bag.command_log_times if unstamped else bag.command_times
        starts.append(np.minimum(logs, bag.command_times))
        spans.append(np.abs(bag.command_times - logs).astype(np.float64))
    return choose_phase(np.concatenate(starts), step_ns, np.concatenate(spans))


def _first_pixels(streams: BagStreams, topic: str) -> np.ndarray:
    """Decoded pixels of the first image kept on ``topic`` (its size and colour)."""
    first = int(streams.image_numbers[0]) if streams.image_numbers.size else 0
    with BagReader(streams.path) as reader:
        for index, (_, _, data) in enumerate(reader.raw_messages([topic])):
            if index == first:
                try:
                    return decode_image(deserialize(data, streams.image_type), streams.image_type)
                except MessageError as exc:
                    raise MessageError(f"{where(streams.path, topic, index)}: {exc}") from None
    raise DataError(f"bag {str(streams.path)!r} has no image on {topic!r}")


def read_stream_trajectory(
    bags: Sequence[Path | str],
    spec: StreamSpec,
    *,
    pose_topic: str | None = None,
    reward_topic: str | None = None,
    require_ground_truth: bool = False,
    pose_frame: str = DEFAULT_POSE_FRAME,
    streams: Sequence[BagStreams] | None = None,
) -> Trajectory:
    """Read ``bags`` onto the spec's step grid (see the module docstring and core.resample).

    Every bag starts its own grid and segments. ``require_ground_truth`` demands the pose
    topic. Refused with a one-line error: a camera or command topic missing or of another
    type than the spec's, an undecodable or inconsistent message, a step period at which
    most steps have no new image, a bag with no usable step. ``streams``: the bags' streams
    already read (:func:`read_bag_streams`, with the same pose and reward topics and
    components that include the codebook's), else read here.
    """
    if not bags:
        raise ConfigError("no bag given")
    codebook = spec.codebook
    if streams is None:
        streams = read_bag_streams(
            bags, image_topic=spec.image_topic, action_topic=spec.action_topic,
            components=codebook.components, pose_topic=pose_topic, reward_topic=reward_topic,
            require_pose=require_ground_truth, pose_frame=pose_frame,
        )  # fmt: skip
    else:
        _check_given(streams, bags, codebook.components, exact=False)
    parts: list[dict[str, np.ndarray]] = []
    sources: list[dict[str, Any]] = []
    segment_offset = 0
    for bag in streams:
        path = bag.path
        for what, got, expected in (
            ("camera", bag.image_type, spec.image_type),
            ("command", bag.action_type, spec.action_type),
        ):
            if got != expected:
                raise DataError(
                    f"bag {str(path)!r}: the model's {what} topic carries {expected}, this bag's "
                    f"carries {got}"
                )
        if codebook.kind == "sim" and bag.environment is None:
            raise DataError(
                f"bag {str(path)!r} does not come from sim_node, but the model's actions are "
                "the simulator's"
            )
        steps = resample_grid(bag.image_times, bag.command_times, spec.grid)
        period = spec.grid.step_ns / NS_PER_S
        if steps.grid_steps == 0 or steps.fresh < MIN_FRESH_FRACTION * steps.grid_steps:
            raise DataError(
                f"bag {str(path)!r}, topic {spec.image_topic!r}: only {steps.fresh} of "
                f"{steps.grid_steps} steps of {period:g} s have a new image (the camera's "
                f"median period is {_median_period(bag.image_times):g} s); use a longer "
                "--step-period"
            )
        if steps.stamps.size == 0:
            raise DataError(
                f"bag {str(path)!r}: no step of {period:g} s has both an image and a command in "
                f"force ({steps.stale_image} camera gaps, {steps.no_command} without a command "
                f"on {spec.action_topic!r})"
            )
        columns = [bag.components.index(c) for c in codebook.components]
        commands = bag.commands[steps.command_index][:, columns]
        actions, distance = codebook.assign(commands)
        observations = _decode_images(
            path,
            spec.image_topic,
            spec.image_type,
            bag.image_numbers[steps.image_index],
            spec.preprocessing,
        )
        positions = _poses_at(bag, steps.stamps)
        if require_ground_truth and np.isnan(positions).all():
            raise DataError(
                f"bag {str(path)!r}: the poses on {pose_topic!r} cover none of the steps"
            )
        rewards = _step_rewards(bag, steps.stamps, spec.grid.step_ns)
        breaks = np.diff(steps.stamps) != spec.grid.step_ns
        segments = segment_offset + np.concatenate([[0], np.cumsum(breaks)])
        segment_offset = int(segments[-1]) + 1
        # far commands per command message put in force (dated), as the filter node counts
        # them, not per step: a step holds the command in force, which may be held over
        _, message_distance = codebook.assign(bag.commands[:, columns])
        far = message_distance > codebook.far_distance
        parts.append(
            {
                "stamps": steps.stamps,
                "observations": observations,
                "actions": actions,
                "velocities": commands,
                "positions": positions,
                "rewards": rewards,
                "segments": segments.astype(np.int64),
            }
        )
        camera = _first_pixels(bag, spec.image_topic).shape
        sources.append(
            {
                "path": str(path),
                "camera": {"height": int(camera[0]), "width": int(camera[1])},
                "steps": int(steps.stamps.size),
                "segments": int(breaks.sum()) + 1,
                "grid_steps": steps.grid_steps,
                "camera_gaps": steps.stale_image,
                "command_gaps": steps.no_command,
                "images_out_of_order": bag.dropped_images,
                "command_messages": int(far.size),
                "far_commands": int(far.sum()),
                "worst_command_distance": float(message_distance.max(initial=0.0)),
                "stamps_ns": [int(steps.stamps[0]), int(steps.stamps[-1])],
                "environment": bag.environment,
                "generator": None,
                "topics": {
                    "image": spec.image_topic,
                    "action": spec.action_topic,
                    "pose": pose_topic,
                    "pose_frame": pose_frame,
                    "reward": reward_topic,
                },
            }
        )
    merged = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    merged["positions"] = _planar_unless_turning(merged["positions"])
    prep = spec.preprocessing
    return Trajectory(
        **merged,
        image_shape=(prep.height, prep.width),
        n_actions=len(codebook),
        sources=sources,
    )


def _median_period(times: np.ndarray) -> float:
    return float(np.median(np.diff(times))) / NS_PER_S if times.size > 1 else float("nan")
