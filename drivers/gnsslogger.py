"""Android GnssLogger text logs to bdsfix events: ``Raw,`` rows to measurement epochs.

Reference: Android ``android.location.GnssMeasurement`` and ``GnssClock`` (API 24+; the
HAL's ``IGnssMeasurementCallback``), and the column layout GnssLogger writes in its header
(``# Raw,ElapsedRealtimeMillis,TimeNanos,...``; the header's names are read, so a log of
another version with the same names reads the same).

- **Receiver time** (``GnssClock``): GPST nanoseconds since the GPS epoch are
  ``TimeNanos + TimeOffsetNanos - (FullBiasNanos + BiasNanos)``, kept in integers where the
  values are (FullBiasNanos is ~1.2e18: beyond a float's 53 bits). ``BiasUncertaintyNanos``
  is how well the phone knows that time: carried on the epoch as ``time_unc_s``, the prior
  of a coarse-time fix (the pipeline keeps fractional ranges out of the fix while it
  exceeds :data:`service.engine.timetag.COARSE_TIME_S`). A change of
  ``HardwareClockDiscontinuityCount`` is a restart of the phone's clock: counted
  (``android_clock_restarts``) and the epoch carries ``restarted=True``. An epoch whose
  BiasNanos is not a finite number, or whose time is not a GPS week within
  [:data:`MIN_GPS_WEEK`, :data:`MAX_GPS_WEEK`] (a FullBiasNanos of -1e30, of the wrong sign,
  0), is skipped with its rows (``android_bad_time``): no time, no measurement.
- **One row per satellite and signal**: the Raw rows of one epoch are its measurements, a
  satellite's signal once; a repeated one (the same Svid and band again in the epoch) is
  the same measurement, so the first is kept and the later ones are dropped
  (``android_duplicate_rows``; :meth:`service.core.types.MeasurementEpoch.from_columns`
  drops them), and an epoch reads at most :data:`MAX_EPOCH_ROWS` rows, the later ones
  dropped (``android_excess_rows``): a log whose TimeNanos never changes is then many
  epochs' rows in one, bounded, not one epoch of thousands of rows.
- **Per signal**, ``State`` (:data:`STATE_BITS`) says how much of the transmit time
  ``ReceivedSvTimeNanos`` holds (:func:`known_period_s`): modulo 1 ms at code lock, 2 ms at
  BeiDou D2 bit sync, 4 ms at Galileo E1B/C code lock, 20 ms at bit sync, 100 ms at Galileo
  E1C secondary code lock, 0.6 s at BeiDou D2 subframe sync, 2 s at Galileo E1B page sync,
  6 s at subframe sync, the whole week once the time of week is decoded or known;
  ``STATE_MSEC_AMBIGUOUS`` caps it at 1 ms. A signal whose
  ``ReceivedSvTimeUncertaintyNanos`` exceeds :data:`MAX_SV_TIME_UNC_NS` gives no range
  (``android_sv_time_uncertain``), nor one without code lock (``android_no_code_lock``).
  A full range becomes ``pr_m``; a partial one ``frac_pr_m`` modulo c times ``period_s``
  (the receive time taken on the satellite's own time scale: BDT is GPST - 14 s, which
  matters for the 0.6 s and 6 s periods).
- **Signals** by ``ConstellationType`` (1 GPS, 3 GLONASS, 4 QZSS, 5 BeiDou, 6 Galileo) and
  ``CarrierFrequencyHz`` (empty: the system's primary frequency, as the Android docs say):
  BeiDou B1I (1561.098 MHz, RINEX ``2I``), GPS L1 C/A and Galileo E1 (1575.42 MHz, ``1C``)
  are kept with their RINEX IDs (``C06``, ``G05``, ``E11``); other bands and systems are
  counted (``android_other_band``, ``android_other_gnss``).
- ``PseudorangeRateMetersPerSecond`` becomes ``doppler_hz`` = -rate / wavelength (the
  RINEX sign, positive when approaching, as :func:`service.engine.velocity.range_rate_m_s`
  reads it back); ``Cn0DbHz`` the C/N0; ``MultipathIndicator`` 1 (detected) is counted
  (``android_multipath``).
- ``Fix,`` rows (the phone's own fix) become :class:`~service.core.types.ReceiverFix`
  events; ``Status,`` rows are counted (``android_status_rows``).
- ``Nav,`` rows (``GnssNavigationMessage``: Svid, Type, Status, MessageId, Sub-messageId,
  data bytes as signed decimals): BeiDou D1 (type 0x0501) and D2 (0x0502) subframes with
  parity passed or rebuilt (Status 1, 2) become :class:`~service.core.types.NavSubframe`
  events (``android_nav_bds``), whose SOW the tracker takes and whose ephemerides the
  assembler decodes, as a receiver's own: each of the 10 words of 30 bits sits in the last 30
  bits of 4 bytes, MSB first (``getData()``). They are tagged with the receive time of the
  latest Raw epoch read (``android_nav_no_time`` before any). Other types (GPS L1 C/A
  0x0101, GLONASS 0x0301, Galileo, ...) are counted by type (``android_nav_<type>``) and
  not decoded: give ``--nav``.

Counter keys: ``android_nav_bds``, ``android_nav_bad``, ``android_nav_no_time``,
``android_nav_<type hex>``, ``android_raw_rows``, ``epochs_android``, ``android_bad_rows``,
``android_other_gnss``, ``android_other_band``, ``android_no_code_lock``,
``android_sv_time_uncertain``, ``android_full``, ``android_fractional``,
``android_multipath``, ``android_clock_restarts``, ``android_fix_rows``,
``android_nav_rows``, ``android_status_rows``, ``android_bad_svid``, ``android_bad_time``,
``android_duplicate_rows``, ``android_excess_rows``.
"""

