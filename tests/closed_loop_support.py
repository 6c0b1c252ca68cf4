"""What a recorded closed loop of the standard protocol must hold, whatever its transport."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from tpsr_ros.core.episodes import Trajectory, track_trajectory
from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.io.model_io import load_model
from tpsr_ros.io.trajectory import read_trajectory

__all__ = ["check_recorded_closed_loop"]


def check_recorded_closed_loop(bag: Path, model: Path) -> Trajectory:
    """Assert that the recorded ``/tpsr/state`` equals offline tracking of the recorded bag
    at every step of the 10 trials of 50 steps, that every command was recorded and that no
    step was lost; return the recorded trajectory (its rewards give the score)."""
    trajectory = read_trajectory([bag], require_ground_truth=True)
    offline = track_trajectory(load_model(model), trajectory)
    with BagReader(bag) as reader:
        published = {
            m.stamp_of(state): m.state_to_array(state)
            for state in (msg.decode() for msg in reader.messages(["/tpsr/state"]))
        }
        commands = reader.message_counts["/cmd_vel"]
        # ten resets each take a step stamp no camera frame carries: none is a loss
        missing = reader.custom_data["recorder.missing_by_stamps"]
        by_topic = reader.custom_data["recorder.by_topic"]
    assert len(trajectory) == len(published) == 500 and len(trajectory.segment_bounds()) == 10
    worst = max(
        np.abs(published[int(s)] - offline.states[i]).max() for i, s in enumerate(trajectory.stamps)
    )
    assert worst <= 1e-9
    assert commands == 510  # 50 per trial and the ignored 51st
    assert missing == "0", by_topic
    return trajectory
