"""u-blox UBX frames to bdsfix events: framing, message parsing and mapping.

Sources: u-blox F9 HPG Interface Description ("UBX protocol": frame structure, checksum;
UBX-RXM-RAWX, UBX-RXM-MEASX, UBX-RXM-SFRBX, UBX-NAV-TIMEGPS, UBX-NAV-PVT). BDS B1I facts
from BDS-SIS-ICD-B1I-3.0 (1 ms ranging code, section 3.2; D1/D2 navigation messages,
section 5).

- Frame: ``B5 62 class id length(u16 LE) payload ck_a ck_b``, 8-bit Fletcher checksum over
  class..payload (:data:`FRAMING`).
- Parsing: RXM-RAWX, RXM-MEASX and RXM-SFRBX, which arrive every epoch, are unpacked with
  :mod:`struct` (:func:`parse_rxm`; the mapper reads RAWX, MEASX and SFRBX frames straight
  from their struct tuples, :func:`_rawx_rows`, :func:`_measx_rows` and
  :func:`_sfrbx_fields`); any other message
  the mapper reads, and an RXM payload whose length does not match its count, is parsed by
  pyubx2. Both give the same field names and scales (the tests compare the two on every
  real capture).
- RXM-RAWX: BDS (gnssId 3) B1I (sigId 0 = B1I D1, 1 = B1I D2) give RINEX signal ``2I``.
  ``prMes`` is a full pseudorange only when trkStat bit 0 (prValid) is set; otherwise NaN.
  The time tag is (``week``, ``rcvTow``) on the GPST scale. MEASX pairs with the RAWX whose
  ``rcvTow`` is within ``pair_tolerance_s`` of its ``gpsTOW``; an epoch with MEASX only is
  tagged ``gpsTOW`` (ms, GPST) with the week of the stream, or
  :data:`~service.core.types.UNKNOWN_WEEK` before the stream has given one (counted,
  ``epoch_no_week``; the pipeline declines it, ``no_time``).
- RXM-MEASX (BDS gnssId 3; GPS gnssId 0 and Galileo gnssId 2 when the mapper's ``systems``
  include them): the code phase (``codePhase`` in 2^-21 ms, ``intCodePhase`` in ms) is the
  pseudorange modulo the code period T of the satellite's signal (1 ms for B1I and GPS L1
  C/A, 4 ms for Galileo E1: :attr:`~service.core.systems.SystemConstants.code_period_s`),
  read as ``c * mod(t_ms + intCodePhase + codePhase, T)`` with ``t_ms`` the epoch's time
  tag in whole ms (RAWX ``rcvTow`` when the epoch has one, else MEASX ``gpsTOW``; it drops
  out for T = 1 ms; for Galileo E1 it is what makes ``mod(prMes, c*4ms)`` of the ZED-F9P
  capture agree, the code phase counting from the receiver's own millisecond epochs).
  MEASX has no signal field: a dual-band receiver writes one block per tracked signal under
  the same ``svId`` (GPS L1 C/A and L2C, Galileo E1 and E5b). The GPS and Galileo block
  read is the one whose chips, ``wholeChips + fracChips/1024``, are 1023 times
  ``codePhase`` modulo 1023 (L1 C/A and E1 are 1.023 Mchip/s: IS-GPS-200 3.3.2.3, Galileo
  OS SIS ICD 2.3.3; E5b's 10.23 and L2C's 0.5115 Mchip/s are not); the others are counted,
  ``measx_<G|E>_other_signal``. The fraction lacks a receiver-internal delay calibration
  that is applied to prMes only and carried by no MEASX field, one per system (about 2 m
  apart between GPS and BDS on the ZED-F9P). The mapper calibrates each system against
  RAWX: its offset is the median of ``mod(prMes, c*T) - fraction`` over the system's
  satellites with both in one epoch (refused and counted, ``measx_offset_rejected``, when
  they spread over 30 m), and is kept for later epochs (``measx_offset_m`` presets every
  system's). Before a system's calibration its raw fraction is used and counted
  (``measx_uncalibrated``): the offset is then common to the system's fractional rows and
  goes into its receiver clock bias.
- One :class:`MeasurementEpoch` per receive epoch combines RAWX and MEASX: ``pr_m`` from a
  valid prMes; ``frac_pr_m`` = ``mod(prMes, c*T)`` when prMes is valid (so that it is
  exactly consistent with ``pr_m``), else the calibrated MEASX fraction; ``period_s`` T of
  each satellite's system. A satellite only MEASX has is named by its system's signal
  (:attr:`~service.core.systems.SystemConstants.signal`: ``2I``, ``1C``, ``1C``).
- RXM-SFRBX (BDS; GPS L1 C/A LNAV and Galileo E1-B/E5b-I I/NAV pages when the mapper's
  ``systems`` include them) becomes a
  :class:`NavSubframe` via :mod:`drivers.sfrbx`, time-tagged with
  the latest measurement time, or, in a stream without RAWX/MEASX, with the latest
  navigation epoch of UBX-NAV-TIMEGPS (week and time of week valid) or UBX-NAV-PVT (date
  and time valid). A subframe before any of them is counted (``sfrbx_no_time``).

Counter keys: ``ubx:<NAME>`` per message, ``ubx_ignored``, ``ubx_poll``,
``rawx_meas_other_gnss``, ``rawx_bds_other_signal``, ``rawx_pr_invalid``,
``rawx_pr_implausible``, ``measx_invalid``, ``measx_G_other_signal``,
``measx_E_other_signal``, ``measx_only_sats``, ``measx_uncalibrated``,
``measx_offset_rejected``, ``epochs_ubx``, ``epoch_late_message``, ``epoch_no_week``,
``ubx_bad_time``, ``sfrbx_bds``, ``sfrbx_gps``, ``sfrbx_gal``, ``sfrbx_other_gnss``,
``sfrbx_no_time``, ``sfrbx_unmapped``, ``subframes``, ``nav_pvt_bad_date`` (a NAV-PVT date
outside :data:`NAV_PVT_YEARS`), ``nav_pvt_week_disagrees`` (a NAV-PVT week the stream's
week rule ignored, or more than a day from the receiver's own time of RXM-RAWX /
NAV-TIMEGPS: :class:`~drivers.framing.WeekContext`).
"""

