"""Lockstep on the in-process bus: sim_node's episode_steps, and the filter node driving the
simulator through the standard protocol with the headless evaluation's exact result."""

from __future__ import annotations

import time

import pytest

from sim_node.node import SimNode
from tpsr_ros.io import messages as m
from tpsr_ros.runtime import LATCHED_QOS, Node, NodeOptions, parse_ros_args
from tpsr_ros.runtime.inproc import InprocBus, InprocTransport

S = 10**9


class Driver:
    """Resets the simulator and collects rewards, episode starts and states."""

    def __init__(self, bus: InprocBus) -> None:
        self.node = Node(NodeOptions(name="driver"), transport=InprocTransport("/driver", bus))
        self.rewards: list[tuple[int, float]] = []
        self.starts: list[int] = []
        self.states: list[tuple[int, list[float]]] = []
        self.node.create_subscription(
            "/reward",
            m.REWARD_TYPE,
            lambda x: self.rewards.append((m.stamp_of(x), m.reward_to_sample(x).reward)),
        )
        self.node.create_subscription(
            "/sim/episode_start",
            m.POSE_TYPE,
            lambda x: self.starts.append(m.stamp_of(x)),
            LATCHED_QOS,
        )
        self.node.create_subscription(
            "/tpsr/state",
            m.STATE_TYPE,
            lambda x: self.states.append((m.stamp_of(x), list(m.state_to_array(x)))),
        )
        self.reset = self.node.create_publisher("/sim/reset", m.POSE_TYPE)
        self.cmd = self.node.create_publisher("/cmd_vel", m.TWIST_TYPE)


def spin(nodes, until, timeout=30.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        for node in nodes:
            node.spin_once(0.0)
        if until():
            return
        time.sleep(0.0005)
    raise AssertionError("timed out")


def start_sim(bus, *params):
    args = []
    for p in params:
        args += ["-p", p]
    options = NodeOptions.for_node(SimNode, parse_ros_args(args))
    return SimNode(options, transport=InprocTransport("/sim_node", bus))


def test_episode_steps_ignores_commands_until_the_next_reset():
    bus = InprocBus()
    driver = Driver(bus)
    sim = start_sim(bus, "mode:=command", "episode_steps:=3", "seed:=4")
    nodes = [sim, driver.node]
    try:
        spin(nodes, lambda: len(driver.starts) == 1)
        for _ in range(5):
            driver.cmd.publish(m.twist_msg(3.0, 0.0))
        spin(nodes, lambda: sim.ignored_commands == 2)
        assert sim.steps_published == 3 and [s for s, _ in driver.rewards] == [S, 2 * S, 3 * S]
        driver.reset.publish(m.pose_msg(0, 10.0, 10.0))
        spin(nodes, lambda: len(driver.starts) == 2)
        assert driver.starts[-1] == 4 * S
        driver.cmd.publish(m.twist_msg(0.0, 3.0))
        spin(nodes, lambda: sim.steps_published == 4)
        assert driver.rewards[-1][0] == 5 * S and sim.ignored_commands == 2
    finally:
        sim.close()
        driver.node.close()


def test_episode_steps_zero_never_ignores():
    bus = InprocBus()
    driver = Driver(bus)
    sim = start_sim(bus, "mode:=command")
    try:
        for k in range(1, 61):
            driver.cmd.publish(m.twist_msg(3.0, 0.0))
            spin([sim, driver.node], lambda k=k: sim.steps_published == k)
        assert sim.ignored_commands == 0
    finally:
        sim.close()
        driver.node.close()


@pytest.mark.slow
def test_the_filter_drives_the_standard_protocol_exactly_like_the_headless_evaluation(
    tmp_path,
):
    """Same trials as learner.evaluate for the same policy (seed 2026, 10 starts x 50)."""
    from test_filter_node import fit_small_model, random_policy

    from learner.evaluate import START_POSITIONS, STEPS, evaluate
    from learner.representations import load_tracker
    from tpsr_ros.filter_node import FilterNode
    from tpsr_ros.io.policy import load_policy

    model = fit_small_model(tmp_path)
    policy = random_policy(model, tmp_path / "policy.npz", seed=5)
    headless = evaluate(load_policy(policy), load_tracker(model), "full")

    bus = InprocBus()
    driver = Driver(bus)
    sim = start_sim(bus, "mode:=command", "seed:=2026", f"episode_steps:={STEPS}")
    nodes = [sim, driver.node]
    spin(nodes, lambda: len(driver.starts) == 1)  # the start-up reset
    try:
        trials = []
        for i, (x, y) in enumerate(START_POSITIONS):
            driver.reset.publish(m.pose_msg(0, x, y))
            spin(nodes, lambda i=i: len(driver.starts) == i + 2)
            if i == 0:  # the filter joins after the first reset, as in the closed loop
                options = NodeOptions.for_node(FilterNode, model=str(model), policy=str(policy))
                nodes.append(FilterNode(options, transport=InprocTransport("/f", bus)))
            before = len(driver.rewards)
            spin(
                nodes,
                lambda i=i, b=before: (
                    len(driver.rewards) == b + STEPS and sim.ignored_commands == i + 1
                ),
            )
            got = driver.rewards[before:]
            assert [s for s, _ in got] == [driver.starts[-1] + k * S for k in range(1, STEPS + 1)]
            trials.append(sum(r for _, r in got))
        assert trials == [t.reward for t in headless.trials]
        assert len(driver.states) == len(START_POSITIONS) * STEPS
    finally:
        for node in nodes:
            node.close()
        driver.node.close()