from __future__ import annotations

import datetime as dt
import logging
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np

from service.core.bds_nav import b1i_subframe
from service.core.constants import C_M_S
from service.core.counters import Counters
from service.core.errors import DecodeError
from service.core.systems import (
    SYSTEM_CONSTANTS,
    GnssSystem,
    constants_of,
    sat_id,
    wavelength_m,
)
from service.core.timebase import gpst_from_utc
from service.core.types import MeasurementEpoch, NavSubframe, ReceiverFix

log = logging.getLogger(__name__)

MAGIC = b"Raw,ElapsedRealtimeMillis,"
"""What the header of a GnssLogger log carries (content detection)."""

STATE_BITS: dict[str, int] = {
    "CODE_LOCK": 1,
    "BIT_SYNC": 2,
    "SUBFRAME_SYNC": 4,
    "TOW_DECODED": 8,
    "MSEC_AMBIGUOUS": 16,
    "SYMBOL_SYNC": 32,
    "GLO_STRING_SYNC": 64,
    "GLO_TOD_DECODED": 128,
    "BDS_D2_BIT_SYNC": 256,
    "BDS_D2_SUBFRAME_SYNC": 512,
    "GAL_E1BC_CODE_LOCK": 1024,
    "GAL_E1C_2ND_CODE_LOCK": 2048,
    "GAL_E1B_PAGE_SYNC": 4096,
    "SBAS_SYNC": 8192,
    "TOW_KNOWN": 16384,
    "GLO_TOD_KNOWN": 32768,
    "2ND_CODE_LOCK": 65536,
}
"""``GnssMeasurement.STATE_*`` (Android API 24; TOW_KNOWN, GLO_TOD_KNOWN API 26;
2ND_CODE_LOCK API 29)."""

MAX_SV_TIME_UNC_NS = 1000.0
"""A signal whose ReceivedSvTimeUncertaintyNanos exceeds this gives no range: 1 us is
300 m, far beyond the code noise (good signals in the shared logs report 6-170 ns; the
phones write 1e9 for a time they do not hold)."""

