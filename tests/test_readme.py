"""The README: short, its array example runs as printed and its states mean something, its
robot-bag commands run."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

from learner.jobs import ENVIRONMENTS

README = Path(__file__).resolve().parents[1] / "README.md"


def _array_example() -> str:
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Learning from arrays") :]
    match = re.search(r"```python\n(.*?)```", section, re.DOTALL)
    assert match is not None, "no python block in the README's array section"
    return match.group(1)


def test_the_readme_array_example_runs() -> None:
    code = _array_example()
    assert len(code.strip().splitlines()) <= 10
    namespace: dict[str, object] = {}
    exec(compile(code, str(README), "exec"), namespace)
    states = namespace["states"]
    actions, observations = namespace["actions"], namespace["observations"]
    model, state = namespace["model"], namespace["state"]
    # the preset's rank 8, held to the 6 singular values of P_TH the data support (a ring
    # of 6 cells: the system's own dimension)
    assert isinstance(states, np.ndarray) and states.shape == (3000, 6)
    assert model.fit_info["sized"]["rank"] == [8, 6]  # type: ignore[attr-defined]
    # update is the one-step form of track (Algorithm 4, bit for bit)
    np.testing.assert_array_equal(state, states[0])
    again = model.initial_state()  # type: ignore[attr-defined]
    for k in range(20):
        again, _ = model.update(again, actions[k], observations[k])  # type: ignore[attr-defined,index]
    np.testing.assert_array_equal(again, states[19])
    # the states locate the robot on the ring: a linear read-out of the cell
    cells = np.cumsum(actions) % 6  # type: ignore[call-overload]
    features = np.c_[states, np.ones(len(states))]
    weights = np.linalg.lstsq(features[:2000], np.eye(6)[cells[:2000]], rcond=None)[0]
    accuracy = np.mean(np.argmax(features[2000:] @ weights, axis=1) == cells[2000:])
    assert accuracy > 0.92  # 0.937 at rank 6; the two noise directions of rank 8 gave 0.95


def test_the_readme_fits_a_screen_and_speaks_of_the_software() -> None:
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= 150
    assert text.index("make demo") < text.index("make test") < text.index("## ")  # set-up first
    results = text.split("<!-- results: written by python -m learner report -->")[1]
    rows = results.split("<!-- end of results -->")[0].count("\n| `")
    assert rows == len(ENVIRONMENTS)  # its table: a row per environment
    for link in re.findall(r"\]\(([^)#]+)\)", text):  # every link leads somewhere
        assert (README.parent / link).exists(), link


def test_the_user_api_is_the_package() -> None:
    import tpsr_ros

    for name in (
        "TPSRConfig",
        "fit",
        "TPSRModel",
        "PCAConfig",
        "Trajectory",
        "make_episodes",
        "OnlineTracker",
        "load_model",
        "save_model",
    ):
        assert name in tpsr_ros.__all__
        assert getattr(tpsr_ros, name) is not None
    assert set(tpsr_ros.__all__) == set(tpsr_ros._API)
    from tpsr_ros.core.tpsr import TPSRModel

    assert tpsr_ros.TPSRModel is TPSRModel


def _robot_commands() -> list[str]:
    text = README.read_text(encoding="utf-8")
    section = text[text.index("## Learning from your robot's bag") :]
    match = re.search(r"```sh\n(.*?)```", section, re.DOTALL)
    assert match is not None, "no sh block in the README's robot section"
    return match.group(1).replace("\\\n", " ").strip().splitlines()


@pytest.mark.slow
def test_the_readme_robot_bag_commands_run(tmp_path) -> None:
    import os
    import shlex
    import subprocess
    import sys

    commands = _robot_commands()
    assert [c.split()[:3] for c in commands] == [
        ["python", "-m", "sim_node.robot_bag"],
        ["python", "-m", "learner"],
        ["python", "-m", "learner"],
        ["python", "-m", "learner"],
    ]
    root = README.parent
    env = {**os.environ, "PYTHONPATH": str(root)}
    small = {"--steps 9000": "--steps 900"}  # the same commands on a small bag
    outputs = []
    for command in commands:
        for long, short in small.items():
            command = command.replace(long, short)
        argv = [sys.executable, *shlex.split(command)[1:]]
        if argv[3:4] == ["fit"]:
            argv += ["--obs-centers", "40", "--ht-centers", "80", "--rank", "3"]
        done = subprocess.run(argv, cwd=tmp_path, env=env, capture_output=True, text=True)
        assert done.returncode == 0, (command, done.stderr[-2000:])
        outputs.append(done.stdout + done.stderr)
    # 900 steps: at most 15 actions (one per 60 steps), fewer if a code is never in force
    said = r"1[0-5] actions over linear.x, linear.y \(kmeans\) \(default sized"
    assert re.search(said, outputs[1])
    assert "R^2 of true position from states" in outputs[2]
    for name in ("robot_bag", "robot_model.npz", "robot_states.png", "robot_policy.npz"):
        assert (tmp_path / name).exists(), name
