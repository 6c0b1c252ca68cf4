"""Fit sizes that follow the data: kernel centres and whitening dimensions a data set can carry.

The presets' sizes suit the simulator's thousands of episodes (1000 history/test and 500
observation centres, the guide's); a short robot log of 69 episodes cannot carry them, and
a 4-value observation cannot be whitened to 10 dimensions. :func:`size_to_data` lowers
each size the data cannot carry, and only those, to what it can:

- kernel centres: at most half the episodes (the rest train; ``first`` centres are taken
  out of the data), for histories and tests and for observations alike;
- whitening dimensions: at most the dimension of what is whitened (``d^O`` of the
  observation, unless ``obs_variance`` chooses it; ``d^H = d^T`` of the shorter of history
  and test) and fewer than the episodes;
- rank: at most the history/test centres (the features are one more, the constant), and,
  once ``P_TH`` is known, at most its singular values that the training episodes support
  (at least ``0.05 / sqrt(t)`` of the largest, ``t`` training episodes:
  :func:`tpsr_ros.core.tpsr_stages.supported_rank`, applied by the fit);
- the refinement through the filter: data too short for two of its windows are not
  refined (``refine_epochs`` 0: :func:`tpsr_ros.core.refine.refine_tpsr`, applied after
  the spectral fit).

Sizes named in ``fixed`` (set on purpose by the user) are never changed: a fit that cannot
carry them fails with the reason (a rank above the supported singular values too). At 2000
episodes of 16x16 images and more, no size of any preset changes.
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import dataclass, replace

from tpsr_ros.core.tpsr_config import TPSRConfig
from tpsr_ros.core.tpsr_stages import singular_value_floor

__all__ = ["SIZED_FIELDS", "Sizing", "describe_sizing", "size_to_data"]

SIZED_FIELDS = ("ht_centers", "obs_centers", "obs_dim", "ht_dim", "rank")


@dataclass(frozen=True)
class Sizing:
    """Size the fit to the data, leaving the fields in ``fixed`` as configured."""

    fixed: frozenset[str] = frozenset()

    def __init__(self, fixed: Collection[str] = ()) -> None:
        object.__setattr__(self, "fixed", frozenset(fixed))

    def sizes(self, name: str) -> bool:
        """Whether the fit may change the field ``name`` to what the data carry."""
        return name not in self.fixed


def size_to_data(
    config: TPSRConfig, n_episodes: int, obs_size: int, sizing: Sizing
) -> tuple[TPSRConfig, dict[str, tuple[int, int]]]:
    """``config`` with the sizes ``n_episodes`` episodes of ``obs_size`` values can carry.

    Returns the new config and the changes, ``{field: (configured, sized)}``.
    """
    half = max(1, int(n_episodes) // 2)
    whitened = min(config.history_length, config.test_length) * int(obs_size)
    limits = {
        "ht_centers": half,
        "obs_centers": half,
        "obs_dim": min(int(obs_size), max(1, int(n_episodes) - 1)),
        "ht_dim": min(whitened, max(1, int(n_episodes) - 1)),
    }
    changes: dict[str, tuple[int, int]] = {}
    values: dict[str, int] = {}
    if config.obs_variance > 0:  # the variance chooses d^O (never more than the data have)
        del limits["obs_dim"]
    for name, limit in limits.items():
        configured = getattr(config, name)
        if sizing.sizes(name) and configured > limit:
            values[name] = limit
            changes[name] = (configured, limit)
    ht_centers = values.get("ht_centers", config.ht_centers)
    if sizing.sizes("rank") and config.rank > ht_centers:
        values["rank"] = ht_centers
        changes["rank"] = (config.rank, ht_centers)
    return (replace(config, **values) if values else config), changes


def describe_sizing(
    n_episodes: int, changes: dict[str, tuple[int, int]], n_train: int | None = None
) -> str:
    """``69 episodes: ht_centers 1000 -> 34, ...``: what :func:`size_to_data` changed.

    With ``n_train`` (the fit's training episodes), a rank change says the rank rule's
    floor (:func:`tpsr_ros.core.tpsr_stages.singular_value_floor`).
    """

    def part(name: str, old: int, new: int) -> str:
        text = f"{name} {old} -> {new}"
        if name == "rank" and n_train is not None:
            floor = singular_value_floor(1.0, n_train)
            text += (
                f" (the singular values of P_TH that {n_train} training episodes support: "
                f"at least {floor:.2g} of the largest)"
            )
        return text

    parts = ", ".join(part(name, old, new) for name, (old, new) in changes.items())
    return f"{n_episodes} episodes carry less than configured: {parts} (set them to keep them)"
