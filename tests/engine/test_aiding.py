"""Height aiding (service.engine.aiding): the kernel's height row and the held height.

The row, on the HKSC station (BeiDou, 2021; its surveyed position the truth): a height
known to a centimetre pins the fix's height and adds one degree of freedom; a height
known to a kilometre leaves the fix as it was; a wrong height at a tight sigma fails the
chi-square test instead of moving the fix; the fast fix with the same row is SPP's
solution. The held height, on fixes made here: the median of the window, its sigma
sqrt(s0^2 + (rate dt)^2 + (grade d)^2) worked by hand, nothing before the minimum
number of fixes, after a gap longer than the window or after a reset.
"""

from __future__ import annotations

import math
from dataclasses import replace
from functools import cache

import numpy as np
import pytest

from drivers.rinex import RinexObsReader
from service.commands.solve import load_navigation
from service.core.geometry import ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from service.core.types import Fix, MeasurementEpoch
from service.engine.aiding import HeightAid, Predictor, predicted_residuals
from service.engine.solver import SolverConfig, fractionalize, solve
from tests.support.independent import HKSC_TRUTH_ECEF_M
from tests.support.paths import DATA

HKSC = DATA / "hksc-2021"
TRUE_H_M = float(ecef_to_geodetic(HKSC_TRUTH_ECEF_M)[2])


@cache
def _hksc() -> tuple[list[MeasurementEpoch], object, object]:
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")], systems={"C"})
    epochs = list(RinexObsReader(HKSC / "hksc1610.obs", systems={"C"}))
    return epochs[::20], store, iono


def _height(fix: Fix) -> float:
    return float(ecef_to_geodetic(np.asarray(fix.x_ecef_m))[2])


def test_a_tight_height_row_pins_the_height_and_adds_a_degree_of_freedom():
    epochs, store, iono = _hksc()
    for ep in epochs:
        plain = solve(ep, store, iono, SolverConfig(), "spp")
        aided = solve(ep, store, iono, SolverConfig(height_aid=(TRUE_H_M, 0.01)), "spp")
        assert plain.ok and aided.ok, (plain.reason, aided.reason)
        assert abs(_height(aided) - TRUE_H_M) < 0.05, _height(aided)
        assert aided.redundancy == plain.redundancy + 1
        assert aided.used == plain.used
        # the DOPs are the satellites' geometry; the covariance and levels take the row
        # (at a position centimetres away)
        assert aided.pdop == pytest.approx(plain.pdop, rel=1e-6)
        assert aided.vdop == pytest.approx(plain.vdop, rel=1e-6)
        assert aided.cov_enu_m2[2][2] < 0.01**2 * 1.01
        # the row's own fault has a slope: a biased height moves the fix 1:1 and the test
        # sees it only through the satellites, so the VPL does not shrink with the sigma
        assert math.isfinite(aided.vpl_m) and math.isfinite(aided.hpl_m)
        # the horizontal error stays metre-level (the station's SPP is ~1 m)
        d = np.subtract(aided.x_ecef_m, HKSC_TRUTH_ECEF_M)
        lat, lon, _ = ecef_to_geodetic(HKSC_TRUTH_ECEF_M)
        enu = enu_rotation(lat, lon) @ d
        assert math.hypot(enu[0], enu[1]) < 3.0


def test_a_loose_height_row_leaves_the_fix_as_it_was():
    epochs, store, iono = _hksc()
    for ep in epochs:
        plain = solve(ep, store, iono, SolverConfig(), "spp")
        loose = solve(ep, store, iono, SolverConfig(height_aid=(TRUE_H_M + 50.0, 1e5)), "spp")
        assert np.linalg.norm(np.subtract(loose.x_ecef_m, plain.x_ecef_m)) < 1e-3
        # the levels differ by the test's one more degree of freedom only
        assert loose.redundancy == plain.redundancy + 1
        assert loose.hpl_m == pytest.approx(plain.hpl_m, rel=0.02)


