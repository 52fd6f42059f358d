"""BDT/GPST/UTC arithmetic, including week rollover (hypothesis property tests)."""

import datetime as dt

from hypothesis import given
from hypothesis import strategies as st

from service.core import timebase as tb


def test_bdt_epoch_is_gps_week_1356_plus_14s():
    # BDT 0 = 2006-01-01 00:00:00 UTC; GPST - UTC was 14 s then (ICD B1I 4.2).
    week, tow = tb.gpst_from_utc(dt.datetime(2006, 1, 1))
    assert (week, tow) == (1356, 14.0)
    assert tb.gpst_to_bdt(week, tow) == (0, 0.0)


def test_known_leap_seconds():
    assert tb.leap_seconds(dt.datetime(2015, 5, 19, 4)) == 16
    assert tb.leap_seconds(dt.datetime(2021, 6, 10)) == 18


def test_bdt_rollover_at_week_start():
    # GPST week w, tow 5 s is BDT week w-1357, sow 604791 (14 s earlier, previous week)
    assert tb.gpst_to_bdt(2200, 5.0) == (2200 - 1357, 604791.0)
    assert tb.bdt_to_gpst(843, 604795.0) == (2200, 9.0)


@given(st.integers(1356, 4000), st.floats(0, 604800, exclude_max=True))
def test_gpst_bdt_round_trip(week, tow):
    bw, bs = tb.gpst_to_bdt(week, tow)
    assert 0 <= bs < 604800
    gw, gt = tb.bdt_to_gpst(bw, bs)
    assert tb.diff_s(gw, gt, week, tow) == 0 or abs(tb.diff_s(gw, gt, week, tow)) < 1e-9
    assert abs(tb.diff_s(week, tow, bw + 1356, bs) - 14.0) < 1e-9


@given(st.integers(1000, 4000), st.floats(-2e6, 2e6))
def test_normalize_keeps_instant(week, sow):
    w, s = tb.normalize(week, sow)
    assert 0 <= s < 604800
    assert abs(tb.diff_s(w, s, week, sow)) < 1e-6


@given(st.datetimes(dt.datetime(2017, 1, 2), dt.datetime(2040, 1, 1)))
def test_utc_round_trip(t):
    t = t.replace(microsecond=(t.microsecond // 1000) * 1000)
    week, tow = tb.gpst_from_utc(t)
    back = tb.utc_from_gpst(week, tow)
    assert abs((back - t).total_seconds()) < 1e-6
