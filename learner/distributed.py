"""The streamed TPSR fit on a Dask cluster (``learner fit --workers N`` / ``--scheduler ADDR``).

:class:`DaskEngine` runs the passes of :func:`tpsr_ros.core.streamed_fit.fit_tpsr_streamed`
as ``dask.distributed`` tasks. Workers read the bags themselves, from the same paths, and
what they compute stays on them as futures; the client receives sums:

- pass 1: one task per bag (segments never cross bags, so each bag's episodes are its
  own); the moments (two ``k x k`` scatters and one more per bag, e.g. 3 x 4.7 MB for
  16x16 RGB) are merged as a binary tree of tasks and only the total is fetched;
- pass 2: one task per bag; each bag's whitened rows (~30 floats per episode) **stay on
  its worker**. The client fetches only each bag's episode count and the rows kernel
  centres are chosen from: for 'first' centres the first ``max(l_H, l_O)`` episodes in
  bag order (client memory independent of the data), for k-means every row (the
  client runs k-means on all of them, as the in-memory fit does);
- the feature sums (action counts, ``P_H``/``P_TH``, the per-action ``B`` sums): tasks on
  slices of those futures, a few per worker, reduced as a tree. ``P_TH`` partial sums
  travel only while ``P_TH`` is at most :data:`MAX_SHIPPED_P_TH_BYTES`; for larger ones
  (thousands of centres) each bag's training rows are fetched in turn and summed into one
  ``P_TH`` in the client, in place (a worker's and a tree's copies of 3 GB would not fit).

With ``max_episodes`` the first pass counts each bag's episodes and re-reads the bag where
the limit falls with its share; later bags are left out.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import operator
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import CancelledError
from pathlib import Path
from types import MappingProxyType
from typing import Any, TypeVar

import numpy as np

from tpsr_ros.core.episode_stream import (
    EpisodeMoments,
    box_rows,
    episode_cutter,
    episode_moments,
    episodes_of,
    merge_moments,
    whitened_episodes,
)
from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.streamed_fit import (
    PSums,
    WhitenedStore,
    block_rows,
    p_sums,
    parameter_sums,
)
from tpsr_ros.core.tpsr import BoxData
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.whitened import ActionSums, Centres, WhitenedRows, Whitenings
from tpsr_ros.io.bag_chunks import BagChunks

__all__ = [
    "MAX_SHIPPED_P_TH_BYTES",
    "SCHEDULER_HTTP",
    "DaskEngine",
    "check_bags_readable_here",
    "check_bags_visible",
    "dask_client",
    "gather",
    "result",
    "tree_reduce",
    "wait_for",
]

MAX_SHIPPED_P_TH_BYTES = 256 * 2**20
DEFAULT_TIMEOUT = 10.0
SCHEDULER_HTTP = MappingProxyType({"dashboard_address": "127.0.0.1:0"})
"""The local cluster scheduler's HTTP server (health, metrics; served without a dashboard
too): on a free loopback port, not Dask's default 8787, where another cluster (a second
fit, the user's own) would make it warn that the port is in use."""

T = TypeVar("T")


def _distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise ConfigError(
            "--workers and --scheduler need dask.distributed: pip install 'tpsr-ros[dask]'"
        ) from None
    return distributed


async def _probe(address: str, timeout: float) -> None:
    """Open and close one comm to ``address``, the whole handshake bounded by ``timeout``.

    ``distributed.Client(address, timeout=...)`` bounds only the TCP connect: a listener that
    accepts and never answers would hold it forever.
    """
    import distributed.comm

    comm = await asyncio.wait_for(distributed.comm.connect(address, timeout=timeout), timeout)
    await comm.close()


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


