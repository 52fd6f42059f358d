"""RTCM3 frames to bdsfix events: framing, and the BDS messages (and GPS and Galileo ones
when their systems are asked for), parsed by pyrtcm, mapped.

Reference: RTCM Standard 10403.3: section 4 (transport layer: ``D3``, 6 reserved zero bits,
10-bit length, payload, CRC-24Q over header and payload; :data:`FRAMING`), section 3.5.12
(Multiple Signal Messages, MSM) and 3.5.13 / Table 3.5-130 ff. (message 1042, BDS satellite
ephemeris), with the field definitions of section 3.4 (DF397-DF408, DF427, DF488-DF515).
BDS facts from BDS-SIS-ICD-B1I-3.0.

- BDS MSM4/5/6/7 (1124-1127): per satellite the rough range in integer milliseconds (DF397,
  255 = unknown) and modulo 1 ms (DF398); per cell the fine pseudorange (DF400 in MSM4/5,
  DF405 in MSM6/7). A cell's full pseudorange is c*1ms*(DF397 + DF398 + fine). A cell whose
  integer milliseconds are unknown is kept as a *fractional* measurement,
  ``frac_pr_m = c*1ms*((DF398 + fine) mod 1)`` with ``pr_m`` NaN (RTKLIB drops such cells).
  Only B1I cells (signal ID 2, RINEX ``2I``; Table 3.5-108) enter the epoch.
- GPS MSM 1074-1077 and Galileo MSM 1094-1097 (:data:`OTHER_MSM`), when the mapper's
  ``systems`` include theirs: the same cells, GPS L1 C/A and Galileo E1 (B, C or B+C) only
  (:data:`OTHER_MSM_SIGNALS`), their epoch time the system's own TOW (DF004, DF248); GPS
  1019 and Galileo I/NAV 1046 become ephemerides (:data:`EPH_OF_SYSTEM`).
- The BDS MSM epoch time DF427 is BDT milliseconds of week; GPST = BDT + 14 s. The GPS week
  comes from a :class:`~drivers.framing.WeekContext` shared with the other mappers of the
  stream: the latest exact week (UBX RXM-RAWX / NAV-TIMEGPS), else the week and t_oe of the
  latest broadcast ephemeris in the stream (:data:`EPH_WEEKS`: 1042 BDS, 1019 GPS, 1044
  QZSS, 1045/1046 Galileo, whichever comes first), else a hint (``--gps-week``, the system
  clock of a live stream); the time of week is put in the week nearest that reference. A
  truncated broadcast week is resolved by :meth:`~drivers.framing.WeekContext.broadcast_week`.
  An MSM epoch before any week is known is passed on with
  :data:`~service.core.types.UNKNOWN_WEEK` (counted, ``msm_no_week``): the pipeline declines
  it (``no_time``) rather than the stream losing it.
- 1042 becomes an :class:`~service.core.types.Ephemeris` (``source="rtcm"``). pyrtcm applies the
  scale factors (toe/toc in s, angles in semicircles, TGD in ns); angles and rates are turned
  into radians with the ICD's pi = 3.1415926535898 (ICD 5.2.4.9).

Counter keys: ``rtcm:<number>`` per message, ``rtcm_ignored``, ``msm_bds``,
``msm_cells_b1i``, ``msm_cells_other_signal``, ``msm_cells_fractional``,
``msm_cells_invalid``, ``msm_duplicate_cells``, ``msm_no_week``, ``msm_bad_time``, ``epochs_rtcm``,
``ephemerides_rtcm``, ``msm_<system>``, ``msm_cells_<system>`` and
``ephemerides_rtcm_<system>`` (GPS ``G``, Galileo ``E``), ``eph_bad_prn``,
``eph_week_<number>`` (a week taken from a non-BDS
ephemeris), ``eph_week_disagrees`` (a 1019, 1042, 1044, 1045 or 1046 whose week and t_oe are
more than a day from the stream's time, or from the receiver's own in a stream that carries
it: ignored for the week, see :class:`~drivers.framing.WeekContext`; the set, if one is
made, is still passed on),
``eph_bad_toe`` (a t_oe or t_oc outside the week: no week is taken from that message, a
1019/1046 gives no set, and a 1042 is passed on for the ephemeris store to refuse),
``eph_week_handovers`` (a 1019/1044/1045/1046 broadcast at a week's end for a t_oe in the
next week, or the reverse, whose week of transmission was moved to its t_oe's:
:meth:`~drivers.framing.WeekContext.toe_week`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from pyrtcm import VALNONE, RTCMReader

from drivers.framing import BinaryFraming, Event, WeekContext
from service.core.constants import C_M_S, ICD_PI, URA_M, WEEK_S
from service.core.counters import Counters
from service.core.gal_nav import galileo_sisa_m, inav_health
from service.core.rtcm1042 import EPH_1042_FIELDS, EPH_1042_INT_FIELDS
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem, sat_id
from service.core.timebase import (
    BDT_GPST_OFFSET_S,
    GST_GPS_WEEK_OFFSET,
    bdt_to_gpst,
    diff_s,
    gpst_sow_to_bdt_sow,
    gpst_to_bdt,
)
from service.core.types import UNKNOWN_WEEK, Ephemeris, MeasurementEpoch

log = logging.getLogger(__name__)

MSM_SYSTEM = GnssSystem.BDS
"""The system of the MSM messages read (1124-1127); the others are counted and dropped."""
_BDS = SYSTEM_CONSTANTS[MSM_SYSTEM]
LIGHT_MS_M = C_M_S * 1e-3
"""The range unit of MSM (DF397, DF398, the fine ranges): one light-millisecond [m]."""
B1I_CODE_RANGE_M = C_M_S * _BDS.code_period_s
"""c times the B1I code period: a range known from the code phase alone is known modulo
this [m]."""
B1I_CODE_PERIOD_MS = _BDS.code_period_s * 1e3
B1I_WAVELENGTH_M = C_M_S / _BDS.carrier_hz

# --- frame (section 4, "Transport layer") ---------------------------------------------------
PREAMBLE = 0xD3
HEADER_LEN = 3  # preamble, 6 reserved bits, 10-bit length
MAX_PAYLOAD = 1023


def _crc24q_table() -> tuple[int, ...]:
    poly = 0x1864CFB
    table = []
    for i in range(256):
        crc = i << 16
        for _ in range(8):
            crc <<= 1
            if crc & 0x1000000:
                crc ^= poly
        table.append(crc & 0xFFFFFF)
    return tuple(table)


_CRC24Q = _crc24q_table()


def crc24q(data: bytes | bytearray | memoryview) -> int:
    """CRC-24Q (Qualcomm) of ``data``, as used by RTCM3 (RTCM 10403.3 section 4.2)."""
    crc = 0
    for octet in bytes(data):
        crc = ((crc << 8) & 0xFFFFFF) ^ _CRC24Q[(crc >> 16) ^ octet]
    return crc


def payload_len(header: bytes) -> int | None:
    """Payload length from the 3-byte header; None when a reserved bit is set or the length
    is zero (a message holds at least its 12-bit number)."""
    if header[1] & 0xFC:
        return None
    n = ((header[1] & 0x03) << 8) | header[2]
    return n if n > 0 else None


def checksum_ok(frame: bytes) -> bool:
    """The trailing CRC-24Q of a whole frame matches header and payload."""
    return crc24q(frame[:-3]) == int.from_bytes(frame[-3:], "big")


FRAMING = BinaryFraming(
    sync=bytes((PREAMBLE,)),
    header_len=HEADER_LEN,
    trailer_len=3,
    payload_len=payload_len,
    check=checksum_ok,
    max_payload=MAX_PAYLOAD,
)

BDS_MSM = {1124: 4, 1125: 5, 1126: 6, 1127: 7}
"""BDS MSM message numbers and their MSM level."""
OTHER_MSM: dict[int, tuple[GnssSystem, int]] = {
    **{1070 + k: (GnssSystem.GPS, k) for k in (4, 5, 6, 7)},
    **{1090 + k: (GnssSystem.GAL, k) for k in (4, 5, 6, 7)},
}
"""GPS (1074-1077) and Galileo (1094-1097) MSM numbers: system and MSM level; read when the
mapper's ``systems`` include theirs (issue 19)."""
OTHER_MSM_TIME_DF = {GnssSystem.GPS: "DF004", GnssSystem.GAL: "DF248"}
"""The epoch time field of an MSM: GPS TOW [ms] (DF004), Galileo GST TOW [ms] (DF248;
GST = GPST to tens of ns, OS SIS ICD 5.1.8)."""
OTHER_MSM_SIGNALS: dict[GnssSystem, dict[int, str]] = {
    GnssSystem.GPS: {2: "1C"},  # L1 C/A (Table 3.5-91)
    GnssSystem.GAL: {2: "1C", 4: "1B", 5: "1X"},  # E1 C, B, B+C (Table 3.5-99)
}
"""The MSM signal IDs read per system: the signal bdsfix ranges on (RINEX code)."""

