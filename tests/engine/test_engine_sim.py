"""The fast fix on physically simulated measurements (real 2021 broadcast ephemerides).

Measurements come from service.sim.rangegen (light time, Sagnac, satellite clock, noise) at a
known position; the checks are that the fast fix recovers the true integers, equals the SPP
of the same full pseudoranges, and declines rather than returning anything wrong.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.core.bds import is_geo
from service.core.constants import C_M_S
from service.core.ephemeris import EphemerisStore
from service.core.geometry import geodetic_to_ecef
from service.core.orbit import EphemerisArrays
from service.core.timebase import gpst_to_bdt
from service.core.types import MeasurementEpoch
from service.engine.solver import SolverConfig, fractionalize, solve
from service.sim.rangegen import true_ranges
from tests.support.independent import eph_from_georinex, georinex_bds_ephemerides
from tests.support.paths import DATA

WEEK, TOW = 2161, 4 * 86400 + 3 * 3600 + 36 * 60 + 18.0  # 2021-06-10 03:36:18 GPST
# the paper's settings: no corrections, equal weights, no PDOP gate (Table 2 has none)
CFG = SolverConfig(
    elmask_deg=0.0, beta=3000.0, iono="off", tropo="off", weighted=False, pdop_max=math.inf
)


@pytest.fixture(scope="module")
def store() -> EphemerisStore:
    s = EphemerisStore()
    for rec in georinex_bds_ephemerides(DATA / "hksc-2021" / "hksc1610.nav"):
        if "_" not in rec["prn"]:
            s.add(eph_from_georinex(rec))
    return s


def _scene(store, lat_deg, lon_deg, alt_m, dt_s, clock_s, noise_m, seed):
    week, tow = WEEK, TOW + dt_s
    bw, bs = gpst_to_bdt(week, tow)
    ephs = [e for e in (store.select(p, bw, bs) for p in store.prns) if e is not None]
    arr = EphemerisArrays.from_ephemerides(ephs)
    x = geodetic_to_ecef(np.radians(lat_deg), np.radians(lon_deg), alt_m)
    tr = true_ranges(arr, x, week, tow, clock_s, noise_m=noise_m, rng=np.random.default_rng(seed))
    vis = np.flatnonzero(tr.el_rad >= 0)
    prn = [tr.prn[i] for i in vis]
    ep = MeasurementEpoch.from_columns(
        tr.tag_gpst_week, tr.tag_gpst_tow_s, prn, ["2I"] * len(prn), tr.pr_m[vis]
    )
    return x, ep


def _check(store, x, ep):
    n_geo = sum(is_geo(p) for p in ep.prn)
    frac_ep = fractionalize(ep)
    fast = solve(frac_ep, store, cfg=CFG, solver="fast")
    spp = solve(ep, store, cfg=CFG, solver="spp")
    assert spp.ok
    if fast.ok:
        assert n_geo >= 4
        assert np.linalg.norm(np.subtract(fast.x_ecef_m, spp.x_ecef_m)) <= 1e-3
        ct = C_M_S * 1e-3
        for prn, n in fast.ambiguity.items():
            i = ep.prn.index(prn)
            assert n == round((ep.pr_m[i] - frac_ep.frac_pr_m[i]) / ct)
        assert np.linalg.norm(np.subtract(spp.x_ecef_m, x)) < 100.0
    else:
        assert fast.reason
    return fast, spp


@settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    lat=st.floats(-70, 70),
    lon=st.floats(75, 145),
    alt=st.sampled_from([0.0, 500.0, 1_000_000.0]),
    dt_s=st.floats(-1500, 1500),
    clock_s=st.floats(-5, 5),
    seed=st.integers(0, 2**32 - 1),
)
def test_fast_equals_spp_when_the_gate_passes(store, lat, lon, alt, dt_s, clock_s, seed):
    x, ep = _scene(store, lat, lon, alt, dt_s, clock_s, 1.3, seed)
    fast, _ = _check(store, x, ep)
    if fast.gdop_full is not None and fast.gdop_full < 3000 and fast.ok:
        assert fast.mode == "fast"


def test_fewer_than_four_geos_declines_with_reason(store):
    # 10 deg W sees at most 2 of the five GEOs (58.75-160 deg E)
    x, ep = _scene(store, 40.0, -10.0, 0.0, 0.0, 0.0, 1.3, 1)
    fast, spp = _check(store, x, ep)
    assert spp.ok and not fast.ok
    assert fast.reason.startswith("too few full measurements")


def test_all_full_reduces_to_spp(store):
    _x, ep = _scene(store, 22.3, 114.2, 0.0, 0.0, 0.003, 1.3, 2)
    fast = solve(ep, store, cfg=CFG, solver="fast")
    spp = solve(ep, store, cfg=CFG, solver="spp")
    assert fast.mode == "spp" and not fast.ambiguity
    assert np.linalg.norm(np.subtract(fast.x_ecef_m, spp.x_ecef_m)) < 1e-6


def test_wrong_integer_is_never_published(store):
    """A 1-ms slip injected on one non-GEO is either repaired or refused, never published."""
    x, ep = _scene(store, 22.3, 114.2, 0.0, 0.0, 0.001, 1.3, 3)
    frac = fractionalize(ep)
    truth = solve(frac, store, cfg=CFG, solver="fast")
    assert truth.mode == "fast"
    for prn in truth.ambiguity:
        i = frac.prn.index(prn)
        for slip_m in (C_M_S * 1e-3 * 0.5, 150e3, 3e3, 400.0):
            pr = frac.frac_pr_m.copy()
            pr[i] = np.mod(pr[i] + slip_m, C_M_S * 1e-3)
            bad = MeasurementEpoch.from_columns(
                frac.gpst_week, frac.gpst_tow_s, frac.prn, frac.signal, frac.pr_m, pr, frac.period_s
            )
            fix = solve(bad, store, cfg=CFG, solver="fast")
            if fix.ok:
                # published: every integer reported is the true one; the damaged satellite
                # is either repaired or excluded (and then reported, not used)
                assert fix.ambiguity == {p: truth.ambiguity[p] for p in fix.ambiguity}
                assert set(truth.ambiguity) - set(fix.ambiguity) <= {prn}
                if prn not in fix.ambiguity:
                    assert prn in fix.excluded and prn not in fix.used
                assert np.linalg.norm(np.subtract(fix.x_ecef_m, x)) < 1000.0
            else:
                assert fix.reason
