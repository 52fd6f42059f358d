"""GPS and Galileo from the Septentrio SBF capture (issue 19): MeasEpoch GPS L1 C/A and
Galileo E1 rows, GPSNav/GALNav ephemerides, GPSIon, GALGstGps (GGTO) and GPSRawCA subframes
of ../shared/data/leuven-septentrio-sbf-2025 with ``--systems C,G,E``.

The dataset has no RINEX nav file of its day; the references are pysbf2's own parse of the
blocks (counts, week, SISA index), the ranges the receiver measured from the position it
computed itself (PVTGeodetic), the IS-GPS-200 LNAV parity of each raw subframe, and the
Galileo I/NAV words of GALRawINAV decoded independently (tests/drivers/test_gal_inav.py).
"""

from __future__ import annotations

import functools
import math
import struct

import numpy as np
import pytest
from pysbf2 import SBFReader

from drivers.sbf import GAL_NAV, SbfMapper
from drivers.source import open_source
from service.core.constants import C_M_S
from service.core.counters import Counters, skipped_input
from service.core.ephemeris import EphemerisStore, ephemeris_problem
from service.core.geometry import geodetic_to_ecef
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.types import (
    Ephemeris,
    KlobucharParams,
    MeasurementEpoch,
    NavSubframe,
    TimeOffset,
)
from service.engine.solver import IonoSet, SolverConfig, solve
from tests.support.captures import edit_sbf_field
from tests.support.paths import DATA

LOG = DATA / "leuven-septentrio-sbf-2025" / "log_0000.sbf"
OMEGA_E = 7.2921151467e-5  # IS-GPS-200 20.3.3.4.3 and OS SIS ICD 5.1.1 (the same value)


@functools.cache
def _blocks() -> tuple[tuple[bytes, object], ...]:
    with open(LOG, "rb") as fh:
        return tuple((bytes(raw), msg) for raw, msg in SBFReader(fh))


@functools.cache
def _events(systems: str) -> tuple[tuple, dict]:
    with open_source(str(LOG), systems=frozenset(systems)) as src:
        events = tuple(src)
        return events, dict(src.counters)


def _of(events, kind):
    return [e for e in events if isinstance(e, kind)]


def test_default_systems_keep_beidou_alone():
    events, counters = _events("C")
    assert {e.prn[0] for e in _of(events, Ephemeris)} == {"C"}
    assert all({p[0] for p in ep.prn} == {"C"} for ep in _of(events, MeasurementEpoch))
    assert not _of(events, TimeOffset)
    assert all(k.system == "BDS" for k in _of(events, KlobucharParams))
    assert all(s.nav_type == "D1" for s in _of(events, NavSubframe))
    assert "meas_G" not in counters and "ephemerides_sbf_G" not in counters


def test_every_gps_and_galileo_nav_block_becomes_an_ephemeris():
    """18 GPSNav and 16 GALNav (all I/NAV, Source 2) give one set each; the week resolves to
    the block's WNc (GPSNav's WNt_oe is modulo 1024), SISA index 107 is 3.12 m (OS SIS ICD
    Table 76), and the one Galileo set flagged unhealthy by the receiver (E14, E1-B HS = 1)
    is refused by the store with the ``unhealthy`` check; every other set passes the
    store's entry checks."""
    kinds = [m.identity for _, m in _blocks()]
    events, counters = _events("CGE")
    ephs = _of(events, Ephemeris)
    gps = [e for e in ephs if e.prn[0] == "G"]
    gal = [e for e in ephs if e.prn[0] == "E"]
    assert len(gps) == kinds.count("GPSNav") == 18
    assert len(gal) == kinds.count("GALNav") == 16
    assert counters["ephemerides_sbf_G"] == 18 and counters["ephemerides_sbf_E"] == 16
    galnav = {f"E{m.SVID - 70:02d}": m for _, m in _blocks() if m.identity == "GALNav"}
    for e in gal:
        m = galnav[e.prn]
        assert e.week == int(m.WNt_oe) - 1356  # GPS week -> BDT week
        assert e.toe_sow_s == (float(m.t_oe) - 14.0) % 604800
        assert e.aode == int(m.IODnav)
    assert {round(e.ura_m, 2) for e in gal} == {3.12}
    store = EphemerisStore()
    kept = {e.prn for e in gps + gal if store.add(e)}
    assert kept == {e.prn for e in gps + gal} - {"E14"}
    assert store.refused_by_reason == {"unhealthy": 1}
    gpsnav = {f"G{m.PRN:02d}": m for _, m in _blocks() if m.identity == "GPSNav"}
    for e in gps:
        assert e.week + 1356 == 2360 and e.aode == int(gpsnav[e.prn].IODE2)
        assert ephemeris_problem(e) is None


