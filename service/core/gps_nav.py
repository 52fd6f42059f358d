"""GPS L1 C/A LNAV subframe decoder (IS-GPS-200N 20.3.2-20.3.5): subframes 1-3 to ephemerides.

Words and parity (20.3.5)
    A subframe is 300 bits in ten 30-bit words, MSB first: 24 data bits then 6 parity bits
    D25-D30, a (32,26) Hamming code over the word's source data bits d1-d24 and the last two
    parity bits D29*, D30* of the previous word (Table 20-XIV). The transmitted data bits are
    d_i XOR D30*. Bits 29-30 of word 10 are solved to be zero (20.3.5.2), so word 1 of every
    subframe follows D29* = D30* = 0.

    u-blox RXM-SFRBX delivers each word in bits 29-0 with the D30* polarity taken off all 30
    bits (the data bits are the source bits d1-d24, the parity bits are D25-D30 XOR D30*).
    Checked on the PolyU F9P capture: every word of 202 L1 C/A subframes passes this way,
    while read as transmitted (data XOR D30*) 41 % of the words after word 3 fail. In that
    form the parity of Table 20-XIV reduces to P(d, D29' XOR D30', 0), with D29', D30' the
    delivered last two bits of the previous word (the D30* terms cancel), which is what
    :func:`subframe_data` checks; :func:`delivered_word` is the inverse.

Data stream
    Without the parity a subframe is 240 data bits (10 x 24). Field tables give (start,
    length) in that stream: ICD bit b of word w (1-based, b <= 24) is stream bit
    24 (w - 1) + b - 1. Split fields (M0, e, sqrt A, Omega0, i0, omega; IODC) are joined MSBs
    first.

Messages (20.3.3)
    - TLM (word 1): preamble 10001011. HOW (word 2): the 17-bit truncated TOW count (units of
      6 s: the GPST at the leading edge of the *next* subframe) and subframe ID bits 20-22
      (20.3.3.2).
    - Subframe 1 (20.3.3.3, Table 20-I): WN (10 bits, modulo 1024), URA index, SV health,
      IODC, T_GD, t_oc, a_f2, a_f1, a_f0.
    - Subframes 2 and 3 (20.3.3.4, Tables 20-III, 20-V): IODE and the Keplerian set; t_oe in
      subframe 2.
    - Subframe 4 page 18 (SV ID 56, 20.3.3.5.1.7): Klobuchar alpha/beta.
    Scale factors per Tables 20-I, 20-III, 20-X; semicircles converted with the ICD's
    pi = 3.1415926535898. The offsets agree with RTKLIB ``decode_subfrm1..3``.

An ephemeris is held on BDT as every set is (:class:`~service.core.types.Ephemeris`).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

from service.core.constants import ICD_PI, URA_M, WEEK_S
from service.core.errors import DecodeError
from service.core.timebase import BDT_GPST_OFFSET_S, gpst_sow_to_bdt_sow, toe_gpst_to_bdt
from service.core.types import Ephemeris, KlobucharParams, NavSubframe

log = logging.getLogger(__name__)

PREAMBLE = 0b10001011
"""TLM preamble, word 1 bits 1-8 (20.3.3.1)."""
SUBFRAME_S = 6.0
"""LNAV subframe period (300 bits at 50 bps, 20.3.2)."""
DATA_BITS = 240
_WORD_MASK = (1 << 30) - 1

# Table 20-XIV: the data bits d1..d24 (1-based) each parity bit D25..D30 sums, and which of
# D29* (29) / D30* (30) of the previous word enters it.
_PARITY_TERMS: tuple[tuple[int, tuple[int, ...]], ...] = (
    (29, (1, 2, 3, 5, 6, 10, 11, 12, 13, 14, 17, 18, 20, 23)),
    (30, (2, 3, 4, 6, 7, 11, 12, 13, 14, 15, 18, 19, 21, 24)),
    (29, (1, 3, 4, 5, 7, 8, 12, 13, 14, 15, 16, 19, 20, 22)),
    (30, (2, 4, 5, 6, 8, 9, 13, 14, 15, 16, 17, 20, 21, 23)),
    (30, (1, 3, 5, 6, 7, 9, 10, 14, 15, 16, 17, 18, 21, 22, 24)),
    (29, (3, 5, 6, 8, 9, 10, 11, 13, 15, 19, 22, 23, 24)),
)
_PARITY_MASKS = tuple((prev, sum(1 << (24 - i) for i in bits)) for prev, bits in _PARITY_TERMS)


def parity(data24: int, d29_prev: int, d30_prev: int) -> int:
    """D25-D30 of a word from its source data bits d1-d24 and D29*, D30* (Table 20-XIV)."""
    out = 0
    for prev, mask in _PARITY_MASKS:
        bit = (data24 & mask).bit_count() & 1
        bit ^= d29_prev if prev == 29 else d30_prev
        out = out << 1 | bit
    return out


def encode_word(data24: int, d29_prev: int, d30_prev: int) -> int:
    """An on-air 30-bit word: data bits inverted when D30* is set, parity appended (20.3.5.2)."""
    tx = data24 ^ (0xFFFFFF if d30_prev else 0)
    return tx << 6 | parity(data24, d29_prev, d30_prev)


def delivered_word(onair: int, d30_prev: int) -> int:
    """The word as u-blox RXM-SFRBX delivers it: the on-air word with D30* taken off all 30
    bits."""
    return onair ^ (_WORD_MASK if d30_prev else 0)


def subframe_data(words: Sequence[int]) -> int:
    """The 240-bit data stream of ten delivered words (see the module docstring);
    DecodeError on a parity failure or a missing preamble."""
    if len(words) != 10:
        raise DecodeError(f"an LNAV subframe has 10 words, got {len(words)}")
    data = 0
    prev = 0  # word 10 of the previous subframe ends in D29 = D30 = 0 (20.3.5.2)
    for k, w in enumerate(words):
        w = int(w)
        if not 0 <= w <= _WORD_MASK:
            raise DecodeError(f"not a 30-bit word: {w:#x}")
        d = w >> 6
        if parity(d, ((prev >> 1) ^ prev) & 1, 0) != w & 0x3F:
            raise DecodeError(f"word {k + 1} fails LNAV parity")
        data = data << 24 | d
        prev = w
    if data >> (DATA_BITS - 8) != PREAMBLE:
        raise DecodeError("no LNAV preamble in word 1")
    return data


def subframe_words(data: int) -> list[int]:
    """Ten words as u-blox delivers them (on-air parity per 20.3.5, then D30* taken off) of
    a 240-bit data stream, starting after a word with D29 = D30 = 0."""
    words = []
    d29 = d30 = 0
    for k in range(10):
        onair = encode_word((data >> (DATA_BITS - 24 * (k + 1))) & 0xFFFFFF, d29, d30)
        words.append(delivered_word(onair, d30))
        d29, d30 = (onair >> 1) & 1, onair & 1
    return words


def _get(data: int, start: int, length: int, signed: bool = False) -> int:
    v = (data >> (DATA_BITS - start - length)) & ((1 << length) - 1)
    return v - (1 << length) if signed and v >> (length - 1) else v


def _join(data: int, hi: tuple[int, int], lo: tuple[int, int], signed: bool) -> int:
    v = _get(data, *hi) << lo[1] | _get(data, *lo)
    n = hi[1] + lo[1]
    return v - (1 << n) if signed and v >> (n - 1) else v


@dataclass(frozen=True, slots=True)
class LnavHeader:
    """HOW of a subframe: its subframe ID and TOW count x 6 s (GPST of the next subframe)."""

    subframe_id: int
    tow_next_s: int

    @property
    def start_tow_s(self) -> float:
        """GPST second of week of this subframe's first bit (20.3.3.2)."""
        return float((self.tow_next_s - SUBFRAME_S) % WEEK_S)


