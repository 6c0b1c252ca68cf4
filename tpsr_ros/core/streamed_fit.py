"""Streamed TPSR fit: guide Algorithms 1-3 over data that never sit in memory at once.

:func:`fit_tpsr_streamed` learns the model of ``fit_tpsr_episodes(make_episodes(whole))``
(equal to rounding, ~1e-12 relative) from a *chunk source*: a callable returning a fresh
iterator of :class:`~tpsr_ros.core.episodes.Trajectory` chunks whose concatenation is the
whole trajectory (e.g. :func:`tpsr_ros.io.trajectory.iter_trajectory_chunks`). It runs the
fit's one driver (:func:`tpsr_ros.core.tpsr.run_fit`) on :class:`StreamedFit`, which reads
the data twice:

1. **pass 1**: chunks are cut into episodes exactly as :func:`make_episodes` cuts the whole
   (:class:`EpisodeCutter` carries the unfinished tail of a segment into the next chunk and
   honours ``max_episodes``); each chunk's histories, tests and current observations give
   :class:`~tpsr_ros.core.moments.Moments` (mean, centred scatter), merged pairwise. The
   whitenings (Algorithm 1) come from the merged covariances.
2. **pass 2**: every episode is whitened (action codes joined, as the in-memory fit does)
   and only its whitened rows (``d_H + d_T + d_O`` floats, ~30) and current action are
   kept, in ``.npy`` memory maps in a temporary directory (:class:`WhitenedStore`; on
   Dask, on the workers).

Then, from the store and without reading the data again: kernel centres, the sums of
``phi_H`` and ``phi_T0^T phi_H`` over blocks of rows (:class:`PSums`; ``P_TH`` is
accumulated in place by BLAS ``dgemm``, so a 20 001 x 20 001 ``P_TH`` exists once), the
top-``r`` SVD, and a second blocked pass over the rows for the per-action sums of
``B_ao'``. A state box (``state_clip_quantile > 0``) reads its at most 4000 episodes a third
time. A refined fit (``refine_epochs``) reads its first ``refine_steps`` steps once more
and refines on them in memory (:func:`refinement_steps`), as the in-memory fit does. No
``(t, l)`` feature matrix for all of ``t`` and no ``O(t l^2)`` tensor is ever
formed: memory is bounded by the chunk size, the block size (:data:`BLOCK_BYTES`),
``P_TH`` and a refinement's ``refine_steps``, not by the data length.

Where the passes run is a :class:`StreamEngine`: :class:`ChunkEngine` runs them in this
process; ``learner.distributed`` runs the same functions as Dask tasks (one per bag, partial
sums reduced as a tree). The per-block arithmetic is the in-memory fit's own
(:mod:`tpsr_ros.core.tpsr_stages`).
"""

from __future__ import annotations

import tempfile
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
import scipy.linalg.blas

from tpsr_ros.core.episode_stream import (
    EpisodeCutter,
    EpisodeMoments,
    box_rows,
    episode_cutter,
    episode_moments,
    episodes_of,
    merge_moments,
    refinement_steps,
    whitened_episodes,
)
from tpsr_ros.core.episodes import Trajectory, no_usable_episodes
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.moments import Moments
from tpsr_ros.core.pca_baseline import PCAConfig, PCAModel
from tpsr_ros.core.refine import refine_tpsr
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr import BoxData, Survey, run_fit
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.tpsr_model import TPSRModel
from tpsr_ros.core.tpsr_stages import (
    Progress,
    action_sums,
    ht_features,
    obs_features,
    projected_outer,
    training_start,
)
from tpsr_ros.core.whitened import (
    WHITENED_FIELDS,
    ActionSums,
    Centres,
    WhitenedRows,
    Whitenings,
)
from tpsr_ros.core.whitening import Whitening

__all__ = [
    "BLOCK_BYTES",
    "WHITENED_FIELDS",
    "ChunkEngine",
    "ChunkSource",
    "EpisodeCutter",
    "EpisodeMoments",
    "PSums",
    "StreamEngine",
    "StreamedFit",
    "WhitenedStore",
    "block_rows",
    "box_rows",
    "episode_moments",
    "fit_pca_streamed",
    "fit_tpsr_streamed",
    "merge_moments",
    "p_sums",
    "parameter_sums",
    "whitened_episodes",
]
# EpisodeCutter, EpisodeMoments, episode_moments, merge_moments, whitened_episodes and
# box_rows live in tpsr_ros.core.episode_stream; they are named here for the engines.

ChunkSource = Callable[[], Iterable[Trajectory]]
"""Returns a fresh iterator over the chunks on every call (the fit reads the data twice)."""

BLOCK_BYTES = 64 * 2**20
"""Target size of one block's feature matrix; blocks hold 512 to 8192 rows."""

