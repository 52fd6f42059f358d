"""Septentrio SBF blocks to bdsfix events: framing; BeiDou, GPS and Galileo blocks mapped.

Reference: Septentrio "mosaic-X5 Reference Guide" (firmware 4.x), section "SBF Outline"
(block header, CRC, ID, length; "Do-Not-Use" values), "Signal Type" (signal numbers) and
"Satellite ID" (SVID) tables, and the block definitions of MeasEpoch (4027), BDSNav (4081),
BDSIon (4120), BDSRaw (4047), PVTGeodetic (4007) and, for GPS and Galileo, GPSNav (5891),
GPSIon (5893), GALNav (4002), GALIon (4030) and GALGstGps (4032). Nav, iono, raw and PVT
blocks are parsed by pysbf2 (which applies the scale factors); MeasEpoch, which arrives every
epoch and whose signed type-2 offsets (CodeOffsetMSB, DopplerOffsetMSB) pysbf2 1.0.7 reads
unsigned, is unpacked here with :mod:`struct` (the tests compare the two on every row of the
real capture, pysbf2's code offset sign-corrected).

- Frame: ``$@``, CRC u16, ID u16 (bits 0-12 block number, 13-15 revision), Length u16 (the
  whole block, a multiple of 4), body. The CRC is CRC-16-CCITT (polynomial 0x1021, initial
  0) over ID, Length and body (:data:`FRAMING`).
- Time: every block starts with TOW (u4, ms) and WNc (u2, continuous week), both on GPST
  (4294967295 / 65535: do-not-use, counted ``sbf_bad_time``).
- MeasEpoch: one type-1 sub-block per satellite (its first signal), N2 type-2 sub-blocks for
  its other signals, as offsets from the type-1 values (code offset signed 3+16 bits of 1 mm,
  Doppler offset signed 5+16 bits of 1e-4 Hz after scaling the type-1 Doppler by the carrier
  ratio). The signal number is SigIdxLo, or 32 + ObsInfo bits 3-7 when SigIdxLo is 31.
  BeiDou (SVID 141-180: C01-C40, 223-245: C41-C63) B1I (signal 28) gives RINEX ``2I``: the
  full pseudorange, C/N0 (0.25 dB-Hz + 10, except GPS L1P/L2P), Doppler and lock time.
  Other BeiDou signals are counted (``meas_bds_other_signal``). GPS L1 C/A and Galileo E1
  rows are read the same way when their systems are asked for (``meas_G``, ``meas_E``;
  their other signals counted), other systems are counted (``meas_other_gnss``), as are
  signals of an auxiliary antenna (``meas_aux_antenna``), missing pseudoranges
  (``meas_pr_invalid``) and implausible ones (``meas_pr_implausible``).
  Each MeasEpoch is one :class:`~service.core.types.MeasurementEpoch` (``epochs_sbf``),
  tagged with the block's TOW/WNc, the receiver's own time (the week is exact).
- BDSNav becomes an :class:`~service.core.types.Ephemeris` (BDT week WNt_oe, t_oe and t_oc
  in BDT seconds; angles in semicircles times the ICD's pi, BDS-SIS-ICD-B1I-3.0 5.2.4.12;
  URA index to metres as for decoded subframes), ``ephemerides_sbf``.
- BDSIon becomes :class:`~service.core.types.KlobucharParams` (``system="BDS"``).
- BDSRaw on B1I (signal 28) with CRCPassed becomes a :class:`~service.core.types.NavSubframe`
  tagged with the block's time: NavBits holds the 300 bits MSB first in ten little-endian
  u4 (the 10 words of 30 bits, parity included); one failing the header checks is counted
  (``bdsraw_unmapped``), other signals and failed CRCs too (``bdsraw_other_signal``,
  ``bdsraw_crc_failed``).
- PVTGeodetic: the receiver's own fix becomes a :class:`~service.core.types.ReceiverFix`
  (``sbf-pvtgeodetic``), carried beside bdsfix's fixes for comparison, and is kept as
  :attr:`SbfMapper.receiver_fix` (ECEF) (``sbf_pvt``; ``sbf_pvt_no_fix`` when its mode is
  0 or a value is do-not-use).

Counter keys: ``sbf:<Name>`` per block, ``sbf_ignored``, ``epochs_sbf``, ``sbf_bad_time``,
``meas_other_gnss``, ``meas_bds_other_signal``, ``meas_aux_antenna``, ``meas_pr_invalid``,
``meas_pr_implausible``, ``ephemerides_sbf``, ``eph_bad_prn``, ``iono_sbf``, ``subframes``,
``bdsraw_other_signal``, ``bdsraw_crc_failed``, ``bdsraw_unmapped``, ``sbf_pvt``,
``sbf_pvt_no_fix``; with GPS/Galileo: ``meas_G``, ``meas_E``, ``meas_G_other_signal``,
``meas_E_other_signal``, ``ephemerides_sbf_G``, ``ephemerides_sbf_E``, ``galnav_fnav``,
``galnav_no_e1b_health`` (a GALNav block whose E1-B health is flagged not available:
refused), ``eph_bad_week``, ``eph_week_disagrees`` (a BDSNav, GPSNav or GALNav week and
t_oe more than a day from the stream's time, the receiver's own once a MeasEpoch has given
it: not taken, the set passed on, as RTCM's; see :class:`~drivers.framing.WeekContext`),
``eph_bad_toe`` (a
BDSNav, GPSNav or GALNav whose t_oe or t_oc is no time of the week, as RTCM's: no week is
taken from it, a GPSNav/GALNav gives no set, a BDSNav is passed on for the ephemeris store
to refuse), ``iono_sbf_G``,
``sbf_gal_ion_unused``, ``ggto_sbf``,
``gpsraw_crc_failed``, ``gpsraw_unmapped``, ``galraw_other_signal``, ``galraw_crc_failed``,
``galraw_unmapped``.
"""

