"""A policy of a robot model driving the simulator: the standard protocol (10 starts, 50
greedy steps) with the robot bag's camera and the simulator snapping each command.

A model learned from a ``sim_node.robot_bag`` bag sees that bag's camera (40x40 by
default) through its own preprocessing, and chooses codes of its k-means codebook; the
simulator executes the nearest of its own actions to the code's command (as ``sim_node``
in command mode snaps ``/cmd_vel``), and the model is updated with the code it chose, as
the filter node is with the command in force.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from learner.evaluate import Evaluation, run_protocol
from sim_node import SimConfig
from tpsr_ros.core.actions import environment_grid
from tpsr_ros.core.images import preprocess_images
from tpsr_ros.io.model_io import ModelFile
from tpsr_ros.io.policy import Policy


@dataclass
class _CodeTracker:
    """The model's states from the camera's images and the codes the policy chose."""

    model_file: ModelFile
    chosen: list[int] = field(default_factory=list)
    representation: str = "tpsr"

    @property
    def fingerprint(self) -> str:
        return self.model_file.fingerprint

    def start(self, image: np.ndarray, position: np.ndarray) -> np.ndarray:
        return self.model_file.model.initial_state()

    def step(self, state, action, image, position):
        observation = preprocess_images(image[None], self.model_file.spec.preprocessing)[0]
        return self.model_file.model.update(state, self.chosen[-1], observation)[0]

    def track(self, trajectory):  # not used by the protocol
        raise NotImplementedError


def sim_actions_of_codes(model_file: ModelFile, environment: str = "full") -> np.ndarray:
    """The simulator's action nearest to each code of the model's codebook."""
    book = model_file.spec.codebook
    grid = environment_grid(environment)
    commands = np.zeros((len(book), len(grid.components)))
    for column, name in enumerate(grid.components):
        if name in book.components:
            commands[:, column] = book.codes[:, book.components.index(name)]
    return grid.indices(commands)


def evaluate_robot_policy(
    policy: Policy, model_file: ModelFile, *, environment: str = "full", image_size: int = 40
) -> Evaluation:
    """The standard protocol for ``policy`` on ``model_file``'s states (module docstring)."""
    policy.check_model(model_file.fingerprint)
    to_sim = sim_actions_of_codes(model_file, environment)
    tracker = _CodeTracker(model_file)

    def choose(state: np.ndarray) -> int:
        code = int(policy.action(state))
        tracker.chosen.append(code)
        return int(to_sim[code])

    config = SimConfig(environment=environment, image_size=image_size)
    return run_protocol(choose, tracker, config)