def block_rows(n_features: int) -> int:
    """Rows per block so that a ``(rows, n_features)`` float64 matrix is ~:data:`BLOCK_BYTES`."""
    return int(min(8192, max(512, BLOCK_BYTES // (8 * max(1, n_features)))))


class WhitenedStore:
    """Whitened episodes in ``.npy`` memory maps in a temporary directory (a context manager).

    ``write`` fills rows in any order; ``rows`` gives views. The directory and its files are
    removed on exit, whatever happened.
    """

    def __init__(
        self,
        n_episodes: int,
        widths: Mapping[str, int],
        directory: Path | str | None = None,
    ) -> None:
        self._tmp = tempfile.TemporaryDirectory(prefix="tpsr-stream-", dir=directory)
        root = Path(self._tmp.name)
        shapes = {name: (n_episodes, width) for name, width in widths.items()}
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
            for name in WHITENED_FIELDS
        })  # fmt: skip

    def close(self) -> None:
        """Drop the memory maps and remove the directory."""
        self._arrays.clear()
        self._tmp.cleanup()

    def __enter__(self) -> WhitenedStore:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


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
        self,
        history_length: int,
        test_length: int,
        max_episodes: int | None,
        stride: int | None = None,
    ) -> EpisodeMoments | None:
        """Pass 1: the merged moments of the first ``max_episodes`` episodes, one starting
        every ``stride`` steps (:class:`EpisodeCutter`)."""

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

    def box_data(self, indices: np.ndarray, cfg: TPSRConfig, max_episodes: int | None) -> BoxData:
        """The raw episodes ``indices`` (sorted; a third read of their data), for the box."""


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
        self,
        history_length: int,
        test_length: int,
        max_episodes: int | None,
        stride: int | None = None,
    ) -> EpisodeMoments | None:
        """Pass 1 (see :class:`StreamEngine`)."""
        return episode_moments(
            self.source(), history_length, test_length, max_episodes, stride
        )

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

    def box_data(self, indices: np.ndarray, cfg: TPSRConfig, max_episodes: int | None) -> BoxData:
        """See :class:`StreamEngine`."""
        cutter = episode_cutter(cfg, max_episodes)
        return box_rows(episodes_of(self.source(), cutter), indices)


def check_pass_counts(second: int, first: int) -> None:
    """Refuse a second pass that saw other episodes than the first (the data changed)."""
    if second != first:
        raise DataError(
            f"the second pass over the data gave {second} episodes, the first {first} (did a "
            "bag change during the fit?)"
        )


