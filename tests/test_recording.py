"""The recorder's ROS-free pieces: the subscription planner and the loss ledger."""

from __future__ import annotations

import json
from dataclasses import dataclass

import pytest

from tpsr_ros.core.errors import BagError
from tpsr_ros.io.qos import DEFAULT_QOS, SENSOR_DATA_QOS, QoSProfile
from tpsr_ros.io.recording import LossLedger, SubscriptionPlanner

S = 10**9


@dataclass(frozen=True)
class Publisher:
    topic: str
    msgtype: str
    qos: QoSProfile = DEFAULT_QOS


def test_the_planner_selects_adapts_and_refuses_a_type_clash() -> None:
    planner = SubscriptionPlanner(None)
    planned, warnings = planner.plan([
        Publisher("/camera", "sensor_msgs/msg/Image", SENSOR_DATA_QOS),
        Publisher("/rosout", "rcl_interfaces/msg/Log"),  # excluded by default
        Publisher("/_hidden", "std_msgs/msg/String"),
        Publisher("/odd", "no_pkg/msg/Unknown"),
    ])  # fmt: skip
    assert [p.topic for p in planned] == ["/camera"]
    assert planned[0].qos.reliability.value == "best_effort"  # it adapts to the publisher
    assert warnings == [(("/odd", "type"), "not recording /odd: unknown message type "
                                          "no_pkg/msg/Unknown")]
    again, _ = planner.plan([Publisher("/camera", "sensor_msgs/msg/Image", SENSOR_DATA_QOS)])
    assert again == []  # planned once
    with pytest.raises(BagError, match="recorded as sensor_msgs/msg/Image"):
        planner.plan([Publisher("/camera", "std_msgs/msg/String")])
    with pytest.raises(BagError, match="published as"):
        SubscriptionPlanner(None).plan(
            [Publisher("/x", "std_msgs/msg/String"), Publisher("/x", "std_msgs/msg/Header")]
        )
    named = SubscriptionPlanner({"/_hidden"})
    assert [p.topic for p in named.plan([Publisher("/_hidden", "std_msgs/msg/String")])[0]] == [
        "/_hidden"
    ]


def test_the_ledger_counts_every_kind_of_loss_per_topic() -> None:
    ledger = LossLedger()
    cadence = ledger.add_topic("/camera", stamped=True)
    assert ledger.add_topic("/cmd_vel", stamped=False) is None
    assert cadence is not None
    for k in [*range(1, 21), 23, 24]:  # two camera frames missing (21, 22)
        cadence.add(k * S // 10)
    ledger.recorded["/camera"] += 20
    ledger.dropped["/camera"] += 1
    ledger.rejected["/cmd_vel"] += 1
    assert ledger.middleware_lost({"/camera": 3}) == [
        "lost 3 messages on /camera before they reached the recorder (reported by the "
        "middleware; 3 on this topic so far)"
    ]
    assert ledger.middleware_lost({"/camera": 3}) == []  # said once
    (line,) = ledger.new_missing()
    assert line.startswith("2 messages missing on /camera by its header stamps (a 10 Hz")
    assert ledger.totals() == (20, 3, 1, 1, 2) and ledger.any_loss()
    assert "lost 3 (reported by the middleware), dropped 1 (write cache full), rejected 1; " \
        "missing 2 by header stamps" == ledger.losses()
    assert ledger.diagnostics_values()["/camera missing by stamps"] == 2
    assert json.loads(ledger.custom_data()["recorder.by_topic"])["/cmd_vel"]["rejected"] == 1
    assert ledger.index("/camera") == 21


def test_only_sensor_streams_are_judged_by_their_stamps() -> None:
    """A camera's missing frames are losses; a step the filter node skipped (a grid gap on
    /tpsr/state) or a command not sent is not."""
    from tpsr_ros.io.recording import judged_by_stamps

    for sensor in ("sensor_msgs/msg/Image", "sensor_msgs/msg/CompressedImage",
                   "nav_msgs/msg/Odometry", "sensor_msgs/msg/Imu"):  # fmt: skip
        assert judged_by_stamps(sensor)
    for derived in ("sensor_msgs/msg/JointState", "geometry_msgs/msg/TwistStamped",
                    "diagnostic_msgs/msg/DiagnosticArray", "std_msgs/msg/Header"):  # fmt: skip
        assert not judged_by_stamps(derived)
