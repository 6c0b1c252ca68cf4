"""Streamed TPSR fit: guide Algorithms 1-3 over data that never sit in memory at once.

:func:`fit_tpsr_streamed` learns the model of ``fit_tpsr_episodes(make_episodes(whole))``
(equal to rounding, ~1e-12 relative) from a *chunk source*: a callable returning a fresh
iterator of :class:`~tpsr_ros.core.episodes.Trajectory` chunks whose concatenation is the
whole trajectory (e.g. :func:`tpsr_ros.io.trajectory.iter_trajectory_chunks`). It reads the
data twice:

1. **pass 1**: chunks are cut into episodes exactly as :func:`make_episodes` cuts the whole
   (:class:`EpisodeCutter` carries the unfinished tail of a segment into the next chunk and
   honours ``max_episodes``); each chunk's histories, tests and current observations give
   :class:`~tpsr_ros.core.moments.Moments` (mean, centred scatter), merged pairwise. The
   whitenings (Algorithm 1) come from the merged covariances.
2. **pass 2**: every episode is whitened and only its whitened rows (``d_H + d_T + d_O``
   floats, ~30, plus ``d_T`` for ``from-current``) and current action are kept, in ``.npy``
   memory maps in a temporary directory (:class:`WhitenedStore`; on Dask, on the workers).

Then, from the store and without reading the data again: kernel centres (the first rows, or
k-means on the whitened rows exactly as :func:`~tpsr_ros.core.features.select_centers`), the
sums of ``phi_H`` and ``phi_T0^T phi_H`` over blocks of rows (:class:`PSums`; ``P_TH`` is
accumulated in place by BLAS ``dgemm``, so a 20 001 x 20 001 ``P_TH`` exists once), the
top-``r`` SVD, and a second blocked pass over the rows for the per-action sums of ``B_ao'``
(:class:`ActionSums`). No ``(t, l)`` feature matrix for all of ``t`` and no ``O(t l^2)`` tensor
is ever formed: memory is bounded by the chunk size, the block size (:data:`BLOCK_BYTES`) and
``P_TH``, not by the data length.

Where the work runs is an *engine* (:class:`StreamEngine`): :class:`ChunkEngine` runs it in
this process; ``learner.distributed`` runs the same functions as Dask tasks (one per bag,
partial sums reduced as a tree). The per-block arithmetic is the in-memory fit's own
(:func:`~tpsr_ros.core.tpsr.ht_features`, :func:`~tpsr_ros.core.tpsr.projected_outer`,
:func:`~tpsr_ros.core.tpsr.action_sums`, ...).
"""

from __future__ import annotations

import dataclasses
import tempfile
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

import numpy as np
import scipy.linalg.blas

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
from tpsr_ros.core.pca_baseline import PCAConfig, PCAModel
from tpsr_ros.core.tpsr import (
    Progress,
    Stopwatch,
    TPSRConfig,
    TPSRModel,
    action_operators,
    action_sums,
    assemble_model,
    check_action_counts,
    check_enough_episodes,
    ht_features,
    kernel_centres,
    obs_features,
    projected_outer,
    start_and_normaliser,
    truncated_svd,
    whiten_test_window,
)
from tpsr_ros.core.whitening import Whitening, check_finite_matrix

__all__ = [
    "BLOCK_BYTES",
    "ActionSums",
    "Centres",
    "ChunkEngine",
    "ChunkSource",
    "EpisodeCutter",
    "EpisodeMoments",
    "PSums",
    "StreamEngine",
    "WhitenedRows",
    "WhitenedStore",
    "Whitenings",
    "block_rows",
    "episode_moments",
    "fit_pca_streamed",
    "fit_tpsr_streamed",
    "merge_moments",
    "p_sums",
    "parameter_sums",
    "whitened_episodes",
]

ChunkSource = Callable[[], Iterable[Trajectory]]
"""Returns a fresh iterator over the chunks on every call (the fit reads the data twice)."""

BLOCK_BYTES = 64 * 2**20
"""Target size of one block's feature matrix; blocks hold 512 to 8192 rows."""


