"""`bdsfix coverage` reproduces the paper's Table 3 on its Table 1 constellation.

Independent checks: the GEO slots the paper names, GMST against the IAU 2006 Earth-rotation
formula, two-body invariants, the ICD broadcast-form propagation, and the study's counts and
GDOP values against a plain per-point loop with ENU elevations and numpy.linalg.inv.
"""

from __future__ import annotations

import datetime as dt
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from service.commands.cli import main
from service.core.geometry import ecef_to_geodetic, geodetic_to_ecef, look_angles
from service.core.timebase import gmst_rad
from service.sim.constellation import positions_ecef, positions_eci, table1
from service.studies.coverage import (
    CoverageConfig,
    geo_gdop,
    nav_geo_positions,
    run_coverage,
    trace_inverse_normal,
)
from tests.support.paths import DATA

GM_M3_S2 = 3.986004418e14  # CGCS2000, BDS-SIS-ICD-B1I-3.0 3.2 (written here, not imported)

# The slots the paper gives for G1, G3, G4, G5, G6 (Table 1 order: C01, C03, C04, C05, C02)
PAPER_GEO_LON_DEG = {"C01": 140.0, "C03": 110.5, "C04": 160.0, "C05": 58.75, "C02": 80.0}


# --------------------------------------------------------------------------- Table 3


@pytest.fixture(scope="module")
def table3(tmp_path_factory):
    """The default study (8 days, 300 s, 1 deg, 0 and 1000 km), through the CLI."""
    out = tmp_path_factory.mktemp("cov") / "cov.json"
    png = out.with_suffix(".png")
    assert main(["coverage", "--json", str(out), "--plot", str(png), "--no-progress"]) == 0
    return json.loads(out.read_text()), png


@pytest.mark.slow
def test_table3_surface(table3):
    s = table3[0]["altitudes"]["0"]
    assert s["max_pct"] == 100.0
    assert abs(s["min_pct"] - 76.7) <= 0.5
    assert abs(s["all_pct"] - 99.4) <= 0.2


@pytest.mark.slow
def test_table3_1000km(table3):
    s = table3[0]["altitudes"]["1000000"]
    assert s["max_pct"] == 100.0
    assert abs(s["min_pct"] - 75.9) <= 0.5
    assert abs(s["all_pct"] - 99.4) <= 0.2


@pytest.mark.slow
def test_table3_all_area(table3):
    s = table3[0]["all"]
    assert s["max_pct"] == 100.0
    assert abs(s["min_pct"] - 76.3) <= 0.5
    assert abs(s["all_pct"] - 99.4) <= 0.2


@pytest.mark.slow
def test_geo4_area_extents_as_in_the_paper(table3):
    doc = table3[0]
    paper = {"0": (59, 161, -78, 79), "1000000": (60, 159, -76, 77)}
    for key, (lon0, lon1, lat0, lat1) in paper.items():
        a = doc["altitudes"][key]["area"]
        assert abs(a["lon_min_deg"] - lon0) <= 1 and abs(a["lon_max_deg"] - lon1) <= 1, key
        assert abs(a["lat_min_deg"] - lat0) <= 1 and abs(a["lat_max_deg"] - lat1) <= 1, key
    assert doc["epochs"] == 8 * 86400 // 300
    assert doc["points"] == 181 * 360


@pytest.mark.slow
def test_plot_shows_the_areas(table3):
    import matplotlib.image as mpimg

    png = table3[1]
    img = mpimg.imread(png)[..., :3]
    assert img.shape[0] > 400 and img.shape[1] > 800
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    fill = (r > 0.95) & (g > 0.7) & (g < 0.85) & (b > 0.5) & (b < 0.7)  # light orange
    red = (r > 0.75) & (g < 0.3) & (b < 0.3)
    blue = (b > 0.6) & (r < 0.3) & (g > 0.35) & (g < 0.6)
    assert fill.mean() > 0.1  # the worst-epoch usable area covers a good part of the map
    assert red.sum() > 500 and blue.sum() > 500  # both outlines drawn


# --------------------------------------------------------------------------- constellation


def test_table1_geos_sit_at_the_paper_slots():
    geos = table1().geos()
    lat, lon, h = ecef_to_geodetic(positions_ecef(geos, [0.0])[0])
    for prn, la, lo, alt in zip(geos.prns, np.degrees(lat), np.degrees(lon), h, strict=True):
        assert abs(lo - PAPER_GEO_LON_DEG[prn]) < 1.0, prn
        assert abs(la) < 2.0, prn  # inclinations below 1.7 deg
        assert abs(alt - 35_786e3) < 10e3, prn


