"""On the rclpy backend the ROS arguments reach rcl: ``--disable-stdout-logs`` silences the
console, as with any ROS 2 node."""

from __future__ import annotations

import os
import signal
import time

import pytest
from graph_support import fresh_domain, rclpy_available

from tpsr_ros.runtime.launcher import NodeProcess

pytestmark = [
    pytest.mark.rclpy,
    pytest.mark.skipif(not rclpy_available(), reason="rclpy (ROS 2) not importable"),
]


@pytest.mark.slow
@pytest.mark.parametrize("flag", [None, "--disable-stdout-logs"])
def test_disable_stdout_logs_silences_an_rclpy_node(flag, tmp_path):
    env = {**os.environ, "TPSR_TRANSPORT": "rclpy", "ROS_DOMAIN_ID": str(fresh_domain(61)),
           "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST"}  # fmt: skip
    args = ["--ros-args", "-p", "rate:=20", "-p", "steps:=3", *([flag] if flag else [])]
    node = NodeProcess("sim", "sim_node", args, log_path=tmp_path / "sim.log", env=env)
    try:
        # started and stepped (three steps at 20 Hz); a node that logs is seen doing so, a
        # silenced one is given the 3 s its logs took at the most
        deadline = time.monotonic() + (30 if flag is None else 3)
        while time.monotonic() < deadline and "episode starts at" not in node.text():
            time.sleep(0.05)
        os.kill(node.pid, signal.SIGINT)
        code = node.wait(30)
    finally:
        node.kill()
    assert code == 0, node.text()
    assert ("episode starts at" in node.text()) == (flag is None), node.text()
