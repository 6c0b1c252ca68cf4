"""Parameters of a TPSR fit (guide table 3.5), validated on construction.

One frozen dataclass; every field carries its help text (:func:`tpsr_ros.core.fields.option`),
from which ``learner fit`` builds its options. The defaults are the guide's (figure 4.5 with
rank 5, section 4.3); :mod:`tpsr_ros.core.presets` names other settings.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from typing import Any, Literal

import numpy as np

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.fields import option as _param

__all__ = ["TPSRConfig", "chosen_by_the_fit"]


_NUMBER_RULES: tuple[tuple[tuple[str, ...], Callable[[float], bool], str], ...] = (
    (("sigma_obs", "sigma_ht"), lambda v: np.isfinite(v) and v > 0, "a positive finite number"),
    (
        ("history_action_weight", "test_action_weight"),
        lambda v: np.isfinite(v) and v >= 0,
        "a non-negative finite number",
    ),
    (("state_clip_quantile",), lambda v: v == 0 or 0 < v < 0.5, "0 or in (0, 0.5)"),
    (("action_pooling",), lambda v: np.isfinite(v) and 0 <= v <= 1, "a number in [0, 1]"),
    (("obs_variance",), lambda v: v == 0 or 0 < v < 1, "0 or in (0, 1)"),
    (("refine_pull",), lambda v: np.isfinite(v) and v >= 0, "a non-negative finite number"),
    (("refine_carry",), lambda v: 0 <= v < 1, "a number in [0, 1)"),
    (("obs_effective_centres",), lambda v: v == 0 or 1 <= v < np.inf, "0 or a number >= 1"),
)
"""The real-valued parameters of :class:`TPSRConfig`: names, the rule, and how it reads."""


@dataclass(frozen=True)
class TPSRConfig:
    """Parameters of a TPSR fit (guide table 3.5); defaults: figure 4.5, rank 5 (section 4.3).

    History and test whitening dimensions, kernel centres and widths are coupled (``ht_*``),
    as in the guide's experiments.
    """

    history_length: int = _param(1, "m: observations per history (guide h/t-length)")
    test_length: int = _param(1, "n: observations per test (guide h/t-length)")
    obs_dim: int = _param(10, "d^O: dimensions kept when whitening current observations")
    obs_variance: float = _param(
        0.0,
        "keep instead the fewest d^O that explain this fraction of the current observations' "
        "variance (0: obs_dim, the guide; the fitted model's obs_dim records the d^O chosen)",
    )
    ht_dim: int = _param(10, "d^H = d^T: dimensions kept when whitening histories and tests")
    obs_centers: int = _param(500, "l^O: number of observation kernel centres")
    ht_centers: int = _param(1000, "l^H = l^T: number of history and test kernel centres")
    sigma_obs: float = _param(1.0, "sigma^O: kernel width of observation features")
    obs_effective_centres: float = _param(
        0.0,
        "widen sigma^O where needed so that the median observation's kernel weights spread "
        "over at least this many effective centres, 1 / sum w^2 (0: sigma^O as given, the "
        "guide; the fitted model's sigma_obs records the width used; see "
        "tpsr_ros.core.kernel_width)",
    )
    sigma_ht: float = _param(2.0, "sigma^H = sigma^T: kernel width of history/test features")
    rank: int = _param(5, "r: dimension of the TPSR state (singular values kept; guide dim)")
    center_selection: Literal["first", "kmeans"] = _param(
        "first",
        "kernel centres: the first episodes (guide) or k-means centroids",
        cli="--centers",
        choices=("first", "kmeans"),
    )
    normalize_ht_features: bool = _param(
        False, "normalise history/test features to sum 1 (Boots et al.; the guide does not)"
    )
    p_th_tests: Literal["after-current", "from-current"] = _param(
        "after-current",
        "test window of P_TH: after the current pair (guide eq. 3.2) or starting at it "
        "(Boots et al. 2011)",
        choices=("after-current", "from-current"),
    )
    overlapping_episodes: bool = _param(
        False,
        "cut an episode at every step, overlapping (every window of the data a sample), "
        "instead of every m + 1 + n steps (the guide)",
    )
    history_action_weight: float = _param(
        0.0,
        "weight of each history step's action code joined to its observations before the "
        "RBF kernel (0: observations only, the guide; see tpsr_ros.core.action_features)",
    )
    test_action_weight: float = _param(
        0.0, "weight of each test step's action code joined to its observations (0: the guide)"
    )
    state_clip_quantile: float = _param(
        0.0,
        "clip every tracked state into the [q, 1 - q] quantiles of its training episodes' "
        "states (0: no clipping, the guide; see tpsr_ros.core.state_box)",
    )
    action_pooling: float = _param(
        0.0,
        "shrink each action's operators toward their mean over all actions by this fraction "
        "(0: one operator per action, the guide; 1: one for all; see pool_actions)",
    )
    refine_epochs: int = _param(
        0,
        "refine the spectral model through its filter for at most this many L-BFGS "
        "iterations, one pass over the data each (0: the spectral model, the guide; see "
        "tpsr_ros.core.refine)",
    )
    refine_steps: int = _param(
        50_000,
        "refinement: at most this many steps, the first of the training data (a streamed "
        "fit holds them in memory: 50000 steps of a 16x16 RGB camera take 0.3 GB)",
    )
    refine_window: int = _param(
        16, "refinement: steps backpropagated before each window's scored steps, and scored"
    )
    refine_horizon: int = _param(
        10, "refinement: the states predict the next this many observations"
    )
    refine_past: int = _param(
        0,
        "refinement: the states also predict the last this many observations before the "
        "current one, which a state can only do by carrying its past forward (0: the next "
        "ones only; at most refine_window; see tpsr_ros.core.refine)",
    )
    refine_pull: float = _param(
        1e-3, "refinement: weight of the pull toward the spectral parameters"
    )
    refine_carry: float = _param(
        0.0,
        "refinement: start from a filter whose typical step carries this fraction of the "
        "previous state forward through the action (0: the spectral filter, which forgets "
        "within a step; see tpsr_ros.core.refine)",
    )
    refine_carry_rule: Literal["always", "aliased"] = _param(
        "always",
        "refinement: when to start from the carried filter (always; aliased: only where the "
        "previous image helps to predict the next ones, held out, so that a camera whose "
        "image tells the place keeps a filter without lag; see tpsr_ros.core.history_gain)",
        choices=("always", "aliased"),
    )
    refine_scaling: Literal["none", "groups"] = _param(
        "none",
        "refinement: the search's variables (none: the parameters themselves; groups: each "
        "group, B_o', the actions' factors and b_inf, divided by its root mean square at the "
        "start, so that a step changes each by a like fraction; see tpsr_ros.core.refine)",
        choices=("none", "groups"),
    )
    seed: int = _param(0, "seed of k-means and of the SVD start vector")

    def __post_init__(self) -> None:
        for name in (
            "history_length",
            "test_length",
            "obs_dim",
            "ht_dim",
            "obs_centers",
            "ht_centers",
            "rank",
            "refine_steps",
            "refine_window",
            "refine_horizon",
        ):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise ConfigError(f"{name} must be a positive integer, not {value!r}")
        for names, valid, rule in _NUMBER_RULES:
            for name in names:
                value = getattr(self, name)
                real = not isinstance(value, bool) and isinstance(value, (int, float, np.floating))
                if not (real and valid(value)):
                    raise ConfigError(f"{name} must be {rule}, not {value!r}")
        for f in fields(self):
            allowed = f.metadata.get("choices")
            if allowed is not None and getattr(self, f.name) not in allowed:
                raise ConfigError(
                    f"{f.name} must be one of {list(allowed)}, not {getattr(self, f.name)!r}"
                )
        if not isinstance(self.overlapping_episodes, bool):
            raise ConfigError(
                f"overlapping_episodes must be true or false, not {self.overlapping_episodes!r}"
            )
        if not isinstance(self.normalize_ht_features, bool):
            raise ConfigError(
                f"normalize_ht_features must be true or false, not {self.normalize_ht_features!r}"
            )
        for name in ("seed", "refine_epochs", "refine_past"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
                raise ConfigError(f"{name} must be a non-negative integer, not {value!r}")
        if self.refine_past > self.refine_window:  # a scored step's past lies in its window
            raise ConfigError(
                f"refine_past {self.refine_past} exceeds refine_window {self.refine_window}"
            )
        if self.refine_epochs and self.state_clip_quantile > 0:  # refused before any fit
            raise ConfigError(
                "refinement does not support the state box (state_clip_quantile > 0): set "
                "one of refine_epochs and state_clip_quantile to 0"
            )
        if self.rank > self.ht_centers + 1:
            raise ConfigError(
                f"rank {self.rank} exceeds the {self.ht_centers + 1} history/test features "
                "(ht_centers + 1)"
            )

    @property
    def window_steps(self) -> int:
        """Steps of one episode's window, ``m + 1 + n``: its history, the current step and
        its test."""
        return self.history_length + 1 + self.test_length

    @property
    def episode_stride(self) -> int:
        """Steps between the starts of consecutive episodes (1 when they overlap)."""
        return 1 if self.overlapping_episodes else self.window_steps

    @property
    def uses_actions(self) -> bool:
        """Whether histories or tests carry action codes (:mod:`tpsr_ros.core.action_features`)."""
        return self.history_action_weight > 0 or self.test_action_weight > 0

    def to_dict(self) -> dict[str, Any]:
        """Parameters as a JSON-serialisable dict."""
        return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict[str, Any]) -> TPSRConfig:
        """Inverse of :meth:`to_dict`; unknown names are refused."""
        known = {f.name for f in fields(cls)}
        if unknown := sorted(set(values) - known):
            raise ConfigError(f"unknown TPSR parameters {unknown}")
        return cls(**values)


def chosen_by_the_fit(values: dict[str, Any]) -> frozenset[str]:
    """The fields a fit records as it chose them from the data, not as they were given: d^O
    (``obs_variance``'s choice) and, where ``obs_effective_centres`` is set, sigma^O."""
    widened = bool(values.get("obs_effective_centres"))
    return frozenset({"obs_dim", "sigma_obs"} if widened else {"obs_dim"})
