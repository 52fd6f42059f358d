"""Data that crosses stages: frozen, slotted dataclasses with units in every numeric name.

Per-satellite data travel as numpy columns (docs/architecture.md, "Types").
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from service.core.constants import WEEK_S
from service.core.declines import Declined
from service.core.errors import DecodeError
from service.core.systems import constants_of

FixMode = Literal["fast", "spp", "none"]

UNKNOWN_WEEK = -1
"""``gpst_week`` of an epoch whose source gives only a time of week while no week is known
yet (RTCM MSM or UBX MEASX before any ephemeris or time message): the epoch still reaches
the pipeline, which declines it (``no_time``), and ``gpst_tow_s`` is the time of week."""


@dataclass(frozen=True, slots=True, eq=False)
class MeasurementEpoch:
    """One receive epoch of code measurements, each row a satellite named by its RINEX 3 ID
    (its system: :func:`service.core.systems.system_of`).

    Times are the receiver's time tag on the GPST scale. ``pr_m`` is the full pseudorange or
    NaN when the satellite's transmit time is not yet known; ``frac_pr_m`` is the pseudorange
    modulo c*T with T = ``period_s`` (the code period of the satellite's signal, 0.001 s for
    B1I, or a longer known period such as 0.020), NaN when unknown. ``gpst_week`` is
    :data:`UNKNOWN_WEEK` while the source knows only the time of week. ``time_unc_s`` is how
    well the receiver knows its time tag (1-sigma, e.g. an Android phone's
    BiasUncertaintyNanos; NaN: the source does not say, taken as exact), ``restarted`` that
    the receiver's clock restarted just before this epoch (Android
    HardwareClockDiscontinuityCount).

    Two invariants hold for every epoch, whichever reader built it: its time is a number
    (a non-finite ``gpst_tow_s`` raises :class:`~service.core.errors.DecodeError` at
    construction: a reader checks its time fields first and counts what it skips, so this
    is the backstop, never reached by a reader that does), and each (satellite, signal) pair
    is one row (:meth:`from_columns` keeps the first of repeated pairs; the readers count
    the rows it dropped, e.g. ``android_duplicate_rows``, ``duplicate_records``).
    """

    gpst_week: int
    gpst_tow_s: float
    prn: tuple[str, ...]
    signal: tuple[str, ...]
    pr_m: np.ndarray
    frac_pr_m: np.ndarray
    period_s: np.ndarray
    cn0_dbhz: np.ndarray
    doppler_hz: np.ndarray
    lock_s: np.ndarray
    source: str = ""
    time_unc_s: float = math.nan
    restarted: bool = False

    def __post_init__(self) -> None:
        if not math.isfinite(self.gpst_tow_s):
            raise DecodeError(
                f"{self.source or 'measurement'} epoch at GPS week {self.gpst_week} with time "
                f"of week {self.gpst_tow_s!r}: not a time"
            )

    def __len__(self) -> int:
        return len(self.prn)

    @property
    def week_known(self) -> bool:
        """False while the source knows only the time of week (:data:`UNKNOWN_WEEK`)."""
        return self.gpst_week >= 0

    def rows(self, idx: Sequence[int] | np.ndarray) -> MeasurementEpoch:
        """This epoch with the rows ``idx`` only (in that order); every column taken alike."""
        ii = np.asarray(idx, dtype=np.intp)
        return replace(
            self,
            prn=tuple(self.prn[i] for i in ii.tolist()),
            signal=tuple(self.signal[i] for i in ii.tolist()),
            pr_m=self.pr_m[ii],
            frac_pr_m=self.frac_pr_m[ii],
            period_s=self.period_s[ii],
            cn0_dbhz=self.cn0_dbhz[ii],
            doppler_hz=self.doppler_hz[ii],
            lock_s=self.lock_s[ii],
        )

    @classmethod
    def from_columns(
        cls,
        gpst_week: int,
        gpst_tow_s: float,
        prn: list[str] | tuple[str, ...],
        signal: list[str] | tuple[str, ...],
        pr_m: np.ndarray | Sequence[float],
        frac_pr_m: np.ndarray | Sequence[float] | None = None,
        period_s: np.ndarray | Sequence[float] | float | None = None,
        cn0_dbhz: np.ndarray | Sequence[float] | None = None,
        doppler_hz: np.ndarray | Sequence[float] | None = None,
        lock_s: np.ndarray | Sequence[float] | None = None,
        source: str = "",
        time_unc_s: float = math.nan,
        restarted: bool = False,
    ) -> MeasurementEpoch:
        """Build an epoch, filling absent columns with NaN and deriving ``frac_pr_m``;
        ``period_s`` None is each satellite's system's code period
        (:attr:`service.core.systems.SystemConstants.code_period_s`).

        A (``prn``, ``signal``) pair given more than once is one row, its first (a repeated
        record is the same measurement, not a second one: solving it twice would double its
        weight and shrink the protection levels); the caller counts the dropped rows as
        ``len(prn) - len(epoch)``."""
        n = len(prn)
        pr = np.asarray(pr_m, dtype=float).reshape(n)
        if period_s is None:
            period_s = [constants_of(p).code_period_s for p in prn]
        # (np.full and np.array: a third of broadcast_to's cost, once per epoch)
        if isinstance(period_s, (int, float)):  # one period for all
            period = np.full(n, float(period_s))
        else:
            period = np.array(period_s, dtype=float)
            if period.shape != (n,):
                period = np.broadcast_to(period, (n,)).copy()
        if frac_pr_m is None:
            frac = np.mod(pr, period * 299_792_458.0)
        else:
            frac = np.asarray(frac_pr_m, dtype=float).reshape(n)

        def col(v: np.ndarray | Sequence[float] | None) -> np.ndarray:
            return np.full(n, np.nan) if v is None else np.asarray(v, dtype=float).reshape(n)

        epoch = cls(
            gpst_week=int(gpst_week),
            gpst_tow_s=float(gpst_tow_s),
            prn=tuple(prn),
            signal=tuple(signal),
            pr_m=pr,
            frac_pr_m=frac,
            period_s=period,
            cn0_dbhz=col(cn0_dbhz),
            doppler_hz=col(doppler_hz),
            lock_s=col(lock_s),
            source=source,
            time_unc_s=float(time_unc_s),
            restarted=restarted,
        )
        pairs = list(zip(epoch.prn, epoch.signal, strict=True))
        if len(set(pairs)) == n:
            return epoch
        first: dict[tuple[str, str], int] = {}
        for i, pair in enumerate(pairs):
            first.setdefault(pair, i)
        return epoch.rows(sorted(first.values()))


@dataclass(frozen=True, slots=True)
class ReceiverFix:
    """A position the receiver computed itself (an Android ``Fix,`` row, a Septentrio
    PVTGeodetic), carried beside bdsfix's own fix for comparison, never used by the engine.

    ``source`` names it (``android-gps``, ``sbf-pvtgeodetic``); the time is GPST;
    ``accuracy_m`` the receiver's own horizontal accuracy estimate (NaN: not given)."""

    source: str
    gpst_week: int
    gpst_tow_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    accuracy_m: float = math.nan


