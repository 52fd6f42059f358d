"""B1I navigation codec: BCH and word properties (hypothesis), the real PolyU F9P subframes
against the RINEX nav file and against pygnssutils RawNav, an independent decoder."""

from __future__ import annotations

import dataclasses
import math

import pytest
import pyubx2
from hypothesis import given, settings
from hypothesis import strategies as st
from pygnssutils import rawnav_subframes_bds as rawbds
from pygnssutils.rawnav import RawNav

from drivers.rinex import read_nav
from drivers.sfrbx import nav_subframe_from_sfrbx
from service import bds_nav as bn
from service.types import Ephemeris, KlobucharParams
from tests._independent import DATA

UBX = DATA / "hk-polyu-f9p-ubx-2024/COM18___9600_240925_072456.ubx"
NAV = DATA / "hk-polyu-f9p-ubx-2024/hksc269h.24f"
RAWNAV_DEFS = {
    1: rawbds.BDS_D1_SUBFRAME_1,
    2: rawbds.BDS_D1_SUBFRAME_2,
    3: rawbds.BDS_D1_SUBFRAME_3,
}


@given(st.integers(0, 0x7FF))
def test_bch_round_trip_and_single_error_correction(info):
    code = info << 4 | bn.bch_parity(info)
    assert bn.bch_decode(code) == (info, 0)
    for bit in range(15):
        assert bn.bch_decode(code ^ (1 << bit)) == (info, 1)


@given(st.integers(0, (1 << 22) - 1), st.integers(0, (1 << 11) - 1))
def test_words_and_interleaving_round_trip(data22, info):
    w = bn.encode_word(data22, first=False)
    assert bn.decode_word(w, False) == (data22, 0)
    assert bn.deinterleave_word(bn.interleave_word(w)) == w
    first = bn.encode_word(bn.PREAMBLE << 15 | info, first=True)
    assert bn.decode_word(first, True) == (bn.PREAMBLE << 15 | info, 0)


def test_interleave_alternates_codeword_bits():
    # codeword 1 all ones, codeword 2 all zeros -> on air 1010...10
    w = 0x7FF << 19 | 0xF << 4
    assert bn.interleave_word(w) == int("10" * 15, 2)


def _real_subframes():
    out, rawx_tow = [], None
    with UBX.open("rb") as fh:
        for _raw, msg in pyubx2.UBXReader(fh, protfilter=2, quitonerror=0):
            if msg is None:
                continue
            if msg.identity == "RXM-RAWX":
                rawx_tow = msg.rcvTow
            elif msg.identity == "RXM-SFRBX" and msg.gnssId == 3 and msg.sigId == 0:
                out.append((msg, rawx_tow))
    return out


@pytest.fixture(scope="module")
def real():
    return _real_subframes()


def test_real_subframes_parity_preamble_and_sow(real):
    assert len(real) >= 130  # 136 of the 230 BDS subframes are B1I (the rest B2I)
    last: dict[str, int] = {}
    for msg, rawx_tow in real:
        sf = nav_subframe_from_sfrbx(msg, 2333, rawx_tow or 0.0)
        assert sf is not None and sf.nav_type == "D1" and 1 <= sf.fra_id <= 5
        _, corrected = bn.subframe_data(sf.words)
        assert corrected == 0
        # the subframe arrived at its end: SOW (BDT) + 14 s (GPST) + 6 s = the receiver time
        assert abs(sf.sow_s + 14 + 6 - rawx_tow) <= 1.0
        if sf.prn in last:
            assert (sf.sow_s - last[sf.prn]) % 6 == 0
        last[sf.prn] = sf.sow_s


def test_real_ephemerides_equal_the_rinex_nav_file(real):
    nav = read_nav(NAV)
    asm = bn.EphemerisAssembler()
    ephs, ionos = [], []
    for msg, _ in real:
        words = [getattr(msg, f"dwrd_{i:02d}") for i in range(1, 11)]
        for item in asm.feed(f"C{msg.svId:02d}", "D1", words):
            (ephs if isinstance(item, Ephemeris) else ionos).append(item)
    assert len(ephs) >= 8
    assert ionos[0].alpha[0] == pytest.approx(4.4703e-08, rel=1e-4)  # BDSA line of the .24f
    for e in ephs:
        (ref,) = [r for r in nav.ephemerides[e.prn] if r.toe_sow_s == e.toe_sow_s]
        for f in (
            "sqrt_a_sqrt_m",
            "e",
            "i0_rad",
            "omega0_rad",
            "omega_rad",
            "m0_rad",
            "delta_n_rad_s",
            "omega_dot_rad_s",
            "idot_rad_s",
            "cuc_rad",
            "cus_rad",
            "crc_m",
            "crs_m",
            "cic_rad",
            "cis_rad",
            "af0_s",
            "af1_s_s",
            "af2_s_s2",
            "tgd1_s",
            "toc_sow_s",
        ):
            assert math.isclose(getattr(e, f), getattr(ref, f), rel_tol=1e-9, abs_tol=1e-15), f
        assert (e.week, e.health, e.aode) == (ref.week, ref.health, ref.aode)


