"""A model learned from a robot bag, scored in the simulator: the filter node's lockstep steps,
the one-line refusals of what the simulator cannot play, and (slow) the closed loop over the
nodes equal to ``learner evaluate`` and clearly above the floors."""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys

import numpy as np
import pytest
from cli_support import run_entry
from graph_support import LOOPBACK, fresh_domain

from learner.sim_robot import recorded_camera, simulated_robot
from sim_node import SimConfig
from tpsr_ros.core.codebook import ActionCodebook
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.resample import GridConfig, GridStepper
from tpsr_ros.filter_node.stepping import LockstepStepping
from tpsr_ros.io.model_io import open_model

S = 10**9
GRID = GridConfig(
    step_ns=S, camera_period_ns=S // 4, image_timeout_ns=S, command_timeout_ns=2 * S,
    phase_ns=150_000_000,
)


def test_the_grid_rules_cannot_close_a_lockstep_step_and_lockstep_does():
    """A lockstep robot sends image k only after command k: the grid waits for an image
    after the step, so step k never closes; one step per image closes it at once."""
    stepper = GridStepper(GRID)
    assert stepper.add_command(S, 7) == []  # command 1, dated by image 1
    assert stepper.add_image(S, "image 1") == []  # the step at 1.15 s waits for image 2
    assert stepper.flush() == []  # nothing before the newest image to close

    lockstep = LockstepStepping(GRID, jump_threshold_ns=S)
    assert lockstep.add_image(0, "before any command").steps == []
    lockstep.command(7)
    (step,) = lockstep.add_image(S, "image 1").steps
    assert (step.stamp, step.action, step.image) == (S + 150_000_000, 7, "image 1")
    lockstep.command(3)
    assert lockstep.add_image(S + 100_000_000, "same grid step").problem == "late"
    lockstep.command(4)
    assert lockstep.episode_start(2 * S)  # the reset's stamp, after the last step's image
    lockstep.command(5)  # an ignored command, then the first of an episode: the last counts
    (step,) = lockstep.add_image(3 * S + 150_000_000, "on a grid time").steps
    assert (step.stamp, step.action) == (3 * S + 150_000_000, 5)
    counts = lockstep.counts()
    assert (counts["command_gaps"], counts["late"]) == (1, 1)
    assert lockstep.add_image(0, "back in time").jumped
    with pytest.raises(ConfigError, match="phase"):
        LockstepStepping(dataclasses.replace(GRID, phase_ns=None), jump_threshold_ns=S)


def _episode_boundary(start_first: bool) -> list[tuple[str, object]]:
    """Three steps, the last command (ignored by the robot), a reset at 4 s and the
    node's command from b_*, then the episode's first image at 5 s: the episode start and
    that image in either arrival order, as the node calls the stepping."""
    lockstep = LockstepStepping(GRID, jump_threshold_ns=5 * S)
    events: list[tuple[str, object]] = []

    def steps(added):
        events.extend(("step", (s.stamp, s.action, s.image)) for s in added.steps)

    for k in (1, 2, 3):
        lockstep.command(k)
        steps(lockstep.add_image(k * S, f"image {k}"))
    lockstep.command(4)  # answers step 3; the robot ignores it (the episode's end)

    def start():
        events.append(("restart", lockstep.episode_start(4 * S)))
        lockstep.command(9)  # the node's command from b_*, sent on the restart
        steps(lockstep.release())

    if start_first:
        start()
        steps(lockstep.add_image(5 * S, "image 5"))
    else:
        steps(lockstep.add_image(5 * S, "image 5"))
        start()
    lockstep.command(6)
    steps(lockstep.add_image(6 * S, "image 6"))
    events.append(("counts", lockstep.counts()))
    return events


def test_lockstep_steps_do_not_depend_on_the_arrival_order_of_an_episode_start():
    """Stamps decide: a start at 4 s applies to the image at 5 s whichever arrives first,
    and that image takes the command of the restarted state, never the ignored one."""
    first, second = _episode_boundary(True), _episode_boundary(False)
    assert first == second
    assert ("step", (5 * S + 150_000_000, 9, "image 5")) in first
    assert ("restart", True) in first