@dataclass(frozen=True, slots=True)
class Ephemeris:
    """Broadcast Keplerian ephemeris and clock of the satellite ``prn`` (BDS: ICD B1I
    5.2.4.9-5.2.4.12, Table 5-11; the fields are those of GPS LNAV and Galileo too, and
    :func:`service.core.orbit.sat_pos_clock` evaluates them with the constants of the ID's
    system).

    ``toe_sow_s``/``toc_sow_s`` are BDT seconds of week in BDT ``week``: the store and the
    solver select and evaluate every set on BDT, so a set of another system is put on BDT
    (GPST and GST - 14 s, week - 1356) by its reader; the orbit takes t_oe back on the
    system's own scale for its Omega_e t_oe term (:mod:`service.core.orbit`). Angles in
    radians, rates in rad/s. ``health`` is SatH1 (0 = healthy; GPS SV health, Galileo SV
    health bits). ``tgd1_s`` is the group delay of the signal in use (B1I: T_GD1; GPS L1
    C/A: T_GD; Galileo E1: BGD(E1,E5b) of an I/NAV set, BGD(E1,E5a) of an F/NAV one).
    ``aode``/``aodc``: BDS AODE/AODC, GPS IODE/IODC, Galileo IODnav. ``ura_m``: URA, or
    Galileo's SISA.
    """

    prn: str
    week: int
    toe_sow_s: float
    toc_sow_s: float
    af0_s: float
    af1_s_s: float
    af2_s_s2: float
    sqrt_a_sqrt_m: float
    e: float
    i0_rad: float
    omega0_rad: float
    omega_rad: float
    m0_rad: float
    delta_n_rad_s: float
    omega_dot_rad_s: float
    idot_rad_s: float
    cuc_rad: float
    cus_rad: float
    crc_m: float
    crs_m: float
    cic_rad: float
    cis_rad: float
    tgd1_s: float = 0.0
    tgd2_s: float = 0.0
    health: int = 0
    aode: int = 0
    aodc: int = 0
    ura_m: float = 0.0
    source: str = "rinex"


