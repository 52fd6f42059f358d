"""Galileo navigation data: SISA, the GST-GPS time offset (GGTO) and I/NAV words.

SISA (OS SIS ICD 5.1.12, Table 76) is the accuracy class of a Galileo set, held as
:attr:`~service.core.types.Ephemeris.ura_m` as URA is for BeiDou and GPS.

GGTO (OS SIS ICD 5.1.8, I/NAV word type 10, F/NAV page type 4; RINEX 3 ``TIME SYSTEM CORR``
``GAGP``; Septentrio SBF GALGstGps): GST - GPST = A0G + A1G (t - t0G + 604800 (WN - WN0G)),
with the week WN0G broadcast modulo 64. bdsfix solves one receiver clock per system
(:mod:`service.engine.layout`), so the offset between GST and GPST goes into Galileo's clock
and needs no correction; it is recorded (STATUS ``ggto_ns``) for the user to see.

I/NAV (OS SIS ICD 4.3.2.2, 4.3.5): a nominal page (2 s: even part, odd part, CRC-24Q) carries
one 128-bit word whose first 6 bits are its type. :func:`inav_word` / :func:`inav_word_of_parts`
check a page as u-blox RXM-SFRBX or SBF GALRawINAV deliver it; :func:`word_tow_s` reads the
time of week of word types 0, 5 and 6 (the tracker's Galileo time); :class:`InavAssembler`
makes ephemerides of word types 1-5 and the GGTO of word type 10, their fields read by
pygnssutils' RawNav from its transcription of the ICD's word tables. :func:`encode_word` and
:func:`encode_page` are the inverses, for the virtual receiver.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from typing import Any

from service.core.constants import ICD_PI, WEEK_S
from service.core.errors import DecodeError
from service.core.timebase import (
    BDT_GPST_OFFSET_S,
    GST_GPS_WEEK_OFFSET,
    gpst_sow_to_bdt_sow,
    toe_gpst_to_bdt,
)
from service.core.types import Ephemeris, NavSubframe, TimeOffset


def galileo_sisa_m(index: int) -> float:
    """SISA [m] of its index (Galileo OS SIS ICD 5.1.12, Table 76): 0-49 by 1 cm, 50-74 from
    0.5 m by 2 cm, 75-99 from 1 m by 4 cm, 100-125 from 2 m by 16 cm; 126-254 spare and 255
    NAPA (no accuracy prediction available): NaN, which the store refuses."""
    if 0 <= index < 50:
        return index * 0.01
    if index < 75:
        return 0.5 + (index - 50) * 0.02
    if index < 100:
        return 1.0 + (index - 75) * 0.04
    if index < 126:
        return 2.0 + (index - 100) * 0.16
    return math.nan


WN0G_MODULUS = 64
"""WN0G is broadcast in 6 bits (OS SIS ICD 5.1.8, I/NAV word type 10)."""


def week_near(broadcast: int, modulus: int, ref_week: int) -> int:
    """The full week of one broadcast modulo ``modulus`` nearest ``ref_week``."""
    return ref_week + ((broadcast - ref_week + modulus // 2) % modulus - modulus // 2)


# --- I/NAV pages (OS SIS ICD 4.3.2.2, 4.3.5) -----------------------------------------------
CRC24Q_POLY = 0x1864CFB
"""CRC-24Q generator (OS SIS ICD 4.3.2.2.2: the I/NAV page CRC, as RTCM 3's)."""
INAV_TOW_WORDS = frozenset({0, 5, 6})
"""Word types that carry WN and TOW (ICD 4.3.5: word type 0 when its Time field is '10',
word types 5 and 6). The TOW is GST at the start of the page that carries it: on the PolyU
F9P capture every such E1-B and E5b-I page arrives with the measurement epoch TOW + 2 s."""
INAV_SUBFRAME_S = 30.0
E1B_TOW_PAGE_STARTS_S = (5.0, 17.0, 19.0, 25.0, 27.0)
"""GST seconds modulo 30 at which the E1-B pages that carry a TOW start (word 6, two word
0, word 5, word 0): the nominal I/NAV sub-frame of ICD 4.3.5 as broadcast (pages 2 s,
starting on odd GST seconds on E1-B, word types 2, 4, 6, 7/9, 8/10, 17/18, 19/20, 16, 0, 0,
1, 3, 5, 0, 16), read off the 520 E1-B pages of the PolyU F9P capture (2024-09-25). A
receiver that syncs to the pages knows the time of week at the end of the next of these
pages: the virtual receiver's and the restart emulator's rule for Galileo."""


def next_tow_page_start_s(gst_tow_s: float) -> float:
    """The start [GST s of week, may pass the week's end] of the first E1-B page carrying a
    TOW that starts at or after ``gst_tow_s`` (:data:`E1B_TOW_PAGE_STARTS_S`)."""
    base = math.floor(gst_tow_s / INAV_SUBFRAME_S) * INAV_SUBFRAME_S
    for k in range(2):
        for start in E1B_TOW_PAGE_STARTS_S:
            t = base + k * INAV_SUBFRAME_S + start
            if t >= gst_tow_s - 1e-9:
                return t
    raise AssertionError("unreachable: every 30 s sub-frame has a TOW page")


def crc24q_bits(value: int, n_bits: int) -> int:
    """CRC-24Q of the ``n_bits`` low bits of ``value`` taken MSB first (zero initial value,
    so leading zero bits change nothing)."""
    crc = 0
    for k in range(n_bits - 1, -1, -1):
        crc ^= ((value >> k) & 1) << 23
        crc = ((crc << 1) ^ CRC24Q_POLY) & 0xFFFFFF if crc & 0x800000 else (crc << 1) & 0xFFFFFF
    return crc


def _bits(stream: int, total: int, start: int, length: int) -> int:
    return (stream >> (total - start - length)) & ((1 << length) - 1)


def inav_word_of_parts(even: int, odd: int) -> int:
    """The 128-bit data word of a nominal I/NAV page from its even part's first 114 bits
    (Even/Odd, Page Type, Data 1/2: 112 bits) and its odd part's first 82 + 24 bits (Even/Odd,
    Page Type, Data 2/2: 16 bits, Reserved 1 / OSNMA 40, SAR 22, Spare 2; then the CRC),
    given as ``odd`` = its first 106 bits (ICD 4.3.2.2, nominal page layout). DecodeError
    for parts out of order (even part's bit 0, odd's 1), an alert page (Page Type 1) or a
    CRC-24Q failure over the 196 bits from the even part's first bit to the odd part's Spare
    (4.3.2.2.2)."""
    if even >> 113 != 0 or (odd >> 105) & 1 != 1:
        raise DecodeError("I/NAV page parts out of order (even/odd bits)")
    if (even >> 112) & 1 or (odd >> 104) & 1:
        raise DecodeError("I/NAV alert page")
    if crc24q_bits(even << 82 | odd >> 24, 196) != odd & 0xFFFFFF:
        raise DecodeError("I/NAV page fails CRC-24Q")
    return (even & ((1 << 112) - 1)) << 16 | (odd >> 88) & 0xFFFF


def inav_word(dwords: Sequence[int]) -> int:
    """The 128-bit data word of a nominal I/NAV page as u-blox RXM-SFRBX delivers it
    (gnssId 2, sigId 1 E1-B or 5 E5b-I): eight 32-bit dwords, MSB first, the even part (120
    bits: 114 + Tail 6) and 8 pad bits, then the odd part (120 bits: 106 + Reserved 2 (8) +
    Tail (6)) and 8 pad bits (the layout pygnssutils' RawNavReader reads);
    :func:`inav_word_of_parts` checks it."""
    if len(dwords) != 8:
        raise DecodeError(f"an I/NAV page has 8 dwords, got {len(dwords)}")
    page = 0
    for d in dwords:
        page = page << 32 | (int(d) & 0xFFFFFFFF)
    return inav_word_of_parts(_bits(page, 256, 0, 114), _bits(page, 256, 128, 106))


def word_type(word: int) -> int:
    """The word type (its first 6 bits) of a 128-bit I/NAV word."""
    return word >> 122


def word_tow_s(word: int) -> int | None:
    """The GST time of week [s] a word of type 0 (Time field '10'), 5 or 6 carries (ICD
    4.3.5), else None."""
    wt = word_type(word)
    if wt == 5:
        return _bits(word, 128, 85, 20)
    if wt == 6:
        return _bits(word, 128, 105, 20)
    if wt == 0 and _bits(word, 128, 6, 2) == 2:
        return _bits(word, 128, 108, 20)
    return None


def inav_subframe(
    prn: str, word: int, gpst_week: int, gpst_tow_s: float, signal: str = "1B"
) -> NavSubframe:
    """A received I/NAV word as the tracker and the assembler take it: ``fra_id`` its word
    type, ``sow_s`` the GST time of week at the start of its page when the word carries one
    (types 0/5/6, ICD 4.3.5; -1 otherwise), ``words`` the 128-bit word alone."""
    tow = word_tow_s(word)
    return NavSubframe(
        prn=prn,
        nav_type="INAV",
        fra_id=word_type(word),
        sow_s=-1 if tow is None else tow,
        words=(word,),
        gpst_week=gpst_week,
        gpst_tow_s=gpst_tow_s,
        signal=signal,
    )


@functools.cache
def _word_definitions() -> dict[int, dict[str, Any]]:
    """pygnssutils' transcription of the ICD's tables of word types 1-6 and 10, by type.

    Imported at the first word decoded or encoded, not with this module: importing
    ``pygnssutils`` loads every tool of the package (its NTRIP client, TLS, its servers),
    about 35 ms at each start of a command that reads no I/NAV word (``bdsfix solve``)."""
    from pygnssutils.rawnav_subframes_gal import (
        GAL_INAV_WORD_1,
        GAL_INAV_WORD_2,
        GAL_INAV_WORD_3,
        GAL_INAV_WORD_4,
        GAL_INAV_WORD_5,
        GAL_INAV_WORD_6,
        GAL_INAV_WORD_10,
    )

    return {
        1: GAL_INAV_WORD_1,
        2: GAL_INAV_WORD_2,
        3: GAL_INAV_WORD_3,
        4: GAL_INAV_WORD_4,
        5: GAL_INAV_WORD_5,
        6: GAL_INAV_WORD_6,
        10: GAL_INAV_WORD_10,
    }


def _iodnav(word: int) -> int:
    return _bits(word, 128, 6, 10)


def _fields(prn: str, words: dict[int, int]) -> Any:
    """The fields of ``words`` (word type -> 128-bit word) as pygnssutils' RawNav reads them
    from its transcription of the ICD's word tables (scaled; angles in semicircles)."""
    from pygnssutils.rawnav import RawNav

    defs = _word_definitions()
    nav = RawNav("E", int(prn[1:]), "1X")
    for wt, word in words.items():
        nav.parse(word, defs[wt], 1 << wt)
    return nav


def inav_health(e1b_dvs: int, e1b_hs: int, e5b_dvs: int, e5b_hs: int) -> int:
    """A Galileo satellite's E1-B and E5b data validity (1 bit) and signal health (2 bits)
    (OS SIS ICD 5.1.9.3) packed as RINEX 3.04 Table A8 packs them, which RTCM 1046 and
    SBF GALNav sets follow here too: bit 0 E1-B DVS, bits 1-2 E1-B HS, bit 6 E5b DVS,
    bits 7-8 E5b HS (:attr:`Ephemeris.health`; 0 is healthy)."""
    return e1b_dvs | e1b_hs << 1 | e5b_dvs << 6 | e5b_hs << 7


def ephemeris_from_words(prn: str, words: dict[int, int], gpst_week: int) -> Ephemeris:
    """The ephemeris of I/NAV word types 1-4 (one IODnav) and 5 (ICD 4.3.5, the word type tables;
    fields by pygnssutils' RawNav), on BDT (GST - 14 s, the GST week + 1024 on the GPS
    count, resolved against ``gpst_week``: ICD 5.1.2). The clock is for (E1, E5b): the E1
    group delay is BGD(E1,E5b) and the accuracy SISA(E1,E5b) (5.1.5, 5.1.12). Health as RINEX
    3.04 Table A8 packs it (bit 0 E1-B DVS, bits 1-2 E1-B HS, bit 6 E5b DVS, bits 7-8 E5b
    HS): word type 5 orders them E5b HS, E1-B HS, E5b DVS, E1-B DVS (pygnssutils 1.3.1
    labels those bits e5ahs, e5bhs, e5advs, e5bdvs; they are read here by position)."""
    nav = _fields(prn, {wt: words[wt] for wt in (1, 2, 3, 4, 5)})
    w5 = words[5]
    e5b_hs, e1b_hs = _bits(w5, 128, 67, 2), _bits(w5, 128, 69, 2)
    e5b_dvs, e1b_dvs = _bits(w5, 128, 71, 1), _bits(w5, 128, 72, 1)
    week_tx = week_near(int(nav.wn) + GST_GPS_WEEK_OFFSET, 4096, gpst_week)
    tow_tx = float(nav.tow)
    toe = float(nav.toe)
    # t_oe is within half a week of the transmission
    week = week_tx + (1 if toe - tow_tx < -WEEK_S / 2 else -1 if toe - tow_tx > WEEK_S / 2 else 0)
    bdt_week, toe_bdt = toe_gpst_to_bdt(week, toe)  # (beyond the week: as read, refused)
    sc = ICD_PI
    return Ephemeris(
        prn=prn,
        week=bdt_week,
        toe_sow_s=toe_bdt,
        toc_sow_s=gpst_sow_to_bdt_sow(float(nav.toc)),
        af0_s=float(nav.af0),
        af1_s_s=float(nav.af1),
        af2_s_s2=float(nav.af2),
        sqrt_a_sqrt_m=float(nav.sqrta),
        e=float(nav.e),
        i0_rad=float(nav.i0) * sc,
        omega0_rad=float(nav.omega0) * sc,
        omega_rad=float(nav.omega) * sc,
        m0_rad=float(nav.m0) * sc,
        delta_n_rad_s=float(nav.deltan) * sc,
        omega_dot_rad_s=float(nav.omegadot) * sc,
        idot_rad_s=float(nav.idot) * sc,
        cuc_rad=float(nav.cuc),
        cus_rad=float(nav.cus),
        crc_m=float(nav.crc),
        crs_m=float(nav.crs),
        cic_rad=float(nav.cic),
        cis_rad=float(nav.cis),
        tgd1_s=float(nav.bgde5b),
        tgd2_s=float(nav.bgde5a),
        health=inav_health(e1b_dvs, e1b_hs, e5b_dvs, e5b_hs),
        aode=int(nav.iodn),
        ura_m=galileo_sisa_m(int(nav.sisa)),
        source="subframes",
    )


def ggto_from_word10(prn: str, word: int, gpst_week: int) -> TimeOffset:
    """GGTO of word type 10 (ICD 4.3.5: A0G 2^-35 s, A1G 2^-51 s/s, t0G 3600 s,
    WN0G modulo 64; fields by pygnssutils' RawNav)."""
    nav = _fields(prn, {10: word})
    return TimeOffset(
        "GAGP",
        float(nav.a0g),
        float(nav.a1g),
        float(nav.t0g),
        week_near(int(nav.wn0g), WN0G_MODULUS, gpst_week),
        "subframes",
    )


class InavAssembler:
    """Collects each Galileo satellite's I/NAV words (E1-B and E5b-I alike: the same words)
    into ephemerides, and word type 10 into the GGTO.

    A set is words 1-4 of one IODnav (IODnav, ICD 5.1.9: a new issue changes all four) with the
    latest word 5 (health, BGD, WN/TOW); it is returned when complete and different from the
    last one returned for the satellite, the GGTO whenever it changes."""

    def __init__(self) -> None:
        self._words: dict[tuple[str, int], int] = {}
        self._last: dict[str, Ephemeris] = {}
        self._ggto: TimeOffset | None = None
        self.counters: dict[str, int] = {"words": 0, "ephemerides": 0, "mixed_iodnav": 0}

    def feed(self, prn: str, word: int, gpst_week: int) -> list[Ephemeris | TimeOffset]:
        """One 128-bit word of ``prn`` received in GPS week ``gpst_week``."""
        self.counters["words"] += 1
        wt = word_type(word)
        if wt == 10:
            ggto = ggto_from_word10(prn, word, gpst_week)
            if ggto != self._ggto:
                self._ggto = ggto
                return [ggto]
            return []
        if not 1 <= wt <= 5:
            return []
        self._words[(prn, wt)] = word
        words = {k: self._words.get((prn, k)) for k in (1, 2, 3, 4, 5)}
        have = {k: w for k, w in words.items() if w is not None}
        if len(have) < 5:
            return []
        if len({_iodnav(have[k]) for k in (1, 2, 3, 4)}) != 1:
            if 1 <= wt <= 4:
                self.counters["mixed_iodnav"] += 1
            return []
        eph = ephemeris_from_words(prn, have, gpst_week)
        if eph == self._last.get(prn):
            return []
        self._last[prn] = eph
        self.counters["ephemerides"] += 1
        return [eph]


# --- encoding (the virtual receiver) ---------------------------------------------------------
E1B_SUBFRAME_WORDS = (2, 4, 6, 63, 63, 63, 63, 63, 0, 0, 1, 3, 5, 0, 63)
"""Word type of each E1-B page of a 30 s sub-frame as the virtual receiver sends it: the
broadcast schedule of :data:`E1B_TOW_PAGE_STARTS_S` (pages starting at GST 1, 3, ..., 29 s
modulo 30), with word type 63 (dummy, ICD 4.3.5) where the real signal carries almanacs,
FEC2 and reduced CED, which bdsfix does not read."""
E1B_FIRST_PAGE_S = 1.0
"""E1-B pages start on odd GST seconds (the PolyU capture)."""


def sisa_index(sisa_m: float) -> int:
    """The SISA index whose value is nearest ``sisa_m`` (Table 76), 255 (NAPA) for NaN."""
    if not math.isfinite(sisa_m):
        return 255
    return min(range(126), key=lambda i: abs(galileo_sisa_m(i) - sisa_m))


def pack_word(definition: dict[str, Any], values: dict[str, float]) -> int:
    """A 128-bit I/NAV word from pygnssutils' transcription of its ICD table (fields in
    order: (bits, U/S, scale)); each value divided by its scale and rounded, absent or
    reserved fields zero."""
    word = 0
    used = 0
    for name, spec in definition.items():
        if not isinstance(spec, tuple):
            continue
        length, _encoding, scale = spec
        raw = round(values.get(name, 0.0) / (scale if scale not in (0, 1) else 1))
        word = word << length | (raw & ((1 << length) - 1))
        used += length
    if used != 128:
        raise ValueError(f"a word definition of {used} bits")
    return word


def encode_word(
    eph: Ephemeris, wtype: int, gst_week: int, tow_s: int, iono: tuple[float, ...] = ()
) -> int:
    """The 128-bit word of type ``wtype`` (0, 1-6 or 63) for ``eph`` (held on BDT, put back
    on GST here), ``gst_week`` and ``tow_s`` the page start (types 0, 5, 6): the inverse of
    :func:`ephemeris_from_words` and :func:`word_tow_s`."""
    if wtype == 63:
        return 63 << 122
    if wtype == 0:  # Time '10': WN and TOW valid
        return 2 << 120 | (gst_week % 4096) << 20 | (tow_s % int(WEEK_S))
    sc = ICD_PI
    toe = (eph.toe_sow_s + BDT_GPST_OFFSET_S) % WEEK_S
    toc = (eph.toc_sow_s + BDT_GPST_OFFSET_S) % WEEK_S
    values: dict[str, float] = {
        "sid": wtype,
        "iodn": eph.aode,
        "toe": toe,
        "m0": eph.m0_rad / sc,
        "e": eph.e,
        "sqrta": eph.sqrt_a_sqrt_m,
        "omega0": eph.omega0_rad / sc,
        "i0": eph.i0_rad / sc,
        "omega": eph.omega_rad / sc,
        "idot": eph.idot_rad_s / sc,
        "omegadot": eph.omega_dot_rad_s / sc,
        "deltan": eph.delta_n_rad_s / sc,
        "cuc": eph.cuc_rad,
        "cus": eph.cus_rad,
        "crc": eph.crc_m,
        "crs": eph.crs_m,
        "sisa": sisa_index(eph.ura_m),
        "sv": int(eph.prn[1:]),
        "cic": eph.cic_rad,
        "cis": eph.cis_rad,
        "toc": toc,
        "af0": eph.af0_s,
        "af1": eph.af1_s_s,
        "af2": eph.af2_s_s2,
        "bgde5a": eph.tgd2_s,
        "bgde5b": eph.tgd1_s,
        "wn": gst_week % 4096,
        "tow": tow_s % int(WEEK_S),
    }
    if wtype == 5:  # health by position (see ephemeris_from_words)
        h = eph.health
        values |= {"e5ahs": h >> 7 & 3, "e5bhs": h >> 1 & 3, "e5advs": h >> 6 & 1}
        values |= {"e5bdvs": h & 1, "ai0": iono[0] if iono else 0.0}
    return pack_word(_word_definitions()[wtype], values)


def encode_page(word: int) -> list[int]:
    """The eight u-blox RXM-SFRBX dwords of a nominal page carrying ``word`` (the layout
    :func:`inav_word` reads; reserved, SAR and spare fields zero, CRC-24Q computed)."""
    even = word >> 16  # Even/Odd 0, Page Type 0, Data 1/2
    odd106 = (1 << 105) | (word & 0xFFFF) << 88  # Even/Odd 1, Page Type 0, Data 2/2, zeros
    crc = crc24q_bits(even << 82 | odd106 >> 24, 196)
    page = (even << 6) << 8  # tail, pad
    odd = (odd106 | crc) << 8 << 6  # SSP, tail
    page = page << 128 | odd << 8  # pad
    return [(page >> (32 * (7 - i))) & 0xFFFFFFFF for i in range(8)]
