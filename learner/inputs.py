"""The learner's inputs: topic and step-grid options, and bags read as a model reads them.

``learner fit --step-period SECONDS`` resamples the camera and command streams onto a step
grid (:mod:`tpsr_ros.core.resample`) and remembers its topics, preprocessing, grid and
action codebook in the model (:class:`tpsr_ros.io.streams.StreamSpec`). ``learner plot`` and
``learner policy`` then read bags with :func:`read_for_model`: the model's own spec for such
models, the exact-stamp pairing of simulator bags for the others.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from learner.config_file import TOPIC_KEYS
from tpsr_ros.cli import positive_int
from tpsr_ros.core.actions import environment_grid
from tpsr_ros.core.codebook import COMPONENTS, DEFAULT_COMPONENTS
from tpsr_ros.core.episodes import Trajectory
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.presets import turns
from tpsr_ros.core.units import NS_PER_S
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.model_io import ModelFile, metadata_field, open_model
from tpsr_ros.io.stream_spec import StreamSpec
from tpsr_ros.io.streams import DEFAULT_POSE_FRAME, FitOptions, read_stream_trajectory
from tpsr_ros.io.trajectory import Topics, read_trajectory

__all__ = [
    "add_stream_options",
    "apply_config_inputs",
    "environment_label",
    "far_commands_line",
    "fit_options_from_args",
    "image_size",
    "open_simulator_model",
    "read_for_model",
    "recorded_topic",
    "require_camera",
    "require_given_topics",
    "require_simulator_model",
    "robot_turns",
    "stream_inputs",
    "topics_from_args",
]

GRID_ONLY = (
    "image_size",
    "grey",
    "actions",
    "components",
    "image_timeout",
    "command_timeout",
    "step_offset",
)


def image_size(text: str) -> tuple[int, int]:
    """argparse type: ``N`` (N x N) or ``WxH``; returns ``(height, width)``."""
    parts = text.lower().split("x")
    if len(parts) == 1:
        side = positive_int(parts[0])
        return side, side
    if len(parts) != 2:
        raise argparse.ArgumentTypeError(f"{text!r} is not N or WxH")
    width, height = positive_int(parts[0]), positive_int(parts[1])
    return height, width


def _components(text: str) -> tuple[str, ...]:
    names = tuple(n.strip() for n in text.split(",") if n.strip())
    if not names or any(n not in COMPONENTS for n in names):
        raise argparse.ArgumentTypeError(
            f"{text!r} is not a comma-separated list of {', '.join(COMPONENTS)}"
        )
    return names


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not 1e-6 <= value <= 1e5:
        raise argparse.ArgumentTypeError(f"{text} s is not in [1e-6, 1e5]")
    return value


def add_stream_options(parser: argparse.ArgumentParser | argparse._ArgumentGroup) -> None:
    """The options of robot bags (``learner fit``)."""
    parser.add_argument(
        "--step-period",
        type=_seconds,
        default=None,
        metavar="SECONDS",
        help="resample camera and commands onto steps this far apart (robot bags): between "
        "one camera frame (1.2 x the camera period fit prints) and the time one command "
        "lasts, the short end for a short recording; without it, images and actions are "
        "paired by identical stamp (simulator bags)",
    )
    parser.add_argument(
        "--image-size",
        type=image_size,
        default=None,
        metavar="N|WxH",
        help="observation pixels, resized down by area averaging (default: 16 on the camera's "
        "longer side, aspect kept)",
    )
    parser.add_argument(
        "--grey",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="grey (luma) observations (default: grey for a grey camera, colour otherwise)",
    )
    parser.add_argument(
        "--actions",
        type=positive_int,
        default=None,
        metavar="K",
        help="learn a codebook of K actions from the commands (k-means, seeded by --seed); "
        "default: the simulator's 25 pairs for simulator bags, else one per 60 steps (2 to "
        "25) that the data support",
    )
    parser.add_argument(
        "--components",
        type=_components,
        default=None,
        metavar="C,C...",
        help="command components of the actions; constant ones drop out (default: "
        f"{','.join(DEFAULT_COMPONENTS)})",
    )
    parser.add_argument(
        "--image-timeout",
        type=_seconds,
        default=None,
        metavar="SECONDS",
        help="a step whose latest image is older is a gap (camera silence; default: one step, "
        "or twice the camera's 95th-percentile frame interval if longer)",
    )
    parser.add_argument(
        "--command-timeout",
        type=_seconds,
        default=None,
        metavar="SECONDS",
        help="a command stays in force this long; a step with none in force is a gap "
        "(default: two steps, or twice the commands' 95th-percentile interval if longer)",
    )
    parser.add_argument(
        "--step-offset",
        type=float,
        default=None,
        metavar="SECONDS",
        help="step times are SECONDS + k * --step-period on the bag clock (default: the "
        "offset that keeps steps farthest from image and command stamps)",
    )


def fit_options_from_args(args: argparse.Namespace) -> FitOptions | None:
    """The :class:`FitOptions` of the command line; None without ``--step-period``."""
    if args.step_period is None:
        given = [
            f"--{n.replace('_', '-')}"
            for n in GRID_ONLY
            if getattr(args, n) not in (None, DEFAULT_COMPONENTS)
        ]
        if given:
            raise ConfigError(
                f"{', '.join(given)} need --step-period (exact-stamp pairing reads simulator "
                "bags as they are)"
            )
        return None
    return FitOptions(
        step_period=args.step_period,
        image_size=args.image_size,
        grey=args.grey,
        components=tuple(args.components or DEFAULT_COMPONENTS),
        actions=args.actions,
        image_timeout=args.image_timeout,
        command_timeout=args.command_timeout,
        step_offset=args.step_offset,
        seed=int(args.seed) if isinstance(getattr(args, "seed", None), int) else 0,
    )


def apply_config_inputs(args: argparse.Namespace, values: dict[str, Any]) -> list[str]:
    """Take the config file's ``input`` options for those not given on the command line;
    returns the names taken."""
    taken = []
    for key, value in values.items():
        current = getattr(args, key, None)
        if current is None:
            setattr(args, key, value)
            taken.append(key)
    return taken


def stream_inputs(args: argparse.Namespace, spec: StreamSpec | None) -> dict[str, Any]:
    """The ``input`` section of a config file: the topics given and, for robot bags, the
    spec's resolved options, so that ``learner fit --config`` reads the data the same way."""
    values: dict[str, Any] = {
        key: getattr(args, key)
        for key in TOPIC_KEYS
        if getattr(args, key, None) is not None
    }
    if spec is None:
        return values
    grid, prep, codebook = spec.grid, spec.preprocessing, spec.codebook
    values.update(
        image_topic=spec.image_topic,
        action_topic=spec.action_topic,
        step_period=grid.step_ns / NS_PER_S,
        step_offset=None if grid.phase_ns is None else grid.phase_ns / NS_PER_S,
        image_timeout=grid.image_timeout_ns / NS_PER_S,
        command_timeout=grid.command_timeout_ns / NS_PER_S,
        image_size=(prep.height, prep.width),
        grey=prep.grey,
        components=tuple(codebook.components),
        actions=len(codebook) if codebook.kind == "kmeans" else None,
    )
    return values