def _header(data: int) -> LnavHeader:
    tow = _get(data, 24, 17) * 6
    sfid = _get(data, 43, 3)
    if not 1 <= sfid <= 5:
        raise DecodeError(f"LNAV subframe ID {sfid} out of range 1-5")
    if tow >= WEEK_S + SUBFRAME_S:
        raise DecodeError(f"TOW count {tow // 6} is not a time of week")
    return LnavHeader(sfid, tow % int(WEEK_S))


def parse_header(words: Sequence[int]) -> LnavHeader:
    """HOW of a subframe (parity, preamble, subframe ID checked; DecodeError if not)."""
    return _header(subframe_data(words))


def lnav_subframe(
    prn: str, words: tuple[int, ...], gpst_week: int, gpst_tow_s: float
) -> NavSubframe:
    """A received LNAV subframe as the tracker takes it: ``sow_s`` is the HOW's time (GPST
    of the next subframe's start, as broadcast), ``fra_id`` the subframe ID."""
    head = parse_header(words)
    return NavSubframe(
        prn=prn,
        nav_type="LNAV",
        fra_id=head.subframe_id,
        sow_s=head.tow_next_s,
        words=words,
        gpst_week=gpst_week,
        gpst_tow_s=gpst_tow_s,
        signal="1C",
    )


