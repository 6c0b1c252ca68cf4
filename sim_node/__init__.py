"""Simulated mobile robot of the guide's section 4.1, with no ROS imports in its core.

``RobotEnv`` (reset/step/seed like Gymnasium) for one step at a time, ``random_rollout``
for long random trajectories, ``python -m sim_node`` as a ROS 2 node and
``python -m sim_node.generate`` for bags.
"""

from sim_node.config import DistractorConfig, Environment, SimConfig
from sim_node.env import RobotEnv
from sim_node.rollout import Rollout, random_rollout
from tpsr_ros.core.actions import ACTIONS, VELOCITIES, action_index

__all__ = [
    "ACTIONS",
    "VELOCITIES",
    "DistractorConfig",
    "Environment",
    "RobotEnv",
    "Rollout",
    "SimConfig",
    "action_index",
    "random_rollout",
]
