"""BDS B1I navigation message codec (D1 and D2), both directions (BDS-SIS-ICD-B1I-3.0, 5.1-5.3).

Words and parity (ICD 5.1.3)
    A subframe is 300 bits in ten 30-bit words, MSB first. Word 1 sends bits 1-15 (preamble
    11100010010, Rev) uncoded and bits 16-26 as one BCH(15,11,1) codeword (parity 27-30).
    Words 2-10 carry two 11-bit groups, each BCH(15,11,1)-coded with g(x) = x^4 + x + 1; the
    ICD numbers a word's bits as ``[info1 11][info2 11][parity1 4][parity2 4]`` and transmits
    the two 15-bit codewords interleaved bit by bit, codeword 1 first
    (:func:`interleave_word`). Every word here is in the ICD-numbered (de-interleaved) form,
    which is also what u-blox RXM-SFRBX delivers (checked on the real captures: every word
    passes BCH in this form, while read as on-air order ~99.6 % of the words fail).
    BCH(15,11,1) is a perfect code: every non-zero syndrome names one bit, so a single error
    per codeword is corrected and two errors are *miscorrected*, never detected. Damage is
    caught only by the preamble and the range checks of :func:`parse_header`.

Data stream
    Without the parity bits a subframe is a 224-bit stream (26 + 9 x 22 bits) in which every
    field split by parity (SOW, toc, toe, ...) is contiguous. Field tables give
    (start, length) in that stream; :func:`data_bit_index` maps an ICD bit number to it
    (ICD bit 19 -> 18, bit 31 -> 26, bit 43 -> 38).

Messages (one table each, one interpreting routine :func:`unpack_set` / :func:`pack_message`)
    - Header, all subframes (5.2.3, 5.3.2): FraID bits 16-18, SOW 20 bits (8 MSBs at 19-26,
      12 LSBs at 31-42). Page number: D2 subframe 1 Pnum 4 bits at 43-46 (pages 1-10);
      D1 subframes 4/5 and D2 subframe 5 Rev at 43 then Pnum 7 bits at 44-50.
    - D1 subframes 1-3 (5.2.4): clock, TGD1/2, Klobuchar alpha/beta, ephemeris; toe is split
      2 MSBs in subframe 2 and 15 LSBs in subframe 3.
    - D2 subframe 1 pages 1-10 (5.3.3): the same parameters, split across ten pages, one page
      per 3 s frame; page 2 carries the Klobuchar alpha/beta. Words 6-10 are reserved.
    Scale factors and widths per ICD Tables 5-9/5-10 (and 5-11 for the ephemeris); angles
    and their rates are broadcast in semicircles and converted with pi = 3.1415926535898 as
    the ICD prescribes. The layouts agree bit for bit with RTKLIB ``decode_bds_d1/d2``.

SOW (see :func:`subframe_start_sow_s`)
    D1: SOW is the BDT second of week of the leading edge of its own subframe (subframes 6 s
    apart). D2: every subframe of a 3 s frame carries the SOW of the frame's subframe 1.

Secondary code (5.2.1): D1 bits are additionally spread by the 20-bit Neumann-Hoffman code
:data:`NH_CODE` at 1 kbps; D2 has none. It matters only to signal-level simulation.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Literal

from service.core.constants import ICD_PI, URA_M, WEEK_S
from service.core.errors import DecodeError, EphemerisError
from service.core.types import Ephemeris, KlobucharParams, NavSubframe

log = logging.getLogger(__name__)

NavType = Literal["D1", "D2"]

PREAMBLE = 0b11100010010
"""Subframe preamble, ICD bits 1-11 (5.2.3)."""
NH_CODE = (0, 0, 0, 0, 0, 1, 0, 0, 1, 1, 0, 1, 0, 1, 0, 0, 1, 1, 1, 0)
"""Neumann-Hoffman secondary code on D1, one chip per 1 ms code period (ICD 5.2.1)."""
D1_SUBFRAME_S = 6.0
D2_SUBFRAME_S = 0.6
D2_FRAME_S = 3.0
D1_FRAME_S = 30.0
DATA_BITS = 224
"""Information bits of a subframe: 26 (word 1) + 9 x 22."""
_GEN = 0b10011  # g(x) = x^4 + x + 1 (ICD 5.1.3)
_WORD_MASK = (1 << 30) - 1


# --- BCH(15,11,1), ICD 5.1.3 ----------------------------------------------------------------


def bch_parity(info11: int) -> int:
    """4 parity bits of an 11-bit group: info(x) * x^4 mod g(x), g(x) = x^4 + x + 1."""
    r = (info11 & 0x7FF) << 4
    for i in range(14, 3, -1):
        if r >> i & 1:
            r ^= _GEN << (i - 4)
    return r & 0xF


def _parity_table() -> tuple[int, ...]:
    """:func:`bch_parity` of every 11-bit group, from the parities of the 11 single bits:
    the code is linear (the parity of a XOR of groups is the XOR of their parities), so the
    table doubles 11 times instead of dividing 2048 groups bit by bit at each start."""
    table = [0]
    for bit in range(11):
        p = bch_parity(1 << bit)
        table += [t ^ p for t in table]
    return tuple(table)


_PARITY = _parity_table()
"""bch_parity of every 11-bit group: the decoder looks parities up (two per word, ten words
per subframe, five subframes at every D2 boundary) instead of dividing bit by bit."""

_SYNDROME_TO_BIT: dict[int, int] = {}
for _pos in range(15):
    _err = 1 << _pos
    _SYNDROME_TO_BIT[bch_parity(_err >> 4) ^ (_err & 0xF)] = _pos


def bch_decode(code15: int) -> tuple[int, int]:
    """(info11, corrected bit count) of a 15-bit codeword ``[info 11][parity 4]``.

    The non-zero syndrome of a perfect code always names one bit, which is flipped; two or
    more errors therefore come back miscorrected with a count of 1 (ICD 5.1.3).
    """
    syndrome = _PARITY[(code15 >> 4) & 0x7FF] ^ (code15 & 0xF)
    if syndrome == 0:
        return code15 >> 4, 0
    return (code15 ^ (1 << _SYNDROME_TO_BIT[syndrome])) >> 4, 1


# --- words ----------------------------------------------------------------------------------


def encode_word(data: int, first: bool) -> int:
    """30-bit word (ICD bit order, parity appended) from its information bits.

    ``first``: word 1, ``data`` = 26 bits (preamble, Rev, FraID, SOW MSBs), of which the last
    11 are coded. Otherwise ``data`` = 22 bits, two 11-bit groups each coded.
    """
    if first:
        if not 0 <= data < 1 << 26:
            raise ValueError(f"word 1 carries 26 information bits, got {data:#x}")
        return data << 4 | bch_parity(data & 0x7FF)
    if not 0 <= data < 1 << 22:
        raise ValueError(f"words 2-10 carry 22 information bits, got {data:#x}")
    i1, i2 = data >> 11, data & 0x7FF
    return i1 << 19 | i2 << 8 | bch_parity(i1) << 4 | bch_parity(i2)


def decode_word(word: int, first: bool) -> tuple[int, int]:
    """(information bits, corrected bit count) of a 30-bit word; see :func:`encode_word`.

    Raises :class:`DecodeError` for a value that is not a 30-bit word (BCH(15,11,1) itself
    never reports a codeword as uncorrectable, see :func:`bch_decode`).
    """
    if not 0 <= word <= _WORD_MASK:
        raise DecodeError(f"not a 30-bit word: {word:#x}")
    if first:
        info, n = bch_decode(((word >> 4) & 0x7FF) << 4 | (word & 0xF))
        return (word >> 15) << 11 | info, n
    i1, n1 = bch_decode(((word >> 19) & 0x7FF) << 4 | ((word >> 4) & 0xF))
    i2, n2 = bch_decode(((word >> 8) & 0x7FF) << 4 | (word & 0xF))
    return i1 << 11 | i2, n1 + n2


def interleave_word(word: int) -> int:
    """On-air bit order of a word 2-10: codeword bits alternate, codeword 1 first (5.1.3)."""
    c1 = ((word >> 19) & 0x7FF) << 4 | ((word >> 4) & 0xF)
    c2 = ((word >> 8) & 0x7FF) << 4 | (word & 0xF)
    out = 0
    for k in range(14, -1, -1):
        out = out << 2 | ((c1 >> k) & 1) << 1 | ((c2 >> k) & 1)
    return out


def deinterleave_word(bits: int) -> int:
    """ICD-numbered word from its 30 on-air bits (inverse of :func:`interleave_word`)."""
    c1 = c2 = 0
    for k in range(14, -1, -1):
        pair = (bits >> (2 * k)) & 0b11
        c1 = c1 << 1 | pair >> 1
        c2 = c2 << 1 | (pair & 1)
    return (c1 >> 4) << 19 | (c2 >> 4) << 8 | (c1 & 0xF) << 4 | (c2 & 0xF)


def data_bit_index(icd_bit: int) -> int:
    """0-based position in the 224-bit data stream of a 1-based ICD subframe bit (not parity)."""
    word, pos = divmod(icd_bit - 1, 30)
    limit = 26 if word == 0 else 22
    if not 0 <= word < 10 or pos >= limit:
        raise ValueError(f"ICD bit {icd_bit} is a parity bit or outside the subframe")
    return pos if word == 0 else 26 + 22 * (word - 1) + pos


def subframe_data(words: Sequence[int], decode: int = 10) -> tuple[int, int]:
    """(224-bit data stream, corrected bit count) of ten words; no preamble -> DecodeError.
    ``decode``: how many of the words, from the first, are decoded (BCH); the others are
    only checked to be 30-bit words (as :func:`decode_word` checks them) and their bits
    left 0 (:func:`parse_header`: the header is in words 1-2)."""
    if len(words) != 10:
        raise DecodeError(f"a B1I subframe has 10 words, got {len(words)}")
    data, fixed = decode_word(int(words[0]), True)
    for w in words[1:decode]:
        d, n = decode_word(int(w), False)
        data = data << 22 | d
        fixed += n
    for w in words[max(decode, 1) :]:
        if not 0 <= int(w) <= _WORD_MASK:
            raise DecodeError(f"not a 30-bit word: {int(w):#x}")
    data <<= 22 * (10 - max(decode, 1))
    if _get(data, *HEADER["preamble"]) != PREAMBLE:
        raise DecodeError(f"no B1I preamble in word 1 ({int(words[0]):#010x})")
    return data, fixed


def subframe_words(data: int) -> list[int]:
    """Ten 30-bit words (parity added) from a 224-bit data stream."""
    words = [encode_word(data >> (DATA_BITS - 26), True)]
    for k in range(9):
        words.append(encode_word((data >> (DATA_BITS - 48 - 22 * k)) & 0x3FFFFF, False))
    return words


def _get(data: int, start: int, length: int) -> int:
    return (data >> (DATA_BITS - start - length)) & ((1 << length) - 1)


def _put(data: int, start: int, length: int, value: int) -> int:
    mask = (1 << length) - 1
    shift = DATA_BITS - start - length
    return (data & ~(mask << shift)) | ((value & mask) << shift)


# --- protocol tables ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Param:
    """One broadcast parameter: total width, two's complement or not, LSB, unit kind.

    ``semicircles``: the LSB is in semicircles (or semicircles/s) and the physical value is in
    rad (rad/s). ``wrap``: an angle that is reduced to [-1, 1) semicircles when encoded.
    """

    bits: int
    signed: bool
    lsb: float
    semicircles: bool = False
    wrap: bool = False


PARAMS: dict[str, Param] = {
    # header (5.2.3)
    "preamble": Param(11, False, 1.0),
    "rev": Param(4, False, 1.0),
    "fra_id": Param(3, False, 1.0),
    "sow": Param(20, False, 1.0),
    # week, health, URA, group delay, clock (5.2.4.4-5.2.4.11, Table 5-9)
    "sath1": Param(1, False, 1.0),
    "aodc": Param(5, False, 1.0),
    "urai": Param(4, False, 1.0),
    "wn": Param(13, False, 1.0),
    "toc": Param(17, False, 8.0),
    "tgd1": Param(10, True, 1e-10),
    "tgd2": Param(10, True, 1e-10),
    "af0": Param(24, True, 2.0**-33),
    "af1": Param(22, True, 2.0**-50),
    "af2": Param(11, True, 2.0**-66),
    "aode": Param(5, False, 1.0),
    # Klobuchar (5.2.4.7, Table 5-9): alpha [s, s/sc, s/sc^2, s/sc^3], beta likewise
    "alpha0": Param(8, True, 2.0**-30),
    "alpha1": Param(8, True, 2.0**-27),
    "alpha2": Param(8, True, 2.0**-24),
    "alpha3": Param(8, True, 2.0**-24),
    "beta0": Param(8, True, 2.0**11),
    "beta1": Param(8, True, 2.0**14),
    "beta2": Param(8, True, 2.0**16),
    "beta3": Param(8, True, 2.0**16),
    # ephemeris (5.2.4.12, Table 5-10)
    "sqrta": Param(32, False, 2.0**-19),
    "e": Param(32, False, 2.0**-33),
    "omega": Param(32, True, 2.0**-31, True, True),
    "deltan": Param(16, True, 2.0**-43, True),
    "m0": Param(32, True, 2.0**-31, True, True),
    "omega0": Param(32, True, 2.0**-31, True, True),
    "omegadot": Param(24, True, 2.0**-43, True),
    "i0": Param(32, True, 2.0**-31, True, True),
    "idot": Param(14, True, 2.0**-43, True),
    "cuc": Param(18, True, 2.0**-31),
    "cus": Param(18, True, 2.0**-31),
    "crc": Param(18, True, 2.0**-6),
    "crs": Param(18, True, 2.0**-6),
    "cic": Param(18, True, 2.0**-31),
    "cis": Param(18, True, 2.0**-31),
    "toe": Param(17, False, 8.0),
    # page numbers
}

Part = tuple[str, int, int]
"""(parameter, start, length) in the 224-bit data stream; split parameters MSBs first."""
MsgKey = tuple[str, int, int]
"""(nav type, FraID, page); page 0 for subframes that are not paged."""

HEADER: dict[str, tuple[int, int]] = {
    "preamble": (0, 11),
    "rev": (11, 4),
    "fra_id": (15, 3),
    "sow": (18, 20),
}
"""(start, length) of the word 1 fields and SOW, common to every subframe (5.2.3, 5.3.2)."""

PAGE_NUMBER: dict[tuple[str, int], tuple[int, int, int]] = {
    ("D2", 1): (38, 4, 10),
    ("D1", 4): (39, 7, 24),
    ("D1", 5): (39, 7, 24),
    ("D2", 5): (39, 7, 120),
}
"""(start, length, page count) of Pnum in the paged subframes (5.2.3, 5.3.2)."""

LAYOUT: dict[MsgKey, tuple[Part, ...]] = {
    ("D1", 1, 0): (
        ("sath1", 38, 1),
        ("aodc", 39, 5),
        ("urai", 44, 4),
        ("wn", 48, 13),
        ("toc", 61, 17),
        ("tgd1", 78, 10),
        ("tgd2", 88, 10),
        ("alpha0", 98, 8),
        ("alpha1", 106, 8),
        ("alpha2", 114, 8),
        ("alpha3", 122, 8),
        ("beta0", 130, 8),
        ("beta1", 138, 8),
        ("beta2", 146, 8),
        ("beta3", 154, 8),
        ("af2", 162, 11),
        ("af0", 173, 24),
        ("af1", 197, 22),
        ("aode", 219, 5),
    ),
    ("D1", 2, 0): (
        ("deltan", 38, 16),
        ("cuc", 54, 18),
        ("m0", 72, 32),
        ("e", 104, 32),
        ("cus", 136, 18),
        ("crc", 154, 18),
        ("crs", 172, 18),
        ("sqrta", 190, 32),
        ("toe", 222, 2),
    ),
    ("D1", 3, 0): (
        ("toe", 38, 15),
        ("i0", 53, 32),
        ("cic", 85, 18),
        ("omegadot", 103, 24),
        ("cis", 127, 18),
        ("idot", 145, 14),
        ("omega0", 159, 32),
        ("omega", 191, 32),
    ),
    ("D2", 1, 1): (
        ("sath1", 42, 1),
        ("aodc", 43, 5),
        ("urai", 48, 4),
        ("wn", 52, 13),
        ("toc", 65, 17),
        ("tgd1", 82, 10),
        ("tgd2", 92, 10),
    ),
    ("D2", 1, 2): (
        ("alpha0", 42, 8),
        ("alpha1", 50, 8),
        ("alpha2", 58, 8),
        ("alpha3", 66, 8),
        ("beta0", 74, 8),
        ("beta1", 82, 8),
        ("beta2", 90, 8),
        ("beta3", 98, 8),
    ),
    ("D2", 1, 3): (("af0", 80, 24), ("af1", 104, 4)),
    ("D2", 1, 4): (
        ("af1", 42, 18),
        ("af2", 60, 11),
        ("aode", 71, 5),
        ("deltan", 76, 16),
        ("cuc", 92, 14),
    ),
    ("D2", 1, 5): (("cuc", 42, 4), ("m0", 46, 32), ("cus", 78, 18), ("e", 96, 10)),
    ("D2", 1, 6): (("e", 42, 22), ("sqrta", 64, 32), ("cic", 96, 10)),
    ("D2", 1, 7): (("cic", 42, 8), ("cis", 50, 18), ("toe", 68, 17), ("i0", 85, 21)),
    ("D2", 1, 8): (("i0", 42, 11), ("crc", 53, 18), ("crs", 71, 18), ("omegadot", 89, 19)),
    ("D2", 1, 9): (("omegadot", 42, 5), ("omega0", 47, 32), ("omega", 79, 27)),
    ("D2", 1, 10): (("omega", 42, 5), ("idot", 47, 14)),
}
"""Field layouts: D1 subframes 1-3 (ICD Figs 5-8..5-10), D2 subframe 1 pages 1-10 (5-16-x)."""

D1_SET: tuple[MsgKey, ...] = (("D1", 1, 0), ("D1", 2, 0), ("D1", 3, 0))
D2_SET: tuple[MsgKey, ...] = tuple(("D2", 1, p) for p in range(1, 11))
IONO_PARAMS = ("alpha0", "alpha1", "alpha2", "alpha3", "beta0", "beta1", "beta2", "beta3")

EPHEMERIS_PARAMS: dict[str, str] = {
    "af0": "af0_s",
    "af1": "af1_s_s",
    "af2": "af2_s_s2",
    "sqrta": "sqrt_a_sqrt_m",
    "e": "e",
    "i0": "i0_rad",
    "omega0": "omega0_rad",
    "omega": "omega_rad",
    "m0": "m0_rad",
    "deltan": "delta_n_rad_s",
    "omegadot": "omega_dot_rad_s",
    "idot": "idot_rad_s",
    "cuc": "cuc_rad",
    "cus": "cus_rad",
    "crc": "crc_m",
    "crs": "crs_m",
    "cic": "cic_rad",
    "cis": "cis_rad",
    "tgd1": "tgd1_s",
    "tgd2": "tgd2_s",
    "toe": "toe_sow_s",
    "toc": "toc_sow_s",
}
"""Broadcast parameter -> :class:`Ephemeris` attribute for the real-valued fields."""


def _shift_table(
    msg_set: tuple[MsgKey, ...],
) -> dict[tuple[MsgKey, str, int], int]:
    """Bits of each part's parameter that follow the part (for packing split fields)."""
    out: dict[tuple[MsgKey, str, int], int] = {}
    used: dict[str, int] = {}
    for key in msg_set:
        for name, start, length in LAYOUT[key]:
            used[name] = used.get(name, 0) + length
            out[(key, name, start)] = PARAMS[name].bits - used[name]
    return out