def _week_near(wn10: int, ref_week: int) -> int:
    """The full GPS week of a 10-bit WN nearest the receiver's week (20.3.3.3.1.1)."""
    return ref_week + ((wn10 - ref_week + 512) % 1024 - 512)


def _ura_m(index: int) -> float:
    return URA_M[index] if 0 <= index < len(URA_M) else float("nan")


def ephemeris_from_subframes(prn: str, sf1: int, sf2: int, sf3: int, ref_week: int) -> Ephemeris:
    """Ephemeris of subframes 1-3 (data streams), on BDT; ``ref_week`` (the receiver's GPS
    week) resolves WN modulo 1024. Field offsets: 20.3.3.3 Table 20-I, 20.3.3.4 Table 20-III."""
    sc = ICD_PI
    week_tx = _week_near(_get(sf1, 48, 10), ref_week)
    tow_tx = _header(sf1).start_tow_s
    toe = _get(sf2, 216, 16) * 16.0
    toc = _get(sf1, 176, 16) * 16.0
    # t_oe is within half a week of the transmission (20.3.4.5)
    week = week_tx + (1 if toe - tow_tx < -WEEK_S / 2 else -1 if toe - tow_tx > WEEK_S / 2 else 0)
    bdt_week, toe_bdt = toe_gpst_to_bdt(week, toe)  # (beyond the week: as read, refused)
    return Ephemeris(
        prn=prn,
        week=bdt_week,
        toe_sow_s=toe_bdt,
        toc_sow_s=gpst_sow_to_bdt_sow(toc),
        af0_s=_get(sf1, 216, 22, True) * 2.0**-31,
        af1_s_s=_get(sf1, 200, 16, True) * 2.0**-43,
        af2_s_s2=_get(sf1, 192, 8, True) * 2.0**-55,
        sqrt_a_sqrt_m=_join(sf2, (184, 8), (192, 24), False) * 2.0**-19,
        e=_join(sf2, (136, 8), (144, 24), False) * 2.0**-33,
        i0_rad=_join(sf3, (112, 8), (120, 24), True) * 2.0**-31 * sc,
        omega0_rad=_join(sf3, (64, 8), (72, 24), True) * 2.0**-31 * sc,
        omega_rad=_join(sf3, (160, 8), (168, 24), True) * 2.0**-31 * sc,
        m0_rad=_join(sf2, (88, 8), (96, 24), True) * 2.0**-31 * sc,
        delta_n_rad_s=_get(sf2, 72, 16, True) * 2.0**-43 * sc,
        omega_dot_rad_s=_get(sf3, 192, 24, True) * 2.0**-43 * sc,
        idot_rad_s=_get(sf3, 224, 14, True) * 2.0**-43 * sc,
        cuc_rad=_get(sf2, 120, 16, True) * 2.0**-29,
        cus_rad=_get(sf2, 168, 16, True) * 2.0**-29,
        crc_m=_get(sf3, 144, 16, True) * 2.0**-5,
        crs_m=_get(sf2, 56, 16, True) * 2.0**-5,
        cic_rad=_get(sf3, 48, 16, True) * 2.0**-29,
        cis_rad=_get(sf3, 96, 16, True) * 2.0**-29,
        tgd1_s=_get(sf1, 160, 8, True) * 2.0**-31,
        health=_get(sf1, 64, 6),
        aode=_get(sf2, 48, 8),
        aodc=_join(sf1, (70, 2), (168, 8), False),
        ura_m=_ura_m(_get(sf1, 60, 4)),
        source="subframes",
    )


