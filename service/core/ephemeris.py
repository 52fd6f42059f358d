"""Ephemeris store: entry checks, selection by toe, health and age, a bound on what is
held, and an atomically persisted copy.

Selection follows common receiver practice for BDS (ICD B1I 5.2.4.9: ephemerides are
referenced to t_oe and updated hourly): the healthy set whose t_oe is nearest to the
requested time, within ``max_age_s``. Every ephemeris, whatever its source (RINEX, decoded
D1/D2, RTCM 1042, the persisted store), enters through :meth:`EphemerisStore.add`, which
refuses a set that :func:`ephemeris_problem` finds fault with.

The store is bounded by design, so that months of unattended running cost what an hour
does: at most MAX_SETS_PER_PRN sets per satellite (the oldest t_oe goes first), and
:meth:`EphemerisStore.prune` keeps only the sets of the last KEEP_S (see there).
Selection is a binary search in each satellite's sets sorted by t_oe.

The receiver's own sets (decoded from its subframes, ``source == "subframes"``) are the
reference for the others (RINEX, RTCM 1042 from a caster, the persisted store): a set of one
kind that puts the satellite more than CONSISTENCY_MAX_M from where a set of the other kind
held for it does (positions and clocks compared at the midpoint of their t_oe, sets at most
CONSISTENCY_WINDOW_S apart) loses: an outside set is refused, an outside set held is dropped
when the receiver's own arrives. The loser is never selected nor saved; each conflict is
counted and logged (rate-limited).
"""

from __future__ import annotations

import dataclasses
import datetime as dt
import json
import logging
import math
import os
import time
from bisect import bisect_left
from collections.abc import Callable, Iterable, Iterator, Sequence
from numbers import Real
from pathlib import Path

import numpy as np

from service.core.constants import C_M_S, WEEK_S
from service.core.counters import Counters
from service.core.errors import BdsfixError, EphemerisError
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.ratelog import RateLimitedLog
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem, constants_of, prn_number, system_of
from service.core.timebase import diff_s
from service.core.types import Ephemeris, KlobucharParams

log = logging.getLogger(__name__)

STORE_VERSION = 1
ARRAYS_CACHE_SIZE = 256
STORE_FILE_MODE = 0o600
"""Mode of the saved store whatever the umask (it lives in the daemon's 0700 state
directory)."""
STORE_WRITE_BATCH = 64
"""Sets JSON-encoded per call when saving: each call holds the interpreter lock briefly, so
a save in a background thread never stalls the receiver loop."""

KEEP_S = 86_400.0
""":meth:`EphemerisStore.prune` keeps a satellite's sets whose t_oe is less than this [s]
before the reference time (a day: BDS uploads a new set every hour, ICD B1I 5.2.4.9, and
a receiver selects one within ``max_age_s``, 2 h by default)."""
MAX_SETS_PER_PRN = 64
"""Most sets held per satellite (the oldest t_oe goes first): a day before and a day after
the reference at one set an hour (49) with room for off-hour uploads. This bounds the
store whatever the times it is fed."""

# The windows below hold for every system of service.core.systems.SYSTEM_CONSTANTS (checked
# in tests/core/test_ephemeris_sanity.py against the GPS and Galileo sets of a real
# navigation file); a system whose orbits fall outside them (Galileo E14/E18, e = 0.16) needs
# its own windows here.
SQRT_A_MIN_SQRT_M = 5000.0
SQRT_A_MAX_SQRT_M = 6700.0
"""Window for sqrt(A) [sqrt(m)]: a from 25,000 to 44,890 km. BDS MEOs have a = 27,906 km
(sqrt(A) 5282.6), IGSOs and GEOs a = 42,164 km (sqrt(A) 6493.4); GPS a = 26,560 km
(5153.6), Galileo 29,600 km (5440.6), QZSS 42,164 km. The BDS broadcast field
(ICD B1I 5.2.4.12: 32 bits unsigned, scale 2^-19) spans 0-8192, far wider."""
ECCENTRICITY_MAX = 0.1
"""Upper bound (exclusive) for e. BDS, GPS and Galileo orbits are near circular (e of order
0.001-0.03; QZSS IGSOs 0.075); the broadcast field (32 bits unsigned, scale 2^-33) spans
0-0.5."""
I0_MAX_RAD = math.radians(70.0)
"""Upper bound for i0 (lower bound 0). IGSOs and MEOs fly at 41-56 deg, GEOs below
10 deg."""
R_MIN_M = 25_000_000.0
R_MAX_M = 45_000_000.0
"""Window for the satellite's geocentric radius at t_oe [m]: GPS 26,560 km, BDS MEO 27,906
km, Galileo 29,600 km and IGSO/GEO 42,164 km, each within a * e plus the C_rc/C_rs
harmonics."""
URA_MAX_M = 6144.0
"""URAI 14 is URA <= 6144 m, URAI 15 is URA > 6144 m (ICD B1I 5.2.4.5): no bound at all,
so such a set is refused. 0.0 means "not stated" (RINEX writers, Table 1) and passes."""
OWN_SOURCES = frozenset({"subframes"})
"""Sources of the receiver's own sets: decoded from its subframes (D1/D2, UBX RXM-SFRBX)."""
CONSISTENCY_WINDOW_S = 4 * 3600.0
CONSISTENCY_MAX_M = 1000.0
"""Two sets of one satellite whose t_oe are at most CONSISTENCY_WINDOW_S apart agree when,
at the midpoint of their t_oe, their positions and their clocks (times c) differ by at most
CONSISTENCY_MAX_M. Measured on the five real nav files (tests/core/test_ephemeris_poison.py):
sets up to 4 h apart differ by at most 17.3 m in position and 6.3 m in clock, while further
apart a GEO's extrapolation reaches hundreds of km (C05, 2019-04-28: 367 km at 10 h); a
t_oe written a week off moves a MEO 4,555 km (Omega_e t_oe). 1 km is 58 times the largest
agreement measured; a smaller error is a range error that RAIM tests (chi-square,
exclusion)."""


