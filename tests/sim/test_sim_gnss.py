"""The virtual receiver with GPS and Galileo satellites from a real mixed nav file (HKSC
2021-06-10, ../shared/data/hksc-2021/hksc1610.nav), each with its own message timing:
GPS LNAV subframes on 6 s of GPST with the HOW (IS-GPS-200 20.3.2, 20.3.3.2), Galileo E1-B
I/NAV pages of 2 s on odd GST seconds, the time known at the end of a page of word type
0/5/6 (OS SIS ICD 4.3.5).

References: the nav file's own sets (the subframes and pages the stream carries decode back
to them), the ICDs' boundaries, and the true position the stream was made at.
"""

from __future__ import annotations

import dataclasses
import functools
import math

import numpy as np
import pytest

from drivers.source import StreamDecoder
from service.core.ephemeris import EphemerisStore
from service.core.types import Ephemeris, MeasurementEpoch, NavSubframe
from service.engine.pipeline import Pipeline
from service.sim.scenario import default_start_gpst
from service.sim.simulator import SimConfig, Simulator
from tests.support.nav import HKSC_2021_NAV, hksc_2021_ephemerides

C_M_S = 299_792_458.0


def _config(systems: str, duration_s: float = 40.0) -> SimConfig:
    week, tow = default_start_gpst([e for e in hksc_2021_ephemerides() if e.prn[0] == "C"])
    return SimConfig(
        lat_deg=22.3,
        lon_deg=114.2,
        alt_m=20.0,
        start_gpst_week=week,
        start_gpst_tow_s=tow,
        duration_s=duration_s,
        rate_hz=10.0,
        systems=systems,
    )


@functools.cache
def _run(systems: str) -> tuple[Simulator, list, list, Pipeline, dict]:
    sim = Simulator(hksc_2021_ephemerides(), _config(systems))
    dec = StreamDecoder(mapper_options={"ubx": {"systems": frozenset(systems)}})
    pipe = Pipeline(store=EphemerisStore())
    sim_epochs, results = [], []
    for ep, data in sim.ubx_epochs():
        sim_epochs.append(ep)
        for ev in dec.feed(data):
            if isinstance(ev, NavSubframe):
                pipe.on_subframe(ev)
            elif isinstance(ev, MeasurementEpoch):
                results.append(pipe.on_epoch(ev))
    return sim, sim_epochs, results, pipe, dict(dec.counters)


def test_beidou_stream_is_the_same_bytes_whatever_else_is_simulated():
    """A BeiDou-only run (the default systems) gives the bytes it gave before GPS and Galileo
    joined: other systems draw from their own random streams."""
    cfg = _config("C", duration_s=5.0)
    alone = Simulator([e for e in hksc_2021_ephemerides() if e.prn[0] == "C"], cfg)
    given_all = Simulator(hksc_2021_ephemerides(), cfg)  # systems "C": the others are left out
    assert alone.prns == given_all.prns and all(p[0] == "C" for p in alone.prns)
    a = b"".join(d for _, d in alone.ubx_epochs())
    b = b"".join(d for _, d in given_all.ubx_epochs())
    assert a == b
    with_others = Simulator(hksc_2021_ephemerides(), _config("CGE", duration_s=5.0))
    bds_pr = [
        ep.pr_m[[i for i, p in enumerate(ep.prn) if p[0] == "C"]]
        for ep, _ in with_others.ubx_epochs()
    ]
    again = Simulator(
        [e for e in hksc_2021_ephemerides() if e.prn[0] == "C"], cfg
    )  # (a run uses its draws)
    assert all(
        np.array_equal(x.pr_m, y) for (x, _), y in zip(again.ubx_epochs(), bds_pr, strict=True)
    )


def test_each_system_becomes_full_on_its_own_message_timing():
    """GPS: 1.2 s after the first LNAV subframe start (a multiple of 6 s of GPST) after bit
    sync; Galileo: at the end of the first E1-B page carrying a TOW that starts after page
    sync (pages start on odd GST seconds; TOW pages at 5, 17, 19, 25, 27 s modulo 30); both
    one flight time later (checked to 5 ms: a wrong boundary is seconds off)."""
    sim, sim_epochs, _, _, _ = _run("CGE")
    start = sim.cfg.start_gpst_tow_s
    first: dict[str, tuple[float, float]] = {}
    for ep in sim_epochs:
        for i, prn in enumerate(ep.prn):
            if ep.full[i] and prn not in first:
                first[prn] = (ep.t_s, float(ep.pr_m[i]))
    gps = [p for p in sim.prns if p[0] == "G"]
    gal = [p for p in sim.prns if p[0] == "E"]
    assert len(gps) >= 8 and len(gal) >= 5
    for prn in gps + gal:
        st = sim._sats[prn]
        # transmit time it is known: the pseudorange less the receiver clock offset is the
        # flight time to within the satellite clock (< 2 ms)
        known_gpst = start + st.full_s - first[prn][1] / C_M_S + sim.cfg.clock_offset_s
        assert first[prn][0] - 0.1 < st.full_s <= first[prn][0] + 1e-9
        if prn[0] == "G":
            assert math.isclose((known_gpst - 1.2) % 6.0, 0.0, abs_tol=5e-3) or math.isclose(
                (known_gpst - 1.2) % 6.0, 6.0, abs_tol=5e-3
            )
        else:
            page_start = (known_gpst - 2.0) % 30.0
            assert min(abs(page_start - s) for s in (5, 17, 19, 25, 27)) < 5e-3, page_start