def klobuchar_from_subframe4(data: int) -> KlobucharParams | None:
    """GPS Klobuchar coefficients of subframe 4 page 18 (SV ID 56; 20.3.3.5.1.7), else None."""
    if _header(data).subframe_id != 4 or _get(data, 50, 6) != 56:
        return None
    a = [_get(data, 56 + 8 * k, 8, True) for k in range(4)]
    b = [_get(data, 88 + 8 * k, 8, True) for k in range(4)]
    return KlobucharParams(
        alpha=(a[0] * 2.0**-30, a[1] * 2.0**-27, a[2] * 2.0**-24, a[3] * 2.0**-24),
        beta=(b[0] * 2.0**11, b[1] * 2.0**14, b[2] * 2.0**16, b[3] * 2.0**16),
        system="GPS",
    )


class LnavAssembler:
    """Collects LNAV subframes 1-3 of each satellite into ephemerides.

    A set is consistent when subframe 1's IODC LSBs and the IODEs of subframes 2 and 3 agree
    (20.3.4.4: a new set changes them together). An ephemeris is returned when its set
    completes and differs from the last one returned for that satellite; the Klobuchar
    coefficients of subframe 4 page 18 whenever they change.
    """

    def __init__(self) -> None:
        self._parts: dict[tuple[str, int], int] = {}
        self._last: dict[str, Ephemeris] = {}
        self._iono: KlobucharParams | None = None
        self.counters: dict[str, int] = {
            "subframes": 0,
            "bad_subframes": 0,
            "mismatched_sets": 0,
            "ephemerides": 0,
        }

    def feed(
        self, prn: str, words: Sequence[int], gpst_week: int
    ) -> list[Ephemeris | KlobucharParams]:
        """One subframe of ``prn`` received in GPS week ``gpst_week``; new ephemerides/iono."""
        self.counters["subframes"] += 1
        try:
            data = subframe_data(words)
            head = _header(data)
        except DecodeError as exc:
            self.counters["bad_subframes"] += 1
            log.debug("%s: LNAV subframe rejected: %s", prn, exc)
            return []
        if head.subframe_id == 4:
            iono = klobuchar_from_subframe4(data)
            if iono is not None and iono != self._iono:
                self._iono = iono
                return [iono]
            return []
        if head.subframe_id > 3:
            return []
        self._parts[(prn, head.subframe_id)] = data
        parts = [self._parts.get((prn, k)) for k in (1, 2, 3)]
        if any(p is None for p in parts):
            return []
        sf1, sf2, sf3 = (p for p in parts if p is not None)
        if not _get(sf1, 168, 8) == _get(sf2, 48, 8) == _get(sf3, 216, 8):
            if head.subframe_id == 3:
                self.counters["mismatched_sets"] += 1
            return []
        eph = ephemeris_from_subframes(prn, sf1, sf2, sf3, gpst_week)
        if eph == self._last.get(prn):
            return []
        self._last[prn] = eph
        self.counters["ephemerides"] += 1
        return [eph]


def _put(fields: list[tuple[int, int, int]], start: int, length: int, value: int) -> None:
    fields.append((start, length, value & ((1 << length) - 1)))


def _put_split(
    fields: list[tuple[int, int, int]], hi: tuple[int, int], lo: tuple[int, int], value: int
) -> None:
    _put(fields, lo[0], lo[1], value)
    _put(fields, hi[0], hi[1], value >> lo[1])