from __future__ import annotations

import datetime as dt
import itertools
import logging
import math
import operator
import struct
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np
from pyubx2 import UBX_MSGIDS, VALNONE, UBXReader

from drivers import framing
from drivers.framing import BinaryFraming, Event, WeekContext
from drivers.sfrbx import UBX_GNSS, nav_subframe, sfrbx_dwords
from service.core.constants import C_M_S, WEEK_S
from service.core.counters import Counters
from service.core.ratelog import RateLimitedLog
from service.core.stats import median
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem, sat_id
from service.core.timebase import diff_s, gpst_from_utc, normalize
from service.core.types import UNKNOWN_WEEK, MeasurementEpoch

log = logging.getLogger(__name__)

_PERIOD_S: dict[str, float] = {s.value: k.code_period_s for s, k in SYSTEM_CONSTANTS.items()}
_PERIOD_MS: dict[str, int] = {x: round(t * 1e3) for x, t in _PERIOD_S.items()}
_CODE_RANGE_M: dict[str, float] = {x: C_M_S * t for x, t in _PERIOD_S.items()}
"""Per satellite letter: the code period T, in s and whole ms, and c*T [m] (what a
fractional range is known modulo)."""

# u-blox signal identifiers (gnssId 3) -> RINEX 3 observation code; only B1I is used.
BDS_SIGNALS: dict[int, str] = {0: "2I", 1: "2I"}  # B1I D1, B1I D2
OTHER_SIGNALS: dict[GnssSystem, dict[int, str]] = {
    GnssSystem.GPS: {0: "1C"},  # gnssId 0 sigId 0: L1 C/A
    GnssSystem.GAL: {0: "1C", 1: "1B"},  # gnssId 2 sigId 0: E1 C, 1: E1 B
}
"""RXM-RAWX signals of GPS and Galileo read when the mapper's ``systems`` include them
(u-blox F9 interface description, "Signal identifiers"; issue 19)."""

# --- frame (Interface Description, "UBX frame structure" and "UBX checksum") ---------------
SYNC = b"\xb5\x62"
HEADER_LEN = 6  # sync, class, id, length
DEFAULT_MAX_PAYLOAD = 8192
"""Longest payload the framer accepts by default [bytes] (the length field allows 65535)."""


def fletcher8(data: bytes | bytearray | memoryview) -> bytes:
    """UBX 8-bit Fletcher checksum ``(ck_a, ck_b)`` of class..payload: ``ck_a`` the byte
    sum, ``ck_b`` the sum of the running ``ck_a`` values, both modulo 256. Plain ``sum`` and
    ``accumulate`` (C loops): a frame is checked before its epoch is solved, and numpy's
    per-call cost, several times the sums' for a few hundred bytes, was on that path."""
    b = bytes(data)
    return bytes((sum(b) & 0xFF, sum(itertools.accumulate(b)) & 0xFF))


def payload_len(header: bytes) -> int:
    """Payload length of a frame from its 6-byte header (u16 little-endian)."""
    return header[4] | (header[5] << 8)


def checksum_ok(frame: bytes) -> bool:
    """The trailing ``ck_a ck_b`` of a whole frame match class..payload."""
    return fletcher8(frame[2:-2]) == frame[-2:]


class UbxFraming(BinaryFraming):
    """The UBX frame layout as a :class:`~drivers.framing.BinaryFraming`, whose
    :meth:`measure` reads the length field and checks the checksum in place: every frame of
    an epoch is measured between its last byte and its fix, and the generic method's calls
    and copies (``payload_len``, ``check``, :func:`fletcher8`) were a tenth of an epoch's
    decoding there. Same results as the generic method on any bytes (tests compare them)."""

    def measure(self, buf: bytes | bytearray, pos: int, max_payload: int) -> int:
        avail = len(buf) - pos
        if avail > 1 and buf[pos + 1] != SYNC[1]:
            return framing.NOT_A_FRAME
        if avail < HEADER_LEN:
            return framing.NEED_MORE
        n_payload = buf[pos + 4] | (buf[pos + 5] << 8)
        if n_payload > max_payload:
            return framing.BAD_LENGTH
        size = HEADER_LEN + n_payload + 2
        if avail < size:
            return framing.NEED_MORE
        body = bytes(buf[pos + 2 : pos + size - 2])  # class..payload
        if (sum(body) & 0xFF) != buf[pos + size - 2]:
            return framing.BAD_CHECKSUM
        if (sum(itertools.accumulate(body)) & 0xFF) != buf[pos + size - 1]:
            return framing.BAD_CHECKSUM
        return size


FRAMING = UbxFraming(
    sync=SYNC,
    header_len=HEADER_LEN,
    trailer_len=2,
    payload_len=payload_len,
    check=checksum_ok,
    max_payload=DEFAULT_MAX_PAYLOAD,
)


NAV_PVT_YEARS = (2010, 2100)
"""The years a UBX-NAV-PVT date may have (the message came with u-blox 7, 2012): a date
outside them, flagged valid, is a damaged frame's, and no week is taken from it."""

# Messages the mapper reads; everything else is counted by name and ignored.
RAWX, MEASX, SFRBX = "RXM-RAWX", "RXM-MEASX", "RXM-SFRBX"
USED_MESSAGES = frozenset({RAWX, MEASX, SFRBX, "NAV-TIMEGPS", "NAV-PVT"})