from __future__ import annotations

import binascii
import logging
import math
import struct
from typing import Any

import numpy as np
from pysbf2 import SBFMessage
from pysbf2.sbfhelpers import block2idrev
from pysbf2.sbftypes_core import SBF_MSGIDS

from drivers.framing import BinaryFraming, Event, WeekContext
from service.core.bds import nav_type as bds_nav_type
from service.core.bds_nav import b1i_subframe
from service.core.constants import ICD_PI, URA_M, WEEK_S
from service.core.counters import Counters
from service.core.errors import DecodeError
from service.core.gal_nav import (
    WN0G_MODULUS,
    galileo_sisa_m,
    inav_health,
    inav_subframe,
    inav_word_of_parts,
    week_near,
)
from service.core.geometry import geodetic_to_ecef
from service.core.gps_nav import lnav_subframe
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem, sat_id
from service.core.timebase import bdt_to_gpst, gpst_sow_to_bdt_sow, gpst_to_bdt
from service.core.types import (
    Ephemeris,
    KlobucharParams,
    MeasurementEpoch,
    ReceiverFix,
    TimeOffset,
)

log = logging.getLogger(__name__)

_BDS = SYSTEM_CONSTANTS[GnssSystem.BDS]

# --- frame ("SBF Outline": block header) --------------------------------------------------
SYNC = b"$@"
HEADER_LEN = 8  # sync, CRC, ID, Length
DEFAULT_MAX_PAYLOAD = 16384
"""Longest block body the framer accepts by default [bytes] (the length field allows
65535; the largest block of the shared captures, BBSamples, is 4032 bytes)."""


def payload_len(header: bytes) -> int | None:
    """Body length of a block from its 8-byte header (Length u16 LE counts the whole block
    and is a multiple of 4); None for an impossible length."""
    length = header[6] | (header[7] << 8)
    if length < HEADER_LEN or length % 4:
        return None
    return length - HEADER_LEN


def crc16(data: bytes | bytearray | memoryview) -> int:
    """CRC-16-CCITT (polynomial 0x1021, initial value 0), as SBF computes it."""
    return binascii.crc_hqx(bytes(data), 0)


def checksum_ok(frame: bytes) -> bool:
    """The CRC field (bytes 2-3, LE) matches ID, Length and body."""
    return crc16(frame[4:]) == frame[2] | (frame[3] << 8)


def parse_block(raw: bytes) -> Any:
    """pysbf2's message of one block whose CRC the framing has checked (:func:`checksum_ok`):
    what ``SBFReader.parse(raw)`` builds (its body: ID and revision, CRC, length, payload
    with bit fields parsed and scale factors applied), without the CRC that parse computes
    again, in Python, whatever its ``validate`` says (pysbf2 1.0.7): that CRC was a third of
    the CPU time of mapping the Leuven capture's navigation blocks."""
    msgid, revno = block2idrev(raw[4:6])
    return SBFMessage(
        msgid,
        revno,
        raw[2:4],
        int.from_bytes(raw[6:8], "little"),
        payload=raw[8:],
        parsebitfield=1,
        scaling=True,
    )


FRAMING = BinaryFraming(
    sync=SYNC,
    header_len=HEADER_LEN,
    trailer_len=0,
    payload_len=payload_len,
    check=checksum_ok,
    max_payload=DEFAULT_MAX_PAYLOAD,
)

# --- block numbers -----------------------------------------------------------------------
MEAS_EPOCH, PVT_GEODETIC, BDS_RAW, BDS_NAV, BDS_ION = 4027, 4007, 4047, 4081, 4120
GPS_NAV, GPS_ION, GAL_NAV, GAL_ION, GAL_GST_GPS = 5891, 5893, 4002, 4030, 4032
GPS_RAW_CA = 4017
GAL_RAW_INAV = 4023
_PARSED = frozenset({PVT_GEODETIC, BDS_RAW, BDS_NAV, BDS_ION})
_PARSED_GPS = frozenset({GPS_NAV, GPS_ION, GPS_RAW_CA})
_PARSED_GAL = frozenset({GAL_NAV, GAL_ION, GAL_GST_GPS, GAL_RAW_INAV})
_OTHER_NAV = frozenset({GPS_NAV, GPS_ION, GAL_NAV, GAL_ION, GAL_GST_GPS})
_NAV_BLOCKS = {GnssSystem.GPS: _PARSED_GPS, GnssSystem.GAL: _PARSED_GAL}
"""Navigation blocks of GPS and Galileo, parsed when the mapper's ``systems`` include the
system (else counted ``sbf_ignored``)."""

