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


# Every leap second since the GPS epoch, from IERS Bulletin C, written out here independently
# of the module's table: (UTC day that starts with the new offset, GPST - UTC from then on).
# Each is inserted as 23:59:60 UTC at the end of the day before.
LEAPS_SINCE_1980 = [
    (dt.datetime(1981, 7, 1), 1),
    (dt.datetime(1982, 7, 1), 2),
    (dt.datetime(1983, 7, 1), 3),
    (dt.datetime(1985, 7, 1), 4),
    (dt.datetime(1988, 1, 1), 5),
    (dt.datetime(1990, 1, 1), 6),
    (dt.datetime(1991, 1, 1), 7),
    (dt.datetime(1992, 7, 1), 8),
    (dt.datetime(1993, 7, 1), 9),
    (dt.datetime(1994, 7, 1), 10),
    (dt.datetime(1996, 1, 1), 11),
    (dt.datetime(1997, 7, 1), 12),
    (dt.datetime(1999, 1, 1), 13),
    (dt.datetime(2006, 1, 1), 14),
    (dt.datetime(2009, 1, 1), 15),
    (dt.datetime(2012, 7, 1), 16),
    (dt.datetime(2015, 7, 1), 17),
    (dt.datetime(2017, 1, 1), 18),
]


def _week_tow(gpst: dt.datetime) -> tuple[int, float]:
    """A naive GPST datetime to (week, tow), by plain datetime arithmetic."""
    seconds = (gpst - dt.datetime(1980, 1, 6)).total_seconds()
    week, tow = divmod(seconds, 604800.0)
    return int(week), tow


def _around_leap(day: dt.datetime, n: int) -> list[tuple[dt.datetime, dt.datetime, bool]]:
    """(GPST instant, its UTC label, inside the inserted second) just before, at and after
    the leap second that starts ``day`` with GPST - UTC = n. UTC labels up to 23:59:59 of the
    day before are n - 1 s behind GPST, labels from 00:00:00 of ``day`` n s behind; the
    inserted second 23:59:60.x lies between and is labelled 23:59:59.x (repeated)."""
    sec = dt.timedelta(seconds=1)
    half = dt.timedelta(milliseconds=500)
    rows = []
    for utc in (day - 2 * sec, day - sec, day - sec + half):  # 23:59:58, 23:59:59, 23:59:59.5
        rows.append((utc + (n - 1) * sec, utc, False))
    rows.append((day - sec + (n - 1) * sec + sec, day - sec, True))  # 23:59:60.0
    rows.append((day - sec + (n - 1) * sec + sec + half, day - sec + half, True))  # 23:59:60.5
    for utc in (day, day + half, day + sec, day + 2 * sec):  # 00:00:00 ... 00:00:02
        rows.append((utc + n * sec, utc, False))
    return rows


def test_utc_from_gpst_around_every_leap_second_since_1980():
    wrong = []
    for day, n in LEAPS_SINCE_1980:
        for gpst, utc, in_leap in _around_leap(day, n):
            week, tow = _week_tow(gpst)
            got = tb.utc_from_gpst(week, tow)
            if got != utc or tb.gpst_in_leap_second(week, tow) != in_leap:
                wrong.append((str(gpst), str(utc), str(got)))
    assert wrong == []


def test_utc_from_gpst_before_the_first_leap_second_is_gpst():
    # GPST and UTC coincided at the GPS epoch and until 1981-07-01
    assert tb.utc_from_gpst(0, 0.0) == dt.datetime(1980, 1, 6)
    assert tb.utc_from_gpst(*_week_tow(dt.datetime(1981, 6, 30, 23, 59, 59))) == dt.datetime(
        1981, 6, 30, 23, 59, 59
    )


def test_the_2015_leap_second_as_the_issue_saw_it():
    # GPS week 1851 starts 2015-06-28; tow 259200 s is 2015-07-01 00:00:00 GPST, and
    # GPST - UTC went from 16 to 17 s at 2015-07-01 00:00:00 UTC (= 00:00:17 GPST).
    assert _week_tow(dt.datetime(2015, 7, 1)) == (1851, 259200.0)
    labels = [tb.utc_from_gpst(1851, tow) for tow in (259215.0, 259216.0, 259217.0, 259218.0)]
    assert [t.strftime("%H:%M:%S") for t in labels] == [
        "23:59:59",  # 23:59:59 UTC
        "23:59:59",  # 23:59:60 UTC, the inserted second (a datetime has no second 60)
        "00:00:00",
        "00:00:01",
    ]
    assert [tb.gpst_in_leap_second(1851, tow) for tow in (259215.0, 259216.0, 259217.0)] == [
        False,
        True,
        False,
    ]


@given(st.integers(0, 1000), st.sampled_from(LEAPS_SINCE_1980))
def test_gpst_from_utc_inverts_utc_from_gpst_off_the_leap_second(k, leap):
    # instants up to 1000 s either side of each leap (the inserted second itself has no
    # datetime of its own, so it is left out)
    day, n = leap
    for utc in (day + dt.timedelta(seconds=k), day - dt.timedelta(seconds=k + 1)):
        week, tow = tb.gpst_from_utc(utc)
        assert tb.utc_from_gpst(week, tow) == utc
        assert tb.leap_seconds(utc) == (n if utc >= day else n - 1)
