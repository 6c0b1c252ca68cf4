"""Robot motion and wall collisions with pymunk.

The robot is a disk in a square room. A step sets the executed velocity once and lets
pymunk integrate ``physics_substeps`` substeps: a wall stops the velocity component that
pushes into it and the robot slides along it (frictionless, inelastic). The planar robot
never turns; the ``drive`` robot (:meth:`RoomWorld.drive`) has a heading that turns at
the commanded rate, its velocity set along the heading at every substep (a wall cannot
turn it: the disk's moment stays infinite and the heading is integrated here). Walls are
5 m thick and a substep moves at most ~0.7 m, so the robot cannot tunnel through a wall
even at 6 m per step.

A step has *wall contact* when a wall pushed back on the robot during the step (a
non-zero contact impulse): the commanded motion was blocked. Touching or sliding along a
wall without pressing into it is not contact.
"""

from __future__ import annotations

import numpy as np
import pymunk

__all__ = ["RoomWorld"]

_ROBOT, _WALL = 1, 2
_WALL_THICKNESS = 5.0
_IMPULSE_EPS = 1e-9


class RoomWorld:
    """A pymunk space holding the room walls and the robot disk."""

    def __init__(self, room_size: float, robot_radius: float, substeps: int) -> None:
        self.room_size = room_size
        self.robot_radius = robot_radius
        self.substeps = substeps
        self._space = pymunk.Space()
        self._space.collision_slop = 1e-4
        self._space.collision_bias = 0.0  # resolve any overlap completely within one substep
        self._body = pymunk.Body(1.0, float("inf"))  # infinite moment: heading never turns
        disk = pymunk.Circle(self._body, robot_radius)
        disk.collision_type, disk.friction, disk.elasticity = _ROBOT, 0.0, 0.0
        self._space.add(self._body, disk)
        half, size = _WALL_THICKNESS, room_size
        far = size + 2 * half
        for a, b in (
            ((-2 * half, -half), (far, -half)),
            ((size + half, -2 * half), (size + half, far)),
            ((far, size + half), (-2 * half, size + half)),
            ((-half, far), (-half, -2 * half)),
        ):
            wall = pymunk.Segment(self._space.static_body, a, b, half)
            wall.collision_type, wall.friction, wall.elasticity = _WALL, 0.0, 0.0
            self._space.add(wall)
        self._max_impulse = 0.0
        self.heading = np.pi / 2  # radians from +x; the planar robot faces north for ever
        self._space.on_collision(_ROBOT, _WALL, post_solve=self._record_impulse)

    def _record_impulse(self, arbiter: pymunk.Arbiter, space: pymunk.Space, data: object) -> None:
        self._max_impulse = max(self._max_impulse, arbiter.total_impulse.length)

    @property
    def position(self) -> np.ndarray:
        """Robot centre ``(x, y)`` in metres."""
        return np.array(self._body.position)

    def place(self, x: float, y: float, heading: float = np.pi / 2) -> None:
        """Teleport the robot (at rest, facing ``heading``), clamped so it lies fully inside
        the room."""
        self.heading = float(np.mod(heading, 2 * np.pi))
        low, high = self.robot_radius, self.room_size - self.robot_radius
        self._body.position = (float(np.clip(x, low, high)), float(np.clip(y, low, high)))
        self._body.velocity = (0.0, 0.0)
        self._space.reindex_shapes_for_body(self._body)

    def move(self, vx: float, vy: float, duration: float) -> bool:
        """Drive at ``(vx, vy)`` m/s for ``duration`` s; return whether a wall blocked it."""
        self._max_impulse = 0.0
        self._body.velocity = (float(vx), float(vy))
        dt = duration / self.substeps
        for _ in range(self.substeps):
            self._space.step(dt)
        return self._settle(dt)

    def drive(self, speed: float, turn_rate: float, duration: float) -> bool:
        """Drive forward at ``speed`` m/s while turning at ``turn_rate`` rad/s for
        ``duration`` s; return whether a wall blocked it.

        Each substep moves along the chord of its piece of the arc (the heading at its
        middle, the chord's length), so a free step of constant speed and turn rate ends
        exactly on the arc it commands.
        """
        self._max_impulse = 0.0
        dt = duration / self.substeps
        chord = speed * float(np.sinc(0.5 * turn_rate * dt / np.pi))  # sin(x)/x, x = w dt / 2
        heading = self.heading
        for _ in range(self.substeps):
            middle = heading + 0.5 * turn_rate * dt
            self._body.velocity = (chord * np.cos(middle), chord * np.sin(middle))
            self._space.step(dt)
            heading += turn_rate * dt
        self.heading = float(np.mod(heading, 2 * np.pi))
        return self._settle(dt)

    def _settle(self, dt: float) -> bool:
        # At rest, one more substep lets pymunk push out any overlap left by the last one.
        self._body.velocity = (0.0, 0.0)
        self._space.step(dt)
        return self._max_impulse > _IMPULSE_EPS