def _signed_field_max(bits: int, lsb: float) -> float:
    """Largest magnitude a two's complement field of ``bits`` bits and scale ``lsb`` can
    carry: 2^(bits-1) LSB (its most negative value)."""
    return 2.0 ** (bits - 1) * lsb


@dataclasses.dataclass(frozen=True, slots=True)
class ClockBounds:
    """Largest |value| a system's broadcast can carry for the clock terms and group delays
    (from the field's width and scale factor): a set beyond any of them was not broadcast
    as such, whatever wrote it."""

    af0_s: float
    af1_s_s: float
    af2_s_s2: float
    group_delay_s: float
    """T_GD / TGD1 / TGD2 / BGD: both ``tgd1_s`` and ``tgd2_s``."""


_GPS_CLOCK = ClockBounds(
    # IS-GPS-200 20.3.3.3, Table 20-I/20-III: a_f0 22 bits x 2^-31 s, a_f1 16 bits x 2^-43
    # s/s, a_f2 8 bits x 2^-55 s/s^2, T_GD 8 bits x 2^-31 s (all two's complement)
    af0_s=_signed_field_max(22, 2.0**-31),  # 2^-10 s, 977 us
    af1_s_s=_signed_field_max(16, 2.0**-43),  # 2^-28
    af2_s_s2=_signed_field_max(8, 2.0**-55),  # 2^-48
    group_delay_s=_signed_field_max(8, 2.0**-31),  # 2^-24 s, 59.6 ns
)
CLOCK_BOUNDS: dict[GnssSystem, ClockBounds] = {
    # BDS-SIS-ICD-B1I-3.0 5.2.4.10 (a0 24 bits x 2^-33 s, a1 22 bits x 2^-50 s/s, a2 11 bits
    # x 2^-66 s/s^2) and 5.2.4.8 (TGD1, TGD2 10 bits x 0.1 ns)
    GnssSystem.BDS: ClockBounds(
        af0_s=_signed_field_max(24, 2.0**-33),  # 2^-10 s
        af1_s_s=_signed_field_max(22, 2.0**-50),  # 2^-29
        af2_s_s2=_signed_field_max(11, 2.0**-66),  # 2^-56
        group_delay_s=_signed_field_max(10, 1e-10),  # 51.2 ns
    ),
    GnssSystem.GPS: _GPS_CLOCK,
    # IS-QZSS-PNT 4.1.2: the LNAV subframes of IS-GPS-200, the same fields
    GnssSystem.QZS: _GPS_CLOCK,
    # Galileo OS SIS ICD 5.1.3 (af0 31 bits x 2^-34 s, af1 21 bits x 2^-46 s/s, af2 6 bits x
    # 2^-59 s/s^2; I/NAV and F/NAV alike) and 5.1.5 (BGD 10 bits x 2^-32 s)
    GnssSystem.GAL: ClockBounds(
        af0_s=_signed_field_max(31, 2.0**-34),  # 2^-4 s, 62.5 ms
        af1_s_s=_signed_field_max(21, 2.0**-46),  # 2^-26
        af2_s_s2=_signed_field_max(6, 2.0**-59),  # 2^-54
        group_delay_s=_signed_field_max(10, 2.0**-32),  # 2^-23 s, 119 ns
    ),
}
"""Per system, the bounds of the ``clock`` and ``group_delay`` checks of
:func:`ephemeris_problem`. The real recordings reach at most: af0 2^-10 s (BDS C58, unhealthy,
2024; the bound is inclusive), 7.0 ms (Galileo E09), 0.81 ms (GPS); |TGD| 48 ns (BDS),
47 ns (Galileo BGD), 20 ns (GPS)."""
TOC_TOE_MAX_S = 4 * 3600.0
"""Most |t_oc - t_oe| [s] (across the week's end) of a set: each system broadcasts its clock
and orbit for one epoch (BDS 5.2.4.9-10, GPS 20.3.4.5, Galileo 5.1.2-3); every set of the
real recordings has t_oc = t_oe. A clock reference hours from the orbit's is a damaged field
(a t_oc wrapped into the week, a field of another set)."""

LOG_INTERVAL_S = 60.0
"""A refusal log line per (PRN, check) at most this often (wall clock); the next says how
many refusals it stood for."""

_NUMERIC_FIELDS = tuple(
    f.name for f in dataclasses.fields(Ephemeris) if f.name not in ("prn", "source", "ura_m")
)


@dataclasses.dataclass(frozen=True, slots=True)
class EphemerisProblem:
    """Why an ephemeris is refused: ``check`` names the test (a counter key), ``detail``
    says what was found, for the log."""

    check: str
    detail: str

    def __str__(self) -> str:
        return self.detail