def _receiver_ecef() -> dict[float, np.ndarray]:
    out = {}
    for raw, m in _blocks():
        if m.identity == "PVTGeodetic":
            tow = int.from_bytes(raw[8:12], "little") / 1000
            out[tow] = geodetic_to_ecef(float(m.Latitude), float(m.Longitude), float(m.Height))
    return out


@pytest.mark.parametrize("system", ["G", "E"])
def test_ephemerides_put_satellites_where_the_ranges_say(system):
    """The GPS / Galileo set of each satellite at its transmit time, seen from the receiver's
    own PVTGeodetic position: pseudorange - geometric range + c * satellite clock is the
    receiver clock (common) plus atmosphere; above 15 deg elevation its spread is under
    25 m in every epoch (a semicircle, t_oe or week error moves satellites by km)."""
    events, _ = _events("CGE")
    ephs = {e.prn: e for e in _of(events, Ephemeris) if e.prn[0] == system and not e.health}
    rx_of = _receiver_ecef()
    n_epochs = 0
    for epoch in _of(events, MeasurementEpoch):
        rx = rx_of[epoch.gpst_tow_s]
        up = rx / np.linalg.norm(rx)
        res = []
        for prn, pr, sig in zip(epoch.prn, epoch.pr_m, epoch.signal, strict=True):
            if prn not in ephs:
                continue
            assert sig == "1C"
            eph = ephs[prn]
            t_bdt = epoch.gpst_tow_s - 14.0 - pr / C_M_S
            pos, clk = sat_pos_clock(EphemerisArrays.from_ephemerides([eph]), eph.week, t_bdt)
            rot = OMEGA_E * pr / C_M_S
            x, y, z = pos[0]
            sat = np.array(
                [x * math.cos(rot) + y * math.sin(rot), y * math.cos(rot) - x * math.sin(rot), z]
            )
            los = sat - rx
            rng = np.linalg.norm(los)
            if np.dot(los / rng, up) > math.sin(math.radians(15)):
                res.append(pr - rng + C_M_S * clk[0])
        assert len(res) >= 5
        assert np.ptp(res) < 25.0, (epoch.gpst_tow_s, res)
        n_epochs += 1
    assert n_epochs == 12


def test_rows_of_each_system_follow_the_reference_guide_signal_table():
    """GPS rows are signal 0 (L1 C/A) of SVIDs 1-37, Galileo rows signal 17 (E1) of SVIDs
    71-106, one per satellite, with a full pseudorange and the system's code period."""
    events, counters = _events("CGE")
    epochs = _of(events, MeasurementEpoch)
    assert len(epochs) == 12
    for ep in epochs:
        by = {s: [i for i, p in enumerate(ep.prn) if p[0] == s] for s in "CGE"}
        assert len(by["G"]) == 12 and 9 <= len(by["E"]) <= 10 and 8 <= len(by["C"]) <= 11
        assert all(ep.signal[i] == "1C" for i in by["G"] + by["E"])
        assert np.all(np.isfinite(ep.pr_m))
        assert set(ep.period_s[by["E"]]) == {4e-3} and set(ep.period_s[by["G"]]) == {1e-3}
    assert counters["meas_G"] == sum(sum(p[0] == "G" for p in e.prn) for e in epochs)


