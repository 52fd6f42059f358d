"""GPS time (GPST), BeiDou time (BDT) and UTC, with week rollover.

BDT started at 2006-01-01 00:00:00 UTC (BDS-SIS-ICD-B1I-3.0, section 4.2); at that instant
GPST - UTC was 14 s, so GPST = BDT + 14 s and GPS week = BDS week + 1356.
All times here are (week, seconds-of-week) pairs; :func:`diff_s` gives differences that stay
exact across week boundaries, which a single float since 1980 would not.
"""

from __future__ import annotations

import bisect
import datetime as dt

import numpy as np

from service.core.constants import WEEK_S

BDT_GPS_WEEK_OFFSET = 1356
BDT_GPST_OFFSET_S = 14.0
GPS_EPOCH = dt.datetime(1980, 1, 6)

# (first UTC day in force, GPST - UTC in seconds from then on): every leap second since the
# GPS epoch (GPST = UTC on 1980-01-06), IERS Bulletin C; each one is inserted as 23:59:60 on
# the day before. The last was announced in Bulletin C 52 (2016): none since, at writing.
_LEAP_TABLE: tuple[tuple[dt.datetime, int], ...] = (
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
)
_LEAP_GPST: tuple[tuple[dt.datetime, dt.datetime, int], ...] = tuple(
    (start + dt.timedelta(seconds=leap - 1), start + dt.timedelta(seconds=leap), leap)
    for start, leap in _LEAP_TABLE
)
"""Per leap second, on the GPST scale: the start and end of the inserted second and GPST -
UTC from its end (worked out once: NMEA asks for them twice an epoch)."""
_LEAP_INSERTED_GPST: tuple[dt.datetime, ...] = tuple(inserted for inserted, _e, _l in _LEAP_GPST)
"""The inserted seconds' starts on the GPST scale, ascending: a binary search finds the
leap second in force at an instant (:mod:`bisect`; the table is in date order)."""