def _finite(value: object) -> bool:
    if type(value) is float:  # nearly every field: without the ABC check of Real (slow)
        return math.isfinite(value)
    try:
        return isinstance(value, Real) and math.isfinite(value)
    except OverflowError:  # an int beyond any float
        return False


def ephemeris_problem(eph: Ephemeris) -> EphemerisProblem | None:
    """What is wrong with ``eph`` for positioning, or None when it is usable.

    Checks, in order, with the ``check`` names used as counter keys:

    - ``prn``: the ID names a supported system (:data:`service.core.systems.SYSTEM_CONSTANTS`)
      and a PRN number within its range (``C01``-``C63``, ``G01``-``G32``, ...);
    - ``unhealthy``: the health field (BDS SatH1, ICD B1I 5.2.4.6; GPS SV health,
      IS-GPS-200 20.3.3.3.1.4) is not 0;
    - ``not_finite``: a numeric field is not a finite number;
    - ``time_of_week``: t_oe or t_oc is not a time of the set's week, 0 <= t < 604800 s
      (ICD B1I 5.2.4.9 and 5.2.4.10: seconds of the BDT week; the 17-bit fields, 8 s LSB,
      could carry up to 1,048,568 s). A set written as week - 1 with t_oe + 604800 s is the
      same instant, but the user algorithm's Omega_e t_oe term (5.2.4.12, Table 5-11) then
      turns the orbit by Omega_e 604800 s (0.16 rad mod 2 pi): 4,555 km off for a MEO. It is
      refused, not normalised: its writer does not follow the ICD, so its other fields
      deserve no more trust, and the receiver's own sets (or a conforming source) cover the
      satellite;
    - ``toc_toe``: t_oc is within TOC_TOE_MAX_S of t_oe (across the week's end): a set's clock
      and orbit are referenced to one epoch (5.2.4.9-5.2.4.10);
    - ``ura``: URA is the unusable class URAI 15, > 6144 m, or not a number (5.2.4.5);
    - ``sqrt_a``, ``eccentricity``, ``inclination``: sqrt(A), e and i0 (ephemeris
      parameters, 5.2.4.12) within the windows of this module's constants;
    - ``clock``: |af0|, |af1|, |af2| at most what the system's broadcast fields can carry
      (:data:`CLOCK_BOUNDS`: BDS ICD B1I 5.2.4.10, a0 < 2^-10 s; IS-GPS-200 20.3.3.3, a_f0 <
      2^-10 s; Galileo OS SIS ICD 5.1.3, af0 < 2^-4 s; af1 and af2 likewise). A set beyond
      them was never broadcast as such, and one absurd clock term would otherwise spoil
      every epoch's solution, not one satellite's range;
    - ``group_delay``: |tgd1|, |tgd2| (BDS TGD1/TGD2, 5.2.4.8; GPS T_GD, 20.3.3.3.3.2;
      Galileo BGD, 5.1.5) within their field's range, likewise;
    - ``radius``: the position at t_oe by the user algorithm of the satellite's system
      (5.2.4.12, Table 5-11, and the BeiDou GEO algorithm for C01-C05/C59-C63;
      :func:`service.core.orbit.sat_pos_clock`) is finite and its radius within
      [R_MIN_M, R_MAX_M]; this also catches absurd harmonic corrections.

    Computed with numpy warnings silenced, so a bad set never prints a RuntimeWarning.
    """
    problem = _field_problem(eph)
    if problem is not None:
        return problem
    return _radius_problem(float(radii_at_toe_m([eph])[0]))


def _radius_problem(r_m: float) -> EphemerisProblem | None:
    """The ``radius`` check of :func:`ephemeris_problem` on the radius at t_oe."""
    if not R_MIN_M <= r_m <= R_MAX_M:  # also NaN
        return EphemerisProblem(
            "radius",
            f"radius at toe {r_m / 1e3:.0f} km outside "
            f"[{R_MIN_M / 1e3:.0f}, {R_MAX_M / 1e3:.0f}] km",
        )
    return None


def radii_at_toe_m(ephs: Sequence[Ephemeris]) -> np.ndarray:
    """|position| [m] of each set at its own t_oe by its system's user algorithm (the
    ``radius`` check of :func:`ephemeris_problem`), in one vectorised call; sets that pass
    the other checks only (a set refused by them may not compute)."""
    with np.errstate(all="ignore"):
        arrays = EphemerisArrays.from_ephemerides(ephs)
        pos_m, _ = sat_pos_clock(arrays, arrays.week, arrays.toe_sow_s)
        return np.asarray(np.linalg.norm(pos_m, axis=-1))