def test_the_stream_carries_lnav_subframes_and_inav_pages_that_decode_to_the_nav_sets():
    """Cold start (no held ephemerides): the GPS and Galileo sets come from the stream's own
    SFRBX (LNAV subframes 1-3, I/NAV words 1-5), equal to the nav file's sets (GPS URA: the
    index's bound, 2.4 m, where the file writes 2.0 m); then SPP with a clock per system."""
    sim, _, results, pipe, counters = _run("CGE")
    assert counters["sfrbx_gps"] > 40 and counters["sfrbx_gal"] > 100
    assert counters.get("sfrbx_unmapped", 0) == 0
    held = {e.prn: e for e in pipe.store.all()}
    in_view = {e.prn: e for e in sim.ephemerides}
    decoded = [p for p in held if p[0] in "GE"]
    assert len([p for p in decoded if p[0] == "G"]) >= 8
    assert len([p for p in decoded if p[0] == "E"]) >= 5
    for prn in decoded:
        got, want = held[prn], in_view[prn]
        for f in dataclasses.fields(Ephemeris):
            if f.name in ("prn", "source") or (f.name == "ura_m" and prn[0] == "G"):
                continue
            a, b = getattr(got, f.name), getattr(want, f.name)
            assert math.isclose(a, b, rel_tol=1e-9, abs_tol=1e-15), (prn, f.name, a, b)
    fixes = [r.fix for r in results if r.fix.ok and set(r.fix.clocks_m) == {"C", "G", "E"}]
    assert len(fixes) >= 50  # measured 60: the Galileo sets complete after ~34 s (words 1-5)
    err = [np.linalg.norm(np.subtract(f.x_ecef_m, sim.x_ecef_m)) for f in fixes]
    assert max(err) < 10.0, max(err)


def test_simulate_with_gps_and_galileo_then_replay(tmp_path, capsys):
    """``bdsfix simulate --nav NAV --systems C,G,E`` writes a stream whose GPS and Galileo
    sets reach ``replay --systems C,G,E`` only through its SFRBX (the RTCM prefix carries
    BeiDou's 1042): every epoch fixes, fast fixes included, with every recovered integer
    confirmed when its satellite's time arrives (integrity failures 0)."""
    from service.commands.cli import main

    ubx = tmp_path / "mixed.ubx"
    out = tmp_path / "fixes.jsonl"
    argv = ["simulate", "--nav", str(HKSC_2021_NAV), "--systems", "C,G,E", "--lat-deg", "22.3"]
    argv += ["--lon-deg", "114.2", "--duration-s", "40", "--max-speed", "--out", str(ubx)]
    assert main(argv) == 0
    capsys.readouterr()
    replay = ["replay", "--max-speed", "--systems", "C,G,E", "--jsonl-out", str(out), str(ubx)]
    assert main(replay) == 0
    import json

    recs = [json.loads(line) for line in out.read_text().splitlines()]
    fixes = [r for r in recs if r["class"] == "FIX"]
    assert sum(r["mode"] == "fast" for r in fixes) > 0
    assert len(fixes) == 400 and all(r["mode"] in ("fast", "spp") for r in fixes)
    assert any(set(r.get("used_by_system", {})) == {"C", "G", "E"} for r in fixes)
    tracks = [r for r in recs if r["class"] == "TRACK" and r["event"] == "sow"]
    assert {r["nav_type"] for r in tracks} == {"D1", "D2", "LNAV", "INAV"}
    summary = capsys.readouterr().err
    assert "failures 0" in summary and "integrity checks 0," not in summary, summary


@pytest.mark.slow
def test_ttff_study_includes_gps_and_galileo():
    """``ttff --simulate NAV --systems C,G,E`` (4 restarts of 20 s): the fast fix equals SPP
    of the rows the daemon had to < 1 mm as with BeiDou alone; the conventional fix comes
    earlier with GPS and Galileo (measured median 5.35 s against 6.10 s)."""
    import json
    import subprocess
    import sys

    docs = {}
    for systems in ("C", "C,G,E"):
        cmd = [
            sys.executable,
            "-m",
            "service.commands.cli",
            "ttff",
            "--simulate",
            str(HKSC_2021_NAV),
        ]
        cmd += ["--systems", systems, "--trials", "4", "--trial-s", "20", "--json"]
        cmd += ["--lat-deg", "22.3", "--lon-deg", "114.2"]
        run = subprocess.run(cmd, capture_output=True, text=True, check=True, timeout=900)
        docs[systems] = json.loads(run.stdout)
    for doc in docs.values():
        assert doc["fast"]["success_pct"] == 100.0
        assert doc["fast"]["max_diff_to_spp_m"] < 1e-3
    assert docs["C,G,E"]["conventional"]["median_s"] < docs["C"]["conventional"]["median_s"]


def test_builtin_scenario_flies_a_nav_files_gps_and_galileo_satellites(tmp_path, capsys):
    """``bdsfix replay --nav NAV --systems C,G,E`` with no capture: the built-in virtual
    receiver flies the nav file's satellites instead of Table 1, GPS and Galileo included on
    their own message timing; every epoch fixes, the later ones with the three systems, and
    every integer a fast fix recovered is confirmed. Without ``--nav`` it is Table 1 as
    before (BeiDou only: the README's figures, tests/system/test_readme_walkthrough.py)."""
    from service.commands.cli import main

    out = tmp_path / "fixes.jsonl"
    argv = ["replay", "--max-speed", "--nav", str(HKSC_2021_NAV), "--systems", "C,G,E"]
    assert main([*argv, "--jsonl-out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "warm start with the nav file's ephemerides" in err
    assert "failures 0" in err and "integrity checks 0," not in err, err
    import json

    fixes = [
        r
        for r in (json.loads(line) for line in out.read_text().splitlines())
        if r["class"] == "FIX"
    ]
    assert len(fixes) == 600 and all(r["mode"] in ("fast", "spp") for r in fixes)
    assert set(fixes[-1]["used_by_system"]) == {"C", "G", "E"}