PR_MAX_M = 1e8
"""Upper bound of a plausible pseudorange [m]: a BDS GEO/IGSO (35,786 km altitude,
BDS-SIS-ICD-B1I-3.0 section 3, space constellation) is at most ~42,000 km from a user on
the Earth, and u-blox keeps its receiver clock within 1 ms (300 km). A prMes flagged valid
but NaN, infinite or outside (0, PR_MAX_M) is counted (``rawx_pr_implausible``), not used."""
MEASX_INVALID_INT_MS = 255
MEASX_INVALID_CHIPS = 65535
L1_CHIPS_PER_MS = 1023
"""Chips per ms of GPS L1 C/A (IS-GPS-200 3.3.2.3: 1.023 MHz, 1023 chips in 1 ms) and
Galileo E1-B/C (OS SIS ICD 2.3.3: 1.023 MHz, 4092 chips in 4 ms)."""
MEASX_CHIP_TOLERANCE = 0.01
"""How far [chips] ``wholeChips + fracChips/1024`` of a 1.023 Mchip/s block may be from
1023 times ``codePhase`` (modulo 1023): two roundings of one measurement, 2^-10 chip and
2^-21 ms = 0.0005 chip (0.0012 chip at most on the ZED-F9P capture, the nearest E5b or L2C
block 0.1 chip away)."""


@dataclass(slots=True)
class _Sat:
    prn: str
    pr_m: float = math.nan
    code_ms: float = math.nan  # MEASX codePhase [ms]
    code_int_ms: int = 0  # MEASX intCodePhase [ms]
    cn0_dbhz: float = math.nan
    doppler_hz: float = math.nan
    lock_s: float = math.nan
    signal: str = "2I"


@dataclass(slots=True)
class _Pending:
    week: int
    tow_s: float
    kinds: set[str] = field(default_factory=set)
    sats: dict[str, _Sat] = field(default_factory=dict)
    week_exact: bool = True  # False: week from a hint (system clock), not from the data


# --- RXM-RAWX / RXM-MEASX / RXM-SFRBX as data: the messages of every measurement epoch -----
# Layouts from the u-blox F9 HPG Interface Description (UBX-RXM-RAWX: 16-byte header and
# 32-byte blocks; UBX-RXM-MEASX: 44-byte header and 24-byte blocks; UBX-RXM-SFRBX: 8-byte
# header and 4-byte data words), the same fields and scales as pyubx2's UBX_PAYLOADS_GET
# tables. pyubx2 builds a Python attribute per field and bit, too slow for messages that
# arrive every epoch; these are unpacked with one struct call per block instead.
_UBX_CLASS_RXM = 0x02
_ID_RAWX, _ID_MEASX, _ID_SFRBX = 0x15, 0x14, 0x13
_RAWX_HEAD = struct.Struct("<dHbBBB2x")  # rcvTow week leapS numMeas recStat version
_RAWX_MEAS = struct.Struct("<ddfBBBBHBBBBBx")  # prMes cpMes doMes gnssId..trkStat
_MEASX_HEAD = struct.Struct("<B3xIII4xIHHH2xHBB8x")  # version gpsTOW..numSv flags
_MEASX_SV = struct.Struct("<BBBBiiHHIBB2x")  # gnssId svId cNo mpathIndic .. pseuRangeRMSErr
_SFRBX_HEAD = struct.Struct("<BBBBBBBx")  # gnssId svId sigId freqId numWords chn version
_SFRBX_WORD = struct.Struct("<I")  # dwrd
MEASX_CODE_PHASE_LSB_MS = 2.0**-21
MEASX_DOPPLER_HZ_LSB = 0.2
MEASX_DOPPLER_MS_LSB = 0.04


class RxmMessage:
    """RXM-RAWX, RXM-MEASX or RXM-SFRBX unpacked with :mod:`struct`: ``identity`` and the
    header fields as attributes and one dict per repeated block in ``blocks``, all named
    as pyubx2 names them. A block field is also an attribute ``<field>_<nn>`` (block nn,
    from 01) as in pyubx2, so either kind of message reads the same way."""

    def __init__(self, identity: str, head: dict[str, Any], blocks: list[dict[str, Any]]) -> None:
        self.identity = identity
        self.__dict__.update(head)
        self.blocks = blocks

    def __getattr__(self, name: str) -> Any:  # only for names not set in __init__
        field_name, _, nn = name.rpartition("_")
        if field_name and nn.isdigit() and 1 <= int(nn) <= len(self.blocks):
            block = self.blocks[int(nn) - 1]
            if field_name in block:
                return block[field_name]
        raise AttributeError(name)

    def fields(self) -> dict[str, Any]:
        """Every field under pyubx2's flat name (header, then ``<field>_<nn>``)."""
        out = {k: v for k, v in vars(self).items() if k not in ("identity", "blocks")}
        for k, block in enumerate(self.blocks, start=1):
            out.update({f"{name}_{k:02d}": value for name, value in block.items()})
        return out


class _Pyubx2Block:
    """Block ``i`` (from 1) of a pyubx2 message, read as a mapping of plain field names."""

    __slots__ = ("_msg", "_sfx")

    def __init__(self, msg: Any, i: int) -> None:
        self._msg = msg
        self._sfx = f"_{i:02d}"

    def __getitem__(self, name: str) -> Any:
        return getattr(self._msg, name + self._sfx)


def _blocks(msg: Any, count: str) -> list[Any]:
    """The repeated blocks of a RXM message, from :func:`parse_rxm` or from pyubx2."""
    if isinstance(msg, RxmMessage):
        return msg.blocks
    return [_Pyubx2Block(msg, i) for i in range(1, int(getattr(msg, count)) + 1)]


def _bits(shift: int, mask: int) -> Callable[[int], int]:
    return lambda v: (v >> shift) & mask


# attribute, index in the unpacked tuple, and None (as is), a scale, or a bit extractor
_Field = tuple[str, int, float | Callable[[int], int] | None]


