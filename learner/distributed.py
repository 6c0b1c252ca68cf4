"""The streamed TPSR fit on a Dask cluster (``learner fit --workers N`` / ``--scheduler ADDR``).

:class:`DaskEngine` runs the passes of :func:`tpsr_ros.core.streamed_fit.fit_tpsr_streamed`
as ``dask.distributed`` tasks:

- pass 1 and pass 2: one task per bag (segments never cross bags, so each bag's episodes
  are its own). Workers read the bags themselves, from the same paths, so only the results
  travel: pass 1 the moments (two ``k x k`` scatters and one more per bag, e.g. 3 x 4.7 MB
  for 16x16 RGB), merged as a binary tree of tasks; pass 2 each bag's whitened rows
  (~30 floats per episode), written into the client's memory maps in bag order, so 'first'
  centres are the first episodes of the first bag;
- the feature sums: the training rows split into a few parts per worker, one task each,
  reduced as a tree. ``P_TH`` partial sums travel only while ``P_TH`` is at most
  :data:`MAX_SHIPPED_P_TH_BYTES`; larger ones (thousands of centres) are summed in the
  client's process, in place.

With ``max_episodes`` the first pass counts each bag's episodes and re-reads the bag where
the limit falls with its share; later bags are left out.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.streamed_fit import (
    ActionSums,
    Centres,
    EpisodeMoments,
    PSums,
    WhitenedRows,
    WhitenedStore,
    Whitenings,
    block_rows,
    episode_moments,
    merge_moments,
    p_sums,
    parameter_sums,
    whitened_episodes,
)
from tpsr_ros.core.tpsr import TPSRConfig
from tpsr_ros.io.bag_chunks import BagChunks

__all__ = ["MAX_SHIPPED_P_TH_BYTES", "DaskEngine", "check_bags_visible", "dask_client"]

MAX_SHIPPED_P_TH_BYTES = 256 * 2**20
DEFAULT_TIMEOUT = 10.0

T = TypeVar("T")


def _distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise ConfigError(
            "--workers and --scheduler need dask.distributed: pip install 'tpsr-ros[dask]'"
        ) from None
    return distributed


@contextlib.contextmanager
def dask_client(
    *, scheduler: str | None = None, workers: int | None = None, timeout: float = DEFAULT_TIMEOUT
) -> Iterator[Any]:
    """Yield a ``distributed.Client`` of the scheduler at ``scheduler`` or of a local cluster.

    A scheduler that does not answer within ``timeout`` seconds is a one-line ``ConfigError``.
    The local cluster has ``workers`` processes of one thread each. On exit the client (and
    the local cluster) close; a worker lost mid-fit becomes a one-line ``ConfigError``.
    """
    distributed = _distributed()
    with contextlib.ExitStack() as stack:
        if scheduler is not None:
            try:
                client = distributed.Client(scheduler, timeout=f"{timeout}s", set_as_default=False)
            except (OSError, TimeoutError, ValueError) as exc:
                reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise ConfigError(
                    f"no Dask scheduler answers at {scheduler!r} within {timeout:g} s ({reason})"
                ) from None
        else:
            cluster = stack.enter_context(
                distributed.LocalCluster(
                    n_workers=int(workers or 1),
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    silence_logs=logging.ERROR,
                )
            )
            client = distributed.Client(cluster, set_as_default=False)
        stack.callback(client.close)
        try:
            yield client
        except (distributed.client.FutureCancelledError, distributed.KilledWorker) as exc:
            raise ConfigError(f"the Dask cluster lost a task: {exc}") from None


def _missing(bags: Sequence[str]) -> list[str]:
    return [bag for bag in bags if not Path(bag).is_dir()]


def check_bags_visible(client: Any, bags: Sequence[Path | str]) -> None:
    """Refuse bags that some worker cannot see at the same path (workers read them)."""
    paths = [str(Path(bag).absolute()) for bag in bags]
    answers: dict[str, list[str]] = client.run(_missing, paths)
    if not answers:
        raise ConfigError("the Dask cluster has no workers")
    for worker, missing in sorted(answers.items()):
        if missing:
            raise ConfigError(
                f"Dask worker {worker} cannot see bag(s) {missing}: workers read the bags "
                "themselves, so they must be on storage every worker mounts at the same path"
            )


def _bag_moments(
    reader: BagChunks, bag: str, m: int, n: int, limit: int | None
) -> EpisodeMoments | None:
    return episode_moments(reader.read(bag), m, n, limit)


def _bag_whitened(
    reader: BagChunks, bag: str, whitenings: Whitenings, cfg: TPSRConfig, limit: int | None
) -> WhitenedRows | None:
    parts = list(whitened_episodes(reader.read(bag), whitenings, cfg, limit))
    if not parts:
        return None
    names = ("history", "test", "observation", "test0", "actions")
    return WhitenedRows(
        *(
            None if getattr(parts[0], name) is None
            else np.concatenate([getattr(p, name) for p in parts])
            for name in names
        )
    )  # fmt: skip


def _count(moments: EpisodeMoments | None) -> int:
    return 0 if moments is None else moments.episodes


def _merge_psums(a: PSums, b: PSums) -> PSums:
    return a.merged(b)


def _merge_action_sums(a: ActionSums, b: ActionSums) -> ActionSums:
    return a.merged(b)


def tree_reduce(client: Any, futures: list[Any], combine: Callable[[T, T], T]) -> T:
    """Combine ``futures`` pairwise on the cluster, level by level, and fetch the result."""
    if not futures:
        raise ConfigError("nothing to reduce")
    while len(futures) > 1:
        pairs = zip(futures[::2], futures[1::2], strict=False)
        merged = [client.submit(combine, a, b, pure=False) for a, b in pairs]
        futures = merged + ([futures[-1]] if len(futures) % 2 else [])
    return futures[0].result()  # type: ignore[no-any-return]


class DaskEngine:
    """Runs the streamed fit's passes on the workers of ``client`` (one task per bag)."""

    def __init__(self, client: Any, bags: Sequence[Path | str], reader: BagChunks) -> None:
        self.client = client
        self.bags = [str(Path(bag).absolute()) for bag in bags]
        self.reader = reader
        self.n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        self.description = f"dask, {self.n_workers} worker(s) at {client.scheduler.address}"
        self._limits: list[int | None] = []
        self._counts: list[int] = []

    def moments(self, history_length: int, test_length: int, max_episodes: int | None) -> Any:
        """Pass 1: one task per bag, counts fetched, moments merged as a tree."""
        submit = self.client.submit
        m, n = history_length, test_length
        futures = [
            submit(_bag_moments, self.reader, bag, m, n, None, pure=False) for bag in self.bags
        ]
        counts = self.client.gather([submit(_count, f, pure=False) for f in futures])
        limits: list[int | None] = [None] * len(self.bags)
        if max_episodes is not None:
            remaining = max_episodes
            for i, count in enumerate(counts):
                limits[i] = min(count, remaining)
                if 0 < remaining < count:  # the limit falls inside this bag: re-read its share
                    futures[i] = submit(
                        _bag_moments, self.reader, self.bags[i], m, n, remaining, pure=False
                    )
                counts[i] = limits[i]  # bags after the limit: 0, left out
                remaining -= counts[i]
        self._limits, self._counts = limits, counts
        kept = [f for f, c in zip(futures, counts, strict=True) if c > 0]
        return tree_reduce(self.client, kept, merge_moments) if kept else None

    def whiten(
        self,
        whitenings: Whitenings,
        cfg: TPSRConfig,
        max_episodes: int | None,
        store: WhitenedStore,
    ) -> None:
        """Pass 2: one task per bag; each bag's rows go to its place in ``store``."""
        shared = self.client.scatter(whitenings, broadcast=True, hash=False)
        offsets = np.concatenate([[0], np.cumsum(self._counts)]).astype(int)
        futures = {
            self.client.submit(
                _bag_whitened, self.reader, bag, shared, cfg, self._limits[i], pure=False
            ): i
            for i, bag in enumerate(self.bags)
            if self._counts[i] > 0
        }
        for future, i in futures.items():  # all run at once; fetched in bag order
            rows = future.result()
            got = 0 if rows is None else len(rows)
            if got != self._counts[i]:
                raise DataError(
                    f"bag {self.bags[i]!r} gave {got} episodes in the second pass and "
                    f"{self._counts[i]} in the first (did it change during the fit?)"
                )
            store.write(int(offsets[i]), rows)

    def _parts(self, rows: WhitenedRows, n_features: int) -> list[WhitenedRows]:
        size = max(block_rows(n_features), -(-len(rows) // (2 * self.n_workers)))
        return [rows.rows(a, a + size).copy() for a in range(0, len(rows), size)]

    def p_sums(self, rows: WhitenedRows, centres: Centres, cfg: TPSRConfig) -> PSums:
        """Eqs. 3.1-3.2 sums: parts of the rows on the workers, or here for a huge ``P_TH``."""
        n_t, n_h = centres.test.shape[0] + 1, centres.history.shape[0] + 1
        if n_t * n_h * 8 > MAX_SHIPPED_P_TH_BYTES:
            return p_sums(rows, centres, cfg)
        shared = self.client.scatter(centres, broadcast=True, hash=False)
        futures = [
            self.client.submit(p_sums, part, shared, cfg, pure=False)
            for part in self._parts(rows, max(n_t, n_h))
        ]
        return tree_reduce(self.client, futures, _merge_psums)

    def parameter_sums(
        self,
        rows: WhitenedRows,
        centres: Centres,
        svd: tuple[np.ndarray, np.ndarray, np.ndarray],
        cfg: TPSRConfig,
        n_actions: int,
    ) -> ActionSums:
        """Eqs. 3.3 and 3.7 sums over parts of the rows on the workers."""
        shared = self.client.scatter((centres, svd), broadcast=True, hash=False)
        widest = max(centres.test.shape[0], centres.history.shape[0]) + 1
        futures = [
            self.client.submit(_parameter_sums, part, shared, cfg, n_actions, pure=False)
            for part in self._parts(rows, widest)
        ]
        return tree_reduce(self.client, futures, _merge_action_sums)


def _parameter_sums(
    rows: WhitenedRows,
    shared: tuple[Centres, tuple[np.ndarray, np.ndarray, np.ndarray]],
    cfg: TPSRConfig,
    n_actions: int,
) -> ActionSums:
    centres, svd = shared
    return parameter_sums(rows, centres, svd, cfg, n_actions)