TOW_DNU = 4294967295
WNC_DNU = 65535

# --- signals ("Signal Type" table) and satellites ("Satellite ID" table) ------------------
SIG_B1I = 28
SIG_GPS_L1CA = 0
SIG_GAL_E1 = 17
OTHER_SIGNALS: dict[GnssSystem, tuple[int, str]] = {
    GnssSystem.GPS: (SIG_GPS_L1CA, "1C"),
    GnssSystem.GAL: (SIG_GAL_E1, "1C"),
}
"""MeasEpoch signals of GPS (L1 C/A, signal 0) and Galileo (E1 B/C, signal 17, tracked on
the pilot: RINEX ``1C``) read when the mapper's ``systems`` include them (issue 19)."""
_GAL_RAW_SIGNALS = {17: "1B", 21: "7I"}
"""GALRawINAV signals whose I/NAV words are read: E1-B (17) and E5b-I (21)."""
GAL_SOURCE_INAV = 2
"""GALNav/GALIon/GALGstGps ``Source``: 2 I/NAV, 16 F/NAV (Reference Guide, GALNav)."""
BGD_DNU_S = -2e10
SIG_CARRIER_HZ: dict[int, float] = {
    0: 1575.42e6,  # GPS L1CA
    1: 1575.42e6,  # GPS L1P
    2: 1227.60e6,  # GPS L2P
    3: 1227.60e6,  # GPS L2C
    4: 1176.45e6,  # GPS L5
    5: 1575.42e6,  # GPS L1C
    13: 1575.42e6,  # BDS B1C
    14: 1176.45e6,  # BDS B2a
    17: 1575.42e6,  # GAL E1
    19: 1278.75e6,  # GAL E6
    20: 1176.45e6,  # GAL E5a
    21: 1207.14e6,  # GAL E5b
    22: 1191.795e6,  # GAL E5 AltBOC
    24: 1575.42e6,  # SBAS L1
    25: 1176.45e6,  # SBAS L5
    28: _BDS.carrier_hz,  # BDS B1I
    29: 1207.14e6,  # BDS B2I
    30: 1268.52e6,  # BDS B3I
    34: 1207.14e6,  # BDS B2b
}
"""Carrier frequency by signal number, for the Doppler of a type-2 sub-block (its offset is
from the type-1 Doppler scaled by the carrier ratio); a pair not listed gives NaN."""


def bds_prn(svid: int) -> int | None:
    """BeiDou PRN of an SBF SVID (141-180: C01-C40, 223-245: C41-C63), else None."""
    if 141 <= svid <= 180:
        return svid - 140
    if 223 <= svid <= 245:
        return svid - 182
    return None


def gps_prn(svid: int) -> int | None:
    """GPS PRN of an SBF SVID (1-37), else None."""
    return svid if 1 <= svid <= 37 else None


def gal_prn(svid: int) -> int | None:
    """Galileo PRN of an SBF SVID (71-106: E01-E36), else None."""
    return svid - 70 if 71 <= svid <= 106 else None


_PRN_OF = {GnssSystem.BDS: bds_prn, GnssSystem.GPS: gps_prn, GnssSystem.GAL: gal_prn}


def svid_system(svid: int) -> tuple[GnssSystem, int] | None:
    """(system, PRN) of a BeiDou, GPS or Galileo SVID, else None."""
    for system, of in _PRN_OF.items():
        n = of(svid)
        if n is not None:
            return system, n
    return None


def signal_number(sig_lo: int, obs_info: int) -> int:
    """The signal number of a measurement: SigIdxLo, or 32 + ObsInfo bits 3-7 when it is 31."""
    return 32 + (obs_info >> 3) if sig_lo == 31 else sig_lo


def cn0_dbhz(raw: int, sig: int) -> float:
    """C/N0 of a MeasEpoch CN0 field: 0.25 dB-Hz, + 10 dB-Hz except GPS L1P/L2P (1, 2)."""
    if raw == 255:
        return math.nan
    return raw * 0.25 + (0.0 if sig in (1, 2) else 10.0)


# MeasEpoch layout: header after the block header, type-1 and type-2 sub-blocks
_ME_HEAD = struct.Struct("<IHBBBBBB")  # TOW WNc N1 SB1Length SB2Length CommonFlags Cum Res
_ME_T1 = struct.Struct("<BBBBIiHbBHBB")  # RxChannel Type SVID Misc CodeLSB Doppler ...
_ME_T2 = struct.Struct("<BBBBbBHHH")  # Type LockTime CN0 OffsetsMSB CarrierMSB ObsInfo ...
DOPPLER_DNU = -(2**31)