def block_rows(n_features: int) -> int:
    """Rows per block so that a ``(rows, n_features)`` float64 matrix is ~:data:`BLOCK_BYTES`."""
    return int(min(8192, max(512, BLOCK_BYTES // (8 * max(1, n_features)))))


def _joined(head: Trajectory, tail: Trajectory) -> Trajectory:
    return dataclasses.replace(
        tail,
        **{n: np.concatenate([getattr(head, n), getattr(tail, n)]) for n in STEP_FIELDS},
    )


class EpisodeCutter:
    """Cuts consecutive chunks of one trajectory into the episodes of :func:`make_episodes`.

    The rows of a segment that do not yet fill an episode are carried into the next chunk
    when it continues that segment (same segment number) and dropped otherwise, exactly as
    ``make_episodes`` drops a segment's remainder. At most ``max_episodes`` are cut.
    """

    def __init__(
        self, history_length: int, test_length: int, max_episodes: int | None = None
    ) -> None:
        self.m, self.n = int(history_length), int(test_length)
        if self.m < 1 or self.n < 1:
            raise ConfigError(
                f"history and test lengths must be at least 1, not {self.m} and {self.n}"
            )
        if max_episodes is not None and max_episodes < 0:
            raise ConfigError(f"the number of episodes must not be negative, not {max_episodes}")
        self.span = self.m + 1 + self.n
        self.limit = max_episodes
        self.emitted = 0
        self.steps = 0
        self.segments = 0
        self.stamps: tuple[int, int] | None = None
        """First and last stamp of the steps read (ns)."""
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
        done = last_start + (len(data) - last_start) // self.span * self.span
        self._carry = data.rows(done, len(data)) if done < len(data) else None
        first = episode_starts(data, self.span)
        if self.limit is not None:
            first = first[: self.limit - self.emitted]
        self.emitted += int(first.size)
        return episodes_at(data, first, self.m, self.n) if first.size else None


def _checked(chunk: Trajectory) -> Trajectory:
    check_finite_matrix(chunk.observations, "observations")
    if len(chunk) and (chunk.actions.min() < 0 or chunk.actions.max() >= chunk.n_actions):
        raise DataError(f"action indices must lie in 0..{chunk.n_actions - 1}")
    return chunk


def _episodes(chunks: Iterable[Trajectory], cutter: EpisodeCutter) -> Iterator[Episodes]:
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
) -> EpisodeMoments | None:
    """Pass 1 over ``chunks``: moments of their first ``max_episodes`` episodes (None: none)."""
    total: EpisodeMoments | None = None
    cutter = EpisodeCutter(history_length, test_length, max_episodes)
    for episodes in _episodes(chunks, cutter):
        total = merge_moments(total, EpisodeMoments.of(episodes))
    if total is None:
        return None
    return dataclasses.replace(
        total, steps=cutter.steps, segments=cutter.segments, stamps=cutter.stamps
    )


@dataclass(frozen=True, eq=False)
class Whitenings:
    """Algorithm 1's three whitenings, fitted from pass 1's moments."""

    history: Whitening
    test: Whitening
    obs: Whitening

    @classmethod
    def fit(cls, moments: EpisodeMoments, cfg: TPSRConfig) -> Whitenings:
        """Whitenings of histories and tests (``d^H = d^T``) and observations (``d^O``)."""
        return cls(
            Whitening.from_moments(moments.history, cfg.ht_dim, what="histories"),
            Whitening.from_moments(moments.test, cfg.ht_dim, what="tests"),
            Whitening.from_moments(
                moments.observation,
                cfg.obs_dim,
                what="current observations",
                variance=cfg.obs_variance,
            ),
        )

    def apply(self, episodes: Episodes, cfg: TPSRConfig) -> WhitenedRows:
        """Whitened rows of ``episodes`` (with the ``from-current`` test window if asked)."""
        test0 = None
        if cfg.p_th_tests == "from-current":
            test0 = whiten_test_window(
                self.test, episodes.observation, episodes.test, cfg.test_length
            )
        return WhitenedRows(
            self.history.transform(episodes.history),
            self.test.transform(episodes.test),
            self.obs.transform(episodes.observation),
            test0,
            np.asarray(episodes.action, dtype=np.int64),
        )


@dataclass(frozen=True, eq=False)
class WhitenedRows:
    """Whitened episodes: histories, tests, current observations, ``P_TH`` tests, actions."""

    history: np.ndarray
    test: np.ndarray
    observation: np.ndarray
    test0: np.ndarray | None
    """Tests of ``P_TH`` (None: ``test`` itself, the guide's ``after-current``)."""
    actions: np.ndarray

    def __len__(self) -> int:
        return int(self.actions.shape[0])

    @classmethod
    def concatenate(cls, parts: Sequence[WhitenedRows]) -> WhitenedRows:
        """The rows of ``parts``, one after the other."""
        return cls(**{
            name: None if getattr(parts[0], name) is None
            else np.concatenate([getattr(part, name) for part in parts])
            for name in _WHITENED_FIELDS
        })  # fmt: skip

    def rows(self, start: int, stop: int) -> WhitenedRows:
        """Rows ``start:stop`` (views)."""
        return self._map(lambda array: array[start:stop])

    def copy(self) -> WhitenedRows:
        """In-memory copy (e.g. to send a block of a memory map to a worker)."""
        return self._map(np.array)

    def _map(self, function: Callable[[np.ndarray], np.ndarray]) -> WhitenedRows:
        """``function`` of every array (a missing ``test0`` stays missing)."""
        return WhitenedRows(**{
            name: None if (array := getattr(self, name)) is None else function(array)
            for name in _WHITENED_FIELDS
        })  # fmt: skip


_WHITENED_FIELDS = tuple(field.name for field in dataclasses.fields(WhitenedRows))


def whitened_episodes(
    chunks: Iterable[Trajectory],
    whitenings: Whitenings,
    cfg: TPSRConfig,
    max_episodes: int | None = None,
) -> Iterator[WhitenedRows]:
    """Pass 2 over ``chunks``: the whitened rows of their first ``max_episodes`` episodes."""
    cutter = EpisodeCutter(cfg.history_length, cfg.test_length, max_episodes)
    for episodes in _episodes(chunks, cutter):
        yield whitenings.apply(episodes, cfg)


class WhitenedStore:
    """Whitened episodes in ``.npy`` memory maps in a temporary directory (a context manager).

    ``write`` fills rows in any order; ``rows`` gives views. The directory and its files are
    removed on exit, whatever happened.
    """

    def __init__(
        self,
        n_episodes: int,
        whitenings: Whitenings,
        cfg: TPSRConfig,
        directory: Path | str | None = None,
    ) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="tpsr-stream-", dir=directory)
        root = Path(self._tmp.name)
        shapes = {
            "history": (n_episodes, whitenings.history.n_components),
            "test": (n_episodes, whitenings.test.n_components),
            "observation": (n_episodes, whitenings.obs.n_components),
        }
        if cfg.p_th_tests == "from-current":
            shapes["test0"] = shapes["test"]
        self._arrays = {
            name: np.lib.format.open_memmap(root / f"{name}.npy", "w+", np.float64, shape)
            for name, shape in shapes.items()
        }
        self._arrays["actions"] = np.lib.format.open_memmap(
            root / "actions.npy", "w+", np.int64, (n_episodes,)
        )
        self.n_episodes = int(n_episodes)

    @property
    def nbytes(self) -> int:
        """Bytes of the memory maps."""
        return int(sum(a.nbytes for a in self._arrays.values()))

    def write(self, start: int, rows: WhitenedRows) -> None:
        """Store ``rows`` as episodes ``start .. start + len(rows) - 1``."""
        stop = start + len(rows)
        if stop > self.n_episodes:
            raise DataError(
                f"the data gave more than the {self.n_episodes} episodes of the first pass "
                "(did a bag change during the fit?)"
            )
        for name, array in self._arrays.items():
            value = getattr(rows, name)
            if value is not None:
                array[start:stop] = value

    def rows(self, start: int = 0, stop: int | None = None) -> WhitenedRows:
        """Return views of episodes ``start:stop``."""
        end = self.n_episodes if stop is None else stop
        return WhitenedRows(**{
            name: self._arrays[name][start:end] if name in self._arrays else None
            for name in _WHITENED_FIELDS
        })  # fmt: skip

    def close(self) -> None:
        """Drop the memory maps and remove the directory."""
        self._arrays.clear()
        self._tmp.cleanup()

    def __enter__(self) -> WhitenedStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True, eq=False)
