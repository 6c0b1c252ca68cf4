"""CDR bytes of a whole chunk of simulator steps at once, for the bag generator.

Building five message objects per step and serialising each with rosbags costs about 200 us
a step, most of the generator's time. Yet the messages of one topic differ from step to step
only in fixed-size fields at fixed places: the stamp, the image pixels, the commanded
velocity, the position, the reward values. So each topic's message is serialised once by
rosbags as a template, with sentinel values that locate those fields in its bytes, and a
chunk's payloads are that template repeated with the fields written by numpy (in ``drive``
also the orientation's z and w, which carry the heading). ``tests/test_generate.py`` checks
the bytes against rosbags message by message.
"""

from __future__ import annotations

import numpy as np

from sim_node.config import SimConfig
from sim_node.rollout import Rollout
from sim_node.topics import SimTopics, step_messages
from tpsr_ros.core.errors import MessageError
from tpsr_ros.io import messages as m

__all__ = ["chunk_payloads"]

_SENTINELS = (1234.5678125, -8765.4321875, 4242.4242)
_HEADING_SENTINEL = 1.2345678  # its half-angle's sine and cosine locate the quaternion
_STAMP = slice(4, 12)  # after the encapsulation header: Time{int32 sec, uint32 nanosec}


def _offsets(template: bytes, values: tuple[float, ...]) -> list[int]:
    """Byte offsets of the float64 ``values`` in ``template`` (each must occur once)."""
    found = []
    for value in values:
        pattern = np.float64(value).tobytes()
        offset = template.find(pattern)
        if offset < 0 or template.find(pattern, offset + 1) >= 0:
            raise AssertionError(f"sentinel {value} not unique in the CDR template")
        found.append(offset)
    return found


def _put_float64(rows: np.ndarray, offset: int, values: np.ndarray) -> None:
    rows[:, offset : offset + 8] = np.asarray(values, "<f8").reshape(-1, 1).view(np.uint8)


def chunk_payloads(
    topics: SimTopics, part: Rollout, config: SimConfig | None = None
) -> dict[str, list[bytes]]:
    """Per topic, the CDR payload of every step of ``part`` (in step order) of a run of
    ``config``'s simulator (default: a planar one)."""
    drives = config is not None and config.drives
    components = config.actions.components if config is not None else ("linear.x", "linear.y")
    n = len(part)
    sec, nanosec = np.divmod(np.asarray(part.stamps_ns, dtype=np.int64), 1_000_000_000)
    if sec.min() < 0 or sec.max() >= 2**31:
        raise MessageError("stamps outside the range of a ROS time")
    stamp = np.empty((n, 8), dtype=np.uint8)
    stamp[:, :4] = sec.astype("<i4").reshape(-1, 1).view(np.uint8)
    stamp[:, 4:] = nanosec.astype("<u4").reshape(-1, 1).view(np.uint8)
    sentinel = m.RewardSample(_SENTINELS[0], False, False)
    templates = step_messages(
        topics,
        0,
        np.zeros_like(part.images[0]),
        np.array(_SENTINELS[:2]),
        np.array(_SENTINELS[:2]),
        sentinel,
        components=components,
        heading=_HEADING_SENTINEL if drives else None,
    )
    half = 0.5 * _HEADING_SENTINEL
    quaternion = (float(np.sin(half)), float(np.cos(half)))
    payloads: dict[str, list[bytes]] = {}
    for topic, msgtype, msg in templates:
        template = m.serialize(msg, msgtype)
        rows = np.tile(np.frombuffer(template, dtype=np.uint8), (n, 1))
        rows[:, _STAMP] = stamp
        if msgtype == m.IMAGE_TYPE:
            pixels = part.images.reshape(n, -1)
            rows[:, len(template) - pixels.shape[1] :] = pixels
        elif msgtype in (m.ACTION_TYPE, m.POSE_TYPE):
            values = part.commands if msgtype == m.ACTION_TYPE else part.positions
            for column, offset in enumerate(_offsets(template, _SENTINELS[:2])):
                _put_float64(rows, offset, values[:, column])
            if msgtype == m.POSE_TYPE and drives:
                z, w = _offsets(template, quaternion)
                _put_float64(rows, z, np.sin(0.5 * part.headings))
                _put_float64(rows, w, np.cos(0.5 * part.headings))
        elif msgtype == m.REWARD_TYPE:
            (offset,) = _offsets(template, _SENTINELS[:1])
            _put_float64(rows, offset, part.rewards)
            _put_float64(rows, offset + 8, part.wall_contact.astype(np.float64))
            _put_float64(rows, offset + 16, part.goal_zone.astype(np.float64))
        payloads[topic] = [row.tobytes() for row in rows]
    return payloads
