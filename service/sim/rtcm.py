"""RTCM 3 message 1042 (BDS satellite ephemeris) as the virtual receiver writes it, so that
a simulated capture carries the ephemerides it was made with (as assisted receivers have
them) and replays to fast fixes with no nav file.

The message layout and the field widths and resolutions are pyrtcm's tables (RTCM 10403.3
Table 3.5-130 ff.); the field mapping is :mod:`service.core.rtcm1042`; the frame (preamble
0xD3, 10-bit length, CRC-24Q) is RTCM 10403.3 section 4.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

from pyrtcm.rtcmhelpers import calc_crc24q
from pyrtcm.rtcmtypes_core import RTCM_DATA_FIELDS
from pyrtcm.rtcmtypes_get import RTCM_PAYLOADS_GET

from service.core.constants import URA_M
from service.core.rtcm1042 import EPH_1042_FIELDS, EPH_1042_INT_FIELDS
from service.core.systems import prn_number
from service.core.timebase import diff_s, gpst_to_bdt
from service.core.types import Ephemeris

_BY_FIELD = {df: (name, factor) for name, df, factor in EPH_1042_FIELDS}


def _ura_index(ura_m: float) -> int:
    """URAI of a URA [m]: the first interval whose upper bound holds it (ICD 5.2.4.5)."""
    if not math.isfinite(ura_m):
        return len(URA_M) - 1
    return next(i for i, bound in enumerate(URA_M) if ura_m <= bound)


def _raw(df: str, eph: Ephemeris) -> int:
    """The integer a data field carries for ``eph``."""
    if df == "DF002":
        return 1042
    if df == "DF488":
        return prn_number(eph.prn)
    if df == "DF490":
        return _ura_index(eph.ura_m)
    name, factor = _BY_FIELD[df]
    value = getattr(eph, name)
    if name in EPH_1042_INT_FIELDS:
        return int(value)
    resolution = RTCM_DATA_FIELDS[df][2]
    raw = float(value) / factor / resolution
    if df in ("DF493", "DF505") and abs(raw - round(raw)) > 1e-6:
        raise ValueError(f"{eph.prn}: t_oe/t_oc {value} s is not a multiple of {resolution} s")
    return round(raw)


def frame_1042(eph: Ephemeris) -> bytes:
    """One RTCM 3 frame of message 1042 for ``eph``."""
    bits = 0
    n_bits = 0
    for df in RTCM_PAYLOADS_GET["1042"]:
        kind, width = RTCM_DATA_FIELDS[df][0], RTCM_DATA_FIELDS[df][1]
        raw = _raw(df, eph)
        low, high = (
            (-(1 << (width - 1)), (1 << (width - 1)) - 1)
            if kind == "INT"
            else (0, (1 << width) - 1)
        )
        if not low <= raw <= high:
            raise ValueError(f"{eph.prn} {df}: {raw} does not fit {kind}{width}")
        bits = (bits << width) | (raw & ((1 << width) - 1))
        n_bits += width
    pad = -n_bits % 8
    payload = (bits << pad).to_bytes((n_bits + pad) // 8, "big")
    head = bytes((0xD3, len(payload) >> 8 & 0x03, len(payload) & 0xFF))
    return head + payload + calc_crc24q(head + payload).to_bytes(3, "big")


def broadcast_sets(
    ephs: Sequence[Ephemeris], prns: Sequence[str], gpst_week: int, gpst_tow_s: float
) -> list[Ephemeris]:
    """Per satellite of ``prns``, the set whose t_oe is nearest the start (what a receiver
    holds then)."""
    bdt = gpst_to_bdt(gpst_week, gpst_tow_s)
    out = []
    for prn in prns:
        mine = [e for e in ephs if e.prn == prn]
        if mine:
            out.append(min(mine, key=lambda e: abs(diff_s(e.week, e.toe_sow_s, *bdt))))
    return out