_SHIFTS = {**_shift_table(D1_SET), **_shift_table(D2_SET)}


# --- the one interpreting routine (both directions) -----------------------------------------


def unpack_set(messages: Sequence[tuple[MsgKey, int]]) -> dict[str, int]:
    """Raw two's-complement integers of every parameter laid out in ``messages``.

    ``messages`` are (layout key, data stream) pairs in set order (D1 subframes 1, 2, 3; D2
    pages 1..10); split parameters are concatenated MSBs first in that order.
    """
    raw: dict[str, int] = {}
    width: dict[str, int] = {}
    for key, data in messages:
        for name, start, length in LAYOUT[key]:
            raw[name] = raw.get(name, 0) << length | _get(data, start, length)
            width[name] = width.get(name, 0) + length
    for name, n in raw.items():
        p = PARAMS[name]
        if width[name] != p.bits:
            raise DecodeError(f"{name}: {width[name]} of {p.bits} bits present")
        if p.signed and n >> (p.bits - 1):
            raw[name] = n - (1 << p.bits)
    return raw


def pack_message(key: MsgKey, data: int, raw: Mapping[str, int]) -> int:
    """Put the parts of ``raw`` (integers, see :func:`to_raw`) that ``key`` carries into data."""
    for name, start, length in LAYOUT[key]:
        part = (raw[name] >> _SHIFTS[(key, name, start)]) & ((1 << length) - 1)
        data = _put(data, start, length, part)
    return data