def _field_problem(eph: Ephemeris) -> EphemerisProblem | None:
    """:func:`ephemeris_problem`'s checks before the radius one, in its order."""
    try:
        prn_max = constants_of(eph.prn).prn_max
        number = prn_number(eph.prn)
    except (BdsfixError, ValueError, TypeError, IndexError):
        prn_max, number = 0, 0
    if not (isinstance(eph.prn, str) and 1 <= number <= prn_max):
        supported = ", ".join(s.name for s in SYSTEM_CONSTANTS)
        return EphemerisProblem(
            "prn", f"PRN {eph.prn!r} is not a satellite ID of a supported system ({supported})"
        )
    if _finite(eph.health) and eph.health != 0:
        return EphemerisProblem("unhealthy", f"unhealthy (SatH1={eph.health})")
    for name in _NUMERIC_FIELDS:
        value = getattr(eph, name)
        if not _finite(value):
            return EphemerisProblem("not_finite", f"{name} is {value!r}, not a finite number")
    for name in ("toe_sow_s", "toc_sow_s"):
        if not 0.0 <= getattr(eph, name) < WEEK_S:
            return EphemerisProblem(
                "time_of_week",
                f"{name} {getattr(eph, name):g} s is not a time of week [0, {WEEK_S:g}) s",
            )
    toc_toe_s = (eph.toc_sow_s - eph.toe_sow_s + WEEK_S / 2) % WEEK_S - WEEK_S / 2
    if abs(toc_toe_s) > TOC_TOE_MAX_S:
        return EphemerisProblem(
            "toc_toe",
            f"toc {eph.toc_sow_s:g} s is {toc_toe_s / 3600:+.1f} h from toe {eph.toe_sow_s:g} s "
            f"(at most {TOC_TOE_MAX_S / 3600:g} h)",
        )
    ura_m = eph.ura_m
    if not (isinstance(ura_m, Real) and 0.0 <= ura_m <= URA_MAX_M):
        return EphemerisProblem(
            "ura", f"URA {ura_m!r} m: no usable accuracy (URAI 15 is > {URA_MAX_M:g} m)"
        )
    if not SQRT_A_MIN_SQRT_M <= eph.sqrt_a_sqrt_m <= SQRT_A_MAX_SQRT_M:
        return EphemerisProblem(
            "sqrt_a",
            f"sqrtA {eph.sqrt_a_sqrt_m:g} sqrt(m) outside "
            f"[{SQRT_A_MIN_SQRT_M:g}, {SQRT_A_MAX_SQRT_M:g}]",
        )
    if not 0.0 <= eph.e < ECCENTRICITY_MAX:
        return EphemerisProblem("eccentricity", f"e {eph.e:g} outside [0, {ECCENTRICITY_MAX:g})")
    if not 0.0 <= eph.i0_rad <= I0_MAX_RAD:
        return EphemerisProblem(
            "inclination",
            f"i0 {math.degrees(eph.i0_rad):.2f} deg outside [0, {math.degrees(I0_MAX_RAD):g}] deg",
        )
    bounds = CLOCK_BOUNDS.get(system_of(eph.prn))
    if bounds is not None:
        for name, value, bound in (
            ("af0", eph.af0_s, bounds.af0_s),
            ("af1", eph.af1_s_s, bounds.af1_s_s),
            ("af2", eph.af2_s_s2, bounds.af2_s_s2),
        ):
            if not abs(value) <= bound:
                return EphemerisProblem(
                    "clock",
                    f"{name} {value:g} beyond what the broadcast can carry (|{name}| <= {bound:g})",
                )
        for name, value in (("tgd1", eph.tgd1_s), ("tgd2", eph.tgd2_s)):
            if not math.isfinite(value):  # (SBF's do-not-use, e.g. a GALNav BGD)
                return EphemerisProblem("group_delay", f"{name} not available")
            if not abs(value) <= bounds.group_delay_s:
                return EphemerisProblem(
                    "group_delay",
                    f"{name} {value:g} s beyond what the broadcast can carry "
                    f"(|{name}| <= {bounds.group_delay_s:g} s)",
                )
    return None


def _disagreements(
    eph: Ephemeris, others: Sequence[Ephemeris]
) -> list[tuple[float, float, int, float]]:
    """Per set of ``others``: how far it and ``eph`` put the satellite [m] and its clock
    (times c) [m] at the midpoint of their t_oe, and that time (BDT week, sow); by the user
    algorithm (ICD B1I 5.2.4.10, 5.2.4.12) in one vectorised call."""
    t_e = eph.week * WEEK_S + eph.toe_sow_s
    mid_s = np.array([0.5 * (t_e + o.week * WEEK_S + o.toe_sow_s) for o in others])
    weeks = np.floor(mid_s / WEEK_S)
    sows = mid_s - weeks * WEEK_S
    arrays = EphemerisArrays.from_ephemerides([eph] * len(others) + list(others))
    with np.errstate(all="ignore"):
        pos_m, clk_s = sat_pos_clock(arrays, np.tile(weeks, 2), np.tile(sows, 2))
    n = len(others)
    d_pos = np.linalg.norm(pos_m[:n] - pos_m[n:], axis=1)
    d_clk = np.abs(clk_s[:n] - clk_s[n:]) * C_M_S
    return [
        (float(p), float(c), int(w), float(t))
        for p, c, w, t in zip(d_pos, d_clk, weeks, sows, strict=True)
    ]


_Key = tuple[int, float]  # (BDT week, t_oe [s of week])