def _rawnav(prn: int, subframes) -> RawNav:
    rn = RawNav("C", prn, "2I")
    for words in subframes:
        data = 0
        for w in words:
            data = data << 30 | (w & 0x3FFFFFFF)
        fra = (words[0] >> 12) & 7
        if fra in RAWNAV_DEFS:
            rn.parse(data, RAWNAV_DEFS[fra], 0, sequence=False)
    return rn


def _compare_with_rawnav(e: Ephemeris, rn: RawNav) -> None:
    pi = bn.ICD_PI
    pairs = {
        "sqrta": e.sqrt_a_sqrt_m,
        "e": e.e,
        "m0": e.m0_rad / pi,
        "i0": e.i0_rad / pi,
        "omega0": e.omega0_rad / pi,
        "omega": e.omega_rad / pi,
        "deltan": e.delta_n_rad_s / pi,
        "omegadot": e.omega_dot_rad_s / pi,
        "idot": e.idot_rad_s / pi,
        "cuc": e.cuc_rad,
        "cus": e.cus_rad,
        "crc": e.crc_m,
        "crs": e.crs_m,
        "cic": e.cic_rad,
        "cis": e.cis_rad,
        "af0": e.af0_s,
        "af1": e.af1_s_s,
        "toe": e.toe_sow_s,
        "toc": e.toc_sow_s,
        "tgd1": e.tgd1_s * 1e9,
    }
    for k, v in pairs.items():
        assert math.isclose(getattr(rn, k), v, rel_tol=1e-9, abs_tol=1e-15), k


def test_real_subframes_decode_like_rawnav(real):
    by_prn: dict[int, list] = {}
    for msg, _ in real:
        by_prn.setdefault(msg.svId, []).append(
            [getattr(msg, f"dwrd_{i:02d}") for i in range(1, 11)]
        )
    checked = 0
    for prn, sfs in by_prn.items():
        asm = bn.EphemerisAssembler()
        ephs = [
            x for w in sfs for x in asm.feed(f"C{prn:02d}", "D1", w) if isinstance(x, Ephemeris)
        ]
        if ephs:
            firsts = {}
            for w in sfs:  # the frame that completed the first set
                firsts.setdefault((w[0] >> 12) & 7, w)
            _compare_with_rawnav(ephs[0], _rawnav(prn, [firsts[k] for k in sorted(firsts)]))
            checked += 1
    assert checked >= 8


finite = st.floats(allow_nan=False, allow_infinity=False)