@dataclass(frozen=True, slots=True)
class KlobucharParams:
    """Broadcast Klobuchar coefficients: alpha [s, s/sc, s/sc^2, s/sc^3], beta [s, ...].

    ``system`` is ``"BDS"`` for BDSA/BDSB (D1 subframe 1, D2 subframe 1 page 2) or ``"GPS"``
    for GPSA/GPSB used as a fallback.
    """

    alpha: tuple[float, float, float, float]
    beta: tuple[float, float, float, float]
    system: Literal["BDS", "GPS"] = "BDS"


@dataclass(frozen=True, slots=True)
class TimeOffset:
    """A broadcast offset between two system times (the GGTO, :mod:`service.core.gal_nav`):
    ``pair`` as RINEX 3 names it (``GAGP``: GST - GPST), ``a0_s`` + ``a1_s_s`` (t -
    ``t_ref_s``) seconds, the reference week ``week`` on the GPS week count (a week broadcast
    modulo 64 resolved against the receiver's), ``source`` the input it came from."""

    pair: str
    a0_s: float
    a1_s_s: float
    t_ref_s: float
    week: int
    source: str = ""

    def at_s(self, gps_week: int, gps_tow_s: float) -> float:
        """The offset [s] at a GPST instant (OS SIS ICD 5.1.8)."""
        return self.a0_s + self.a1_s_s * (
            gps_tow_s - self.t_ref_s + WEEK_S * (gps_week - self.week)
        )


@dataclass(frozen=True, slots=True)
class NavSubframe:
    """One navigation subframe: 10 words of 30 bits as received (parity included).

    ``nav_type`` ``D1``/``D2``: a BDS B1I subframe, ``sow_s`` its SOW (BDT). ``LNAV``: a GPS
    L1 C/A subframe (:mod:`service.core.gps_nav`), ``sow_s`` its HOW time (GPST of the next
    subframe's start, IS-GPS-200 20.3.3.2) and ``fra_id`` its subframe ID. ``INAV``: a
    Galileo I/NAV word of a nominal page (:mod:`service.core.gal_nav`), ``words`` the 128-bit
    word alone, ``fra_id`` its word type, ``sow_s`` the GST time of week at its page's start
    when the word carries one (types 0/5/6), else -1.
    """

    prn: str
    nav_type: Literal["D1", "D2", "LNAV", "INAV"]
    fra_id: int
    sow_s: int
    words: tuple[int, ...]
    gpst_week: int
    gpst_tow_s: float
    page: int | None = None
    signal: str = "2I"


@dataclass(frozen=True, slots=True)
class SatView:
    """One satellite as seen at an epoch (for GSV/GSA and the ZMQ ``SKY`` topic)."""

    prn: str
    el_deg: float
    az_deg: float
    cn0_dbhz: float
    used: bool
    full: bool
    signal: str = "2I"


