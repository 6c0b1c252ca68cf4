"""Trajectories read from rosbag2 bags: the bag side of :mod:`tpsr_ros.core.episodes`.

A *step* is one image and one action carrying the identical header stamp (DESIGN.md: step
k's messages are all stamped t_k; the log time is ignored). Steps are sorted by stamp and
split into *segments* of consecutive stamps (exactly ``step_ns`` apart): a gap, a step whose
image or action is missing, and a bag boundary each end a segment. The pure part (the
:class:`~tpsr_ros.core.episodes.Trajectory` and how it is cut into episodes) is in
:mod:`tpsr_ros.core.episodes`.

Bags are read as a stream, in log-time order, so memory does not grow with their length
(:func:`iter_trajectory_chunks`; :func:`read_trajectory` is its chunks concatenated).
Messages are decoded straight from their CDR bytes (:mod:`tpsr_ros.io.cdr_fields`). A
step's messages need not be adjacent in the file: each stamp waits, with whatever of its
image, action, pose and reward has arrived, until ``reorder_window`` (default
:data:`REORDER_WINDOW`) later distinct stamps of the four topics have been read; then it
is final, a step if it has an image and an action. So a bag may be out of stamp order as
long as no message comes after messages of ``reorder_window`` later stamps; one whose
stamp is already final may be refused with a ``BagError`` naming it (it cannot be placed:
the steps before it may already be handed out). Memory is bounded by the pending stamps'
message bytes plus one chunk: both are capped in bytes (:data:`PENDING_BYTES`,
:data:`CHUNK_BYTES`), so large images get a shorter window and smaller chunks.

Live streams are paired the same way (:class:`StampPairing`, the decoders, the conversion
of :func:`entry_steps`): :class:`LiveSteps` takes a simulator's messages as they arrive (the
learner node) and gives the trajectory a recording of them would give.
"""

from __future__ import annotations

import heapq
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from tpsr_ros.core.actions import ActionGrid, environment_grid
from tpsr_ros.core.episodes import (
    DEFAULT_ACTION_TOLERANCE,
    DEFAULT_IMAGE_SHAPE,
    STEP_NS,
    Trajectory,
    images_to_observations,
)
from tpsr_ros.core.errors import BagError, ConfigError, DataError, MessageError
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.cdr_fields import (
    ImageDecoder,
    PoseDecoder,
    RewardDecoder,
    TwistDecoder,
)
from tpsr_ros.io.messages import ACTION_TYPE, IMAGE_TYPE, POSE_TYPE, REWARD_TYPE, peek_stamp

__all__ = [
    "DEFAULT_CHUNK_STEPS",
    "REORDER_WINDOW",
    "LateMessage",
    "LiveSteps",
    "RepeatedMessage",
    "StampPairing",
    "StepChunk",
    "Topics",
    "iter_trajectory_chunks",
    "read_trajectory",
]

DEFAULT_CHUNK_STEPS = 8192
"""Steps per chunk of :func:`iter_trajectory_chunks` (16x16 images: 50 MB of observations)."""
REORDER_WINDOW = 4096
"""Distinct stamps (over the four topics) a message may trail in a bag (module docstring):
4096 steps of 1 s when only images and actions are stamped; pending messages of 16x16
images take about 4 MB."""
CHUNK_BYTES = 128 * 2**20
"""Float64 observations of one chunk at most: a chunk has at most this many bytes' worth of
steps (16x16 images: 21 845, above the default 8192; 640x480: 18)."""
PENDING_BYTES = 256 * 2**20
"""Image bytes waiting to be paired at most: the window is at most this many bytes' worth of
stamps (16x16 images: 349 525, above the default 4096; 640x480: 291)."""