EPH_BDS = 1042


@dataclass(frozen=True, slots=True)
class EphWeek:
    """Where a non-BDS ephemeris message carries its week, t_oe and t_oc (RTCM 10403.3
    section 3.5.6 ff.): the week field modulo ``modulus`` counts from GPS week ``offset``."""

    system: str
    week_df: str
    toe_df: str
    toc_df: str
    modulus: int
    offset: int = 0


EPH_WEEKS: dict[int, EphWeek] = {
    1019: EphWeek("GPS", "DF076", "DF093", "DF081", 1024),  # DF076 10 bits
    1044: EphWeek("QZSS", "DF452", "DF442", "DF430", 1024),  # 10 bits, GPS week numbering
    1045: EphWeek("Galileo F/NAV", "DF289", "DF304", "DF293", 4096, GST_GPS_WEEK_OFFSET),
    1046: EphWeek("Galileo I/NAV", "DF289", "DF304", "DF293", 4096, GST_GPS_WEEK_OFFSET),
}
"""Ephemerides of other systems whose week and t_oe give the stream a week, or are compared
with it once it has one (:meth:`~drivers.framing.WeekContext.set_approx`); the week they
carry is that of their transmission (:meth:`~drivers.framing.WeekContext.toe_week`). The
1042 BDS week, 13 bits from BDT week 0, comes with the ephemeris itself."""
USED_MESSAGES = frozenset({*BDS_MSM, EPH_BDS, *EPH_WEEKS})
EPH_OF_SYSTEM = {1019: GnssSystem.GPS, 1046: GnssSystem.GAL}
"""Ephemeris messages mapped to :class:`Ephemeris` when their system is read: GPS 1019 and
Galileo I/NAV 1046 (E1 users take the I/NAV clock and BGD(E1,E5b); F/NAV 1045 gives the
week only)."""