def test_a_wrong_tight_height_fails_the_test_instead_of_moving_the_fix():
    """100 m off at a 1 m sigma: the satellites contradict it; the test fails and no
    exclusion of a satellite can pass (the row is never excluded), so nothing is
    published 100 m off."""
    epochs, store, iono = _hksc()
    for ep in epochs:
        fix = solve(ep, store, iono, SolverConfig(height_aid=(TRUE_H_M + 100.0, 1.0)), "spp")
        assert not fix.ok and fix.reason_code == "chi2", fix.reason


def test_the_fast_fix_with_the_row_is_spp_with_the_row():
    epochs, store, iono = _hksc()
    cfg = SolverConfig(height_aid=(TRUE_H_M + 2.0, 3.0))
    n = 0
    for ep in epochs:
        fast = solve(fractionalize(ep), store, iono, cfg, "fast")
        spp = solve(ep, store, iono, cfg, "spp")
        assert fast.ok and spp.ok and fast.used == spp.used, (fast.reason, spp.reason)
        assert np.linalg.norm(np.subtract(fast.x_ecef_m, spp.x_ecef_m)) <= 1e-3
        assert fast.redundancy == spp.redundancy and fast.vpl_m == pytest.approx(spp.vpl_m)
        n += 1
    assert n == len(epochs)


# ---- the held height ----------------------------------------------------------------------

LAT, LON = math.radians(22.3), math.radians(114.18)
ROT = enu_rotation(LAT, LON)
CFG = SolverConfig(height_aiding=True)


def _fix(tow_s: float, h_m: float, east_m: float = 0.0, ok: bool = True) -> Fix:
    x = geodetic_to_ecef(LAT, LON, h_m) + ROT.T @ np.array([east_m, 0.0, 0.0])
    return Fix("spp", "spp" if ok else "none", 2051, tow_s, x_ecef_m=tuple(float(v) for v in x))


def test_the_held_height_is_the_median_of_the_window_with_a_growing_sigma():
    held = HeightAid()
    assert held.prior(2051, 100.0, CFG) is None  # no history: no aid for a first fix
    held.update(_fix(100.0, 10.0), CFG)
    held.update(_fix(101.0, 40.0, east_m=30.0), CFG)  # an outlier: the median ignores it
    assert held.prior(2051, 102.0, CFG) is None  # 2 < height_aid_min_fixes
    held.update(_fix(102.0, 12.0, east_m=60.0), CFG)
    held.update(_fix(103.0, 99.0, ok=False), CFG)  # a decline holds nothing
    h, sigma = held.prior(2051, 112.0, CFG)
    assert h == pytest.approx(12.0, abs=1e-3)
    # 10 s since the newest fix (no speed known), half the 60 m span moved
    want = math.sqrt(3.0**2 + (0.1 * 10.0) ** 2 + (0.05 * 30.0) ** 2)
    assert sigma == pytest.approx(want, rel=1e-3)
    tight = replace(CFG, height_aid_rate_m_s=0.0, height_aid_grade=0.0)
    assert held.prior(2051, 112.0, tight)[1] == pytest.approx(3.0)
    # the window: at 161.5 s only the fix of 102 s is within 60 s
    assert held.prior(2051, 161.5, CFG) is None
    one = replace(CFG, height_aid_min_fixes=1)
    assert held.prior(2051, 161.5, one)[0] == pytest.approx(12.0, abs=1e-3)
    assert held.prior(2051, 163.0, one) is None
    held.reset()
    assert held.prior(2051, 104.0, CFG) is None


def test_a_small_sigma_is_never_rounded_below_its_setting():
    """The held sigma is given to a 10 cm step: a 4 cm setting stays 4 cm (rounded it was
    0, and every aided fix a ZeroDivisionError decline), and the aided solve is a fix."""
    held = HeightAid()
    small = replace(CFG, height_aid_sigma_m=0.04, height_aid_rate_m_s=0.0, height_aid_grade=0.0)
    for t in range(3):
        held.update(_fix(100.0 + t, 10.0), small)
    h, sigma = held.prior(2051, 103.0, small)
    assert h == pytest.approx(10.0) and sigma == pytest.approx(0.04)
    epochs, store, iono = _hksc()
    fix = solve(epochs[0], store, iono, SolverConfig(height_aid=(TRUE_H_M, sigma)), "spp")
    assert fix.ok, fix.reason


