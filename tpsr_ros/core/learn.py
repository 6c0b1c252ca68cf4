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
is sized the same way, except the fields where it departs from the default preset: those
were set on purpose and are kept (a rank above what the data support is refused), as
``learner fit`` keeps its options. So ``fit(a, o)`` and ``fit(a, o, <the default preset's
config>)`` are the same model.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from tpsr_ros.core.episodes import Episodes, Trajectory, make_episodes
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.fit_basis import FitBasis
from tpsr_ros.core.pca_baseline import PCAConfig, PCAModel, fit_pca
from tpsr_ros.core.presets import DEFAULT_PRESET, departures, get_preset
from tpsr_ros.core.refine import refine_tpsr
from tpsr_ros.core.sizing import Sizing
from tpsr_ros.core.tpsr import Progress, TPSRConfig, TPSRModel, fit_tpsr_episodes

__all__ = ["fit", "fit_tpsr_trajectory", "refined_on_trajectory"]

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
        config: :class:`TPSRConfig` (sized to the data but where it departs from the
            default preset) or :class:`PCAConfig` (used as given); None: the default
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
        if isinstance(data, Episodes):  # cut episodes carry no steps in order to refine on
            config = replace(config, refine_epochs=0)
    if not isinstance(config, (TPSRConfig, PCAConfig)):
        raise ConfigError(f"config must be a TPSRConfig or PCAConfig, not {type(config).__name__}")
    if sizing is None and isinstance(config, TPSRConfig):  # what departs was set on purpose
        reference = get_preset(DEFAULT_PRESET).tpsr_config(turning=turning)
        sizing = Sizing(departures(config, reference))
    if isinstance(data, Trajectory) and isinstance(config, TPSRConfig):
        return fit_tpsr_trajectory(
            data, config, max_episodes=max_episodes, progress=progress, sizing=sizing
        )
    if isinstance(data, Trajectory):
        episodes = make_episodes(data, 1, 1, max_episodes=max_episodes)
    else:
        episodes = data
    if isinstance(config, PCAConfig):
        return fit_pca(episodes.steps(), n_actions=episodes.n_actions, config=config)
    if config.refine_epochs:
        raise ConfigError(
            "refinement runs on a trajectory (steps in order), not on episodes already cut: "
            "pass a Trajectory, or refine_epochs=0"
        )
    return fit_tpsr_episodes(episodes, config=config, progress=progress, sizing=sizing)


def fit_tpsr_trajectory(
    trajectory: Trajectory,
    config: TPSRConfig,
    *,
    max_episodes: int | None = None,
    progress: Progress | None = None,
    sizing: Sizing | None = None,
    action_codes: np.ndarray | None = None,
    episodes: Episodes | None = None,
    basis: FitBasis | None = None,
) -> TPSRModel:
    """The spectral TPSR of ``trajectory``'s episodes (Algorithm 3), then, with
    ``config.refine_epochs``, refined through its filter on the trajectory's steps
    (:mod:`tpsr_ros.core.refine`); ``sizing``, ``action_codes`` and ``basis`` (a refit's
    frozen whitenings and centres: the config is the basis's) as in ``run_fit``;
    ``episodes``: the trajectory's episodes when already cut."""
    if episodes is None:
        episodes = make_episodes(
            trajectory,
            config.history_length,
            config.test_length,
            max_episodes=max_episodes,
            stride=config.episode_stride,
        )
    model = fit_tpsr_episodes(
        episodes, config=config, progress=progress, sizing=sizing, action_codes=action_codes,
        basis=basis,
    )  # fmt: skip
    return refined_on_trajectory(
        model, trajectory, episodes, max_episodes, progress, sizing=sizing
    )


def refined_on_trajectory(
    model: TPSRModel,
    trajectory: Trajectory,
    episodes: Episodes,
    max_episodes: int | None = None,
    progress: Progress | None = None,
    *,
    sizing: Sizing | None = None,
) -> TPSRModel:
    """``model`` refined through its filter on the steps its ``episodes`` (of
    ``trajectory``) use, at most the first ``refine_steps``, when its config asks for it
    (``refine_epochs``); else itself. ``sizing``: the fit's, which may skip it on data too
    short (:func:`~tpsr_ros.core.refine.refine_tpsr`)."""
    if not model.config.refine_epochs:
        return model
    if progress is not None:
        progress("refinement through the filter")
    steps = len(trajectory) if max_episodes is None else _steps_of(trajectory, episodes)
    part = trajectory.rows(0, min(steps, model.config.refine_steps))
    return refine_tpsr(
        model, part.actions, part.observations, part.segment_bounds(), progress=progress,
        sizing=sizing,
    )  # fmt: skip


def _steps_of(trajectory: Trajectory, episodes: Episodes) -> int:
    """The trajectory's steps up to the last one the episodes use."""
    last = int(np.searchsorted(trajectory.stamps, episodes.stamps[-1]))
    return min(len(trajectory), last + 1 + episodes.test_length)


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
