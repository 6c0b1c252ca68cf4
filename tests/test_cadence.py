"""Messages missing from a steady stream are counted from its stamps, and only there."""

from __future__ import annotations

import numpy as np

from tpsr_ros.core.cadence import CadenceGaps

PERIOD = 33_333_333  # 30 Hz


def _feed(stamps) -> CadenceGaps:
    gaps = CadenceGaps()
    for stamp in stamps:
        gaps.add(int(stamp))
    return gaps


def _camera(count: int, jitter: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 10**12 + np.arange(count) * PERIOD + rng.uniform(-jitter, jitter, count) * PERIOD


def test_holes_in_a_jittery_camera_are_counted_exactly():
    stamps = _camera(600, jitter=0.1, seed=1)
    holes = [[40], [41, 42, 43], list(range(100, 130)), [599 - 1]]
    kept = np.delete(stamps, np.concatenate(holes))
    gaps = _feed(kept)
    assert gaps.missing == sum(map(len, holes)) == 35
    assert gaps.gaps == 3  # 40-43 is one gap
    assert abs(gaps.period_ns - PERIOD) < 0.05 * PERIOD


def test_a_steady_stream_without_holes_counts_nothing():
    assert _feed(_camera(2000, jitter=0.2, seed=2)).missing == 0


def test_a_camera_with_30_percent_interval_jitter_loses_nothing():
    rng = np.random.default_rng(8)
    intervals = rng.uniform(0.7, 1.3, 5000) * PERIOD
    assert _feed(10**12 + np.cumsum(intervals).astype(np.int64)).missing == 0
    assert _feed(_camera(5000, jitter=0.3, seed=10)).missing == 0  # stamps off by 30 %


def test_a_camera_with_a_third_of_its_intervals_stretched_loses_nothing():
    rng = np.random.default_rng(9)
    intervals = np.full(5000, PERIOD, dtype=np.float64)
    stretched = rng.random(5000) < 1 / 3
    intervals[stretched] *= rng.uniform(1.0, 3.0, int(stretched.sum()))
    assert _feed(10**12 + np.cumsum(intervals).astype(np.int64)).missing == 0


def test_irregular_streams_are_not_judged():
    rng = np.random.default_rng(3)
    events = 10**12 + np.cumsum(rng.exponential(PERIOD, 2000)).astype(np.int64)  # commands
    gaps = _feed(events)
    assert gaps.missing == 0 and gaps.period_ns is None
    two_cameras = np.sort(np.concatenate([_camera(500, 0.0, 4), _camera(500, 0.0, 5) + 10**7]))
    assert _feed(two_cameras).missing == 0  # interleaved: intervals of 10 and 23 ms


def test_time_going_back_starts_afresh_and_duplicates_are_ignored():
    first = _camera(100, jitter=0.0, seed=6)
    again = _camera(100, jitter=0.0, seed=6)  # a bag replayed in a loop
    gaps = _feed(np.concatenate([first, again, again[-1:]]))
    assert gaps.missing == 0
    gaps.add(int(again[-1] + 4 * PERIOD))  # the cadence was learnt again after the jump
    assert gaps.missing == 3


def test_nothing_is_counted_before_the_cadence_is_known():
    stamps = _camera(20, jitter=0.0, seed=7)
    gaps = _feed(np.delete(stamps, [3, 4, 5]))  # the hole comes before 8 intervals
    assert gaps.missing == 0
