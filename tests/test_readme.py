"""The README's array example runs as printed, and its states mean something."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

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
    assert isinstance(states, np.ndarray) and states.shape == (3000, 5)
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
    assert accuracy > 0.95


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