@settings(max_examples=25, deadline=None)
@given(
    sqrt_a=st.floats(5000, 6500),
    e=st.floats(0, 0.02),
    ang=st.lists(st.floats(-3.14, 3.14), min_size=4, max_size=4),
    rates=st.lists(st.floats(-2.5e-9, 2.5e-9), min_size=3, max_size=3),
    harm=st.lists(st.floats(-1e-5, 1e-5), min_size=4, max_size=4),
    rc=st.lists(st.floats(-1000, 1000), min_size=2, max_size=2),
    af0=st.floats(-9e-4, 9e-4),
    toe=st.integers(0, 604792 // 8),
    week=st.integers(0, 8191),
    sow=st.integers(0, 20159),
)
def test_d1_encode_decode_round_trip(sqrt_a, e, ang, rates, harm, rc, af0, toe, week, sow):
    eph = Ephemeris(
        prn="C11",
        week=week,
        toe_sow_s=toe * 8.0,
        toc_sow_s=toe * 8.0,
        af0_s=af0,
        af1_s_s=1e-11,
        af2_s_s2=0.0,
        sqrt_a_sqrt_m=sqrt_a,
        e=e,
        i0_rad=ang[0],
        omega0_rad=ang[1],
        omega_rad=ang[2],
        m0_rad=ang[3],
        delta_n_rad_s=rates[0] / 10,
        omega_dot_rad_s=rates[1],
        idot_rad_s=rates[2],
        cuc_rad=harm[0],
        cus_rad=harm[1],
        cic_rad=harm[2],
        cis_rad=harm[3],
        crc_m=rc[0],
        crs_m=rc[1],
        tgd1_s=2e-9,
        aode=7,
        aodc=3,
        ura_m=2.4,
    )
    iono = KlobucharParams(alpha=(1e-8, 2e-8, -1e-7, 1e-7), beta=(1e5, 0.0, -2e5, 1e5))
    sfs = bn.encode_d1_subframes(eph, sow * 30, iono)
    asm = bn.EphemerisAssembler()
    out = [x for sf in sfs for x in asm.feed("C11", "D1", sf)]
    (got,) = [x for x in out if isinstance(x, Ephemeris)]
    (io,) = [x for x in out if isinstance(x, KlobucharParams)]
    scale = {
        "sqrt_a_sqrt_m": 2**-19,
        "e": 2**-33,
        "af0_s": 2**-33,
        "crc_m": 2**-6,
        "crs_m": 2**-6,
        "cuc_rad": 2**-31,
        "cus_rad": 2**-31,
    }
    for f, q in scale.items():
        assert abs(getattr(got, f) - getattr(eph, f)) <= q / 2 + 1e-15, f
    for f in ("i0_rad", "omega0_rad", "omega_rad", "m0_rad"):
        assert abs(getattr(got, f) - getattr(eph, f)) <= bn.ICD_PI * 2**-31, f
    assert (got.week, got.toe_sow_s, got.aode) == (eph.week, eph.toe_sow_s, eph.aode)
    assert abs(io.alpha[0] - 1e-8) <= 2**-31 and io.beta[2] == -3 * 2**16  # quantised
    for k, sf in enumerate(sfs, start=1):
        h = bn.parse_header(sf, "D1")
        assert (h.fra_id, h.sow_s) == (k, sow * 30 + 6 * (k - 1))
    # a second decoder agrees on the encoded subframes
    _compare_with_rawnav(got, _rawnav(11, sfs[:3]))


def test_d2_frame_headers_and_pages():
    eph = read_nav(NAV).ephemerides["C01"][0]
    for frame in (0, 1, 9, 37):
        sfs = bn.encode_d2_frame(eph, frame * 3, frame % 10 + 1)
        for k, sf in enumerate(sfs, start=1):
            h = bn.parse_header(sf, "D2")
            assert (h.fra_id, h.sow_s) == (k, frame * 3)
            if k == 1:
                assert h.page == frame % 10 + 1


def test_corrupted_word_is_corrected_or_rejected():
    eph = dataclasses.replace(read_nav(NAV).ephemerides["C06"][0])
    sf = bn.encode_d1_subframes(eph, 300)[1]
    bad = list(sf)
    bad[4] ^= 1 << 7  # one bit in word 5
    assert bn.subframe_data(bad) == (bn.subframe_data(sf)[0], 1)
    no_preamble = [sf[0] ^ (1 << 29), *sf[1:]]
    with pytest.raises(bn.DecodeError):
        bn.subframe_data(no_preamble)


@pytest.mark.parametrize("prn", ["C01", "C02", "C03", "C04", "C05"])
def test_d2_ephemeris_pages_round_trip(prn):
    """D2 subframe 1 pages 1-10 over ten frames give back the GEO ephemeris (quantised)."""
    eph = read_nav(DATA / "hksc-2021/hksc1610.nav").ephemerides[prn][0]
    asm = bn.EphemerisAssembler()
    out = []
    for frame in range(200, 215):  # starts mid-cycle: the set completes at the next page 10
        out += asm.feed(prn, "D2", bn.encode_d2_frame(eph, frame * 3, frame % 10 + 1)[0])
    (got,) = out
    assert (got.week, got.toe_sow_s, got.toc_sow_s, got.aode) == (
        eph.week,
        eph.toe_sow_s,
        eph.toc_sow_s,
        eph.aode,
    )
    assert abs(got.sqrt_a_sqrt_m - eph.sqrt_a_sqrt_m) <= 2**-20
    for f in ("m0_rad", "omega_rad", "omega0_rad", "i0_rad"):
        assert abs(math.remainder(getattr(got, f) - getattr(eph, f), 2 * math.pi)) <= 2**-31 * 4
    for f, q in (
        ("af0_s", 2**-33),
        ("af1_s_s", 2**-50),
        ("crc_m", 2**-6),
        ("cuc_rad", 2**-31),
        ("omega_dot_rad_s", 4 * 2**-43),
        ("idot_rad_s", 4 * 2**-43),
    ):
        assert abs(getattr(got, f) - getattr(eph, f)) <= q, f
