"""The data-dependent pieces of a TPSR fit, frozen so that a refit on more data keeps them.

Algorithm 3 reads its data in an order of decisions: the whitenings (Algorithm 1), then the
kernel centres chosen among the whitened rows (Algorithm 2), then ``P_TH``, its SVD and the
operators. Only the first two depend on the data in a way that more data would change; the
rest are sums and their solution. A :class:`FitBasis` holds those two, as a fit chose them;
:func:`tpsr_ros.core.tpsr.run_fit` given one whitens with it and keeps its centres, so a model
refitted on a longer recording of the same robot (the learner node's refits, ``learner fit
--init-from MODEL``) differs from the first only in what the sums say. The fit's sizes are
then the basis's: its whitening dimensions and centres are kept, and the rank follows the
rank rule from the rank the first fit was asked for (``requested_rank``).

A first fit also keeps a :class:`Sketch` of ``P_TH``: its leading left and right singular
vectors, a few more than the rank asked for. A refit that projects its features on them
reduces its data to sums of fixed size that merge and decay, and solves them without
another pass (:mod:`tpsr_ros.core.fit_statistics`).

Its arrays are stored beside the model's (``basis_*``) and, like the viewer's read-outs,
outside the model's fingerprint: they are not needed to filter.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from tpsr_ros.core.errors import ConfigError, DataError
from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.tpsr_stages import top_singular_triplets
from tpsr_ros.core.whitened import Centres, Whitenings
from tpsr_ros.core.whitening import Whitening

__all__ = ["SKETCH_MARGIN", "WHITENING_PARTS", "FitBasis", "Sketch", "basis_shapes"]

WHITENING_PARTS = ("mean", "components", "eigenvalues", "ratio")
"""The arrays stored for each whitening (``Whitening``'s four fields, in order)."""

_WHITENINGS = ("history", "test", "obs")

SKETCH_MARGIN = 48
"""Singular vectors of ``P_TH`` a sketch keeps beyond the rank asked for: room for the
leading directions of more data to lie in its span. Measured on the learner node's
refits of `partial-strip` (first version at 1000 steps, refits at 8000-12000 steps, 7 runs):
with 16 more the refits from the sums scored 161 against 218 for the two-pass refits of
the same steps; with 48 more, 205."""


@dataclass(frozen=True, eq=False)
class Sketch:
    """Orthonormal bases of the leading test and history directions of a first fit's ``P_TH``.

    ``test`` ``(l_T + 1, w)`` and ``history`` ``(l_H + 1, w)``: the top ``w`` left and right
    singular vectors. A refit's features are projected on them before they are summed, so
    its sums have the fixed size ``w x w`` whatever the data (``P_TH``'s exact SVD is the
    sketch's when ``w`` spans its whole range).
    """

    test: np.ndarray
    history: np.ndarray

    def __post_init__(self) -> None:
        for name in ("test", "history"):
            basis = getattr(self, name)
            if basis.ndim != 2 or not 1 <= basis.shape[1] <= basis.shape[0]:
                raise DataError(f"the sketch's {name} basis of shape {basis.shape} is not (l, w)")
        if self.test.shape[1] != self.history.shape[1]:
            raise DataError(
                f"the sketch keeps {self.test.shape[1]} test and {self.history.shape[1]} history "
                "directions: they must be as many"
            )

    @property
    def width(self) -> int:
        """The directions ``w`` kept on each side."""
        return int(self.test.shape[1])

    @classmethod
    def of(cls, p_th: np.ndarray, rank: int, seed: int = 0) -> Sketch:
        """The top ``rank + SKETCH_MARGIN`` singular vectors of ``p_th`` (all, when fewer)."""
        width = min(int(rank) + SKETCH_MARGIN, min(p_th.shape))
        u, _, v = top_singular_triplets(p_th, width, seed=seed)
        return cls(np.ascontiguousarray(u), np.ascontiguousarray(v))


@dataclass(frozen=True, eq=False)
class FitBasis:
    """Whitenings and kernel centres of a fit, and the rank it was asked for.

    ``config`` is the configuration the basis was fitted with (the sized one, the rank as
    asked): a refit uses it as its own.
    """

    config: TPSRConfig
    history: Whitening
    test: Whitening
    obs: Whitening
    centres: Centres
    sketch: Sketch | None = None
    """``P_TH``'s leading directions (None: a basis stored before sketches were kept)."""

    def __post_init__(self) -> None:
        cfg = self.config
        if self.history.n_components != cfg.ht_dim or self.test.n_components != cfg.ht_dim:
            raise DataError(
                f"the basis whitens histories and tests to {self.history.n_components} and "
                f"{self.test.n_components} dimensions, its config to {cfg.ht_dim}"
            )
        if self.obs.n_components != cfg.obs_dim:
            raise DataError(
                f"the basis whitens observations to {self.obs.n_components} dimensions, its "
                f"config to {cfg.obs_dim}"
            )
        k = self.obs.n_features_in
        if (self.history.n_features_in, self.test.n_features_in) != (
            cfg.history_length * k,
            cfg.test_length * k,
        ):
            raise DataError("the basis's history and test whitenings do not fit its observations")
        shapes = {
            "history": (self.centres.history.shape[0], cfg.ht_centers),
            "test": (self.centres.test.shape[0], cfg.ht_centers),
            "observation": (self.centres.observation.shape, (cfg.obs_centers, cfg.obs_dim)),
        }
        for name, (found, expected) in shapes.items():
            if found != expected:
                raise DataError(f"the basis has {found} {name} centres, its config {expected}")
        if self.sketch is not None:
            expected_rows = (cfg.ht_centers + 1, cfg.ht_centers + 1)
            if (self.sketch.test.shape[0], self.sketch.history.shape[0]) != expected_rows:
                raise DataError(
                    f"the sketch's bases have {self.sketch.test.shape[0]} and "
                    f"{self.sketch.history.shape[0]} rows, the features {cfg.ht_centers + 1}"
                )
            if self.sketch.width < cfg.rank:
                raise DataError(
                    f"the sketch keeps {self.sketch.width} directions, fewer than rank {cfg.rank}"
                )

    @property
    def obs_size(self) -> int:
        """Length ``k`` of the observations the basis whitens."""
        return self.obs.n_features_in

    def whitenings(self, codes: np.ndarray | None) -> Whitenings:
        """The frozen whitenings, with this fit's action codes."""
        return Whitenings(self.history, self.test, self.obs, codes)

    def fit_config(self, rank: int | None = None) -> TPSRConfig:
        """The config a refit runs with: the basis's own, at ``rank`` if given."""
        if rank is None:
            return self.config
        if rank > self.config.ht_centers:
            raise ConfigError(
                f"rank {rank} is above the basis's {self.config.ht_centers} history centres"
            )
        return replace(self.config, rank=int(rank))

    def to_arrays(self) -> dict[str, np.ndarray]:
        """The arrays stored beside a model's, named ``basis_*``."""
        arrays = {
            f"basis_{name}_{part}": np.asarray(array, dtype=np.float64)
            for name in _WHITENINGS
            for part, array in zip(WHITENING_PARTS, _fields(getattr(self, name)), strict=True)
        }
        arrays["basis_history_centers"] = self.centres.history
        arrays["basis_test_centers"] = self.centres.test
        if self.sketch is not None:
            arrays["basis_sketch_test"] = self.sketch.test
            arrays["basis_sketch_history"] = self.sketch.history
        return arrays

    def metadata(self) -> dict[str, Any]:
        """What the arrays' shapes follow from, beyond the model's parameters."""
        metadata = {
            "rank": int(self.config.rank),
            "history_width": int(self.centres.history.shape[1]),
            "test_width": int(self.centres.test.shape[1]),
        }
        if self.sketch is not None:
            metadata["sketch_width"] = self.sketch.width
        return metadata

    @classmethod
    def from_arrays(
        cls,
        arrays: dict[str, np.ndarray],
        config: TPSRConfig,
        obs_centers: np.ndarray,
    ) -> FitBasis:
        """The basis of :meth:`to_arrays` (``config``: the basis's; ``obs_centers``: the
        model's, which it shares)."""
        whitenings = {
            name: Whitening(*(arrays[f"basis_{name}_{part}"] for part in WHITENING_PARTS))
            for name in _WHITENINGS
        }
        centres = Centres(
            arrays["basis_history_centers"], arrays["basis_test_centers"], obs_centers
        )
        sketch = None
        if "basis_sketch_test" in arrays:
            sketch = Sketch(arrays["basis_sketch_test"], arrays["basis_sketch_history"])
        return cls(config, centres=centres, sketch=sketch, **whitenings)


def _fields(whitening: Whitening) -> tuple[np.ndarray, ...]:
    return (
        whitening.mean_,
        whitening.components_,
        whitening.eigenvalues_,
        whitening.explained_variance_ratio_,
    )


def basis_shapes(
    parameters: dict[str, Any], basis: dict[str, Any], obs_size: int
) -> dict[str, tuple[int, ...]]:
    """The shapes of the ``basis_*`` arrays implied by a model's parameters and the basis
    metadata of :meth:`FitBasis.metadata` (to check a file before reading its arrays)."""
    k = int(obs_size)
    m, n = int(parameters["history_length"]), int(parameters["test_length"])
    d_ht, d_o, l_ht = int(parameters["ht_dim"]), int(parameters["obs_dim"]), int(
        parameters["ht_centers"]
    )
    shapes: dict[str, tuple[int, ...]] = {}
    for name, width, dim in (("history", m * k, d_ht), ("test", n * k, d_ht), ("obs", k, d_o)):
        shapes.update({
            f"basis_{name}_mean": (width,),
            f"basis_{name}_components": (width, dim),
            f"basis_{name}_eigenvalues": (dim,),
            f"basis_{name}_ratio": (dim,),
        })  # fmt: skip
    shapes["basis_history_centers"] = (l_ht, int(basis["history_width"]))
    shapes["basis_test_centers"] = (l_ht, int(basis["test_width"]))
    if "sketch_width" in basis:
        shapes["basis_sketch_test"] = (l_ht + 1, int(basis["sketch_width"]))
        shapes["basis_sketch_history"] = (l_ht + 1, int(basis["sketch_width"]))
    return shapes
