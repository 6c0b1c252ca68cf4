"""A simulated run recorded the way a real robot records it (test data for robot bags).

    python -m sim_node.robot_bag --steps 300 --seed 0 --encoding bgr8 -o robot_bag
    python -m sim_node.robot_bag --timeline step-start --steps 6000 -o robot_bag
    python -m sim_node.robot_bag --timeline phone --steps 70 -o phone_bag

The simulator's random run (the 25 velocity pairs) is re-recorded as a researcher's robot
would: a camera of its own size and rate with late, jittered stamps, unstamped continuous
velocity commands at their own times, and odometry. Three timelines (``--timeline``):

- ``moving`` (default): 1 s steps. ``/front_camera/image_raw`` (``sensor_msgs/msg/Image``,
  bgr8 or mono8, 40x40; ``--encoding jpeg``: ``CompressedImage`` on ``.../compressed``) at
  4 Hz on quarter seconds, stamped 5..40 ms late, rendering the robot as it moves (step
  ``k`` moves it linearly during ``[k-1, k]`` s); ``/cmd_vel`` (``Twist``, unstamped) 0.4
  and 0.9 s into each step (+ 0..20 ms): the step's pair plus uniform ±0.6 m/s per
  component as linear.x/linear.y; ``/odom`` at 10 Hz.
- ``step-start``: as ``moving``, but the four frames of a step all show the scene at the
  step's start, the two commands are sent at the step's start and half a second later
  (+ 0..20 ms), and ``/odom`` runs at 4 Hz.
- ``phone``: a phone on a differential-drive base. Steps of 0.3 s; a 256x96 JPEG camera
  at 18 Hz nominal, about 14 Hz on average as a third of its intervals are stretched up to
  3x; one ``Twist``
  per frame, logged at the frame's stamp (linear.x and angular.z carry the step's pair
  plus ±0.6 jitter); ``/odom`` at 10 Hz. ``--phone-camera runs``: a phone whose camera
  keeps a steady 64 ms (±5 %) for runs of 20 to 45 frames, each run ending in one long
  frame of 2, 2.2, 3 or 3.5 periods (intervals of 61 to 224 ms, about 14 Hz).

``--drop-frames I,J,...`` leaves those camera frames (0-based) out of the bag, as a camera
driver that drops frames would; every other message stays (test data for loss counting).

``--environment drive`` records the differential-drive robot: its 9 (speed, turn rate)
pairs as linear.x/angular.z on every timeline, the jitter scaled to the grid's spacing
(a fifth of it, as ±0.6 is of the planar grid's 3 m/s), the camera turning with the robot
(``--field-of-view``, default 300 degrees), and the heading in ``/odom``'s orientation.

Every timeline adds ``/reward`` (``sensor_msgs/msg/JointState``, the simulator's reward of
each step, stamped at the step's end), unless ``--no-reward`` leaves it out as a real
robot would (``learner policy --goal-region`` then gives rewards from ``/odom``). Images
are logged 1..3 ms after their stamp. The run starts 100 s into the bag's clock.
Everything is seeded. The bag carries no ``tpsr_ros.environment`` entry: it is a "robot"
bag, not a simulator bag.
"""

from __future__ import annotations

import argparse
import functools
import io
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim_node.camera import Camera
from sim_node.config import Environment, SimConfig
from sim_node.options import add_drive_options, add_vertical_half_extent_option
from sim_node.rollout import random_rollout
from tpsr_ros.cli import ArgumentParser, positive_int, run_cli
from tpsr_ros.core.actions import DEFAULT_TURN_RATE_DEG
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.images import LUMA
from tpsr_ros.core.units import NS_PER_S
from tpsr_ros.io.bag import BagWriter, check_bag_path_free
from tpsr_ros.io.messages import (
    REWARD_TYPE,
    TWIST_TYPE,
    RewardSample,
    header_msg,
    jazzy_typestore,
    reward_msg,
    serialize,
    twist_from_components,
)

__all__ = ["ENCODINGS", "TIMELINES", "RobotBagConfig", "main", "write_robot_bag"]

PROG = "python -m sim_node.robot_bag"
ENCODINGS = ("bgr8", "mono8", "jpeg")
TIMELINES = ("moving", "step-start", "phone")
IMAGE_TOPIC = "/front_camera/image_raw"
COMPRESSED_TOPIC = "/front_camera/image_raw/compressed"
ODOM_TYPE = "nav_msgs/msg/Odometry"
START_S = 100  # the run starts 100 s into the bag's clock
PHONE_CAMERA = (96, 256)  # (height, width)
PHONE_RATE = 18.0  # Hz nominal; about 14 Hz on average with the stretched intervals
PHONE_STEP_S = 0.3
PHONE_CAMERAS = ("stretched", "runs")
PHONE_RUNS_PERIOD_S = 0.064  # the ``runs`` phone camera's steady period
RENDER_CHUNK = 512  # frames rendered at once