class _Sets:
    """One satellite's sets: by (week, t_oe) in insertion order (which breaks ties between
    equally near sets, as it always has) and sorted by t_oe for the binary search."""

    __slots__ = ("by_key", "order", "seq")

    def __init__(self) -> None:
        self.by_key: dict[_Key, Ephemeris] = {}
        self.order: list[tuple[float, int, _Key]] = []  # (t_oe [s since BDT 0], seq, key)
        self.seq = 0

    def put(self, eph: Ephemeris) -> None:
        key = (eph.week, eph.toe_sow_s)
        if key not in self.by_key:
            self.seq += 1
            t_s = eph.week * WEEK_S + eph.toe_sow_s
            self.order.insert(bisect_left(self.order, (t_s, self.seq)), (t_s, self.seq, key))
        self.by_key[key] = eph

    def remove(self, key: _Key) -> None:
        """Drop the set of ``key``."""
        del self.by_key[key]
        self.order = [o for o in self.order if o[2] != key]

    def near(self, t_s: float, span_s: float) -> list[Ephemeris]:
        """The sets whose t_oe [s since BDT 0] is within ``span_s`` of ``t_s``."""
        order = self.order
        lo = bisect_left(order, (t_s - span_s,))
        hi = bisect_left(order, (t_s + span_s, math.inf))
        return [self.by_key[key] for _, _, key in order[lo:hi]]

    def drop_oldest(self, n: int) -> int:
        """Drop the ``n`` sets with the oldest t_oe; returns ``n``."""
        for _, _, key in self.order[:n]:
            del self.by_key[key]
        del self.order[:n]
        return n

    def drop_until(self, t_s: float) -> int:
        """Drop the sets whose t_oe [s since BDT 0] is at or before ``t_s``; returns how many."""
        return self.drop_oldest(bisect_left(self.order, (t_s, math.inf)))

    def nearest(self, bdt_week: int, bdt_sow_s: float) -> Ephemeris:
        """The set whose t_oe is nearest the BDT time (the earliest received on a tie)."""
        order = self.order
        i = bisect_left(order, (bdt_week * WEEK_S + bdt_sow_s,))
        cands = []
        if i < len(order):
            cands.append(order[i])  # the first at or after the time (lowest seq of its t_oe)
        if i > 0:
            cands.append(order[bisect_left(order, (order[i - 1][0],))])  # the last t_oe before
        return min(
            (self.by_key[key] for _, _, key in sorted(cands, key=lambda o: o[1])),
            key=lambda e: abs(diff_s(bdt_week, bdt_sow_s, e.week, e.toe_sow_s)),
        )


@dataclasses.dataclass(frozen=True, slots=True)
class StoreSnapshot:
    """What the store holds at one moment, immutable: taken in the receiver loop (a tuple of
    references, cheap) and written by :func:`write_store` in any thread."""

    ephemerides: tuple[Ephemeris, ...]
    iono: KlobucharParams | None = None

    def __len__(self) -> int:
        return len(self.ephemerides)


