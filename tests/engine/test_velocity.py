"""The Doppler velocity solution (service.engine.velocity) on rows built here.

Satellites are placed at given elevations and azimuths 21 500 km from a receiver at HKSC,
with velocities drawn at random; the range rates are written from the observation
equation of the module docstring (rdot = e . (v_s - v) + d - c dts/dt) with the test's own
east-north-up frame, so the solution must give back v and d; a row made faulty must be
excluded; without redundancy there is no test; fewer than four rows give no solution.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from service.core.constants import C_M_S
from service.engine.velocity import DopplerRows, solve_velocity
from tests.support.fixes import HKSC_ECEF_M, geodetic_deg_m
from tests.support.independent import enu_rows

SKY_DEG = [(80, 10), (45, 70), (40, 160), (35, 250), (30, 320), (20, 110), (60, 200), (15, 20)]


def _rows(v_enu, drift_m_s, n=8, seed=1, fault_m_s=0.0):
    rng = np.random.default_rng(seed)
    lat, lon, _ = geodetic_deg_m(*HKSC_ECEF_M)
    rot = enu_rows(lat, lon)
    x = np.array(HKSC_ECEF_M)
    prn, sat, e_list = [], [], []
    for k, (el, az) in enumerate(SKY_DEG[:n]):
        el_r, az_r = math.radians(el), math.radians(az)
        e_enu = np.array(
            [math.cos(el_r) * math.sin(az_r), math.cos(el_r) * math.cos(az_r), math.sin(el_r)]
        )
        e = rot.T @ e_enu
        sat.append(x + 21_500e3 * e)
        e_list.append(e)
        prn.append(f"C{k + 19:02d}")
    sat_v = rng.normal(0.0, 2000.0, (n, 3))
    dts = rng.normal(0.0, 1e-11, n)
    v = rot.T @ np.asarray(v_enu, dtype=float)
    rate = np.array([e @ (sv - v) for e, sv in zip(e_list, sat_v, strict=True)])
    rate = rate + drift_m_s - C_M_S * dts
    rate[0] += fault_m_s
    return DopplerRows(
        prn=tuple(prn),
        range_rate_m_s=rate,
        cn0_dbhz=np.full(n, 45.0),
        sat_ecef_m=np.array(sat),
        sat_vel_ecef_m_s=sat_v,
        sat_clock_drift_s_s=dts,
    )


def test_gives_back_the_velocity_and_drift():
    v_enu = (12.0, -5.0, 0.3)
    vel = solve_velocity(_rows(v_enu, -321.5), np.array(HKSC_ECEF_M))
    assert vel is not None
    assert np.allclose(vel.v_enu_m_s, v_enu, atol=1e-6)
    assert vel.clock_drift_m_s == pytest.approx(-321.5, abs=1e-6)
    assert vel.speed_m_s == pytest.approx(13.0, abs=1e-6)
    assert vel.course_deg == pytest.approx(math.degrees(math.atan2(12.0, -5.0)) % 360, abs=1e-6)
    assert vel.redundancy == len(SKY_DEG) - 4 and vel.chi2 is not None and vel.chi2 < 1e-6
    assert vel.excluded == () and all(s > 0 for s in vel.std_v_enu_m_s)


def test_a_faulty_doppler_is_excluded():
    vel = solve_velocity(_rows((3.0, 4.0, 0.0), 10.0, fault_m_s=5.0), np.array(HKSC_ECEF_M))
    assert vel is not None and vel.excluded == ("C19",)
    assert np.allclose(vel.v_enu_m_s, (3.0, 4.0, 0.0), atol=1e-6)


def test_four_rows_have_no_test_and_three_no_solution():
    four = solve_velocity(_rows((1.0, 0.0, 0.0), 0.0, n=4), np.array(HKSC_ECEF_M))
    assert four is not None and four.redundancy == 0 and four.chi2 is None
    assert np.allclose(four.v_enu_m_s, (1.0, 0.0, 0.0), atol=1e-6)
    assert solve_velocity(_rows((1.0, 0.0, 0.0), 0.0, n=3), np.array(HKSC_ECEF_M)) is None


@pytest.mark.parametrize("systems", ["C", "CG"])
def test_a_chunk_gives_what_each_epoch_gives_alone(systems):
    """bdsfix solve's path (with_velocities over the TST urban drive's SPP fixes, with
    exclusions and failed tests among them) == the stream's path (with_velocity one
    epoch at a time), to 1e-9 m/s. With GPS the chunk mixes epochs with and without GPS
    rows: each keeps its own clock drifts (one layout over all had left 13 epochs without
    the velocity they have alone)."""
    from drivers.rinex import RinexObsReader
    from service.commands.solve import load_navigation
    from service.engine.solver import solve_many
    from service.engine.velocity import with_velocities, with_velocity
    from tests.support.paths import DATA

    tst = DATA / "hk-tst-urban-2019"
    navs = [str(tst / "hksc1180.19b"), *([str(tst / "hksc1180.19n")] if "G" in systems else [])]
    store, iono = load_navigation(navs, systems=systems)
    epochs = list(RinexObsReader(str(tst / "COM3_190428_124409.obs"), systems=systems))
    fixes = solve_many(epochs, store, iono, None, "spp")
    layouts = {len({p[0] for p in f.used}) for f in fixes if f.ok}
    assert layouts == ({1} if systems == "C" else {1, 2})  # GPS rows in some epochs only
    together = with_velocities(list(zip(fixes, epochs, strict=True)), store)
    alone = [with_velocity(f, ep, store) for f, ep in zip(fixes, epochs, strict=True)]
    n_vel = n_excl = 0
    for a, b in zip(together, alone, strict=True):
        assert (a.velocity is None) == (b.velocity is None)
        if a.velocity is None:
            continue
        n_vel += 1
        n_excl += bool(a.velocity.excluded)
        assert a.velocity.excluded == b.velocity.excluded and a.velocity.used == b.velocity.used
        assert np.allclose(a.velocity.v_enu_m_s, b.velocity.v_enu_m_s, atol=1e-9, rtol=0)
        assert a.velocity.clock_drift_m_s == pytest.approx(b.velocity.clock_drift_m_s, abs=1e-9)
        assert np.allclose(a.velocity.std_v_enu_m_s, b.velocity.std_v_enu_m_s, atol=1e-12)
    assert n_vel >= 1000 and n_excl >= 10
    assert sum(f.ok for f in fixes) > n_vel  # some fixes have no trusted velocity


def test_a_failed_test_at_redundancy_one_gives_no_velocity_whatever_the_rounding():
    """Urban TST drive, three SPP fixes of five satellites whose Doppler test fails at
    redundancy 1: every row's w-test then has the same size, so no row can be told apart
    (fault exclusion needs redundancy >= 2 before it). No velocity is reported, and moving
    the fix by 1e-7 m or 1e-5 m does not change that (before, the row excluded, and a speed
    of 1.4 to 56.5 m/s published untested, followed the rounding)."""
    from dataclasses import replace

    from drivers.rinex import RinexObsReader
    from service.commands.solve import load_navigation
    from service.engine.solver import solve
    from service.engine.velocity import with_velocity
    from tests.support.paths import DATA

    d = DATA / "hk-tst-urban-2019"
    store, iono = load_navigation([str(d / "hksc1180.19b")])
    wanted = {46320.003, 46062.003, 47281.0}
    epochs = [
        e for e in RinexObsReader(d / "COM3_190428_124409.obs") if round(e.gpst_tow_s, 3) in wanted
    ]
    assert len(epochs) == 3
    for ep in epochs:
        fix = solve(ep, store, iono, solver="spp")
        assert fix.ok and len(fix.used) == 5
        for dx in (0.0, 1e-7, -1e-7, 1e-5):
            moved = replace(fix, x_ecef_m=tuple(np.add(fix.x_ecef_m, dx)))
            assert with_velocity(moved, ep, store).velocity is None, (ep.gpst_tow_s, dx)