def to_physical(name: str, n: int) -> float:
    """Physical value (s, m, rad, rad/s, ...) of a raw parameter integer."""
    p = PARAMS[name]
    v = n * p.lsb
    return v * ICD_PI if p.semicircles else v


def to_raw(name: str, value: float) -> int:
    """Raw integer of a physical value: rounded to the LSB, range-checked (EphemerisError)."""
    p = PARAMS[name]
    v = value / ICD_PI if p.semicircles else value
    if not math.isfinite(v):
        raise EphemerisError(f"{name}={value} is not finite")
    if p.wrap:
        v = (v + 1.0) % 2.0 - 1.0
    n = round(v / p.lsb)
    if p.wrap and n == 1 << (p.bits - 1):  # +1 semicircle rounds onto -1
        n = -n
    lo, hi = (-(1 << (p.bits - 1)), 1 << (p.bits - 1)) if p.signed else (0, 1 << p.bits)
    if not lo <= n < hi:
        raise EphemerisError(f"{name}={value} does not fit {p.bits} bits (LSB {p.lsb:g})")
    return n


# --- header ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class SubframeHeader:
    """FraID, SOW [s] as broadcast, and the page number of paged subframes (else None)."""

    fra_id: int
    sow_s: int
    page: int | None = None


def parse_header(words: Sequence[int], nav_type: str) -> SubframeHeader:
    """Header of a subframe (ICD 5.2.3 D1, 5.3.2 D2): preamble, FraID, SOW, page number.

    DecodeError for a missing preamble, FraID outside 1-5, SOW >= 604800 or a page number
    outside the subframe's page range.
    """
    # the header is in words 1 and 2 (bits 0-47): the others checked, not decoded (the
    # same result or error, at a fifth of the BCH work, on the path from a SFRBX to its
    # epoch's fix)
    data, _ = subframe_data(words, decode=2)
    return _header(data, nav_type)