class EphemerisStore:
    """Ephemerides per PRN plus the latest broadcast ionosphere coefficients."""

    def __init__(
        self,
        max_age_s: float = 7200.0,
        clock: Callable[[], float] = time.monotonic,
        max_sets_per_prn: int = MAX_SETS_PER_PRN,
    ) -> None:
        self.max_age_s = max_age_s
        self.max_sets_per_prn = max_sets_per_prn
        self._by_prn: dict[str, _Sets] = {}
        self.iono: KlobucharParams | None = None
        self.refused = 0
        self.refused_by_reason = Counters()
        """Refusals per :class:`EphemerisProblem` check name."""
        self.last_refusal: EphemerisProblem | None = None
        """Why the latest refused set was refused."""
        self.evicted = 0
        """Sets dropped to keep MAX_SETS_PER_PRN (not counting :meth:`prune`)."""
        self.dropped_inconsistent = 0
        """Outside sets dropped because the receiver's own set contradicted them."""
        self.dropped_unhealthy = 0
        """Held sets dropped because the same set (PRN, week, t_oe) came again marked
        unhealthy (:meth:`add`)."""
        self._refusal_log = RateLimitedLog(log, LOG_INTERVAL_S, clock)  # per (PRN, check)
        # column form of recently used ephemeris sets (the same set serves many epochs);
        # keyed by object identity, the entry holds the objects so identities stay unique
        self._arrays: dict[tuple[int, ...], tuple[tuple[Ephemeris, ...], EphemerisArrays]] = {}
        # per satellite, the last answer of select() and the span of times [s since BDT
        # week 0] over which it cannot change (select_span), with the max_age_s it holds
        # for; emptied whenever the sets change
        self._spans: dict[str, tuple[Ephemeris, float, float, float]] = {}

    def __len__(self) -> int:
        return sum(len(v.order) for v in self._by_prn.values())

    @property
    def prns(self) -> list[str]:
        return sorted(self._by_prn)

    def add(self, eph: Ephemeris, radius_m: float | None = None) -> bool:
        """Hold ``eph`` unless :func:`ephemeris_problem` refuses it or a held set of the
        receiver's own contradicts it (check ``inconsistent``, see :meth:`_settle`); returns
        whether it was kept. A refused set is counted (``refused``, ``refused_by_reason``)
        and logged, and never replaces a set already held, with one exception: a set
        refused as ``unhealthy`` drops the held set of the same (week, t_oe)
        (``dropped_unhealthy``), since the satellite has since flagged that very set (Galileo
        raises HS/DVS in I/NAV word type 5 without a new IODnav, OS SIS ICD 5.1.9.3; GPS and
        BeiDou may do the same with their health words). A set with the (week, t_oe) of
        one held replaces it, except an outside copy of an own set (kept as it is, True);
        beyond ``max_sets_per_prn`` the satellite's oldest t_oe goes (``evicted``).
        ``radius_m``: the set's radius at t_oe from :meth:`add_all`, which has run the other
        checks of :func:`ephemeris_problem` and found nothing (None: every check here)."""
        problem = ephemeris_problem(eph) if radius_m is None else _radius_problem(radius_m)
        sets = self._by_prn.get(eph.prn)
        if problem is None and sets is not None:
            problem = self._settle(sets, eph)
            if problem is None and eph.source not in OWN_SOURCES:
                held = sets.by_key.get((eph.week, eph.toe_sow_s))
                if held is not None and held.source in OWN_SOURCES:
                    return True  # the same set, and the receiver's own copy stays
        if problem is not None:
            self.refused += 1
            self.refused_by_reason[problem.check] += 1
            self.last_refusal = problem
            self._log_refusal(eph, problem)
            key = (eph.week, eph.toe_sow_s)
            if problem.check == "unhealthy" and sets is not None and key in sets.by_key:
                sets.remove(key)  # never use a set its satellite now flags
                if not sets.order:
                    del self._by_prn[eph.prn]
                self._spans.pop(eph.prn, None)
                self.dropped_unhealthy += 1
            return False
        if sets is None:
            sets = self._by_prn[eph.prn] = _Sets()
        sets.put(eph)
        self._spans.pop(eph.prn, None)
        excess = len(sets.order) - self.max_sets_per_prn
        if excess > 0:
            self.evicted += sets.drop_oldest(excess)
        return True

    def _settle(self, sets: _Sets, eph: Ephemeris) -> EphemerisProblem | None:
        """Compare ``eph`` with the held sets of the other kind (own / outside, see the
        module docstring) within CONSISTENCY_WINDOW_S. An outside ``eph`` that a held own set
        contradicts is refused (the problem, check ``inconsistent``); an own ``eph`` drops
        the outside sets it contradicts (counted ``dropped_inconsistent``, logged)."""
        own = eph.source in OWN_SOURCES
        t_s = eph.week * WEEK_S + eph.toe_sow_s
        others = [
            h for h in sets.near(t_s, CONSISTENCY_WINDOW_S) if (h.source in OWN_SOURCES) != own
        ]
        if not others:
            return None
        worst = None
        for held, (pos_m, clk_m, week, sow) in zip(
            others, _disagreements(eph, others), strict=True
        ):
            if not (pos_m > CONSISTENCY_MAX_M or clk_m > CONSISTENCY_MAX_M):
                continue  # they agree (NaN, which entry-checked sets do not give, is no proof)
            what = (
                f"{pos_m / 1e3:.1f} km in position, {clk_m / 1e3:.1f} km in clock at BDT "
                f"week {week} sow {sow:.0f}"
            )
            if not own:
                size_m = max(pos_m, clk_m)
                if worst is None or size_m > worst[0]:
                    worst = (size_m, held, what)
                continue
            sets.remove((held.week, held.toe_sow_s))
            self._spans.pop(eph.prn, None)
            self.dropped_inconsistent += 1
            self._refusal_log.warning(
                (str(eph.prn), "inconsistent"),
                "dropped ephemeris %s week %s toe %s from %s: the receiver's own set (week %s "
                "toe %s) puts the satellite elsewhere: %s",
                held.prn,
                held.week,
                held.toe_sow_s,
                held.source,
                eph.week,
                eph.toe_sow_s,
                what,
            )
        if worst is None:
            return None
        held = worst[1]
        return EphemerisProblem(
            "inconsistent",
            f"the receiver's own set (week {held.week} toe {held.toe_sow_s}) puts the "
            f"satellite elsewhere: {worst[2]}",
        )

    def _log_refusal(self, eph: Ephemeris, problem: EphemerisProblem) -> None:
        """One line per (PRN, check) per LOG_INTERVAL_S: WARNING, or INFO for SatH1 != 0
        (a satellite flagged unhealthy is normal operation, not damaged data)."""
        self._refusal_log.log(
            logging.INFO if problem.check == "unhealthy" else logging.WARNING,
            (str(eph.prn), problem.check),
            "refused ephemeris %s week %s toe %s from %s: %s",
            eph.prn,
            eph.week,
            eph.toe_sow_s,
            eph.source,
            problem,
        )

    def arrays(self, ephs: Sequence[Ephemeris]) -> EphemerisArrays:
        """``EphemerisArrays.from_ephemerides(ephs)``, memoised for repeated sets."""
        key = tuple(map(id, ephs))
        hit = self._arrays.get(key)
        if hit is not None:
            return hit[1]
        if len(self._arrays) >= ARRAYS_CACHE_SIZE:
            self._arrays.clear()
        arr = EphemerisArrays.from_ephemerides(ephs)
        self._arrays[key] = (tuple(ephs), arr)
        return arr

    def add_all(self, ephs: Iterable[Ephemeris]) -> int:
        """:meth:`add` of each set in turn; returns how many were kept. The checks of
        :func:`ephemeris_problem` run first on every set, the radius one for all the sets
        that pass the others in one vectorised call (:func:`radii_at_toe_m`): one numpy
        call per nav file instead of one per set (a day's mixed nav file: 0.1 ms a set)."""
        ephs = list(ephs)
        checked = [e for e in ephs if _field_problem(e) is None]
        radius = dict(zip(map(id, checked), radii_at_toe_m(checked).tolist(), strict=True))
        return sum(self.add(e, radius.get(id(e))) for e in ephs)

    def select(self, prn: str, bdt_week: int, bdt_sow_s: float) -> Ephemeris | None:
        """Healthy ephemeris of ``prn`` with t_oe nearest the BDT time, or None if too old.

        A binary search among the satellite's sets: the cost does not grow with them; an
        epoch inside the span of the satellite's previous answer (:meth:`select_span`) gets
        that answer without the search."""
        hit = self._spans.get(prn)
        t_s = bdt_week * WEEK_S + bdt_sow_s
        if hit is not None and hit[1] < t_s < hit[2] and hit[3] == self.max_age_s:
            return hit[0]
        eph, lo, hi = self.select_span(prn, bdt_week, bdt_sow_s)
        if eph is not None:
            self._spans[prn] = (eph, lo, hi, self.max_age_s)
        return eph

    def _select(self, prn: str, bdt_week: int, bdt_sow_s: float) -> Ephemeris | None:
        sets = self._by_prn.get(prn)
        if not sets:
            return None
        best = sets.nearest(bdt_week, bdt_sow_s)
        if abs(diff_s(bdt_week, bdt_sow_s, best.week, best.toe_sow_s)) > self.max_age_s:
            return None
        return best

    def select_span(
        self, prn: str, bdt_week: int, bdt_sow_s: float
    ) -> tuple[Ephemeris | None, float, float]:
        """:meth:`select`, and the open span (lo, hi) of times [s since BDT week 0, sow]
        around the given one over which :meth:`select` certainly returns the same set: nearer
        its t_oe than either neighbouring t_oe and within ``max_age_s`` (less a microsecond
        each side, against rounding). A batch of epochs asks again only when it leaves the
        span. (nan, nan) with None."""
        eph = self._select(prn, bdt_week, bdt_sow_s)
        if eph is None:
            return None, math.nan, math.nan
        order = self._by_prn[prn].order
        t_e = eph.week * WEEK_S + eph.toe_sow_s
        j = bisect_left(order, (t_e,))
        lo, hi = t_e - self.max_age_s, t_e + self.max_age_s
        if j > 0:
            lo = max(lo, 0.5 * (order[j - 1][0] + t_e))
        if j + 1 < len(order):
            hi = min(hi, 0.5 * (t_e + order[j + 1][0]))
        return eph, lo + 1e-6, hi - 1e-6

    def prune(self, bdt_week: int, bdt_sow_s: float, keep_s: float = KEEP_S) -> int:
        """Keep what can still be used at the given BDT time (the latest measurement): per
        satellite, the sets whose t_oe is less than ``keep_s`` before that time or before the
        satellite's newest t_oe, whichever is earlier. Returns how many sets were dropped.

        BDS uploads a set every hour (ICD B1I 5.2.4.9) and a receiver uses the one nearest
        its time within ``max_age_s``; with ``keep_s`` a day, each satellite keeps its last
        day (24 hourly sets) however long the history. The newest t_oe guards against one
        bad time tag: a satellite always keeps its latest day, and sets ahead of the time
        (a day's navigation file loaded at start) stay until the count bound evicts them."""
        t_s = bdt_week * WEEK_S + bdt_sow_s
        dropped = 0
        self._spans.clear()
        for prn in list(self._by_prn):
            sets = self._by_prn[prn]
            dropped += sets.drop_until(min(t_s, sets.order[-1][0]) - keep_s)
            if not sets.order:
                del self._by_prn[prn]
        return dropped

    def all(self) -> list[Ephemeris]:
        """Every set held: by PRN, each satellite's in the order first received."""
        return [e for prn in self.prns for e in self._by_prn[prn].by_key.values()]

    # --- persistence -------------------------------------------------------------------
    def snapshot(self) -> StoreSnapshot:
        """The content to save, taken in O(sets) reference copies (no encoding)."""
        return StoreSnapshot(tuple(self.all()), self.iono)

    def save(self, path: str | Path) -> None:
        """Write the store now (see :func:`write_store`)."""
        write_store(path, self.snapshot())

    @classmethod
    def load(cls, path: str | Path, max_age_s: float = 7200.0) -> EphemerisStore:
        """Read a store written by :meth:`save`. A file that cannot be read, is not JSON or
        is not shaped as :meth:`save` writes it (a list, ``ephemerides`` not a list of
        objects, a field missing, unknown or of the wrong type) raises EphemerisError.

        Each set goes through :meth:`add`, so one that fails the entry checks is refused
        and logged, and the rest are kept."""
        store = cls(max_age_s=max_age_s)
        try:
            doc = json.loads(Path(path).read_text(encoding="utf-8"))
            if not isinstance(doc, dict):
                raise ValueError(f"a JSON {type(doc).__name__}, not an object")
            version = doc.get("version")
            if version != STORE_VERSION or isinstance(version, bool):
                raise EphemerisError(f"{path}: unsupported store version {version!r}")
            items = doc.get("ephemerides")
            if not isinstance(items, list):
                raise ValueError(f"'ephemerides' is {type(items).__name__}, not a list")
            ephs = [_ephemeris_from_json(item) for item in items]
            iono = _iono_from_json(doc.get("iono"))
        except (OSError, ValueError, RecursionError) as exc:
            raise EphemerisError(f"{path}: cannot read ephemeris store: {exc}") from exc
        store.add_all(ephs)
        store.iono = iono
        return store

    @staticmethod
    def set_aside(path: str | Path, problem: object) -> Path | None:
        """Move a store that cannot be loaded out of the way, to ``<name>.corrupt-<UTC time>``
        beside it, with one WARNING line; the daemon then starts empty and its next save writes
        a fresh store. Returns the new path (None if the move failed: the line says so)."""
        path = Path(path)
        stamp = dt.datetime.now(dt.UTC).strftime("%Y%m%dT%H%M%SZ")
        target = path.with_name(f"{path.name}.corrupt-{stamp}")
        n = 0
        while target.exists() or target.is_symlink():
            n += 1
            target = path.with_name(f"{path.name}.corrupt-{stamp}-{n}")
        reason = " ".join(str(problem).split())  # one line whatever the message holds
        try:
            os.rename(path, target)
        except OSError as exc:
            log.warning(
                "%s; cannot move it aside (%s); starting with an empty store", reason, exc.strerror
            )
            return None
        log.warning("%s; moved aside to %s; starting with an empty store", reason, target)
        return target


