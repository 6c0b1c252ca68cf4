"""One ``fit`` for every state model: data in, a model with ``update`` and ``track`` out.

``fit(actions, observations)`` takes arrays (``(T,)`` action indices, ``(T, k)``
observations), ``fit(trajectory)`` a :class:`Trajectory` and ``fit(episodes)`` episodes
already cut. A trajectory is cut into the episodes of guide section 3.1
(:func:`tpsr_ros.core.episodes.make_episodes`, ``m`` and ``n`` from the config) and fitted
with Algorithms 1-3 (:func:`tpsr_ros.core.tpsr.fit_tpsr`); with a :class:`PCAConfig` the PCA
baseline is fitted on every step of the episodes instead (guide 4.2). The model tracks
states with Algorithm 4: ``model.update(state, action, observation)`` for one step,
``model.track(actions, observations)`` for a trajectory (equal bit for bit).

Without a config the fit takes the default preset (:mod:`tpsr_ros.core.presets`) with its
sizes fitted to the data (:mod:`tpsr_ros.core.sizing`: a few hundred steps cannot carry a
thousand kernel centres); ``model.fit_info["sized"]`` says what changed. A config given
is used exactly as given.
"""

from __future__ import annotations

import numpy as np

from tpsr_ros.core.episodes import Episodes, Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.pca_baseline import PCAConfig, PCAModel, fit_pca
from tpsr_ros.core.presets import DEFAULT_PRESET, get_preset
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr import Progress, TPSRConfig, TPSRModel, fit_tpsr_episodes

__all__ = ["fit"]

Config = TPSRConfig | PCAConfig


def fit(
    actions: np.ndarray | Trajectory | Episodes,
    observations: np.ndarray | Config | None = None,
    config: Config | None = None,
    *,
    max_episodes: int | None = None,
    progress: Progress | None = None,
    turning: bool = False,
) -> TPSRModel | PCAModel:
    """Learn a TPSR (default) or the PCA baseline from arrays, a trajectory or episodes.

    Args:
        actions: ``(T,)`` action indices with ``observations`` ``(T, k)``; or a
            :class:`Trajectory` (e.g. :meth:`Trajectory.from_arrays`), cut here into episodes
            of ``config.history_length`` / ``test_length`` (1 and 1 for PCA), or
            :class:`Episodes` already cut (then without ``observations``).
        observations: ``(T, k)`` observations, one per action (``o_k`` seen after ``a_k``).
            ``fit(trajectory, config)`` is accepted too.
        config: :class:`TPSRConfig` or :class:`PCAConfig`, used as given; None: the default
            preset's TPSR, sized to the data (with its turning robot's changes if
            ``turning``: for a robot whose actions turn it, e.g. ``cmd_vel``'s angular.z).
        max_episodes: cut only the first episodes of a trajectory (guide ``|E|``).
        progress: called with the name of each stage of a TPSR fit.

    """
    if isinstance(observations, (TPSRConfig, PCAConfig)):
        if config is not None:
            raise ConfigError("give the config once: fit(trajectory, config)")
        observations, config = None, observations
    data = _data(actions, observations)
    sizing = None
    if config is None:
        config, sizing = get_preset(DEFAULT_PRESET).tpsr_config(turning=turning), Sizing()
    if not isinstance(config, (TPSRConfig, PCAConfig)):
        raise ConfigError(f"config must be a TPSRConfig or PCAConfig, not {type(config).__name__}")
    if isinstance(data, Trajectory):
        m, n = (
            (config.history_length, config.test_length)
            if isinstance(config, TPSRConfig)
            else (1, 1)
        )
        episodes = make_episodes(data, m, n, max_episodes=max_episodes)
    else:
        episodes = data
    if isinstance(config, PCAConfig):
        return fit_pca(episodes.steps(), n_actions=episodes.n_actions, config=config)
    return fit_tpsr_episodes(episodes, config=config, progress=progress, sizing=sizing)


def _data(
    actions: np.ndarray | Trajectory | Episodes, observations: np.ndarray | None
) -> Trajectory | Episodes:
    """The trajectory or episodes the arguments of :func:`fit` describe."""
    if isinstance(actions, (Trajectory, Episodes)):
        if observations is not None:
            raise ConfigError(
                f"fit takes a {type(actions).__name__} alone, or actions and observations"
            )
        return actions
    if observations is None:
        raise ConfigError(
            "fit takes actions (T,) and observations (T, k), a Trajectory or Episodes, not "
            f"{type(actions).__name__} alone"
        )
    return Trajectory.from_arrays(np.asarray(actions), np.asarray(observations))
