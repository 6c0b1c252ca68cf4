"""What a model learned on the step grid remembers about its input streams.

Stored in the model metadata under ``"input"`` (:mod:`tpsr_ros.io.model_io`); read by
:mod:`tpsr_ros.io.streams` (bags) and the filter node (live streams). Kept apart from the
bag reader so that loading a model needs no bag library.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from tpsr_ros.core.codebook import ActionCodebook
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.images import Preprocessing
from tpsr_ros.core.resample import GridConfig
from tpsr_ros.io.images import IMAGE_TYPES

__all__ = ["COMMAND_TYPES", "TWIST_STAMPED_TYPE", "TWIST_TYPE", "StreamSpec"]

TWIST_TYPE = "geometry_msgs/msg/Twist"
TWIST_STAMPED_TYPE = "geometry_msgs/msg/TwistStamped"
COMMAND_TYPES = (TWIST_TYPE, TWIST_STAMPED_TYPE)


@dataclass(frozen=True)
class StreamSpec:
    """The inputs of a model learned on the step grid (see the module docstring)."""

    image_topic: str
    image_type: str
    action_topic: str
    action_type: str
    preprocessing: Preprocessing
    codebook: ActionCodebook
    grid: GridConfig

    def __post_init__(self) -> None:
        if self.image_type not in IMAGE_TYPES:
            raise ConfigError(f"camera type {self.image_type} is not one of {IMAGE_TYPES}")
        if self.action_type not in COMMAND_TYPES:
            raise ConfigError(f"command type {self.action_type} is not one of {COMMAND_TYPES}")

    def as_dict(self) -> dict[str, Any]:
        """JSON form (model metadata ``"input"``)."""
        return {
            "sampling": "grid",
            "image": {
                "topic": self.image_topic,
                "type": self.image_type,
                **self.preprocessing.as_dict(),
            },
            "action": {"topic": self.action_topic, "type": self.action_type},
            "codebook": self.codebook.as_dict(),
            "grid": self.grid.as_dict(),
        }

    @classmethod
    def from_dict(cls, data: Any) -> StreamSpec:
        """Inverse of :meth:`as_dict`; malformed entries raise ``ConfigError``."""
        if not isinstance(data, dict) or data.get("sampling") != "grid":
            raise ConfigError("the input entry is not a step-grid description")
        image, action = data.get("image"), data.get("action")
        if not isinstance(image, dict) or not isinstance(action, dict):
            raise ConfigError("the input entry lacks its image or action description")
        for key, entry in (("image", image), ("action", action)):
            for name in ("topic", "type"):
                if not isinstance(entry.get(name), str) or not 0 < len(entry[name]) < 256:
                    raise ConfigError(f"the input {key} {name} is not a name")
        return cls(
            image_topic=image["topic"],
            image_type=image["type"],
            action_topic=action["topic"],
            action_type=action["type"],
            preprocessing=Preprocessing(
                image.get("height"), image.get("width"), image.get("grey", False)
            ),
            codebook=ActionCodebook.from_dict(data.get("codebook")),
            grid=GridConfig.from_dict(data.get("grid")),
        )
