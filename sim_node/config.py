"""Simulator configuration: the guide's section 4.1 environment as frozen dataclasses.

Units are metres and seconds; one step lasts 1 s, so a velocity of 3 m/s moves 3 m.
The room spans ``[0, room_size]`` in x (west to east) and y (south to north); the goal is
the north-east (top right) corner.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

from tpsr_ros.core.actions import DEFAULT_TURN_RATE_DEG, PLANAR, ActionGrid, drive_grid
from tpsr_ros.core.errors import ConfigError

__all__ = [
    "DEFAULT_COMMAND_TOLERANCE",
    "DEFAULT_VERTICAL_HALF_EXTENT",
    "MAX_VERTICAL_HALF_EXTENT",
    "STRIP_VERTICAL_HALF_EXTENT",
    "DistractorConfig",
    "Environment",
    "SimConfig",
    "check_vertical_half_extent",
]

STEP_SECONDS = 1.0
DEFAULT_COMMAND_TOLERANCE = 3.0
"""Command mode: the farthest (m/s) a ``/cmd_vel`` component may lie from the planar grid's
nearest speed (0, ±3, ±6); relative to the grid's spacing for other grids."""
DEFAULT_VERTICAL_HALF_EXTENT = 0.2
"""The camera's vertical half-extent (tangent of the half-angle, ±11.3°) of the guide's
environments: a wall farther than 10 m shows its top and the floor."""
STRIP_VERTICAL_HALF_EXTENT = 0.1
"""``partial-strip``'s (±5.7°): a wall fills every row within 20 m, so most views of a wall
no longer tell the distance to it."""
MAX_VERTICAL_HALF_EXTENT = 5.0
"""Largest vertical half-extent accepted: ±78.7°; the rows are even in tangent, so a view
near ±90° would spend almost every row on the floor and the sky."""


def check_vertical_half_extent(value: float) -> float:
    """``value`` if it is a vertical half-extent the camera can render, else ``ConfigError``."""
    if isinstance(value, bool) or not (isinstance(value, (int, float)) and math.isfinite(value)):
        raise ConfigError(f"vertical_half_extent must be a number, got {value!r}")
    if not 0 < value <= MAX_VERTICAL_HALF_EXTENT:
        raise ConfigError(
            "vertical_half_extent (the tangent of the camera's half vertical field of view) "
            f"must be in (0, {MAX_VERTICAL_HALF_EXTENT:g}], got {value:g}"
        )
    return float(value)


class Environment(str, Enum):
    """The three environments of the guide's chapter 4; ``partial-strip``: ``partial``'s
    60 degree camera with a vertical extent that hides the walls' distance (the results
    appendix's camera study: there a reactive policy stops solving the task); ``drive``: a
    differential-drive robot that turns, its camera turning with it (300 degrees unless
    given)."""

    FULL = "full"
    PARTIAL = "partial"
    DISTRACTORS = "distractors"
    PARTIAL_STRIP = "partial-strip"
    DRIVE = "drive"

    @property
    def narrow(self) -> bool:
        """Whether the camera sees 60 degrees (``partial``, ``partial-strip``), not 300."""
        return self in (Environment.PARTIAL, Environment.PARTIAL_STRIP)

    @property
    def vertical_half_extent(self) -> float:
        """The camera's vertical half-extent unless one is given."""
        if self is Environment.PARTIAL_STRIP:
            return STRIP_VERTICAL_HALF_EXTENT
        return DEFAULT_VERTICAL_HALF_EXTENT

    @classmethod
    def parse(cls, name: str | Environment) -> Environment:
        """Environment from its name; unknown names raise ``ConfigError``."""
        try:
            return cls(name)
        except ValueError:
            choices = ", ".join(e.value for e in cls)
            raise ConfigError(f"unknown environment {name!r}; choose one of {choices}") from None


