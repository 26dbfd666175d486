"""drivers.timesync: counter unwrapping, min-offset mapping with clamping, the skew check.

Every expected value is worked out by hand in the comment beside it.
"""

from __future__ import annotations

import pytest

from drivers.timesync import CounterUnwrapper, OffsetMapper, SkewCheck

MS = 1_000_000  # ns
S = 1_000_000_000  # ns


# -- CounterUnwrapper --------------------------------------------------------------------


def test_first_reading_is_taken_as_it_is():
    u = CounterUnwrapper(bits=16, tick_ns=MS)
    assert u.unwrap(65500, host_ns=7 * S) == 65500 * MS
    assert u.count == 65500


def test_a_wrap_continues_the_count():
    u = CounterUnwrapper(bits=16, tick_ns=MS)
    u.unwrap(65500, 0)
    # (4 - 65500) mod 65536 = 40 ticks, and the host saw 40 ms: no hidden wrap
    assert u.unwrap(4, 40 * MS) == 65540 * MS
    assert u.wraps_from_host_time == 0


def test_a_long_silence_spanning_several_wraps_is_counted_from_host_time():
    u = CounterUnwrapper(bits=16, tick_ns=MS)
    u.unwrap(1000, 0)
    # 3 wraps and 500 ms later: 1000 + 197108 = 198108 = 3 * 65536 + 1500
    elapsed_ms = 3 * 65536 + 500
    # the counter moved 500 ticks; round((197108 - 500) / 65536) = 3 hidden wraps
    assert u.unwrap(1500, elapsed_ms * MS) == 198108 * MS
    assert u.wraps_from_host_time == 3
    # host time 20 s late (a delayed read): round((217108 - 500) / 65536) = round(3.31) = 3
    u2 = CounterUnwrapper(bits=16, tick_ns=MS)
    u2.unwrap(1000, 0)
    assert u2.unwrap(1500, (elapsed_ms + 20_000) * MS) == 198108 * MS


def test_host_time_shorter_than_the_counter_step_adds_no_negative_wrap():
    u = CounterUnwrapper(bits=16, tick_ns=MS)
    u.unwrap(100, 0)
    # 50 ticks in 30 ms of host time: round(-20 / 65536) = 0, never negative
    assert u.unwrap(150, 30 * MS) == 150 * MS


def test_bits_and_tick_are_parameters():
    u = CounterUnwrapper(bits=8, tick_ns=10_000)  # 256 values of 10 us
    assert u.unwrap(250, 0) == 2_500_000
    # (5 - 250) mod 256 = 11 ticks = 110 us
    assert u.unwrap(5, 110_000) == 261 * 10_000
    # same raw value two wraps (2 * 256 * 10 us = 5.12 ms) later: 261 + 512 = 773
    assert u.unwrap(5, 110_000 + 5_120_000) == 773 * 10_000
    assert u.wraps_from_host_time == 2
    with pytest.raises(ValueError):
        CounterUnwrapper(bits=0, tick_ns=1)
    with pytest.raises(ValueError):
        CounterUnwrapper(bits=16, tick_ns=0)


# -- OffsetMapper ------------------------------------------------------------------------


def test_the_fastest_reading_sets_the_offset_and_a_delayed_one_does_not_move_it():
    m = OffsetMapper(window_ns=10 * S)
    assert m.offset_ns is None
    m.observe(1000 * MS, 5000 * MS)  # candidate 4000 ms
    assert m.stamp(1000 * MS) == 5000 * MS
    m.observe(1020 * MS, 5030 * MS)  # delayed 10 ms: candidate 4010 ms > 4000 ms
    assert m.offset_ns == 4000 * MS
    assert m.stamp(1020 * MS) == 5020 * MS
    m.observe(1040 * MS, 5035 * MS)  # faster: candidate 3995 ms becomes the offset
    assert m.stamp(1040 * MS) == 5035 * MS
    assert m.clamps == 0


def test_an_old_best_offset_leaves_the_window():
    m = OffsetMapper(window_ns=100 * MS)
    m.observe(1000 * MS, 5000 * MS)  # 4000
    m.observe(1050 * MS, 5060 * MS)  # 4010, the best is still 4000
    assert m.offset_ns == 4000 * MS
    # newest device time 1101 ms: horizon 1001 ms drops the 1000 ms reading
    m.observe(1101 * MS, 5111 * MS)  # 4010
    assert m.offset_ns == 4010 * MS
    assert m.stamp(1101 * MS) == 5111 * MS


def test_a_stamp_that_would_go_back_is_clamped_and_counted():
    m = OffsetMapper(window_ns=10 * S)
    m.observe(1000 * MS, 5000 * MS)
    assert m.stamp(1000 * MS) == 5000 * MS
    # the device clock ran ahead: 1001 and 1050 both received at 5020 ms
    m.observe(1001 * MS, 5020 * MS)  # candidate 4019
    m.observe(1050 * MS, 5020 * MS)  # candidate 3970: the new offset
    # 1001 + 3970 = 4971 ms < 5000 ms: raised to 5000 ms
    assert m.stamp(1001 * MS) == 5000 * MS
    assert m.clamps == 1
    assert m.stamp(1050 * MS) == 5020 * MS
    # a host-stamped reading goes through the same clamp
    assert m.clamp(4000 * MS) == 5020 * MS
    assert m.clamp(5021 * MS) == 5021 * MS
    assert m.clamps == 2


def test_stamp_before_any_observation_raises():
    with pytest.raises(RuntimeError):
        OffsetMapper(window_ns=S).stamp(0)
    with pytest.raises(ValueError):
        OffsetMapper(window_ns=-1)


# -- SkewCheck ---------------------------------------------------------------------------


def test_skew_check_accepts_within_the_limit_and_counts_rejections():
    c = SkewCheck(max_skew_ns=2 * S)
    assert c.accept(10 * S, 10 * S)
    assert c.accept(12 * S, 10 * S)  # exactly 2 s: accepted
    assert c.rejected == 0
    assert not c.accept(12 * S + 1, 10 * S)
    assert (c.rejected, c.last_skew_ns) == (1, 2 * S + 1)
    assert not c.accept(7_900 * MS, 10 * S)
    assert (c.rejected, c.last_skew_ns) == (2, -2_100 * MS)