WEEK_NS = 604_800 * 10**9
MIN_GPS_WEEK = 1877
"""GPS week of 2016-01-01: no phone gave raw measurements before Android 7 (API 24, 2016),
so an earlier week is a broken clock field (FullBiasNanos 0 or of the wrong sign)."""
MAX_GPS_WEEK = 4096
"""GPS week of 2058-07-07: a later week is a broken clock field (FullBiasNanos -1e30 or
-2**63), not a recording."""
MAX_EPOCH_ROWS = 1024
"""The most Raw rows one epoch reads. Every satellite of the seven constellations Android
names (GPS 32, SBAS 39, GLONASS 24 slots and up to 14 frequency numbers, QZSS 10, BeiDou
63, Galileo 36, NavIC 14: under 250 Svids) on three bands each is under 750 rows; more is a
log whose TimeNanos does not advance, whose rows beyond this are dropped
(``android_excess_rows``) so that no input makes one epoch unbounded."""
BDT_MINUS_GPST_NS = -14 * 10**9
"""BDT = GPST - 14 s (BDS-SIS-ICD-B1I-3.0 4.3)."""

_CONSTELLATION: dict[int, GnssSystem] = {
    1: GnssSystem.GPS,
    2: GnssSystem.SBAS,
    3: GnssSystem.GLO,
    4: GnssSystem.QZS,
    5: GnssSystem.BDS,
    6: GnssSystem.GAL,
    7: GnssSystem.IRN,
}
"""``GnssStatus.CONSTELLATION_*``."""

_BANDS_HZ: dict[GnssSystem, tuple[float, str]] = {
    GnssSystem.BDS: (1_561.098e6, "2I"),
    GnssSystem.GPS: (1_575.42e6, "1C"),
    GnssSystem.GAL: (1_575.42e6, "1C"),
}
"""The band bdsfix reads per system: carrier [Hz] and RINEX 3 signal name."""
BAND_TOLERANCE_HZ = 1e6
"""A carrier within this of the band's centre is that band (the phones write 1561.09798,
1575.42003 MHz; the next bands are tens of MHz away)."""

DEFAULT_COLUMNS = [
    "Raw",
    "ElapsedRealtimeMillis",
    "TimeNanos",
    "LeapSecond",
    "TimeUncertaintyNanos",
    "FullBiasNanos",
    "BiasNanos",
    "BiasUncertaintyNanos",
    "DriftNanosPerSecond",
    "DriftUncertaintyNanosPerSecond",
    "HardwareClockDiscontinuityCount",
    "Svid",
    "TimeOffsetNanos",
    "State",
    "ReceivedSvTimeNanos",
    "ReceivedSvTimeUncertaintyNanos",
    "Cn0DbHz",
    "PseudorangeRateMetersPerSecond",
    "PseudorangeRateUncertaintyMetersPerSecond",
    "AccumulatedDeltaRangeState",
    "AccumulatedDeltaRangeMeters",
    "AccumulatedDeltaRangeUncertaintyMeters",
    "CarrierFrequencyHz",
    "CarrierCycles",
    "CarrierPhase",
    "CarrierPhaseUncertainty",
    "MultipathIndicator",
    "SnrInDb",
    "ConstellationType",
    "AgcDb",
]
"""GnssLogger v2's Raw columns, for a log without its header."""
DEFAULT_FIX_COLUMNS = "Fix,Provider,Latitude,Longitude,Altitude,Speed,Accuracy,(UTC)TimeInMs"

NAV_BDS_D1, NAV_BDS_D2 = 0x0501, 0x0502
"""``GnssNavigationMessage.TYPE_BDS_D1`` / ``TYPE_BDS_D2``."""
NAV_STATUS_OK = (1, 2)
"""``STATUS_PARITY_PASSED``, ``STATUS_PARITY_REBUILT``."""


def nav_words(data: bytes) -> tuple[int, ...]:
    """The ten 30-bit words of a GPS L1 C/A or BeiDou D1/D2 subframe from
    ``GnssNavigationMessage.getData()``'s 40 bytes (each word in the last 30 bits of 4
    bytes, big-endian)."""
    if len(data) != 40:
        raise ValueError(f"{len(data)} data bytes, expected 40")
    return tuple(int.from_bytes(data[4 * i : 4 * i + 4], "big") & 0x3FFFFFFF for i in range(10))


def state_names(state: int) -> tuple[str, ...]:
    """The ``STATE_*`` names of the bits set in ``state``, lowest bit first (unknown bits
    as ``BIT<n>``)."""
    names = [name for name, bit in STATE_BITS.items() if state & bit]
    known = sum(STATE_BITS.values())
    names += [f"BIT{n}" for n in range(32) if state & ~known & (1 << n)]
    return tuple(names)