def test_table1_geos_stay_on_station_for_the_study():
    geos = table1().geos()
    t = np.arange(0.0, 8 * 86400.0 + 1, 3600.0)
    _, lon, _ = ecef_to_geodetic(positions_ecef(geos, t))
    drift = np.degrees(np.abs(lon - lon[:1])).max(axis=0)
    assert (drift < 0.6).all()  # a few km of semi-major axis off synchronous: slow drift


def test_gmst_matches_the_earth_rotation_angle_form():
    """IAU 1982 GMST vs the IAU 2006 form ERA + polynomial (Capitaine et al. 2003)."""
    for utc in (
        dt.datetime(2000, 1, 1, 12),
        dt.datetime(2015, 5, 19, 4),
        dt.datetime(2015, 5, 27, 3, 55),
        dt.datetime(2021, 6, 10, 3, 36),
    ):
        du = (utc - dt.datetime(2000, 1, 1, 12)).total_seconds() / 86400.0
        era = 2 * math.pi * ((0.7790572732640 + 1.00273781191135448 * du) % 1.0)
        t = du / 36525.0
        poly_as = 0.014506 + 4612.156534 * t + 1.3915817 * t**2 - 0.00000044 * t**3
        ref = (era + math.radians(poly_as / 3600.0)) % (2 * math.pi)
        epoch = dt.datetime(2015, 5, 19, 4)
        got = float(gmst_rad(epoch, (utc - epoch).total_seconds()))
        assert abs(math.remainder(got - ref, 2 * math.pi)) < 1e-6, utc  # 0.2 arcsec


def test_two_body_invariants():
    const = table1()
    a = np.array([s.a_m for s in const.sats])
    e = np.array([s.e for s in const.sats])
    period = 2 * math.pi * np.sqrt(a**3 / GM_M3_S2)
    t = np.linspace(0.0, 2 * 86400.0, 97)
    r = np.linalg.norm(positions_eci(const, t), axis=-1)
    assert (r >= a * (1 - e) - 1e-3).all() and (r <= a * (1 + e) + 1e-3).all()
    for i, sat in enumerate(const.sats):
        p0 = positions_eci(const, [0.0])[0, i]
        p1 = positions_eci(const, [period[i]])[0, i]
        assert np.linalg.norm(p1 - p0) < 1e-3, sat.prn
        # the orbit normal from r x v gives back the inclination and node of Table 1
        pa, pb = positions_eci(const, [0.0, 1.0])[:, i]
        h = np.cross(pa, pb - pa)
        h /= np.linalg.norm(h)
        assert abs(math.acos(h[2]) - sat.inc_rad) < 1e-6, sat.prn
        node = math.atan2(h[0], -h[1])
        assert abs(math.remainder(node - sat.raan_eci_rad, 2 * math.pi)) < 1e-4, sat.prn


def test_direct_propagation_matches_the_broadcast_form():
    """service.sim.keplerian's ICD-form ephemerides (GEO frame re-expressed) give the same orbits;
    they rotate the Earth at the CGCS2000 rate, GMST at 7.2921158553e-5 rad/s."""
    import datetime as dt

    from service.core.orbit import EphemerisArrays, sat_pos_clock
    from service.core.timebase import gpst_from_utc, gpst_to_bdt
    from service.sim.keplerian import TABLE1_EPOCH_UTC, table1_ephemerides

    ephs = table1_ephemerides(0.0)  # t_oe a multiple of 8 s at or after the epoch
    week, epoch_sow = gpst_to_bdt(*gpst_from_utc(dt.datetime(*TABLE1_EPOCH_UTC)))
    arr = EphemerisArrays.from_ephemerides(ephs)
    const = table1()
    assert const.prns == tuple(e.prn for e in ephs)
    for dt_s in (0.0, 600.0, 3600.0, 86400.0):
        pos, _ = sat_pos_clock(arr, week, np.full(len(ephs), epoch_sow + dt_s))
        ref = positions_ecef(const, [dt_s])[0]
        rate_gap_m = 8.6e-12 * dt_s * 42.2e6
        assert np.linalg.norm(pos - ref, axis=1).max() < 0.01 + rate_gap_m, dt_s


# --------------------------------------------------------------------------- kernel


