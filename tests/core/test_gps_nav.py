"""GPS LNAV codec (service.core.gps_nav) and its RXM-SFRBX mapping (drivers.sfrbx).

Expected values never come from the code under test:
- the 202 real L1 C/A subframes of the PolyU F9P capture, their parity and bits against
  pygnssutils (RawNavReader reassembles the subframe, RawNav decodes its fields from its own
  IS-GPS-200 tables);
- the decoded ephemerides against the station's RINEX nav file of the same hour;
- the time tags against the receiver's RAWX time (a subframe ends when the next one starts).
"""

from __future__ import annotations

import functools
import math

import pytest
from pygnssutils import rawnav_subframes_gps as rawgps
from pygnssutils.rawnav import RawNav
from pygnssutils.rawnav_reader import RawNavReader
from pyubx2 import UBXReader

from drivers.rinex import read_nav
from drivers.sfrbx import nav_subframe_from_sfrbx
from service.core import gps_nav as gn
from service.core.errors import DecodeError
from service.core.timebase import bdt_to_gpst
from service.core.types import Ephemeris
from tests.support.paths import DATA

POLYU = DATA / "hk-polyu-f9p-ubx-2024"
POLYU_UBX = POLYU / "COM18___9600_240925_072456.ubx"
PI = 3.1415926535898  # IS-GPS-200 20.3.3.4.3.1
WORD = (1 << 30) - 1


@functools.cache
def _sfrbx() -> tuple[tuple[object, float], ...]:
    """Every GPS SFRBX of the capture with the RAWX time tag (GPST tow) before it."""
    out = []
    tow = math.nan
    with open(POLYU_UBX, "rb") as fh:
        for _, msg in UBXReader(fh, protfilter=2, quitonerror=0):
            if msg is None:
                continue
            if msg.identity == "RXM-RAWX":
                tow = float(msg.rcvTow)
            elif msg.identity == "RXM-SFRBX" and msg.gnssId == 0:
                out.append((msg, tow))
    return tuple(out)


def _words(msg) -> tuple[int, ...]:
    return tuple(getattr(msg, f"dwrd_{i:02d}") & WORD for i in range(1, 11))


def _l1ca():
    return [(m, t) for m, t in _sfrbx() if m.sigId == 0]


def test_every_real_l1ca_subframe_passes_parity_and_matches_pygnssutils():
    """202 L1 C/A subframes: parity holds on every word, the bits (words joined) are the
    subframe pygnssutils reassembles, the HOW subframe ID is pygnssutils', and the encoder
    gives the words back. L2C CNAV (sigId 4) is not mapped."""
    reader = RawNavReader()
    rows = _l1ca()
    assert len(rows) == 202
    for msg, tow in rows:
        ref = reader.process_rxm_sfrbx(msg)
        words = _words(msg)
        data = gn.subframe_data(words)
        assert gn.subframe_words(data) == list(words)
        sub = nav_subframe_from_sfrbx(msg, 2333, tow)
        assert sub is not None and sub.nav_type == "LNAV" and sub.signal == "1C"
        assert (sub.prn, sub.fra_id) == (f"G{ref['svid']:02d}", ref["subframeid"])
        assert sum(w << (30 * (9 - k)) for k, w in enumerate(sub.words)) == ref["subframe"]
    cnav = [m for m, _ in _sfrbx() if m.sigId == 4]
    assert cnav and all(nav_subframe_from_sfrbx(m, 2333, 0.0) is None for m in cnav)


def test_any_single_bit_error_fails_parity():
    """The (32,26) Hamming code detects every single error (distance 4, 20.3.5.2): each of the
    300 bits of a real subframe flipped in turn is refused."""
    words = list(_words(_l1ca()[0][0]))
    for k in range(10):
        for bit in range(30):
            bad = words.copy()
            bad[k] ^= 1 << bit
            with pytest.raises(DecodeError):
                gn.subframe_data(bad)


