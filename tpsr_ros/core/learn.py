"""One ``fit`` for every state model: data in, a model with ``update`` and ``track`` out.

``fit(trajectory)`` cuts the trajectory into the episodes of guide section 3.1
(:func:`tpsr_ros.core.episodes.make_episodes`, ``m`` and ``n`` from the config) and runs
Algorithms 1-3 (:func:`tpsr_ros.core.tpsr.fit_tpsr`); with a :class:`PCAConfig` it fits the
PCA baseline on every step of the episodes instead (guide 4.2). The model it returns tracks
states with Algorithm 4: ``model.update(state, action, observation)`` for one step,
``model.track(actions, observations)`` for a trajectory (equal bit for bit).
"""

from __future__ import annotations

from tpsr_ros.core.episodes import Episodes, Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.pca_baseline import PCAConfig, PCAModel, fit_pca
from tpsr_ros.core.tpsr import Progress, TPSRConfig, TPSRModel, fit_tpsr_episodes

__all__ = ["fit"]


def fit(
    data: Trajectory | Episodes,
    config: TPSRConfig | PCAConfig | None = None,
    *,
    max_episodes: int | None = None,
    progress: Progress | None = None,
) -> TPSRModel | PCAModel:
    """Learn a TPSR (default) or the PCA baseline from a trajectory or from cut episodes.

    Args:
        data: a :class:`Trajectory` (e.g. :meth:`Trajectory.from_arrays`), cut here into
            episodes of ``config.history_length`` / ``test_length`` (1 and 1 for PCA), or
            :class:`Episodes` already cut.
        config: :class:`TPSRConfig` (default: the guide's settings) or :class:`PCAConfig`.
        max_episodes: cut only the first episodes of a trajectory (guide ``|E|``).
        progress: called with the name of each stage of a TPSR fit.

    """
    cfg = TPSRConfig() if config is None else config
    if not isinstance(cfg, (TPSRConfig, PCAConfig)):
        raise ConfigError(f"config must be a TPSRConfig or PCAConfig, not {type(cfg).__name__}")
    if isinstance(data, Trajectory):
        m, n = (cfg.history_length, cfg.test_length) if isinstance(cfg, TPSRConfig) else (1, 1)
        episodes = make_episodes(data, m, n, max_episodes=max_episodes)
    elif isinstance(data, Episodes):
        episodes = data
    else:
        raise ConfigError(f"fit takes a Trajectory or Episodes, not {type(data).__name__}")
    if isinstance(cfg, PCAConfig):
        return fit_pca(episodes.steps(), n_actions=episodes.n_actions, config=cfg)
    return fit_tpsr_episodes(episodes, config=cfg, progress=progress)