def b1i_subframe(
    prn: str,
    nav_type: Literal["D1", "D2"],
    words: tuple[int, ...],
    gpst_week: int,
    gpst_tow_s: float,
) -> NavSubframe:
    """A received B1I subframe (ten 30-bit words, parity included) as the tracker takes it,
    with its header read (:func:`parse_header`; DecodeError if it is not one), time-tagged
    by the receiver at GPST (week, tow)."""
    head = parse_header(words, nav_type)
    return NavSubframe(
        prn=prn,
        nav_type=nav_type,
        fra_id=head.fra_id,
        sow_s=head.sow_s,
        words=words,
        gpst_week=gpst_week,
        gpst_tow_s=gpst_tow_s,
        page=head.page,
        signal="2I",
    )


def _header(data: int, nav_type: str) -> SubframeHeader:
    fra = _get(data, *HEADER["fra_id"])
    if not 1 <= fra <= 5:
        raise DecodeError(f"FraID {fra} out of range 1-5")
    sow = _get(data, *HEADER["sow"])
    if sow >= WEEK_S:
        raise DecodeError(f"SOW {sow} is not a second of the week")
    page = None
    paged = PAGE_NUMBER.get((nav_type, fra))
    if paged is not None:
        start, length, count = paged
        page = _get(data, start, length)
        if not 1 <= page <= count:
            raise DecodeError(f"{nav_type} subframe {fra} page {page} out of range 1-{count}")
    return SubframeHeader(fra, sow, page)


