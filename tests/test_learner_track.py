"""learner track: the offline states the filter node is held to, as CSV or NPZ, exactly."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
from cli_support import run_entry

from tpsr_ros.core.episodes import track_trajectory
from tpsr_ros.io.model_io import load_model
from tpsr_ros.io.trajectory import read_trajectory

BAG = Path(__file__).resolve().parents[1] / "bags" / "partial"
SMALL = ["--obs-centers", "40", "--ht-centers", "80", "--rank", "3"]


def test_track_writes_every_state_exactly_in_either_format(tmp_path, capsys):
    model = tmp_path / "m.npz"
    assert run_entry(["fit", str(BAG), "-o", str(model), *SMALL], capsys)[0] == 0
    expected = track_trajectory(load_model(model), trajectory := read_trajectory([BAG]))
    code, _, err = run_entry(["track", str(model), str(BAG), "-o", str(tmp_path / "s.csv")],
                             capsys)
    assert code == 0 and "3000 steps in 1 segment(s)" in err, err
    with (tmp_path / "s.csv").open() as handle:
        rows = list(csv.reader(handle))
    assert rows[0] == ["stamp_ns", "b0", "b1", "b2", "x", "y"]
    table = np.array(rows[1:], dtype=float)
    np.testing.assert_array_equal(table[:, 0].astype(np.int64), trajectory.stamps)
    np.testing.assert_array_equal(table[:, 1:4], expected.states)  # round-trips exactly
    np.testing.assert_array_equal(table[:, 4:], trajectory.positions)
    code, _, err = run_entry(["track", str(model), str(BAG), "-o", str(tmp_path / "s.npz")],
                             capsys)
    assert code == 0, err
    with np.load(tmp_path / "s.npz", allow_pickle=False) as archive:
        np.testing.assert_array_equal(archive["states"], expected.states)
        np.testing.assert_array_equal(archive["recovered"], expected.recovered)
        assert archive["stamp_ns"].dtype == np.int64
    code, _, err = run_entry(["track", str(model), str(BAG), "-o", str(tmp_path / "s.npz")],
                             capsys)
    assert code == 1 and "use --force" in err
    code, _, err = run_entry(["track", str(model), str(BAG), "-o", str(tmp_path / "s.json")],
                             capsys)
    assert code == 1 and "write a .csv or .npz file" in err