@dataclass(frozen=True)
class Topics:
    """Topic names read from bags (defaults from DESIGN.md)."""

    image: str = field(default="/camera/image_raw", metadata={"help": "camera image topic"})
    action: str = field(
        default="/action",
        metadata={"help": "executed action topic (TwistStamped; Twist too with --step-period)"},
    )
    pose: str = field(
        default="/ground_truth/pose",
        metadata={
            "help": "ground-truth pose topic (PoseStamped; with --step-period also Odometry, "
            "TransformStamped, PoseWithCovarianceStamped)"
        },
    )
    reward: str = field(default="/reward", metadata={"help": "reward topic"})

    def types(self) -> dict[str, str]:
        """Topic name to expected ROS type."""
        return {
            self.image: IMAGE_TYPE,
            self.action: ACTION_TYPE,
            self.pose: POSE_TYPE,
            self.reward: REWARD_TYPE,
        }


def bag_custom_data(reader: BagReader) -> tuple[str | None, Any]:
    """Environment name and generator settings that ``sim_node.generate`` stores in a bag."""
    custom = getattr(reader, "custom_data", None)
    if not isinstance(custom, dict):
        return None, None
    env = custom.get("tpsr_ros.environment")
    try:
        generator = json.loads(custom["tpsr_ros.generator"])
    except (KeyError, TypeError, ValueError):
        generator = None
    except RecursionError:  # e.g. 5000 nested '[': hostile, not merely malformed
        raise BagError(
            f"bag {str(reader.path)!r}: custom_data 'tpsr_ros.generator' is nested too deeply "
            "to be the generator's settings"
        ) from None
    return (str(env) if env else None), generator


def generated_vertical_half_extent(generator: Any) -> float | None:
    """The camera's vertical half-extent that a generated bag's settings record (None when
    the bag records none: a robot's bag, or settings not from ``sim_node.generate``)."""
    config = generator.get("config") if isinstance(generator, dict) else None
    value = config.get("vertical_half_extent") if isinstance(config, dict) else None
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    return float(value) if np.isfinite(value) and value > 0 else None


@dataclass(frozen=True)
class _Options:
    topics: Topics
    step_ns: int
    action_tolerance: float
    require_ground_truth: bool
    chunk_steps: int
    reorder_window: int
    environment: str | None = None  # of bags that do not say theirs (the model's)


@dataclass(frozen=True)
class StepChunk:
    """Consecutive steps of one bag or live stream, with pixels still uint8 (a chunk before
    conversion to observations)."""

    stamps: np.ndarray  # (n,) int64
    pixels: np.ndarray  # (n, H, W, 3) uint8
    actions: np.ndarray  # (n,) int64
    velocities: np.ndarray  # (n, 2): the commands' two grid components
    positions: np.ndarray  # (n, 2), drive (n, 4) with the heading's cos, sin; NaN: no pose
    rewards: np.ndarray  # (n,), NaN where no reward
    segments: np.ndarray  # (n,) int64, numbered over all bags
    source: dict[str, Any] | None  # the bag's source dict on its last chunk only
    n_actions: int  # of the bag's action grid

    def trajectory(self) -> Trajectory:
        """The steps as a trajectory (pixels converted to observations)."""
        return _trajectory([self])


def _trajectory(parts: Sequence[StepChunk]) -> Trajectory:
    """One trajectory of ``parts`` in order (pixels converted once, after concatenating)."""

    def joined(name: str) -> np.ndarray:
        arrays = [getattr(p, name) for p in parts]
        return arrays[0] if len(arrays) == 1 else np.concatenate(arrays)

    pixels = joined("pixels")
    if len({(p.n_actions, p.positions.shape[1]) for p in parts}) > 1:
        raise DataError(
            "the bags come from simulators with different actions (drive and a planar "
            "environment): learn from one kind at a time"
        )
    return Trajectory(
        stamps=joined("stamps"),
        observations=images_to_observations(pixels),
        actions=joined("actions"),
        velocities=joined("velocities"),
        positions=joined("positions"),
        rewards=joined("rewards"),
        segments=joined("segments"),
        image_shape=(int(pixels.shape[1]), int(pixels.shape[2])),
        n_actions=parts[0].n_actions,
        sources=[p.source for p in parts if p.source is not None],
    )


_IMAGE, _ACTION, _POSE, _REWARD = range(4)


class LateMessage(Exception):
    """A message whose stamp is already final (it cannot join its step any more)."""


class RepeatedMessage(Exception):
    """A second message of one kind with a stamp that already has one."""


