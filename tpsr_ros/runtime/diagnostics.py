"""``diagnostic_msgs/msg/DiagnosticArray`` messages and the statistics nodes report in them.

ROS 2 nodes report their health on ``/diagnostics`` (robot_localization, drivers, the
``diagnostic_updater`` library): an array of ``DiagnosticStatus`` entries, each with a
level (OK, WARN, ERROR, STALE), a name (``"<node>: <task>"``), a one-line message, a
hardware id and string key-value pairs. ``rqt_robot_monitor``, ``ros2 topic echo
/diagnostics`` and the diagnostic aggregator read them. The layouts come from the rosbags
Jazzy typestore like every other message (:mod:`tpsr_ros.io.messages`).

:class:`RollingPercentiles` keeps the last N samples of a quantity (e.g. processing
latency) for p50/p99 reports.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from tpsr_ros.io.messages import header_msg, jazzy_typestore

__all__ = [
    "DIAGNOSTICS_TYPE",
    "ERROR",
    "LEVEL_NAMES",
    "OK",
    "STALE",
    "WARN",
    "RollingPercentiles",
    "diagnostic_array",
    "diagnostic_status",
    "status_values",
]

DIAGNOSTICS_TYPE = "diagnostic_msgs/msg/DiagnosticArray"
OK, WARN, ERROR, STALE = 0, 1, 2, 3
LEVEL_NAMES = {OK: "OK", WARN: "WARN", ERROR: "ERROR", STALE: "STALE"}


def _t(name: str) -> Any:
    return jazzy_typestore().types[name]


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:.6g}"
    return str(value)


def diagnostic_status(
    level: int,
    name: str,
    message: str,
    values: Mapping[str, Any],
    hardware_id: str = "",
) -> Any:
    """One ``DiagnosticStatus``; values are written as text (floats with 6 significant digits)."""
    if level not in LEVEL_NAMES:
        raise ValueError(f"diagnostic level {level} is not one of {sorted(LEVEL_NAMES)}")
    key_value = _t("diagnostic_msgs/msg/KeyValue")
    return _t("diagnostic_msgs/msg/DiagnosticStatus")(
        level=int(level),
        name=name,
        message=message,
        hardware_id=hardware_id,
        values=[key_value(key=str(k), value=_text(v)) for k, v in values.items()],
    )


def diagnostic_array(stamp_ns: int, statuses: list[Any]) -> Any:
    """``DiagnosticArray`` stamped ``stamp_ns`` holding ``statuses``."""
    return _t(DIAGNOSTICS_TYPE)(header=header_msg(stamp_ns, ""), status=list(statuses))


def status_values(status: Any) -> dict[str, str]:
    """Key-value pairs of a ``DiagnosticStatus`` as a dict."""
    return {kv.key: kv.value for kv in status.values}


class RollingPercentiles:
    """The last ``size`` samples of a quantity, with percentiles over them.

    Samples are float64 in one numpy buffer (8 bytes each, where a deque of Python floats
    takes about 32) that grows up to ``size`` and then wraps, so a large ``size`` (the
    player keeps every message's lateness) costs only what is used.
    """

    def __init__(self, size: int = 1000) -> None:
        self._size = max(int(size), 0)
        self._buffer = np.empty(min(self._size, 1024))
        self._added = 0  # samples ever added

    def add(self, value: float) -> None:
        """Record one sample (the oldest is forgotten once there are ``size``)."""
        if not self._size:
            return
        index = self._added % self._size
        if index == len(self._buffer):  # still filling: grow, doubling up to size
            grown = np.empty(min(2 * len(self._buffer), self._size))
            grown[:index] = self._buffer
            self._buffer = grown
        self._buffer[index] = float(value)
        self._added += 1

    def __len__(self) -> int:
        return min(self._added, self._size)

    def percentiles(self, *qs: float) -> tuple[float, ...]:
        """Percentiles ``qs`` (0-100) of the samples; NaN each when there are none."""
        if not len(self):
            return tuple(float("nan") for _ in qs)
        return tuple(float(v) for v in np.percentile(self._buffer[: len(self)], qs))