_FIELDS = tuple(f.name for f in dataclasses.fields(Ephemeris))
_REQUIRED = frozenset(
    f.name
    for f in dataclasses.fields(Ephemeris)
    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING
)
_TEXT_FIELDS = frozenset({"prn", "source"})


def _number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _ephemeris_from_json(item: object) -> Ephemeris:
    """One stored set, its shape checked (values are checked by :meth:`EphemerisStore.add`);
    ValueError says what is wrong."""
    if not isinstance(item, dict):
        raise ValueError(f"an ephemeris is a JSON {type(item).__name__}, not an object")
    unknown = item.keys() - set(_FIELDS)
    missing = _REQUIRED - item.keys()
    if unknown or missing:
        raise ValueError(f"ephemeris fields unknown {sorted(unknown)}, missing {sorted(missing)}")
    for name, value in item.items():
        if not (isinstance(value, str) if name in _TEXT_FIELDS else _number(value)):
            raise ValueError(f"ephemeris field {name} is {value!r}")
    return Ephemeris(**{**item, "source": "store"})


def _iono_from_json(io: object) -> KlobucharParams | None:
    if io is None:
        return None
    if not (
        isinstance(io, dict)
        and io.keys() == {"alpha", "beta", "system"}
        and io["system"] in ("BDS", "GPS")
        and all(
            isinstance(io[k], list) and len(io[k]) == 4 and all(map(_number, io[k]))
            for k in ("alpha", "beta")
        )
    ):
        raise ValueError(f"'iono' is not Klobuchar coefficients: {io!r:.80}")
    return KlobucharParams(alpha=tuple(io["alpha"]), beta=tuple(io["beta"]), system=io["system"])