class Centres:
    """Kernel centres (whitened): histories ``(l_H, d_H)``, tests, observations ``(l_O, d_O)``."""

    history: np.ndarray
    test: np.ndarray
    observation: np.ndarray


def _select_centres(rows: WhitenedRows, cfg: TPSRConfig) -> Centres:
    """Algorithm 2's centres, as the in-memory fit chooses them (same seeds)."""
    return Centres(*kernel_centres(rows.history, rows.test, rows.observation, cfg))


@dataclass(eq=False)
class PSums:
    """Sums over training episodes: ``phi_H`` ``(l_H + 1,)``, ``phi_T0^T phi_H`` (Fortran order)."""

    count: int
    history: np.ndarray
    cross: np.ndarray

    @classmethod
    def zeros(cls, n_test_features: int, n_history_features: int) -> PSums:
        """Empty sums (``cross`` allocated once, Fortran-ordered for in-place ``dgemm``)."""
        return cls(
            0,
            np.zeros(n_history_features),
            np.zeros((n_test_features, n_history_features), order="F"),
        )

    def add(self, phi_h: np.ndarray, phi_t0: np.ndarray) -> None:
        """Add a block's features in place: ``cross += phi_T0^T phi_H`` with no temporary."""
        self.count += int(phi_h.shape[0])
        self.history += phi_h.sum(axis=0)
        out = scipy.linalg.blas.dgemm(
            1.0, phi_t0.T, phi_h.T, beta=1.0, c=self.cross, trans_b=True, overwrite_c=True
        )
        if out is not self.cross:  # pragma: no cover - f2py copied despite Fortran order
            self.cross[...] = out

    def merged(self, other: PSums) -> PSums:
        """Return a new :class:`PSums` of both (for tree reductions; inputs untouched)."""
        return PSums(
            self.count + other.count,
            self.history + other.history,
            np.asfortranarray(self.cross + other.cross),
        )