def known_period_s(system: GnssSystem, state: int) -> float | None:
    """How much of the transmit time a signal in ``state`` holds: the period [s] its
    ReceivedSvTimeNanos is known modulo, ``math.inf`` for the whole week (time of week
    decoded or known), None without code lock (Android ``GnssMeasurement.getReceivedSv
    TimeNanos``: GPS code lock 1 ms, bit sync 20 ms, subframe sync 6 s; BeiDou D2 bit sync
    2 ms, D2 subframe sync 600 ms; Galileo E1B/C code lock 4 ms, E1C 2nd code lock 100 ms,
    E1B page sync 2 s). ``STATE_MSEC_AMBIGUOUS`` caps the period at 1 ms."""
    s = STATE_BITS
    lock = state & s["CODE_LOCK"] or (system is GnssSystem.GAL and state & s["GAL_E1BC_CODE_LOCK"])
    if not lock:
        return None
    if state & (s["TOW_DECODED"] | s["TOW_KNOWN"]) and not state & s["MSEC_AMBIGUOUS"]:
        return math.inf
    period = 4e-3 if system is GnssSystem.GAL else 1e-3
    steps: tuple[tuple[str, float], ...] = (("BIT_SYNC", 0.02), ("SUBFRAME_SYNC", 6.0))
    if system is GnssSystem.BDS:
        steps = (("BDS_D2_BIT_SYNC", 0.002), *steps[:1], ("BDS_D2_SUBFRAME_SYNC", 0.6), steps[1])
    elif system is GnssSystem.GAL:
        steps = (("GAL_E1C_2ND_CODE_LOCK", 0.1), ("GAL_E1B_PAGE_SYNC", 2.0))
    for name, value in steps:
        if state & s[name]:
            period = max(period, value)
    if state & s["MSEC_AMBIGUOUS"]:
        period = min(period, 1e-3)
    return period


@dataclass(slots=True)
class _Row:
    prn: str
    signal: str
    state: int
    period_s: float  # inf: full
    t_rx_ns: int  # receive time on the satellite's time scale, integer ns of week
    t_rx_frac_ns: float
    t_sv_ns: int
    cn0_dbhz: float
    doppler_hz: float


def _int(text: str) -> int:
    return int(float(text)) if ("e" in text or "E" in text or "." in text) else int(text)


def _float(text: str) -> float:
    return float(text) if text else math.nan


