"""Continuous velocity commands to the discrete actions of the per-action operators.

An :class:`ActionCodebook` names the command components it uses (``linear.x``,
``angular.z``...) and holds one code (a command vector) per action. Two kinds:

- ``sim``: a simulator's action grid (:mod:`tpsr_ros.core.actions`): the 25 ``(linear.x,
  linear.y)`` pairs, or ``drive``'s 9 ``(linear.x, angular.z)``; each component snapped
  on its own, as every simulator bag has always been read;
- ``kmeans``: codes learned from the training commands by k-means (:func:`fit_codebook`,
  seeded, best of several restarts); a command maps to its nearest code (Euclidean, in the
  commands' own units).

Commands far from every code are not hidden: :meth:`ActionCodebook.assign` returns each
command's distance to its code, and :attr:`ActionCodebook.far_distance` (half the smallest
distance between two codes) is the line beyond which a command is reported as far.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from scipy.cluster.vq import ClusterError, kmeans2, vq
from scipy.spatial.distance import cdist

from tpsr_ros.core.actions import ActionGrid, environment_grid
from tpsr_ros.core.errors import ConfigError, DataError

__all__ = [
    "COMPONENTS",
    "DEFAULT_COMPONENTS",
    "ActionCodebook",
    "cluster_count",
    "fit_codebook",
    "sim_codebook",
]

COMPONENTS = (
    "linear.x",
    "linear.y",
    "linear.z",
    "angular.x",
    "angular.y",
    "angular.z",
)
"""Twist components a codebook can use."""
DEFAULT_COMPONENTS = ("linear.x", "linear.y", "angular.z")
KMEANS_RESTARTS = 10
CLUSTERED = 0.5
"""Mean silhouette from which commands count as forming clear clusters (a robot driven by a
few discrete commands plus jitter: 0.7-0.8 at jitter of a fifth of the spacing; 0.4 for
commands spread evenly)."""
SILHOUETTE_SAMPLE = 1000
"""Commands the cluster count looks at (seeded sample): the silhouette costs their square."""


@dataclass(frozen=True, eq=False)
class ActionCodebook:
    """Discrete actions as command vectors.

    Attributes:
        kind: ``"sim"`` (a simulator's grid: every combination of per-component levels,
            row-major) or ``"kmeans"``.
        components: the Twist components of each code, e.g. ``("linear.x", "linear.y")``.
        codes: ``(K, len(components))`` float64, the command of each action.

    """

    kind: str
    components: tuple[str, ...]
    codes: np.ndarray

    def __post_init__(self) -> None:
        codes = np.array(self.codes, dtype=np.float64)
        if self.kind not in ("sim", "kmeans"):
            raise ConfigError(f"codebook kind {self.kind!r} is not sim or kmeans")
        if not self.components or any(c not in COMPONENTS for c in self.components):
            raise ConfigError(
                f"codebook components {list(self.components)} must be some of {list(COMPONENTS)}"
            )
        if len(set(self.components)) != len(self.components):
            raise ConfigError(f"codebook components {list(self.components)} repeat")
        if codes.ndim != 2 or codes.shape[1] != len(self.components) or codes.shape[0] < 1:
            raise ConfigError(
                f"codebook codes must be (K, {len(self.components)}), got {codes.shape}"
            )
        if not np.isfinite(codes).all():
            raise ConfigError("codebook codes must be finite")
        codes.setflags(write=False)
        object.__setattr__(self, "components", tuple(self.components))
        object.__setattr__(self, "codes", codes)
        if self.kind == "sim" and not np.array_equal(self._grid.codes, codes):
            raise ConfigError("a sim codebook's codes must be a full grid in row-major order")

    @cached_property
    def _grid(self) -> ActionGrid:
        """The grid whose levels are each column's values (kind ``sim``)."""
        levels = tuple(tuple(float(v) for v in np.unique(col)) for col in self.codes.T)
        return ActionGrid(self.components, levels)

    def __len__(self) -> int:
        return int(self.codes.shape[0])

    @cached_property
    def far_distance(self) -> float:
        """Half the smallest distance between two codes: commands beyond it are reported.

        Cached: the codes are fixed, and the filter node asks for it at every command.
        """
        if len(self) < 2:
            return float("inf")
        gaps = np.linalg.norm(self.codes[:, None, :] - self.codes[None, :, :], axis=2)
        return float(gaps[np.triu_indices(len(self), 1)].min() / 2)

    def assign(self, commands: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Action index ``(N,)`` and distance to its code ``(N,)`` of commands ``(N, d)``."""
        cmd = np.asarray(commands, dtype=np.float64).reshape(-1, len(self.components))
        if not np.isfinite(cmd).all():
            raise DataError("a velocity command is not finite")
        if self.kind == "sim":
            index = self._grid.indices(cmd)
        else:
            index, _ = vq(cmd, self.codes, check_finite=False)  # no (N, K, d) temporaries
        distance = np.linalg.norm(cmd - self.codes[index], axis=1)
        return index.astype(np.int64), distance

    def command(self, action: int) -> dict[str, float]:
        """The command of ``action`` as component name to value (others are 0)."""
        return {name: float(v) for name, v in zip(self.components, self.codes[action], strict=True)}

    def as_dict(self) -> dict[str, Any]:
        """JSON form for model metadata."""
        return {
            "kind": self.kind,
            "components": list(self.components),
            "codes": self.codes.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Any) -> ActionCodebook:
        """Inverse of :meth:`as_dict`; anything malformed raises ``ConfigError``."""
        if not isinstance(data, dict):
            raise ConfigError("codebook is not an object")
        components, codes = data.get("components"), data.get("codes")
        if not isinstance(components, list) or not all(isinstance(c, str) for c in components):
            raise ConfigError("codebook components are not a list of names")
        if not isinstance(codes, list) or len(codes) > 100_000:
            raise ConfigError("codebook codes are not a list")
        try:
            array = np.array(codes, dtype=np.float64)
        except (TypeError, ValueError):
            raise ConfigError("codebook codes are not a numeric table") from None
        return cls(str(data.get("kind")), tuple(components), array)


def sim_codebook(environment: str | None = None) -> ActionCodebook:
    """The actions of a simulator environment: ``drive``'s 9, else the 25 velocity pairs."""
    grid = environment_grid(environment)
    return ActionCodebook("sim", grid.components, grid.codes)


def _farthest_first(points: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    """``k`` points: a random one, then repeatedly the point farthest from those chosen."""
    chosen = [int(rng.integers(points.shape[0]))]
    distance = np.linalg.norm(points - points[chosen[0]], axis=1)
    for _ in range(k - 1):
        chosen.append(int(distance.argmax()))
        distance = np.minimum(distance, np.linalg.norm(points - points[chosen[-1]], axis=1))
    return points[chosen].copy()


def fit_codebook(
    commands: np.ndarray, components: tuple[str, ...], k: int, seed: int
) -> ActionCodebook:
    """K-means codebook of ``k`` codes on ``commands (N, d)``: the best of seeded restarts.

    Needs at least ``k`` distinct commands. Codes are sorted lexicographically, so the
    action numbering does not depend on the initialisation.
    """
    cmd = np.asarray(commands, dtype=np.float64)
    if cmd.ndim != 2 or cmd.shape[1] != len(components):
        raise ConfigError(f"commands must be (N, {len(components)}), got {cmd.shape}")
    if k < 1:
        raise ConfigError(f"the number of actions must be >= 1, not {k}")
    distinct = np.unique(cmd, axis=0).shape[0]
    if distinct < k:
        raise DataError(
            f"{cmd.shape[0]} commands ({distinct} distinct) are fewer than the {k} codebook "
            "entries asked for (lower --actions)"
        )
    rng = np.random.default_rng(seed)
    best: tuple[float, np.ndarray] | None = None
    for restart in range(KMEANS_RESTARTS):
        # even restarts start from farthest-first points (one per well-separated cluster),
        # odd ones from k-means++; Lloyd's iterations refine both
        try:
            if restart % 2 == 0:
                start = _farthest_first(cmd, k, rng)
                codes, labels = kmeans2(cmd, start, minit="matrix", iter=50, missing="raise")
            else:
                codes, labels = kmeans2(cmd, k, minit="++", iter=50, seed=rng, missing="raise")
        except ClusterError:  # a code lost every command in this restart
            continue
        inertia = float(((cmd - codes[labels]) ** 2).sum())
        if best is None or inertia < best[0]:
            best = (inertia, codes)
    if best is None:
        raise DataError(f"k-means left a code empty in every restart; lower --actions from {k}")
    codes = best[1][np.lexsort(best[1].T[::-1])]
    return ActionCodebook("kmeans", tuple(components), codes)


def _silhouette(distances: np.ndarray, labels: np.ndarray, k: int) -> float:
    """Mean silhouette of a labelling, from the points' pairwise ``distances`` ``(n, n)``.

    A point's ``a`` is its mean distance to the others of its cluster, ``b`` the smallest
    mean distance to another cluster; a point alone in its cluster scores 0.
    """
    onehot = np.zeros((labels.size, k))
    onehot[np.arange(labels.size), labels] = 1.0
    counts = onehot.sum(axis=0)
    sums = distances @ onehot  # (n, k): summed distance to each cluster
    own = counts[labels]
    a = sums[np.arange(labels.size), labels] / np.maximum(own - 1, 1)
    means = np.where(counts > 0, sums / np.maximum(counts, 1), np.inf)
    means[np.arange(labels.size), labels] = np.inf
    b = means.min(axis=1)
    score = np.where(own > 1, (b - a) / np.maximum(np.maximum(a, b), 1e-300), 0.0)
    return float(score.mean())


def cluster_count(commands: np.ndarray, most: int, seed: int) -> int | None:
    """How many clusters the commands ``(N, d)`` form, if they form clear ones (else None).

    A robot driven by a few discrete commands (teleoperation with fixed speeds, a planner's
    actions, a simulator's grid) records them as tight clusters; its actions are those
    commands, however many steps the data have. The count is the ``K`` in ``2..most`` whose
    k-means labelling of a seeded sample of :data:`SILHOUETTE_SAMPLE` commands has the
    highest mean silhouette, provided that reaches :data:`CLUSTERED`.
    """
    cmd = np.asarray(commands, dtype=np.float64)
    rng = np.random.default_rng(seed)
    sample = cmd[rng.choice(cmd.shape[0], min(cmd.shape[0], SILHOUETTE_SAMPLE), replace=False)]
    distinct = np.unique(sample, axis=0).shape[0]
    if distinct < 3:
        return None
    distances = cdist(sample, sample)
    best_score, best_k = -np.inf, None
    for k in range(2, min(most, distinct - 1) + 1):
        start = _farthest_first(sample, k, rng)  # one start per well-separated cluster
        try:
            _, labels = kmeans2(sample, start, minit="matrix", iter=50, missing="raise")
        except ClusterError:  # a code lost every command: not k clear clusters
            continue
        score = _silhouette(distances, labels, k)
        if score > best_score:
            best_score, best_k = score, k
    return best_k if best_score >= CLUSTERED else None
