"""The PolyU F9P capture fixes with GPS from its own RXM-SFRBX LNAV subframes, no nav file.

``bdsfix replay --systems C,G`` on the capture alone: the GPS ephemerides come only from the
decoded subframes 1-3 (service.core.gps_nav), the BeiDou ones from the D1 subframes. The
expected positions are the receiver's own NAV-PVT (read with pyubx2), never bdsfix output.
Measured: 182 fixes (BeiDou alone: the same 182, from 14 s), GPS rows in 166 of them from
30 s on (when the first GPS subframes 1-3 have arrived), error to NAV-PVT p50 4.1 m, max
23.3 m over all fixes.
"""

from __future__ import annotations

import json
import math

import numpy as np
from pyubx2 import UBXReader

from service.commands.cli import main
from service.core.geometry import geodetic_to_ecef
from tests.support.paths import DATA

CAPTURE = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"


def _nav_pvt() -> dict[int, np.ndarray]:
    pvt = {}
    with open(CAPTURE, "rb") as fh:
        for _, msg in UBXReader(fh, quitonerror=0):
            if msg is not None and getattr(msg, "identity", "") == "NAV-PVT":
                llh = (math.radians(msg.lat), math.radians(msg.lon), msg.height / 1000.0)
                pvt[round(msg.iTOW / 1000) % 604800] = geodetic_to_ecef(*llh)
    return pvt


def test_gps_from_own_sfrbx_fixes_near_the_receivers_solution(tmp_path):
    out = tmp_path / "fixes.jsonl"
    rc = main(["replay", "--max-speed", "--systems", "C,G", "--jsonl-out", str(out), str(CAPTURE)])
    assert rc == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    fixes = [r for r in recs if r["class"] == "FIX" and r["mode"] == "spp"]
    with_gps = [r for r in fixes if r.get("used_by_system", {}).get("G", 0) > 0]
    assert len(fixes) == 182
    assert len(with_gps) == 166 and with_gps[0]["since_start_s"] == 30.0
    assert all(r["used_by_system"]["G"] >= 4 for r in with_gps[:1])
    pvt = _nav_pvt()
    err = [np.linalg.norm(np.subtract(r["x_ecef_m"], pvt[round(r["gpst_tow_s"])])) for r in fixes]
    assert float(np.median(err)) < 6.0 and max(err) < 30.0, (np.median(err), max(err))
    sow = [r for r in recs if r["class"] == "TRACK" and r["event"] == "sow"]
    gps = [r for r in sow if r["prn"].startswith("G")]
    assert gps and all(r["nav_type"] == "LNAV" and r["sow_s"] % 6 == 0 for r in gps)


def test_perth_phone_fixes_at_its_first_full_gps_ranges(tmp_path):
    """The Android Perth start-up log with its same-day nav file: BeiDou alone fixes first at
    26.18 s; with GPS the first fix from full ranges comes at 12.0 s, when the phone's first
    four GPS ranges have their TOW decoded (the log's own state bits), from GPS rows alone,
    and before it, from the first epoch, coarse-time fixes from the fractional GPS (and
    BeiDou) ranges (service.engine.coarse, the phone's time uncertainty as the prior). Their
    positions are checked against the BeiDou-only fixes' median (the log has no truth):
    11.5 m at 12.0 s, the coarse-time fixes within 40 m."""
    d = DATA / "android-perth-s8-2017"
    nav = d / "PERT00AUS_R_20172780000_01D_MN.rnx"
    first = {}
    fixes = {}
    for systems in ("C", "C,G"):
        out = tmp_path / f"perth-{systems}.jsonl"
        argv = ["replay", "--max-speed", "--systems", systems, "--nav", str(nav)]
        rc = main([*argv, "--jsonl-out", str(out), str(d / "SensorLog20171005.txt")])
        assert rc == 0
        recs = [json.loads(line) for line in out.read_text().splitlines()]
        fixes[systems] = [r for r in recs if r["class"] == "FIX" and r["mode"] != "none"]
        first[systems] = next(r for r in fixes[systems] if r.get("method") != "coarse_time")
    assert round(first["C"]["since_start_s"], 2) == 26.18
    assert fixes["C"][0] is first["C"]  # BeiDou alone: too few rows for a coarse-time fix
    assert first["C,G"]["since_start_s"] == 12.0
    assert first["C,G"]["n_full"] >= 4
    median = np.median([r["x_ecef_m"] for r in fixes["C"]], axis=0)
    assert np.linalg.norm(np.subtract(first["C,G"]["x_ecef_m"], median)) < 20.0
    coarse = [r for r in fixes["C,G"] if r["since_start_s"] < 12.0]
    assert len(coarse) == 12 and coarse[0]["since_start_s"] == 0.0
    assert all(r["method"] == "coarse_time" and r["n_full"] == 0 for r in coarse)
    assert all(np.linalg.norm(np.subtract(r["x_ecef_m"], median)) < 40.0 for r in coarse)


def test_galileo_from_own_inav_pages_fixes_near_the_receivers_solution(tmp_path):
    """``--systems C,G,E`` on the capture alone: Galileo ephemerides from its own E1-B and
    E5b-I I/NAV pages (service.core.gal_nav, fields by pygnssutils' RawNav). Measured: the
    same 182 fixes, every one with Galileo rows (from 14 s), error to NAV-PVT p50 2.6 m,
    max 21.9 m (C,G: 4.1 m, 23.3 m); Galileo TRACK ``sow`` events are INAV pages whose TOW
    is a page start (even GST second on E5b-I, odd on E1-B)."""
    out = tmp_path / "fixes.jsonl"
    argv = ["replay", "--max-speed", "--systems", "C,G,E", "--jsonl-out", str(out), str(CAPTURE)]
    assert main(argv) == 0
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    fixes = [r for r in recs if r["class"] == "FIX" and r["mode"] == "spp"]
    assert len(fixes) == 182
    assert all(r.get("used_by_system", {}).get("E", 0) >= 2 for r in fixes)
    pvt = _nav_pvt()
    err = [np.linalg.norm(np.subtract(r["x_ecef_m"], pvt[round(r["gpst_tow_s"])])) for r in fixes]
    assert float(np.median(err)) < 3.5 and max(err) < 25.0, (np.median(err), max(err))
    sow = [r for r in recs if r["class"] == "TRACK" and r["event"] == "sow"]
    gal = [r for r in sow if r["prn"].startswith("E")]
    assert len(gal) > 400 and all(r["nav_type"] == "INAV" for r in gal)
    assert all(r["gpst_tow_s"] == r["sow_s"] + 2.0 for r in gal)
