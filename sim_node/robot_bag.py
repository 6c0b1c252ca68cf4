"""A simulated run recorded the way a real robot records it (test data for robot bags).

    python -m sim_node.robot_bag --steps 300 --seed 0 --encoding bgr8 -o robot_bag

The simulator's random run (1 s steps, the 25 velocity pairs) is re-recorded as a
researcher's robot would: a camera of its own size and rate with late, jittered stamps,
unstamped continuous velocity commands at their own rate, and odometry. Shape (defaults):

- ``/front_camera/image_raw``: ``sensor_msgs/msg/Image``, bgr8 (or mono8), 40x40, 4 Hz,
  stamped 5..40 ms after the frame time (``--encoding jpeg``: ``sensor_msgs/msg/CompressedImage``
  on ``/front_camera/image_raw/compressed``);
- ``/cmd_vel``: ``geometry_msgs/msg/Twist`` at 2 Hz, unstamped: the step's pair plus uniform
  ±0.6 m/s per component, angular.z 0;
- ``/odom``: ``nav_msgs/msg/Odometry`` at 10 Hz (position, frame ``odom``);
- ``/reward``: ``sensor_msgs/msg/JointState`` at 1 Hz, the simulator's reward of each step.

Timeline: simulator step ``k`` moves the robot during ``[k-1, k]`` s (positions are
interpolated linearly inside a step; frames and odometry render those positions); its two
commands are logged 0.4 and 0.9 s into the step (+ 0..20 ms); the camera frames fall on
quarter seconds. Images are logged 1..3 ms after their stamp. Everything is seeded.
The bag carries no ``tpsr_ros.environment`` entry: it is a "robot" bag, not a simulator bag.
"""

from __future__ import annotations

import io
import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim_node.camera import Camera
from sim_node.config import SimConfig
from sim_node.rollout import random_rollout
from tpsr_ros.cli import ArgumentParser, positive_int, run_cli
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

__all__ = ["ENCODINGS", "RobotBagConfig", "main", "write_robot_bag"]

PROG = "python -m sim_node.robot_bag"
ENCODINGS = ("bgr8", "mono8", "jpeg")
IMAGE_TOPIC = "/front_camera/image_raw"
COMPRESSED_TOPIC = "/front_camera/image_raw/compressed"
ODOM_TYPE = "nav_msgs/msg/Odometry"
START_S = 100  # the run starts 100 s into the bag's clock


@dataclass(frozen=True)
class RobotBagConfig:
    """Settings of a robot-shaped bag (see the module docstring)."""

    steps: int = 300
    seed: int = 0
    encoding: str = "bgr8"
    image_size: int = 40
    camera_rate: float = 4.0
    environment: str = "full"
    command_jitter: float = 0.6
    jpeg_quality: int = 90
    command_topic: str = "/cmd_vel"

    def __post_init__(self) -> None:
        if self.encoding not in ENCODINGS:
            raise ConfigError(f"encoding {self.encoding!r} is not one of {ENCODINGS}")
        if self.steps < 3 or self.image_size < 1 or self.camera_rate not in (1.0, 2.0, 4.0, 5.0):
            raise ConfigError("steps >= 3, image_size >= 1 and camera_rate 1, 2, 4 or 5 Hz")

    @property
    def image_topic(self) -> str:
        """The camera topic (``.../compressed`` for jpeg)."""
        return COMPRESSED_TOPIC if self.encoding == "jpeg" else IMAGE_TOPIC


def _t(name: str) -> Any:
    return jazzy_typestore().types[name]


def _interpolated(positions: np.ndarray, times: np.ndarray) -> np.ndarray:
    """Position at ``times`` (s, in [1, N]): step k moves from positions[k-2] to positions[k-1]."""
    steps = np.arange(1, positions.shape[0] + 1, dtype=np.float64)
    return np.column_stack([np.interp(times, steps, positions[:, i]) for i in range(2)])


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


def _odometry(stamp: int, x: float, y: float) -> Any:
    pose = _t("geometry_msgs/msg/Pose")(
        position=_t("geometry_msgs/msg/Point")(x=float(x), y=float(y), z=0.0),
        orientation=_t("geometry_msgs/msg/Quaternion")(x=0.0, y=0.0, z=0.0, w=1.0),
    )
    return _t(ODOM_TYPE)(
        header=header_msg(stamp, "odom"),
        child_frame_id="base_link",
        pose=_t("geometry_msgs/msg/PoseWithCovariance")(pose=pose, covariance=np.zeros(36)),
        twist=_t("geometry_msgs/msg/TwistWithCovariance")(
            twist=twist_from_components({}), covariance=np.zeros(36)
        ),
    )