def subframe_start_sow_s(header: SubframeHeader, nav_type: str) -> float:
    """BDT second of week at which the subframe's first bit (preamble edge) left the satellite.

    D1 (ICD 5.2.4.3): the SOW counts at the leading edge of its own subframe, so the start
    is the SOW itself (subframes 6 s apart; the real captures show every SFRBX arriving
    SOW + 14 s + 6 s GPST, and FraID = (SOW / 6) mod 5 + 1).

    D2: every subframe of a 3 s frame carries the SOW of the frame's subframe 1, and subframe
    k starts at SOW + 0.6 (k - 1) s. This reading is confirmed by two independent sources:
    - The ICD (5.3.3, D2 SOW) defines it at "the leading edge of preamble first bit in
      subframe 1 of each frame", as transcribed in GNSSTk (ARL:UT), BDSD2NavData.hpp. The
      ICD text itself could not be retrieved here, only that transcription.
    - Racelogic SatGen, a signal simulator (NavigationDataB1ID2.Generate), writes
      3 x frame count into all five subframes of a frame and advances it only when the
      subframe counter wraps to 1.
    - PocketSDR (T. Takasu, decode_D1D2NAV) sets the signal time from the SOW of every D1
      subframe but only of D2 subframe 1; GNSS-SDR reads the D2 SOW only from subframe 1.
      Both fit subframes 2-5 not marking their own start. RTKLIB (decode_bds_d2) and
      GNSSTk expect the SOWs of consecutive subframe-1 pages 3 s apart.
    No public capture with D2 subframes exists to check it on data.
    """
    if nav_type == "D2":
        return header.sow_s + D2_SUBFRAME_S * (header.fra_id - 1)
    return float(header.sow_s)