@dataclass(frozen=True, slots=True)
class _RxmLayout:
    identity: str
    head: struct.Struct
    head_fields: tuple[_Field, ...]
    count_index: int  # header element holding the number of blocks
    block: struct.Struct
    block_fields: tuple[_Field, ...]


_RXM_LAYOUTS: dict[int, _RxmLayout] = {
    _ID_RAWX: _RxmLayout(
        RAWX,
        _RAWX_HEAD,
        (
            ("rcvTow", 0, None),
            ("week", 1, None),
            ("leapS", 2, None),
            ("numMeas", 3, None),
            ("leapSec", 4, _bits(0, 1)),
            ("clkReset", 4, _bits(1, 1)),
        ),
        3,
        _RAWX_MEAS,
        (
            ("prMes", 0, None),
            ("cpMes", 1, None),
            ("doMes", 2, None),
            ("gnssId", 3, None),
            ("svId", 4, None),
            ("sigId", 5, None),
            ("freqId", 6, None),
            ("locktime", 7, None),
            ("cno", 8, None),
            ("prStd", 9, _bits(0, 0x0F)),
            ("prValid", 12, _bits(0, 1)),
            ("cpValid", 12, _bits(1, 1)),
        ),
    ),
    _ID_MEASX: _RxmLayout(
        MEASX,
        _MEASX_HEAD,
        (
            ("version", 0, None),
            ("gpsTOW", 1, None),
            ("gloTOW", 2, None),
            ("bdsTOW", 3, None),
            ("qzssTOW", 4, None),
            ("numSv", 9, None),
            ("towSet", 10, _bits(0, 3)),
        ),
        9,
        _MEASX_SV,
        (
            ("gnssId", 0, None),
            ("svId", 1, None),
            ("cNo", 2, None),
            ("mpathIndic", 3, None),
            ("dopplerMS", 4, MEASX_DOPPLER_MS_LSB),
            ("dopplerHz", 5, MEASX_DOPPLER_HZ_LSB),
            ("wholeChips", 6, None),
            ("fracChips", 7, None),
            ("codePhase", 8, MEASX_CODE_PHASE_LSB_MS),
            ("intCodePhase", 9, None),
            ("pseuRangeRMSErr", 10, None),
        ),
    ),
    _ID_SFRBX: _RxmLayout(
        SFRBX,
        _SFRBX_HEAD,
        (
            ("gnssId", 0, None),
            ("svId", 1, None),
            ("sigId", 2, None),
            ("freqId", 3, None),
            ("numWords", 4, None),
            ("chn", 5, None),
            ("version", 6, None),
        ),
        4,
        _SFRBX_WORD,
        (("dwrd", 0, None),),
    ),
}


def _value(raw: Any, how: float | Callable[[int], int] | None) -> Any:
    if how is None:
        return raw
    if isinstance(how, float):
        return raw * how
    return how(raw)


def parse_rxm(raw: bytes) -> RxmMessage | None:
    """Unpack a whole UBX frame (sync..checksum, checksum already verified) if it is a
    RXM-RAWX, RXM-MEASX or RXM-SFRBX of consistent length; ``None`` otherwise."""
    if len(raw) < 8 or raw[2] != _UBX_CLASS_RXM:
        return None
    layout = _RXM_LAYOUTS.get(raw[3])
    if layout is None:
        return None
    payload = memoryview(raw)[6:-2]
    if len(payload) < layout.head.size:
        return None
    head = layout.head.unpack_from(payload)
    n = head[layout.count_index]
    if len(payload) != layout.head.size + n * layout.block.size:
        return None
    fields = {name: _value(head[i], how) for name, i, how in layout.head_fields}
    blocks = [
        {name: _value(v[i], how) for name, i, how in layout.block_fields}
        for v in layout.block.iter_unpack(payload[layout.head.size :])
    ]
    return RxmMessage(layout.identity, fields, blocks)


_RAWX_COUNTER, _MEASX_COUNTER, _SFRBX_COUNTER = f"ubx:{RAWX}", f"ubx:{MEASX}", f"ubx:{SFRBX}"

RAWX_SIGNALS_KEPT = 1024
"""(gnssId, svId, sigId) triples whose mapping a :class:`UbxMapper` keeps (a receiver's few
tens; the bound holds against a stream of damaged rows, which are then mapped each time)."""


_RawxRow = tuple[int, int, int, float, float, int, int, int]
"""What the mapper reads of a RAWX measurement block: gnssId, svId, sigId, prMes, doMes,
locktime [ms], cno and prValid (trkStat bit 0)."""


def _rawx_rows(raw: bytes) -> tuple[int, float, list[_RawxRow]] | None:
    """Week, rcvTow and the measurement rows of a whole RXM-RAWX frame of consistent length
    (None otherwise): the fields :func:`parse_rxm` gives, straight from the struct tuples
    (the last message of a u-blox epoch: on the path from its last byte to its fix)."""
    payload = memoryview(raw)[6:-2]
    if len(payload) < _RAWX_HEAD.size:
        return None
    tow, week, _leap, n, _stat, _version = _RAWX_HEAD.unpack_from(payload)
    if len(payload) != _RAWX_HEAD.size + n * _RAWX_MEAS.size:
        return None
    rows = [
        (v[3], v[4], v[5], v[0], v[2], v[7], v[8], v[12] & 1)
        for v in _RAWX_MEAS.iter_unpack(payload[_RAWX_HEAD.size :])
    ]
    return week, tow, rows


_MeasxRow = tuple[int, int, int, float, int, int, float, int]
"""What the mapper reads of a MEASX satellite block: gnssId, svId, cNo, dopplerHz [Hz],
wholeChips, fracChips, codePhase [ms] and intCodePhase [ms], scaled as :func:`parse_rxm`
scales them."""


