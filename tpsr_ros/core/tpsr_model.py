"""A learned TPSR (guide table 3.4) and what Algorithm 4 needs to track states with it."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, ClassVar

import numpy as np

from tpsr_ros.core import filtering
from tpsr_ros.core.errors import DataError
from tpsr_ros.core.fit_basis import FitBasis
from tpsr_ros.core.state_model import Track, UpdateInfo
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.whitening import Whitening

__all__ = ["TPSRModel", "assemble_model"]


@dataclass(frozen=True, eq=False)
class TPSRModel:
    """A learned TPSR (guide table 3.4) plus what Algorithm 4 needs to track states.

    Attributes:
        config: the parameters of the fit.
        obs_mean: ``(k,)`` whitening mean of current observations (``mean^O``).
        obs_whitening: ``(k, d_O)`` whitening matrix of current observations (``W^O``).
        obs_centers: ``(l_O, d_O)`` observation kernel centres (whitened).
        b_star: ``(r,)`` starting state ``b_*``.
        b_inf: ``(r,)`` normaliser ``b_inf``.
        B: ``(n_actions, l_O, r, r)``; ``B[a, o']`` is ``B_ao'``.
        singular_values: ``(>= r,)`` largest singular values of ``P_TH`` (first ``r`` kept).
        explained_variance: whitening explained-variance ratios, keys ``obs``, ``history``,
            ``test``, each ``(d,)``.
        fit_info: JSON-serialisable diagnostics (sample counts, timings in seconds).
        state_box: ``(2, r)`` low and high bound of every state coordinate, or None (no
            clipping); present exactly when ``config.state_clip_quantile > 0``.
        basis: the whitenings and kernel centres the fit chose (a refit keeps them:
            :mod:`tpsr_ros.core.fit_basis`); None for models read from files without them.
            Not among the arrays that define the filter (nor its fingerprint).

    """

    method: ClassVar[str] = "tpsr"

    config: TPSRConfig
    obs_mean: np.ndarray
    obs_whitening: np.ndarray
    obs_centers: np.ndarray
    b_star: np.ndarray
    b_inf: np.ndarray
    B: np.ndarray
    singular_values: np.ndarray
    explained_variance: dict[str, np.ndarray]
    fit_info: dict[str, Any] = field(default_factory=dict)
    state_box: np.ndarray | None = None
    basis: FitBasis | None = None

    ARRAY_NAMES: ClassVar[tuple[str, ...]] = (
        "obs_mean",
        "obs_whitening",
        "obs_centers",
        "b_star",
        "b_inf",
        "B",
        "singular_values",
        "explained_variance_obs",
        "explained_variance_history",
        "explained_variance_test",
    )

    def __post_init__(self) -> None:
        r, k = self.config.rank, self.obs_mean.shape[0]
        d_o, l_o = self.config.obs_dim, self.config.obs_centers
        n_act = self.B.shape[0] if self.B.ndim == 4 and self.B.shape[0] >= 1 else "n_actions>=1"
        expected = {
            "obs_mean": (k,),
            "obs_whitening": (k, d_o),
            "obs_centers": (l_o, d_o),
            "b_star": (r,),
            "b_inf": (r,),
            "B": (n_act, l_o, r, r),
        }
        for name, shape in expected.items():
            arr = getattr(self, name)
            if arr.shape != shape:
                raise DataError(f"TPSR array {name} has shape {arr.shape}, expected {shape}")
        clipped = self.config.state_clip_quantile > 0
        if clipped != (self.state_box is not None):
            raise DataError(
                "TPSR state_box must be present exactly when state_clip_quantile > 0 "
                f"(state_clip_quantile {self.config.state_clip_quantile})"
            )
        if self.state_box is not None and (
            self.state_box.shape != (2, r) or not (self.state_box[0] <= self.state_box[1]).all()
        ):
            raise DataError(
                f"TPSR state_box has shape {self.state_box.shape} or low above high bounds, "
                f"expected (2, {r}) low <= high"
            )
        if self.singular_values.ndim != 1 or self.singular_values.shape[0] < r:
            raise DataError(
                f"TPSR singular_values has shape {self.singular_values.shape}, expected at "
                f"least {r} values"
            )

    # --- StateModel interface -------------------------------------------------------------
    @property
    def state_dim(self) -> int:
        """TPSR dimension ``r``."""
        return int(self.config.rank)

    @property
    def n_actions(self) -> int:
        """Number of actions (first axis of ``B``)."""
        return int(self.B.shape[0])

    @property
    def obs_size(self) -> int:
        """Observation length ``k``."""
        return int(self.obs_mean.shape[0])

    def initial_state(self) -> np.ndarray:
        """``b_*`` (a copy)."""
        return np.array(self.b_star)

    @cached_property
    def derived(self) -> filtering.Derived:
        """What every update derives from the parameters, computed on first use."""
        return filtering.derive(self)

    def update(
        self, state: np.ndarray, action: int, observation: np.ndarray
    ) -> tuple[np.ndarray, UpdateInfo]:
        """Algorithm 4; see :func:`tpsr_ros.core.filtering.update`."""
        return filtering.update(self, state, action, observation)

    def track(
        self, actions: np.ndarray, observations: np.ndarray, initial: np.ndarray | None = None
    ) -> Track:
        """Algorithm 4 over a trajectory; see :func:`tpsr_ros.core.filtering.track`."""
        return filtering.track(self, actions, observations, initial)

    def parameters(self) -> dict[str, Any]:
        """Return the :class:`TPSRConfig` as a dict."""
        return self.config.to_dict()

    def summary(self) -> dict[str, Any]:
        """Singular values, whitening explained variance and fit diagnostics."""
        return {
            "singular_values": self.singular_values.tolist(),
            "explained_variance": {
                key: {"total": float(val.sum()), "per_dimension": val.tolist()}
                for key, val in self.explained_variance.items()
            },
            **self.fit_info,
        }

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Numeric content keyed by :attr:`ARRAY_NAMES`."""
        arrays = {
            name: getattr(self, name)
            for name in self.ARRAY_NAMES
            if not name.startswith("explained_variance_")
        }
        for key in ("obs", "history", "test"):
            arrays[f"explained_variance_{key}"] = self.explained_variance[key]
        if self.state_box is not None:
            arrays["state_box"] = self.state_box
        return arrays

    @classmethod
    def from_arrays(
        cls, arrays: dict[str, np.ndarray], parameters: dict[str, Any], summary: dict[str, Any]
    ) -> TPSRModel:
        """Rebuild a model from :meth:`to_arrays`, :meth:`parameters` and :meth:`summary`."""
        config = TPSRConfig.from_dict(parameters)
        info = {
            k: v for k, v in summary.items() if k not in ("singular_values", "explained_variance")
        }
        return cls(
            config=config,
            obs_mean=arrays["obs_mean"],
            obs_whitening=arrays["obs_whitening"],
            obs_centers=arrays["obs_centers"],
            b_star=arrays["b_star"],
            b_inf=arrays["b_inf"],
            B=arrays["B"],
            singular_values=arrays["singular_values"],
            explained_variance={
                key: arrays[f"explained_variance_{key}"] for key in ("obs", "history", "test")
            },
            fit_info=info,
            state_box=arrays.get("state_box"),
        )


def assemble_model(
    cfg: TPSRConfig,
    whitenings: tuple[Whitening, Whitening, Whitening],
    obs_centers: np.ndarray,
    parameters: tuple[np.ndarray, np.ndarray, np.ndarray],
    singular_values: np.ndarray,
    fit_info: dict[str, Any],
) -> TPSRModel:
    """The model of a fit (in memory or streamed): the observation whitening and centres,
    ``(b_*, b_inf, B)``, and the explained variance of the history, test and observation
    whitenings. Its config records the ``d^O`` the observation whitening kept."""
    history, test, obs = whitenings
    b_star, b_inf, big_b = parameters
    return TPSRModel(
        config=replace(cfg, obs_dim=obs.n_components),
        obs_mean=obs.mean_,
        obs_whitening=np.ascontiguousarray(obs.matrix_),
        obs_centers=obs_centers,
        b_star=b_star,
        b_inf=b_inf,
        B=big_b,
        singular_values=singular_values,
        explained_variance={
            "obs": obs.explained_variance_ratio_,
            "history": history.explained_variance_ratio_,
            "test": test.explained_variance_ratio_,
        },
        fit_info=fit_info,
    )