def test_how_time_is_the_end_of_the_subframe_as_received():
    """The HOW TOW count x 6 s is the GPST at the next subframe's start (20.3.3.2): the
    receiver puts each SFRBX out after the RAWX of the epoch at which it completed (flight
    time ~70 ms, 1 Hz epochs). Measured: 191 subframes follow the RAWX of exactly that time,
    4 the RAWX one second later, 7 come before the first RAWX."""
    lag = [gn.parse_header(_words(m)).tow_next_s - t for m, t in _l1ca() if math.isfinite(t)]
    assert (len(lag), lag.count(0.0), lag.count(-1.0)) == (195, 191, 4)
    for msg, _ in _l1ca():
        head = gn.parse_header(_words(msg))
        assert head.start_tow_s == head.tow_next_s - 6.0 and head.tow_next_s % 6 == 0


def _ephemerides() -> list[Ephemeris]:
    asm = gn.LnavAssembler()
    out = [x for msg, _ in _l1ca() for x in asm.feed(f"G{msg.svId:02d}", _words(msg), 2333)]
    assert asm.counters["bad_subframes"] == 0 and asm.counters["mismatched_sets"] == 0
    return [x for x in out if isinstance(x, Ephemeris)]


EXACT = ("week", "toe_sow_s", "toc_sow_s", "health", "aode", "aodc")
REAL = (
    "af0_s", "af1_s_s", "af2_s_s2", "sqrt_a_sqrt_m", "e", "i0_rad", "omega0_rad",
    "omega_rad", "m0_rad", "delta_n_rad_s", "omega_dot_rad_s", "idot_rad_s", "cuc_rad",
    "cus_rad", "crc_m", "crs_m", "cic_rad", "cis_rad", "tgd1_s",
)  # fmt: skip


def test_decoded_ephemerides_equal_the_rinex_nav_of_the_hour():
    """The 8 sets the capture completes (G10 G12 G23 G25 G26 G28 G31 G32) are the station's
    RINEX nav sets of the same PRN and toe: times, IODE/IODC and health exactly; T_GD, the
    Keplerian and clock terms to 1e-7 relative (the RINEX writer's float rounding, far below
    each LSB)."""
    rinex = read_nav(POLYU / "hksc269h.24n", systems="G").ephemerides
    got = _ephemerides()
    assert sorted(e.prn for e in got) == [
        "G10", "G12", "G23", "G25", "G26", "G28", "G31", "G32",
    ]  # fmt: skip
    for e in got:
        ref = next(r for r in rinex[e.prn] if (r.week, r.toe_sow_s) == (e.week, e.toe_sow_s))
        for name in EXACT:
            assert getattr(e, name) == getattr(ref, name), (e.prn, name)
        for name in REAL:
            a, b = getattr(e, name), getattr(ref, name)
            assert math.isclose(a, b, rel_tol=1e-7, abs_tol=1e-19), (e.prn, name, a, b)
        assert bdt_to_gpst(e.week, e.toe_sow_s) == (2333, 288000.0) or e.prn == "G12"


def _rawnav(prn: int, subframes: list[tuple[int, ...]]) -> RawNav:
    rn = RawNav("G", prn, "1C")
    defs = {
        1: rawgps.GPS_LNAV_SUBFRAME_1,
        2: rawgps.GPS_LNAV_SUBFRAME_2,
        3: rawgps.GPS_LNAV_SUBFRAME_3,
    }
    for words in subframes:
        data = sum(w << (30 * (9 - k)) for k, w in enumerate(words))
        rn.parse(data, defs[gn.parse_header(words).subframe_id], 0, sequence=True)
    return rn


