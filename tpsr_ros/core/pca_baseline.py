"""The PCA baseline of guide section 4.2: state = current observation on its first principal axes.

An observation-to-state mapping without memory (Jonschkowski and Brock 2015, as compared in
the guide's figures 4.5, 4.7, 4.8): the state after ``(a_s, o_s)`` is
``(o_s - mean) @ components`` whatever came before, so actions and the previous state are
ignored. The projection is not rescaled (principal component scores, as the guide plots
them). It offers the :class:`tpsr_ros.core.state_model.StateModel` interface so fitted Q,
evaluation, plots and the filter node treat it like a TPSR.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, ClassVar

import numpy as np

from tpsr_ros.core.errors import DataError
from tpsr_ros.core.fields import check_positive_int, config_dict, config_from_dict, option
from tpsr_ros.core.state_model import Track, UpdateInfo, check_actions, check_observations
from tpsr_ros.core.whitening import Whitening

__all__ = ["PCAConfig", "PCAModel", "fit_pca"]


@dataclass(frozen=True)
class PCAConfig:
    """Parameters of the PCA baseline (guide figure 4.5: dim 2)."""

    dim: int = option(
        2, "PCA baseline: number of principal components (state dim)", cli="--pca-dim"
    )

    def __post_init__(self) -> None:
        check_positive_int(self.dim, "PCA dim")

    def to_dict(self) -> dict[str, Any]:
        """Parameters as a JSON-serialisable dict."""
        return config_dict(self)

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> PCAConfig:
        """Inverse of :meth:`to_dict`; unknown names are refused."""
        return config_from_dict(cls, values, "PCA")  # type: ignore[no-any-return]


@dataclass(frozen=True, eq=False)
class PCAModel:
    """A fitted PCA baseline.

    Attributes:
        config: the parameters.
        n_actions_: number of actions of the data it was fitted for (ignored by updates).
        mean: ``(k,)`` mean observation.
        components: ``(k, dim)`` orthonormal principal axes, largest variance first.
        eigenvalues: ``(dim,)`` variances along the axes.
        explained_variance_ratio: ``(dim,)``.
        fit_info: JSON-serialisable diagnostics.

    """

    method: ClassVar[str] = "pca"

    config: PCAConfig
    n_actions_: int
    mean: np.ndarray
    components: np.ndarray
    eigenvalues: np.ndarray
    explained_variance_ratio: np.ndarray
    fit_info: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        k, d = self.mean.shape[0], self.config.dim
        for name, shape in {
            "mean": (k,),
            "components": (k, d),
            "eigenvalues": (d,),
            "explained_variance_ratio": (d,),
        }.items():
            if getattr(self, name).shape != shape:
                raise DataError(
                    f"PCA array {name} has shape {getattr(self, name).shape}, expected {shape}"
                )
        if self.n_actions_ < 1:
            raise DataError(f"PCA model n_actions must be at least 1, not {self.n_actions_}")

    @property
    def state_dim(self) -> int:
        """Number of principal components."""
        return int(self.config.dim)

    @property
    def n_actions(self) -> int:
        """Number of actions (kept for the interface; updates ignore actions)."""
        return int(self.n_actions_)

    @property
    def obs_size(self) -> int:
        """Observation length ``k``."""
        return int(self.mean.shape[0])

    def initial_state(self) -> np.ndarray:
        """Projection of the mean observation: zeros."""
        return np.zeros(self.state_dim)

    def _project(self, observations: np.ndarray) -> np.ndarray:
        obs = check_observations(observations, self.obs_size)
        # Row by row (stacked matmul) so that one update equals the batch bit for bit.
        states: np.ndarray = np.matmul((obs - self.mean)[:, None, :], self.components)[:, 0, :]
        return states

    def update(
        self, state: np.ndarray, action: int, observation: np.ndarray
    ) -> tuple[np.ndarray, UpdateInfo]:
        """Return the projection of ``observation (k,)``; ``state`` and ``action`` are unused."""
        check_actions(np.asarray([action]), self.n_actions, 1)
        new = self._project(np.asarray(observation, dtype=np.float64)[None, :])[0]
        return new, UpdateInfo(normalizer=float("nan"), recovered=False)

    def track(
        self, actions: np.ndarray, observations: np.ndarray, initial: np.ndarray | None = None
    ) -> Track:
        """Project every observation ``(T, k)`` -> states ``(T, dim)``."""
        states = self._project(observations)
        check_actions(actions, self.n_actions, states.shape[0])
        n = states.shape[0]
        return Track(states, np.full(n, np.nan), np.zeros(n, dtype=bool))

    def parameters(self) -> dict[str, Any]:
        """Return the :class:`PCAConfig` as a dict."""
        return self.config.to_dict()

    def summary(self) -> dict[str, Any]:
        """Explained variance and fit diagnostics."""
        return {
            "explained_variance": {
                "obs": {
                    "total": float(self.explained_variance_ratio.sum()),
                    "per_dimension": self.explained_variance_ratio.tolist(),
                }
            },
            **self.fit_info,
        }

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Numeric content."""
        return {
            "mean": self.mean,
            "components": self.components,
            "eigenvalues": self.eigenvalues,
            "explained_variance_ratio": self.explained_variance_ratio,
            "n_actions": np.asarray(self.n_actions_, dtype=np.int64),
        }

    @classmethod
    def from_arrays(
        cls, arrays: dict[str, np.ndarray], parameters: dict[str, Any], summary: dict[str, Any]
    ) -> PCAModel:
        """Rebuild from :meth:`to_arrays`, :meth:`parameters` and :meth:`summary`."""
        return cls(
            config=PCAConfig.from_dict(parameters),
            n_actions_=int(arrays["n_actions"]),
            mean=arrays["mean"],
            components=arrays["components"],
            eigenvalues=arrays["eigenvalues"],
            explained_variance_ratio=arrays["explained_variance_ratio"],
            fit_info={k: v for k, v in summary.items() if k != "explained_variance"},
        )


def fit_pca(
    observations: np.ndarray, *, n_actions: int, config: PCAConfig | None = None
) -> PCAModel:
    """Fit the baseline on observations ``(T, k)`` (every step of the training trajectory)."""
    cfg = config if config is not None else PCAConfig()
    start = time.perf_counter()
    pca = Whitening.fit(observations, cfg.dim, what="observations")
    return PCAModel(
        config=cfg,
        n_actions_=int(n_actions),
        mean=pca.mean_,
        components=pca.components_,
        eigenvalues=pca.eigenvalues_,
        explained_variance_ratio=pca.explained_variance_ratio_,
        fit_info={
            "steps": int(np.asarray(observations).shape[0]),
            "timings": {"PCA": round(time.perf_counter() - start, 6)},
        },
    )