def p_sums(
    rows: WhitenedRows, centres: Centres, cfg: TPSRConfig, into: PSums | None = None
) -> PSums:
    """Eqs. 3.1 and 3.2 unnormalised over ``rows``, block by block (added to ``into`` if given)."""
    n_t, n_h = centres.test.shape[0] + 1, centres.history.shape[0] + 1
    sums = PSums.zeros(n_t, n_h) if into is None else into
    step = block_rows(max(centres.test.shape[0], centres.history.shape[0]) + 1)
    for start in range(0, len(rows), step):
        block = rows.rows(start, start + step)
        phi_h = ht_features(np.asarray(block.history), centres.history, cfg)
        test0 = block.test if block.test0 is None else block.test0
        phi_t0 = ht_features(np.asarray(test0), centres.test, cfg)
        sums.add(phi_h, phi_t0)
    return sums


@dataclass(eq=False)
class ActionSums:
    """Per action: training samples and ``sum phi_O[i, o'] outer(A_T[i], A_H[i])``."""

    counts: np.ndarray
    sums: np.ndarray

    @classmethod
    def zeros(cls, n_actions: int, n_obs_centres: int, rank: int) -> ActionSums:
        """Empty sums ``(n_actions, l_O, r^2)``."""
        counts = np.zeros(n_actions, dtype=np.int64)
        return cls(counts, np.zeros((n_actions, n_obs_centres, rank**2)))

    def merged(self, other: ActionSums) -> ActionSums:
        """Return a new :class:`ActionSums` of both."""
        return ActionSums(self.counts + other.counts, self.sums + other.sums)


def parameter_sums(
    rows: WhitenedRows,
    centres: Centres,
    svd: tuple[np.ndarray, np.ndarray, np.ndarray],
    cfg: TPSRConfig,
    n_actions: int,
) -> ActionSums:
    """Eqs. 3.3 and 3.7 unnormalised over ``rows``, block by block."""
    r = svd[1].shape[0]
    total = ActionSums.zeros(n_actions, centres.observation.shape[0], r)
    widest = max(centres.test.shape[0], centres.history.shape[0], centres.observation.shape[0])
    step = block_rows(widest + 1)
    for start in range(0, len(rows), step):
        block = rows.rows(start, start + step)
        phi_h = ht_features(np.asarray(block.history), centres.history, cfg)
        phi_t = ht_features(np.asarray(block.test), centres.test, cfg)
        outer = projected_outer(phi_h, phi_t, svd)
        del phi_h, phi_t
        phi_o = obs_features(np.asarray(block.observation), centres.observation, cfg)
        actions = np.asarray(block.actions)
        counts = np.bincount(actions, minlength=n_actions)
        total.sums += action_sums(phi_o, outer, actions, counts)
        total.counts += counts
    return total