@dataclass(frozen=True)
class RobotBagConfig:
    """Settings of a robot-shaped bag (see the module docstring).

    ``encoding`` None: jpeg for the ``phone`` timeline, bgr8 otherwise. ``image_size`` and
    ``camera_rate`` shape the ``moving`` and ``step-start`` cameras (the phone's is fixed).
    """

    steps: int = 300
    seed: int = 0
    encoding: str | None = None
    image_size: int = 40
    camera_rate: float = 4.0
    environment: str = "full"
    vertical_half_extent: float | None = None
    field_of_view_deg: float | None = None
    turn_rate_deg: float = DEFAULT_TURN_RATE_DEG
    command_jitter: float = 0.6
    jpeg_quality: int = 90
    command_topic: str = "/cmd_vel"
    timeline: str = "moving"
    phone_camera: str = "stretched"
    drop_frames: tuple[int, ...] = ()
    reward: bool = True

    def __post_init__(self) -> None:
        if self.timeline not in TIMELINES:
            raise ConfigError(f"timeline {self.timeline!r} is not one of {TIMELINES}")
        if self.phone_camera not in PHONE_CAMERAS:
            raise ConfigError(f"phone camera {self.phone_camera!r} is not one of {PHONE_CAMERAS}")
        if self.phone_camera != "stretched" and self.timeline != "phone":
            raise ConfigError("--phone-camera applies to the phone timeline only")
        if any(k < 0 for k in self.drop_frames):
            raise ConfigError(f"dropped frames are 0-based indices, got {list(self.drop_frames)}")
        object.__setattr__(self, "drop_frames", tuple(sorted({int(k) for k in self.drop_frames})))
        if self.encoding is None:
            object.__setattr__(self, "encoding", "jpeg" if self.timeline == "phone" else "bgr8")
        if self.encoding not in ENCODINGS:
            raise ConfigError(f"encoding {self.encoding!r} is not one of {ENCODINGS}")
        if self.steps < 3 or self.image_size < 1 or self.camera_rate not in (1.0, 2.0, 4.0, 5.0):
            raise ConfigError("steps >= 3, image_size >= 1 and camera_rate 1, 2, 4 or 5 Hz")
        self.sim_config()  # validates the environment, camera and turn rate

    def sim_config(self, image_size: int = 16) -> SimConfig:
        """The simulator the bag shows, rendering ``image_size`` pixels square."""
        return SimConfig(
            environment=self.environment,
            image_size=image_size,
            vertical_half_extent=self.vertical_half_extent,
            field_of_view_deg=self.field_of_view_deg,
            turn_rate_deg=self.turn_rate_deg,
        )

    @property
    def image_topic(self) -> str:
        """The camera topic (``.../compressed`` for jpeg)."""
        return COMPRESSED_TOPIC if self.encoding == "jpeg" else IMAGE_TOPIC

    @property
    def step_seconds(self) -> float:
        """Bag seconds per simulator step."""
        return PHONE_STEP_S if self.timeline == "phone" else 1.0


@dataclass(frozen=True)
class Timeline:
    """When everything happens, in seconds since the run's start (step ``k`` ends at
    ``k * step_seconds``), and what the camera and odometry see."""

    frame_s: np.ndarray  # (F,) frame times
    frame_poses: np.ndarray  # (F, 3) the x, y and (unwrapped) heading the frames show
    stamp_delay_ns: tuple[int, int]  # header stamp minus frame time: uniform in [lo, hi]
    command_s: np.ndarray  # (C,) when the commands are sent
    command_delay_ns: int  # their log times are up to this much later (uniform)
    command_steps: np.ndarray  # (C,) the step (1-based) each command belongs to
    components: tuple[str, str]  # the Twist components carrying the pair
    odom_s: np.ndarray


def _trail(run: Any) -> np.ndarray:
    """``(N, 3)``: the position and heading after each step, the heading unwrapped so that
    interpolating between steps turns the short way the robot turned."""
    return np.column_stack([run.positions, np.unwrap(run.headings)])