def _header_data(fra_id: int, sow_s: int) -> int:
    if not 0 <= sow_s < WEEK_S:
        raise EphemerisError(f"SOW {sow_s} is not a second of the week")
    data = _put(0, *HEADER["preamble"], PREAMBLE)
    data = _put(data, *HEADER["fra_id"], fra_id)
    return _put(data, *HEADER["sow"], sow_s)


def _put_page(data: int, nav_type: str, fra_id: int, page: int) -> int:
    start, length, count = PAGE_NUMBER[(nav_type, fra_id)]
    if not 1 <= page <= count:
        raise EphemerisError(f"{nav_type} subframe {fra_id} page {page} out of range 1-{count}")
    return _put(data, start, length, page)


# --- ephemeris <-> parameters ---------------------------------------------------------------


def _ura_index(ura_m: float) -> int:
    return next((i for i, u in enumerate(URA_M) if ura_m <= u), 15)


def _week_of_toe(wn: int, sow_s: float, toe_s: float) -> int:
    """Week of toe given the week (WN) and SOW of transmission: toe within half a week."""
    return wn - _week_step(sow_s, toe_s)


def _week_step(sow_s: float, toe_s: float) -> int:
    """+1 when toe (previous week) is more than half a week after the SOW, -1 the reverse."""
    if toe_s - sow_s > WEEK_S / 2:
        return 1
    if toe_s - sow_s < -WEEK_S / 2:
        return -1
    return 0