def _loop_counts(sats, lats, lons, alt_m, elmask_deg, beta):
    """Per-epoch (>= 4 GEOs, GDOP_full < beta) counts, one point at a time."""
    la, lo = np.meshgrid(np.radians(lats), np.radians(lons), indexing="ij")
    la, lo = la.ravel(), lo.ravel()
    x = geodetic_to_ecef(la, lo, alt_m)
    out = []
    for sat in sats:
        el, _ = look_angles(x, np.broadcast_to(sat, (len(x), *sat.shape)), (la, lo))
        n4 = nu = 0
        for p in range(len(x)):
            vis = el[p] >= math.radians(elmask_deg)
            if vis.sum() < 4:
                continue
            n4 += 1
            los = sat[vis] - x[p]
            los /= np.linalg.norm(los, axis=1)[:, None]
            g = np.column_stack([-los, np.ones(len(los))])
            nu += math.sqrt(np.trace(np.linalg.inv(g.T @ g))) < beta
        out.append((n4, nu))
    return np.array(out)


@pytest.mark.parametrize("elmask_deg", [0.0, 10.0])
def test_study_counts_match_a_per_point_loop(elmask_deg):
    cfg = CoverageConfig(
        days=0.5, step_s=1800.0, grid_deg=5.0, altitudes_m=(0.0, 1e6), elmask_deg=elmask_deg
    )
    sats = positions_ecef(table1().geos(), np.arange(cfg.n_epochs) * cfg.step_s)
    res = run_coverage(cfg, sats, workers=1)
    for r in res.altitudes:
        ref = _loop_counts(sats, res.lats_deg, res.lons_deg, r.altitude_m, elmask_deg, cfg.beta)
        assert (r.n_geo4 == ref[:, 0]).all() and (r.n_usable == ref[:, 1]).all()
        assert r.n_geo4.min() > 0
    if elmask_deg == 0.0:  # the window includes the worst epoch (+3.5 h)
        assert (res.altitudes[0].n_usable < res.altitudes[0].n_geo4).any()


def test_parallel_and_serial_agree():
    cfg = CoverageConfig(days=0.5, step_s=900.0, grid_deg=4.0)
    one = run_coverage(cfg, workers=1)
    two = run_coverage(cfg, workers=2)
    for a, b in zip(one.altitudes, two.altitudes, strict=True):
        assert (a.n_geo4 == b.n_geo4).all() and (a.n_usable == b.n_usable).all()
        assert (a.geo4_any == b.geo4_any).all() and a.worst_epoch == b.worst_epoch


@pytest.mark.parametrize("alt_m", [0.0, 1e6])
def test_gdop_values_match_linalg_at_the_worst_epoch(alt_m):
    """Full 1-deg grid at +3.5 h, where GDOP_full reaches 1e4: relative error < 1e-7."""
    sat = positions_ecef(table1().geos(), [3.5 * 3600.0])[0]
    la, lo = np.meshgrid(
        np.radians(np.arange(-90.0, 91.0)), np.radians(np.arange(-180.0, 180.0)), indexing="ij"
    )
    la, lo = la.ravel(), lo.ravel()
    x = geodetic_to_ecef(la, lo, alt_m)
    up = np.column_stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)])
    n_vis, gd = geo_gdop(sat, x, up)
    el, _ = look_angles(x, np.broadcast_to(sat, (len(x), *sat.shape)), (la, lo))
    vis = el >= 0.0
    assert (n_vis == vis.sum(axis=1)).all()
    idx = np.flatnonzero(vis.sum(axis=1) >= 4)
    los = sat[None] - x[idx, None]
    los /= np.linalg.norm(los, axis=2)[..., None]
    g = np.concatenate([-los, np.ones((len(idx), len(sat), 1))], axis=2) * vis[idx, :, None]
    ref = np.sqrt(np.trace(np.linalg.inv(np.einsum("psi,psj->pij", g, g)), axis1=1, axis2=2))
    assert ref.max() > 3000.0  # the hard, near-singular case is present
    np.testing.assert_allclose(gd[idx], ref, rtol=1e-7)
    assert np.isinf(gd[np.setdiff1d(np.arange(len(x)), idx)]).all()


@settings(max_examples=200, deadline=None)
@given(
    st.lists(st.floats(-1, 1), min_size=18, max_size=18),
    st.integers(4, 6),
    st.floats(0.0, 0.2),
)
def test_trace_inverse_matches_numpy(vals, n, squash):
    """Random unit vectors, squashed towards a plane to make D near-singular."""
    v = np.array(vals[: 3 * n]).reshape(n, 3)
    v[:, 2] *= squash
    norm = np.linalg.norm(v, axis=1)
    if (norm < 1e-3).any():
        return
    e = v / norm[:, None]
    g = np.column_stack([-e, np.ones(n)])
    d = g.T @ g
    if np.linalg.cond(d) > 1e12:
        return
    ref = float(np.trace(np.linalg.inv(d)))
    assert math.isclose(float(trace_inverse_normal(d)), ref, rel_tol=1e-6)