def topics_from_args(args: argparse.Namespace) -> Topics:
    """The :class:`Topics` of the ``--NAME-topic`` options given, defaults for the others."""
    return Topics(
        **{
            f.name: getattr(args, f"{f.name}_topic", None) or f.default
            for f in dataclasses.fields(Topics)
        }
    )


def require_given_topics(bags: Sequence[Path], args: argparse.Namespace) -> None:
    """Refuse a topic named by an option (``--pose-topic``, ``--reward-topic``) that a bag
    lacks: a topic given on purpose is not optional, even where the default one is."""
    given = {
        f"--{name}-topic": topic
        for name in ("pose", "reward")
        if (topic := getattr(args, f"{name}_topic", None))
    }
    if not given:
        return
    for bag in bags:
        with BagReader(bag) as reader:
            available = reader.topics_with_messages
        for option, topic in given.items():
            if topic not in available:
                raise ConfigError(
                    f"bag {str(bag)!r} has no messages on {option} {topic} (it has "
                    f"{sorted(available)})"
                )


def recorded_topic(metadata: dict[str, Any], name: str) -> str | None:
    """The ``name`` topic (or ``pose_frame``) recorded by the model's first training bag."""
    bags = metadata_field(metadata, "training", "bags")
    topic = metadata_field(bags[0], "topics", name) if isinstance(bags, list) and bags else None
    return topic if isinstance(topic, str) else None


def environment_label(environment: str | None) -> str:
    """How a model's or bag's data names its source: ``environment full`` for a simulator's,
    ``a robot bag (no simulator environment)`` for the others (None is no environment)."""
    return f"environment {environment}" if environment else "a robot bag (no simulator environment)"