GPS_1019_FIELDS: tuple[tuple[str, str, bool], ...] = (
    # (Ephemeris attribute, data field, in semicircles) RTCM 10403.3 Table 3.5-21
    ("af0_s", "DF084", False), ("af1_s_s", "DF083", False), ("af2_s_s2", "DF082", False),
    ("sqrt_a_sqrt_m", "DF092", False), ("e", "DF090", False), ("i0_rad", "DF097", True),
    ("omega0_rad", "DF095", True), ("omega_rad", "DF099", True), ("m0_rad", "DF088", True),
    ("delta_n_rad_s", "DF087", True), ("omega_dot_rad_s", "DF100", True),
    ("idot_rad_s", "DF079", True), ("cuc_rad", "DF089", False), ("cus_rad", "DF091", False),
    ("crc_m", "DF098", False), ("crs_m", "DF086", False), ("cic_rad", "DF094", False),
    ("cis_rad", "DF096", False),
)  # fmt: skip
GAL_1046_FIELDS: tuple[tuple[str, str, bool], ...] = (
    # RTCM 10403.3 Table 3.5-114 (I/NAV)
    ("af0_s", "DF296", False), ("af1_s_s", "DF295", False), ("af2_s_s2", "DF294", False),
    ("sqrt_a_sqrt_m", "DF303", False), ("e", "DF301", False), ("i0_rad", "DF308", True),
    ("omega0_rad", "DF306", True), ("omega_rad", "DF310", True), ("m0_rad", "DF299", True),
    ("delta_n_rad_s", "DF298", True), ("omega_dot_rad_s", "DF311", True),
    ("idot_rad_s", "DF292", True), ("cuc_rad", "DF300", False), ("cus_rad", "DF302", False),
    ("crc_m", "DF309", False), ("crs_m", "DF297", False), ("cic_rad", "DF305", False),
    ("cis_rad", "DF307", False),
)  # fmt: skip


MSM_RANGE = range(1071, 1138)
"""All MSM numbers (GPS 107x ... IRNSS 113x); their header layout is common."""