class StreamEngine(Protocol):
    """Where the streamed fit's passes run (this process, or a Dask cluster).

    After pass 2 the engine holds every episode's whitened rows (:class:`ChunkEngine`: in
    the fit's :class:`WhitenedStore`; Dask: on the workers) and sums over the training rows
    ``start:`` where they are.
    """

    description: str
    keeps_rows: bool
    """True: the engine keeps the rows itself and fills only the store's rows (those kernel
    centres are chosen from); False: the store holds every episode."""

    def moments(
        self, history_length: int, test_length: int, max_episodes: int | None
    ) -> EpisodeMoments | None:
        """Pass 1: the merged moments of the first ``max_episodes`` episodes."""

    def whiten(
        self,
        whitenings: Whitenings,
        cfg: TPSRConfig,
        max_episodes: int | None,
        store: WhitenedStore,
    ) -> None:
        """Pass 2: whiten every episode; write the first ``store.n_episodes`` into ``store``."""

    def action_counts(self, store: WhitenedStore, start: int, n_actions: int) -> np.ndarray:
        """Training episodes per action over the rows ``start:``."""

    def p_sums(self, store: WhitenedStore, start: int, centres: Centres, cfg: TPSRConfig) -> PSums:
        """:func:`p_sums` over the rows ``start:`` (split and reduced as the engine likes)."""

    def parameter_sums(
        self,
        store: WhitenedStore,
        start: int,
        centres: Centres,
        svd: tuple[np.ndarray, np.ndarray, np.ndarray],
        cfg: TPSRConfig,
        n_actions: int,
    ) -> ActionSums:
        """:func:`parameter_sums` over the rows ``start:``."""


class ChunkEngine:
    """Runs every pass in this process, reading the chunks of ``source`` in order."""

    description = "streamed, 1 process"
    keeps_rows = False

    def __init__(self, source: ChunkSource) -> None:
        if not callable(source):
            raise ConfigError(
                "a streamed fit reads its data twice: give a callable that returns a fresh "
                "iterator of chunks"
            )
        self.source = source

    def moments(
        self, history_length: int, test_length: int, max_episodes: int | None
    ) -> EpisodeMoments | None:
        """Pass 1 (see :class:`StreamEngine`)."""
        return episode_moments(self.source(), history_length, test_length, max_episodes)

    def whiten(
        self,
        whitenings: Whitenings,
        cfg: TPSRConfig,
        max_episodes: int | None,
        store: WhitenedStore,
    ) -> None:
        """Pass 2 (see :class:`StreamEngine`)."""
        written = 0
        for rows in whitened_episodes(self.source(), whitenings, cfg, max_episodes):
            store.write(written, rows)
            written += len(rows)
        check_pass_counts(written, store.n_episodes)

    def action_counts(self, store: WhitenedStore, start: int, n_actions: int) -> np.ndarray:
        """See :class:`StreamEngine`."""
        return np.bincount(np.asarray(store.rows(start).actions), minlength=n_actions)

    def p_sums(self, store: WhitenedStore, start: int, centres: Centres, cfg: TPSRConfig) -> PSums:
        """See :class:`StreamEngine`."""
        return p_sums(store.rows(start), centres, cfg)

    def parameter_sums(
        self,
        store: WhitenedStore,
        start: int,
        centres: Centres,
        svd: tuple[np.ndarray, np.ndarray, np.ndarray],
        cfg: TPSRConfig,
        n_actions: int,
    ) -> ActionSums:
        """See :class:`StreamEngine`."""
        return parameter_sums(store.rows(start), centres, svd, cfg, n_actions)


def check_pass_counts(second: int, first: int) -> None:
    """Refuse a second pass that saw other episodes than the first (the data changed)."""
    if second != first:
        raise DataError(
            f"the second pass over the data gave {second} episodes, the first {first} (did a "
            "bag change during the fit?)"
        )