def _ura_index(ura_m: float) -> int:
    """The smallest URA index whose bound covers ``ura_m`` (20.3.3.3.1.3)."""
    return next((i for i, bound in enumerate(URA_M) if ura_m <= bound + 1e-9), len(URA_M) - 1)


def encode_subframe(eph: Ephemeris, subframe_id: int, tow_next_s: int, gps_week: int) -> int:
    """The 240-bit data stream of LNAV subframe ``subframe_id`` (1-5) of ``eph`` (a set held
    on BDT, put back on GPST here), with the HOW's TOW count of ``tow_next_s`` (the GPST of
    the next subframe's start, 20.3.3.2) and WN = ``gps_week`` mod 1024: the inverse of
    :func:`ephemeris_from_subframes` (the same field offsets, Tables 20-I, 20-III; values
    rounded to their scale factors). Subframes 4 and 5 carry no data here (page ID 0).
    Words as u-blox delivers them: :func:`subframe_words`."""
    sc = ICD_PI
    f: list[tuple[int, int, int]] = []
    _put(f, 0, 8, PREAMBLE)
    _put(f, 24, 17, (tow_next_s % int(WEEK_S)) // 6)
    _put(f, 43, 3, subframe_id)
    toe_gpst = (eph.toe_sow_s + BDT_GPST_OFFSET_S) % WEEK_S
    toc_gpst = (eph.toc_sow_s + BDT_GPST_OFFSET_S) % WEEK_S
    if subframe_id == 1:
        _put(f, 48, 10, gps_week % 1024)
        _put(f, 60, 4, _ura_index(eph.ura_m))
        _put(f, 64, 6, eph.health)
        _put_split(f, (70, 2), (168, 8), eph.aodc if eph.aodc else eph.aode)
        _put(f, 160, 8, round(eph.tgd1_s / 2.0**-31))
        _put(f, 176, 16, round(toc_gpst / 16.0))
        _put(f, 192, 8, round(eph.af2_s_s2 / 2.0**-55))
        _put(f, 200, 16, round(eph.af1_s_s / 2.0**-43))
        _put(f, 216, 22, round(eph.af0_s / 2.0**-31))
    elif subframe_id == 2:
        _put(f, 48, 8, eph.aode)
        _put(f, 56, 16, round(eph.crs_m / 2.0**-5))
        _put(f, 72, 16, round(eph.delta_n_rad_s / sc / 2.0**-43))
        _put_split(f, (88, 8), (96, 24), round(eph.m0_rad / sc / 2.0**-31))
        _put(f, 120, 16, round(eph.cuc_rad / 2.0**-29))
        _put_split(f, (136, 8), (144, 24), round(eph.e / 2.0**-33))
        _put(f, 168, 16, round(eph.cus_rad / 2.0**-29))
        _put_split(f, (184, 8), (192, 24), round(eph.sqrt_a_sqrt_m / 2.0**-19))
        _put(f, 216, 16, round(toe_gpst / 16.0))
    elif subframe_id == 3:
        _put(f, 48, 16, round(eph.cic_rad / 2.0**-29))
        _put_split(f, (64, 8), (72, 24), round(eph.omega0_rad / sc / 2.0**-31))
        _put(f, 96, 16, round(eph.cis_rad / 2.0**-29))
        _put_split(f, (112, 8), (120, 24), round(eph.i0_rad / sc / 2.0**-31))
        _put(f, 144, 16, round(eph.crc_m / 2.0**-5))
        _put_split(f, (160, 8), (168, 24), round(eph.omega_rad / sc / 2.0**-31))
        _put(f, 192, 24, round(eph.omega_dot_rad_s / sc / 2.0**-43))
        _put(f, 216, 8, eph.aode)
        _put(f, 224, 14, round(eph.idot_rad_s / sc / 2.0**-43))
    data = 0
    for start, length, value in f:
        data |= value << (DATA_BITS - start - length)
    return data