class StampPairing:
    """A step's image, action, pose and reward paired by identical stamp as they stream past.

    Stamps wait, with whatever of their four messages has arrived, until more than
    ``window`` later stamps are pending; then the smallest becomes final (one per new
    stamp). :meth:`add` returns the entries made final, ``(stamp, [image, action, pose,
    reward])`` with None for what never came; :meth:`flush` makes every pending stamp final.
    """

    def __init__(self, window: int) -> None:
        self.window = int(window)
        self._pending: dict[int, list[Any]] = {}
        self._heap: list[int] = []
        self.final = -(2**63)
        """The largest stamp made final."""

    @property
    def pending(self) -> int:
        """Stamps waiting."""
        return len(self._heap)

    def add(self, kind: int, stamp: int, value: Any) -> list[tuple[int, list[Any]]]:
        """Pair one message (``kind``: image 0, action 1, pose 2, reward 3); raise
        :class:`LateMessage` or :class:`RepeatedMessage` for one that cannot be paired."""
        entry = self._pending.get(stamp)
        if entry is None:
            if stamp <= self.final:
                raise LateMessage(stamp)
            entry = self._pending[stamp] = [None, None, None, None]
            entry[kind] = value
            heapq.heappush(self._heap, stamp)
            if len(self._heap) > self.window:
                self.final = heapq.heappop(self._heap)
                return [(self.final, self._pending.pop(self.final))]
            return []
        if entry[kind] is not None:
            raise RepeatedMessage(stamp)
        entry[kind] = value
        return []

    def flush(self) -> list[tuple[int, list[Any]]]:
        """Every pending stamp, made final in stamp order."""
        finals = []
        while self._heap:
            self.final = heapq.heappop(self._heap)
            finals.append((self.final, self._pending.pop(self.final)))
        return finals


@dataclass(frozen=True)
class StepLayout:
    """How final entries become arrays: image size, pose width, step period, action grid."""

    image_shape: tuple[int, int]
    pose_width: int
    step_ns: int
    grid: ActionGrid
    action_tolerance: float


def entry_steps(
    buffer: Sequence[tuple[int, list[Any]]],
    layout: StepLayout,
    last_stamp: int | None,
    segment: int,
) -> StepChunk:
    """Steps of final entries (each with an image and an action), their segments numbered
    after ``segment``, a new one where a stamp is not ``step_ns`` after the one before
    (``last_stamp``: the step before the first; None: a new segment). Raises the grid's
    ``ConfigError`` for an action off the grid."""
    count = len(buffer)
    stamps = np.fromiter((s for s, _ in buffer), dtype=np.int64, count=count)
    entries = [e for _, e in buffer]
    height, width = layout.image_shape
    pixels = np.frombuffer(b"".join(e[_IMAGE] for e in entries), dtype=np.uint8)
    velocities = np.array([e[_ACTION] for e in entries], dtype=np.float64).reshape(count, 2)
    no_pose = (np.nan,) * layout.pose_width
    positions = np.array(
        [no_pose if e[_POSE] is None else e[_POSE] for e in entries], dtype=np.float64
    ).reshape(count, layout.pose_width)
    rewards = np.array(
        [np.nan if e[_REWARD] is None else e[_REWARD] for e in entries], dtype=np.float64
    )
    breaks = np.empty(count, dtype=bool)
    breaks[0] = last_stamp is None or stamps[0] - last_stamp != layout.step_ns
    breaks[1:] = np.diff(stamps) != layout.step_ns
    segments = segment + np.cumsum(breaks, dtype=np.int64)
    actions = layout.grid.indices(velocities, layout.action_tolerance)
    return StepChunk(
        stamps=stamps,
        pixels=pixels.reshape(count, height, width, 3),
        actions=actions,
        velocities=velocities,
        positions=positions,
        rewards=rewards,
        segments=segments,
        source=None,
        n_actions=len(layout.grid),
    )