@contextlib.contextmanager
def dask_client(
    *, scheduler: str | None = None, workers: int | None = None, timeout: float = DEFAULT_TIMEOUT
) -> Iterator[Any]:
    """Yield a ``distributed.Client`` of the scheduler at ``scheduler`` or of a local cluster.

    A scheduler that does not answer within ``timeout`` seconds (no connection, or a
    connection with no handshake) is a one-line ``ConfigError``. The local cluster has
    ``workers`` processes of one thread each, with worker logs silenced below CRITICAL (a
    failed task is reported once, by the client, as one line) and its scheduler's HTTP
    server on a free loopback port (:data:`SCHEDULER_HTTP`). On exit the client (and the
    local cluster) close; a task lost with its worker becomes a one-line ``ConfigError``.
    """
    distributed = _distributed()
    with contextlib.ExitStack() as stack:
        if scheduler is not None:
            try:
                asyncio.run(_probe(scheduler, timeout))
                client = distributed.Client(scheduler, timeout=f"{timeout}s", set_as_default=False)
            except (OSError, TimeoutError, asyncio.TimeoutError, ValueError) as exc:
                raise ConfigError(
                    f"no Dask scheduler answers at {scheduler!r} within {timeout:g} s "
                    f"({_first_line(exc)})"
                ) from None
        else:
            cluster = stack.enter_context(
                distributed.LocalCluster(
                    n_workers=int(workers or 1),
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    scheduler_kwargs=SCHEDULER_HTTP,
                    silence_logs=logging.CRITICAL,
                )
            )
            client = distributed.Client(cluster, set_as_default=False)
        stack.callback(client.close)
        try:
            yield client
        except (CancelledError, distributed.KilledWorker) as exc:
            first_sentence = _first_line(exc).split(". ")[0].rstrip(".")
            raise ConfigError(f"the Dask cluster lost a task: {first_sentence}") from None


def wait_for(client: Any, futures: Sequence[Any], poll: float = DEFAULT_TIMEOUT) -> None:
    """Wait until ``futures`` are done; a cluster left with no workers is a ``ConfigError``.

    Dask waits for new workers forever when every worker has gone; this checks the
    scheduler every ``poll`` seconds instead.
    """
    distributed = _distributed()
    while True:
        try:
            with client.as_current():
                distributed.wait(list(futures), timeout=poll)
            return
        except distributed.TimeoutError:  # asyncio's, not the builtin, on Python 3.10
            if not client.nthreads():
                raise ConfigError(
                    f"the Dask scheduler at {client.scheduler.address} has no workers left "
                    "(tasks would wait for new workers forever)"
                ) from None


def result(client: Any, future: Any, poll: float = DEFAULT_TIMEOUT) -> Any:
    """``future.result()`` after :func:`wait_for`."""
    wait_for(client, [future], poll)
    return future.result()


def gather(client: Any, futures: Sequence[Any], poll: float = DEFAULT_TIMEOUT) -> list[Any]:
    """``client.gather(futures)`` after :func:`wait_for`."""
    wait_for(client, futures, poll)
    return client.gather(list(futures))  # type: ignore[no-any-return]


def _missing(bags: Sequence[str]) -> list[str]:
    return [bag for bag in bags if not Path(bag).is_dir()]


def check_bags_readable_here(bags: Sequence[Path | str], why: str) -> None:
    """Refuse bags this process cannot see (``why``: what reads them here, and the way out)."""
    if missing := _missing([str(bag) for bag in bags]):
        raise ConfigError(f"this process cannot see bag(s) {missing}: {why}")


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
    reader: BagChunks, bag: str, m: int, n: int, limit: int | None, stride: int | None
) -> EpisodeMoments | None:
    return episode_moments(reader.read(bag), m, n, limit, stride)


def _bag_whitened(
    reader: BagChunks, bag: str, whitenings: Whitenings, cfg: TPSRConfig, limit: int | None
) -> WhitenedRows | None:
    parts = list(whitened_episodes(reader.read(bag), whitenings, cfg, limit))
    return WhitenedRows.concatenate(parts) if parts else None


def _bag_box(
    reader: BagChunks, bag: str, cfg: TPSRConfig, limit: int | None, indices: np.ndarray
) -> BoxData:
    cutter = episode_cutter(cfg, limit)
    return box_rows(episodes_of(reader.read(bag), cutter), indices)


def _count(moments: EpisodeMoments | None) -> int:
    return 0 if moments is None else moments.episodes


def _length(rows: WhitenedRows | None) -> int:
    return 0 if rows is None else len(rows)


def _slice(rows: WhitenedRows, start: int, stop: int) -> WhitenedRows:
    return rows.rows(start, stop).copy()


def _action_counts(rows: WhitenedRows, start: int, stop: int, n_actions: int) -> np.ndarray:
    return np.bincount(rows.actions[start:stop], minlength=n_actions)