def test_unweighted_the_row_weighs_as_its_sigma_against_the_uniform_sigma():
    """weighted=False (the studies): every range weighs as ``sigma_uniform_m``, so the
    height row weighs (sigma_uniform / sigma_aid)^2 in the estimate, as in the test and
    protection levels. An aid 5 m above the plain fix at 3 m weighs as one range: the
    height moves by 5 m x q / (q + 1), q the plain fix's vertical variance over
    sigma_uniform^2 (Sherman-Morrison: one row added to the normal equations)."""
    epochs, store, iono = _hksc()
    cfg = SolverConfig(weighted=False)
    ep = epochs[0]
    plain = solve(ep, store, iono, cfg, "spp")
    h0 = _height(plain)
    aided = solve(ep, store, iono, replace(cfg, height_aid=(h0 + 5.0, 3.0)), "spp")
    assert plain.ok and aided.ok
    q_uu = plain.cov_enu_m2[2][2] / 3.0**2
    want = 5.0 * q_uu / (q_uu + 1.0)
    assert _height(aided) - h0 == pytest.approx(want, rel=0.02), q_uu


def test_cfg_for_gives_the_row_only_with_height_aiding_on():
    held = HeightAid()
    for t in range(5):
        held.update(_fix(200.0 + t, 8.0), CFG)
    off = SolverConfig()
    assert held.cfg_for(2051, 205.0, off) is off
    on = held.cfg_for(2051, 205.0, CFG)
    assert on.height_aid is not None and on.height_aid[0] == pytest.approx(8.0, abs=1e-3)


# ---- the prediction screen -------------------------------------------------------------------


def _with_velocity(fix: Fix, ep: MeasurementEpoch, store) -> Fix:
    from service.engine.velocity import with_velocity

    moving = with_velocity(fix, ep, store)
    assert moving.velocity is not None
    return moving


def test_the_residuals_at_the_true_position_are_metres_on_the_station():
    """At the surveyed position every range's residual less its system's median is what
    the atmosphere's differences and the orbits leave: metres, far below a 30 m screen."""
    epochs, store, _ = _hksc()
    for ep in epochs:
        res = predicted_residuals(ep, store, HKSC_TRUTH_ECEF_M)
        assert len(res) == int(np.isfinite(ep.pr_m).sum())
        assert max(abs(r) for r in res.values()) < 15.0, res


def test_the_screen_leaves_out_a_lengthened_range_and_only_it():
    _, store, iono = _hksc()
    ep0, ep1, *_ = RinexObsReader(HKSC / "hksc1610.obs", systems={"C"})  # 1 s apart
    far = _hksc()[0][1]  # 20 s after ep0
    cfg = SolverConfig(screen_predicted_m=30.0)
    pred = Predictor()
    pred.update(_with_velocity(solve(ep0, store, iono, cfg, "spp"), ep0, store))
    assert pred.screen(far, store, cfg) == (far, {})  # beyond PREDICTION_MAX_AGE_S
    assert pred.screen(ep0, store, cfg) == (ep0, {})  # (dt = 0: no prediction either)
    assert pred.screen(ep1, store, cfg) == (ep1, {})  # nothing 30 m long
    # one range 80 m long
    i = int(np.flatnonzero(np.isfinite(ep1.pr_m))[2])
    pr = ep1.pr_m.copy()
    pr[i] += 80.0
    bad = replace(ep1, pr_m=pr)
    kept, why = pred.screen(bad, store, cfg)
    assert list(why) == [ep1.prn[i]] and "m longer than predicted" in why[ep1.prn[i]]
    assert ep1.prn[i] not in kept.prn and len(kept.prn) == len(ep1.prn) - 1
    # off: nothing left out
    assert pred.screen(bad, store, SolverConfig()) == (bad, {})


