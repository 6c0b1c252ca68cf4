"""A run whose room changes under the robot (`generate_bag(..., then=...)`), as the room-change
study of `learner competence --switch-to` generates it."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from sim_node import SimConfig
from sim_node.generate import generate_bag
from tpsr_ros.core.errors import ConfigError
from tpsr_ros.io.trajectory import LiveSteps


def test_the_room_changes_under_the_robot_and_the_run_goes_on(tmp_path):
    full, distractors = SimConfig(environment="full"), SimConfig(environment="distractors")
    generate_bag(tmp_path / "plain", full, 60, seed=5)
    generate_bag(tmp_path / "switch", full, 60, seed=5, then=(distractors, 40))
    plain = LiveSteps.of_bag(tmp_path / "plain", "full").trajectory()
    switch = LiveSteps.of_bag(tmp_path / "switch", "full").trajectory()
    assert len(switch) == 100
    np.testing.assert_array_equal(np.diff(switch.stamps), 10**9)  # one clock, a step a second
    assert len(switch.segment_bounds()) == 1  # no reset: the same run
    for name in ("observations", "actions", "positions", "rewards"):  # the first room's part
        np.testing.assert_array_equal(getattr(switch, name)[:60], getattr(plain, name))
    longest = np.linalg.norm(np.diff(plain.positions, axis=0), axis=1).max()
    across = np.linalg.norm(switch.positions[60] - switch.positions[59])
    assert across <= longest + 1e-9  # the robot goes on from where it was: one step's move
    red = switch.observations.reshape(100, 16, 16, 3)
    redness = (red[..., 0] - red[..., 1:].max(axis=-1)).max(axis=(1, 2))
    assert redness[60:].max() > redness[:60].max()  # red distractors only after the change
    metadata = yaml.safe_load((tmp_path / "switch" / "metadata.yaml").read_text())
    custom = metadata["rosbag2_bagfile_information"]["custom_data"]
    assert '"environment": "distractors"' in custom["tpsr_ros.switch"]


def test_a_room_of_another_robot_is_refused(tmp_path):
    with pytest.raises(ConfigError, match="same robot"):
        generate_bag(
            tmp_path / "bag", SimConfig(environment="full"), 10, seed=0,
            then=(SimConfig(environment="drive"), 10),
        )  # fmt: skip
    assert not (tmp_path / "bag").exists()