def _p_sums(rows: WhitenedRows, start: int, stop: int, centres: Centres, cfg: TPSRConfig) -> PSums:
    return p_sums(rows.rows(start, stop), centres, cfg)


def _parameter_sums(
    rows: WhitenedRows,
    start: int,
    stop: int,
    shared: tuple[Centres, tuple[np.ndarray, np.ndarray, np.ndarray]],
    cfg: TPSRConfig,
    n_actions: int,
) -> ActionSums:
    centres, svd = shared
    return parameter_sums(rows.rows(start, stop), centres, svd, cfg, n_actions)


def _merged(a: T, b: T) -> T:
    """``a.merged(b)`` of two partial sums (PSums, ActionSums), as a picklable function."""
    return a.merged(b)  # type: ignore[attr-defined,no-any-return]


def tree_reduce(
    client: Any, futures: list[Any], combine: Callable[[T, T], T], poll: float = DEFAULT_TIMEOUT
) -> T:
    """Combine ``futures`` pairwise on the cluster, level by level, and fetch the result."""
    if not futures:
        raise ConfigError("nothing to reduce")
    while len(futures) > 1:
        pairs = zip(futures[::2], futures[1::2], strict=False)
        merged = [client.submit(combine, a, b, pure=False) for a, b in pairs]
        futures = merged + ([futures[-1]] if len(futures) % 2 else [])
    return result(client, futures[0], poll)  # type: ignore[no-any-return]