@dataclass(frozen=True)
class DistractorConfig:
    """Randomly moving distractors (guide figure 4.6): three disks on the floor and one
    rectangle on each wall, differing from their background only in the red channel.

    Each moves as a slow reflected Gaussian random walk: ``step_std`` metres (standard
    deviation per coordinate) per 1 s step, 1.5 m by default, so a distractor persists
    from step to step like the guide's "randomly moving" objects and drifts across the
    room over tens of steps. (Steps of 15 m, the first version, redrew them almost
    independently every step: white noise rather than moving objects.) Sizes are ours
    (the guide gives none): disks of radius 6 m and 16 m wide rectangles over the full
    wall height.
    """

    floor_count: int = 3
    floor_radius: float = 6.0
    wall_half_width: float = 8.0
    wall_bottom: float = 0.0
    wall_top: float = 4.0
    step_std: float = 1.5

    def __post_init__(self) -> None:
        if self.floor_count < 0:
            raise ConfigError("floor_count must be >= 0")
        if self.floor_radius <= 0 or self.wall_half_width <= 0 or self.step_std < 0:
            raise ConfigError("distractor sizes must be positive and step_std >= 0")
        if not 0 <= self.wall_bottom < self.wall_top:
            raise ConfigError("wall distractor needs 0 <= wall_bottom < wall_top")


@dataclass(frozen=True)
class SimConfig:
    """Everything that defines a simulated environment; validated on construction.

    ``vertical_half_extent`` is the tangent of the camera's half vertical field of view
    (None: the environment's, :attr:`vertical_extent`): 0.2 (±11.3°) makes a panoramic
    strip in which the walls fill most rows. With a tall
    view (±45°) the looming of a near wall dominates the image variance and folds the
    principal components of the room (PCA then fails even in ``full``, unlike guide
    figure 4.5 d-f); with the strip, PCA maps x and y orthogonally as in the guide.
    """

    environment: Environment = Environment.FULL
    room_size: float = 45.0
    wall_height: float = 4.0
    robot_radius: float = 1.0
    robot_height: float = 2.0
    image_size: int = 16
    field_of_view_deg: float | None = None
    turn_rate_deg: float = DEFAULT_TURN_RATE_DEG
    vertical_half_extent: float | None = None
    rays_per_column: int = 8
    noise_fraction: float = 0.1
    goal_radius: float = 15.0
    goal_reward: float = 10.0
    wall_reward: float = -1.0
    physics_substeps: int = 10
    start_time_ns: int = 0
    distractors: DistractorConfig = field(default_factory=DistractorConfig)

    def __post_init__(self) -> None:
        object.__setattr__(self, "environment", Environment.parse(self.environment))
        if self.room_size <= 2 * self.robot_radius or self.robot_radius <= 0:
            raise ConfigError("room must be wider than the robot and the radius positive")
        if not 0 < self.robot_height < self.wall_height:
            raise ConfigError("the camera (robot_height) must sit below the top of the walls")
        if self.image_size < 1 or self.rays_per_column < 1 or self.physics_substeps < 1:
            raise ConfigError("image_size, rays_per_column and physics_substeps must be >= 1")
        fov = self.field_of_view_deg
        if fov is not None and (
            isinstance(fov, bool) or not isinstance(fov, (int, float)) or not 0 < fov <= 360
        ):
            raise ConfigError(f"field of view must be in (0, 360] degrees, got {fov!r}")
        drive_grid(self.turn_rate_deg)  # validates the turn rate
        if self.vertical_half_extent is not None:
            check_vertical_half_extent(self.vertical_half_extent)
        if self.noise_fraction < 0 or self.goal_radius <= 0:
            raise ConfigError("goal_radius must be > 0 and noise_fraction >= 0")
        if self.start_time_ns < 0:
            raise ConfigError("start_time_ns must be >= 0")

    @property
    def fov_deg(self) -> float:
        """Horizontal field of view: the one given, else 300 deg (full, distractors, drive)
        or 60 deg (partial, partial-strip)."""
        if self.field_of_view_deg is not None:
            return float(self.field_of_view_deg)
        return 60.0 if self.environment.narrow else 300.0

    @property
    def vertical_extent(self) -> float:
        """The camera's vertical half-extent: the one given, else the environment's."""
        if self.vertical_half_extent is not None:
            return float(self.vertical_half_extent)
        return self.environment.vertical_half_extent

    @property
    def drives(self) -> bool:
        """Whether the robot turns (``drive``): it has a heading, the camera turns with it."""
        return self.environment is Environment.DRIVE

    @property
    def actions(self) -> ActionGrid:
        """The commands of the actions: the planar 25 or ``drive``'s 9 (speed, turn rate)."""
        return drive_grid(self.turn_rate_deg) if self.drives else PLANAR

    @property
    def has_distractors(self) -> bool:
        """Whether the camera sees the moving distractors."""
        return self.environment is Environment.DISTRACTORS

    @property
    def step_seconds(self) -> float:
        """Duration of one step (fixed by the design: 1 s)."""
        return STEP_SECONDS
