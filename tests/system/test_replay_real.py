"""Replays against independent truths: u-blox's own NAV-PVT, the HKSC survey, and the
restart emulation's timeline on HKSC."""

from __future__ import annotations

import json

import numpy as np
import pytest
import pyubx2

from service.commands.cli import main
from service.core.geometry import geodetic_to_ecef
from tests.support.independent import HKSC_TRUTH_ECEF_M
from tests.support.paths import DATA


def _replay(tmp_path, *args):
    out = tmp_path / "out.jsonl"
    assert main(["replay", *map(str, args), "--max-speed", "--jsonl-out", str(out)]) == 0
    return [json.loads(x) for x in out.read_text().splitlines()]


def test_polyu_bds_only_spp_agrees_with_the_receiver_nav_pvt(tmp_path):
    d = DATA / "hk-polyu-f9p-ubx-2024"
    ubx = d / "COM18___9600_240925_072456.ubx"
    fixes = [r for r in _replay(tmp_path, ubx, "--nav", d / "hksc269h.24f") if r["class"] == "FIX"]
    pvt = {}
    with ubx.open("rb") as fh:
        for _raw, msg in pyubx2.UBXReader(fh, protfilter=2, quitonerror=0):
            if msg is not None and msg.identity == "NAV-PVT" and msg.fixType == 3:
                pvt[round(msg.iTOW / 1000.0) % 604800] = geodetic_to_ecef(
                    np.radians(msg.lat), np.radians(msg.lon), msg.height / 1000.0
                )
    errs = []
    for f in fixes:
        assert f["mode"] == "spp" and f["n_frac"] == 0  # the F9P tracks no GEO
        key = round(f["gpst_tow_s"] - f["clock_bias_m"] / 299792458.0)
        if key in pvt:
            errs.append(np.linalg.norm(np.subtract(f["x_ecef_m"], pvt[key])))
    assert len(errs) >= 150
    assert np.median(errs) < 15.0, np.median(errs)


def test_hksc_replay_fixes_fast_and_near_the_survey(tmp_path):
    d = DATA / "hksc-2021"
    recs = _replay(tmp_path, d / "hksc1610.obs", "--nav", d / "hksc1610.nav")
    fixes = [r for r in recs if r["class"] == "FIX"]
    assert len(fixes) == 205 and all(f["mode"] == "spp" for f in fixes)
    err = [np.linalg.norm(np.subtract(f["x_ecef_m"], HKSC_TRUTH_ECEF_M)) for f in fixes]
    assert np.sqrt(np.mean(np.square(err))) < 2.1


def test_hksc_restart_first_fast_fix_after_geos_then_spp_after_d1(tmp_path):
    """--restart-at: fractional until each SOW (the SOW-decode rule: 0.12 s into the first D2
    subframe after bit sync, 1.2 s into the first D1 subframe); the first fast fix of the
    paper's method comes at the first epoch with four GEOs full, and only SPP fixes once the
    D1 SOWs have arrived. Before four GEOs are full the coarse-time fix
    (service/engine/coarse.py) fixes the restart epoch itself."""
    d = DATA / "hksc-2021"
    recs = _replay(tmp_path, d / "hksc1610.obs", "--nav", d / "hksc1610.nav", "--restart-at", "60")
    fixes = [r for r in recs if r["class"] == "FIX"]
    t_restart = fixes[0]["gpst_tow_s"] + 60
    track = [
        r
        for r in recs
        if r["class"] == "TRACK" and r["event"] == "full" and r["gpst_tow_s"] >= t_restart
    ]
    after = [f for f in fixes if f["gpst_tow_s"] >= t_restart]
    assert after[0]["since_start_s"] == 0.0 and after[0]["mode"] == "fast"
    assert after[0]["method"] == "coarse_time" and abs(after[0]["time_offset_s"]) < 0.01
    geo_full = sorted(t["since_start_s"] for t in track if t["nav_type"] == "D2")
    d1_full = sorted(t["since_start_s"] for t in track if t["nav_type"] == "D1")
    assert len(geo_full) == 5 and geo_full[3] <= 2.0
    first_fast = next(f for f in after if f["mode"] == "fast" and "method" not in f)
    assert first_fast["since_start_s"] == geo_full[3]  # the epoch the 4th GEO went full
    assert all(f["mode"] != "spp" for f in after if f["since_start_s"] < d1_full[-1])
    assert all(f["mode"] == "spp" for f in after if f["since_start_s"] >= d1_full[-1])
    ttff = first_fast["since_start_s"]
    conventional = next(f for f in after if f["mode"] == "spp")["since_start_s"]
    # a D1 SOW needs 1.2 s after a preamble that came after bit sync (>= 0.1 s)
    assert ttff < 3.0 and conventional >= 1.3 and conventional > ttff
    print(f"HKSC restart: first fast fix {ttff:.0f} s, first SPP {conventional:.0f} s")


def test_restart_timeline_agrees_with_the_jsonl(tmp_path, capsys):
    """The timeline printed after ``--restart-at 30`` counts from the restart: each first
    event is the first of its kind in the JSONL at or after the restart (the fixes and SOW
    decodes of the receiver before it do not count)."""
    d = DATA / "hksc-2021"
    recs = _replay(tmp_path, d / "hksc1610.obs", "--nav", d / "hksc1610.nav", "--restart-at", "30")
    timeline = {}
    for line in capsys.readouterr().err.splitlines():
        if line.startswith("  first ") and "t =" in line:
            key, _, value = line.strip().partition(" t = ")
            timeline[key.strip()] = float(value.removesuffix(" s"))
    t_restart = next(r for r in recs if r["class"] == "FIX")["gpst_tow_s"] + 30
    after = [r for r in recs if r.get("gpst_tow_s", -1.0) >= t_restart]
    fixes = [r for r in after if r["class"] == "FIX"]
    track = [r for r in after if r["class"] == "TRACK" and r["event"] == "full"]
    want = {
        "first fast fix": next(f for f in fixes if f["mode"] == "fast")["since_start_s"],
        # (the coarse-time fix of the restart epoch: 0 s)
        "first conventional fix": next(f for f in fixes if f["mode"] == "spp")["since_start_s"],
        "first GEO SOW decoded": min(t["since_start_s"] for t in track if t["nav_type"] == "D2"),
        "first non-GEO SOW decoded": min(
            t["since_start_s"] for t in track if t["nav_type"] == "D1"
        ),
        # the epoch where the fourth satellite became full (HKSC keeps its satellites)
        "first 4 full ranges": sorted(
            {t["prn"]: t["since_start_s"] for t in reversed(track)}.values()
        )[3],
    }
    assert timeline == pytest.approx(want, abs=0.005)
    assert want["first conventional fix"] > 0.0  # SPP waits for the D1 SOWs after a restart
