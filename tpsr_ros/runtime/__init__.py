"""Node runtime: one node API over rclpy, Cyclone DDS (ROS 2 conventions) or an in-process bus.

Nodes subclass :class:`Node` and start with :func:`run_node`; parameters are frozen
dataclass fields declared with :func:`param`; ``TPSR_TRANSPORT=rclpy|dds|inproc`` picks
the middleware (default: rclpy if importable, else dds). See ``msgs_doc/README.md``.
:class:`Launch` starts node processes, waits on the graph and stops them
(:mod:`tpsr_ros.runtime.launcher`).
"""

from tpsr_ros.io.qos import (
    DEFAULT_QOS,
    LATCHED_QOS,
    SENSOR_DATA_QOS,
    Durability,
    History,
    QoSProfile,
    Reliability,
)
from tpsr_ros.runtime.entry import parse_node_args, run_node
from tpsr_ros.runtime.launcher import Launch, LaunchError, NodeProcess
from tpsr_ros.runtime.node import (
    EndpointInfo,
    Logger,
    Node,
    NodeOptions,
    Publisher,
    Subscription,
    Timer,
)
from tpsr_ros.runtime.params import NoParameters, ParamSpec, param, param_specs
from tpsr_ros.runtime.ros_args import RosArgs, UsageError, parse_ros_args
from tpsr_ros.runtime.transport import TopicEndpoint, Transport

__all__ = [
    "DEFAULT_QOS",
    "LATCHED_QOS",
    "SENSOR_DATA_QOS",
    "Durability",
    "EndpointInfo",
    "History",
    "Launch",
    "LaunchError",
    "Logger",
    "NoParameters",
    "Node",
    "NodeOptions",
    "NodeProcess",
    "ParamSpec",
    "Publisher",
    "QoSProfile",
    "Reliability",
    "RosArgs",
    "Subscription",
    "Timer",
    "TopicEndpoint",
    "Transport",
    "UsageError",
    "param",
    "param_specs",
    "parse_node_args",
    "parse_ros_args",
    "run_node",
]