def _one_second_steps(config: RobotBagConfig, run: Any, *, at_step_start: bool) -> Timeline:
    """Steps of 1 s, frames at the camera's rate, two commands per step k = 2..N.

    ``moving``: frames from 1 s to N s show the robot where it is at the frame's time,
    commands 0.4 and 0.9 s into their step, odometry at 10 Hz. ``step-start``: the frames
    of a step (1 s to before N s) all show the scene at the step's start, commands at its
    start and half a second later, odometry at the camera's 4 Hz.
    """
    n, per_step = config.steps, round(config.camera_rate)
    frames = (n - 1) * per_step + (0 if at_step_start else 1)
    frame_s = 1.0 + np.arange(frames) / config.camera_rate
    step_k = np.repeat(np.arange(2, n + 1), 2)
    command_s = step_k - 1 + np.tile([0.0, 0.5] if at_step_start else [0.4, 0.9], n - 1)
    odom_rate = 4 if at_step_start else 10
    return Timeline(
        frame_s=frame_s,
        frame_poses=_interpolated(_trail(run), np.floor(frame_s) if at_step_start else frame_s),
        stamp_delay_ns=(5_000_000, 40_000_000),
        command_s=command_s,
        command_delay_ns=20_000_000,
        command_steps=step_k,
        components=run_components(config),
        odom_s=1.0 + np.arange((n - 1) * odom_rate + 1) / odom_rate,
    )


def _phone(config: RobotBagConfig, run: Any) -> Timeline:
    rng = np.random.default_rng(config.seed + 2)  # the camera's own clock
    step_s, n = PHONE_STEP_S, config.steps
    span = (n - 1) * step_s
    if config.phone_camera == "runs":
        intervals = _steady_runs(rng, int(span / PHONE_RUNS_PERIOD_S) + 2)
    else:
        intervals = np.full(int(span * PHONE_RATE * 1.5) + 2, 1.0 / PHONE_RATE)
        stretched = rng.random(intervals.size) < 1 / 3
        intervals[stretched] *= rng.uniform(1.0, 3.0, int(stretched.sum()))
    frame_s = step_s + np.concatenate([[0.0], np.cumsum(intervals)])
    frame_s = frame_s[frame_s <= n * step_s]
    # one command per frame, at its stamp: the pair of the step the frame falls in
    command_steps = np.minimum(n, np.floor(frame_s / step_s).astype(np.int64) + 1)
    return Timeline(
        frame_s=frame_s,
        frame_poses=_interpolated(_trail(run), frame_s / step_s),
        stamp_delay_ns=(0, 0),
        command_s=frame_s,
        command_delay_ns=0,
        command_steps=command_steps,
        components=("linear.x", "angular.z"),
        odom_s=step_s + np.arange(int(span * 10) + 1) / 10.0,
    )


def _steady_runs(rng: np.random.Generator, count: int) -> np.ndarray:
    """``count`` frame intervals (s) of the ``runs`` phone camera: 64 ms ±5 % for runs of 20
    to 45 frames, each run ending in one frame of 2, 2.2, 3 or 3.5 periods."""
    intervals = PHONE_RUNS_PERIOD_S * rng.uniform(0.95, 1.05, count)
    k = int(rng.integers(20, 46))
    while k < count:
        intervals[k] *= rng.choice([2.0, 2.2, 3.0, 3.5])
        k += int(rng.integers(21, 47))
    return intervals


def run_components(config: RobotBagConfig) -> tuple[str, str]:
    """The Twist components carrying the run's pairs on the one-second timelines: the
    simulator's own (``drive``: linear.x, angular.z; else linear.x, linear.y)."""
    first, second = config.sim_config().actions.components
    return first, second


_TIMELINES = {
    "moving": functools.partial(_one_second_steps, at_step_start=False),
    "step-start": functools.partial(_one_second_steps, at_step_start=True),
    "phone": _phone,
}


def _t(name: str) -> Any:
    return jazzy_typestore().types[name]