# --------------------------------------------------------------------------- CLI and nav


def test_cli_json_contract(tmp_path, capsys):
    out = tmp_path / "c.json"
    args = ["coverage", "--days", "0.25", "--step-s", "3600", "--grid-deg", "5"]
    rc = main([*args, "--altitudes-m", "0,500000", "--json", str(out), "--no-progress"])
    assert rc == 0
    assert "max %" in capsys.readouterr().out  # the summary table
    doc = json.loads(out.read_text())
    assert set(doc) == {"altitudes", "all", "epochs", "points"}
    assert set(doc["altitudes"]) == {"0", "500000"}
    assert doc["epochs"] == 6 and doc["points"] == 37 * 72
    for v in [*doc["altitudes"].values(), doc["all"]]:
        assert {"max_pct", "min_pct", "all_pct"} <= set(v)
        assert all(isinstance(v[k], float) for k in ("max_pct", "min_pct", "all_pct"))
        assert 0.0 <= v["min_pct"] <= v["all_pct"] <= v["max_pct"] <= 100.0
    for v in doc["altitudes"].values():
        assert set(v["area"]) == {"lon_min_deg", "lon_max_deg", "lat_min_deg", "lat_max_deg"}
    # "-" writes the JSON alone to stdout
    assert main([*args, "--json", "-", "--no-progress"]) == 0
    assert json.loads(capsys.readouterr().out)["epochs"] == 6


def test_cli_rejects_bad_values(capsys):
    assert main(["coverage", "--days", "0", "--no-progress"]) == 2
    assert "--days" in capsys.readouterr().err
    assert main(["coverage", "--days", "0.1", "--start", "yesterday", "--no-progress"]) == 2


NAV_2021 = DATA / "hksc-2021" / "hksc1610.nav"


def test_broadcast_geo_positions_match_georinex_and_the_icd():
    """Nearest-t_oe broadcast GEO positions vs georinex records run through a scalar
    transcription of the ICD algorithm; and they are geostationary (first principles)."""
    from drivers.rinex import read_nav
    from tests.support.independent import georinex_bds_ephemerides, icd_position

    nav = read_nav(NAV_2021)
    c01 = nav.ephemerides["C01"][0]  # sets sorted by (week, toe)
    t_s = np.arange(0.0, 4 * 3600.1, 900.0)
    prns, pos = nav_geo_positions(nav.ephemerides, (c01.week, c01.toe_sow_s), t_s)
    assert prns == ("C01", "C02", "C03", "C04", "C05")
    recs = georinex_bds_ephemerides(NAV_2021)
    for j, prn in enumerate(prns):
        mine = [r for r in recs if r["prn"] == prn and r["SatH1"] == 0]
        for k, t in enumerate(t_s):
            sow = c01.toe_sow_s + t
            rec = min(mine, key=lambda r: abs(r["Toe"] - sow))
            ref = np.array(icd_position(rec, sow, geo=True))
            assert np.linalg.norm(pos[k, j] - ref) < 1e-3, (prn, t)
    lat, lon, _ = ecef_to_geodetic(pos)
    r = np.linalg.norm(pos, axis=-1)
    assert (np.abs(r - 42_164e3) < 50e3).all()
    assert (np.abs(np.degrees(lat)) < 2.0).all()
    assert (np.degrees(np.ptp(lon, axis=0)) < 0.1).all()


def test_cli_nav_study(tmp_path, capsys):
    out = tmp_path / "nav.json"
    base = ["coverage", "--nav", str(NAV_2021), "--step-s", "1800", "--grid-deg", "5"]
    assert main([*base, "--days", "0.15", "--json", str(out), "--no-progress"]) == 0
    s = json.loads(out.read_text())["altitudes"]["0"]
    assert s["max_pct"] == 100.0
    assert 55 <= s["area"]["lon_min_deg"] <= 65 and 155 <= s["area"]["lon_max_deg"] <= 170
    capsys.readouterr()
    # a study longer than the file's four hours of ephemerides is refused, with the reason
    assert main([*base, "--days", "1", "--no-progress"]) == 2
    assert "inside the file's span" in capsys.readouterr().err