def ephemeris_raw(
    eph: Ephemeris, sow_s: int, iono: KlobucharParams | None = None
) -> dict[str, int]:
    """Raw integers of every subframe 1-3 / page 1-10 parameter for transmission at SOW.

    ``eph.week`` is the week of toe; WN is the week of transmission (5.2.4.4), so it differs
    by one when toe and the transmission lie on either side of a week boundary.
    """
    raw = {name: to_raw(name, getattr(eph, attr)) for name, attr in EPHEMERIS_PARAMS.items()}
    a = iono.alpha if iono is not None else (0.0,) * 4
    b = iono.beta if iono is not None else (0.0,) * 4
    for name, value in zip(IONO_PARAMS, (*a, *b), strict=True):
        raw[name] = to_raw(name, value)
    wn = eph.week + _week_step(sow_s, eph.toe_sow_s)
    raw |= {
        "sath1": to_raw("sath1", eph.health),
        "aodc": to_raw("aodc", eph.aodc),
        "aode": to_raw("aode", eph.aode),
        "urai": _ura_index(eph.ura_m),
        "wn": to_raw("wn", wn),
    }
    return raw


def ephemeris_from_raw(prn: str, raw: Mapping[str, int], sow_s: float) -> Ephemeris:
    """Ephemeris from the raw parameters of a complete set sent at BDT SOW ``sow_s``."""
    values = {attr: to_physical(name, raw[name]) for name, attr in EPHEMERIS_PARAMS.items()}
    return Ephemeris(
        prn=prn,
        week=_week_of_toe(raw["wn"], sow_s, values["toe_sow_s"]),
        health=raw["sath1"],
        aode=raw["aode"],
        aodc=raw["aodc"],
        ura_m=URA_M[raw["urai"]],
        source="subframes",
        **values,
    )


def klobuchar_from_raw(raw: Mapping[str, int]) -> KlobucharParams:
    """BDS Klobuchar coefficients (D1 subframe 1, D2 subframe 1 page 2; ICD 5.2.4.7)."""
    v = [to_physical(name, raw[name]) for name in IONO_PARAMS]
    return KlobucharParams(alpha=(v[0], v[1], v[2], v[3]), beta=(v[4], v[5], v[6], v[7]))


KLOBUCHAR_GRID_TOLERANCE_LSB = 0.1
"""A coefficient within this many LSBs of a whole LSB is a print of that broadcast value."""


def klobuchar_on_grid(iono: KlobucharParams) -> KlobucharParams:
    """Klobuchar coefficients read from print (a RINEX header's ``IONOSPHERIC CORR``,
    4-5 digits) back on their broadcast values: each a whole ICD LSB (BDS-SIS-ICD-B1I-3.0
    5.2.4.7, Table 5-9; IS-GPS-200 20.3.3.5.1 has the same scale factors), as a receiver
    decodes them from the subframes. With 8-bit coefficients a 5-digit print is at most
    0.07 LSB from its value; the print rounded back differs by up to ~5e-4 relative, 0.1 mm
    of a slant delay. Unchanged unless every coefficient is within
    :data:`KLOBUCHAR_GRID_TOLERANCE_LSB` LSB of the grid (not a print of broadcast values)."""
    values = (*iono.alpha, *iono.beta)
    raw = []
    for name, value in zip(IONO_PARAMS, values, strict=True):
        p = PARAMS[name]
        n = round(value / p.lsb) if math.isfinite(value) else 0
        half = 1 << (p.bits - 1)
        if not (abs(value / p.lsb - n) <= KLOBUCHAR_GRID_TOLERANCE_LSB and -half <= n < half):
            return iono
        raw.append(n)
    out = klobuchar_from_raw(dict(zip(IONO_PARAMS, raw, strict=True)))
    return replace(out, system=iono.system)


def quantise_ephemeris(eph: Ephemeris) -> Ephemeris:
    """The ephemeris as a receiver decodes it: every field rounded to its ICD LSB."""
    values: dict[str, Any] = {
        attr: to_physical(name, to_raw(name, getattr(eph, attr)))
        for name, attr in EPHEMERIS_PARAMS.items()
    }
    return replace(eph, ura_m=URA_M[_ura_index(eph.ura_m)], source="subframes", **values)


# --- encoders -------------------------------------------------------------------------------