def test_lockstep_holds_an_image_after_a_gap_and_ignores_a_lagging_clock():
    lockstep = LockstepStepping(GRID, jump_threshold_ns=5 * S)
    lockstep.command(1)
    assert lockstep.clock(S) is False
    assert len(lockstep.add_image(S, "image 1").steps) == 1
    for k in range(2, 12):  # the clock's messages lag the images by more than the bound
        assert len(lockstep.add_image(k * S, f"image {k}").steps) == 1
    assert lockstep.clock(2 * S) is False and lockstep.counts()["time_jumps"] == 0
    assert lockstep.add_image(14 * S, "after a gap").steps == []  # held: a start may precede
    assert lockstep.release().steps == []  # no start before it
    (step,) = lockstep.flush().steps  # the lateness bound expired: the stream goes on
    assert (step.stamp, step.action, step.image) == (14 * S + 150_000_000, 1, "after a gap")
    assert lockstep.episode_start(13 * S) is False  # older than a stepped image: stale
    assert lockstep.clock(20 * S) is False
    assert lockstep.clock(0) is True  # the clock's own time jumped back: restart


@pytest.fixture(scope="module")
def robot(tmp_path_factory):
    """A robot bag (the simulator's reward on /reward), its model and a policy on it."""
    from learner.cli import main as learner_main
    from sim_node.robot_bag import main as robot_bag

    tmp = tmp_path_factory.mktemp("robot_closed_loop")
    bag, model, policy = tmp / "robot", tmp / "model.npz", tmp / "policy.npz"
    # 2000 steps: all ten trials reach the goal, 456 (3000: 432; 4000: 460) against floors
    # of 38
    assert robot_bag(["--steps", "2000", "--seed", "0", "-o", str(bag)]) == 0
    assert learner_main([
        "fit", str(bag), "--image-topic", "/front_camera/image_raw", "--action-topic",
        "/cmd_vel", "--pose-topic", "/odom", "--step-period", "1.0", "-o", str(model),
    ]) == 0  # fmt: skip
    assert learner_main(
        ["policy", str(model), str(bag), "--reward-topic", "/reward", "-o", str(policy)]
    ) == 0
    return tmp


@pytest.mark.slow
def test_refusals_name_what_the_simulator_cannot_play(robot, capsys):
    model_file = open_model(robot / "model.npz")
    assert recorded_camera(model_file.metadata) == (40, 40)  # fit records the robot's camera
    full = SimConfig(environment="full")
    played = simulated_robot(model_file, full)
    assert played.camera_size == 40 and played.image_topic == "/front_camera/image_raw"
    spec = model_file.spec
    assert spec is not None

    def refused(match: str, config: SimConfig = full, **changes) -> None:
        changed = dataclasses.replace(model_file, spec=dataclasses.replace(spec, **changes))
        with pytest.raises(ConfigError, match=match) as exc:
            simulated_robot(changed, config)
        assert "\n" not in str(exc.value)

    refused("steps every 0.5 s, the simulator every 1 s", grid=dataclasses.replace(
        spec.grid, step_ns=S // 2, phase_ns=0))  # fmt: skip
    refused("reads sensor_msgs/msg/CompressedImage", image_type="sensor_msgs/msg/CompressedImage")
    turning = ActionCodebook("kmeans", ("linear.x", "angular.z"), np.array([[3.0, 0.5], [0, 0]]))
    refused("commands angular.z, which the simulator's full robot does not have",
            codebook=turning)  # fmt: skip
    far = ActionCodebook("kmeans", ("linear.x",), np.array([[0.0], [20.0]]))
    refused("a code the simulator cannot execute", codebook=far)
    refused("does not have", SimConfig(environment="drive"))  # linear.y on a robot that turns
    for command in ("evaluate", "closed-loop"):  # refused before any process starts
        status, _, err = run_entry(
            [command, str(robot / "policy.npz"), "--environment", "full", "--camera-size", "8"],
            capsys,
        )
        assert status == 1 and err.count("\n") == 1, err
        assert "takes 16x16 observations, more than a 8x8 camera gives" in err


@pytest.mark.slow
def test_closed_loop_of_a_robot_model_equals_the_headless_score_above_the_floors(
    robot, capsys
):
    from learner.cli import main as learner_main
    from learner.floors import constant_floor, random_floor

    policy = robot / "policy.npz"
    assert learner_main(["evaluate", str(policy), "--environment", "full"]) == 0
    headless = capsys.readouterr().out.splitlines()
    env = {**os.environ, "CYCLONEDDS_URI": LOOPBACK, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "learner", "closed-loop", str(policy), "--environment", "full",
         "--domain-id", str(fresh_domain(61))],
        capture_output=True, text=True, timeout=240, env=env,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "-p lockstep:=true" in proc.stderr and "image_size:=40" in proc.stderr
    lines = proc.stdout.splitlines()
    assert lines == headless and len(lines) == 11, (lines, headless)  # every trial, exactly
    score = float(lines[-1].split()[1])
    floors = max(constant_floor("full").evaluation.score, random_floor("full", policy_seed=0).score)
    assert score > floors + 200, (score, floors)
    assert sum("goal zone at step" in line for line in lines) >= 8