class StreamedFit:
    """The data of a :class:`StreamEngine`'s passes, as :func:`tpsr_ros.core.tpsr.run_fit`
    reads them (a context manager: the temporary store goes on exit)."""

    stages: Mapping[str, str | None] = {
        "survey": "pass 1: whitening statistics",
        "rows": "pass 2: whitened episodes",
        "features": None,
    }

    def __init__(
        self,
        passes: StreamEngine,
        max_episodes: int | None = None,
        scratch_dir: Path | str | None = None,
    ) -> None:
        self.passes = passes
        self.max_episodes = max_episodes
        self.scratch_dir = scratch_dir
        self._moments: EpisodeMoments | None = None
        self._store: WhitenedStore | None = None

    @property
    def store(self) -> WhitenedStore:
        """The whitened rows pass 2 kept here."""
        assert self._store is not None, "pass 2 has not run"
        return self._store

    def survey(self, cfg: TPSRConfig) -> Survey:
        """Pass 1: the merged moments of the first ``max_episodes`` episodes."""
        moments = self.passes.moments(
            cfg.history_length, cfg.test_length, self.max_episodes, cfg.episode_stride
        )
        if moments is None:
            raise no_usable_episodes(cfg.history_length, cfg.test_length, "the data")
        self._moments = moments
        info = {
            "steps": int(moments.steps),
            "segments": int(moments.segments),
            "stamps_ns": list(moments.stamps) if moments.stamps else [],
        }
        return Survey(moments.episodes, moments.n_actions, moments.observation.dim, info)

    def whitenings(self, cfg: TPSRConfig, codes: np.ndarray | None) -> Whitenings:
        """Whitenings from the merged covariances."""
        m = self._moments
        assert m is not None
        return Whitenings.from_moments(m.history, m.test, m.observation, cfg, codes)

    def whiten(self, whitenings: Whitenings, cfg: TPSRConfig) -> None:
        """Pass 2: every episode whitened; the store holds those the centres come from."""
        assert self._moments is not None
        n_episodes = self._moments.episodes
        first = cfg.center_selection == "first"
        stored = training_start(cfg) if first and self.passes.keeps_rows else n_episodes
        self._store = WhitenedStore(stored, whitenings.widths(cfg), self.scratch_dir)
        self.passes.whiten(whitenings, cfg, self.max_episodes, self._store)

    def centre_rows(self) -> WhitenedRows:
        """The stored rows."""
        return self.store.rows()

    def action_counts(self, start: int, n_actions: int) -> np.ndarray:
        """Training episodes per action, counted by the passes."""
        return self.passes.action_counts(self.store, start, n_actions)

    def features(self, start: int, centres: Centres, cfg: TPSRConfig) -> None:
        """Nothing: features are computed block by block inside the sums."""

    def p_statistics(
        self, start: int, centres: Centres, cfg: TPSRConfig
    ) -> tuple[np.ndarray, np.ndarray, int]:
        """``P_H`` and ``P_TH`` from the blocked sums (``P_TH`` divided in place)."""
        sums = self.passes.p_sums(self.store, start, centres, cfg)
        n_train = sums.count
        p_th = sums.cross
        p_th /= n_train
        return sums.history / n_train, p_th, int(n_train)

    def parameter_sums(
        self,
        start: int,
        centres: Centres,
        svd: tuple[np.ndarray, np.ndarray, np.ndarray],
        cfg: TPSRConfig,
        n_actions: int,
    ) -> ActionSums:
        """The blocked per-action sums."""
        return self.passes.parameter_sums(self.store, start, centres, svd, cfg, n_actions)

    def box_data(self, indices: np.ndarray, cfg: TPSRConfig) -> BoxData:
        """The state box's episodes, read a third time."""
        return self.passes.box_data(indices, cfg, self.max_episodes)

    def info(self) -> dict[str, Any]:
        """What ran the passes and how much scratch space the rows took."""
        return {"streamed": {"engine": self.passes.description, "scratch_bytes": self.store.nbytes}}

    def close(self) -> None:
        """Remove the temporary store."""
        if self._store is not None:
            self._store.close()

    def __enter__(self) -> StreamedFit:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def fit_tpsr_streamed(
    source: ChunkSource | StreamEngine,
    *,
    config: TPSRConfig | None = None,
    max_episodes: int | None = None,
    progress: Progress | None = None,
    scratch_dir: Path | str | None = None,
    sizing: Sizing | None = None,
    action_codes: np.ndarray | None = None,
    refine_source: ChunkSource | None = None,
) -> TPSRModel:
    """Learn the TPSR of ``fit_tpsr_episodes(make_episodes(whole, m, n, max_episodes))``,
    and refine it as :func:`~tpsr_ros.core.learn.fit_tpsr_trajectory` does when the config
    asks for it (``refine_epochs``): on the same steps, the first ``refine_steps``, read
    once more and held in memory (:func:`refinement_steps`). The search follows the last
    bits of its spectral start, so the refined operators agree with the fit in memory's
    only as closely as the search allows (on 24000 steps of ``partial-strip``: 0.5 % of
    their largest value, the same number of iterations).

    Args:
        source: a :data:`ChunkSource` (run here by a :class:`ChunkEngine`) or an engine.
        config: parameters (default :class:`TPSRConfig`); every option of the in-memory fit.
        max_episodes: use only the first episodes (guide ``|E|``).
        progress: called with the name of each stage as it starts.
        scratch_dir: where the temporary memory maps go (default: the system's temp dir).
        sizing: size the fit to the data once pass 1 has counted it, as
            :func:`~tpsr_ros.core.tpsr.fit_tpsr` does.
        action_codes: the command of each action, for action-aware features.
        refine_source: the chunks the refinement reads its steps from, in this process
            (default: ``source`` when it is a chunk source; an engine needs it).

    Raises:
        DataError: as :func:`~tpsr_ros.core.tpsr.fit_tpsr`, and when the second pass does not
            see the episodes of the first (the data changed).

    """
    if max_episodes is not None and max_episodes < 1:
        raise ConfigError(f"the number of episodes must be at least 1, not {max_episodes}")
    is_engine = hasattr(source, "moments")
    if refine_source is None and not is_engine:
        refine_source = source  # type: ignore[assignment]
    if config is not None and config.refine_epochs and refine_source is None:
        raise ConfigError(
            "the refinement reads its steps in this process: give refine_source, or "
            "refine_epochs=0"
        )
    passes: StreamEngine = source if is_engine else ChunkEngine(source)  # type: ignore[arg-type,assignment]
    with StreamedFit(passes, max_episodes, scratch_dir) as engine:
        model = run_fit(
            engine, config, progress=progress, sizing=sizing, action_codes=action_codes
        )
    if not model.config.refine_epochs:
        return model
    assert refine_source is not None
    if progress is not None:
        progress(f"reading the steps to refine on (at most {model.config.refine_steps})")
    steps = refinement_steps(refine_source(), model.config, max_episodes)
    if progress is not None:
        progress("refinement through the filter")
    return refine_tpsr(
        model, steps.actions, steps.observations, steps.segment_bounds(), progress=progress,
        sizing=sizing,
    )  # fmt: skip


def fit_pca_streamed(
    source: ChunkSource,
    *,
    config: PCAConfig | None = None,
    history_length: int = 1,
    test_length: int = 1,
    max_episodes: int | None = None,
    stride: int | None = None,
) -> PCAModel:
    """Fit the PCA baseline from one pass of merged moments.

    Equal to rounding to :func:`~tpsr_ros.core.pca_baseline.fit_pca` on every step of the
    episodes (one starting every ``stride`` steps; default ``m + 1 + n``, as
    :class:`~tpsr_ros.core.episode_stream.EpisodeCutter`).
    """
    cfg = config if config is not None else PCAConfig()
    start = time.perf_counter()
    total: Moments | None = None
    n_actions = 0
    cutter = EpisodeCutter(history_length, test_length, max_episodes, stride=stride)
    for episodes in episodes_of(source(), cutter):
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