class DaskEngine:
    """Runs the streamed fit's passes on the workers of ``client`` (one task per bag).

    After pass 2 each bag's whitened rows are a future on a worker (:attr:`keeps_rows`).
    """

    keeps_rows = True

    def __init__(
        self,
        client: Any,
        bags: Sequence[Path | str],
        reader: BagChunks,
        poll: float = DEFAULT_TIMEOUT,
    ) -> None:
        self.client = client
        self.poll = poll
        """Seconds between checks that the cluster still has workers."""
        self.bags = [str(Path(bag).absolute()) for bag in bags]
        self.reader = reader
        self.n_workers = max(1, len(client.scheduler_info().get("workers", {})))
        self.description = f"dask, {self.n_workers} worker(s) at {client.scheduler.address}"
        self._limits: list[int | None] = []
        self._counts: list[int] = []
        self._rows: list[tuple[Any, int, int]] = []
        """Pass 2: each bag's whitened rows (a future) with its first episode and count."""

    def moments(
        self,
        history_length: int,
        test_length: int,
        max_episodes: int | None,
        stride: int | None = None,
    ) -> Any:
        """Pass 1: one task per bag, counts fetched, moments merged as a tree."""
        submit = self.client.submit
        m, n = history_length, test_length
        futures = [
            submit(_bag_moments, self.reader, bag, m, n, None, stride, pure=False)
            for bag in self.bags
        ]
        counts = gather(self.client, [submit(_count, f, pure=False) for f in futures], self.poll)
        limits: list[int | None] = [None] * len(self.bags)
        if max_episodes is not None:
            remaining = max_episodes
            for i, count in enumerate(counts):
                limits[i] = min(count, remaining)
                if 0 < remaining < count:  # the limit falls inside this bag: re-read its share
                    futures[i] = submit(
                        _bag_moments, self.reader, self.bags[i], m, n, remaining, stride,
                        pure=False,
                    )
                counts[i] = limits[i]  # bags after the limit: 0, left out
                remaining -= counts[i]
        self._limits, self._counts = limits, counts
        kept = [f for f, c in zip(futures, counts, strict=True) if c > 0]
        return tree_reduce(self.client, kept, merge_moments, self.poll) if kept else None

    def whiten(
        self,
        whitenings: Whitenings,
        cfg: TPSRConfig,
        max_episodes: int | None,
        store: WhitenedStore,
    ) -> None:
        """Pass 2: one task per bag, rows kept on the workers; ``store`` gets the first rows."""
        shared = self.client.scatter(whitenings, broadcast=True, hash=False)
        offsets = np.concatenate([[0], np.cumsum(self._counts)]).astype(int)
        kept = [i for i in range(len(self.bags)) if self._counts[i] > 0]
        futures = [
            self.client.submit(
                _bag_whitened, self.reader, self.bags[i], shared, cfg, self._limits[i], pure=False
            )
            for i in kept
        ]
        lengths = gather(
            self.client, [self.client.submit(_length, f, pure=False) for f in futures], self.poll
        )
        for i, got in zip(kept, lengths, strict=True):
            if got != self._counts[i]:
                raise DataError(
                    f"bag {self.bags[i]!r} gave {got} episodes in the second pass and "
                    f"{self._counts[i]} in the first (did it change during the fit?)"
                )
        self._rows = [
            (future, int(offsets[i]), self._counts[i])
            for future, i in zip(futures, kept, strict=True)
        ]
        for future, first, count in self._rows:  # one bag at a time, in bag order
            wanted = min(count, store.n_episodes - first)
            if wanted <= 0:
                break
            part = self.client.submit(_slice, future, 0, wanted, pure=False)
            store.write(first, result(self.client, part, self.poll))

    def _ranges(self, start: int, n_features: int) -> list[tuple[Any, int, int]]:
        """Slices ``(future, a, b)`` of the rows ``start:``, a few per worker."""
        total = sum(count for _, _, count in self._rows) - start
        size = max(block_rows(n_features), -(-total // (2 * self.n_workers)))
        ranges = []
        for future, first, count in self._rows:
            for a in range(max(0, start - first), count, size):
                ranges.append((future, a, min(a + size, count)))
        return ranges

    def action_counts(self, store: WhitenedStore, start: int, n_actions: int) -> np.ndarray:
        """Training episodes per action, counted on the workers."""
        futures = [
            self.client.submit(_action_counts, future, a, b, n_actions, pure=False)
            for future, a, b in self._ranges(start, 1)
        ]
        return tree_reduce(self.client, futures, operator.add, self.poll)

    def p_sums(self, store: WhitenedStore, start: int, centres: Centres, cfg: TPSRConfig) -> PSums:
        """Eqs. 3.1-3.2 sums on the workers (or here, bag by bag, for a huge ``P_TH``)."""
        n_t, n_h = centres.test.shape[0] + 1, centres.history.shape[0] + 1
        ranges = self._ranges(start, max(n_t, n_h))
        if n_t * n_h * 8 > MAX_SHIPPED_P_TH_BYTES:
            sums = PSums.zeros(n_t, n_h)
            for future, a, b in ranges:  # the rows come here, one slice at a time
                part = self.client.submit(_slice, future, a, b, pure=False)
                p_sums(result(self.client, part, self.poll), centres, cfg, into=sums)
            return sums
        shared = self.client.scatter(centres, broadcast=True, hash=False)
        futures = [
            self.client.submit(_p_sums, future, a, b, shared, cfg, pure=False)
            for future, a, b in ranges
        ]
        return tree_reduce(self.client, futures, _merged, self.poll)

    def parameter_sums(
        self,
        store: WhitenedStore,
        start: int,
        centres: Centres,
        svd: tuple[np.ndarray, np.ndarray, np.ndarray],
        cfg: TPSRConfig,
        n_actions: int,
    ) -> ActionSums:
        """Eqs. 3.3 and 3.7 sums on the workers, reduced as a tree."""
        shared = self.client.scatter((centres, svd), broadcast=True, hash=False)
        widest = max(centres.test.shape[0], centres.history.shape[0]) + 1
        futures = [
            self.client.submit(_parameter_sums, future, a, b, shared, cfg, n_actions, pure=False)
            for future, a, b in self._ranges(start, widest)
        ]
        return tree_reduce(self.client, futures, _merged, self.poll)

    def box_data(self, indices: np.ndarray, cfg: TPSRConfig, max_episodes: int | None) -> BoxData:
        """The state box's episodes: each bag's own read by a task, gathered in bag order."""
        offsets = np.concatenate([[0], np.cumsum(self._counts)]).astype(int)
        futures = []
        for i, bag in enumerate(self.bags):
            local = indices[(indices >= offsets[i]) & (indices < offsets[i + 1])] - offsets[i]
            if local.size:
                futures.append(
                    self.client.submit(
                        _bag_box, self.reader, bag, cfg, self._limits[i], local, pure=False
                    )
                )
        parts = gather(self.client, futures, self.poll)
        joined = [np.concatenate(column) for column in zip(*parts, strict=True)]
        return joined[0], joined[1], joined[2], joined[3]
