"""The simulator as a ROS 2 node: boilerplate around ``RobotEnv`` (see msgs_doc/sim_node.md).

Time: simulation time advances 1 s per event and never jumps back. Start-up performs a
reset at t_0 (random start from the seed); every step and every later reset takes the
next stamp, so after a step at t_k a reset happens at t_{k+1} and the next step is
t_{k+2}. A step publishes exactly ``sim_node.topics.step_messages`` (image, action,
ground truth, reward, clock), all stamped t_k; a reset publishes ``/sim/episode_start``
(latched) and ``/clock``, and no image or action, so images and actions stay paired 1:1.

Modes: ``explore`` takes a uniformly random action every 1/rate s (until ``steps`` steps, if
set); ``command`` takes one step per ``/cmd_vel`` Twist, snapped to the nearest of the
environment's actions (``linear.x``, ``linear.y``; ``drive``: ``linear.x``, ``angular.z``),
and with ``episode_steps`` N > 0 ignores further commands once N steps were taken since the
last reset (a controller answering the last step of an episode in lockstep then takes no
extra step). ``/sim/reset`` (PoseStamped, frame ``map``) restarts at a position (``drive``:
and the orientation's heading). Every ignored command is announced on ``sim/cmd_ignored`` (a
Header stamped with the last event's time, ``frame_id`` the reason), so a driver can tell
through the graph that a command was consumed without a step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from sim_node.config import (
    DEFAULT_COMMAND_TOLERANCE,
    MAX_VERTICAL_HALF_EXTENT,
    Environment,
    SimConfig,
    check_vertical_half_extent,
)
from sim_node.env import RobotEnv
from sim_node.topics import CMD_IGNORED_TOPIC, SimTopics, step_messages
from tpsr_ros.core.actions import PLANAR
from tpsr_ros.core.errors import ConfigError, MessageError
from tpsr_ros.core.units import NS_PER_S as _NS
from tpsr_ros.io import messages as m
from tpsr_ros.runtime import LATCHED_QOS, Node, param

__all__ = ["CMD_IGNORED_TOPIC", "EPISODE_START_TOPIC", "RESET_TOPIC", "SimNode", "SimNodeParams"]

# Relative names (the step topics too, see SimTopics.relative): `-r __ns:=/robot1` puts
# every topic of the node under /robot1/, so robots run side by side.
RESET_TOPIC = "sim/reset"
EPISODE_START_TOPIC = "sim/episode_start"
CMD_VEL_TOPIC = "cmd_vel"
IGNORED_REASONS = ("explore_mode", "not_started", "episode_steps")
"""``frame_id`` of a ``sim/cmd_ignored`` Header: why the command took no step."""


@dataclass(frozen=True)
class SimNodeParams:
    """Parameters of ``python -m sim_node``."""

    environment: str = param(
        "full",
        "camera of the guide's chapter 4: full (300 deg), partial (60 deg) or distractors; "
        "partial-strip: partial's with a vertical extent that hides the walls' distance; "
        "drive: a differential-drive robot whose 300 deg camera turns with it",
        choices=tuple(e.value for e in Environment),
    )
    vertical_half_extent: float = param(
        0.0,
        "camera: tangent of the half vertical field of view; 0: the environment's (0.2, "
        "±11.3°: a wall farther than 10 m shows its top and the floor; partial-strip 0.1)",
        minimum=0.0,
        maximum=MAX_VERTICAL_HALF_EXTENT,
    )
    image_size: int = param(
        16,
        "camera: pixels on each side of /camera/image_raw (16: the guide's; a robot model's "
        "camera may be larger)",
        minimum=1,
        maximum=1024,
    )
    seed: int = param(
        0, "seed of every random stream (start, actions, noise, distractors)", minimum=0
    )
    mode: str = param(
        "explore",
        "explore: a uniformly random action every 1/rate s; command: one step per /cmd_vel",
        choices=("explore", "command"),
    )
    rate: float = param(10.0, "explore mode: steps per second of wall-clock time", positive=True)
    steps: int = param(
        0, "explore mode: stop stepping after this many steps (0 = never)", minimum=0
    )
    wait_for_subscribers: int = param(
        0,
        "before the first reset, wait until every published topic has this many subscriptions",
        minimum=0,
    )
    command_tolerance: float = param(
        DEFAULT_COMMAND_TOLERANCE,
        "command mode: reject a /cmd_vel component farther than this (m/s) from 0, ±3, ±6 "
        "(drive: as far relative to the spacing of its speeds, 1.5 m/s, and turn rates, 45°)",
        positive=True,
    )
    episode_steps: int = param(
        0,
        "command mode: ignore /cmd_vel after this many steps since the last reset (0 = never)",
        minimum=0,
    )

    def __post_init__(self) -> None:
        if self.seed < 0:
            raise ConfigError(f"seed must be >= 0, got {self.seed}")
        if self.vertical_half_extent != 0:
            check_vertical_half_extent(self.vertical_half_extent)
        if not (math.isfinite(self.rate) and self.rate > 0):
            raise ConfigError(f"rate must be a positive number of Hz, got {self.rate}")
        if self.steps < 0 or self.wait_for_subscribers < 0 or self.episode_steps < 0:
            raise ConfigError("steps, wait_for_subscribers and episode_steps must be >= 0")
        if not (math.isfinite(self.command_tolerance) and self.command_tolerance > 0):
            raise ConfigError(f"command_tolerance must be > 0, got {self.command_tolerance}")


class SimNode(Node):
    """Publishes each simulator step's messages; executes /cmd_vel or random actions."""

    default_name = "sim_node"
    Params = SimNodeParams
    description = "The simulated robot (guide section 4.1) as a ROS 2 node."

    def setup(self) -> None:
        """Create the environment, publishers, subscriptions and the explore timer."""
        p: SimNodeParams = self.params
        self.config = SimConfig(
            environment=p.environment,
            vertical_half_extent=p.vertical_half_extent or None,
            image_size=p.image_size,
        )
        self.env = RobotEnv(self.config, seed=p.seed)
        grid = self.config.actions
        self._command_limits = tuple(p.command_tolerance * grid.spacing() / PLANAR.spacing())
        self.topics = SimTopics().relative()
        self.step_publishers = {
            name: self.create_publisher(name, msgtype)
            for name, msgtype in self.topics.types().items()
        }
        self.episode_publisher = self.create_publisher(
            EPISODE_START_TOPIC, m.POSE_TYPE, LATCHED_QOS
        )
        self.ignored_publisher = self.create_publisher(CMD_IGNORED_TOPIC, m.HEADER_TYPE)
        self.create_subscription(RESET_TOPIC, m.POSE_TYPE, self.on_reset)
        self.create_subscription(CMD_VEL_TOPIC, m.TWIST_TYPE, self.on_cmd_vel)
        self._warned_explore = False
        self.steps_published = 0
        self.resets = 0
        self.episode_step_count = 0
        self.ignored_commands = 0
        self._time_index = -1
        self.started = False
        self._explore_done = False
        if p.wait_for_subscribers:
            self.logger.info(
                f"waiting for {p.wait_for_subscribers} subscription(s) on every published topic"
            )
            self._wait_timer = self.create_timer(0.01, self._check_subscribers)
        else:
            self._begin()
        self._explore_timer = None
        if p.mode == "explore":
            self._explore_timer = self.create_timer(1.0 / p.rate, self._explore_tick)

    def on_parameter_change(self, name: str, value: Any) -> str | None:
        """``ros2 param set /sim_node rate R``: explore at the new rate from now on; every
        other parameter is fixed at start-up."""
        if name != "rate":
            return super().on_parameter_change(name, value)
        if self._explore_timer is not None:
            self._explore_timer.cancel()
            self._explore_timer = self.create_timer(1.0 / float(value), self._explore_tick)
        self.logger.info(f"rate set to {value} steps per second")
        return None

    # -- time ------------------------------------------------------------------------

    @property
    def last_stamp_ns(self) -> int | None:
        """Stamp of the last step or reset (None before the first reset)."""
        if self._time_index < 0:
            return None
        return self.config.start_time_ns + self._time_index * _NS

    def _next_stamp(self) -> int:
        self._time_index += 1
        return self.config.start_time_ns + self._time_index * _NS

    # -- events ----------------------------------------------------------------------

    def _check_subscribers(self) -> None:
        needed = self.params.wait_for_subscribers
        publishers = [*self.step_publishers.values(), self.episode_publisher]
        if all(p.get_subscription_count() >= needed for p in publishers):
            self._wait_timer.cancel()
            self._begin()

    def _begin(self) -> None:
        self.started = True
        self.reset(None)

    def reset(self, position: tuple[float, float] | None, heading: float | None = None) -> None:
        """Reset at the next stamp; publish /sim/episode_start and /clock."""
        options: dict[str, Any] = {} if position is None else {"position": position}
        if heading is not None:
            options["heading"] = heading
        self.env.reset(options=options)
        stamp = self._next_stamp()
        x, y = (float(v) for v in self.env.position)
        heading = self.env.heading if self.config.drives else None
        self.episode_publisher.publish(m.pose_msg(stamp, x, y, heading=heading))
        self.step_publishers[self.topics.clock].publish(m.clock_msg(stamp))
        self.resets += 1
        self.episode_step_count = 0
        self.logger.info(f"episode starts at ({x:.2f}, {y:.2f}), t = {stamp / _NS:.0f} s")

    def step(self, action: int) -> None:
        """Execute ``action`` at the next stamp and publish that step's messages."""
        image, reward, _, _, info = self.env.step(action)
        stamp = self._next_stamp()
        sample = m.RewardSample(reward, info["wall_contact"], info["goal_zone"])
        for topic, _, msg in step_messages(
            self.topics,
            stamp,
            image,
            info["command"],
            info["position"],
            sample,
            components=self.config.actions.components,
            heading=info["heading"] if self.config.drives else None,
        ):
            self.step_publishers[topic].publish(msg)
        self.steps_published += 1
        self.episode_step_count += 1

    def _explore_tick(self) -> None:
        if not self.started or self._explore_done:
            return
        self.step(self.env.sample_action())
        if self.params.steps and self.steps_published >= self.params.steps:
            self._explore_done = True
            self.logger.info(f"explore finished: {self.steps_published} steps published")

    def on_cmd_vel(self, msg: Any) -> None:
        """Command mode: one step per Twist, snapped to the nearest action."""
        if self.params.mode != "command":
            if not self._warned_explore:
                self._warned_explore = True
                self.logger.warning("/cmd_vel ignored in explore mode (use -p mode:=command)")
            self._announce_ignored("explore_mode")
            return
        if not self.started:
            self.logger.warning("/cmd_vel ignored: waiting for subscribers before the start")
            self._announce_ignored("not_started")
            return
        limit = self.params.episode_steps
        if limit and self.episode_step_count >= limit:
            self.ignored_commands += 1
            self.logger.debug(
                f"/cmd_vel ignored: episode_steps ({limit}) reached since the last reset "
                f"({self.ignored_commands} ignored in all)"
            )
            self._announce_ignored("episode_steps")
            return
        try:
            grid = self.config.actions
            command = m.twist_components(msg, grid.components)
            action = int(grid.indices(command, self._command_limits)[0])
        except (MessageError, ConfigError) as exc:
            self.logger.warning(f"/cmd_vel rejected: {exc}")
            return
        self.step(action)

    def _announce_ignored(self, reason: str) -> None:
        """Publish ``/sim/cmd_ignored``: a Header at the last event's stamp naming ``reason``."""
        stamp = self.last_stamp_ns
        self.ignored_publisher.publish(m.header_msg(0 if stamp is None else stamp, reason))

    def on_reset(self, msg: Any) -> None:
        """Reset to the PoseStamped position (frame ``map``, inside the room); ``drive``
        also turns to its orientation's heading."""
        if msg.header.frame_id != "map":
            self.logger.warning(f"reset rejected: frame {msg.header.frame_id!r} is not 'map'")
            return
        x, y = m.pose_to_xy(msg)
        cos_h, sin_h = m.quaternion_heading(msg.pose.orientation)
        heading = math.atan2(sin_h, cos_h) if self.config.drives else None
        low = self.config.robot_radius
        high = self.config.room_size - self.config.robot_radius
        if not (math.isfinite(x) and math.isfinite(y) and low <= x <= high and low <= y <= high):
            self.logger.warning(
                f"reset rejected: ({x}, {y}) is outside the room [{low:g}, {high:g}]^2"
            )
            return
        if not self.started:
            self.logger.warning("reset ignored: waiting for subscribers before the start")
            return
        self.reset((x, y), heading)

    def on_shutdown(self) -> None:
        """Log what was published."""
        last = self.last_stamp_ns
        until = "" if last is None else f", last stamp t = {last / _NS:.0f} s"
        ignored = (
            f"; {self.ignored_commands} /cmd_vel ignored after episode_steps"
            if self.ignored_commands
            else ""
        )
        self.logger.info(
            f"published {self.steps_published} steps and {self.resets} resets{until}{ignored}"
        )