def _measx_rows(raw: bytes) -> tuple[int, list[_MeasxRow]] | None:
    """gpsTOW [ms] and the satellite rows of a whole RXM-MEASX frame of consistent length
    (None otherwise), straight from the struct tuples as :func:`_rawx_rows` reads RAWX: the
    message before RAWX in a u-blox epoch, decoded between its last byte and its fix, where
    :func:`parse_rxm`'s dict per block and call per field were 0.14 ms of 0.34."""
    payload = memoryview(raw)[6:-2]
    if len(payload) < _MEASX_HEAD.size:
        return None
    head = _MEASX_HEAD.unpack_from(payload)
    if len(payload) != _MEASX_HEAD.size + head[9] * _MEASX_SV.size:
        return None
    hz, ms = MEASX_DOPPLER_HZ_LSB, MEASX_CODE_PHASE_LSB_MS
    rows = [
        (v[0], v[1], v[2], v[5] * hz, v[6], v[7], v[8] * ms, v[9])
        for v in _MEASX_SV.iter_unpack(payload[_MEASX_HEAD.size :])
    ]
    return head[1], rows


def _sfrbx_fields(raw: bytes) -> tuple[int, int, int, tuple[int, ...]] | None:
    """gnssId, svId, sigId and the data words of a whole RXM-SFRBX frame of consistent
    length (None otherwise), straight from the struct tuples as :func:`_rawx_rows` reads
    RAWX: a receiver's subframes come just before its epoch's measurements, where
    :func:`parse_rxm`'s dict per word was most of their decoding."""
    payload = memoryview(raw)[6:-2]
    if len(payload) < _SFRBX_HEAD.size:
        return None
    gnss_id, sv_id, sig_id, _freq, n, _chn, _version = _SFRBX_HEAD.unpack_from(payload)
    if len(payload) != _SFRBX_HEAD.size + n * _SFRBX_WORD.size:
        return None
    return gnss_id, sv_id, sig_id, struct.unpack_from(f"<{n}I", payload, _SFRBX_HEAD.size)


_BY_PRN = operator.attrgetter("prn")


_Mapped = TypeVar("_Mapped")


def _kept(table: dict[Any, _Mapped], key: Any, mapped: _Mapped) -> _Mapped:
    """``mapped``, what a row of ``key`` was worked out to be, kept in ``table`` for the
    next such row while the table holds fewer than :data:`RAWX_SIGNALS_KEPT` (the bound
    holds against a stream of damaged rows, which are then worked out each time)."""
    if len(table) < RAWX_SIGNALS_KEPT:
        table[key] = mapped
    return mapped


def _chips_at_1023_per_ms(whole_chips: int, frac_chips: int, code_ms: float) -> bool:
    """A MEASX block of a 1.023 Mchip/s signal (GPS L1 C/A, Galileo E1): its chips,
    ``wholeChips + fracChips/1024``, are 1023 x ``codePhase`` [ms] modulo 1023 chips, within
    :data:`MEASX_CHIP_TOLERANCE`."""
    chips = int(whole_chips) + int(frac_chips) / 1024
    half = L1_CHIPS_PER_MS / 2
    d = (chips - L1_CHIPS_PER_MS * float(code_ms) + half) % L1_CHIPS_PER_MS - half
    return abs(d) <= MEASX_CHIP_TOLERANCE