def normalize(week: int, sow_s: float) -> tuple[int, float]:
    """Bring seconds-of-week into [0, 604800), carrying whole weeks."""
    carry = int(sow_s // WEEK_S)
    sow = sow_s - carry * WEEK_S
    if sow >= WEEK_S:  # a tiny negative input rounds up to a whole week
        return week + carry + 1, 0.0
    return week + carry, sow


def diff_s(week_a: int, sow_a: float, week_b: int, sow_b: float) -> float:
    """(a - b) in seconds, for two times on the same scale."""
    return (week_a - week_b) * WEEK_S + (sow_a - sow_b)


def gpst_to_bdt(week: int, tow_s: float) -> tuple[int, float]:
    """GPST (week, tow) to BDT (week, sow)."""
    return normalize(week - BDT_GPS_WEEK_OFFSET, tow_s - BDT_GPST_OFFSET_S)


def gpst_sow_to_bdt_sow(sow_s: float) -> float:
    """A GPST (or GST) time of week [s] as the BDT time of week of the same instant, within
    BDT's week (BDT = GPST - 14 s: the first 14 s of a GPST week are the end of BDT's
    previous one), for a broadcast t_oc held beside its set's t_oe.

    A time outside [0, 604800) s is no time of week (a GPS t_oc field, 16 bits x 16 s,
    reaches 1,048,560 s; Galileo's, 14 bits x 60 s, 983,040 s): it is returned as it is,
    not wrapped into the week, so that the ephemeris store refuses the set (check
    ``time_of_week``) instead of taking a time made of the damage."""
    if not 0.0 <= sow_s < WEEK_S:
        return sow_s
    return (sow_s - BDT_GPST_OFFSET_S) % WEEK_S


def toe_gpst_to_bdt(week: int, toe_s: float) -> tuple[int, float]:
    """A GPS or Galileo set's (week, t_oe) on GPST as its (week, t_oe) on BDT (as every set
    is held): :func:`gpst_to_bdt` when t_oe is a time of the week; a t_oe outside
    [0, 604800) s (a damaged field: GPS LNAV's 16 bits x 16 s reach 1,048,560 s, IS-GPS-200
    20.3.3.4.3 Table 20-III; Galileo's 14 bits x 60 s, 983,040 s; a RINEX record any number)
    is kept as it is, on the BDT week count, not wrapped into a later week, so that the
    ephemeris store refuses the set (check ``time_of_week``) as :func:`gpst_sow_to_bdt_sow`
    does for its t_oc."""
    if not 0.0 <= toe_s < WEEK_S:
        return week - BDT_GPS_WEEK_OFFSET, toe_s
    return gpst_to_bdt(week, toe_s)


def bdt_to_gpst(week: int, sow_s: float) -> tuple[int, float]:
    """BDT (week, sow) to GPST (week, tow)."""
    return normalize(week + BDT_GPS_WEEK_OFFSET, sow_s + BDT_GPST_OFFSET_S)


def gpst_from_datetime(t: dt.datetime) -> tuple[int, float]:
    """A naive datetime read on the GPST scale (as in RINEX epochs) to (week, tow)."""
    delta = t - GPS_EPOCH
    total_s = delta.days * 86400 + delta.seconds
    week, rem = divmod(total_s, WEEK_S)
    return int(week), rem + delta.microseconds * 1e-6


def datetime_from_gpst(week: int, tow_s: float) -> dt.datetime:
    """(week, tow) to a naive datetime on the GPST scale."""
    return GPS_EPOCH + dt.timedelta(weeks=week, seconds=tow_s)


def leap_seconds(utc: dt.datetime) -> int:
    """GPST - UTC [s] at a UTC instant (0 before the first leap second, 1981-07-01)."""
    value = 0
    for start, leap in _LEAP_TABLE:
        if utc >= start:
            value = leap
    return value


def utc_from_gpst(week: int, tow_s: float) -> dt.datetime:
    """GPST (week, tow) to naive UTC datetime.

    The offset is the one in force at the UTC instant, found on the GPST scale: the leap
    second that makes GPST - UTC = n starts at GPST ``day + n - 1`` s (UTC ``day - 1 s``,
    23:59:60) and ends at GPST ``day + n`` s (UTC 00:00:00 of ``day``). A datetime has no
    second 60, so the inserted second itself is given as 23:59:59.x (the second before it
    is repeated, as the Linux kernel does; :func:`gpst_in_leap_second` tells them apart);
    every other instant is exact.
    """
    t = datetime_from_gpst(week, tow_s)
    k = bisect.bisect_right(_LEAP_INSERTED_GPST, t)  # the inserted seconds started by t
    return t - dt.timedelta(seconds=_LEAP_GPST[k - 1][2]) if k else t


def gpst_in_leap_second(week: int, tow_s: float) -> bool:
    """Whether GPST (week, tow) falls in an inserted UTC second (23:59:60.x), which
    :func:`utc_from_gpst` gives as a repeated 23:59:59.x."""
    t = datetime_from_gpst(week, tow_s)
    k = bisect.bisect_right(_LEAP_INSERTED_GPST, t)  # the last one started by t, if any
    return bool(k) and t < _LEAP_GPST[k - 1][1]


J2000_UTC = dt.datetime(2000, 1, 1, 12)
"""J2000.0 (2000-01-01 12:00), here on the UTC scale."""


def gmst_rad(epoch_utc: dt.datetime, dt_s: np.ndarray | float = 0.0) -> np.ndarray:
    """IAU 1982 GMST [rad] at ``epoch_utc + dt_s`` (UT1 taken as UTC), vectorised.

    GMST = 67310.54841 s + (876600 h + 8640184.812866 s) T + 0.093104 s T^2 - 6.2e-6 s T^3,
    T in Julian centuries of UT1 from J2000.0 (Aoki et al. 1982). The whole-day part of the
    epoch is removed before the polynomial so that float64 keeps sub-microsecond precision.
    """
    off = np.asarray(dt_s, dtype=float)
    base_s = (epoch_utc - J2000_UTC).total_seconds()
    t = (base_s + off) / 86400.0 / 36525.0
    # (876600 h) T is exactly the elapsed UT1 seconds: keep only its part modulo one day.
    frac_day_s = np.mod(base_s, 86400.0) + off
    sec = 67310.54841 + frac_day_s + 8640184.812866 * t + 0.093104 * t**2 - 6.2e-6 * t**3
    return np.mod(sec, 86400.0) / 86400.0 * 2.0 * np.pi


def gpst_from_utc(utc: dt.datetime) -> tuple[int, float]:
    """Naive UTC datetime to GPST (week, tow)."""
    return gpst_from_datetime(utc + dt.timedelta(seconds=leap_seconds(utc)))


GST_GPS_WEEK_OFFSET = 1024
"""Galileo System Time week 0 began at GPS week 1024 (1999-08-22; Galileo OS SIS ICD 5.1.2),
and GST runs with GPST (no leap seconds, no offset at this resolution)."""
MIN_SANE_GPS_WEEK = 2296
"""GPS week of 2024-01-07: a system clock before it is taken as unset (a board without a
real-time clock), and a truncated broadcast week is resolved against this week then."""


def nearest_week(week_mod: int, modulus: int, ref_week: int) -> int:
    """The week congruent to ``week_mod`` modulo ``modulus`` nearest ``ref_week`` (the
    rollover of a truncated broadcast week: GPS/QZSS 10 bits, Galileo 12, BDS 13)."""
    base = ref_week - (ref_week - week_mod) % modulus
    return base if ref_week - base <= modulus // 2 else base + modulus


def system_clock_gps_week(now_utc: dt.datetime | None = None) -> int | None:
    """GPS week of the system clock (naive UTC ``now_utc``, default now), or None when the
    clock reads before :data:`MIN_SANE_GPS_WEEK` (unset)."""
    if now_utc is None:
        now_utc = dt.datetime.now(dt.UTC).replace(tzinfo=None)
    week, _ = gpst_from_utc(now_utc)
    return week if week >= MIN_SANE_GPS_WEEK else None
