"""`bdsfix coverage` reproduces the paper's Table 3 on its Table 1 constellation."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.cli import main
from service.coverage import CoverageConfig, run_coverage, trace_inverse_sym4
from service.geometry import ecef_to_geodetic, geodetic_to_ecef
from service.keplerian import table1_ephemerides
from service.orbit import EphemerisArrays, sat_pos_clock


@pytest.fixture(scope="module")
def table3(tmp_path_factory):
    out = tmp_path_factory.mktemp("cov") / "cov.json"
    png = out.with_suffix(".png")
    assert main(["coverage", "--json", str(out), "--plot", str(png), "--no-progress"]) == 0
    return json.loads(out.read_text()), png


def test_table3_surface(table3):
    s = table3[0]["altitudes"]["0"]
    assert s["max_pct"] == 100.0
    assert abs(s["min_pct"] - 76.7) <= 0.5
    assert abs(s["all_pct"] - 99.4) <= 0.2


def test_table3_1000km(table3):
    s = table3[0]["altitudes"]["1000000"]
    assert s["max_pct"] == 100.0
    assert abs(s["min_pct"] - 75.9) <= 0.5
    assert abs(s["all_pct"] - 99.4) <= 0.2


def test_surface_area_and_contract(table3):
    doc, png = table3
    a = doc["altitudes"]["0"]["area"]
    assert abs(a["lon_min_deg"] - 59) <= 1 and abs(a["lon_max_deg"] - 161) <= 1
    assert abs(a["lat_min_deg"] + 78) <= 1 and abs(a["lat_max_deg"] - 79) <= 1
    assert doc["epochs"] == 8 * 86400 // 300 and doc["points"] == 181 * 360
    assert set(doc["all"]) == {"max_pct", "min_pct", "all_pct"}
    assert png.stat().st_size > 20_000


def test_table1_geos_at_the_paper_longitudes():
    ephs = [e for e in table1_ephemerides(0.0) if e.prn in ("C01", "C02", "C03", "C04", "C05")]
    arr = EphemerisArrays.from_ephemerides(ephs)
    pos, _ = sat_pos_clock(arr, ephs[0].week, np.full(5, ephs[0].toe_sow_s))
    _, lon, _ = ecef_to_geodetic(pos)
    want = {"C01": 140.0, "C03": 110.5, "C04": 160.0, "C05": 58.75, "C02": 80.0}
    for e, lo in zip(ephs, np.degrees(lon), strict=True):
        assert abs(lo - want[e.prn]) < 0.5


@settings(max_examples=200, deadline=None)
@given(st.lists(st.floats(-1, 1), min_size=20, max_size=20), st.integers(4, 5))
def test_trace_inverse_matches_numpy(vals, n):
    g = np.concatenate([np.array(vals[: 3 * n]).reshape(n, 3), np.ones((n, 1))], axis=1)
    d = g.T @ g
    if np.linalg.cond(d) > 1e10:
        return
    ref = float(np.trace(np.linalg.inv(d)))
    got = float(
        trace_inverse_sym4(
            *(
                d[i, j]
                for i, j in [
                    (0, 0),
                    (0, 1),
                    (0, 2),
                    (0, 3),
                    (1, 1),
                    (1, 2),
                    (1, 3),
                    (2, 2),
                    (2, 3),
                    (3, 3),
                ]
            )
        )
    )
    assert math.isclose(got, ref, rel_tol=1e-6)


def test_vectorised_counts_match_a_per_point_loop():
    """A short coarse study against a plain loop with numpy.linalg.inv per point."""
    cfg = CoverageConfig(days=0.25, step_s=3 * 3600, grid_deg=6.0, altitudes_m=(0.0,))
    (res,), lats, lons = run_coverage(cfg, progress=False, workers=1)
    ephs = [e for e in table1_ephemerides(0.0) if e.prn in ("C01", "C02", "C03", "C04", "C05")]
    arr = EphemerisArrays.from_ephemerides(ephs)
    for k in range(len(res.n_geo4)):
        pos, _ = sat_pos_clock(arr, ephs[0].week, np.full(5, ephs[0].toe_sow_s + k * cfg.step_s))
        n4 = nu = 0
        for la in lats:
            for lo in lons:
                x = geodetic_to_ecef(math.radians(la), math.radians(lo), 0.0)
                up = np.array(
                    [
                        math.cos(math.radians(la)) * math.cos(math.radians(lo)),
                        math.cos(math.radians(la)) * math.sin(math.radians(lo)),
                        math.sin(math.radians(la)),
                    ]
                )
                los = pos - x
                los /= np.linalg.norm(los, axis=1)[:, None]
                vis = los @ up >= 0
                if vis.sum() < 4:
                    continue
                n4 += 1
                g = np.concatenate([-los[vis], np.ones((int(vis.sum()), 1))], axis=1)
                nu += math.sqrt(np.trace(np.linalg.inv(g.T @ g))) < 3000
        assert (res.n_geo4[k], res.n_usable[k]) == (n4, nu)


def test_broadcast_constellation_from_a_nav_file(tmp_path):
    out = tmp_path / "nav.json"
    nav = str(__import__("tests._independent", fromlist=["DATA"]).DATA / "hksc-2021/hksc1610.nav")
    rc = main(
        [
            "coverage",
            "--nav",
            nav,
            "--epoch",
            "2021-06-10T03:36:00",
            "--days",
            "0.1",
            "--step-s",
            "1800",
            "--grid-deg",
            "5",
            "--json",
            str(out),
            "--no-progress",
        ]
    )
    assert rc == 0
    doc = json.loads(out.read_text())
    s = doc["altitudes"]["0"]
    assert s["min_pct"] > 90.0  # the 2021 GEOs have GDOP far below 3000 (HKSC: 90-100)
    assert 50 <= s["area"]["lon_min_deg"] <= 70 and 155 <= s["area"]["lon_max_deg"] <= 175