@dataclass(frozen=True, slots=True)
class MsmLayout:
    """Which data fields an MSM level carries (RTCM 10403.3 Tables 3.5-78 ff.)."""

    fine_pr: str
    cnr: str
    lock: str
    rates: bool


MSM_LAYOUT: dict[int, MsmLayout] = {
    4: MsmLayout(fine_pr="DF400", cnr="DF403", lock="DF402", rates=False),
    5: MsmLayout(fine_pr="DF400", cnr="DF403", lock="DF402", rates=True),
    6: MsmLayout(fine_pr="DF405", cnr="DF408", lock="DF407", rates=False),
    7: MsmLayout(fine_pr="DF405", cnr="DF408", lock="DF407", rates=True),
}

BDS_MSM_SIGNALS: dict[int, str] = {
    2: "2I", 3: "2Q", 4: "2X", 8: "6I", 9: "6Q", 10: "6X", 14: "7I", 15: "7Q", 16: "7X",
    22: "5D", 23: "5P", 24: "5X", 25: "7D", 30: "1D", 31: "1P", 32: "1X",
}  # fmt: skip
"""BDS MSM signal ID -> RINEX observation code (RTCM 10403.3 Table 3.5-108)."""

B1I_CODE = "2I"
ROUGH_INT_MS_UNKNOWN = 255  # DF397
FINE_PR_INVALID_MS = -(2.0**-10)  # DF400 raw -2^14 * 2^-24 ms; DF405 raw -2^19 * 2^-29 ms
ROUGH_RATE_INVALID_M_S = -8192  # DF399 raw 0x2000
FINE_RATE_INVALID_M_S = -16384 * 1e-4  # DF404 raw 0x4000


def message_number(raw: bytes) -> int:
    """RTCM3 message number (DF002, first 12 payload bits) of a complete frame."""
    return ((raw[3] << 4) | (raw[4] >> 4)) if len(raw) >= 5 else 0


def msm_multiple_message_bit(raw: bytes) -> bool:
    """DF393 of any MSM frame: payload bit 54 (after DF002, DF003 and the 30-bit epoch)."""
    return bool((raw[3 + 6] >> 1) & 1)


def msm_lock_time_s(level: int, indicator: int) -> float:
    """Minimum lock time [s] from DF402 (Table 3.5-74) or DF407 (Table 3.5-75)."""
    if level in (4, 5):
        return 0.0 if indicator == 0 else 2.0 ** (indicator + 4) * 1e-3
    if indicator < 64:
        return indicator * 1e-3
    if indicator > 704:
        return math.nan
    k = indicator // 32 - 1
    return 2.0**k * (indicator - 32 * k) * 1e-3


def msm_cells(msg: Any) -> list[tuple[int, int, int]]:
    """(satellite index, satellite ID, signal ID) per cell, in cell order (Table 3.5-78).

    Satellite mask DF394 (64 bits) and signal mask DF395 (32 bits) are read MSB first
    (bit 1 = ID 1); the cell mask DF396 has NSat*NSig bits, satellite-major.
    """
    sats = [i + 1 for i in range(64) if (msg.DF394 >> (63 - i)) & 1]
    sigs = [j + 1 for j in range(32) if (msg.DF395 >> (31 - j)) & 1]
    n = len(sats) * len(sigs)
    cells = []
    for si, sat in enumerate(sats):
        for gi, sig in enumerate(sigs):
            if (msg.DF396 >> (n - 1 - (si * len(sigs) + gi))) & 1:
                cells.append((si, sat, sig))
    return cells


@dataclass(slots=True)
class _Cell:
    level: int
    pr_m: float
    frac_pr_m: float
    cn0_dbhz: float
    doppler_hz: float
    lock_s: float
    signal: str = B1I_CODE


def ephemeris_from_1042(msg: Any) -> Ephemeris:
    """Map a pyrtcm 1042 message to :class:`Ephemeris` (BDT week and seconds of week).

    DF490 (URAI) becomes the upper bound of its URA interval, URAI 15 (> 6144 m) infinity,
    as for decoded subframes (:data:`service.core.constants.URA_M`), so that the store refuses it.
    """
    values: dict[str, Any] = {}
    for name, df, factor in EPH_1042_FIELDS:
        v = getattr(msg, df)
        values[name] = int(v) if name in EPH_1042_INT_FIELDS else float(v) * factor
    ura_index = int(msg.DF490)
    return Ephemeris(
        prn=sat_id(GnssSystem.BDS, int(msg.DF488)),
        ura_m=URA_M[ura_index] if 0 <= ura_index < len(URA_M) else math.nan,
        source="rtcm",
        **values,
    )


