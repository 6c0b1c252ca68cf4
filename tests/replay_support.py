"""Replaying a bag into a filter node process and collecting what it publishes on
/tpsr/state (the transport comes from TPSR_TRANSPORT, set by the test)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from tpsr_ros.io import messages as m
from tpsr_ros.runtime import Node, NodeOptions
from tpsr_ros.runtime.launcher import Launch

__all__ = ["replay_states"]


def replay_states(
    model: Path, bag: Path, topics: list[str], rate: str, expected: int, log_dir: Path
) -> tuple[list[tuple[int, Any]], str]:
    """Play ``bag``'s ``topics`` at ``rate`` into a filter node for ``model``; the
    ``(stamp, state)`` pairs it published (waiting for ``expected``) and its log."""
    probe = Node(NodeOptions(name=f"probe_{rate.replace('.', '_')}"))
    states: list[tuple[int, Any]] = []
    state_sub = probe.create_subscription(
        "/tpsr/state", m.STATE_TYPE,
        lambda x: states.append((m.stamp_of(x), m.state_to_array(x))),
    )  # fmt: skip
    try:
        with Launch(log_dir, spin=probe.spin_once, timeout_s=60) as launch:
            node = launch.start(
                "filter", "tpsr_ros.filter_node", ["--ros-args", "-p", f"model:={model}"]
            )
            launch.wait("the filter's subscriptions", lambda: "steps of" in node.text())
            # the probe must have matched the state publisher before the first state is sent
            launch.wait("the state publisher", lambda: state_sub.get_publisher_count() > 0)
            player = launch.start("play", "tpsr_ros.play", [
                str(bag), "--rate", rate, "--topics", *topics,
                "--wait-for-subscribers", "1", "--no-clock",
            ])  # fmt: skip
            deadline = time.monotonic() + 60
            while len(states) < expected and time.monotonic() < deadline:
                probe.spin_once(0.05)
            assert player.wait(30) == 0, player.text()
            assert node.stop() == 0, node.text()
    finally:
        probe.close()
    return states, node.text()
