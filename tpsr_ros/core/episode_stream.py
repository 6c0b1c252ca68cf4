"""Episodes from a stream of chunks: cut across chunk boundaries, then summarised or whitened.

A streamed fit never holds the whole trajectory. :class:`EpisodeCutter` cuts consecutive
chunks into exactly the episodes :func:`~tpsr_ros.core.episodes.make_episodes` cuts from the
whole; pass 1 of a streamed fit sums their moments (:func:`episode_moments`), pass 2 whitens
them (:func:`whitened_episodes`), and :func:`box_rows` picks the few a state box needs.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import numpy as np

from tpsr_ros.core.episodes import (
    STEP_FIELDS,
    Episodes,
    Trajectory,
    episode_starts,
    episodes_at,
    no_usable_episodes,
)
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.moments import Moments
from tpsr_ros.core.tpsr import BoxData
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.whitened import WhitenedRows, Whitenings
from tpsr_ros.core.whitening import check_finite_matrix

__all__ = [
    "EpisodeCutter",
    "EpisodeMoments",
    "box_rows",
    "episode_cutter",
    "episode_moments",
    "episodes_of",
    "merge_moments",
    "refinement_steps",
    "whitened_episodes",
]


def _joined(*parts: Trajectory) -> Trajectory:
    """Consecutive parts of one trajectory as one (the last part's metadata)."""
    return dataclasses.replace(
        parts[-1], **{n: np.concatenate([getattr(p, n) for p in parts]) for n in STEP_FIELDS}
    )


class EpisodeCutter:
    """Cuts consecutive chunks of one trajectory into the episodes of :func:`make_episodes`
    (one starting every ``stride`` steps of a segment; default ``m + 1 + n``, 1: every window).

    The rows of a segment from the first start not yet cut on are carried into the next
    chunk when it continues that segment (same segment number) and dropped otherwise,
    exactly as ``make_episodes`` drops a segment's remainder. At most ``max_episodes`` are cut.
    """

    def __init__(
        self,
        history_length: int,
        test_length: int,
        max_episodes: int | None = None,
        stride: int | None = None,
    ) -> None:
        self.m, self.n = int(history_length), int(test_length)
        if self.m < 1 or self.n < 1:
            raise ConfigError(
                f"history and test lengths must be at least 1, not {self.m} and {self.n}"
            )
        if max_episodes is not None and max_episodes < 0:
            raise ConfigError(f"the number of episodes must not be negative, not {max_episodes}")
        self.span = self.m + 1 + self.n
        self.stride = self.span if stride is None else int(stride)
        if not 1 <= self.stride <= self.span:
            raise ConfigError(f"the episode stride must lie in 1..{self.span}, not {stride}")
        self.limit = max_episodes
        self.emitted = 0
        self.steps = 0
        self.segments = 0
        self.stamps: tuple[int, int] | None = None
        """First and last stamp of the steps read (ns)."""
        self.used = 0
        """Steps read up to the last one of the last episode cut (what those episodes use)."""
        self._last_segment: int | None = None
        self._carry: Trajectory | None = None

    @property
    def full(self) -> bool:
        """Whether ``max_episodes`` episodes have been cut."""
        return self.limit is not None and self.emitted >= self.limit

    def cut(self, chunk: Trajectory) -> Episodes | None:
        """Episodes completed by ``chunk`` (None if none)."""
        if self.full or len(chunk) == 0:
            return None
        self.steps += len(chunk)
        self.segments += int(np.count_nonzero(np.diff(chunk.segments)))
        self.segments += int(chunk.segments[0]) != self._last_segment
        self._last_segment = int(chunk.segments[-1])
        first = int(chunk.stamps[0]) if self.stamps is None else self.stamps[0]
        self.stamps = (first, int(chunk.stamps[-1]))
        data = chunk
        if self._carry is not None and int(self._carry.segments[-1]) == int(chunk.segments[0]):
            data = _joined(self._carry, chunk)
        last_start = data.segment_bounds()[-1][0]
        cut_in_last = max(0, (len(data) - last_start - self.span) // self.stride + 1)
        resume = last_start + cut_in_last * self.stride  # the last segment's next start
        self._carry = data.rows(resume, len(data)) if resume < len(data) else None
        first = episode_starts(data, self.span, self.stride)
        if self.limit is not None:
            first = first[: self.limit - self.emitted]
        self.emitted += int(first.size)
        if first.size:
            self.used = self.steps - len(data) + int(first[-1]) + self.span
        return episodes_at(data, first, self.m, self.n) if first.size else None


def episode_cutter(cfg: TPSRConfig, max_episodes: int | None = None) -> EpisodeCutter:
    """The cutter of the episodes a fit of ``cfg`` learns from (its lengths and stride)."""
    return EpisodeCutter(cfg.history_length, cfg.test_length, max_episodes, cfg.episode_stride)


def _checked(chunk: Trajectory) -> Trajectory:
    check_finite_matrix(chunk.observations, "observations")
    if len(chunk) and (chunk.actions.min() < 0 or chunk.actions.max() >= chunk.n_actions):
        raise DataError(f"action indices must lie in 0..{chunk.n_actions - 1}")
    return chunk


def episodes_of(chunks: Iterable[Trajectory], cutter: EpisodeCutter) -> Iterator[Episodes]:
    for chunk in chunks:
        episodes = cutter.cut(_checked(chunk))
        if episodes is not None:
            yield episodes
        if cutter.full:
            return


@dataclass(frozen=True, eq=False)
class EpisodeMoments:
    """Pass 1's result for some episodes: moments of histories, tests, current observations."""

    history: Moments
    test: Moments
    observation: Moments
    n_actions: int
    steps: int = 0
    """Steps read (up to the last episode when ``max_episodes`` stopped the pass early)."""
    segments: int = 0
    stamps: tuple[int, int] | None = None
    """Smallest first and largest last stamp (ns) of the steps read."""

    @property
    def episodes(self) -> int:
        """Number of episodes."""
        return self.observation.count

    @classmethod
    def of(cls, episodes: Episodes) -> EpisodeMoments:
        """Moments of one block of episodes."""
        return cls(
            Moments.of(episodes.history),
            Moments.of(episodes.test),
            Moments.of(episodes.observation),
            int(episodes.n_actions),
        )

    def merge(self, other: EpisodeMoments) -> EpisodeMoments:
        """Moments of both sets of episodes (pairwise update)."""
        if other.n_actions != self.n_actions or other.observation.dim != self.observation.dim:
            raise DataError(
                f"cannot fit data with {self.n_actions} actions and observations of "
                f"{self.observation.dim} values together with data with {other.n_actions} "
                f"actions and {other.observation.dim} values"
            )
        return EpisodeMoments(
            self.history.merge(other.history),
            self.test.merge(other.test),
            self.observation.merge(other.observation),
            self.n_actions,
            self.steps + other.steps,
            self.segments + other.segments,
            _stamp_range(self.stamps, other.stamps),
        )


def _stamp_range(
    a: tuple[int, int] | None, b: tuple[int, int] | None
) -> tuple[int, int] | None:
    if a is None or b is None:
        return a or b
    return min(a[0], b[0]), max(a[1], b[1])


def merge_moments(a: EpisodeMoments | None, b: EpisodeMoments | None) -> EpisodeMoments | None:
    """:meth:`EpisodeMoments.merge` where either side may be None (no episodes)."""
    if a is None:
        return b
    if b is None:
        return a
    return a.merge(b)


def episode_moments(
    chunks: Iterable[Trajectory],
    history_length: int,
    test_length: int,
    max_episodes: int | None = None,
    stride: int | None = None,
) -> EpisodeMoments | None:
    """Pass 1 over ``chunks``: moments of their first ``max_episodes`` episodes, one every
    ``stride`` steps (:class:`EpisodeCutter`; None: none)."""
    total: EpisodeMoments | None = None
    cutter = EpisodeCutter(history_length, test_length, max_episodes, stride)
    for episodes in episodes_of(chunks, cutter):
        total = merge_moments(total, EpisodeMoments.of(episodes))
    if total is None:
        return None
    return dataclasses.replace(
        total, steps=cutter.steps, segments=cutter.segments, stamps=cutter.stamps
    )


def whitened_episodes(
    chunks: Iterable[Trajectory],
    whitenings: Whitenings,
    cfg: TPSRConfig,
    max_episodes: int | None = None,
) -> Iterator[WhitenedRows]:
    """Pass 2 over ``chunks``: the whitened rows of their first ``max_episodes`` episodes."""
    cutter = episode_cutter(cfg, max_episodes)
    for episodes in episodes_of(chunks, cutter):
        yield whitenings.rows(episodes, cfg)


def refinement_steps(
    chunks: Iterable[Trajectory], cfg: TPSRConfig, max_episodes: int | None = None
) -> Trajectory:
    """The steps a fit of ``cfg`` refines on, read from ``chunks``: the first
    ``cfg.refine_steps`` of those its first ``max_episodes`` episodes use, as the fit in
    memory takes them (:func:`tpsr_ros.core.learn.refined_on_trajectory`)."""
    # episodes are cut only to find where the first max_episodes end
    cutter = None if max_episodes is None else episode_cutter(cfg, max_episodes)
    parts: list[Trajectory] = []
    held = 0
    for chunk in chunks:
        chunk = _checked(chunk)
        if cutter is not None:
            cutter.cut(chunk)
        parts.append(chunk.rows(0, min(len(chunk), cfg.refine_steps - held)))
        held += len(parts[-1])
        if held >= cfg.refine_steps or (cutter is not None and cutter.full):
            break
    capped = held >= cfg.refine_steps and not (cutter is not None and cutter.full)
    end = held if cutter is None or capped else min(held, cutter.used)
    if end == 0:
        raise no_usable_episodes(cfg.history_length, cfg.test_length, "the data")
    return _joined(*parts).rows(0, end)


def box_rows(episodes: Iterable[Episodes], indices: np.ndarray) -> BoxData:
    """Histories, history actions, actions and observations of the episodes ``indices``
    (sorted, counted over the episodes given, in order)."""
    parts: list[BoxData] = []
    seen = 0
    for part in episodes:
        local = indices[(indices >= seen) & (indices < seen + len(part))] - seen
        if local.size:
            parts.append((
                part.history[local], part.history_actions[local], part.action[local],
                part.observation[local],
            ))  # fmt: skip
        seen += len(part)
    if not parts:
        raise DataError("none of the state box's episodes was found in the data")
    joined = [np.concatenate(column) for column in zip(*parts, strict=True)]
    return joined[0], joined[1], joined[2], joined[3]
