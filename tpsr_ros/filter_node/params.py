"""Parameters and topic names of the filter node (``python -m tpsr_ros.filter_node``).

Topic names are relative, so ``-r __ns:=/robot1`` moves every topic of a robot's filter under
``/robot1/`` (next to its simulator's); ``/diagnostics`` stays global, as diagnostic
aggregators expect (each status names its node).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.online import SWAP_STATES
from tpsr_ros.io import messages as m
from tpsr_ros.io.stream_spec import TWIST_STAMPED_TYPE
from tpsr_ros.runtime import param

__all__ = [
    "ACTION_TOPIC",
    "CLOCK_TOPIC",
    "CMD_VEL_TOPIC",
    "COMMAND_TYPES",
    "DIAGNOSTICS_TOPIC",
    "IMAGE_TOPIC",
    "MODEL_INFO_TOPIC",
    "MODEL_UPDATE_TOPIC",
    "RESET_TOPIC",
    "STATE_TOPIC",
    "FilterNodeParams",
]

IMAGE_TOPIC = "camera/image_raw"
ACTION_TOPIC = "action"
RESET_TOPIC = "sim/episode_start"
CLOCK_TOPIC = "clock"
STATE_TOPIC = "tpsr/state"
CMD_VEL_TOPIC = "cmd_vel"
DIAGNOSTICS_TOPIC = "/diagnostics"
MODEL_UPDATE_TOPIC = "tpsr/model_update"
MODEL_INFO_TOPIC = "tpsr/model_info"
COMMAND_TYPES = {"twist": m.TWIST_TYPE, "twist_stamped": TWIST_STAMPED_TYPE}


@dataclass(frozen=True)
class FilterNodeParams:
    """Parameters of ``python -m tpsr_ros.filter_node``."""

    model: str = param(
        "", "model file (.npz) written by `learner fit` (required unless wait_for_model)"
    )
    policy: str = param(
        "", "policy file written by `learner policy` for this model; empty: a pure filter"
    )
    queue_size: int = param(
        10,
        "incomplete steps (image or action alone) buffered for pairing; the oldest go first",
        minimum=1,
    )
    step_period: float = param(
        1.0,
        "s between consecutive steps; a step not one period after the last starts from b_*",
        positive=True,
    )
    jump_threshold: float = param(
        5.0,
        "s; a stamp earlier than the last step by more than this is a backwards time jump",
        minimum=0.0,
    )
    image_frame: str = param("camera", "required frame_id of images (empty: any)")
    action_frame: str = param("base_link", "required frame_id of actions (empty: any)")
    sensor_qos: str = param(
        "reliable",
        "reliability of the image and action subscriptions (best_effort also matches "
        "sensor-data publishers)",
        choices=("reliable", "best_effort"),
    )
    check_topics: bool = param(
        True, "refuse a model trained on other image/action topics than the node subscribes"
    )
    wait_for_subscribers: int = param(
        0,
        "hold the first command until /cmd_vel and /tpsr/state each have this many subscriptions",
        minimum=0,
    )
    diagnostics_period: float = param(1.0, "s between /diagnostics reports", positive=True)
    command_type: str = param(
        "twist",
        "type of the /cmd_vel commands: twist (geometry_msgs/Twist) or twist_stamped",
        choices=tuple(COMMAND_TYPES),
    )
    input_timeout: float = param(
        3.0,
        "s; an input silent for longer makes /diagnostics WARN, all inputs silent STALE",
        positive=True,
    )
    far_commands_warn: float = param(
        0.5,
        "fraction (step-grid models); far command messages (farther from every action than "
        "half the codes' spacing, normal for continuous teleoperation) are counted, and make "
        "/diagnostics WARN only when more than this fraction of the command messages since "
        "the last judged report were far, judged over at least 20 of them",
        minimum=0.0,
        maximum=1.0,
    )
    max_latency: float = param(
        1.0,
        "s (step-grid models); a step closes once both inputs passed its time, or once one "
        "input is this far past it (the other late or silent); both silent this long: the "
        "steps before the newest image close",
        positive=True,
    )
    lockstep: bool = param(
        False,
        "step-grid models with a policy: the robot takes one step per command and answers it "
        "with one image (sim_node in command mode); each image is the step at the first grid "
        "time at or after its stamp, with the node's last command as its action (the command "
        "input is not read)",
    )
    view: bool = param(
        True,
        "publish what the state means for a person: tpsr/predicted_image, tpsr/state_markers "
        "and (models fitted with a pose) tpsr/decoded_pose, for Foxglove and RViz (models "
        "without the viewer's read-outs publish none)",
    )
    view_trail: int = param(100, "states in the tpsr/state_markers trail", minimum=1)
    swap_state: str = param(
        "replay",
        "the state after a model swap: replay (the new model re-filters the last "
        "swap_replay_steps steps) or restart (b_*)",
        choices=SWAP_STATES,
    )
    swap_replay_steps: int = param(
        20, "steps kept for re-filtering at a model swap (swap_state replay)", minimum=1
    )
    wait_for_model: bool = param(
        False,
        "with no model given, wait for the first one announced on tpsr/model_update (the "
        "learner node's) and start with it and its policy",
    )

    def __post_init__(self) -> None:
        if self.queue_size < 1:
            raise ConfigError(f"queue_size must be >= 1, got {self.queue_size}")
        for name in ("step_period", "diagnostics_period", "input_timeout", "max_latency"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ConfigError(f"{name} must be a positive number of seconds, got {value}")
        if not (math.isfinite(self.far_commands_warn) and 0 <= self.far_commands_warn <= 1):
            raise ConfigError(f"far_commands_warn must be in [0, 1], got {self.far_commands_warn}")
        if not (math.isfinite(self.jump_threshold) and self.jump_threshold >= 0):
            raise ConfigError(f"jump_threshold must be >= 0 s, got {self.jump_threshold}")
        if self.wait_for_subscribers < 0:
            raise ConfigError("wait_for_subscribers must be >= 0")
        if self.swap_replay_steps < 1:
            raise ConfigError(f"swap_replay_steps must be >= 1, got {self.swap_replay_steps}")
        if self.view_trail < 1:
            raise ConfigError(f"view_trail must be >= 1, got {self.view_trail}")
