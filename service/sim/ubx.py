"""UBX-RXM-RAWX and UBX-RXM-MEASX as the virtual receiver writes them.

Layouts from the u-blox F9 HPG Interface Description (RXM-RAWX version 1, RXM-MEASX
version 1); the checksum is pyubx2's. The driver's parser (:mod:`drivers.ubx`) and pyubx2
both read these frames back in the tests.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from pyubx2.ubxhelpers import calc_checksum

_CLASS_RXM = 0x02
_ID_RAWX, _ID_MEASX = 0x15, 0x14
_RAWX_HEAD = struct.Struct("<dHbBBB2x")  # rcvTow week leapS numMeas recStat version
_RAWX_MEAS = struct.Struct("<ddfBBBBHBBBBBx")  # prMes cpMes doMes gnssId svId sigId .. trkStat
_MEASX_HEAD = struct.Struct("<B3xIII4xIHHH2xHBB8x")  # version gpsTOW .. numSv flags
_MEASX_SV = struct.Struct("<BBBBiiHHIBB2x")  # gnssId svId cNo mpathIndic .. pseuRangeRMSErr


MEASX_DOPPLER_MS_LSB = 0.04
MEASX_DOPPLER_HZ_LSB = 0.2
"""Scale of MEASX dopplerMS [m/s] and dopplerHz [Hz] (F9 HPG Interface Description)."""


def ubx_frame(msg_class: int, msg_id: int, payload: bytes) -> bytes:
    """A complete UBX frame: sync chars, class, id, length, payload, Fletcher checksum."""
    body = bytes((msg_class, msg_id)) + struct.pack("<H", len(payload)) + payload
    return b"\xb5\x62" + body + calc_checksum(body)


@dataclass(frozen=True, slots=True)
class RawxMeas:
    """One RXM-RAWX block as the virtual receiver writes it."""

    pr_m: float
    gnss_id: int
    sv_id: int
    sig_id: int
    locktime_ms: int
    cn0_dbhz: int
    pr_std_index: int
    pr_valid: bool
    doppler_hz: float = 0.0  # doMes: positive for an approaching satellite


def rawx_frame(rcv_tow_s: float, week: int, leap_s: int, meas: list[RawxMeas]) -> bytes:
    """Encode RXM-RAWX (version 1, leap seconds known)."""
    parts = [_RAWX_HEAD.pack(rcv_tow_s, week, leap_s, len(meas), 1, 1)]
    for m in meas:
        parts.append(
            _RAWX_MEAS.pack(
                m.pr_m if m.pr_valid else 0.0,
                0.0,
                m.doppler_hz,
                m.gnss_id,
                m.sv_id,
                m.sig_id,
                0,
                m.locktime_ms,
                m.cn0_dbhz,
                m.pr_std_index & 0x0F,
                0,
                0,
                int(m.pr_valid),
            )
        )
    return ubx_frame(_CLASS_RXM, _ID_RAWX, b"".join(parts))


@dataclass(frozen=True, slots=True)
class MeasxSv:
    """One RXM-MEASX block as the virtual receiver writes it (code phase in 2^-21 ms)."""

    gnss_id: int
    sv_id: int
    cn0_dbhz: int
    whole_chips: int
    code_phase_units: int
    int_code_phase_ms: int = 0
    frac_chips: int = 0  # 2^-10 chip
    doppler_hz: float = 0.0  # the same sign as RAWX doMes; written in m/s and in Hz
    wavelength_m: float = 0.0  # of the carrier, for dopplerMS


def measx_frame(gps_tow_ms: int, bds_tow_ms: int, svs: list[MeasxSv]) -> bytes:
    """Encode RXM-MEASX (version 1; TOW accuracies 0; towSet 2 = TOW known)."""
    parts = [_MEASX_HEAD.pack(1, gps_tow_ms, 0, bds_tow_ms, 0, 0, 0, 0, 0, len(svs), 2)]
    for sv in svs:
        parts.append(
            _MEASX_SV.pack(
                sv.gnss_id,
                sv.sv_id,
                sv.cn0_dbhz,
                0,
                round(sv.doppler_hz * sv.wavelength_m / MEASX_DOPPLER_MS_LSB),
                round(sv.doppler_hz / MEASX_DOPPLER_HZ_LSB),
                sv.whole_chips,
                sv.frac_chips,
                sv.code_phase_units,
                sv.int_code_phase_ms,
                0,
            )
        )
    return ubx_frame(_CLASS_RXM, _ID_MEASX, b"".join(parts))