PR_MAX_M = 1e8
"""Upper bound of a plausible pseudorange [m] (see :data:`drivers.ubx.PR_MAX_M`)."""


def _signed(value: int, bits: int) -> int:
    return value - (1 << bits) if value & (1 << (bits - 1)) else value


def meas_epoch_rows(
    raw: bytes,
) -> tuple[int, int, list[tuple[int, int, int, float, float, float, float]]]:
    """Unpack a whole MeasEpoch block: (TOW ms, WNc, rows), one row per signal:
    (SVID, signal number, antenna, pseudorange m, Doppler Hz, C/N0 dB-Hz, lock time s),
    NaN for a do-not-use value. DecodeError when the sub-blocks overrun the block."""
    body = memoryview(raw)[HEADER_LEN:]
    if len(body) < _ME_HEAD.size:
        raise DecodeError(f"MeasEpoch of {len(raw)} bytes: no header")
    tow, wnc, n1, sb1, sb2, _flags, _jumps, _res = _ME_HEAD.unpack_from(body)
    if sb1 < _ME_T1.size or sb2 < _ME_T2.size:
        raise DecodeError(f"MeasEpoch sub-block lengths {sb1}/{sb2} too short")
    rows: list[tuple[int, int, int, float, float, float, float]] = []
    at = _ME_HEAD.size
    for _ in range(n1):
        if at + sb1 > len(body):
            raise DecodeError("MeasEpoch type-1 sub-blocks overrun the block")
        (_ch, typ, svid, misc, code_lsb, dop, _cl, _cm, cn0, lock, obs, n2) = _ME_T1.unpack_from(
            body, at
        )
        at += sb1
        sig1 = signal_number(typ & 0x1F, obs)
        ant1 = typ >> 5
        code_msb = misc & 0x0F
        pr1 = math.nan if code_msb == 0 and code_lsb == 0 else (code_msb * 2**32 + code_lsb) * 1e-3
        dop1 = math.nan if dop == DOPPLER_DNU else dop * 1e-4
        lock1 = math.nan if lock == 65535 else float(lock)
        rows.append((svid, sig1, ant1, pr1, dop1, cn0_dbhz(cn0, sig1), lock1))
        for _ in range(n2):
            if at + sb2 > len(body):
                raise DecodeError("MeasEpoch type-2 sub-blocks overrun the block")
            typ2, lock2, cn02, off_msb, _cm2, obs2, code_off, _cl2, dop_off = _ME_T2.unpack_from(
                body, at
            )
            at += sb2
            sig2 = signal_number(typ2 & 0x1F, obs2)
            pr2 = pr1 + (_signed(off_msb & 0x07, 3) * 65536 + code_off) * 1e-3
            f1, f2 = SIG_CARRIER_HZ.get(sig1), SIG_CARRIER_HZ.get(sig2)
            if f1 is None or f2 is None:
                dop2 = math.nan
            else:
                dop2 = dop1 * f2 / f1 + (_signed(off_msb >> 3, 5) * 65536 + dop_off) * 1e-4
            lock2_s = math.nan if lock2 == 255 else float(lock2)
            rows.append((svid, sig2, typ2 >> 5, pr2, dop2, cn0_dbhz(cn02, sig2), lock2_s))
    return tow, wnc, rows


def _block_number(raw: bytes) -> int:
    return (raw[4] | (raw[5] << 8)) & 0x1FFF


def block_name(number: int) -> str:
    """pysbf2's name of a block number, or ``0x<hex>`` for one it does not know."""
    entry = SBF_MSGIDS.get(number)
    return str(entry[0]) if entry is not None else f"{number:#06x}"


def ephemeris_from_bdsnav(msg: Any, prn: int) -> Ephemeris:
    """A pysbf2 BDSNav block as an :class:`Ephemeris` (BDT week and seconds of week)."""
    ura_index = int(msg.URA)
    return Ephemeris(
        prn=sat_id(GnssSystem.BDS, prn),
        week=int(msg.WNt_oe),
        toe_sow_s=float(msg.t_oe),
        toc_sow_s=float(msg.t_oc),
        af0_s=float(msg.a_f0),
        af1_s_s=float(msg.a_f1),
        af2_s_s2=float(msg.a_f2),
        sqrt_a_sqrt_m=float(msg.SQRT_A),
        e=float(msg.e),
        i0_rad=float(msg.i_0) * ICD_PI,
        omega0_rad=float(msg.OMEGA_0) * ICD_PI,
        omega_rad=float(msg.omega) * ICD_PI,
        m0_rad=float(msg.M_0) * ICD_PI,
        delta_n_rad_s=float(msg.DEL_N) * ICD_PI,
        omega_dot_rad_s=float(msg.OMEGADOT) * ICD_PI,
        idot_rad_s=float(msg.IDOT) * ICD_PI,
        cuc_rad=float(msg.C_uc),
        cus_rad=float(msg.C_us),
        crc_m=float(msg.C_rc),
        crs_m=float(msg.C_rs),
        cic_rad=float(msg.C_ic),
        cis_rad=float(msg.C_is),
        tgd1_s=float(msg.T_GD1),
        tgd2_s=float(msg.T_GD2),
        health=int(msg.SatH1),
        aode=int(msg.IODE),
        aodc=int(msg.IODC),
        ura_m=URA_M[ura_index] if 0 <= ura_index < len(URA_M) else math.nan,
        source="sbf",
    )


