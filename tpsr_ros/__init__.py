"""tpsr-ros: transformed predictive state representations for ROS 2 robots.

The user API, like scikit-learn's and filterpy's: configure, fit, track::

    from tpsr_ros import TPSRConfig, Trajectory, fit

    model = fit(Trajectory.from_arrays(actions, observations), TPSRConfig(rank=5))
    states = model.track(actions, observations).states        # guide Algorithm 4
    state, info = model.update(model.initial_state(), action, observation)

The layers below it (DESIGN.md "Layout"; ``tests/test_layers.py`` enforces them):
:mod:`tpsr_ros.core` (numpy/scipy only: the algorithms), :mod:`tpsr_ros.io` (messages,
bags, model and policy files; no middleware), :mod:`tpsr_ros.runtime` (transports,
``--ros-args``, the node API, the launcher) and the thin node faces ``filter_node``,
``record``, ``play``, ``bag_info`` and ``bag_recover``.

Names are imported on first use, so ``import tpsr_ros.core`` does not load the I/O layer.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from tpsr_ros.lazy import lazy_exports

__version__ = "0.1.0"

_API = {
    "TPSRConfig": "tpsr_ros.core.tpsr",
    "TPSRModel": "tpsr_ros.core.tpsr",
    "fit_tpsr": "tpsr_ros.core.tpsr",
    "PCAConfig": "tpsr_ros.core.pca_baseline",
    "PCAModel": "tpsr_ros.core.pca_baseline",
    "FQIConfig": "tpsr_ros.core.fqi",
    "QFunction": "tpsr_ros.core.fqi",
    "fit_q": "tpsr_ros.core.fqi",
    "Episodes": "tpsr_ros.core.episodes",
    "Trajectory": "tpsr_ros.core.episodes",
    "images_to_observations": "tpsr_ros.core.episodes",
    "make_episodes": "tpsr_ros.core.episodes",
    "track_trajectory": "tpsr_ros.core.episodes",
    "fit": "tpsr_ros.core.learn",
    "OnlineTracker": "tpsr_ros.core.online",
    "StateModel": "tpsr_ros.core.state_model",
    "Track": "tpsr_ros.core.state_model",
    "UpdateInfo": "tpsr_ros.core.state_model",
    "ConfigError": "tpsr_ros.core.errors",
    "DataError": "tpsr_ros.core.errors",
    "ModelFormatError": "tpsr_ros.core.errors",
    "TpsrError": "tpsr_ros.core.errors",
    "load_model": "tpsr_ros.io.model_io",
    "save_model": "tpsr_ros.io.model_io",
    "Policy": "tpsr_ros.io.policy",
    "load_policy": "tpsr_ros.io.policy",
    "save_policy": "tpsr_ros.io.policy",
    "iter_trajectory_chunks": "tpsr_ros.io.trajectory",
    "read_trajectory": "tpsr_ros.io.trajectory",
}

__all__ = [
    "ConfigError",
    "DataError",
    "Episodes",
    "FQIConfig",
    "ModelFormatError",
    "OnlineTracker",
    "PCAConfig",
    "PCAModel",
    "Policy",
    "QFunction",
    "StateModel",
    "TPSRConfig",
    "TPSRModel",
    "TpsrError",
    "Track",
    "Trajectory",
    "UpdateInfo",
    "fit",
    "fit_q",
    "fit_tpsr",
    "images_to_observations",
    "iter_trajectory_chunks",
    "load_model",
    "load_policy",
    "make_episodes",
    "read_trajectory",
    "save_model",
    "save_policy",
    "track_trajectory",
]

if TYPE_CHECKING:
    from tpsr_ros.core.episodes import (
        Episodes,
        Trajectory,
        images_to_observations,
        make_episodes,
        track_trajectory,
    )
    from tpsr_ros.core.errors import ConfigError, DataError, ModelFormatError, TpsrError
    from tpsr_ros.core.fqi import FQIConfig, QFunction, fit_q
    from tpsr_ros.core.learn import fit
    from tpsr_ros.core.online import OnlineTracker
    from tpsr_ros.core.pca_baseline import PCAConfig, PCAModel
    from tpsr_ros.core.state_model import StateModel, Track, UpdateInfo
    from tpsr_ros.core.tpsr import TPSRConfig, TPSRModel, fit_tpsr
    from tpsr_ros.io.model_io import load_model, save_model
    from tpsr_ros.io.policy import Policy, load_policy, save_policy
    from tpsr_ros.io.trajectory import iter_trajectory_chunks, read_trajectory


__getattr__, __dir__ = lazy_exports(__name__, _API, __all__)
