"""Fast batch path for long random trajectories (the guide's largest set is 135000 steps).

Draws every exploration action, noise sample and distractor move as whole arrays, runs
the pymunk motion in one tight loop and renders the images in vectorised chunks. It
consumes the same streams in the same order as stepping ``RobotEnv`` with
``sample_action``, so with the same seed it yields exactly the same rollout.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np

from sim_node.camera import Camera
from sim_node.config import SimConfig
from sim_node.distractors import distractor_paths
from sim_node.env import motion, pose_of, spawn_streams, start_pose, step_reward
from sim_node.world import RoomWorld
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.units import NS_PER_S as _NS

__all__ = ["Rollout", "iter_random_rollout", "random_rollout"]


@dataclass(frozen=True)
class Rollout:
    """Steps ``first_step .. first_step + N - 1`` of a random run (arrays of length N)."""

    first_step: int
    stamps_ns: np.ndarray  # (N,) int64, t_k = start_time_ns + k s
    actions: np.ndarray  # (N,) int, index into the environment's action grid
    commands: np.ndarray  # (N, 2) commanded velocity (drive: speed, turn rate), m/s, rad/s
    executed: np.ndarray  # (N, 2) executed command (with noise)
    positions: np.ndarray  # (N, 2) true position after the step, m
    headings: np.ndarray  # (N,) true heading after the step, rad from +x (planar: pi/2)
    poses: np.ndarray  # (N, 2) positions, or (N, 4) x, y, cos, sin in drive (pose_of)
    wall_contact: np.ndarray  # (N,) bool
    goal_zone: np.ndarray  # (N,) bool
    rewards: np.ndarray  # (N,) float
    images: np.ndarray  # (N, H, W, 3) uint8, o_k

    def __len__(self) -> int:
        return len(self.actions)


def iter_random_rollout(
    config: SimConfig,
    steps: int,
    seed: int,
    *,
    start: tuple[float, float] | None = None,
    chunk: int = 1024,
) -> Iterator[Rollout]:
    """Yield a ``steps``-long uniformly random run as consecutive chunks of ``chunk`` steps."""
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps <= 0:
        raise ConfigError(f"steps must be a positive integer, got {steps!r}")
    if chunk <= 0:
        raise ConfigError("chunk must be positive")
    streams = spawn_streams(seed)
    start_xy, heading = start_pose(config, streams.start)
    if start is not None:
        start_xy, heading = np.asarray(start, dtype=np.float64), np.pi / 2
    world = RoomWorld(config.room_size, config.robot_radius, config.physics_substeps)
    world.place(*start_xy, heading)
    move = motion(config, world)
    camera = Camera(config)
    grid = config.actions
    actions = streams.actions.integers(0, len(grid), size=steps)
    noise = streams.noise.standard_normal((steps, 2))
    commands = grid.codes[actions]
    executed = commands + config.noise_fraction * np.abs(commands) * noise
    floor = walls = None
    if config.has_distractors:
        _, _, floor, walls = distractor_paths(config, streams.distractors, steps)
    for begin in range(0, steps, chunk):
        end = min(begin + chunk, steps)
        positions = np.empty((end - begin, 2))
        headings = np.empty(end - begin)
        contact = np.empty(end - begin, dtype=bool)
        for i, (first, second) in enumerate(executed[begin:end].tolist()):
            contact[i] = move(first, second, config.step_seconds)
            positions[i] = world.position
            headings[i] = world.heading
        rewards, goal = step_reward(config, positions, contact)
        images = camera.render(
            positions,
            None if floor is None else floor[begin:end],
            None if walls is None else walls[begin:end],
            headings=headings if config.drives else None,
        )
        step_index = np.arange(begin + 1, end + 1, dtype=np.int64)
        yield Rollout(
            first_step=begin + 1,
            stamps_ns=config.start_time_ns + step_index * _NS,
            actions=actions[begin:end],
            commands=commands[begin:end],
            executed=executed[begin:end],
            positions=positions,
            headings=headings,
            poses=pose_of(config, positions, headings),
            wall_contact=contact,
            goal_zone=goal,
            rewards=rewards,
            images=images,
        )


def random_rollout(
    config: SimConfig, steps: int, seed: int, *, start: tuple[float, float] | None = None
) -> Rollout:
    """A whole ``steps``-long uniformly random run in one ``Rollout``."""
    parts = list(iter_random_rollout(config, steps, seed, start=start))
    return Rollout(
        first_step=1,
        **{
            name: np.concatenate([getattr(p, name) for p in parts])
            for name in (
                "stamps_ns", "actions", "commands", "executed", "positions", "headings",
                "poses", "wall_contact", "goal_zone", "rewards", "images",
            )
        },
    )