def far_commands_line(trajectory: Trajectory, spec: StreamSpec) -> str:
    """What the codebook made of a robot bag's commands, in the filter node's unit: command
    messages (``far_commands`` among ``command_messages`` on its ``/diagnostics``), not
    steps, which hold a command over; and the grid steps that were gaps."""
    sources = trajectory.sources
    far = sum(int(s.get("far_commands", 0)) for s in sources)
    messages = sum(int(s.get("command_messages", 0)) for s in sources)
    worst = max(float(s.get("worst_command_distance", 0.0)) for s in sources)
    gaps = sum(int(s.get("camera_gaps", 0)) + int(s.get("command_gaps", 0)) for s in sources)
    steps = sum(int(s.get("grid_steps", 0)) for s in sources)
    return (
        f"commands: {far} of {messages} command messages farther than "
        f"{spec.codebook.far_distance:.3g} from every code (worst {worst:.3g}); {gaps} of "
        f"{steps} grid steps were gaps"
    )


def read_for_model(
    model_file: ModelFile,
    bags: list[Path],
    args: argparse.Namespace,
    *,
    require_ground_truth: bool = False,
) -> Trajectory:
    """Read ``bags`` as the model's training bags were read.

    A model with an input spec takes its camera and command topics from it (``--image-topic``
    and ``--action-topic``, if given, must agree); the pose and reward topics are the ones
    given, else the ones of its training bags. Other models pair the topics given by stamp.
    """
    spec: StreamSpec | None = model_file.spec
    metadata = model_file.metadata
    if spec is None:
        return read_trajectory(
            bags,
            topics=topics_from_args(args),
            require_ground_truth=require_ground_truth,
            environment=model_file.environment,  # a recording of sim_node names none
        )
    for name, own in (("image", spec.image_topic), ("action", spec.action_topic)):
        given = getattr(args, f"{name}_topic", None)
        if given and given != own:
            raise ConfigError(
                f"model {str(model_file.path)!r} reads {name} topic {own}, not {given} (omit "
                f"--{name}-topic: the model remembers it)"
            )
    pose = getattr(args, "pose_topic", None) or recorded_topic(metadata, "pose")
    reward = getattr(args, "reward_topic", None) or recorded_topic(metadata, "reward")
    frame = getattr(args, "pose_frame", None) or recorded_topic(metadata, "pose_frame")
    return read_stream_trajectory(
        bags,
        spec,
        pose_topic=pose,
        reward_topic=reward,
        require_ground_truth=require_ground_truth,
        pose_frame=frame or DEFAULT_POSE_FRAME,
    )


def require_simulator_model(model_file: ModelFile) -> None:
    """Refuse a model learned from robot bags where the simulator's actions are meant.

    The simulator executes the 25 pairs by index; a robot model's action indices name its
    own codebook, so driving the simulator with them would be silently wrong.
    """
    spec = model_file.spec
    if spec is not None and spec.codebook.kind != "sim":
        raise ConfigError(
            f"model {str(model_file.path)!r} was learned from robot bags ({len(spec.codebook)} "
            f"{spec.codebook.kind} actions over {', '.join(spec.codebook.components)}); the "
            "simulator's protocol needs a model of its own 25 actions"
        )


def require_camera(
    model_file: ModelFile, vertical_half_extent: float, where: str = "the simulator's"
) -> None:
    """Refuse images from a camera other than the one of the model's training bags.

    A model learned from images of one vertical extent sees other images in another; its
    states (and any policy on them) would be silently wrong. Models whose bags record no
    camera (robot bags, older models) are not checked. ``where`` names the other camera
    (the simulator's: the option that fixes it is added).
    """
    learned = model_file.vertical_half_extent
    if learned is None or math.isclose(learned, vertical_half_extent, rel_tol=1e-9):
        return
    fix = f"; pass --vertical-half-extent {learned:g}" if where == "the simulator's" else ""
    raise ConfigError(
        f"model {str(model_file.path)!r} was learned from bags whose camera has vertical "
        f"half-extent {learned:g}, but {where} has {vertical_half_extent:g}{fix}"
    )


def open_simulator_model(path: Path | str, vertical_half_extent: float) -> ModelFile:
    """The model file at ``path``, refused unless the simulator with this camera can drive
    it (:func:`require_simulator_model`, :func:`require_camera`)."""
    model_file = open_model(path)
    require_simulator_model(model_file)
    require_camera(model_file, vertical_half_extent)
    return model_file


def robot_turns(spec: StreamSpec | None, environment: str | None) -> bool:
    """Whether the robot of the training data turns: its actions carry a turn rate (a robot
    bag's varying command components; a simulator bag's environment, ``drive``)."""
    if spec is not None:
        return turns(spec.codebook.components)
    return turns(environment_grid(environment).components)