class _BagSteps:
    """The steps of one bag, paired by stamp as its messages stream past (module docstring).

    ``pending`` holds the stamps read but not yet final, each with its image, velocity,
    pose and reward as they arrive; when more than ``reorder_window`` stamps are pending
    the smallest becomes final: a step if it has an image and an action, otherwise its
    messages are unpaired. Final steps collect in a buffer that is handed out as a chunk
    of ``chunk_steps`` when the next step arrives (or when the bag ends, with its source).
    """

    def __init__(self, path: Path, images: ImageDecoder, options: _Options, segment: int):
        self.path = path
        self.options = options
        self.images = images
        self.first_segment = segment
        self.segment = segment - 1  # of the last step handed out
        self.last_stamp: int | None = None
        self.steps = 0
        self.first_stamp = 0
        self.buffer: list[tuple[int, list[Any]]] = []
        self.chunk_limit = options.chunk_steps  # capped in bytes once the image size is known

    def chunks(self) -> Iterator[StepChunk]:
        """The bag's steps in stamp order, ``chunk_steps`` at a time."""
        topics = self.options.topics
        with BagReader(self.path) as reader:
            present = self._check_topics(reader)
            environment, generator = bag_custom_data(reader)
            given = self.options.environment
            if environment is None:
                environment = given
            elif given is not None and environment != given and "drive" in (environment, given):
                raise DataError(
                    f"bag {str(self.path)!r} comes from environment {environment!r}, whose "
                    f"actions are not those of {given!r}"
                )
            drives = environment == "drive"  # the robot that turns: its own actions, a heading
            self.grid = environment_grid(environment)
            self.pose_width = 4 if drives else 2
            decoders = {
                topics.image: (_IMAGE, self.images),
                topics.action: (_ACTION, TwistDecoder(self.grid.components)),
                topics.pose: (_POSE, PoseDecoder(heading=drives)),
                topics.reward: (_REWARD, RewardDecoder()),
            }
            pairing = StampPairing(self.options.reorder_window)  # until the image size is known
            counts = [0, 0, 0, 0]
            for topic, _, data in reader.raw_messages(present):
                kind, decoder = decoders[topic]
                try:
                    stamp, value = decoder.decode(data)
                except MessageError as exc:
                    raise self._bad_message(topic, counts[kind], data, exc) from None
                counts[kind] += 1
                if kind == _IMAGE and counts[_IMAGE] == 1:
                    pairing.window, self.chunk_limit = self._window(), self._chunk_steps()
                try:
                    finals = pairing.add(kind, stamp, value)
                except LateMessage:
                    raise self._too_late(topic, counts[kind] - 1, stamp, pairing.window) from None
                except RepeatedMessage:
                    raise BagError(
                        f"bag {str(self.path)!r}, topic {topic!r}, message {counts[kind] - 1}: "
                        f"a second message with stamp {stamp} ns"
                    ) from None
                for final, entry in finals:
                    if (chunk := self._finish(final, entry)) is not None:
                        yield chunk
            for final, entry in pairing.flush():
                if (chunk := self._finish(final, entry)) is not None:
                    yield chunk
        if not self.buffer:
            raise DataError(
                f"bag {str(self.path)!r} has no image and action with the same stamp "
                f"({counts[_IMAGE]} images, {counts[_ACTION]} actions)"
            )
        last = self._take()
        source = {
            "path": str(self.path),
            "steps": self.steps,
            "segments": self.segment - self.first_segment + 1,
            "unpaired_messages": counts[_IMAGE] + counts[_ACTION] - 2 * self.steps,
            "stamps_ns": [self.first_stamp, int(last.stamps[-1])],
            "environment": environment,
            "vertical_half_extent": generated_vertical_half_extent(generator),
            "generator": generator,
            "topics": {
                "image": topics.image,
                "action": topics.action,
                "pose": topics.pose,
                "reward": topics.reward,
            },
        }
        yield replace(last, source=source)

    def _check_topics(self, reader: BagReader) -> list[str]:
        """The wanted topics the bag has messages on; missing or mistyped ones refused."""
        topics = self.options.topics
        available = reader.topics_with_messages
        required = [topics.image, topics.action]
        if self.options.require_ground_truth:
            required += [topics.pose, topics.reward]
        if missing := [t for t in required if t not in available]:
            raise BagError(
                f"bag {str(self.path)!r} has no messages on topic(s) {missing} (it has "
                f"{sorted(available)})"
            )
        wanted = topics.types()
        for topic, msgtype in wanted.items():
            if topic in available and available[topic] != msgtype:
                hint = ""
                if topic in (topics.image, topics.action):
                    hint = (
                        "; simulator bags pair rgb8 images and TwistStamped actions by "
                        "identical stamp: for a robot's camera and commands add --step-period "
                        "SECONDS (their streams are resampled onto steps of that period)"
                    )
                raise BagError(
                    f"topic {topic!r} of bag {str(self.path)!r} has type {available[topic]}, "
                    f"expected {msgtype}{hint}"
                )
        return [t for t in wanted if t in available]

    def _bad_message(self, topic: str, index: int, data: bytes, exc: MessageError) -> Exception:
        stamp = peek_stamp(data)
        where = f"message {index}" + (f" (stamp {stamp} ns)" if stamp is not None else "")
        return MessageError(f"bag {str(self.path)!r}, topic {topic!r}, {where}: {exc}")

    def _image_bytes(self) -> int:
        height, width = self.images.shape or (1, 1)
        return height * width * 3

    def _window(self) -> int:
        """The reorder window, at most :data:`PENDING_BYTES` of images."""
        return min(self.options.reorder_window, max(16, PENDING_BYTES // self._image_bytes()))

    def _chunk_steps(self) -> int:
        """Steps per chunk, at most :data:`CHUNK_BYTES` of float64 observations."""
        return min(self.options.chunk_steps, max(1, CHUNK_BYTES // (8 * self._image_bytes())))

    def _too_late(self, topic: str, index: int, stamp: int, window: int) -> BagError:
        return BagError(
            f"bag {str(self.path)!r}, topic {topic!r}, message {index} (stamp {stamp} ns) "
            f"comes after messages of {window} or more later stamps: steps are paired in a "
            f"stream that allows messages out of stamp order by fewer than {window} stamps "
            "(or the stamp repeats; a larger reorder_window of read_trajectory reads it)"
        )

    def _finish(self, stamp: int, entry: list[Any]) -> StepChunk | None:
        """Make ``stamp`` final; return the full buffer if a new step needs the room."""
        image, velocity, pose, reward = entry
        if image is None or velocity is None:
            return None
        if self.options.require_ground_truth and (pose is None or reward is None):
            topics = self.options.topics
            missing = topics.pose if pose is None else topics.reward
            raise DataError(
                f"bag {str(self.path)!r} lacks ground truth for some steps: the step at stamp "
                f"{stamp} ns has no message on {missing!r}"
            )
        chunk = self._take() if len(self.buffer) >= self.chunk_limit else None
        if self.steps == 0:
            self.first_stamp = stamp
        self.steps += 1
        self.buffer.append((stamp, entry))
        return chunk

    def _take(self) -> StepChunk:
        """Empty the buffer into a chunk, numbering its segments after the previous one's."""
        assert self.images.shape is not None  # set by the first image decoded
        layout = StepLayout(
            self.images.shape, self.pose_width, self.options.step_ns, self.grid,
            self.options.action_tolerance,
        )  # fmt: skip
        try:
            steps = entry_steps(self.buffer, layout, self.last_stamp, self.segment)
        except ConfigError as exc:
            velocities = np.array([e[_ACTION] for _, e in self.buffer], dtype=np.float64)
            with np.errstate(invalid="ignore"):
                far = np.max(
                    [np.abs(velocities[:, i, None] - np.asarray(v)).min(axis=1)
                     for i, v in enumerate(self.grid.levels)],
                    axis=0,
                )  # fmt: skip
            first = int(np.argmax(~(far <= self.options.action_tolerance)))
            raise DataError(
                f"bag {str(self.path)!r}, topic {self.options.topics.action!r}, the step at "
                f"stamp {int(self.buffer[first][0])} ns: an action cannot be mapped to the "
                f"simulator's {len(self.grid)} actions: {exc}"
            ) from None
        self.buffer = []
        self.segment, self.last_stamp = int(steps.segments[-1]), int(steps.stamps[-1])
        return steps


def _read_steps(bags: Sequence[Path | str], image_shape: tuple[int, int] | None,
                options: _Options) -> Iterator[StepChunk]:
    images = ImageDecoder(image_shape)  # one shape for all bags
    segment = 0
    for bag in bags:
        reader = _BagSteps(Path(bag), images, options, segment)
        yield from reader.chunks()
        segment = reader.segment + 1


def _options(
    bags: Sequence[Path | str], topics: Topics | None, step_ns: int, action_tolerance: float,
    require_ground_truth: bool, chunk_steps: int, reorder_window: int,
    environment: str | None = None,
) -> _Options:
    if not bags:
        raise ConfigError("no bag given")
    if step_ns <= 0:
        raise ConfigError(f"step duration must be positive, not {step_ns} ns")
    if chunk_steps < 1:
        raise ConfigError(f"chunk_steps must be at least 1, not {chunk_steps}")
    if reorder_window < 1:
        raise ConfigError(f"reorder_window must be at least 1 stamp, not {reorder_window}")
    return _Options(
        topics or Topics(), int(step_ns), float(action_tolerance), bool(require_ground_truth),
        int(chunk_steps), int(reorder_window), environment,
    )


def iter_trajectory_chunks(
    bags: Sequence[Path | str],
    *,
    topics: Topics | None = None,
    image_shape: tuple[int, int] | None = DEFAULT_IMAGE_SHAPE,
    step_ns: int = STEP_NS,
    action_tolerance: float = DEFAULT_ACTION_TOLERANCE,
    require_ground_truth: bool = False,
    chunk_steps: int = DEFAULT_CHUNK_STEPS,
    reorder_window: int = REORDER_WINDOW,
    environment: str | None = None,
) -> Iterator[Trajectory]:
    """The steps of ``bags`` as trajectories of at most ``chunk_steps`` steps, in order.

    Concatenated, the chunks are :func:`read_trajectory` of the same arguments (segments
    numbered over all bags). A chunk holds steps of one bag;
    ``sources`` is empty except on each bag's last chunk, which carries that bag's source
    dict. Memory is bounded by ``chunk_steps`` and ``reorder_window``, each capped in bytes
    for large images (see the module docstring), not by the bags. Arguments are checked
    here; bags are read as the chunks are taken.
    """
    options = _options(bags, topics, step_ns, action_tolerance, require_ground_truth,
                       chunk_steps, reorder_window, environment)
    return (steps.trajectory() for steps in _read_steps(bags, image_shape, options))


def read_trajectory(
    bags: Sequence[Path | str],
    *,
    topics: Topics | None = None,
    image_shape: tuple[int, int] | None = DEFAULT_IMAGE_SHAPE,
    step_ns: int = STEP_NS,
    action_tolerance: float = DEFAULT_ACTION_TOLERANCE,
    require_ground_truth: bool = False,
    reorder_window: int = REORDER_WINDOW,
    environment: str | None = None,
) -> Trajectory:
    """Read and pair the steps of ``bags`` (see the module docstring).

    ``image_shape=None`` accepts any size, but all images must share it.
    ``require_ground_truth`` also demands the pose and reward topics; ``reorder_window``
    is how far out of stamp order a message may come. ``environment`` is the simulator of
    bags that do not name theirs (a recording of ``sim_node``: its actions, and in
    ``drive`` the heading); a bag that names another is refused. The chunks of
    :func:`iter_trajectory_chunks` concatenated (pixels converted to observations once).
    """
    options = _options(bags, topics, step_ns, action_tolerance, require_ground_truth,
                       DEFAULT_CHUNK_STEPS, reorder_window, environment)
    return _trajectory(list(_read_steps(bags, image_shape, options)))


class LiveSteps:
    """A simulator's live streams made into steps exactly as a recording of them is read.

    Raw CDR messages of the image, action, pose and reward topics go to :meth:`add` (in
    any order within ``window`` stamps); they are decoded by the bag reader's decoders,
    paired by :class:`StampPairing`, and a final stamp with an image and an action is a
    step. :meth:`trajectory` gives the first steps as :func:`read_trajectory` gives them
    for a bag holding those messages (segments, action indices, NaN for a missing pose or
    reward). ``environment``: the simulator's (``drive`` reads its actions and heading);
    None: the planar environments' 25 actions.
    """

    def __init__(
        self,
        environment: str | None,
        *,
        image_shape: tuple[int, int] | None = DEFAULT_IMAGE_SHAPE,
        window: int = 10,
        step_ns: int = STEP_NS,
        action_tolerance: float = DEFAULT_ACTION_TOLERANCE,
        topics: Topics | None = None,
    ) -> None:
        drives = environment == "drive"
        self.environment = environment
        self.topics = topics or Topics()
        self.grid = environment_grid(environment)
        self.images = ImageDecoder(image_shape)
        self.decoders: dict[int, Any] = {
            _IMAGE: self.images,
            _ACTION: TwistDecoder(self.grid.components),
            _POSE: PoseDecoder(heading=drives),
            _REWARD: RewardDecoder(),
        }
        self.pose_width = 4 if drives else 2
        self.step_ns = int(step_ns)
        self.action_tolerance = float(action_tolerance)
        self.pairing = StampPairing(window)
        self.steps: list[tuple[int, list[Any]]] = []
        self.unpaired = 0

    IMAGE, ACTION, POSE, REWARD = _IMAGE, _ACTION, _POSE, _REWARD
    """The kinds of message :meth:`add` takes."""

    @classmethod
    def of_bag(cls, bag: Path | str, environment: str | None) -> LiveSteps:
        """Every message of a simulator bag's step topics fed in log order, as a node
        subscribing them during the recording got them (then flushed)."""
        live = cls(environment)
        topics = live.topics
        kinds = {topics.image: _IMAGE, topics.action: _ACTION, topics.pose: _POSE,
                 topics.reward: _REWARD}  # fmt: skip
        with BagReader(Path(bag)) as reader:
            for topic, _, data in reader.raw_messages(list(kinds)):
                live.add(kinds[topic], data)
        live.flush()
        return live

    def __len__(self) -> int:
        return len(self.steps)

    def add(self, kind: int, data: bytes) -> int:
        """Decode and pair one message; return how many steps it made final. Raises
        ``MessageError`` (undecodable, or an action off the grid), :class:`LateMessage` or
        :class:`RepeatedMessage`."""
        stamp, value = self.decoders[kind].decode(data)
        if kind == _ACTION:
            try:  # refused here, not when a refit converts it
                self.grid.indices(np.array([value], dtype=np.float64), self.action_tolerance)
            except ConfigError as exc:
                raise MessageError(f"an action off the simulator's grid: {exc}") from None
        return self._keep(self.pairing.add(kind, stamp, value))

    def flush(self) -> int:
        """Make every pending stamp final (the streams paused); return the new steps."""
        return self._keep(self.pairing.flush())

    def _keep(self, finals: list[tuple[int, list[Any]]]) -> int:
        before = len(self.steps)
        for stamp, entry in finals:
            if entry[_IMAGE] is None or entry[_ACTION] is None:
                self.unpaired += 1
            else:
                self.steps.append((stamp, entry))
        return len(self.steps) - before

    def trajectory(self, steps: int | None = None) -> Trajectory:
        """The first ``steps`` final steps (default: all) as one trajectory."""
        return self.chunk(steps).trajectory()

    def chunk(self, steps: int | None = None) -> StepChunk:
        """The first ``steps`` final steps with pixels still uint8 (a compact copy to hand
        to another process; its :meth:`StepChunk.trajectory` is :meth:`trajectory`)."""
        buffer = self.steps if steps is None else self.steps[:steps]
        if not buffer or self.images.shape is None:
            raise DataError("no step has both an image and an action yet")
        layout = StepLayout(
            self.images.shape, self.pose_width, self.step_ns, self.grid, self.action_tolerance
        )
        source = {
            "path": "live",
            "steps": len(buffer),
            "stamps_ns": [int(buffer[0][0]), int(buffer[-1][0])],
            "environment": self.environment,
            "topics": {
                "image": self.topics.image,
                "action": self.topics.action,
                "pose": self.topics.pose,
                "reward": self.topics.reward,
            },
        }
        return replace(entry_steps(buffer, layout, None, -1), source=source)
