"""The exact-time synchroniser: pairing, eviction, duplicates, late and out-of-order messages,
backwards jumps; a property test against a brute-force model of the rules."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from tpsr_ros.core.errors import ConfigError
from tpsr_ros.core.pairing import ExactTimeSynchronizer, Outcome

S = 10**9


def test_pairs_by_identical_stamp_in_either_order():
    sync = ExactTimeSynchronizer()
    assert sync.add(0, 1 * S, "i1").outcome is Outcome.BUFFERED
    result = sync.add(1, 1 * S, "a1")
    assert result.outcome is Outcome.PAIRED and result.items == ("i1", "a1")
    assert sync.add(1, 2 * S, "a2").outcome is Outcome.BUFFERED
    assert sync.add(0, 2 * S, "i2").items == ("i2", "a2")
    assert sync.last_stamp == 2 * S and sync.pending == 0
    assert sync.stats.as_dict() == {
        "paired": 2,
        "dropped": 0,
        "duplicates": 0,
        "late": 0,
        "out_of_order": 0,
        "time_jumps": 0,
    }


def test_a_processed_step_evicts_older_incomplete_ones():
    sync = ExactTimeSynchronizer()
    sync.add(0, 1 * S, "i1")  # its action never comes
    sync.add(1, 2 * S, "a2")  # its image never comes
    sync.add(0, 3 * S, "i3")
    assert sync.add(1, 3 * S, "a3").outcome is Outcome.PAIRED
    assert sync.stats.dropped == 2 and sync.pending == 0
    # the missing partners arriving now are late
    assert sync.add(1, 1 * S, "a1").outcome is Outcome.LATE
    assert sync.add(0, 2 * S, "i2").outcome is Outcome.LATE
    assert sync.stats.late == 2 and sync.stats.out_of_order == 2


def test_the_buffer_is_bounded_oldest_first():
    sync = ExactTimeSynchronizer(queue_size=3)
    for k in range(1, 4):
        assert sync.add(0, k * S, f"i{k}").outcome is Outcome.BUFFERED
    assert sync.add(0, 4 * S, "i4").outcome is Outcome.BUFFERED
    assert sync.stats.dropped == 1 and sync.pending == 3
    # an older message than everything buffered when full is itself the one dropped
    assert sync.add(1, 0, "a0").outcome is Outcome.DROPPED
    assert sync.stats.dropped == 2
    assert sync.add(1, 1 * S, "a1").outcome is Outcome.DROPPED  # i1 was evicted
    assert sync.add(1, 2 * S, "a2").items == ("i2", "a2")


def test_duplicates_keep_the_first_message():
    sync = ExactTimeSynchronizer()
    sync.add(0, 1 * S, "first")
    assert sync.add(0, 1 * S, "second").outcome is Outcome.DUPLICATE
    assert sync.add(1, 1 * S, "a1").items == ("first", "a1")
    assert sync.add(0, 1 * S, "again").outcome is Outcome.DUPLICATE  # already processed
    assert sync.add(1, 1 * S, "again").outcome is Outcome.DUPLICATE
    assert sync.stats.duplicates == 3 and sync.stats.late == 0


def test_out_of_order_messages_are_counted_and_still_paired_in_stamp_order():
    sync = ExactTimeSynchronizer()
    sync.add(0, 2 * S, "i2")
    sync.add(0, 1 * S, "i1")  # out of order on its topic
    assert sync.add(1, 1 * S, "a1").items == ("i1", "a1")
    assert sync.add(1, 2 * S, "a2").items == ("i2", "a2")
    assert sync.stats.out_of_order == 1 and sync.stats.dropped == 0


def test_a_backwards_jump_clears_and_restarts():
    sync = ExactTimeSynchronizer(jump_threshold_ns=5 * S)
    for k in range(1, 21):
        sync.add(0, k * S, k)
        sync.add(1, k * S, k)
    sync.add(0, 21 * S, 21)  # incomplete when time jumps
    late = sync.add(0, 15 * S + S // 2, "late")  # within the threshold: late, not a jump
    assert late.outcome is Outcome.LATE and not late.jumped
    result = sync.add(0, 1 * S, "loop")
    assert result.jumped and result.outcome is Outcome.BUFFERED
    assert sync.stats.time_jumps == 1 and sync.stats.dropped == 1
    assert sync.add(1, 1 * S, "loop").items == ("loop", "loop")


def test_check_time_and_start_after():
    sync = ExactTimeSynchronizer(jump_threshold_ns=5 * S)
    assert not sync.check_time(0)  # nothing processed yet
    sync.add(0, 10 * S, 1)
    sync.add(1, 10 * S, 1)
    assert not sync.check_time(6 * S) and sync.check_time(4 * S)
    assert sync.last_stamp is None and sync.stats.time_jumps == 1
    sync.add(0, 12 * S, 1)
    sync.add(0, 13 * S, 1)
    sync.start_after(12 * S)
    assert sync.pending == 1 and sync.stats.dropped == 1 and sync.last_stamp == 12 * S
    assert sync.add(1, 12 * S, 1).outcome is Outcome.LATE
    with pytest.raises(ConfigError):
        sync.start_after(11 * S)


def test_bad_arguments():
    with pytest.raises(ConfigError):
        ExactTimeSynchronizer(1)
    with pytest.raises(ConfigError):
        ExactTimeSynchronizer(queue_size=0)
    with pytest.raises(ConfigError):
        ExactTimeSynchronizer().add(2, 0, 1)
    with pytest.raises(ConfigError):
        ExactTimeSynchronizer().add(0, 0, None)


messages = st.lists(st.tuples(st.integers(0, 1), st.integers(0, 12)), min_size=0, max_size=60)


@settings(max_examples=300, deadline=None)
@given(messages, st.integers(1, 4))
def test_against_a_brute_force_model(sequence, queue_size):
    """Every emitted step is complete, in increasing stamp order, emitted once; every
    message is accounted for exactly once; the buffer never exceeds queue_size."""
    sync = ExactTimeSynchronizer(queue_size=queue_size, jump_threshold_ns=100 * S)
    emitted = []
    fates = {o: 0 for o in Outcome}
    for index, stamp in sequence:
        result = sync.add(index, stamp * S, (index, stamp))
        fates[result.outcome] += 1
        if result.outcome is Outcome.PAIRED:
            assert result.items == ((0, stamp), (1, stamp))
            emitted.append(stamp)
        assert sync.pending <= queue_size
    assert emitted == sorted(set(emitted))
    stats = sync.stats
    assert stats.paired == len(emitted) == fates[Outcome.PAIRED]
    assert stats.duplicates == fates[Outcome.DUPLICATE]
    assert stats.late == fates[Outcome.LATE]
    # each message: its step was emitted (2 per step), or it is still buffered, or it was
    # duplicate / late, or it belonged to a dropped (incomplete, single-message) step
    assert len(sequence) == (
        2 * stats.paired + sync.pending + stats.duplicates + stats.late + stats.dropped
    )