class GnssLoggerReader:
    """Events of one GnssLogger log, in file order: a
    :class:`~service.core.types.MeasurementEpoch` per receive time (the Raw rows of one
    TimeNanos), a :class:`~service.core.types.ReceiverFix` per Fix row."""

    def __init__(
        self, lines: Iterable[str], counters: Counters | None = None, name: str = ""
    ) -> None:
        self._lines = lines
        self.counters = counters if counters is not None else Counters()
        self.name = name
        self._raw_cols: dict[str, int] = self._columns(DEFAULT_COLUMNS)
        self._fix_cols: dict[str, int] = self._columns(DEFAULT_FIX_COLUMNS.split(","))
        self._discontinuity: int | None = None
        self._time: tuple[int, float] | None = None  # GPST of the latest Raw epoch

    @staticmethod
    def _columns(names: list[str]) -> dict[str, int]:
        cols: dict[str, int] = {}
        for i, name in enumerate(names):
            cols.setdefault(name.strip(), i)  # the first of a repeated name
        return cols

    def __iter__(self) -> Iterator[MeasurementEpoch | ReceiverFix | NavSubframe]:
        pending: list[list[str]] = []
        key: tuple[str, str] | None = None
        for lineno, line in enumerate(self._lines, 1):
            line = line.strip()
            if line.startswith("#"):
                self._header(line.lstrip("# ").strip())
                continue
            fields = line.split(",")
            kind = fields[0]
            if kind == "Raw":
                self.counters["android_raw_rows"] += 1
                c = self._raw_cols
                try:
                    k = (fields[c["TimeNanos"]], fields[c["HardwareClockDiscontinuityCount"]])
                except (KeyError, IndexError):
                    self.counters["android_bad_rows"] += 1
                    continue
                if key is not None and k != key and pending:
                    yield from self._epoch(pending, lineno)
                    pending = []
                key = k
                if len(pending) < MAX_EPOCH_ROWS:
                    pending.append(fields)
                else:
                    if self.counters["android_excess_rows"] == 0:
                        log.warning(
                            "%s:%d: more than %d Raw rows of one TimeNanos; the rest of the "
                            "epoch's rows are dropped",
                            self.name,
                            lineno,
                            MAX_EPOCH_ROWS,
                        )
                    self.counters["android_excess_rows"] += 1
            elif kind == "Fix":
                self.counters["android_fix_rows"] += 1
                fix = self._fix(fields)
                if fix is not None:
                    yield fix
            elif kind == "Nav":
                self.counters["android_nav_rows"] += 1
                if pending and self._time is None:  # the epoch being read gives the time
                    self._time = self._time_of(pending[0])
                sub = self._nav(fields)
                if sub is not None:
                    yield sub
            elif kind == "Status":
                self.counters["android_status_rows"] += 1
        if pending:
            yield from self._epoch(pending, 0)

    def _header(self, text: str) -> None:
        if text.startswith("Raw,"):
            self._raw_cols = self._columns(text.split(","))
        elif text.startswith("Fix,"):
            self._fix_cols = self._columns(text.split(","))

    def _time_of(self, first: list[str]) -> tuple[int, float] | None:
        c = self._raw_cols
        try:
            gps_ns = int(first[c["TimeNanos"]]) - _int(first[c["FullBiasNanos"]])
            bias_ns = float(first[c["BiasNanos"]] or 0.0)
        except (KeyError, IndexError, ValueError, OverflowError):
            return None
        time = _gpst(gps_ns, bias_ns)
        return None if time is None else (time[0], (time[1] - bias_ns) * 1e-9)

    def _nav(self, f: list[str]) -> NavSubframe | None:
        """A BeiDou D1/D2 subframe of a Nav row, or None (counted)."""
        try:
            svid, kind, status = int(f[1]), int(f[2]), int(f[3])
            data = bytes(int(b) & 0xFF for b in f[6:])
        except (IndexError, ValueError):
            self.counters["android_nav_bad"] += 1
            return None
        if kind not in (NAV_BDS_D1, NAV_BDS_D2):
            self.counters[f"android_nav_{kind:#06x}"] += 1
            return None
        if status not in NAV_STATUS_OK or not 1 <= svid <= 63:
            self.counters["android_nav_bad"] += 1
            return None
        if self._time is None:
            self.counters["android_nav_no_time"] += 1
            return None
        nav_type: Literal["D1", "D2"] = "D1" if kind == NAV_BDS_D1 else "D2"
        try:
            sub = b1i_subframe(sat_id(GnssSystem.BDS, svid), nav_type, nav_words(data), *self._time)
        except (DecodeError, ValueError):
            self.counters["android_nav_bad"] += 1
            return None
        self.counters["android_nav_bds"] += 1
        return sub

    def _fix(self, f: list[str]) -> ReceiverFix | None:
        c = self._fix_cols
        try:
            utc = dt.datetime(1970, 1, 1) + dt.timedelta(milliseconds=int(f[c["(UTC)TimeInMs"]]))
            week, tow = gpst_from_utc(utc)
            return ReceiverFix(
                source=f"android-{f[c['Provider']].lower()}",
                gpst_week=week,
                gpst_tow_s=tow,
                lat_deg=float(f[c["Latitude"]]),
                lon_deg=float(f[c["Longitude"]]),
                alt_m=_float(f[c["Altitude"]]),
                accuracy_m=_float(f[c["Accuracy"]]),
            )
        except (KeyError, IndexError, ValueError, OverflowError):
            self.counters["android_bad_rows"] += 1
            return None

    def _epoch(self, rows: list[list[str]], lineno: int) -> Iterator[MeasurementEpoch]:
        c = self._raw_cols
        kept: list[_Row] = []
        first = rows[0]
        try:
            time_ns = int(first[c["TimeNanos"]])
            full_bias_ns = _int(first[c["FullBiasNanos"]])
            bias_ns = float(first[c["BiasNanos"]] or 0.0)
            bias_unc_ns = _float(first[c["BiasUncertaintyNanos"]])
            discontinuity = int(first[c["HardwareClockDiscontinuityCount"]] or 0)
        except (KeyError, IndexError, ValueError, OverflowError):
            self.counters["android_bad_rows"] += len(rows)
            log.warning("%s:%d: epoch without a usable clock, skipped", self.name, lineno)
            return
        gpst = _gpst(time_ns - full_bias_ns, bias_ns)
        if gpst is None:
            self.counters["android_bad_time"] += 1
            if self.counters["android_bad_time"] == 1:
                log.warning(
                    "%s:%d: epoch whose clock (FullBiasNanos %s, BiasNanos %s) gives no GPS "
                    "time in weeks %d-%d, skipped (counted android_bad_time)",
                    self.name,
                    lineno,
                    first[c["FullBiasNanos"]],
                    first[c["BiasNanos"]],
                    MIN_GPS_WEEK,
                    MAX_GPS_WEEK,
                )
            return
        restarted = self._discontinuity is not None and discontinuity != self._discontinuity
        if restarted:
            self.counters["android_clock_restarts"] += 1
        self._discontinuity = discontinuity
        week, tow_int_ns = gpst  # integer ns of week, before BiasNanos
        self._time = (week, (tow_int_ns - bias_ns) * 1e-9)
        for f in rows:
            try:
                row = self._row(f, tow_int_ns, bias_ns)
            except (KeyError, IndexError, ValueError, OverflowError):
                self.counters["android_bad_rows"] += 1
                continue
            if row is not None:
                kept.append(row)
        self.counters["epochs_android"] += 1
        yield self._build(week, tow_int_ns, bias_ns, bias_unc_ns, kept, restarted)

    def _row(self, f: list[str], tow_int_ns: int, bias_ns: float) -> _Row | None:
        c = self._raw_cols
        system = _CONSTELLATION.get(int(f[c["ConstellationType"]]))
        if system is None or system not in _BANDS_HZ:
            self.counters["android_other_gnss"] += 1
            return None
        centre_hz, signal = _BANDS_HZ[system]
        carrier = _float(f[c["CarrierFrequencyHz"]]) if "CarrierFrequencyHz" in c else math.nan
        if math.isfinite(carrier) and abs(carrier - centre_hz) > BAND_TOLERANCE_HZ:
            self.counters["android_other_band"] += 1
            return None
        state = int(f[c["State"]])
        period = known_period_s(system, state)
        if period is None:
            self.counters["android_no_code_lock"] += 1
            return None
        if _float(f[c["ReceivedSvTimeUncertaintyNanos"]]) > MAX_SV_TIME_UNC_NS:
            self.counters["android_sv_time_uncertain"] += 1
            return None
        if f[c["MultipathIndicator"]].strip() == "1":
            self.counters["android_multipath"] += 1
        offset_ns = _float(f[c["TimeOffsetNanos"]])
        offset_ns = 0.0 if math.isnan(offset_ns) else offset_ns
        rx_int = tow_int_ns + (BDT_MINUS_GPST_NS if system is GnssSystem.BDS else 0)
        svid = int(f[c["Svid"]])
        if not 1 <= svid <= SYSTEM_CONSTANTS[system].prn_max:
            self.counters["android_bad_svid"] += 1
            return None
        prn = sat_id(system, svid)
        rate = _float(f[c["PseudorangeRateMetersPerSecond"]])
        return _Row(
            prn=prn,
            signal=signal,
            state=state,
            period_s=period,
            t_rx_ns=rx_int % WEEK_NS,
            t_rx_frac_ns=offset_ns - bias_ns,
            t_sv_ns=_int(f[c["ReceivedSvTimeNanos"]]),
            cn0_dbhz=_float(f[c["Cn0DbHz"]]),
            doppler_hz=-rate / wavelength_m(prn),
        )

    def _build(
        self,
        week: int,
        tow_int_ns: int,
        bias_ns: float,
        bias_unc_ns: float,
        rows: list[_Row],
        restarted: bool,
    ) -> MeasurementEpoch:
        n = len(rows)
        pr = np.full(n, np.nan)
        frac = np.full(n, np.nan)
        period = np.full(n, 1e-3)
        for i, r in enumerate(rows):
            if math.isinf(r.period_s):
                d_ns = (r.t_rx_ns - r.t_sv_ns) % WEEK_NS  # across the week's end
                if d_ns > WEEK_NS // 2:
                    d_ns -= WEEK_NS
                pr[i] = (d_ns + r.t_rx_frac_ns) * 1e-9 * C_M_S
            else:
                p_ns = round(r.period_s * 1e9)
                d_ns = (r.t_rx_ns - r.t_sv_ns) % p_ns
                frac[i] = ((d_ns + r.t_rx_frac_ns) % p_ns) * 1e-9 * C_M_S
                period[i] = r.period_s
        full = np.isfinite(pr)
        for i in np.flatnonzero(full).tolist():
            period[i] = constants_of(rows[i].prn).code_period_s
        frac = np.where(full, np.mod(pr, period * C_M_S), frac)
        epoch = MeasurementEpoch.from_columns(
            week,
            (tow_int_ns - bias_ns) * 1e-9,
            [r.prn for r in rows],
            [r.signal for r in rows],
            pr,
            frac_pr_m=frac,
            period_s=period,
            cn0_dbhz=[r.cn0_dbhz for r in rows],
            doppler_hz=[r.doppler_hz for r in rows],
            source="android",
            # a phone that does not say how well it knows its time is not taken at its word:
            # unknown (inf) keeps its fractional ranges out of the fast fix until a coarse-
            # time fix or full ranges (the pipeline's 1 ms rule)
            time_unc_s=math.inf if math.isnan(bias_unc_ns) else bias_unc_ns * 1e-9,
            restarted=restarted,
        )
        if len(epoch) < n:
            self.counters["android_duplicate_rows"] += n - len(epoch)
        n_full = int(np.count_nonzero(~np.isnan(epoch.pr_m)))  # the full ranges kept
        self.counters["android_full"] += n_full
        self.counters["android_fractional"] += len(epoch) - n_full
        return epoch


