"""The simulator standing in for the robot of a model learned from robot bags.

A model learned with ``learner fit --step-period`` reads its robot's camera through its own
preprocessing and chooses codes of its own codebook. The simulator can play that robot when
it can render the camera (an ``Image`` of the camera's size, square, one image per 1 s
step) and execute the codes (each code's command snapped to the nearest of its actions,
as ``sim_node`` in command mode snaps ``/cmd_vel``). ``learner evaluate`` and ``learner
closed-loop`` both take the camera size and the code-to-action map from here, so the
headless protocol and the one over the nodes drive the simulator identically.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sim_node import SimConfig
from sim_node.config import DEFAULT_COMMAND_TOLERANCE
from tpsr_ros.core.actions import PLANAR
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.units import NS_PER_S
from tpsr_ros.io.images import IMAGE_TYPE
from tpsr_ros.io.model_io import ModelFile, metadata_field

__all__ = ["SimulatedRobot", "is_robot_model", "recorded_camera", "simulated_robot"]


@dataclass(frozen=True)
class SimulatedRobot:
    """How the simulator plays a robot model's robot.

    Attributes:
        camera_size: the simulator camera's pixels on each side (the robot camera's).
        sim_actions: ``(K,)`` the simulator's action index of each code of the codebook.
        image_topic: the model's camera topic (the simulator's camera is remapped to it).
        step_ns, phase_ns: the model's step grid (step times ``phase + k * step``).

    """

    camera_size: int
    sim_actions: np.ndarray
    image_topic: str
    step_ns: int
    phase_ns: int

    def step_time(self, stamp: int) -> int:
        """The grid time of the simulator's step stamped ``stamp``: the first at or after it
        (the filter node's lockstep stamps its state with it)."""
        return int(stamp) + (self.phase_ns - int(stamp)) % self.step_ns

    def execute(self, code: int) -> int:
        """The simulator's action for the policy's code."""
        return int(self.sim_actions[int(code)])


def is_robot_model(model_file: ModelFile) -> bool:
    """Whether the model acts by a codebook of its own (learned from robot bags)."""
    spec = model_file.spec
    return spec is not None and spec.codebook.kind != "sim"


def recorded_camera(metadata: dict[str, Any]) -> tuple[int, int] | None:
    """``(height, width)`` of the first training bag's camera, if the model records it."""
    bags = metadata_field(metadata, "training", "bags")
    camera = metadata_field(bags[0], "camera") if isinstance(bags, list) and bags else None
    if not isinstance(camera, dict):
        return None
    height, width = camera.get("height"), camera.get("width")
    if not (isinstance(height, int) and isinstance(width, int) and height > 0 and width > 0):
        return None
    return height, width


def simulated_robot(
    model_file: ModelFile, config: SimConfig, camera_size: int | None = None
) -> SimulatedRobot:
    """The simulator as the robot of ``model_file`` (module docstring), or a one-line
    ``ConfigError`` saying why it cannot be. ``camera_size`` overrides the recorded camera."""
    spec = model_file.spec
    name = repr(str(model_file.path))
    if spec is None:
        raise ConfigError(f"model {name} was not learned on a step grid (no robot streams)")
    period = spec.grid.step_ns / NS_PER_S
    if spec.grid.step_ns != round(config.step_seconds * NS_PER_S):
        raise ConfigError(
            f"model {name} steps every {period:g} s, the simulator every "
            f"{config.step_seconds:g} s: fit the robot bag with --step-period "
            f"{config.step_seconds:g}"
        )
    if spec.grid.phase_ns is None:
        raise ConfigError(f"model {name} records no step phase (an older fit): refit it")
    if spec.image_type != IMAGE_TYPE:
        raise ConfigError(
            f"model {name} reads {spec.image_type} on {spec.image_topic}; the simulator's "
            f"camera publishes {IMAGE_TYPE} (rgb8)"
        )
    if camera_size is None:
        camera = recorded_camera(model_file.metadata)
        if camera is None and spec.codebook.kind == "sim":  # a simulator bag's camera
            camera = (config.image_size, config.image_size)
        if camera is None:
            raise ConfigError(
                f"model {name} records no camera size (an older fit): pass --camera-size N, "
                "the pixels on each side of its robot's camera"
            )
        if camera[0] != camera[1]:
            raise ConfigError(
                f"model {name} was learned from a {camera[1]}x{camera[0]} camera; the "
                "simulator's camera is square"
            )
        camera_size = camera[0]
    prep = spec.preprocessing
    if camera_size < max(prep.height, prep.width):
        raise ConfigError(
            f"model {name} takes {prep.width}x{prep.height} observations, more than a "
            f"{camera_size}x{camera_size} camera gives"
        )
    return SimulatedRobot(
        int(camera_size),
        sim_actions(model_file, config),
        spec.image_topic,
        int(spec.grid.step_ns),
        int(spec.grid.phase_ns),
    )


def sim_actions(model_file: ModelFile, config: SimConfig) -> np.ndarray:
    """The simulator's action for each code: its command snapped as ``sim_node`` snaps a
    ``/cmd_vel`` (within its default ``command_tolerance``), refused if it cannot be."""
    spec = model_file.spec
    assert spec is not None
    book, grid = spec.codebook, config.actions
    commands = np.zeros((len(book), len(grid.components)))
    for column, component in enumerate(book.components):
        if component in grid.components:
            commands[:, grid.components.index(component)] = book.codes[:, column]
        elif np.any(book.codes[:, column] != 0):
            raise ConfigError(
                f"model {str(model_file.path)!r} commands {component}, which the simulator's "
                f"{config.environment.value} robot does not have (it executes "
                f"{', '.join(grid.components)})"
            )
    limits = tuple(DEFAULT_COMMAND_TOLERANCE * grid.spacing() / PLANAR.spacing())
    try:
        return grid.indices(commands, limits)
    except ConfigError as exc:
        raise ConfigError(
            f"model {str(model_file.path)!r}: a code the simulator cannot execute: {exc}"
        ) from None