def _interpolated(values: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Each column at ``times`` (s, in [1, N]): step k moves from values[k-2] to values[k-1]."""
    steps = np.arange(1, values.shape[0] + 1, dtype=np.float64)
    return np.column_stack(
        [np.interp(times, steps, values[:, i]) for i in range(values.shape[1])]
    )


def _image_message(stamp: int, rgb: np.ndarray, encoding: str, quality: int) -> tuple[str, Any]:
    header = header_msg(stamp, "front_camera")
    if encoding == "jpeg":
        from PIL import Image as PILImage

        buffer = io.BytesIO()
        PILImage.fromarray(rgb).save(buffer, format="JPEG", quality=quality)
        data = np.frombuffer(buffer.getvalue(), dtype=np.uint8)
        msgtype = "sensor_msgs/msg/CompressedImage"
        return msgtype, _t(msgtype)(header=header, format="jpeg", data=data)
    if encoding == "mono8":
        pixels = np.rint(rgb.astype(np.float64) @ LUMA).astype(np.uint8)[:, :, None]
    else:
        pixels = np.ascontiguousarray(rgb[:, :, ::-1])
    height, width, channels = pixels.shape
    msgtype = "sensor_msgs/msg/Image"
    return msgtype, _t(msgtype)(
        header=header,
        height=height,
        width=width,
        encoding=encoding,
        is_bigendian=0,
        step=width * channels,
        data=pixels.reshape(-1),
    )


def _odometry(stamp: int, x: float, y: float, heading: float | None) -> Any:
    """Odometry at ``(x, y)``, turned by ``heading`` (rad about z; None: the identity)."""
    half = 0.0 if heading is None else 0.5 * float(heading)
    pose = _t("geometry_msgs/msg/Pose")(
        position=_t("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=0.0),
        orientation=_t("geometry_msgs/msg/Quaternion")(
            x=0.0, y=0.0, z=float(np.sin(half)), w=float(np.cos(half))
        ),
    )
    return _t(ODOM_TYPE)(
        header=header_msg(stamp, "odom"),
        child_frame_id="base_link",
        pose=_t("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=np.zeros(36)),
        twist=_t("geometry_msgs/msg/TwistWithCovariance")(
            twist=twist_from_components({}), covariance=np.zeros(36)
        ),
    )


def _render(config: RobotBagConfig, poses: np.ndarray) -> np.ndarray:
    """The frames ``(F, H, W, 3)`` uint8 seen from ``poses`` ``(F, 3)`` (the phone's: a
    square render widened)."""
    size = config.image_size if config.timeline != "phone" else PHONE_CAMERA[0]
    sim = config.sim_config(size)
    camera = Camera(sim)
    frames = np.concatenate(
        [
            camera.render(chunk[:, :2], headings=chunk[:, 2] if sim.drives else None)
            for chunk in np.array_split(poses, max(1, -(-len(poses) // RENDER_CHUNK)))
        ]
    )  # in chunks: the renderer's work arrays grow with frames x pixels x rays
    if config.timeline != "phone":
        return frames
    columns = np.arange(PHONE_CAMERA[1]) * size // PHONE_CAMERA[1]  # nearest source column
    return np.ascontiguousarray(frames[:, :, columns])


def _jitter_scale(config: RobotBagConfig) -> np.ndarray:
    """Each component's jitter: ``command_jitter`` per 3 units of its grid spacing (the
    planar grid's spacing is 3 m/s, so its jitter is ``command_jitter`` itself)."""
    return config.command_jitter * config.sim_config().actions.spacing() / 3.0


def write_robot_bag(output: Path | str, config: RobotBagConfig) -> int:
    """Simulate and write the bag; returns the number of messages written."""
    output = check_bag_path_free(Path(output))
    rng = np.random.default_rng(config.seed + 1)
    run = random_rollout(config.sim_config(), config.steps, config.seed)
    n = config.steps
    sec = NS_PER_S
    start = START_S * sec
    timeline = _TIMELINES[config.timeline](config, run)
    encoding = str(config.encoding)  # resolved by RobotBagConfig
    frame_s = timeline.frame_s
    images = _render(config, timeline.frame_poses)
    image_stamps = start + np.rint(frame_s * sec).astype(np.int64)
    low, high = timeline.stamp_delay_ns
    image_stamps += rng.integers(low, high + 1, size=frame_s.size)
    image_logs = image_stamps + rng.integers(1_000_000, 3_000_001, size=frame_s.size)
    # commands jittered in value and (log) time
    command_s = timeline.command_s
    command_logs = start + np.rint(command_s * sec).astype(np.int64)
    command_logs += rng.integers(0, timeline.command_delay_ns + 1, size=command_s.size)
    scale = _jitter_scale(config)
    jitter = rng.uniform(-scale, scale, size=(command_s.size, 2))
    commands = run.commands[timeline.command_steps - 1] + jitter
    odom_s = timeline.odom_s
    odom = _interpolated(_trail(run), odom_s / config.step_seconds)
    turns = config.sim_config().drives
    odom_stamps = start + np.rint(odom_s * sec).astype(np.int64)

    image_type, _ = _image_message(0, images[0], encoding, config.jpeg_quality)
    records: list[tuple[int, int, str, bytes]] = []  # (log time, order, topic, CDR)
    dropped = set(config.drop_frames)
    for i in range(frame_s.size):
        if i in dropped:
            continue
        msgtype, msg = _image_message(
            int(image_stamps[i]), images[i], encoding, config.jpeg_quality
        )
        records.append((int(image_logs[i]), 0, config.image_topic, serialize(msg, msgtype)))
    for i in range(command_s.size):
        twist = twist_from_components(dict(zip(timeline.components, commands[i], strict=True)))
        records.append(
            (int(command_logs[i]), 1, config.command_topic, serialize(twist, TWIST_TYPE))
        )
    for i in range(odom_s.size):
        x, y, heading = odom[i]
        msg = _odometry(int(odom_stamps[i]), x, y, heading if turns else None)
        records.append((int(odom_stamps[i]) + 1_000_000, 2, "/odom", serialize(msg, ODOM_TYPE)))
    for k in range(1, n + 1 if config.reward else 1):
        sample = RewardSample(
            float(run.rewards[k - 1]), bool(run.wall_contact[k - 1]), bool(run.goal_zone[k - 1])
        )
        stamp = start + round(k * config.step_seconds * sec)
        records.append(
            (stamp + 1_000_000, 3, "/reward", serialize(reward_msg(stamp, sample), REWARD_TYPE))
        )
    records.sort(key=lambda r: (r[0], r[1]))
    with BagWriter(output) as writer:
        writer.set_custom_data("tpsr_ros.robot_bag", json.dumps(_settings(config)))
        writer.add_topic(config.image_topic, image_type)
        writer.add_topic(config.command_topic, TWIST_TYPE)
        writer.add_topic("/odom", ODOM_TYPE)
        if config.reward:
            writer.add_topic("/reward", REWARD_TYPE)
        for log_time, _, topic, data in records:
            writer.write(topic, log_time, data)
        return writer.message_count


def _settings(config: RobotBagConfig) -> dict[str, Any]:
    """The config as recorded in the bag; the phone camera and dropped frames only when set
    (bags of the other settings stay byte-identical to earlier ones)."""
    settings = asdict(config)
    if settings["phone_camera"] == "stretched":
        del settings["phone_camera"]
    if not settings["drop_frames"]:
        del settings["drop_frames"]
    return settings


def _frame_list(text: str) -> tuple[int, ...]:
    """``--drop-frames``: comma-separated 0-based frame indices."""
    try:
        return tuple(int(part) for part in text.split(",") if part.strip())
    except ValueError:
        message = f"{text!r} is not a comma-separated list of frame indices"
        raise argparse.ArgumentTypeError(message) from None


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and write one robot-shaped bag."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=positive_int, default=300, help="simulator steps")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random stream")
    parser.add_argument(
        "--timeline", choices=TIMELINES, default="moving", help="when frames and commands come"
    )
    parser.add_argument(
        "--encoding",
        choices=ENCODINGS,
        default=None,
        help="camera encoding (default: jpeg for the phone, bgr8 otherwise)",
    )
    parser.add_argument("--image-size", type=positive_int, default=40, help="camera pixels")
    parser.add_argument(
        "--environment",
        choices=[e.value for e in Environment],
        default="full",
        help="the simulator recorded (drive: the robot that turns)",
    )
    parser.add_argument(
        "--phone-camera",
        choices=PHONE_CAMERAS,
        default="stretched",
        help="the phone timeline's camera: a third of its frames stretched up to 3x, or steady "
        "runs of 64 ms frames each ending in one frame of 2 to 3.5 periods",
    )
    parser.add_argument(
        "--drop-frames",
        type=_frame_list,
        default=(),
        metavar="I,J,...",
        help="camera frames (0-based) left out of the bag, as a driver dropping them",
    )
    add_vertical_half_extent_option(parser)
    add_drive_options(parser)
    parser.add_argument(
        "--no-reward",
        dest="reward",
        action="store_false",
        help="leave out /reward, as a real robot's bag has none",
    )
    parser.add_argument("-o", "--output", required=True, type=Path, help="new bag directory")
    args = parser.parse_args(argv)
    if args.seed < 0:
        parser.error(f"argument --seed: {args.seed} is negative")
    config = RobotBagConfig(
        steps=args.steps,
        seed=args.seed,
        encoding=args.encoding,
        image_size=args.image_size,
        timeline=args.timeline,
        phone_camera=args.phone_camera,
        drop_frames=args.drop_frames,
        environment=args.environment,
        vertical_half_extent=args.vertical_half_extent,
        field_of_view_deg=args.field_of_view,
        turn_rate_deg=args.turn_rate,
        reward=args.reward,
    )
    count = write_robot_bag(args.output, config)
    print(f"wrote {args.output}: {args.steps} steps, {count} messages", file=sys.stderr)
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