def fit_tpsr_streamed(
    source: ChunkSource | StreamEngine,
    *,
    config: TPSRConfig | None = None,
    max_episodes: int | None = None,
    progress: Progress | None = None,
    scratch_dir: Path | str | None = None,
) -> TPSRModel:
    """Learn the TPSR of ``fit_tpsr_episodes(make_episodes(whole, m, n, max_episodes))``.

    Args:
        source: a :data:`ChunkSource` (run here by a :class:`ChunkEngine`) or an engine.
        config: parameters (default :class:`TPSRConfig`).
        max_episodes: use only the first episodes (guide ``|E|``).
        progress: called with the name of each stage as it starts.
        scratch_dir: where the temporary memory maps go (default: the system's temp dir).

    Raises:
        DataError: as :func:`~tpsr_ros.core.tpsr.fit_tpsr`, and when the second pass does not
            see the episodes of the first (the data changed).
        ConfigError: action-aware features (not supported here).

    """
    cfg = config if config is not None else TPSRConfig()
    if max_episodes is not None and max_episodes < 1:
        raise ConfigError(f"the number of episodes must be at least 1, not {max_episodes}")
    if cfg.uses_actions:
        raise ConfigError(
            "the streamed fit does not support action-aware features (history_action_weight, "
            "test_action_weight); fit in memory instead"
        )
    if cfg.state_clip_quantile > 0:
        raise ConfigError(
            "the streamed fit does not support the state box (state_clip_quantile > 0); "
            "fit in memory instead"
        )
    engine: StreamEngine = source if hasattr(source, "moments") else ChunkEngine(source)  # type: ignore[arg-type,assignment]
    watch = Stopwatch(progress)
    watch.stage("pass 1: whitening statistics")
    moments = engine.moments(cfg.history_length, cfg.test_length, max_episodes)
    if moments is None:
        raise no_usable_episodes(cfg.history_length, cfg.test_length, "the data")
    n_episodes, n_actions = moments.episodes, moments.n_actions
    check_enough_episodes(n_episodes, cfg)
    watch.stage("whitening")
    whitenings = Whitenings.fit(moments, cfg)
    first = cfg.center_selection == "first"
    start = max(cfg.ht_centers, cfg.obs_centers) if first else 0  # first training row
    stored = start if first and engine.keeps_rows else n_episodes  # k-means reads every row
    with WhitenedStore(stored, whitenings, cfg, scratch_dir) as store:
        watch.stage("pass 2: whitened episodes")
        engine.whiten(whitenings, cfg, max_episodes, store)
        watch.stage("kernel centres")
        centres = _select_centres(store.rows(), cfg)
        check_action_counts(engine.action_counts(store, start, n_actions))
        watch.stage("P-statistics")
        sums = engine.p_sums(store, start, centres, cfg)
        n_train = sums.count
        p_h = sums.history / n_train
        p_th = sums.cross
        p_th /= n_train
        del sums
        watch.stage("SVD")
        u, s, v, s_all, usable = truncated_svd(p_th, cfg)
        del p_th
        watch.stage("parameters")
        b_star, b_inf = start_and_normaliser(p_h, s, v)
        b_sums = engine.parameter_sums(store, start, centres, (u, s, v), cfg, n_actions)
        scratch = store.nbytes
    watch.stop()
    big_b = action_operators(b_sums.sums, b_sums.counts, cfg.action_pooling)
    fit_info = {
        "episodes": int(n_episodes),
        "steps": int(moments.steps),
        "segments": int(moments.segments),
        "stamps_ns": list(moments.stamps) if moments.stamps else [],
        "training_episodes": int(n_train),
        "samples_per_action": b_sums.counts.tolist(),
        "usable_singular_values": usable,
        "timings": {name: round(sec, 6) for name, sec in watch.timings.items()},
        "streamed": {"engine": engine.description, "scratch_bytes": scratch},
    }
    big_b = big_b.reshape(n_actions, centres.observation.shape[0], cfg.rank, cfg.rank)
    return assemble_model(
        cfg,
        (whitenings.history, whitenings.test, whitenings.obs),
        centres.observation,
        (b_star, b_inf, big_b),
        s_all,
        fit_info,
    )


def fit_pca_streamed(
    source: ChunkSource,
    *,
    config: PCAConfig | None = None,
    history_length: int = 1,
    test_length: int = 1,
    max_episodes: int | None = None,
) -> PCAModel:
    """Fit the PCA baseline from one pass of merged moments.

    Equal to rounding to :func:`~tpsr_ros.core.pca_baseline.fit_pca` on every step of the
    episodes.
    """
    cfg = config if config is not None else PCAConfig()
    start = time.perf_counter()
    total: Moments | None = None
    n_actions = 0
    cutter = EpisodeCutter(history_length, test_length, max_episodes)
    for episodes in _episodes(source(), cutter):
        part = Moments.of(episodes.steps())
        total = part if total is None else total.merge(part)
        n_actions = int(episodes.n_actions)
    if total is None:
        raise no_usable_episodes(history_length, test_length, "the data")
    pca = Whitening.from_moments(total, cfg.dim, what="observations")
    return PCAModel(
        config=cfg,
        n_actions_=n_actions,
        mean=pca.mean_,
        components=pca.components_,
        eigenvalues=pca.eigenvalues_,
        explained_variance_ratio=pca.explained_variance_ratio_,
        fit_info={
            "steps": int(cutter.steps),
            "segments": int(cutter.segments),
            "stamps_ns": list(cutter.stamps or ()),
            "observations": int(total.count),
            "timings": {"PCA (streamed)": round(time.perf_counter() - start, 6)},
        },
    )