@dataclass(frozen=True, slots=True)
class Velocity:
    """Receiver velocity and clock drift of one epoch from Doppler (service.engine.velocity).

    ``v_enu_m_s`` is east, north, up in the local frame of the position fix; ``speed_m_s`` is
    the horizontal speed over ground and ``course_deg`` its direction, clockwise from true
    north in [0, 360); ``clock_drift_m_s`` is c times the receiver clock's rate. Every
    ``std_*`` is the 1-sigma of the value from the weighted least-squares covariance;
    ``redundancy`` = Doppler rows used - unknowns (3 + one drift per system),
    ``chi2``/``chi2_max`` the sanity test of their residuals (None at redundancy 0),
    ``excluded`` the satellites whose Doppler it removed.
    """

    v_enu_m_s: tuple[float, float, float]
    std_v_enu_m_s: tuple[float, float, float]
    speed_m_s: float
    std_speed_m_s: float
    course_deg: float
    std_course_deg: float
    clock_drift_m_s: float
    std_clock_drift_m_s: float
    used: tuple[str, ...] = ()
    excluded: tuple[str, ...] = ()
    redundancy: int = 0
    chi2: float | None = None
    chi2_max: float | None = None


@dataclass(frozen=True, slots=True, eq=False)
class Fix:
    """A solver's result for one epoch; ``mode == "none"`` carries a ``decline`` instead.

    ``solver`` is which solver ran (``fast``/``spp``), ``mode`` what it achieved.
    """

    solver: Literal["fast", "spp"]
    mode: FixMode
    gpst_week: int
    gpst_tow_s: float
    x_ecef_m: tuple[float, float, float] | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_m: float | None = None
    clock_bias_m: float | None = None
    gdop_full: float | None = None
    pdop: float | None = None
    hdop: float | None = None
    vdop: float | None = None
    std_enu_m: tuple[float, float, float] | None = None
    used: tuple[str, ...] = ()
    full: tuple[str, ...] = ()
    fractional: tuple[str, ...] = ()
    ambiguity: dict[str, int] = field(default_factory=dict)
    recovered_pr_m: dict[str, float] = field(default_factory=dict)
    # a coarse-time fix whose whole period common to a system's ranges is in doubt: its
    # integers (units of each row's period), right only relative within each system
    relative_ambiguity: dict[str, int] = field(default_factory=dict)
    resid_rms_m: float | None = None
    iterations: int = 0
    # why a fix is declined (mode "none"): its code, template variant and figures
    decline: Declined | None = None
    sky: tuple[SatView, ...] = ()
    # integrity (service.engine.raim): redundancy (rows - unknowns) of the final solution;
    # the chi-square statistic and its threshold (None at redundancy 0: no test possible);
    # protection levels (inf: a satellite without redundancy, the fix is not protected against it);
    # the east-north-up covariance [m^2] and the satellites excluded, with why
    redundancy: int | None = None
    chi2: float | None = None
    chi2_max: float | None = None
    hpl_m: float | None = None
    vpl_m: float | None = None
    cov_enu_m2: tuple[tuple[float, float, float], ...] | None = None
    excluded: dict[str, str] = field(default_factory=dict)
    # velocity and clock drift from the epoch's Doppler (None: not computed or not trusted)
    velocity: Velocity | None = None
    # the receiver clock of each satellite system [m] by its RINEX letter, when the rows
    # came from more than one (``clock_bias_m`` is the first's: BeiDou's when present)
    clocks_m: dict[str, float] = field(default_factory=dict)
    # how a fast fix was made: None for the paper's method (and SPP), "coarse_time" for the
    # Doppler-prior coarse-time fix (service.engine.coarse), with its solved receive-time
    # offset [s] (true receive time = the epoch's tag + time_offset_s)
    method: str | None = None
    time_offset_s: float | None = None

    @property
    def ok(self) -> bool:
        return self.mode != "none"

    @property
    def reason_code(self) -> str | None:
        """The decline's code (the ``declined_<code>`` counters, the records'
        ``reason_code``); None for a published fix."""
        return None if self.decline is None else self.decline.code.value

    @property
    def reason(self) -> str | None:
        """The decline in words, from the one table (:data:`service.core.declines.DECLINES`);
        None for a published fix."""
        return None if self.decline is None else self.decline.reason