def test_fix_with_every_system_near_the_receivers_own_position():
    """SPP with the capture's own BDSNav/GPSNav/GALNav and BDSIon/GPSIon: every epoch fixes
    with a clock per system (C, G, E) within 5 m of the receiver's own PVTGeodetic
    (measured 3.98-4.37 m); BeiDou alone, 5.93-6.65 m."""
    rx_of = _receiver_ecef()
    err = {}
    for systems in ("C", "CGE"):
        events, _ = _events(systems)
        store, iono = EphemerisStore(), IonoSet()
        store.add_all(_of(events, Ephemeris))
        for k in _of(events, KlobucharParams):
            iono = iono.with_params(k)
        fixes = [
            solve(ep, store, iono, SolverConfig(), "spp") for ep in _of(events, MeasurementEpoch)
        ]
        assert len(fixes) == 12 and all(f.ok for f in fixes)
        assert all(set(f.clocks_m or {"C": 0}) == set(systems) for f in fixes)
        err[systems] = [
            float(np.linalg.norm(np.subtract(f.x_ecef_m, rx_of[f.gpst_tow_s]))) for f in fixes
        ]
    assert max(err["CGE"]) < 5.0, err["CGE"]
    assert np.median(err["CGE"]) < np.median(err["C"])


def test_ggto_iono_and_gps_subframes():
    """GALGstGps is the GGTO (A0G, A1G, t0G, WN0G modulo 64 resolved to the block's week);
    GPSIon the GPS Klobuchar set; each GPSRawCA (CRC passed) an LNAV subframe whose ten
    words are bits 29-0 of each u4 as stored (the LNAV decoder took them: parity and
    preamble pass, IS-GPS-200 20.3.5) and whose HOW time is
    the block's time tag (the subframe's end)."""
    events, _ = _events("CGE")
    blocks = _blocks()
    gst = next(m for _, m in blocks if m.identity == "GALGstGps")
    (off,) = _of(events, TimeOffset)
    assert (off.pair, off.a0_s, off.a1_s_s, off.t_ref_s) == (
        "GAGP",
        float(gst.A_0G),
        float(gst.A_1G),
        float(gst.t_oG),
    )
    assert off.week % 64 == int(gst.WN_oG) and off.week == 2360
    assert off.at_s(2360, 212545.0) == 0.0  # this day's broadcast: A0G = A1G = 0
    ion = next(m for _, m in blocks if m.identity == "GPSIon")
    (gps_k,) = [k for k in _of(events, KlobucharParams) if k.system == "GPS"]
    assert gps_k.alpha == tuple(float(getattr(ion, f"alpha_{i}")) for i in range(4))
    raw = [(r, m) for r, m in blocks if m.identity == "GPSRawCA" and m.CRCPassed]
    lnav = [s for s in _of(events, NavSubframe) if s.nav_type == "LNAV"]
    assert len(lnav) == len(raw) == 24
    for s, (r, m) in zip(lnav, raw, strict=True):
        assert s.prn == f"G{m.SVID:02d}"
        words = [w & 0x3FFFFFFF for (w,) in struct.iter_unpack("<I", bytes(m.NavBits)[:40])]
        assert list(s.words) == words
        assert s.sow_s == int.from_bytes(r[8:12], "little") / 1000
    assert {s.fra_id for s in lnav} == {4, 5}


def test_the_loop_records_the_ggto_in_status_and_solves_with_three_clocks():
    """The capture through the daemon's loop: the GALGstGps reaches the pipeline (counted
    ``ggto_sbf``), STATUS carries ``ggto_ns`` (0: this day's broadcast), and the fixes use a
    clock per system, untouched by the GGTO (recorded, never applied)."""
    from service.daemon.loop import Runner
    from service.engine.pipeline import Pipeline
    from service.output.publish import Publishers

    results = []
    with open_source(str(LOG), systems=frozenset("CGE")) as src:
        runner = Runner(src, Pipeline(EphemerisStore()), Publishers(), on_result=results.append)
        assert runner.run() == 12
        counters = runner.counters()
    assert counters["ggto_sbf"] == 1 and counters["ggto_ns"] == 0.0
    assert all(set(r.fix.clocks_m) == {"C", "G", "E"} for r in results)


