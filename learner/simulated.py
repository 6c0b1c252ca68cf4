"""Simulated trajectories in memory, in the learner's ``Trajectory`` form (no bag needed).

Experiments generate hundreds of random runs; writing each to a bag and reading it back
would only add time. A run from :func:`sim_node.random_rollout` carries exactly what a
generated bag would hold, so it converts directly.
"""

from __future__ import annotations

import numpy as np

from sim_node import SimConfig, random_rollout
from tpsr_ros.core.actions import NUM_ACTIONS
from tpsr_ros.core.episodes import Trajectory, images_to_observations

__all__ = ["random_trajectory"]


def random_trajectory(environment: str, steps: int, seed: int) -> Trajectory:
    """A uniformly random run of ``steps`` steps as one gap-free trajectory."""
    config = SimConfig(environment=environment)
    run = random_rollout(config, steps, seed)
    return Trajectory(
        stamps=run.stamps_ns,
        observations=images_to_observations(run.images),
        actions=run.actions.astype(np.int64),
        velocities=run.commands,
        positions=run.positions,
        rewards=run.rewards,
        segments=np.zeros(steps, dtype=np.int64),
        image_shape=(config.image_size, config.image_size),
        n_actions=NUM_ACTIONS,
        sources=[{"simulated": True, "environment": environment, "seed": seed, "steps": steps}],
    )
