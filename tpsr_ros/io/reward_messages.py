"""Reward messages a robot can publish, and reading one value and its time from each.

Four stock types carry a reward (``learner policy --reward-topic``):

- ``std_msgs/msg/Float32``, ``std_msgs/msg/Float64``: ``data`` is the reward;
- ``std_msgs/msg/Bool``: 1.0 when ``data`` is true, else 0 (a "goal reached" flag);
- ``sensor_msgs/msg/JointState`` as the simulator writes ``/reward``
  (:func:`~tpsr_ros.io.messages.reward_msg`): the first ``name`` is ``reward``, its value
  the first ``position``.

The std_msgs types carry no header: their time is the bag's log time (when the recorder
received them), so publish them when the reward is earned. A ``JointState``'s time is its
header stamp (the log time where the stamp is zero). Every value must be finite.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from tpsr_ros.core.errors import MessageError
from tpsr_ros.io.messages import REWARD_TYPE, deserialize, header_msg, jazzy_typestore, stamp_of

__all__ = [
    "BOOL_TYPE",
    "FLOAT32_TYPE",
    "FLOAT64_TYPE",
    "REWARD_TYPES",
    "decode_reward",
    "reward_message",
    "reward_value",
]

FLOAT32_TYPE = "std_msgs/msg/Float32"
FLOAT64_TYPE = "std_msgs/msg/Float64"
BOOL_TYPE = "std_msgs/msg/Bool"
REWARD_TYPES = (FLOAT32_TYPE, FLOAT64_TYPE, BOOL_TYPE, REWARD_TYPE)
"""The message types a reward topic may carry."""


def reward_value(msg: Any, msgtype: str) -> float:
    """The reward a message of ``msgtype`` carries (module docstring); bad content raises
    ``MessageError``."""
    if msgtype == BOOL_TYPE:
        if not isinstance(msg.data, bool):
            raise MessageError(f"a Bool reward's data is {msg.data!r}, not true or false")
        return 1.0 if msg.data else 0.0
    if msgtype in (FLOAT32_TYPE, FLOAT64_TYPE):
        value = float(msg.data)
    elif msgtype == REWARD_TYPE:
        if tuple(msg.name[:1]) != ("reward",) or len(msg.position) < 1:
            raise MessageError(
                f"a JointState reward names 'reward' first with its value in position (names "
                f"{list(msg.name)[:3]}, {len(msg.position)} positions)"
            )
        value = float(msg.position[0])
    else:
        raise MessageError(f"{msgtype} is not a reward type ({', '.join(REWARD_TYPES)})")
    if not math.isfinite(value):
        raise MessageError(f"the reward {value} is not finite")
    return value


def decode_reward(data: bytes | memoryview, msgtype: str, log_time_ns: int) -> tuple[int, float]:
    """``(time ns, reward)`` of one serialised message: the header stamp of a ``JointState``
    (the log time where it is zero), the log time of the unstamped std_msgs types."""
    if msgtype == BOOL_TYPE and len(data) >= 5 and data[4] not in (0, 1):
        raise MessageError(f"a Bool reward's byte is {data[4]}, not 0 (false) or 1 (true)")
    msg = deserialize(data, msgtype)
    value = reward_value(msg, msgtype)
    if msgtype == REWARD_TYPE:
        stamp = stamp_of(msg)
        return (stamp if stamp > 0 else int(log_time_ns)), value
    return int(log_time_ns), value


def reward_message(msgtype: str, value: float, stamp_ns: int = 0) -> Any:
    """A message of ``msgtype`` carrying ``value`` (a Bool: ``value != 0``); a ``JointState``
    is stamped ``stamp_ns`` and named ``reward``."""
    types = jazzy_typestore().types
    if msgtype == BOOL_TYPE:
        return types[msgtype](data=bool(value))
    if msgtype in (FLOAT32_TYPE, FLOAT64_TYPE):
        return types[msgtype](data=float(value))
    if msgtype == REWARD_TYPE:
        empty = np.zeros(0, dtype=np.float64)
        return types[msgtype](
            header=header_msg(stamp_ns, "map"),
            name=["reward"],
            position=np.array([float(value)]),
            velocity=empty,
            effort=empty,
        )
    raise MessageError(f"{msgtype} is not a reward type ({', '.join(REWARD_TYPES)})")