def _gpst(gps_ns: int, bias_ns: float) -> tuple[int, int] | None:
    """(GPS week, integer ns of week) of an epoch whose receiver time is ``gps_ns`` integer
    ns since the GPS epoch (TimeNanos - FullBiasNanos) before ``bias_ns`` (BiasNanos), or
    None when that is no time: BiasNanos not a finite number, or the week outside
    [:data:`MIN_GPS_WEEK`, :data:`MAX_GPS_WEEK`]."""
    if not math.isfinite(bias_ns):
        return None
    week, tow_int_ns = divmod(gps_ns, WEEK_NS)
    if not MIN_GPS_WEEK <= week <= MAX_GPS_WEEK:
        return None
    return week, tow_int_ns


def events(
    path: str | Path,
    counters: Counters | None = None,
    lenient: bool = True,
    systems: frozenset[str] = frozenset(),
) -> Iterator[MeasurementEpoch | ReceiverFix | NavSubframe]:
    """The events of the GnssLogger log at ``path`` (see :class:`GnssLoggerReader`; a bad
    row is always counted and skipped, ``lenient`` or not). The registry's reader.
    ``systems`` is not used to leave rows out: the tracker and the timeline follow every
    system's time of week (a phone's first four full ranges are often GPS); the solver
    uses the rows of the systems whose ephemerides it holds, which the nav is read for."""
    with open(path, encoding="utf-8", errors="replace") as fh:
        yield from GnssLoggerReader(fh, counters, name=str(path))


def detect(path: Path, head: bytes) -> bool:
    """A GnssLogger log: its header names the Raw columns, or it starts with a Raw row."""
    return MAGIC in head or head.startswith(b"Raw,")


def needs_nav(path: Path) -> bool:
    """True unless the log holds BeiDou D1/D2 Nav rows (whose ephemerides it decodes)."""
    kinds = (f",{NAV_BDS_D1},", f",{NAV_BDS_D2},")
    with open(path, encoding="utf-8", errors="replace") as fh:
        return not any(line.startswith("Nav,") and any(k in line for k in kinds) for line in fh)