def test_the_prediction_moves_the_last_fix_by_its_velocity():
    epochs, store, iono = _hksc()
    ep = epochs[0]
    fix = _with_velocity(solve(ep, store, iono, SolverConfig(), "spp"), ep, store)
    east = replace(fix.velocity, v_enu_m_s=(10.0, 0.0, 0.0))
    pred = Predictor()
    pred.update(replace(fix, velocity=east))
    x = pred.predict(ep.gpst_week, ep.gpst_tow_s + 2.0)
    lat, lon, _ = ecef_to_geodetic(np.asarray(fix.x_ecef_m))
    enu = enu_rotation(lat, lon) @ (x - np.asarray(fix.x_ecef_m))
    assert enu == pytest.approx([20.0, 0.0, 0.0], abs=1e-6)
    assert pred.predict(ep.gpst_week, ep.gpst_tow_s + 3.5) is None  # too old
    pred.update(replace(fix, velocity=None, gpst_tow_s=fix.gpst_tow_s + 1.0))  # not taken
    assert pred.predict(ep.gpst_week, ep.gpst_tow_s + 2.0) is not None
    pred.reset()
    assert pred.predict(ep.gpst_week, ep.gpst_tow_s + 2.0) is None


def test_bdsfix_solve_gives_both_solvers_the_same_rows_and_aid():
    """``bdsfix solve --mode both`` with both settings on HKSC (BeiDou, every epoch in
    order): the fast fix (non-GEO ranges fractional) equals SPP to 1 mm on every epoch,
    as without them; the aid joined from the fourth epoch on (redundancy one more)."""
    from service.commands.solve import BatchOptions, solve_epochs

    _, store, iono = _hksc()
    cfg = SolverConfig(height_aiding=True, screen_predicted_m=30.0)
    opts = BatchOptions(mode="both", cfg=cfg, with_sky=False)
    plain = BatchOptions(mode="spp", with_sky=False)
    epochs = list(RinexObsReader(HKSC / "hksc1610.obs", systems={"C"}))
    got = list(solve_epochs(iter(epochs), store, iono, opts))
    ref = list(solve_epochs(iter(epochs), store, iono, plain))
    assert len(got) == len(epochs) == 205
    for k, ((_, (fast, spp)), (_, (unaided,))) in enumerate(zip(got, ref, strict=True)):
        assert fast.ok and spp.ok and fast.used == spp.used, (fast.reason, spp.reason)
        assert np.linalg.norm(np.subtract(fast.x_ecef_m, spp.x_ecef_m)) <= 1e-3
        assert spp.redundancy == unaided.redundancy + (k >= 3), k
        assert not spp.excluded  # the clean station: nothing 30 m longer than predicted


def test_the_batched_aided_solve_is_the_one_epoch_at_a_time_solve_on_hksc():
    """``bdsfix solve`` solves the aided epochs in batches (solve_aided's fixed point): on
    HKSC with BeiDou, GPS and Galileo (the fast fix joining GPS and Galileo's fractional
    ranges), both solvers, the sky (NMEA), every field of every fix is the one of solving
    each epoch alone from the fixes before it, to the output's bytes (the kernel solving
    several epochs together differs from one alone in the last bits of a float: numpy's
    stacked products sum in another order; the aid, given to 10 cm, does not
    pass such bits on)."""
    from service.commands.solve import BatchOptions
    from service.core.systems import parse_systems
    from tests.support.aided import batched_and_alone

    systems = parse_systems("C,G,E")
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")], systems=systems)
    cfg = SolverConfig(height_aiding=True, screen_predicted_m=30.0)
    opts = BatchOptions(mode="both", cfg=cfg, with_sky=True)
    epochs = list(RinexObsReader(HKSC / "hksc1610.obs", systems=systems))
    got, ref = batched_and_alone(epochs, store, iono, opts)
    assert len(got) == 2 * len(epochs) == 410
    assert got == ref


def test_the_median_is_numpys_to_the_last_bit():
    """The held height's, the screen's and the MEASX calibration's median
    (service.core.stats.median, without numpy's per-call cost) is numpy.median's float on
    odd and even counts, ties and NaN."""
    from service.core.stats import median as _median

    rng = np.random.default_rng(7)
    for n in range(1, 80):
        values = (rng.normal(0.0, 30.0, n) * rng.choice([1e-3, 1.0, 1e5])).tolist()
        assert _median(values) == float(np.median(values)), n
        rounded = [round(v) for v in values]  # ties
        assert _median([float(v) for v in rounded]) == float(np.median(rounded))
    assert math.isnan(_median([1.0, math.nan, 2.0]))