def write_robot_bag(output: Path | str, config: RobotBagConfig) -> int:
    """Simulate and write the bag; returns the number of messages written."""
    output = check_bag_path_free(Path(output))
    rng = np.random.default_rng(config.seed + 1)
    run = random_rollout(SimConfig(environment=config.environment), config.steps, config.seed)
    n = config.steps
    sec = NS_PER_S
    start = START_S * sec
    # camera frames at 1/rate s from 1 s (the end of step 1) to N s
    per_step = round(config.camera_rate)
    frame_s = 1.0 + np.arange((n - 1) * per_step + 1) / config.camera_rate
    camera = Camera(SimConfig(environment=config.environment, image_size=config.image_size))
    images = camera.render(_interpolated(run.positions, frame_s))
    image_stamps = start + np.rint(frame_s * sec).astype(np.int64)
    image_stamps += rng.integers(5_000_000, 40_000_001, size=frame_s.size)
    image_logs = image_stamps + rng.integers(1_000_000, 3_000_001, size=frame_s.size)
    # two commands per step k = 2..N, 0.4 and 0.9 s into it, jittered in value and time
    step_k = np.repeat(np.arange(2, n + 1), 2)
    command_s = step_k - 1 + np.tile([0.4, 0.9], n - 1)
    command_logs = start + np.rint(command_s * sec).astype(np.int64)
    command_logs += rng.integers(0, 20_000_001, size=command_s.size)
    jitter = rng.uniform(-config.command_jitter, config.command_jitter, size=(command_s.size, 2))
    commands = run.commands[step_k - 1] + jitter
    odom_s = 1.0 + np.arange((n - 1) * 10 + 1) / 10.0
    odom_xy = _interpolated(run.positions, odom_s)
    odom_stamps = start + np.rint(odom_s * sec).astype(np.int64)

    image_type, _ = _image_message(0, images[0], config.encoding, config.jpeg_quality)
    records: list[tuple[int, int, str, bytes]] = []  # (log time, order, topic, CDR)
    for i in range(frame_s.size):
        msgtype, msg = _image_message(
            int(image_stamps[i]), images[i], config.encoding, config.jpeg_quality
        )
        records.append((int(image_logs[i]), 0, config.image_topic, serialize(msg, msgtype)))
    for i in range(command_s.size):
        twist = twist_from_components({"linear.x": commands[i, 0], "linear.y": commands[i, 1]})
        records.append(
            (int(command_logs[i]), 1, config.command_topic, serialize(twist, TWIST_TYPE))
        )
    for i in range(odom_s.size):
        msg = _odometry(int(odom_stamps[i]), *odom_xy[i])
        records.append((int(odom_stamps[i]) + 1_000_000, 2, "/odom", serialize(msg, ODOM_TYPE)))
    for k in range(1, n + 1):
        sample = RewardSample(
            float(run.rewards[k - 1]), bool(run.wall_contact[k - 1]), bool(run.goal_zone[k - 1])
        )
        stamp = start + k * sec
        records.append(
            (stamp + 1_000_000, 3, "/reward", serialize(reward_msg(stamp, sample), REWARD_TYPE))
        )
    records.sort(key=lambda r: (r[0], r[1]))
    with BagWriter(output) as writer:
        writer.set_custom_data("tpsr_ros.robot_bag", json.dumps(asdict(config)))
        writer.add_topic(config.image_topic, image_type)
        writer.add_topic(config.command_topic, TWIST_TYPE)
        writer.add_topic("/odom", ODOM_TYPE)
        writer.add_topic("/reward", REWARD_TYPE)
        for log_time, _, topic, data in records:
            writer.write(topic, log_time, data)
        return writer.message_count


def main(argv: list[str] | None = None) -> int:
    """Parse the command line and write one robot-shaped bag."""
    parser = ArgumentParser(prog=PROG, description=__doc__.split("\n")[0])
    parser.add_argument("--steps", type=positive_int, default=300, help="simulator steps (1 s)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random stream")
    parser.add_argument("--encoding", choices=ENCODINGS, default="bgr8", help="camera encoding")
    parser.add_argument("--image-size", type=positive_int, default=40, help="camera pixels")
    parser.add_argument("-o", "--output", required=True, type=Path, help="new bag directory")
    args = parser.parse_args(argv)
    if args.seed < 0:
        parser.error(f"argument --seed: {args.seed} is negative")
    config = RobotBagConfig(
        steps=args.steps, seed=args.seed, encoding=args.encoding, image_size=args.image_size
    )
    count = write_robot_bag(args.output, config)
    print(f"wrote {args.output}: {args.steps} steps, {count} messages", file=sys.stderr)
    return 0


if __name__ == "__main__":
    run_cli(PROG, main)