def _store_chunks(snapshot: StoreSnapshot) -> Iterator[str]:
    """The store's JSON document in pieces of STORE_WRITE_BATCH sets."""
    yield f'{{"version": {STORE_VERSION}, "ephemerides": ['
    ephs = snapshot.ephemerides
    for start in range(0, len(ephs), STORE_WRITE_BATCH):
        batch = ephs[start : start + STORE_WRITE_BATCH]
        yield ("" if start == 0 else ", ") + ", ".join(
            json.dumps({name: getattr(e, name) for name in _FIELDS}) for e in batch
        )
    iono = None if snapshot.iono is None else dataclasses.asdict(snapshot.iono)
    yield f'], "iono": {json.dumps(iono)}}}'


def write_store(path: str | Path, snapshot: StoreSnapshot) -> None:
    """Write ``snapshot`` atomically: a temp file in the same directory (created with
    O_EXCL | O_NOFOLLOW and mode STORE_FILE_MODE whatever the umask), fsync, rename, fsync of
    the directory. A crash (even SIGKILL or power loss) leaves either the old or the new
    store, never a torn one; temp files a crash left behind are removed here (one writer at
    a time: the daemon's store writer thread, or the caller)."""
    path = Path(path)
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    for stale in path.parent.glob(f".{path.name}.*"):  # one writer: these are crash debris
        stale.unlink(missing_ok=True)
    import secrets  # here: secrets loads OpenSSL (~10 ms), a cost for every command's start

    tmp = path.parent / f".{path.name}.{secrets.token_hex(6)}"
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
    fd = os.open(tmp, flags, STORE_FILE_MODE)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            os.fchmod(fh.fileno(), STORE_FILE_MODE)
            for chunk in _store_chunks(snapshot):
                fh.write(chunk)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
        dir_fd = os.open(path.parent, os.O_RDONLY)
        try:
            os.fsync(dir_fd)
        finally:
            os.close(dir_fd)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def select_rows(
    store: EphemerisStore,
    prns: Sequence[str],
    rows: Iterable[int],
    bdt_week: int,
    bdt_sow_s: float,
) -> tuple[list[Ephemeris], list[int]]:
    """The ephemerides (:meth:`EphemerisStore.select`) of the rows ``rows`` (indices into
    ``prns``, in their order) that have one, and the indices of those rows. (Of the store it
    asks ``select`` alone, as the solver does.)"""
    ephs: list[Ephemeris] = []
    idx: list[int] = []
    for i in rows:
        e = store.select(prns[i], bdt_week, bdt_sow_s)
        if e is not None:
            ephs.append(e)
            idx.append(i)
    return ephs, idx