_KEPLER_SEMI = (
    ("i0_rad", "i_0"), ("omega0_rad", "OMEGA_0"), ("omega_rad", "omega"), ("m0_rad", "M_0"),
    ("delta_n_rad_s", "DEL_N"), ("omega_dot_rad_s", "OMEGADOT"), ("idot_rad_s", "IDOT"),
)  # fmt: skip
_KEPLER_PLAIN = (
    ("sqrt_a_sqrt_m", "SQRT_A"), ("e", "e"), ("cuc_rad", "C_uc"), ("cus_rad", "C_us"),
    ("crc_m", "C_rc"), ("crs_m", "C_rs"), ("cic_rad", "C_ic"), ("cis_rad", "C_is"),
    ("af0_s", "a_f0"), ("af1_s_s", "a_f1"), ("af2_s_s2", "a_f2"),
)  # fmt: skip
"""GPSNav/GALNav fields (the same names in both blocks): angles in semicircles, times the
ICD's pi (IS-GPS-200 20.3.3.4.3, OS SIS ICD 5.1.1)."""


def _kepler(msg: Any) -> dict[str, Any]:
    out: dict[str, Any] = {name: float(getattr(msg, f)) * ICD_PI for name, f in _KEPLER_SEMI}
    out.update({name: float(getattr(msg, f)) for name, f in _KEPLER_PLAIN})
    return out


def _times_in_week(msg: Any) -> bool:
    """Whether a BDSNav, GPSNav or GALNav block's t_oe and t_oc (u4 seconds: up to
    4,294,967,295, the do-not-use value) are times of the week, [0, 604800) s (BDS ICD B1I
    5.2.4.9, IS-GPS-200 20.3.4.5, Galileo OS SIS ICD 5.1.2: at most 604,784 s / 604,740 s).
    A GPS or Galileo set put on BDT would otherwise be wrapped into a later week, its time
    made of the damage."""
    return 0.0 <= float(msg.t_oe) < WEEK_S and 0.0 <= float(msg.t_oc) < WEEK_S


def ephemeris_from_gpsnav(msg: Any, prn: int, wnc: int) -> Ephemeris:
    """A pysbf2 GPSNav block (IS-GPS-200 subframes 1-3 as the receiver decoded them) as an
    :class:`Ephemeris` on BDT (GPST - 14 s, as every set is held). WNt_oe is the week
    modulo 1024, resolved against the block's WNc; t_oc shares t_oe's week."""
    week = week_near(int(msg.WNt_oe), 1024, wnc)
    bdt_week, toe_bdt = gpst_to_bdt(week, float(msg.t_oe))
    ura_index = int(msg.URA)
    return Ephemeris(
        prn=sat_id(GnssSystem.GPS, prn),
        week=bdt_week,
        toe_sow_s=toe_bdt,
        toc_sow_s=gpst_sow_to_bdt_sow(float(msg.t_oc)),
        tgd1_s=float(msg.T_gd),
        health=int(msg.health),
        aode=int(msg.IODE2),
        aodc=int(msg.IODC),
        ura_m=URA_M[ura_index] if 0 <= ura_index < len(URA_M) else math.nan,
        source="sbf",
        **_kepler(msg),
    )


def ephemeris_from_galnav(msg: Any, prn: int, wnc: int) -> Ephemeris:
    """A pysbf2 GALNav block of I/NAV (Source 2) as an :class:`Ephemeris` on BDT (GST - 14 s,
    GST = GPST to tens of ns, OS SIS ICD 5.1.8). The I/NAV clock is for (E1, E5b): an E1 user
    takes BGD(E1,E5b) (5.1.5) and SISA(E1,E5b) (5.1.12). Health packed as RINEX 3.04 Table A8
    does (bit 0 E1-B DVS, bits 1-2 E1-B HS, bit 6 E5b DVS, bits 7-8 E5b HS; each pair only
    when the block flags it valid), as RTCM 1046 is. WNt_oe counts GPS weeks; one more than
    a week from the block's WNc is refused (``eph_bad_week``, by the caller)."""
    week = int(msg.WNt_oe)
    bdt_week, toe_bdt = gpst_to_bdt(week, float(msg.t_oe))
    e1b = bool(int(getattr(msg, "L1-BHealth")))  # each pair only where flagged valid
    e5b = bool(int(msg.E5bHealth))
    health = inav_health(
        int(getattr(msg, "L1-Bdvs")) if e1b else 0,
        int(getattr(msg, "L1-Bhs")) if e1b else 0,
        int(msg.E5bdvs) if e5b else 0,
        int(msg.E5bhs) if e5b else 0,
    )
    bgd_e5b, bgd_e5a = float(msg.BGD_L1E5b), float(msg.BGD_L1E5a)
    return Ephemeris(
        prn=sat_id(GnssSystem.GAL, prn),
        week=bdt_week,
        toe_sow_s=toe_bdt,
        toc_sow_s=gpst_sow_to_bdt_sow(float(msg.t_oc)),
        tgd1_s=math.nan if bgd_e5b == BGD_DNU_S else bgd_e5b,
        tgd2_s=0.0 if bgd_e5a == BGD_DNU_S else bgd_e5a,
        health=health,
        aode=int(msg.IODnav),
        ura_m=galileo_sisa_m(int(msg.SISA_L1E5b)),
        source="sbf",
        **_kepler(msg),
    )


