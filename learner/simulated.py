"""Simulated trajectories in memory, in the learner's ``Trajectory`` form (no bag needed).

Experiments generate hundreds of random runs; writing each to a bag and reading it back
would only add time. A run from :func:`sim_node.random_rollout` carries exactly what a
generated bag would hold, so it converts directly.

:class:`SimSettings` holds what an experiment may change about the simulator
(``--set sim.vertical_half_extent=0.03``): the camera's vertical extent.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_node import SimConfig, random_rollout
from sim_node.config import MAX_VERTICAL_HALF_EXTENT, Environment, check_vertical_half_extent
from tpsr_ros.core.episodes import Trajectory, images_to_observations
from tpsr_ros.core.fields import option

__all__ = ["SimSettings", "random_trajectory"]


@dataclass(frozen=True)
class SimSettings:
    """The simulator settings an experiment varies; None: the environment's own."""

    vertical_half_extent: float | None = option(
        None,
        "camera: tangent of the half vertical field of view (default: the environment's)",
        positive=True,
        maximum=MAX_VERTICAL_HALF_EXTENT,
    )

    def __post_init__(self) -> None:
        if self.vertical_half_extent is not None:
            check_vertical_half_extent(self.vertical_half_extent)

    def config(self, environment: Environment | str, **fields: Any) -> SimConfig:
        """The simulator of ``environment`` with these settings (and ``fields``)."""
        return SimConfig(
            environment=Environment.parse(environment),
            vertical_half_extent=self.vertical_half_extent,
            **fields,
        )


def random_trajectory(
    environment: str, steps: int, seed: int, sim: SimSettings | None = None
) -> Trajectory:
    """A uniformly random run of ``steps`` steps as one gap-free trajectory (its positions:
    ``(x, y)``, or ``(x, y, cos, sin)`` of the heading in ``drive``)."""
    sim = sim or SimSettings()
    config = sim.config(environment)
    run = random_rollout(config, steps, seed)
    return Trajectory(
        stamps=run.stamps_ns,
        observations=images_to_observations(run.images),
        actions=run.actions.astype(np.int64),
        velocities=run.commands,
        positions=run.poses,
        rewards=run.rewards,
        segments=np.zeros(steps, dtype=np.int64),
        image_shape=(config.image_size, config.image_size),
        n_actions=len(config.actions),
        sources=[
            {
                "simulated": True,
                "environment": environment,
                "seed": seed,
                "steps": steps,
                "vertical_half_extent": config.vertical_extent,
            }
        ],
    )
