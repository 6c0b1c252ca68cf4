"""The simulated robot as a seeded environment with Gymnasium's reset/step conventions.

One step: the robot executes action a_k (its commanded velocity plus Gaussian noise with
a standard deviation of ``noise_fraction`` of each commanded component) for 1 s, then
the camera sees o_k. In ``drive`` the components are the forward speed and the turn rate,
and the robot has a heading: random at a random start, north unless given at a placed one.
Step k is stamped ``start_time_ns + k * 1 s``; reset is step 0.

Reward of a step (guide 4.1: reach the upper right-hand corner "without hitting walls"):
``wall_reward`` (-1) when a wall blocked the robot during the step, and nothing else,
inside the goal zone too; otherwise ``goal_reward`` (+10) when the robot centre ends the
step closer than ``goal_radius`` (15 m) to the north-east corner; otherwise 0. A
collision overrides the goal reward because otherwise a state-blind push into the corner
earns +9 per step, 90 % of the maximum, and the evaluation could not tell a learned
representation from none (the guide's failing representations score about 0).

Randomness comes from four independent streams spawned from one seed: start position
(and heading), exploration actions, execution noise and distractors. With the same seed
and actions the guide's environments therefore follow exactly the same trajectory.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from sim_node.camera import Camera
from sim_node.config import SimConfig
from sim_node.distractors import Distractors
from sim_node.world import RoomWorld
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.units import NS_PER_S as _NS

__all__ = [
    "RobotEnv",
    "Streams",
    "motion",
    "pose_of",
    "spawn_streams",
    "start_pose",
    "step_reward",
]


class Streams:
    """The four named random generators of one seeded run."""

    def __init__(self, seed: int) -> None:
        if not isinstance(seed, (int, np.integer)) or seed < 0:
            raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
        start, actions, noise, distractors = np.random.SeedSequence(int(seed)).spawn(4)
        self.start = np.random.default_rng(start)
        self.actions = np.random.default_rng(actions)
        self.noise = np.random.default_rng(noise)
        self.distractors = np.random.default_rng(distractors)


def spawn_streams(seed: int) -> Streams:
    """Independent start, action, noise and distractor generators for ``seed``."""
    return Streams(seed)


def start_pose(config: SimConfig, rng: np.random.Generator) -> tuple[np.ndarray, float]:
    """A uniformly random start position, and for ``drive`` a uniformly random heading (the
    planar robot faces north: its start draws nothing more than it always did)."""
    low, high = config.robot_radius, config.room_size - config.robot_radius
    position = rng.uniform(low, high, size=2)
    heading = float(rng.uniform(0.0, 2 * np.pi)) if config.drives else np.pi / 2
    return position, heading


def motion(config: SimConfig, world: RoomWorld) -> Callable[[float, float, float], bool]:
    """How ``world`` carries out an executed command for a duration: ``drive`` (speed, turn
    rate) or move (vx, vy); returns whether a wall blocked it."""
    return world.drive if config.drives else world.move


def pose_of(config: SimConfig, positions: np.ndarray, headings: np.ndarray) -> np.ndarray:
    """Ground truth as the learner sees it: ``(..., 2)`` positions, or for ``drive``
    ``(..., 4)`` rows ``(x, y, cos heading, sin heading)``."""
    positions = np.asarray(positions, dtype=np.float64)
    if not config.drives:
        return positions.copy()
    headings = np.asarray(headings, dtype=np.float64)
    return np.concatenate(
        [positions, np.cos(headings)[..., None], np.sin(headings)[..., None]], axis=-1
    )


def step_reward(config: SimConfig, position: np.ndarray, contact: np.ndarray) -> np.ndarray:
    """Reward and goal-zone flag for positions ``(..., 2)`` and contact flags ``(...)``.

    A blocked step earns ``wall_reward`` whether or not it ends in the goal zone; a free
    step in the zone earns ``goal_reward`` (see the module docstring for why).
    """
    corner = np.array([config.room_size, config.room_size])
    goal = np.linalg.norm(np.asarray(position) - corner, axis=-1) < config.goal_radius
    blocked = np.asarray(contact, dtype=bool)
    reward = np.where(blocked, config.wall_reward, np.where(goal, config.goal_reward, 0.0))
    return reward.astype(np.float64), goal


_NO_IMAGE = np.zeros((0, 0, 3), dtype=np.uint8)
"""The observation of an environment that does not render."""


class RobotEnv:
    """Mobile robot in the guide's room; observations are ``(16, 16, 3)`` uint8 images."""

    def __init__(self, config: SimConfig | None = None, seed: int = 0, render: bool = True) -> None:
        """``render`` False: observations are empty (for controllers that never look; the
        dynamics, rewards and random streams are the same, as rendering draws nothing)."""
        self.config = config or SimConfig()
        self._render = render
        self.camera = Camera(self.config)
        self._world = RoomWorld(
            self.config.room_size, self.config.robot_radius, self.config.physics_substeps
        )
        self._streams = Streams(seed)
        self._actions = self.config.actions
        self._move = motion(self.config, self._world)
        self._distractors: Distractors | None = None
        self._step = 0
        self._ready = False

    @property
    def position(self) -> np.ndarray:
        """True robot centre ``(x, y)`` in metres (ground truth, never a learning input)."""
        return self._world.position

    @property
    def heading(self) -> float:
        """True heading in radians from +x (north, pi/2, for the planar robot)."""
        return self._world.heading

    @property
    def pose(self) -> np.ndarray:
        """The ground truth the learner sees: :func:`pose_of` the position and heading."""
        return pose_of(self.config, self.position, np.asarray(self.heading))

    @property
    def num_actions(self) -> int:
        """How many actions :meth:`step` takes (25 planar, 9 in ``drive``)."""
        return len(self._actions)

    @property
    def step_count(self) -> int:
        """Steps since the last reset."""
        return self._step

    @property
    def stamp_ns(self) -> int:
        """Stamp of the current step: ``start_time_ns + k * 1 s``."""
        return self.config.start_time_ns + self._step * _NS

    def sample_action(self) -> int:
        """A uniformly random action index from the exploration stream."""
        return int(self._streams.actions.integers(0, self.num_actions))

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start a new run; ``seed`` re-seeds every stream, ``options["position"]`` places
        the robot (otherwise uniformly at random) and ``options["heading"]`` (radians)
        turns it. Returns ``(observation, info)``."""
        if seed is not None:
            self._streams = Streams(seed)
        options = options or {}
        start, heading = start_pose(self.config, self._streams.start)
        if "position" in options:
            start = np.asarray(options["position"], dtype=np.float64)
            if start.shape != (2,) or not np.all(np.isfinite(start)):
                raise ConfigError(f"start position must be two finite numbers, got {start}")
            heading = np.pi / 2
        if "heading" in options:
            heading = float(options["heading"])
            if not np.isfinite(heading):
                raise ConfigError(f"start heading must be a finite number, got {heading}")
            if not self.config.drives and heading != np.pi / 2:
                raise ConfigError(f"the {self.config.environment.value} robot cannot turn")
        self._world.place(*start, heading)
        self._distractors = (
            Distractors(self.config, self._streams.distractors)
            if self.config.has_distractors
            else None
        )
        self._step = 0
        self._ready = True
        info = {
            "position": self.position,
            "heading": self.heading,
            "pose": self.pose,
            "step": 0,
            "stamp_ns": self.stamp_ns,
        }
        return self._observe(), info

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Execute action ``action`` (0..24; 0..8 in ``drive``) for one step.

        Returns ``(observation, reward, terminated, truncated, info)`` with info keys
        ``position``, ``heading``, ``pose``, ``command``, ``executed_velocity``,
        ``wall_contact``,
        ``goal_zone``, ``step`` and ``stamp_ns``. The task never terminates; time
        limits belong to the caller.
        """
        if not self._ready:
            raise ConfigError("call reset() before step()")
        count = self.num_actions
        if not (isinstance(action, (int, np.integer)) and 0 <= action < count):
            raise ConfigError(f"action must be an integer in [0, {count}), got {action!r}")
        command = self._actions.codes[int(action)]
        noise = self._streams.noise.standard_normal(2)
        executed = command + self.config.noise_fraction * np.abs(command) * noise
        contact = self._move(executed[0], executed[1], self.config.step_seconds)
        if self._distractors is not None:
            self._distractors.advance()
        self._step += 1
        position = self.position
        reward, goal = step_reward(self.config, position, contact)
        info = {
            "position": position,
            "heading": self.heading,
            "pose": self.pose,
            "command": command.copy(),
            "executed_velocity": executed,
            "wall_contact": bool(contact),
            "goal_zone": bool(goal),
            "step": self._step,
            "stamp_ns": self.stamp_ns,
        }
        return self._observe(), float(reward), False, False, info

    def _observe(self) -> np.ndarray:
        if not self._render:
            return _NO_IMAGE
        if self.config.drives:
            return self.camera.render(self.position[None], headings=np.array([self.heading]))[0]
        if self._distractors is None:
            return self.camera.render(self.position[None])[0]
        floor, walls = self._distractors.positions()
        return self.camera.render(self.position[None], floor[None], walls[None])[0]