def test_a_galnav_block_without_e1b_health_is_refused():
    """A GALNav block whose E1-B health is flagged not available (``L1-BHealth`` 0) gives no
    set: an E1 user would take a satellite of unknown health as healthy (RINEX Table A8 has
    no 'unknown'); the real block, flag set, gives its set."""
    raw_msg = next(m for _, m in _blocks() if m.identity == "GALNav")
    wnc = int(raw_msg.WNc)
    mapper = SbfMapper(Counters(), systems="CGE")
    assert len(mapper._on_other_nav(GAL_NAV, raw_msg, wnc)) == 1

    class _Unknown:  # the real block with its E1-B health flag cleared (pysbf2's is frozen)
        def __getattr__(self, name: str) -> object:
            return 0 if name == "L1-BHealth" else getattr(raw_msg, name)

    unknown = _Unknown()
    assert mapper._on_other_nav(GAL_NAV, unknown, wnc) == []
    assert mapper.counters["galnav_no_e1b_health"] == 1


# byte offsets of t_oe (u4 s) in the blocks (SBF reference guide: GPSNav and BDSNav carry the
# same layout up to t_oe; GALNav's Keplerian floats come first), checked by pysbf2 below
TOE_AT = {"GPSNav": (5891, 88), "GALNav": (GAL_NAV, 100), "BDSNav": (4081, 88)}
LETTER = {"GPSNav": "G", "GALNav": "E", "BDSNav": "C"}
WEEK_S = 604_800  # IS-GPS-200 20.3.3.4.3: t_oe at most 604,784 s


@pytest.mark.parametrize(
    ("block", "damage"),
    [
        # the do-not-use value
        pytest.param("GPSNav", lambda toe: 0xFFFFFFFF, id="gpsnav-ffffffff"),
        # the same time a week on: no time of week
        pytest.param("GPSNav", lambda toe: toe + WEEK_S, id="gpsnav-plus-a-week"),
        pytest.param("GALNav", lambda toe: 0xFFFFFFFF, id="galnav-ffffffff"),
        pytest.param("BDSNav", lambda toe: 0xFFFFFFFF, id="bdsnav-ffffffff"),
    ],
)
def test_a_nav_block_whose_toe_is_no_time_of_the_week_is_counted_and_never_wrapped(
    tmp_path, block, damage
):
    """The first ``block`` with its t_oe outside [0, 604800) s (CRC made again): counted
    ``eph_bad_toe`` 1 (before: nothing), as RTCM 1019/1046/1042 are; a GPSNav/GALNav gives no
    set (before: its time wrapped, week 2360 + 7101 or + 1, the set held as another week's),
    a BDSNav is passed on as read and the store refuses it (check ``time_of_week``)."""
    number, offset = TOE_AT[block]
    hit: list[int] = []

    def first_only(toe: float) -> float:
        hit.append(int(toe))
        return damage(toe) if len(hit) == 1 else toe

    damaged = tmp_path / "toe.sbf"
    assert edit_sbf_field(LOG, damaged, number, offset, "<I", first_only) == 1
    with open(damaged, "rb") as fh:
        toes = [float(m.t_oe) for _, m in SBFReader(fh) if m.identity == block]
    assert toes[0] == damage(hit[0]) and toes[1:] == hit[1:]
    assert all(0 <= t < WEEK_S for t in hit)

    with open_source(str(damaged), systems=frozenset("CGE")) as src:
        events = list(src)
        counters = dict(src.counters)
    clean_events, clean = _events("CGE")
    assert clean.get("eph_bad_toe", 0) == 0 and counters["eph_bad_toe"] == 1
    # the summaries' skipped input (and STATUS) name it
    assert skipped_input(counters).get("eph_bad_toe") == 1
    assert "eph_bad_toe" not in skipped_input(clean)
    letter = LETTER[block]
    mine = [e for e in _of(events, Ephemeris) if e.prn[0] == letter]
    ref = [e for e in _of(clean_events, Ephemeris) if e.prn[0] == letter]
    # every set put on BDT lies within a week of the recording's (WNc 2360, DATA/README.md)
    assert all(abs(e.week + 1356 - 2360) <= 1 for e in mine)
    if block == "BDSNav":
        assert len(mine) == len(ref) == 20  # DATA/README.md: BDSNav x20
        bad = [e for e in mine if e.toe_sow_s == 0xFFFFFFFF]
        assert len(bad) == 1
        store = EphemerisStore()
        assert not store.add(bad[0])
        assert ephemeris_problem(bad[0]).check == "time_of_week"
    else:
        assert len(mine) == len(ref) - 1
        assert counters[f"ephemerides_sbf_{letter}"] == clean[f"ephemerides_sbf_{letter}"] - 1
