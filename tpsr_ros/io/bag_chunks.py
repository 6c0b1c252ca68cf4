"""Bags as chunk sources for the streamed fit, and the survey that refuses mismatched bags.

:class:`BagChunks` says how to read one bag in chunks (simulator bags: exact-stamp pairing,
:func:`tpsr_ros.io.trajectory.iter_trajectory_chunks`; robot bags: the step grid of a
:class:`~tpsr_ros.io.stream_spec.StreamSpec`, read one whole bag at a time and sliced). It
is a small frozen value, so a Dask worker can be sent it and read a bag itself. An
``OSError`` while reading (a bag deleted or unmounted mid-fit) becomes a ``BagError`` naming
the bag.

:func:`survey_bags` reads each simulator bag's metadata and first image before any pass:
bags whose images differ in size or encoding, or whose action topics differ in type, are
refused together, naming both bags, instead of failing after a long first pass.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import BagError, ConfigError
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.stream_spec import StreamSpec
from tpsr_ros.io.streams import DEFAULT_POSE_FRAME, read_stream_trajectory
from tpsr_ros.io.trajectory import (
    DEFAULT_CHUNK_STEPS,
    Topics,
    bag_custom_data,
    generated_vertical_half_extent,
    iter_trajectory_chunks,
)

__all__ = ["DEFAULT_CHUNK_STEPS", "BagChunks", "BagSurvey", "survey_bags"]


def _renumbered(chunk: Trajectory, offset: int) -> Trajectory:
    return dataclasses.replace(chunk, segments=chunk.segments + offset)


@dataclass(frozen=True)
class BagChunks:
    """How to read a bag in chunks of at most ``chunk_steps`` steps."""

    topics: Topics = dataclasses.field(default_factory=Topics)
    chunk_steps: int = DEFAULT_CHUNK_STEPS
    spec: StreamSpec | None = None
    """Robot bags: the step grid (None: simulator bags, images and actions paired by stamp)."""
    pose_frame: str = DEFAULT_POSE_FRAME

    def __post_init__(self) -> None:
        if self.chunk_steps < 1:
            raise ConfigError(f"chunk_steps must be at least 1, not {self.chunk_steps}")

    def read(self, bag: Path | str) -> Iterator[Trajectory]:
        """Yield the chunks of one bag (segments numbered from 0)."""
        try:
            if self.spec is None:
                yield from iter_trajectory_chunks(
                    [bag], topics=self.topics, chunk_steps=self.chunk_steps
                )
                return
            whole = read_stream_trajectory(
                [bag],
                self.spec,
                pose_topic=self.topics.pose,
                reward_topic=self.topics.reward,
                pose_frame=self.pose_frame,
            )
            for start in range(0, len(whole), self.chunk_steps):
                stop = min(start + self.chunk_steps, len(whole))
                yield dataclasses.replace(
                    whole.rows(start, stop),
                    sources=whole.sources if stop == len(whole) else [],
                )
        except OSError as exc:
            raise BagError(f"bag {str(bag)!r} could not be read: {exc}") from None

    def read_all(self, bags: Sequence[Path | str]) -> Iterator[Trajectory]:
        """Yield the chunks of every bag in order, segments numbered across bags."""
        offset = 0
        for bag in bags:
            last = -1
            for chunk in self.read(bag):
                if len(chunk):
                    last = int(chunk.segments[-1])
                yield _renumbered(chunk, offset)
            offset += last + 1


@dataclass(frozen=True)
class BagSurvey:
    """What must agree between the bags of one fit, from metadata and the first image."""

    path: str
    image_type: str
    image_size: tuple[int, int]
    image_encoding: str
    action_type: str
    environment: str | None = None
    vertical_half_extent: float | None = None
    """The simulated camera's, from the generator's settings (None: not a generated bag)."""

    def differences(self, other: BagSurvey) -> list[str]:
        """Human-readable differences from ``other``."""
        out = []
        if self.image_size != other.image_size or self.image_encoding != other.image_encoding:
            out.append(
                f"images {self.image_size[1]}x{self.image_size[0]} {self.image_encoding} vs "
                f"{other.image_size[1]}x{other.image_size[0]} {other.image_encoding}"
            )
        if self.image_type != other.image_type:
            out.append(f"image type {self.image_type} vs {other.image_type}")
        if self.action_type != other.action_type:
            out.append(f"actions {self.action_type} vs {other.action_type}")
        return out


def _survey(path: Path, topics: Topics) -> BagSurvey:
    with BagReader(path) as reader:
        types = reader.topics
        available = reader.topics_with_messages
        for topic in (topics.image, topics.action):
            if topic not in available:
                raise BagError(
                    f"bag {str(path)!r} has no messages on topic {topic!r} (it has "
                    f"{sorted(available)})"
                )
        first = next(iter(reader.messages([topics.image]))).decode()
        environment, generator = bag_custom_data(reader)
        return BagSurvey(
            path=str(path),
            image_type=types[topics.image],
            image_size=(int(first.height), int(first.width)),
            image_encoding=str(first.encoding),
            action_type=types[topics.action],
            environment=environment,
            vertical_half_extent=generated_vertical_half_extent(generator),
        )


def survey_bags(bags: Sequence[Path | str], topics: Topics | None = None) -> list[BagSurvey]:
    """Survey every bag; refuse bags whose image sizes, encodings or action types differ."""
    topics = topics or Topics()
    surveys = [_survey(Path(bag), topics) for bag in bags]
    for survey in surveys[1:]:
        if diff := surveys[0].differences(survey):
            raise BagError(
                f"bags {surveys[0].path!r} and {survey.path!r} cannot be fitted together: "
                f"{'; '.join(diff)}"
            )
    return surveys
