"""BDS B1I navigation message codec: BCH(15,11), words, subframe headers, D1 ephemeris.

BDS-SIS-ICD-B1I-3.0:
- 5.1.3: each 30-bit word carries BCH(15,11,1) codewords, generator g(x) = x^4 + x + 1.
  Word 1 sends its first 15 bits (preamble, Rev) uncoded and bits 16-26 as one codeword;
  words 2-10 carry two 11-bit groups, each coded, and the two codewords are interleaved bit by
  bit on air. Receivers (u-blox RXM-SFRBX, Septentrio BDSRaw) deliver the *deinterleaved*
  form, info bits first: ``[info1 11][info2 11][parity1 4][parity2 4]``; that is the form used
  here, with :func:`interleave_word`/:func:`deinterleave_word` for the on-air order.
- 5.2.3 / 5.3.2: word 1 = preamble 11100010010, Rev (4), FraID (3, bits 16-18), SOW (20 bits:
  8 MSBs at 19-26, 12 LSBs at 31-42). Without the parity bits a subframe is a 224-bit data
  stream in which every split field (SOW, toc, toe, ...) is contiguous, so the field tables
  below give (start, length) in that stream.
- 5.2.4: D1 subframes 1-3 carry clock, TGD, ionosphere (Klobuchar alpha/beta) and ephemeris;
  scale factors per Table 5-9/5-10; angles in semicircles (pi = 3.1415926535898 as the ICD).
- D2 (GEOs): page number Pnum, 4 bits at 43-46 of subframe 1 (7 bits after a Rev bit in
  subframe 5); subframe 1 pages 1-10 (one per 3 s frame, 30 s in all) carry the same
  clock/ephemeris parameters as D1 subframes 1-3, split differently (:data:`D2_PAGES`).
  D2 SOW: see :func:`service.tracker.subframe_start_sow_s`.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

from service.errors import DecodeError
from service.types import Ephemeris, KlobucharParams

log = logging.getLogger(__name__)

PREAMBLE = 0b11100010010
ICD_PI = 3.1415926535898
_GEN = 0b10011  # x^4 + x + 1
DATA_BITS = 224  # 26 (word 1) + 9 * 22

URA_M = (
    2.4,
    3.4,
    4.85,
    6.85,
    9.65,
    13.65,
    24.0,
    48.0,
    96.0,
    192.0,
    384.0,
    768.0,
    1536.0,
    3072.0,
    6144.0,
    6144.0,
)

# --- BCH(15,11) -------------------------------------------------------------------------


def bch_parity(info11: int) -> int:
    """4 parity bits of an 11-bit group: remainder of info(x) x^4 mod g(x) (ICD 5.1.3)."""
    r = (info11 & 0x7FF) << 4
    for i in range(14, 3, -1):
        if r >> i & 1:
            r ^= _GEN << (i - 4)
    return r & 0xF


_SYNDROME_TO_BIT: dict[int, int] = {}
for _pos in range(15):
    _code = 1 << _pos
    _SYNDROME_TO_BIT[bch_parity(_code >> 4) ^ (_code & 0xF)] = _pos


def bch_decode(code15: int) -> tuple[int, int]:
    """(info11, corrected bits) of a 15-bit codeword; one error is corrected.

    A nonzero syndrome names the erroneous bit; BCH(15,11) is perfect, so every syndrome
    maps to exactly one single-bit error (two errors are miscorrected, as with any SEC code).
    """
    syndrome = bch_parity(code15 >> 4) ^ (code15 & 0xF)
    if syndrome == 0:
        return code15 >> 4, 0
    pos = _SYNDROME_TO_BIT[syndrome]
    return (code15 ^ (1 << pos)) >> 4, 1


# --- words -------------------------------------------------------------------------------


def encode_word(data: int, first: bool) -> int:
    """30-bit word (deinterleaved form) from 26 data bits (word 1) or 22 data bits."""
    if first:
        return (data & 0x3FFFFFF) << 4 | bch_parity(data & 0x7FF)
    i1, i2 = (data >> 11) & 0x7FF, data & 0x7FF
    return i1 << 19 | i2 << 8 | bch_parity(i1) << 4 | bch_parity(i2)


def decode_word(word: int, first: bool) -> tuple[int, int]:
    """(data bits, corrected bit count) of a 30-bit word; see :func:`encode_word`."""
    word &= 0x3FFFFFFF
    if first:
        info, n = bch_decode(((word >> 4) & 0x7FF) << 4 | (word & 0xF))
        return (word >> 15) << 11 | info, n
    i1, n1 = bch_decode(((word >> 19) & 0x7FF) << 4 | ((word >> 4) & 0xF))
    i2, n2 = bch_decode(((word >> 8) & 0x7FF) << 4 | (word & 0xF))
    return i1 << 11 | i2, n1 + n2


def interleave_word(word: int) -> int:
    """On-air bit order of words 2-10: codeword bits alternate, codeword 1 first."""
    c1 = ((word >> 19) & 0x7FF) << 4 | ((word >> 4) & 0xF)
    c2 = ((word >> 8) & 0x7FF) << 4 | (word & 0xF)
    out = 0
    for k in range(14, -1, -1):
        out = out << 2 | ((c1 >> k) & 1) << 1 | ((c2 >> k) & 1)
    return out


def deinterleave_word(bits: int) -> int:
    """Inverse of :func:`interleave_word`."""
    c1 = c2 = 0
    for k in range(14, -1, -1):
        pair = (bits >> (2 * k)) & 0b11
        c1 = c1 << 1 | pair >> 1
        c2 = c2 << 1 | (pair & 1)
    return (c1 >> 4) << 19 | (c2 >> 4) << 8 | (c1 & 0xF) << 4 | (c2 & 0xF)


def subframe_data(words: Sequence[int]) -> tuple[int, int]:
    """(224-bit data stream, corrected bits) of ten words; bad preamble -> DecodeError."""
    if len(words) != 10:
        raise DecodeError(f"a B1I subframe has 10 words, got {len(words)}")
    data, fixed = decode_word(words[0], True)
    if data >> 15 != PREAMBLE:
        raise DecodeError(f"no B1I preamble in word 1 ({words[0] & 0x3FFFFFFF:#010x})")
    for w in words[1:]:
        d, n = decode_word(w, False)
        data = data << 22 | d
        fixed += n
    return data, fixed


def subframe_words(data: int) -> list[int]:
    """Ten 30-bit words from a 224-bit data stream (parity added)."""
    words = [encode_word(data >> (DATA_BITS - 26), True)]
    for k in range(9):
        words.append(encode_word((data >> (DATA_BITS - 26 - 22 * (k + 1))) & 0x3FFFFF, False))
    return words


def _get(data: int, start: int, length: int, signed: bool = False) -> int:
    v = (data >> (DATA_BITS - start - length)) & ((1 << length) - 1)
    if signed and v >> (length - 1):
        v -= 1 << length
    return v


def _put(data: int, start: int, length: int, value: int, signed: bool = False) -> int:
    mask = (1 << length) - 1
    lo, hi = (-(1 << (length - 1)), 1 << (length - 1)) if signed else (0, 1 << length)
    if not lo <= value < hi:
        raise ValueError(f"{value} does not fit {'signed ' if signed else ''}{length} bits")
    shift = DATA_BITS - start - length
    return (data & ~(mask << shift)) | ((value & mask) << shift)


# --- header ------------------------------------------------------------------------------

HEADER = {"preamble": (0, 11), "rev": (11, 4), "fra_id": (15, 3), "sow": (18, 20)}


@dataclass(frozen=True, slots=True)
class SubframeHeader:
    """FraID, SOW [s] and, for paged subframes, the page number."""

    fra_id: int
    sow_s: int
    page: int | None = None


def parse_header(words: Sequence[int], nav_type: str) -> SubframeHeader:
    """Header of a subframe (ICD 5.2.3.1 / 5.3.2); D2 subframe 1 and 5, D1 4 and 5 are paged."""
    data, _ = subframe_data(words)
    fra = _get(data, *HEADER["fra_id"])
    if not 1 <= fra <= 5:
        raise DecodeError(f"FraID {fra} out of range")
    page = None
    if nav_type == "D2" and fra == 1:
        page = _get(data, 38, 4)
    elif (nav_type == "D2" and fra == 5) or (nav_type == "D1" and fra in (4, 5)):
        page = _get(data, 39, 7)
    return SubframeHeader(fra, _get(data, *HEADER["sow"]), page)


def _header_data(fra_id: int, sow: int) -> int:
    data = _put(0, 0, 11, PREAMBLE)
    data = _put(data, 15, 3, fra_id)
    return _put(data, 18, 20, sow)


# --- D1 ephemeris: (start, length, signed, scale) in the 224-bit stream; "sc" = semicircles
D1_FIELDS: dict[int, dict[str, tuple[int, int, bool, float, bool]]] = {
    1: {
        "sath1": (38, 1, False, 1.0, False),
        "aodc": (39, 5, False, 1.0, False),
        "urai": (44, 4, False, 1.0, False),
        "wn": (48, 13, False, 1.0, False),
        "toc": (61, 17, False, 8.0, False),
        "tgd1": (78, 10, True, 1e-10, False),
        "tgd2": (88, 10, True, 1e-10, False),
        "alpha0": (98, 8, True, 2.0**-30, False),
        "alpha1": (106, 8, True, 2.0**-27, False),
        "alpha2": (114, 8, True, 2.0**-24, False),
        "alpha3": (122, 8, True, 2.0**-24, False),
        "beta0": (130, 8, True, 2.0**11, False),
        "beta1": (138, 8, True, 2.0**14, False),
        "beta2": (146, 8, True, 2.0**16, False),
        "beta3": (154, 8, True, 2.0**16, False),
        "af2": (162, 11, True, 2.0**-66, False),
        "af0": (173, 24, True, 2.0**-33, False),
        "af1": (197, 22, True, 2.0**-50, False),
        "aode": (219, 5, False, 1.0, False),
    },
    2: {
        "deltan": (38, 16, True, 2.0**-43, True),
        "cuc": (54, 18, True, 2.0**-31, False),
        "m0": (72, 32, True, 2.0**-31, True),
        "e": (104, 32, False, 2.0**-33, False),
        "cus": (136, 18, True, 2.0**-31, False),
        "crc": (154, 18, True, 2.0**-6, False),
        "crs": (172, 18, True, 2.0**-6, False),
        "sqrta": (190, 32, False, 2.0**-19, False),
        "toe_msb": (222, 2, False, 1.0, False),
    },
    3: {
        "toe_lsb": (38, 15, False, 1.0, False),
        "i0": (53, 32, True, 2.0**-31, True),
        "cic": (85, 18, True, 2.0**-31, False),
        "omegadot": (103, 24, True, 2.0**-43, True),
        "cis": (127, 18, True, 2.0**-31, False),
        "idot": (145, 14, True, 2.0**-43, True),
        "omega0": (159, 32, True, 2.0**-31, True),
        "omega": (191, 32, True, 2.0**-31, True),
    },
}


_ANGLES = frozenset({"m0", "i0", "omega0", "omega"})

# D2 subframe 1, pages 1-10 (ICD 5.3.2, one page per 3 s frame): (field, start, length) in
# the 224-bit stream; fields split across pages are listed MSBs first. Words 6-10 are spare.
D2_PAGES: dict[int, tuple[tuple[str, int, int], ...]] = {
    1: (
        ("sath1", 42, 1),
        ("aodc", 43, 5),
        ("urai", 48, 4),
        ("wn", 52, 13),
        ("toc", 65, 17),
        ("tgd1", 82, 10),
        ("tgd2", 92, 10),
    ),
    2: (
        ("alpha0", 42, 8),
        ("alpha1", 50, 8),
        ("alpha2", 58, 8),
        ("alpha3", 66, 8),
        ("beta0", 74, 8),
        ("beta1", 82, 8),
        ("beta2", 90, 8),
        ("beta3", 98, 8),
    ),
    3: (("af0", 80, 24), ("af1", 104, 4)),
    4: (("af1", 42, 18), ("af2", 60, 11), ("aode", 71, 5), ("deltan", 76, 16), ("cuc", 92, 14)),
    5: (("cuc", 42, 4), ("m0", 46, 32), ("cus", 78, 18), ("e", 96, 10)),
    6: (("e", 42, 22), ("sqrta", 64, 32), ("cic", 96, 10)),
    7: (("cic", 42, 8), ("cis", 50, 18), ("toe", 68, 17), ("i0", 85, 21)),
    8: (("i0", 42, 11), ("crc", 53, 18), ("crs", 71, 18), ("omegadot", 89, 19)),
    9: (("omegadot", 42, 5), ("omega0", 47, 32), ("omega", 79, 27)),
    10: (("omega", 42, 5), ("idot", 47, 14)),
}
_D1_ATTR = {k: v for table in D1_FIELDS.values() for k, v in table.items()}
_D1_ATTR["toe"] = (0, 17, False, 8.0, False)


def decode_d1_fields(data: int, fra_id: int) -> dict[str, float]:
    """Physical values of a D1 subframe 1-3 (angles in radians, times in seconds)."""
    out: dict[str, float] = {}
    for name, (start, length, signed, scale, semi) in D1_FIELDS[fra_id].items():
        v = _get(data, start, length, signed) * scale
        out[name] = v * ICD_PI if semi else v
    return out


def encode_d1_fields(data: int, fra_id: int, values: dict[str, float]) -> int:
    for name, (start, length, signed, scale, semi) in D1_FIELDS[fra_id].items():
        v = values.get(name, 0.0)
        if semi:
            v /= ICD_PI
            if name in _ANGLES:  # angles wrap into [-1, 1) semicircles
                v = (v + 1.0) % 2.0 - 1.0
        data = _put(data, start, length, round(v / scale), signed)
    return data


def _scaled_int(name: str, value: float) -> tuple[int, int]:
    """(integer, total width) of a field value, with the D1 scale and signedness."""
    _s, length, signed, scale, semi = _D1_ATTR[name]
    if name == "toe":
        length = 17
    v = value
    if semi:
        v /= ICD_PI
        if name in _ANGLES:
            v = (v + 1.0) % 2.0 - 1.0
    n = round(v / scale)
    lo, hi = (-(1 << (length - 1)), 1 << (length - 1)) if signed else (0, 1 << length)
    if not lo <= n < hi:
        raise ValueError(f"{name}={value} does not fit {length} bits")
    return n & ((1 << length) - 1), length


def _d2_widths() -> dict[str, int]:
    widths: dict[str, int] = {}
    for parts in D2_PAGES.values():
        for name, _start, length in parts:
            widths[name] = widths.get(name, 0) + length
    return widths


D2_WIDTHS = _d2_widths()


def encode_d2_page(data: int, page: int, values: dict[str, float]) -> int:
    """Put the page-``page`` parts of D2 subframe 1 into a data stream (ICD 5.3.2)."""
    done: dict[str, int] = {}
    for pg in range(1, page + 1):
        for name, _start, length in D2_PAGES[pg]:
            done[name] = done.get(name, 0) + (length if pg < page else 0)
    for name, start, length in D2_PAGES[page]:
        n, width = _scaled_int(name, values.get(name, 0.0))
        used = done[name]  # bits of this field sent on earlier pages
        part = (n >> (width - used - length)) & ((1 << length) - 1)
        data = _put(data, start, length, part)
    return data


def decode_d2_pages(pages: dict[int, int]) -> dict[str, float]:
    """Physical values from the data streams of D2 subframe 1 pages 1-10."""
    raw: dict[str, int] = {}
    for pg in range(1, 11):
        for name, start, length in D2_PAGES[pg]:
            raw[name] = raw.get(name, 0) << length | _get(pages[pg], start, length)
    out: dict[str, float] = {}
    for name, n in raw.items():
        _s, _l, signed, scale, semi = _D1_ATTR[name]
        width = D2_WIDTHS[name]
        if signed and n >> (width - 1):
            n -= 1 << width
        v = n * scale
        out[name] = v * ICD_PI if semi else v
    return out


def _ura_index(ura_m: float) -> int:
    return next((i for i, u in enumerate(URA_M) if ura_m <= u), 15)


def ephemeris_values(eph: Ephemeris, iono: KlobucharParams | None) -> dict[str, float]:
    """Subframe 1-3 field values of an ephemeris (the inverse of :class:`EphemerisAssembler`)."""
    toe_units = round(eph.toe_sow_s / 8.0)
    a = iono.alpha if iono is not None else (0.0,) * 4
    b = iono.beta if iono is not None else (0.0,) * 4
    return {
        "sath1": eph.health,
        "aodc": eph.aodc,
        "urai": _ura_index(eph.ura_m),
        "wn": eph.week,
        "toc": eph.toc_sow_s,
        "tgd1": eph.tgd1_s,
        "tgd2": eph.tgd2_s,
        "alpha0": a[0],
        "alpha1": a[1],
        "alpha2": a[2],
        "alpha3": a[3],
        "beta0": b[0],
        "beta1": b[1],
        "beta2": b[2],
        "beta3": b[3],
        "af2": eph.af2_s_s2,
        "af0": eph.af0_s,
        "af1": eph.af1_s_s,
        "aode": eph.aode,
        "deltan": eph.delta_n_rad_s,
        "cuc": eph.cuc_rad,
        "m0": eph.m0_rad,
        "e": eph.e,
        "cus": eph.cus_rad,
        "crc": eph.crc_m,
        "crs": eph.crs_m,
        "sqrta": eph.sqrt_a_sqrt_m,
        "toe_msb": toe_units >> 15,
        "toe_lsb": toe_units & 0x7FFF,
        "i0": eph.i0_rad,
        "cic": eph.cic_rad,
        "omegadot": eph.omega_dot_rad_s,
        "cis": eph.cis_rad,
        "idot": eph.idot_rad_s,
        "omega0": eph.omega0_rad,
        "omega": eph.omega_rad,
    }


def encode_d1_subframes(
    eph: Ephemeris, sow_s: int, iono: KlobucharParams | None = None
) -> list[list[int]]:
    """Subframes 1-5 of one D1 frame whose subframe 1 starts at ``sow_s`` (ICD 5.2.3).

    Subframes 4 and 5 carry their page number (frame count mod 24) and no almanac.
    """
    values = ephemeris_values(eph, iono)
    out = []
    page = (int(sow_s) // 30) % 24 + 1
    for fra in range(1, 6):
        data = _header_data(fra, int(sow_s) + 6 * (fra - 1))
        data = encode_d1_fields(data, fra, values) if fra <= 3 else _put(data, 39, 7, page)
        out.append(subframe_words(data))
    return out


def encode_d2_frame(
    eph: Ephemeris, frame_sow_s: int, page: int, iono: KlobucharParams | None = None
) -> list[list[int]]:
    """Subframes 1-5 of one D2 frame (3 s) starting at ``frame_sow_s`` (ICD 5.3.2).

    Every subframe carries the frame's SOW; subframe 1 carries ephemeris page ``page``
    (1-10) and subframe 5 page ((frame count) mod 120) + 1 (its almanac payload is zero).
    """
    values = ephemeris_values(eph, iono)
    values["toe"] = eph.toe_sow_s
    out = []
    for fra in range(1, 6):
        data = _header_data(fra, int(frame_sow_s))
        if fra == 1:
            data = encode_d2_page(_put(data, 38, 4, page), page, values)
        elif fra == 5:
            data = _put(data, 39, 7, (int(frame_sow_s) // 3) % 120 + 1)
        out.append(subframe_words(data))
    return out


class EphemerisAssembler:
    """Collects D1 subframes 1-3, or D2 subframe 1 pages 1-10, into ephemerides.

    A set is complete when subframes 1, 2 and 3 were received with one toe (split across 2
    and 3) and the SOWs of one frame; each new (prn, toe) is returned once, with the
    Klobuchar coefficients of subframe 1 whenever they change.
    """

    def __init__(self) -> None:
        self._parts: dict[str, dict[int, tuple[int, dict[str, float]]]] = {}
        self._done: set[tuple[str, int, float]] = set()
        self._iono: KlobucharParams | None = None
        self._d2: dict[str, dict[int, tuple[int, int]]] = {}
        self.unsupported = 0
        self.errors = 0

    def feed(
        self, prn: str, nav_type: str, words: Sequence[int]
    ) -> list[Ephemeris | KlobucharParams]:
        if nav_type not in ("D1", "D2"):
            self.unsupported += 1
            return []
        try:
            data, _ = subframe_data(words)
        except DecodeError:
            self.errors += 1
            return []
        fra = _get(data, *HEADER["fra_id"])
        if nav_type == "D2":
            return self._feed_d2(prn, fra, data) if fra == 1 else []
        if fra not in (1, 2, 3):
            return []
        sow = _get(data, *HEADER["sow"])
        parts = self._parts.setdefault(prn, {})
        parts[fra] = (sow, decode_d1_fields(data, fra))
        out: list[Ephemeris | KlobucharParams] = []
        if fra == 1:
            v = parts[1][1]
            iono = KlobucharParams(
                alpha=(v["alpha0"], v["alpha1"], v["alpha2"], v["alpha3"]),
                beta=(v["beta0"], v["beta1"], v["beta2"], v["beta3"]),
            )
            if iono != self._iono:
                self._iono = iono
                out.append(iono)
        if len(parts) == 3:
            s1, s2, s3 = parts[1][0], parts[2][0], parts[3][0]
            if s2 - s1 == 6 and s3 - s2 == 6:
                eph = self._ephemeris(prn, parts[1][1], parts[2][1], parts[3][1])
                key = (prn, eph.week, eph.toe_sow_s)
                if key not in self._done:
                    self._done.add(key)
                    out.append(eph)
        return out

    def _feed_d2(self, prn: str, fra: int, data: int) -> list[Ephemeris | KlobucharParams]:
        """D2 subframe 1: pages 1-10 of ten consecutive frames make one set."""
        page = _get(data, 38, 4)
        if not 1 <= page <= 10:
            return []
        sow = _get(data, *HEADER["sow"])
        pages = self._d2.setdefault(prn, {})
        pages[page] = (sow, data)
        if page != 10 or len(pages) < 10:
            return []
        if any(pages[k][0] != sow - 3 * (10 - k) for k in range(1, 11)):
            return []
        v = decode_d2_pages({k: d for k, (_s, d) in pages.items()})
        units = round(v["toe"] / 8.0)
        v["toe_msb"], v["toe_lsb"] = units >> 15, units & 0x7FFF
        eph = self._ephemeris(prn, v, v, v)
        key = (prn, eph.week, eph.toe_sow_s)
        if key in self._done:
            return []
        self._done.add(key)
        return [eph]

    @staticmethod
    def _ephemeris(
        prn: str, f1: dict[str, float], f2: dict[str, float], f3: dict[str, float]
    ) -> Ephemeris:
        toe = (int(f2["toe_msb"]) << 15 | int(f3["toe_lsb"])) * 8.0
        return Ephemeris(
            prn=prn,
            week=int(f1["wn"]),
            toe_sow_s=toe,
            toc_sow_s=f1["toc"],
            af0_s=f1["af0"],
            af1_s_s=f1["af1"],
            af2_s_s2=f1["af2"],
            sqrt_a_sqrt_m=f2["sqrta"],
            e=f2["e"],
            i0_rad=f3["i0"],
            omega0_rad=f3["omega0"],
            omega_rad=f3["omega"],
            m0_rad=f2["m0"],
            delta_n_rad_s=f2["deltan"],
            omega_dot_rad_s=f3["omegadot"],
            idot_rad_s=f3["idot"],
            cuc_rad=f2["cuc"],
            cus_rad=f2["cus"],
            crc_m=f2["crc"],
            crs_m=f2["crs"],
            cic_rad=f3["cic"],
            cis_rad=f3["cis"],
            tgd1_s=f1["tgd1"],
            tgd2_s=f1["tgd2"],
            health=int(f1["sath1"]),
            aode=int(f1["aode"]),
            aodc=int(f1["aodc"]),
            ura_m=URA_M[int(f1["urai"])],
            source="subframes",
        )