def test_decoded_fields_equal_pygnssutils_rawnav():
    """Every ephemeris field against pygnssutils RawNav decoding the same three subframes
    with its own tables (angles in semicircles, split fields joined by RawNav)."""
    by_prn: dict[str, dict[int, tuple[int, ...]]] = {}
    for msg, _ in _l1ca():
        w = _words(msg)
        by_prn.setdefault(f"G{msg.svId:02d}", {})[gn.parse_header(w).subframe_id] = w
    checked = 0
    for e in _ephemerides():
        sfs = by_prn[e.prn]
        if any(k not in sfs for k in (1, 2, 3)):
            continue
        rn = _rawnav(int(e.prn[1:]), [sfs[1], sfs[2], sfs[3]])
        pairs = {
            "sqrta": e.sqrt_a_sqrt_m,
            "e": e.e,
            "m0": e.m0_rad / PI,
            "i0": e.i0_rad / PI,
            "omega0": e.omega0_rad / PI,
            "omega": e.omega_rad / PI,
            "deltan": e.delta_n_rad_s / PI,
            "omegadot": e.omega_dot_rad_s / PI,
            "idot": e.idot_rad_s / PI,
            "cuc": e.cuc_rad,
            "cus": e.cus_rad,
            "crc": e.crc_m,
            "crs": e.crs_m,
            "cic": e.cic_rad,
            "cis": e.cis_rad,
            "af0": e.af0_s,
            "af1": e.af1_s_s,
            "af2": e.af2_s_s2,
            "tgd": e.tgd1_s,
            "iode": e.aode,
            "svhealth": e.health,
        }
        for name, ours in pairs.items():
            assert math.isclose(ours, getattr(rn, name), rel_tol=1e-12, abs_tol=1e-22), (
                e.prn,
                name,
            )
        w, t = bdt_to_gpst(e.week, e.toe_sow_s)
        assert (w % 1024, t) == (rn.wn, rn.toe)
        checked += 1
    assert checked == 8


def test_another_receivers_subframes_pass_the_same_parity():
    """The gpsd project's u-blox X20P capture: 34 of its 35 L1 C/A subframes pass the
    delivered-word parity (the other fails in word 2 and is refused), and 6 sets complete
    with matching IODC/IODE."""
    asm = gn.LnavAssembler()
    with open(DATA / "ublox-logs" / "ublox-x20p.log", "rb") as fh:
        for _, msg in UBXReader(fh, protfilter=2, quitonerror=0):
            if msg is None or msg.identity != "RXM-SFRBX" or (msg.gnssId, msg.sigId) != (0, 0):
                continue
            asm.feed(f"G{msg.svId:02d}", _words(msg), 2400)
    assert asm.counters == {
        "subframes": 35,
        "bad_subframes": 1,
        "mismatched_sets": 0,
        "ephemerides": 6,
    }


def test_subframe4_page18_gives_the_days_gpsa_gpsb():
    """Klobuchar alpha/beta of subframe 4 page 18 (SV ID 56; IS-GPS-200 Figure 20-1 sheet 8:
    word 3 data ID, SV ID, alpha0, alpha1; word 4 alpha2, alpha3, beta0; word 5 beta1-3;
    scales per Table 20-X). The captures carry no page 18 (it comes every 12.5 min), so the
    page is built here, bit by bit, from the station's GPSA/GPSB of the day (as integers of
    each LSB), and must decode back to them."""
    iono = read_nav(POLYU / "hksc269h.24n", systems="G").iono_gps
    assert iono is not None
    scales = (2.0**-30, 2.0**-27, 2.0**-24, 2.0**-24, 2.0**11, 2.0**14, 2.0**16, 2.0**16)
    ints = [round(v / s) for v, s in zip((*iono.alpha, *iono.beta), scales, strict=True)]
    bits = "10001011" + "0" * 16  # word 1: TLM preamble
    bits += format(285918 // 6, "017b") + "00" + "100" + "00"  # word 2: HOW, subframe ID 4
    bits += "01" + format(56, "06b")  # word 3: data ID 1, SV ID 56
    bits += "".join(format(n & 0xFF, "08b") for n in ints)
    bits += "0" * (240 - len(bits))
    words = gn.subframe_words(int(bits, 2))
    out = gn.LnavAssembler().feed("G10", words, 2333)
    assert len(out) == 1 and out[0].system == "GPS"
    got = (*out[0].alpha, *out[0].beta)
    assert got == tuple(n * s for n, s in zip(ints, scales, strict=True))
    # RINEX prints 5 significant digits: the broadcast integers give its values back to that
    assert got == pytest.approx((*iono.alpha, *iono.beta), rel=5e-5)
