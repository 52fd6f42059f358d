"""The coarse-time first fix with GPS and Galileo rows beside BeiDou, on real recordings.

Each system has its own receiver clock (the inter-system bias unknown) and each row's integer
counts its own code period (1 ms B1I and GPS C/A, 4 ms Galileo E1: ``period_s``, set by
:func:`fractionalize`). A system whose rows are all fractional has a whole period common to
its rows that its clock absorbs: its integers are relative to one of its rows, unless the
clocks make them absolute (service.engine.coarse, step 5). The true integers are read from
the files' full ranges, in each row's own period, never from the code under test.

HKSC (static, Leica GR50, BeiDou + GPS + Galileo, mixed nav file) and the TST urban drive
(u-blox, BeiDou + GPS: its nav files are BeiDou and GPS only, so its Galileo rows have no
ephemeris), restarts emulated as in tests/engine/test_coarse_real.py.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from drivers.rinex import RinexObsReader
from service.commands.solve import load_navigation
from service.core.bds import is_geo
from service.core.constants import C_M_S
from service.core.declines import excluded_why
from service.core.geometry import ecef_to_geodetic, enu_rotation
from service.engine.coarse import COARSE_TIME, CoarseConfig, solve_coarse
from service.engine.solver import SolverConfig, fractionalize, solve
from tests.engine.test_coarse_real import _tst_truth
from tests.support.paths import DATA

HKSC = DATA / "hksc-2021"
TST = DATA / "hk-tst-urban-2019"


def _restarted(ep, k, shift_s=0.0):
    geos = [p for p, v in zip(ep.prn, ep.pr_m, strict=True) if is_geo(p) and np.isfinite(v)][:k]
    fe = fractionalize(ep, keep_full=geos)
    if shift_s:
        fe = replace(fe, gpst_tow_s=fe.gpst_tow_s + shift_s, pr_m=fe.pr_m + shift_s * C_M_S)
    return fe


def _true_integers(ep, fe, shift_s=0.0):
    """Each fractional row's integer in units of its own period, from the file's range."""
    return {
        p: round((full + shift_s * C_M_S - frac) / (C_M_S * t))
        for p, full, frac, t in zip(ep.prn, ep.pr_m, fe.frac_pr_m, fe.period_s, strict=True)
        if not np.isfinite(fe.pr_m[fe.prn.index(p)])
    }


def _wrong(res, truth):
    """Absolute integers compared as they are; relative ones system by system (differences
    to the system's first row: a system's whole period may sit in its clock)."""
    ints = res.integers
    if res.absolute:
        return any(ints[p] != truth[p] for p in ints)
    first: dict[str, str] = {}
    for p in ints:
        first.setdefault(p[:1], p)
    return any(ints[p] - ints[first[p[:1]]] != truth[p] - truth[first[p[:1]]] for p in ints)


def _without(ep, prns):
    return ep.rows([i for i, p in enumerate(ep.prn) if p not in prns])


@pytest.fixture(scope="module")
def hksc():
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")], systems="CGE")
    epochs = []
    for i, ep in enumerate(RinexObsReader(HKSC / "hksc1610.obs", systems="CGE")):
        if i % 8 == 0:
            ref = solve(ep, store, iono, SolverConfig(), "spp")
            if ref.ok:
                epochs.append((ep, ref))
    return store, iono, epochs


@pytest.mark.parametrize("shift_s", [0.0, 2.0, -2.0])
@pytest.mark.parametrize("k", [0, 1, 2, 3])
def test_hksc_three_systems_restarted_with_k_geos_full(hksc, k, shift_s):
    """Every GPS and Galileo range fractional beside the BeiDou ones (Galileo modulo 4 ms):
    every epoch fixed with every system's rows, no wrong integer; with a full GEO the fix is
    SPP of the file's full ranges of all three systems (each GPS and Galileo integer made
    absolute through its clock's difference to BeiDou's), to well under 1 mm."""
    store, iono, epochs = hksc
    assert len(epochs) >= 25
    fixed = 0
    for ep, ref in epochs:
        fe = _restarted(ep, k, shift_s)
        assert {p[:1] for p in fe.prn} == {"C", "G", "E"}
        assert set(fe.period_s[[p[:1] == "E" for p in fe.prn]]) == {4e-3}
        res = solve_coarse(fe, store, iono)
        if not res.fix.ok:
            continue
        fixed += 1
        assert res.fix.method == COARSE_TIME
        assert {p[:1] for p in res.fix.used} == {"C", "G", "E"}
        truth = _true_integers(ep, fe, shift_s)
        assert not _wrong(res, truth)
        diff = float(np.linalg.norm(np.subtract(res.fix.x_ecef_m, ref.x_ecef_m)))
        if k > 0:
            assert res.absolute
            assert set(res.integers) == set(truth)  # every system's, absolute
            assert diff <= 1e-5
            for prn, pr in res.fix.recovered_pr_m.items():
                assert pr == pytest.approx(ep.pr_m[ep.prn.index(prn)] + shift_s * C_M_S, abs=1e-6)
        else:  # the common millisecond in doubt: the coarse-time solution, centimetres
            assert diff <= 0.5
    assert fixed >= 0.99 * len(epochs)


def test_an_inter_system_bias_goes_into_the_systems_clock(hksc):
    """GPS ranges 300 m (1 us) later than BeiDou's (a receiver's inter-system bias): the GPS
    clock takes it, the integers stay right and absolute, and the fix is SPP of the biased
    full ranges (which solves the bias too). Half a millisecond (150 km, the GPS whole
    period in doubt): never a wrong integer, and no GPS integer published as absolute."""
    store, iono, epochs = hksc
    for bias_m, absolute in ((300.0, True), (0.5e-3 * C_M_S, False)):
        for ep, _ in epochs[::6]:
            gps = np.array([p[:1] == "G" for p in ep.prn])
            biased = replace(ep, pr_m=ep.pr_m + np.where(gps, bias_m, 0.0))
            ref = solve(biased, store, iono, SolverConfig(), "spp")
            fe = _restarted(biased, 1)
            res = solve_coarse(fe, store, iono)
            assert res.fix.ok
            assert any(p[:1] == "G" for p in res.integers)
            assert not _wrong(res, _true_integers(biased, fe))
            assert res.absolute is absolute
            if absolute:
                diff = float(np.linalg.norm(np.subtract(res.fix.x_ecef_m, ref.x_ecef_m)))
                assert diff <= 1e-5


def test_tst_whole_drive_with_gps_availability_and_never_a_wrong_integer():
    """Every epoch of the drive where SPP of the file's BeiDou and GPS full ranges fixes,
    every range fractional (k = 0): at least 95 % fixed (measured 97.4 %), none with a wrong
    integer, at most 1 % of the fixes with ground truth outside their HPL. Over the epochs
    where SPP of BeiDou alone fixes (BeiDou alone's own denominator: 84.6 % fixed, its 4-5
    satellite epochs declined too_few_rows) at least 88 % (measured 91.2 %)."""
    navs = [str(TST / "hksc1180.19b"), str(TST / "hksc1180.19n")]
    store, iono = load_navigation(navs, systems="CG")
    truth = _tst_truth()
    cfg, ccfg = SolverConfig(), CoarseConfig()
    n = fixed = with_truth = beyond = with_gps = n_bds = fixed_bds = 0
    for ep in RinexObsReader(TST / "COM3_190428_124409.obs", systems="CG"):
        bds = [i for i, p in enumerate(ep.prn) if p[:1] == "C"]
        bds_ok = solve(ep.rows(bds), store, iono, cfg, "spp").ok
        n_bds += bds_ok
        if not solve(ep, store, iono, cfg, "spp").ok:
            continue
        n += 1
        fe = _restarted(ep, 0)
        res = solve_coarse(fe, store, iono, cfg, ccfg)
        if not res.fix.ok:
            continue
        fixed += 1
        fixed_bds += bds_ok
        with_gps += any(p[:1] == "G" for p in res.fix.used)
        assert not _wrong(res, _true_integers(ep, fe))
        left_out = [p for p, why in res.fix.excluded.items() if why == excluded_why("coarse")]
        assert all(p not in res.fix.used for p in left_out)
        t = truth.get((ep.gpst_week, round(ep.gpst_tow_s)))
        if t is not None:
            with_truth += 1
            lat, lon, _ = ecef_to_geodetic(t)
            e = enu_rotation(lat, lon) @ np.subtract(res.fix.x_ecef_m, t)
            beyond += math.hypot(e[0], e[1]) > res.fix.hpl_m
    print(
        f"TST whole drive C+G k=0: {fixed}/{n} fixed, {beyond} of {with_truth} beyond HPL; "
        f"{fixed_bds}/{n_bds} of the epochs BeiDou-alone SPP fixes"
    )
    assert n >= 1500
    assert fixed >= 0.95 * n
    assert n_bds >= 1500 and fixed_bds >= 0.88 * n_bds
    assert with_gps >= 0.9 * fixed
    assert with_truth >= 350
    assert beyond <= 0.01 * with_truth


PHONE_PERIODS_S = {"C": (1e-3, 2e-3, 0.02), "G": (1e-3, 0.02, 6.0), "E": (4e-3, 0.1, 2.0)}
"""Periods a phone's states give (drivers/gnsslogger.py): BeiDou code, D2 bit, D1 bit; GPS
code, bit, subframe; Galileo E1 code, secondary code, page."""


@pytest.mark.parametrize("k", [0, 1])
def test_mixed_periods_within_each_system(hksc, k):
    """Each system's rows known modulo different periods (a phone's states): each integer
    counts its own period, each system's reference row is its longest period's, and the
    whole periods are resolved (BeiDou's 20 ms from the solved time, then GPS's 6 s and
    Galileo's 2 s through their clocks): every integer absolute and right, the fix SPP of
    the file's full ranges, the recovered ranges the file's, with or without a full GEO."""
    store, iono, epochs = hksc
    for ep, ref in epochs[::5]:
        geos = [p for p in ep.prn if is_geo(p) and np.isfinite(ep.pr_m[ep.prn.index(p)])][:k]
        count: dict[str, int] = {}
        period = []
        for p in ep.prn:
            i = count[p[:1]] = count.get(p[:1], -1) + 1
            period.append(1e-3 if p in geos else PHONE_PERIODS_S[p[:1]][i % 3])
        per = np.array(period)
        full = np.array([p in geos for p in ep.prn])
        fe = replace(
            ep,
            pr_m=np.where(full, ep.pr_m, np.nan),
            frac_pr_m=np.mod(ep.pr_m, C_M_S * per),
            period_s=per,
        )
        res = solve_coarse(fe, store, iono)
        assert res.fix.ok and res.absolute
        truth = _true_integers(ep, fe)
        assert res.integers == truth
        assert np.linalg.norm(np.subtract(res.fix.x_ecef_m, ref.x_ecef_m)) <= 1e-5
        for prn, pr in res.fix.recovered_pr_m.items():
            assert pr == pytest.approx(ep.pr_m[ep.prn.index(prn)], abs=1e-6)


def test_mixed_periods_beidou_alone_every_range_fractional(hksc):
    """BeiDou alone, every range fractional, modulo 1, 2 and 20 ms in turn: a coarse-time
    fix with the right integers (relative to the 20 ms reference row: the 20 ms whole
    period is in doubt at 4 sigma of the solved time), centimetres from SPP. Before each
    system's integers were taken relative to its longest period's row, the first row's
    integer was subtracted from every row's, a whole shift only when all periods are
    equal: no candidate converged and such an epoch was declined ``too_few_rows``."""
    store, iono, epochs = hksc
    for ep, _ in epochs[::5]:
        ep = ep.rows([i for i, p in enumerate(ep.prn) if p[:1] == "C"])
        ref = solve(ep, store, iono, SolverConfig(), "spp")
        per = np.array([PHONE_PERIODS_S["C"][i % 3] for i in range(len(ep.prn))])
        fe = replace(
            ep,
            pr_m=np.full(len(ep.prn), np.nan),
            frac_pr_m=np.mod(ep.pr_m, C_M_S * per),
            period_s=per,
        )
        res = solve_coarse(fe, store, iono)
        assert res.fix.ok and res.fix.method == COARSE_TIME
        truth = _true_integers(ep, fe)
        ref_row = next(p for p, t in zip(fe.prn, per, strict=True) if t == 0.02)
        for p, n in res.integers.items():
            scale = 0 if res.absolute else round(0.02 / per[fe.prn.index(p)])
            assert n == truth[p] - truth[ref_row] * scale
        assert np.linalg.norm(np.subtract(res.fix.x_ecef_m, ref.x_ecef_m)) <= 0.5
