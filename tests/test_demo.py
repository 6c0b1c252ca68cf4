"""``python -m learner.demo`` (what ``make demo`` runs) end to end, on a sixth of its data.

Its closed loop runs over the transport the demo chooses (rclpy when importable): this test is
also the closed-loop check of that transport (the recorded states equal offline tracking, no
image lost); ``test_closed_loop`` checks the Cyclone DDS backend the same way.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from closed_loop_support import check_recorded_closed_loop
from graph_support import LOOPBACK, fresh_domain

from tpsr_ros.io import messages as m
from tpsr_ros.io.bag import BagReader
from tpsr_ros.runtime.backend import choose_backend

pytestmark = [pytest.mark.dds, pytest.mark.slow]


def test_the_demo_runs_end_to_end(tmp_path):
    pytest.importorskip("cyclonedds")
    out = tmp_path / "demo_output"
    out.mkdir()
    (out / "stale.txt").write_text("from an earlier run")  # the directory is recreated
    proc = subprocess.run(
        [sys.executable, "-m", "learner.demo", "--output", str(out),
         "--domain-id", str(fresh_domain()),
         # every stage, on a sixth and a fifth of the data: the closed-loop tests' sizes, where
         # the policy reaches the goal in every trial (466.6, far above the 200 asked below)
         "--train-steps", "4000", "--rl-steps", "3000"],
        capture_output=True,
        text=True,
        timeout=280,
        env={**os.environ, "CYCLONEDDS_URI": LOOPBACK},
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert f"as processes over {choose_backend()[0]}, recorded to" in proc.stderr
    for stage in range(1, 8):
        assert f"[{stage}/7]" in proc.stderr
    scores = re.search(
        r"score over the nodes \(closed loop\): (\S+); headless \(learner evaluate\): (\S+) "
        r"\(identical\)",
        proc.stdout,
    )
    assert scores and scores.group(1) == scores.group(2)
    assert float(scores.group(1)) > 200  # the robot gets to the goal and stays there
    assert not (out / "stale.txt").exists()
    for name in (
        "model.npz",
        "policy.npz",
        "states.png",
        "trajectories.png",
        "logs/sim_node.log",
        "logs/tpsr_filter.log",
        "logs/recorder.log",
    ):
        assert (out / name).is_file(), name
        assert str(out / name.split("/")[0]) in proc.stdout
    closed = out / "bags" / "closed_loop"
    with BagReader(closed) as reader:
        counts = reader.message_counts
        starts = [m.stamp_of(msg.decode()) for msg in reader.messages(["/sim/episode_start"])]
    assert counts["/tpsr/state"] == counts["/camera/image_raw"] == 500
    assert counts["/ground_truth/pose"] == 500
    # every trial's start (t = 1 s + 51 s per trial) is recorded; the start-up reset at t = 0
    # also is unless the driver's first reset overwrites that latched sample before the
    # recorder's reader has matched (the driver's own subscription satisfies the sim's gate)
    trial_starts = [(1 + 51 * i) * 10**9 for i in range(10)]
    assert starts in (trial_starts, [0, *trial_starts])

    # the published /tpsr/state equals offline tracking of the recorded bag, every step, with
    # every command recorded and no image lost
    trajectory = check_recorded_closed_loop(closed, out / "model.npz")
    assert trajectory.rewards.reshape(10, 50).sum(axis=1).mean() == pytest.approx(
        float(scores.group(1)), abs=0.05
    )  # the score printed to one decimal