def encode_d1_subframes(
    eph: Ephemeris, sow_s: int, iono: KlobucharParams | None = None
) -> list[list[int]]:
    """Subframes 1-5 of the D1 frame whose subframe 1 starts at BDT SOW ``sow_s`` (5.2.3).

    Subframe k carries SOW ``sow_s + 6 (k - 1)``. Subframes 4 and 5 carry only their page
    number, (SOW / 30) mod 24 + 1 as observed on the real captures, and a zero almanac.
    """
    sow = int(sow_s)
    raw = ephemeris_raw(eph, sow, iono)
    page = (sow // 30) % 24 + 1
    out = []
    for fra in range(1, 6):
        data = _header_data(fra, sow + 6 * (fra - 1))
        if fra <= 3:
            data = pack_message(("D1", fra, 0), data, raw)
        else:
            data = _put_page(data, "D1", fra, page)
        out.append(subframe_words(data))
    return out


def encode_d2_frame(
    eph: Ephemeris, frame_sow_s: int, page: int, iono: KlobucharParams | None = None
) -> list[list[int]]:
    """Subframes 1-5 of the D2 frame (3 s) starting at BDT SOW ``frame_sow_s`` (5.3.2).

    Every subframe carries the frame's SOW (:func:`subframe_start_sow_s`). Subframe 1 carries
    ephemeris page ``page`` (1-10); subframe 5 its page number (frame count mod 120) + 1 and
    zero payload; subframes 2-4 a header and zero payload.
    """
    sow = int(frame_sow_s)
    raw = ephemeris_raw(eph, sow, iono)
    out = []
    for fra in range(1, 6):
        data = _header_data(fra, sow)
        if fra == 1:
            data = pack_message(("D2", 1, page), _put_page(data, "D2", 1, page), raw)
        elif fra == 5:
            data = _put_page(data, "D2", 5, (sow // 3) % 120 + 1)
        out.append(subframe_words(data))
    return out


# --- assembler ------------------------------------------------------------------------------


class EphemerisAssembler:
    """Collects D1 subframes 1-3, or D2 subframe 1 pages 1-10, into ephemerides.

    A set is consistent when its parts come from consecutive transmissions: D1 subframes 1,
    2, 3 with SOW s, s + 6, s + 12 (one frame); D2 pages 1..10 with SOW s, s + 3, ..., s + 27
    (ten frames). This is the only cross-check the message allows: AODE is sent once per
    set and toe is split across subframes/pages. An ephemeris is returned when its set
    completes and differs from the last one returned for that satellite; Klobuchar
    coefficients (D1 subframe 1, D2 page 2) whenever they change.
    """

    def __init__(self) -> None:
        self._parts: dict[tuple[str, MsgKey], tuple[int, int]] = {}
        self._last: dict[str, Ephemeris] = {}
        self._iono: KlobucharParams | None = None
        self.counters: dict[str, int] = {
            "subframes": 0,
            "bad_subframes": 0,
            "unsupported": 0,
            "mismatched_sets": 0,
            "ephemerides": 0,
        }

    def feed(
        self, prn: str, nav_type: str, words: Sequence[int]
    ) -> list[Ephemeris | KlobucharParams]:
        """One subframe (10 words, ICD order) of ``prn``; new ephemerides / iono, if any."""
        if nav_type not in ("D1", "D2"):
            self.counters["unsupported"] += 1
            return []
        self.counters["subframes"] += 1
        try:
            data, _ = subframe_data(words)
            head = _header(data, nav_type)
        except DecodeError as exc:
            self.counters["bad_subframes"] += 1
            log.debug("%s: subframe rejected: %s", prn, exc)
            return []
        if nav_type == "D1" and head.fra_id <= 3:
            key: MsgKey = ("D1", head.fra_id, 0)
            msg_set, step = D1_SET, 6
        elif nav_type == "D2" and head.fra_id == 1 and head.page is not None:
            key, msg_set, step = ("D2", 1, head.page), D2_SET, 3
        else:
            return []
        self._parts[(prn, key)] = (head.sow_s, data)
        out: list[Ephemeris | KlobucharParams] = []
        if key in (("D1", 1, 0), ("D2", 1, 2)):
            iono = klobuchar_from_raw(unpack_set([(key, data)]))
            if iono != self._iono:
                self._iono = iono
                out.append(iono)
        if key == msg_set[-1]:
            eph = self._complete(prn, msg_set, step)
            if eph is not None and eph != self._last.get(prn):
                self._last[prn] = eph
                self.counters["ephemerides"] += 1
                out.append(eph)
        return out

    def _complete(self, prn: str, msg_set: tuple[MsgKey, ...], step: int) -> Ephemeris | None:
        parts = [self._parts.get((prn, key)) for key in msg_set]
        if any(p is None for p in parts):
            return None
        sows = [p[0] for p in parts if p is not None]
        if any(s != sows[0] + step * k for k, s in enumerate(sows)):
            self.counters["mismatched_sets"] += 1
            return None
        raw = unpack_set([(key, p[1]) for key, p in zip(msg_set, parts, strict=True) if p])
        return ephemeris_from_raw(prn, raw, sows[0])