def navbits_words(navbits: bytes) -> tuple[int, ...]:
    """The 10 words of 30 bits of a BDSRaw NavBits field (ten LE u4, bits MSB first)."""
    if len(navbits) < 40:
        raise DecodeError(f"BDSRaw NavBits of {len(navbits)} bytes")
    stream = 0
    for (word,) in struct.iter_unpack("<I", navbits[:40]):
        stream = (stream << 32) | word
    stream >>= 20  # 320 bits, the last 20 unused
    return tuple((stream >> (30 * (9 - i))) & 0x3FFFFFFF for i in range(10))


class SbfMapper:
    """Stateful mapper: SBF blocks (:meth:`on_frame`) in stream order -> events.

    A MeasEpoch is a whole epoch, emitted at once, except the first of a stream: a logging
    session opens with the measurement blocks of its first second, and the receiver's
    stored navigation blocks (BDSNav, BDSIon) follow them in the same second. The first
    MeasEpoch is therefore held until the next one (or :meth:`flush`: end of stream, idle
    line), so that it meets its ephemerides; the cost is one epoch of latency, once.
    """

    def __init__(
        self,
        counters: Counters | None = None,
        week: WeekContext | None = None,
        *,
        source: str = "sbf",
        systems: frozenset[str] | str = GnssSystem.BDS.value,
    ) -> None:
        self.counters = counters if counters is not None else Counters()
        self.week = week if week is not None else WeekContext()
        self.source = source
        wanted = frozenset(systems)
        self._other = {s: sig for s, sig in OTHER_SIGNALS.items() if s.value in wanted}
        self._parsed = _PARSED.union(
            *(blocks for s, blocks in _NAV_BLOCKS.items() if s.value in wanted)
        )
        self._held: list[Event] | None = []  # the first epoch; None once released
        self.receiver_fix: tuple[int, float, tuple[float, float, float]] | None = None
        """The latest PVTGeodetic with a position: (GPS week, TOW s, ECEF m)."""

    def on_frame(self, raw: bytes) -> list[Event]:
        """Map one CRC-valid SBF block (library errors propagate to the caller)."""
        number = _block_number(raw)
        self.counters[f"sbf:{block_name(number)}"] += 1
        if number == MEAS_EPOCH:
            return self._release(self._on_meas_epoch(raw))
        if number not in self._parsed:
            self.counters["sbf_ignored"] += 1
            return []
        if len(raw) < HEADER_LEN + 6:
            raise DecodeError(f"{block_name(number)} of {len(raw)} bytes: no time stamp")
        msg = parse_block(raw)
        tow, wnc = int.from_bytes(raw[8:12], "little"), int.from_bytes(raw[12:14], "little")
        if number == BDS_NAV:
            return self._on_bds_nav(msg)
        if number in _OTHER_NAV:
            return self._on_other_nav(number, msg, wnc)
        if number == BDS_ION:
            self.counters["iono_sbf"] += 1
            alpha = tuple(float(getattr(msg, f"alpha_{i}")) for i in range(4))
            beta = tuple(float(getattr(msg, f"beta_{i}")) for i in range(4))
            return [KlobucharParams(alpha, beta, "BDS")]  # type: ignore[arg-type]
        if tow == TOW_DNU or wnc == WNC_DNU:
            self.counters["sbf_bad_time"] += 1
            return []
        if number == BDS_RAW:
            return self._on_bds_raw(msg, wnc, tow * 1e-3)
        if number == GPS_RAW_CA:
            return self._on_gps_raw(msg, wnc, tow * 1e-3)
        if number == GAL_RAW_INAV:
            return self._on_gal_raw(msg, wnc, tow * 1e-3)
        return self._on_pvt(msg, wnc, tow * 1e-3)

    def flush(self) -> list[Event]:
        """Emit the held first epoch, if any (end of stream or idle line)."""
        return self._release([])

    def _release(self, new: list[Event]) -> list[Event]:
        held = self._held
        if held is None:
            return new
        if not held:  # nothing held yet: hold this one (nothing when the list is empty)
            self._held = new or []
            return []
        self._held = None
        return held + new

    # --- measurements -----------------------------------------------------------------------
    def _on_meas_epoch(self, raw: bytes) -> list[Event]:
        tow_ms, wnc, rows = meas_epoch_rows(raw)
        if tow_ms == TOW_DNU or wnc == WNC_DNU or not 0 <= tow_ms < WEEK_S * 1000:
            self.counters["sbf_bad_time"] += 1
            return []
        tow = tow_ms * 1e-3
        self.week.set_exact(wnc, tow)
        sats: dict[str, tuple[float, float, float, float]] = {}
        signals: dict[str, str] = {}
        for svid, sig, antenna, pr, dop, cn0, lock in rows:
            found = svid_system(svid)
            if found is None or (found[0] is not GnssSystem.BDS and found[0] not in self._other):
                self.counters["meas_other_gnss"] += 1
                continue
            system, prn = found
            if system is GnssSystem.BDS:
                if sig != SIG_B1I:
                    self.counters["meas_bds_other_signal"] += 1
                    continue
                code = "2I"
            else:
                want_sig, code = self._other[system]
                if sig != want_sig or prn > SYSTEM_CONSTANTS[system].prn_max:
                    self.counters[f"meas_{system.value}_other_signal"] += 1
                    continue
                self.counters[f"meas_{system.value}"] += 1
            if antenna != 0:
                self.counters["meas_aux_antenna"] += 1
                continue
            if math.isnan(pr):
                self.counters["meas_pr_invalid"] += 1
            elif not 0.0 < pr < PR_MAX_M:
                self.counters["meas_pr_implausible"] += 1
                pr = math.nan
            sats[sat_id(system, prn)] = (pr, cn0, dop, lock)
            signals[sat_id(system, prn)] = code
        keep = sorted(p for p, v in sats.items() if not math.isnan(v[0]))
        if not keep:
            return []
        cols = np.array([sats[p] for p in keep], dtype=float)
        self.counters["epochs_sbf"] += 1
        return [
            MeasurementEpoch.from_columns(
                wnc,
                tow,
                keep,
                [signals[p] for p in keep],
                cols[:, 0],
                cn0_dbhz=cols[:, 1],
                doppler_hz=cols[:, 2],
                lock_s=cols[:, 3],
                source=self.source,
            )
        ]

    # --- navigation ---------------------------------------------------------------------------
    def _on_bds_nav(self, msg: Any) -> list[Event]:
        prn = bds_prn(int(msg.PRN))
        if prn is None:
            self.counters["eph_bad_prn"] += 1
            return []
        eph = ephemeris_from_bdsnav(msg, prn)
        if _times_in_week(msg):
            gps_week, gps_tow = bdt_to_gpst(eph.week, eph.toe_sow_s)
            if not self.week.set_approx(gps_week, gps_tow, "SBF BDSNav"):
                self.counters["eph_week_disagrees"] += 1
        else:  # as RTCM 1042: no week from it, passed on for the store to refuse
            self.counters["eph_bad_toe"] += 1
        self.counters["ephemerides_sbf"] += 1
        return [eph]

    def _on_gps_raw(self, msg: Any, wnc: int, tow_s: float) -> list[Event]:
        """A GPSRawCA with CRCPassed: its LNAV subframe (each u4 of NavBits holds one word in
        bits 29-0, in the form :mod:`service.core.gps_nav` checks, as u-blox delivers it)."""
        if not int(msg.CRCPassed):
            self.counters["gpsraw_crc_failed"] += 1
            return []
        prn = gps_prn(int(msg.SVID))
        navbits = bytes(msg.NavBits)
        if prn is None or prn > SYSTEM_CONSTANTS[GnssSystem.GPS].prn_max or len(navbits) < 40:
            self.counters["gpsraw_unmapped"] += 1
            return []
        words = tuple(w & 0x3FFFFFFF for (w,) in struct.iter_unpack("<I", navbits[:40]))
        try:
            subframe = lnav_subframe(sat_id(GnssSystem.GPS, prn), words, wnc, tow_s)
        except DecodeError as exc:
            log.debug("G%02d GPSRawCA rejected: %s", prn, exc)
            self.counters["gpsraw_unmapped"] += 1
            return []
        self.counters["subframes"] += 1
        return [subframe]

    def _on_gal_raw(self, msg: Any, wnc: int, tow_s: float) -> list[Event]:
        """A GALRawINAV (E1-B signal 17, E5b-I signal 21) with CRCPassed: its I/NAV word.
        NavBits is a stream of ten LE u4, MSB first: the even part without its tail (114
        bits), then the odd part (the CRC-24Q is checked again here)."""
        signal = _GAL_RAW_SIGNALS.get(int(msg.SigIdx))
        if signal is None:
            self.counters["galraw_other_signal"] += 1
            return []
        if not int(msg.CRCPassed):
            self.counters["galraw_crc_failed"] += 1
            return []
        prn = gal_prn(int(msg.SVID))
        navbits = bytes(msg.NavBits)
        if prn is None or len(navbits) < 32:
            self.counters["galraw_unmapped"] += 1
            return []
        stream = 0
        for (w,) in struct.iter_unpack("<I", navbits[:32]):
            stream = stream << 32 | w
        even, odd = stream >> (256 - 114), (stream >> (256 - 220)) & ((1 << 106) - 1)
        try:
            word = inav_word_of_parts(even, odd)
        except DecodeError as exc:
            log.debug("E%02d GALRawINAV rejected: %s", prn, exc)
            self.counters["galraw_unmapped"] += 1
            return []
        self.counters["subframes"] += 1
        return [inav_subframe(sat_id(GnssSystem.GAL, prn), word, wnc, tow_s, signal)]

    def _on_other_nav(self, number: int, msg: Any, wnc: int) -> list[Event]:
        """GPSNav, GPSIon, GALNav, GALIon, GALGstGps of a system the mapper reads."""
        if number == GPS_ION:
            self.counters["iono_sbf_G"] += 1
            alpha = tuple(float(getattr(msg, f"alpha_{i}")) for i in range(4))
            beta = tuple(float(getattr(msg, f"beta_{i}")) for i in range(4))
            return [KlobucharParams(alpha, beta, "GPS")]  # type: ignore[arg-type]
        if number == GAL_ION:  # NeQuick-G coefficients: no NeQuick-G model here
            self.counters["sbf_gal_ion_unused"] += 1
            return []
        if wnc == WNC_DNU:
            self.counters["sbf_bad_time"] += 1
            return []
        if number == GAL_GST_GPS:
            self.counters["ggto_sbf"] += 1
            return [
                TimeOffset(
                    "GAGP",
                    float(msg.A_0G),
                    float(msg.A_1G),
                    float(msg.t_oG),
                    week_near(int(msg.WN_oG), WN0G_MODULUS, wnc),
                    "sbf",
                )
            ]
        if number == GPS_NAV:
            prn = gps_prn(int(msg.PRN))
            if prn is None or prn > SYSTEM_CONSTANTS[GnssSystem.GPS].prn_max:
                self.counters["eph_bad_prn"] += 1
                return []
            if not _times_in_week(msg):  # as RTCM 1019: no set (wrapped, it would be damage)
                self.counters["eph_bad_toe"] += 1
                return []
            eph = ephemeris_from_gpsnav(msg, prn, wnc)
        else:
            if int(msg.Source) != GAL_SOURCE_INAV:  # F/NAV: the E5a clock; E1 uses I/NAV's
                self.counters["galnav_fnav"] += 1
                return []
            prn = gal_prn(int(msg.SVID))
            if prn is None:
                self.counters["eph_bad_prn"] += 1
                return []
            if abs(int(msg.WNt_oe) - wnc) > 1:
                self.counters["eph_bad_week"] += 1
                return []
            if not _times_in_week(msg):  # as RTCM 1046: no set
                self.counters["eph_bad_toe"] += 1
                return []
            if not int(getattr(msg, "L1-BHealth")):  # E1-B health unknown: not for an E1 user
                self.counters["galnav_no_e1b_health"] += 1
                return []
            eph = ephemeris_from_galnav(msg, prn, wnc)
        # as BDSNav and RTCM 1019/1046: a week more than a day from the stream's (or the
        # receiver's own) time is counted; the set is passed on all the same
        gps_week, gps_tow = bdt_to_gpst(eph.week, eph.toe_sow_s)
        if not self.week.set_approx(gps_week, gps_tow, f"SBF {block_name(number)}"):
            self.counters["eph_week_disagrees"] += 1
        self.counters[f"ephemerides_sbf_{eph.prn[0]}"] += 1
        return [eph]

    def _on_bds_raw(self, msg: Any, wnc: int, tow_s: float) -> list[Event]:
        if int(msg.SigIdx) != SIG_B1I:
            self.counters["bdsraw_other_signal"] += 1
            return []
        if not int(msg.CRCPassed):
            self.counters["bdsraw_crc_failed"] += 1
            return []
        prn_n = bds_prn(int(msg.SVID))
        if prn_n is None:
            self.counters["bdsraw_unmapped"] += 1
            return []
        prn = sat_id(GnssSystem.BDS, prn_n)
        words = navbits_words(bytes(msg.NavBits))
        nav_type = bds_nav_type(prn)
        try:
            subframe = b1i_subframe(prn, nav_type, words, wnc, tow_s)
        except DecodeError as exc:
            log.debug("%s BDSRaw rejected: %s", prn, exc)
            self.counters["bdsraw_unmapped"] += 1
            return []
        self.counters["subframes"] += 1
        return [subframe]

    def _on_pvt(self, msg: Any, wnc: int, tow_s: float) -> list[Event]:
        self.counters["sbf_pvt"] += 1
        lat, lon, h = float(msg.Latitude), float(msg.Longitude), float(msg.Height)
        if int(msg.Type) == 0 or not all(abs(v) < 1e9 for v in (lat, lon, h)):
            self.counters["sbf_pvt_no_fix"] += 1
            return []
        x = geodetic_to_ecef(lat, lon, h)  # radians, ellipsoidal height
        self.receiver_fix = (wnc, tow_s, (float(x[0]), float(x[1]), float(x[2])))
        return [ReceiverFix("sbf-pvtgeodetic", wnc, tow_s, math.degrees(lat), math.degrees(lon), h)]