class UbxMapper:
    """Stateful mapper: UBX frames (:meth:`on_frame`) or parsed messages (:meth:`on_message`,
    from :func:`parse_rxm` or pyubx2) in stream order -> events.

    Epoch completion follows the stream's own message pattern: the set of measurement
    messages (RAWX, MEASX) seen for the previous epoch is the set an epoch needs, so an
    epoch is emitted the moment its last expected message arrives. Until a stream has shown
    its pattern, RAWX alone completes an epoch. A change of time tag closes a pending epoch
    too (e.g. when MEASX output stops), and :meth:`flush` closes it at end of stream.
    """

    def __init__(
        self,
        counters: Counters | None = None,
        week: WeekContext | None = None,
        *,
        measx_offset_m: float | None = None,
        pair_tolerance_s: float = 0.02,
        source: str = "ubx",
        systems: frozenset[str] | str = GnssSystem.BDS.value,
    ) -> None:
        self.counters = counters if counters is not None else Counters()
        self.week = week if week is not None else WeekContext()
        self.measx_offset_m = measx_offset_m  # preset of every system's calibration
        self.measx_offsets_m: dict[str, float] = {}  # by system letter, measured
        self.pair_tolerance_s = pair_tolerance_s
        self.source = source
        self._other = {s: sig for s, sig in OTHER_SIGNALS.items() if s.value in frozenset(systems)}
        self._expected: frozenset[str] = frozenset({RAWX})
        self._pending: _Pending | None = None
        self._last_emitted: tuple[int, float] | None = None
        self._last_meas_time: tuple[int, float] | None = None
        self._last_nav_time: tuple[int, float] | None = None  # NAV-TIMEGPS / NAV-PVT
        self._log = RateLimitedLog(log)
        self._rawx_signals: dict[tuple[int, int, int], tuple[str | None, str, str]] = {}
        self._measx_sats: dict[tuple[int, int], tuple[str | None, str, str]] = {}

    # --- entry points ------------------------------------------------------------------------
    def on_frame(self, raw: bytes) -> list[Event]:
        """Map one checksum-valid UBX frame (library errors propagate to the caller).

        Messages outside :data:`USED_MESSAGES` are counted by name and not parsed."""
        if raw[2] == _UBX_CLASS_RXM:
            if raw[3] == _ID_RAWX:
                rawx = _rawx_rows(raw)
                if rawx is not None:  # else (a poll, a bad length) as any other message
                    self.counters[_RAWX_COUNTER] += 1
                    return self._rawx(*rawx)
            elif raw[3] == _ID_MEASX:
                measx = _measx_rows(raw)
                if measx is not None:  # else as any other message
                    self.counters[_MEASX_COUNTER] += 1
                    return self._measx(*measx)
            elif raw[3] == _ID_SFRBX:
                sfrbx = _sfrbx_fields(raw)
                if sfrbx is not None:  # else as any other message
                    self.counters[_SFRBX_COUNTER] += 1
                    return self._sfrbx(*sfrbx)
        name = UBX_MSGIDS.get(raw[2:4])
        if name in USED_MESSAGES:
            # the framer has checked the checksum (UbxFraming.measure): not twice
            return self.on_message(parse_rxm(raw) or UBXReader.parse(raw, validate=VALNONE))
        label = name if name is not None else f"0x{raw[2]:02x}-0x{raw[3]:02x}"
        self.counters[f"ubx:{label}"] += 1
        self.counters["ubx_ignored"] += 1
        return []

    def on_message(self, msg: Any) -> list[Event]:
        """Map one parsed UBX message; returns the events it completes."""
        name = str(msg.identity)
        self.counters[f"ubx:{name}"] += 1
        if getattr(msg, "payload", None) == b"":
            # An empty payload is the poll form of an output message (UBX frame structure):
            # pyubx2 parses it without fields. Found by fuzzing (AttributeError before).
            self.counters["ubx_poll"] += 1
            return []
        if name == RAWX:
            return self._on_rawx(msg)
        if name == MEASX:
            return self._on_measx(msg)
        if name == SFRBX:
            return self._on_sfrbx(msg)
        if name == "NAV-TIMEGPS":
            tow = msg.iTOW * 1e-3 + msg.fTOW * 1e-9
            if msg.weekValid and msg.towValid and 0.0 <= tow < WEEK_S:
                self.week.set_exact(int(msg.week), tow)
                self._last_nav_time = normalize(int(msg.week), tow)
        elif name == "NAV-PVT":
            self._on_nav_pvt(msg)
        else:
            self.counters["ubx_ignored"] += 1
        return []

    def flush(self) -> list[Event]:
        """Emit a pending epoch (end of stream or idle line)."""
        return self._close(learn=False)

    # --- measurements -----------------------------------------------------------------------
    def _on_rawx(self, msg: Any) -> list[Event]:
        rows = (
            (
                m["gnssId"],
                m["svId"],
                m["sigId"],
                m["prMes"],
                m["doMes"],
                m["locktime"],
                m["cno"],
                m["prValid"],
            )
            for m in _blocks(msg, "numMeas")
        )
        return self._rawx(int(msg.week), float(msg.rcvTow), rows)

    def _rawx(self, week: int, tow: float, rows: Iterable[_RawxRow]) -> list[Event]:
        """A RAWX epoch: its time and its measurement rows (:data:`_RawxRow`)."""
        if not 0.0 <= tow < WEEK_S:
            self.counters["ubx_bad_time"] += 1
            return []
        self.week.set_exact(week, tow)
        out = self._open(RAWX, week, tow)
        pending = self._pending
        if pending is None:
            return out
        counters, sats, rows_seen = self.counters, pending.sats, self._rawx_signals
        for gnss_id, sv_id, sig_id, pr_m, do_hz, lock_ms, cno, pr_valid in rows:
            key = (gnss_id, sv_id, sig_id)
            seen = rows_seen.get(key) or _kept(rows_seen, key, self._rawx_signal(*key))
            prn, sig, count = seen
            if count:
                counters[count] += 1
            if prn is None:
                continue
            sat = sats.get(prn)
            if sat is None:
                sat = sats[prn] = _Sat(prn)
            sat.signal = sig
            pr_m = float(pr_m)
            if not pr_valid:
                counters["rawx_pr_invalid"] += 1
            elif not 0.0 < pr_m < PR_MAX_M:  # NaN/inf/negative reached the solver before
                counters["rawx_pr_implausible"] += 1
            else:
                sat.pr_m = pr_m
            sat.cn0_dbhz = float(cno)
            sat.doppler_hz = float(do_hz)
            sat.lock_s = float(lock_ms) * 1e-3
        return out + self._maybe_complete()

    def _rawx_signal(self, gnss_id: int, sv_id: int, sig_id: int) -> tuple[str | None, str, str]:
        """What a RAWX row of (gnssId, svId, sigId) is: its satellite ID (None: not used),
        its RINEX signal code and the counter it adds to ("" for none). Worked out once per
        mapper for each triple seen (:data:`RAWX_SIGNALS_KEPT` of them), not per row."""
        system = UBX_GNSS.get(gnss_id)
        if system is GnssSystem.BDS:
            sig = BDS_SIGNALS.get(int(sig_id))
            if sig is None:
                return None, "", "rawx_bds_other_signal"
            return sat_id(system, int(sv_id)), sig, ""
        if system in self._other:
            sig = self._other[system].get(int(sig_id))
            if sig is None or not 1 <= int(sv_id) <= SYSTEM_CONSTANTS[system].prn_max:
                return None, "", f"rawx_{system.value}_other_signal"
            return sat_id(system, int(sv_id)), sig, f"rawx_{system.value}"
        return None, "", "rawx_meas_other_gnss"

    def _on_measx(self, msg: Any) -> list[Event]:
        rows = (
            (
                sv["gnssId"],
                sv["svId"],
                sv["cNo"],
                sv["dopplerHz"],
                sv["wholeChips"],
                sv["fracChips"],
                sv["codePhase"],
                sv["intCodePhase"],
            )
            for sv in _blocks(msg, "numSv")
        )
        return self._measx(int(msg.gpsTOW), rows)

    def _measx(self, tow_ms: int, rows: Iterable[_MeasxRow]) -> list[Event]:
        """A MEASX epoch: its gpsTOW [ms] and its satellite rows (:data:`_MeasxRow`)."""
        tow = int(tow_ms) * 1e-3
        if not 0.0 <= tow < WEEK_S:
            self.counters["ubx_bad_time"] += 1
            return []
        week = self.week.resolve(tow)
        out = self._open(MEASX, UNKNOWN_WEEK if week is None else week, tow, self.week.exact)
        pending = self._pending
        if pending is None:
            return out
        counters, sats, known = self.counters, pending.sats, self._measx_sats
        for gnss_id, sv_id, cno, do_hz, chips, frac_chips, code_ms, int_ms in rows:
            key = (gnss_id, sv_id)
            seen = known.get(key) or _kept(known, key, self._measx_sat(*key))
            prn, signal, other = seen
            if other and (prn is None or not _chips_at_1023_per_ms(chips, frac_chips, code_ms)):
                counters[other] += 1  # L2C, E5b: the same svId, another signal
                continue
            if prn is None:
                continue
            int_ms = int(int_ms)
            if int_ms == MEASX_INVALID_INT_MS or int(chips) == MEASX_INVALID_CHIPS:
                counters["measx_invalid"] += 1
                continue
            sat = sats.get(prn)
            if sat is None:
                sat = sats[prn] = _Sat(prn, signal=signal)
            sat.code_ms = float(code_ms)
            sat.code_int_ms = int_ms
            if sat.cn0_dbhz != sat.cn0_dbhz:  # NaN: RAWX has not given it
                sat.cn0_dbhz = float(cno)
            if sat.doppler_hz != sat.doppler_hz:
                sat.doppler_hz = float(do_hz)
        return out + self._maybe_complete()

    def _measx_sat(self, gnss_id: int, sv_id: int) -> tuple[str | None, str, str]:
        """What a MEASX block of (gnssId, svId) is: its satellite ID (None: not used), the
        signal its system's MEASX measures, and, for GPS and Galileo, the counter of a block
        of another signal ("" for BeiDou, whose blocks are all B1I, and for systems not
        read). Worked out once per mapper for each pair seen, as :meth:`_rawx_signal`."""
        system = UBX_GNSS.get(gnss_id)
        if system is GnssSystem.BDS:
            return sat_id(system, int(sv_id)), SYSTEM_CONSTANTS[system].signal, ""
        if system not in self._other:
            return None, "", ""
        other = f"measx_{system.value}_other_signal"
        if not 1 <= int(sv_id) <= SYSTEM_CONSTANTS[system].prn_max:
            return None, "", other
        return sat_id(system, int(sv_id)), SYSTEM_CONSTANTS[system].signal, other

    def _sat(self, pending: _Pending, prn: str) -> _Sat:
        sat = pending.sats.get(prn)
        if sat is None:
            sat = pending.sats[prn] = _Sat(prn)
        return sat

    def _open(self, kind: str, week: int, tow: float, week_exact: bool = True) -> list[Event]:
        """Make the pending epoch the one at (week, tow); closes a different one first.

        A week that is only a hint (the system clock of a live stream, before the first
        RAWX) is not compared: the RAWX at the same time of week joins that epoch and
        gives it the receiver's own week."""
        if week != UNKNOWN_WEEK:
            self._last_meas_time = (week, tow)
        out: list[Event] = []
        p = self._pending
        if p is not None:
            hinted = not (week_exact and p.week_exact)
            same = self._same_time(
                UNKNOWN_WEEK if hinted else week, tow, UNKNOWN_WEEK if hinted else p.week, p.tow_s
            )
            if kind in p.kinds or not same:
                out = self._close(learn=True)
        last = self._last_emitted
        if self._pending is None and last is not None and self._same_time(week, tow, *last):
            # This epoch was already emitted without this message: learn it, drop it.
            self.counters["epoch_late_message"] += 1
            self._expected = self._expected | {kind}
            return out
        if self._pending is None:
            self._pending = _Pending(week, tow, week_exact=week_exact)
        self._pending.kinds.add(kind)
        if kind == RAWX:  # RAWX carries the receiver's own time tag
            self._pending.week, self._pending.tow_s = week, tow
            self._pending.week_exact = True
        return out

    def _same_time(self, week_a: int, tow_a: float, week_b: int, tow_b: float) -> bool:
        if UNKNOWN_WEEK in (week_a, week_b):  # compare times of week only
            d = (tow_a - tow_b + WEEK_S / 2) % WEEK_S - WEEK_S / 2
        else:
            d = diff_s(week_a, tow_a, week_b, tow_b)
        return abs(d) <= self.pair_tolerance_s

    def _maybe_complete(self) -> list[Event]:
        if self._pending is not None and self._expected <= self._pending.kinds:
            return self._close(learn=False)
        return []

    def _close(self, *, learn: bool) -> list[Event]:
        p, self._pending = self._pending, None
        if p is None:
            return []
        self._expected = frozenset(p.kinds) if learn else self._expected | p.kinds
        self._last_emitted = (p.week, p.tow_s)
        if p.week == UNKNOWN_WEEK:
            self.counters["epoch_no_week"] += 1  # passed on: the pipeline declines it
        epoch = self._build(p)
        if epoch is None:
            return []
        self.counters["epochs_ubx"] += 1
        return [epoch]

    def _build(self, p: _Pending) -> MeasurementEpoch | None:
        """The epoch of ``p``, its satellites in PRN order, MEASX calibrated against RAWX.

        Plain Python over the epoch's few tens of satellites: numpy's per-call cost on
        arrays this small was half the decoding of an epoch, on the path from its last byte
        to its fix. Python's float ``%`` is numpy.mod's floor-mod (fmod, then the divisor's
        sign) and ``max - min`` is ``np.ptp``: the same numbers, bit for bit."""
        sats = sorted(p.sats.values(), key=_BY_PRN)
        finite = math.isfinite
        tow_ms = round(p.tow_s * 1e3)
        # One pass: a row per satellite kept (prn, signal, pr, fraction, period, C/N0,
        # Doppler, lock); a satellite with a full range has its fraction mod(prMes, c*T) at
        # once; one with a MEASX code phase only waits (its place kept) for its system's
        # calibration, which needs every satellite's. The MEASX fraction, uncalibrated, is
        # c * mod(tow_ms + intCodePhase + codePhase, T), the whole ms reduced in integers
        # (module docstring, RXM-MEASX).
        kept: list[tuple[str, str, float, float, float, float, float, float] | None] = []
        waiting: list[tuple[int, _Sat, float]] = []  # (row, satellite, raw fraction)
        d: dict[str, list[float]] = {}  # per system: mod(prMes, c*T) - fraction
        for s in sats:
            x = s.prn[0]
            ct = _CODE_RANGE_M[x]
            pr_m = s.pr_m
            if s.code_ms == s.code_ms:  # not NaN: MEASX gave a code phase
                raw = (C_M_S * ((tow_ms + s.code_int_ms) % _PERIOD_MS[x] + s.code_ms) * 1e-3) % ct
                if not finite(pr_m):
                    if raw == raw:
                        waiting.append((len(kept), s, raw))
                        kept.append(None)
                    continue
                d.setdefault(x, []).append(((pr_m % ct - raw) + ct / 2) % ct - ct / 2)
            elif not finite(pr_m):
                continue
            kept.append(
                (s.prn, s.signal, pr_m, pr_m % ct, _PERIOD_S[x], s.cn0_dbhz, s.doppler_hz, s.lock_s)
            )
        for system, dd in d.items():
            spread_m = max(dd) - min(dd)
            if spread_m < 30.0:
                self.measx_offsets_m[system] = median(dd)
            else:
                self.counters["measx_offset_rejected"] += 1
                self._log.warning(
                    "measx_offset_rejected",
                    "MEASX/RAWX offsets disagree by %.1f m among %s satellites at GPST %d %.3f;"
                    " kept %s",
                    spread_m,
                    system,
                    p.week,
                    p.tow_s,
                    self.measx_offsets_m.get(system, self.measx_offset_m),
                )
        for row, s, raw in waiting:
            x = s.prn[0]
            self.counters["measx_only_sats"] += 1
            offset = self.measx_offsets_m.get(x, self.measx_offset_m)
            if offset is None:
                self.counters["measx_uncalibrated"] += 1
                offset = 0.0
            frac = (raw + offset) % _CODE_RANGE_M[x]
            kept[row] = (
                s.prn,
                s.signal,
                s.pr_m,
                frac,
                _PERIOD_S[x],
                s.cn0_dbhz,
                s.doppler_hz,
                s.lock_s,
            )
        if not kept:
            return None
        prn, signal, *columns = zip(*kept, strict=True)
        # the six float columns in one conversion, each a row of one (6, n) array: what
        # MeasurementEpoch.from_columns makes of them in six
        pr_m, frac_pr_m, period_s, cn0, doppler, lock = np.array(columns, dtype=float)
        return MeasurementEpoch(
            gpst_week=int(p.week),
            gpst_tow_s=float(p.tow_s),
            prn=prn,
            signal=signal,
            pr_m=pr_m,
            frac_pr_m=frac_pr_m,
            period_s=period_s,
            cn0_dbhz=cn0,
            doppler_hz=doppler,
            lock_s=lock,
            source=self.source,
        )

    # --- time ----------------------------------------------------------------------------------
    def _on_nav_pvt(self, msg: Any) -> None:
        if not (msg.validDate and msg.validTime):
            return
        if not NAV_PVT_YEARS[0] <= msg.year <= NAV_PVT_YEARS[1]:
            self.counters["nav_pvt_bad_date"] += 1  # (a damaged frame: not a week to take)
            return
        try:
            utc = dt.datetime(msg.year, msg.month, msg.day, msg.hour, msg.min, msg.second)
        except ValueError:
            return
        week, utc_tow = gpst_from_utc(utc)
        tow = int(msg.iTOW) * 1e-3
        if not 0.0 <= tow < WEEK_S:
            return
        # the week of iTOW: the UTC date's GPST is within seconds of it, but may sit on the
        # other side of a week boundary
        week += round((utc_tow - tow) / WEEK_S)
        self._last_nav_time = (week, tow)
        if not self.week.set_approx(week, tow, "UBX NAV-PVT"):
            self.counters["nav_pvt_week_disagrees"] += 1

    # --- navigation subframes ---------------------------------------------------------------
    def _on_sfrbx(self, msg: Any) -> list[Event]:
        return self._sfrbx(int(msg.gnssId), int(msg.svId), int(msg.sigId), sfrbx_dwords(msg))

    def _sfrbx(self, gnss_id: int, sv_id: int, sig_id: int, dwords: tuple[int, ...]) -> list[Event]:
        """A SFRBX's subframe (:func:`drivers.sfrbx.nav_subframe`), time-tagged with the
        latest measurement or navigation epoch."""
        system = UBX_GNSS.get(gnss_id)
        if system is GnssSystem.GPS and GnssSystem.GPS in self._other:
            self.counters["sfrbx_gps"] += 1
        elif system is GnssSystem.GAL and GnssSystem.GAL in self._other:
            self.counters["sfrbx_gal"] += 1
        elif system is not GnssSystem.BDS:
            self.counters["sfrbx_other_gnss"] += 1
            return []
        else:
            self.counters["sfrbx_bds"] += 1
        when = self._last_meas_time or self._last_nav_time
        if when is None:
            self.counters["sfrbx_no_time"] += 1
            return []
        sub = nav_subframe(gnss_id, sv_id, sig_id, dwords, *when)
        if sub is None:
            self.counters["sfrbx_unmapped"] += 1
            return []
        self.counters["subframes"] += 1
        return [sub]