def _toe_in_week(msg: Any, spec: EphWeek) -> float | None:
    """The t_oe [s] of a non-BDS ephemeris message, or None when its t_oe or t_oc is no time
    of week: DF093/DF081 (16 bits x 16 s) reach 1,048,560 s, DF304/DF293 (14 bits x 60 s)
    983,040 s. Such a message gives neither a week nor a set (wrapping the time into the
    week would make one of the damage)."""
    toe = float(getattr(msg, spec.toe_df))
    if 0.0 <= toe < WEEK_S and 0.0 <= float(getattr(msg, spec.toc_df)) < WEEK_S:
        return toe
    return None


def _same_time(week_a: int, tow_a: float, week_b: int, tow_b: float) -> bool:
    """Two MSM times are one epoch (times of week only while a week is unknown)."""
    if UNKNOWN_WEEK in (week_a, week_b):
        return abs((tow_a - tow_b + WEEK_S / 2) % WEEK_S - WEEK_S / 2) <= 1e-6
    return abs(diff_s(week_a, tow_a, week_b, tow_b)) <= 1e-6


class RtcmMapper:
    """Stateful mapper: RTCM3 frames in stream order -> events.

    BDS MSM cells of one epoch are merged (e.g. 1126 and 1127 of the same time: the higher
    MSM level wins a duplicate cell). The epoch is emitted when the stream's last MSM of
    that time arrives (DF393 = 0 on any MSM), when a BDS MSM of another time arrives, or
    on :meth:`flush`.
    """

    def __init__(
        self,
        counters: Counters | None = None,
        week: WeekContext | None = None,
        *,
        source: str = "rtcm",
        systems: frozenset[str] | str = MSM_SYSTEM.value,
    ) -> None:
        self.counters = counters if counters is not None else Counters()
        self.week = week if week is not None else WeekContext()
        self.source = source
        self.systems = frozenset(systems)
        self._msm = {n: v for n, v in OTHER_MSM.items() if v[0].value in self.systems}
        self._eph = {n for n, s in EPH_OF_SYSTEM.items() if s.value in self.systems}
        self._used = USED_MESSAGES | self._msm.keys()
        self._time: tuple[int, float] | None = None
        self._cells: dict[str, _Cell] = {}

    def on_frame(self, raw: bytes) -> list[Event]:
        """Map one checksum-valid RTCM3 frame (library errors propagate to the caller)."""
        number = message_number(raw)
        self.counters[f"rtcm:{number}"] += 1
        if number in EPH_WEEKS and self.week.exact and number not in self._eph:
            number = 0  # the week is the receiver's own: nothing to read there
        if number in self._used:
            # the framing has checked the CRC-24Q (checksum_ok): pyrtcm need not again
            return self.on_message(RTCMReader.parse(raw, validate=VALNONE))
        self.counters["rtcm_ignored"] += 1
        if number in MSM_RANGE and len(raw) > 10 and not msm_multiple_message_bit(raw):
            return self.flush()
        return []

    def on_message(self, msg: Any) -> list[Event]:
        """Map one parsed pyrtcm message."""
        number = int(msg.identity)
        if number == EPH_BDS:
            return self._on_1042(msg)
        if number in BDS_MSM:
            return self._on_msm(msg, BDS_MSM[number])
        if number in self._msm:
            return self._on_msm(msg, self._msm[number][1], self._msm[number][0])
        out: list[Event] = []
        if number in EPH_WEEKS:
            spec = EPH_WEEKS[number]
            toe = _toe_in_week(msg, spec)
            if toe is None:  # counted once per message: it gives neither a week nor a set
                self.counters["eph_bad_toe"] += 1
                return out
            week = self.week.broadcast_week(
                int(getattr(msg, spec.week_df)), spec.modulus, spec.offset
            )
            week, moved = self.week.toe_week(week, toe)  # (the week of transmission)
            if moved:
                self.counters["eph_week_handovers"] += 1
            self._on_eph_week(number, week, toe)
            if number in self._eph:
                out = self._on_other_eph(msg, number, week, toe)
        return out

    def flush(self) -> list[Event]:
        """Emit the pending BDS epoch, if any."""
        if self._time is None:
            return []
        (week, tow), cells = self._time, self._cells
        self._time, self._cells = None, {}
        if not cells:
            return []
        prns = sorted(cells)
        col = {
            name: np.array([getattr(cells[p], name) for p in prns], dtype=float)
            for name in ("pr_m", "frac_pr_m", "cn0_dbhz", "doppler_hz", "lock_s")
        }
        signals = [cells[p].signal for p in prns]
        self.counters["epochs_rtcm"] += 1
        return [
            MeasurementEpoch.from_columns(
                week,
                tow,
                prns,
                signals,
                col["pr_m"],
                frac_pr_m=col["frac_pr_m"],
                period_s=_BDS.code_period_s,
                cn0_dbhz=col["cn0_dbhz"],
                doppler_hz=col["doppler_hz"],
                lock_s=col["lock_s"],
                source=self.source,
            )
        ]

    # --- 1042 -----------------------------------------------------------------------------
    def _on_1042(self, msg: Any) -> list[Event]:
        if not 1 <= int(msg.DF488) <= _BDS.prn_max:
            self.counters["eph_bad_prn"] += 1
            return []
        eph = ephemeris_from_1042(msg)
        if 0.0 <= eph.toe_sow_s < WEEK_S and 0.0 <= eph.toc_sow_s < WEEK_S:
            gps_week, gps_tow = bdt_to_gpst(eph.week, eph.toe_sow_s)
            if not self.week.set_approx(gps_week, gps_tow, "RTCM 1042 (BDS ephemeris)"):
                self.counters["eph_week_disagrees"] += 1
        else:
            # DF505/DF493 (17 bits, 8 s) can hold up to 1,048,568 s; beyond a week the set
            # breaks the ICD (5.2.4.9): no week from it, and the store refuses it
            # (service.core.ephemeris.ephemeris_problem, check time_of_week)
            self.counters["eph_bad_toe"] += 1
        self.counters["ephemerides_rtcm"] += 1
        return [eph]

    def _on_other_eph(self, msg: Any, number: int, week: int, toe: float) -> list[Event]:
        """A GPS 1019 or Galileo I/NAV 1046 as an :class:`Ephemeris` put on BDT (GPST and
        GST - 14 s, week - 1356, as every set is held); ``week``: its GPS week, from the
        broadcast one; ``toe``: its t_oe [s], checked to be a time of the week
        (:func:`_toe_in_week`)."""
        system = EPH_OF_SYSTEM[number]
        spec = EPH_WEEKS[number]
        if system is GnssSystem.GPS:
            number_df, fields = "DF009", GPS_1019_FIELDS
        else:
            number_df, fields = "DF252", GAL_1046_FIELDS
        n = int(getattr(msg, number_df))
        if not 1 <= n <= SYSTEM_CONSTANTS[system].prn_max:
            self.counters["eph_bad_prn"] += 1
            return []
        values: dict[str, Any] = {
            name: float(getattr(msg, df)) * (ICD_PI if semi else 1.0) for name, df, semi in fields
        }
        bdt_week, toe_bdt = gpst_to_bdt(week, toe)
        toc_bdt = gpst_sow_to_bdt_sow(float(getattr(msg, spec.toc_df)))
        if system is GnssSystem.GPS:
            ura_index = int(msg.DF077)
            extra: dict[str, Any] = {
                "tgd1_s": float(msg.DF101),
                "health": int(msg.DF102),
                "aode": int(msg.DF071),
                "aodc": int(msg.DF085),
                "ura_m": URA_M[ura_index] if 0 <= ura_index < len(URA_M) else math.nan,
            }
        else:  # E1-B and E5b health and validity, as RINEX packs them (Table A8)
            health = inav_health(int(msg.DF317), int(msg.DF316), int(msg.DF288), int(msg.DF287))
            extra = {
                "tgd1_s": float(msg.DF313),
                "tgd2_s": float(msg.DF312),
                "health": health,
                "aode": int(msg.DF290),
                "ura_m": galileo_sisa_m(int(msg.DF286)),
            }
        self.counters[f"ephemerides_rtcm_{system.value}"] += 1
        return [
            Ephemeris(
                prn=sat_id(system, n),
                week=bdt_week,
                toe_sow_s=toe_bdt,
                toc_sow_s=toc_bdt,
                source="rtcm",
                **values,
                **extra,
            )
        ]

    def _on_eph_week(self, number: int, week: int, toe: float) -> None:
        """The GPS ``week`` and t_oe [s] of a non-BDS ephemeris message for the stream's
        week (``eph_week_<number>`` when taken); one more than a day from the stream's time
        (or the receiver's own, which it never replaces) is counted ``eph_week_disagrees``,
        as a 1042's is."""
        exact = self.week.exact
        if not self.week.set_approx(
            week, toe, f"RTCM {number} ({EPH_WEEKS[number].system} ephemeris)"
        ):
            self.counters["eph_week_disagrees"] += 1
        elif not exact:
            self.counters[f"eph_week_{number}"] += 1

    # --- MSM ------------------------------------------------------------------------------
    def _on_msm(self, msg: Any, level: int, system: GnssSystem = MSM_SYSTEM) -> list[Event]:
        bds = system is MSM_SYSTEM
        self.counters["msm_bds" if bds else f"msm_{system.value}"] += 1
        ms = int(msg.DF427 if bds else getattr(msg, OTHER_MSM_TIME_DF[system]))
        if not 0 <= ms < WEEK_S * 1000:
            self.counters["msm_bad_time"] += 1
            return []
        tow = (ms * 1e-3 + (BDT_GPST_OFFSET_S if bds else 0.0)) % WEEK_S
        week = self.week.resolve(tow)
        if week is None:
            self.counters["msm_no_week"] += 1
            week = UNKNOWN_WEEK
        out: list[Event] = []
        if self._time is not None and not _same_time(week, tow, *self._time):
            out = self.flush()
        self._time = (week, tow)  # a week that became known within the epoch is kept
        self._merge(msg, level, system)
        if not int(msg.DF393):
            out += self.flush()
        return out

    def _merge(self, msg: Any, level: int, system: GnssSystem = MSM_SYSTEM) -> None:
        lay = MSM_LAYOUT[level]
        bds = system is MSM_SYSTEM
        signals = OTHER_MSM_SIGNALS.get(system, {})
        wavelength_m = C_M_S / SYSTEM_CONSTANTS[system].carrier_hz
        for k, (si, sat, sig_id) in enumerate(msm_cells(msg), start=1):
            code = B1I_CODE if bds and BDS_MSM_SIGNALS.get(sig_id) == B1I_CODE else None
            if not bds:
                code = signals.get(sig_id)
            if code is None:
                self.counters["msm_cells_other_signal"] += 1
                continue
            s = si + 1
            int_ms = int(getattr(msg, f"DF397_{s:02d}"))
            mod_ms = float(getattr(msg, f"DF398_{s:02d}"))
            fine_ms = float(getattr(msg, f"{lay.fine_pr}_{k:02d}"))
            if fine_ms == FINE_PR_INVALID_MS:
                self.counters["msm_cells_invalid"] += 1
                continue
            if int_ms == ROUGH_INT_MS_UNKNOWN:
                pr = math.nan
                frac = LIGHT_MS_M * ((mod_ms + fine_ms) % B1I_CODE_PERIOD_MS)
                self.counters["msm_cells_fractional"] += 1
            else:
                pr = LIGHT_MS_M * (int_ms + mod_ms + fine_ms)
                frac = float(np.mod(pr, B1I_CODE_RANGE_M))
            cnr = float(getattr(msg, f"{lay.cnr}_{k:02d}"))
            doppler = math.nan
            if lay.rates:
                rough = float(getattr(msg, f"DF399_{s:02d}"))
                fine = float(getattr(msg, f"DF404_{k:02d}"))
                if rough != ROUGH_RATE_INVALID_M_S and abs(fine - FINE_RATE_INVALID_M_S) > 1e-9:
                    doppler = -(rough + fine) / wavelength_m
            cell = _Cell(
                level=level,
                pr_m=pr,
                frac_pr_m=frac,
                cn0_dbhz=cnr if cnr > 0 else math.nan,
                doppler_hz=doppler,
                lock_s=msm_lock_time_s(level, int(getattr(msg, f"{lay.lock}_{k:02d}"))),
                signal=code,
            )
            prn = sat_id(system, sat)
            old = self._cells.get(prn)
            if old is None:
                self.counters["msm_cells_b1i" if bds else f"msm_cells_{system.value}"] += 1
            else:
                self.counters["msm_duplicate_cells"] += 1
                if old.level >= level:
                    continue
            self._cells[prn] = cell
