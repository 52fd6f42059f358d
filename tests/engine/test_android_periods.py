"""Ranges known modulo periods longer than 1 ms (Android states), and a coarse time prior.

A phone reports each signal's transmit time modulo the period its state allows (2 ms at
BeiDou D2 bit sync up to 6 s at subframe sync, drivers/gnsslogger.py). The fast fix takes
each row's own c*T as the ambiguity of its integer (solver rows' ``ct_m``): on real
measurements (the HKSC reference station, 5 GEOs) with four GEOs full and every other
satellite known only modulo such periods, it recovers each full pseudorange exactly and
the SPP position. While the receiver's time is coarse (``time_unc_s`` over 1 ms, a phone
before its first fix) the pipeline keeps fractional ranges out and says why.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest

from drivers.source import open_source
from service.core.constants import C_M_S
from service.core.geometry import ecef_to_geodetic, enu_rotation
from service.core.types import MeasurementEpoch
from service.engine.coarse import moved
from service.engine.solver import fractionalize
from tests.support.nav import pipeline_with_nav
from tests.support.paths import DATA

OBS = DATA / "hksc-2021" / "hksc1610.obs"
NAV = DATA / "hksc-2021" / "hksc1610.nav"
PERTH = DATA / "android-perth-s8-2017"
PERIODS_S = (1e-3, 2e-3, 0.02, 0.1, 0.6, 2.0, 6.0)


def _hksc_epoch() -> MeasurementEpoch:
    with open_source(str(OBS)) as src:
        return next(e for e in itertools.islice(src, 5) if isinstance(e, MeasurementEpoch))


def _partial(epoch: MeasurementEpoch, n_full: int, time_unc_s: float) -> MeasurementEpoch:
    """``epoch`` with its first ``n_full`` GEOs full and every other satellite known modulo
    one of :data:`PERIODS_S` in turn."""
    geos = [p for p in epoch.prn if int(p[1:]) <= 5][:n_full]
    full = np.array([p in geos for p in epoch.prn])
    period = np.array([1e-3 if f else PERIODS_S[k % len(PERIODS_S)] for k, f in enumerate(full)])
    return replace(
        epoch,
        pr_m=np.where(full, epoch.pr_m, np.nan),
        frac_pr_m=np.mod(epoch.pr_m, C_M_S * period),
        period_s=period,
        time_unc_s=time_unc_s,
    )


def test_fast_fix_with_periods_from_2_ms_to_6_s_recovers_the_full_ranges():
    epoch = _hksc_epoch()
    spp = pipeline_with_nav(NAV).on_epoch(epoch).fix
    partial = _partial(epoch, 4, time_unc_s=5e-9)
    assert set(partial.period_s[np.isnan(partial.pr_m)]) == set(PERIODS_S)
    fix = pipeline_with_nav(NAV).on_epoch(partial).fix
    assert fix.mode == "fast" and fix.ok
    assert np.linalg.norm(np.subtract(fix.x_ecef_m, spp.x_ecef_m)) < 1e-3
    assert len(fix.recovered_pr_m) == len(epoch) - 4
    for prn, pr in fix.recovered_pr_m.items():
        assert pr == pytest.approx(epoch.pr_m[epoch.prn.index(prn)], abs=1e-3)


def spp_of(epoch):
    return pipeline_with_nav(NAV).on_epoch(epoch).fix


def test_a_coarse_time_keeps_fractional_ranges_out_and_says_why():
    epoch = _hksc_epoch()
    # no full range: with a time uncertain by 7.25 s (beyond the coarse-time fix's 2 s, and 5
    # sigma beyond the 30 s it takes from a phone) the fractional rows are set aside and the
    # decline names the prior: wait for the first SOW
    fix = pipeline_with_nav(NAV).on_epoch(_partial(epoch, 0, time_unc_s=7.25)).fix
    assert fix.reason_code == "coarse_time"
    assert "+-7.25 s" in fix.reason and "16 fractional" in fix.reason and "0 full" in fix.reason
    # the Perth phone's 5.97 s: 5 sigma (29.8 s) is the coarse-time fix's prior, which takes
    # the epoch (the common millisecond in doubt: the coarse-time solution, within 1 m of SPP)
    fix = pipeline_with_nav(NAV).on_epoch(_partial(epoch, 0, time_unc_s=5.968969500122643)).fix
    assert fix.ok and fix.method == "coarse_time"
    assert np.linalg.norm(np.subtract(fix.x_ecef_m, spp_of(epoch).x_ecef_m)) < 1.0
    # so too with no time uncertainty given at all (a phone that does not say: inf)
    fix = pipeline_with_nav(NAV).on_epoch(_partial(epoch, 0, time_unc_s=math.inf)).fix
    assert fix.reason_code == "coarse_time"
    # with a fine time the paper's fast fix still needs 4 full ranges (its 4 GEOs); the
    # coarse-time fix (service.engine.coarse) takes the epoch instead and gives SPP's position
    fine = pipeline_with_nav(NAV).on_epoch(_partial(epoch, 3, time_unc_s=5e-9)).fix
    assert fine.ok and fine.method == "coarse_time"
    assert np.linalg.norm(np.subtract(fine.x_ecef_m, spp_of(epoch).x_ecef_m)) < 1e-3
    # 4 full GEOs: the fast fix with a fine time; with a coarse time the four GEOs are
    # solved alone (the fractional rows set aside), and their geometry fails the PDOP gate
    assert pipeline_with_nav(NAV).on_epoch(_partial(epoch, 4, time_unc_s=5e-9)).fix.mode == "fast"
    fix = pipeline_with_nav(NAV).on_epoch(_partial(epoch, 4, time_unc_s=5.97)).fix
    assert fix.reason_code == "pdop_gate"


def test_perth_replay_through_thepipeline_with_nav():
    """The Perth start-up with its day's nav (BDS sets read): the first fix is SPP from the
    four BDS IGSO/MEO at 26.18 s (the engine has no GPS sets yet; measured 25.9 m from the
    converged position), every published fix within 100 m of the median of the last 5
    minutes (measured at most 58.5 m), and what comes before is declined for the phone's
    coarse time, the GPS satellites' missing ephemerides or too few full BDS ranges."""
    pipe = pipeline_with_nav(PERTH / "PERT00AUS_R_20172780000_01D_MN.rnx")
    with open_source(str(PERTH / "SensorLog20171005.txt")) as src:
        results = [pipe.on_epoch(e) for e in src if isinstance(e, MeasurementEpoch)]
    assert len(results) == 445
    t0 = results[0].epoch.gpst_tow_s
    fixed = [r for r in results if r.fix.ok]
    assert fixed[0].fix.mode == "spp"
    assert fixed[0].epoch.gpst_tow_s - t0 == pytest.approx(26.18, abs=0.01)
    before = {r.fix.reason_code for r in results if r.epoch.gpst_tow_s < fixed[0].epoch.gpst_tow_s}
    # GPS-only epochs: no GPS sets; then C06 alone or with too few full ranges
    assert before == {"coarse_time", "no_ephemeris", "too_few_full"}
    x = np.array([r.fix.x_ecef_m for r in fixed])
    t = np.array([r.epoch.gpst_tow_s for r in fixed])
    ref = np.median(x[t > t[-1] - 300], axis=0)
    dist = np.linalg.norm(x - ref, axis=1)
    assert dist.max() < 100.0
    # Perth: about 32.0 S, 115.9 E
    lat = np.degrees(np.arctan2(ref[2], np.hypot(ref[0], ref[1])))
    lon = np.degrees(np.arctan2(ref[1], ref[0]))
    assert -32.5 < lat < -31.5 and 115.5 < lon < 116.5


def test_perth_with_gps_and_galileo_fixes_from_the_first_epoch():
    """The Perth start-up with GPS and Galileo rows read: the phone's time is uncertain by
    5.97 s (beyond the 2 s prior) and no SOW has decoded until 12 s, so the coarse-time fix
    takes the phone's own 5 sigma (29.9 s) as its prior. Every epoch is fixed, the first at
    the first Raw row (10 GPS ranges known modulo 1 ms; BeiDou alone: 26.18 s), and the
    epochs 6-11 s, every range fractional with mixed periods (GPS modulo 6 s at subframe
    sync, BeiDou and Galileo modulo 1 ms), are coarse-time fixes with rows of each system.
    Every fix within 100 m of the median of the last 5 minutes (measured at most 26.9 m),
    the coarse-time ones within their HPL of it (measured 3.7-18 m against HPLs of
    21-57 m)."""
    pipe = pipeline_with_nav(PERTH / "PERT00AUS_R_20172780000_01D_MN.rnx", ("C", "G", "E"))
    with open_source(str(PERTH / "SensorLog20171005.txt")) as src:
        results = [pipe.on_epoch(e) for e in src if isinstance(e, MeasurementEpoch)]
    t0 = results[0].epoch.gpst_tow_s
    assert all(r.fix.ok for r in results)
    x = np.array([r.fix.x_ecef_m for r in results])
    t = np.array([r.epoch.gpst_tow_s for r in results]) - t0
    ref = np.median(x[t > t[-1] - 300], axis=0)
    dist = np.linalg.norm(x - ref, axis=1)
    assert dist.max() < 100.0
    mixed = 0
    for r, d in zip(results, dist, strict=True):
        ep = r.epoch
        if ep.gpst_tow_s - t0 >= 12.0:  # the first GPS times of week decoded: full ranges
            break
        assert r.fix.method == "coarse_time"
        assert not np.isfinite(ep.pr_m).any()
        lat, lon, _ = ecef_to_geodetic(ref)
        e = enu_rotation(lat, lon) @ (x[results.index(r)] - ref)
        assert math.hypot(e[0], e[1]) <= r.fix.hpl_m
        gps = {float(p) for p, q in zip(ep.period_s, ep.prn, strict=True) if q[:1] == "G"}
        if gps == {6.0}:
            mixed += 1
            assert {p[:1] for p in r.fix.used} >= {"C", "G"}
    assert mixed == 6  # 6.00-11.00 s


@pytest.mark.parametrize("n_full", [1, 2, 3])
@pytest.mark.parametrize(("time_unc_s", "clock_s"), [(5.97, 0.0), (5.97, 5.97), (math.inf, -7.3)])
def test_the_first_decoded_sow_is_the_time_prior_when_the_tag_is_none(n_full, time_unc_s, clock_s):
    """A phone whose time is unknown or seconds off (time_unc_s beyond the coarse-time fix's
    2 s prior), its tag and ranges on its own clock (here moved by ``clock_s`` together, as
    the phone computes them): once one satellite's SOW has decoded (a full range), its
    transmit time plus a flight time (+-10 ms) is the prior, and the coarse-time fix is SPP
    of the file's full ranges at the true time, its offset the tag's error to 1 ns."""
    epoch = _hksc_epoch()
    spp = spp_of(epoch)
    phone = moved(_partial(epoch, n_full, time_unc_s), clock_s)
    fix = pipeline_with_nav(NAV).on_epoch(phone).fix
    assert fix.ok and fix.method == "coarse_time"
    assert np.linalg.norm(np.subtract(fix.x_ecef_m, spp.x_ecef_m)) <= 1e-3
    assert fix.gpst_tow_s == phone.gpst_tow_s
    true_offset_s = -clock_s - spp.clock_bias_m / C_M_S
    assert fix.time_offset_s == pytest.approx(true_offset_s, abs=1e-9)
    # the recovered ranges are on the phone's clock (what its later SOWs are checked against)
    for prn, pr in fix.recovered_pr_m.items():
        assert pr == pytest.approx(epoch.pr_m[epoch.prn.index(prn)] + C_M_S * clock_s, abs=1e-3)
    assert len(fix.recovered_pr_m) == len(epoch) - n_full


@pytest.mark.parametrize("time_unc_s", [5e-9, 1e-5])
def test_a_phone_time_known_to_microseconds_resolves_the_common_millisecond(time_unc_s):
    """Every range fractional (no GEO full), the phone's time known to ``time_unc_s``
    (BiasUncertaintyNanos, one sigma): the coarse-time fix's prior is 5 sigma of it, the
    solved time leaves no doubt about the millisecond common to every range, and the fix is
    SPP of the file's full ranges with every integer absolute (recovered ranges equal to the
    file's). A file's tag says nothing of its uncertainty (NaN): the 2 s prior, the common
    millisecond in doubt, and the fix is the coarse-time solution (centimetres from SPP)."""
    epoch = _hksc_epoch()
    spp = spp_of(epoch)
    fractional = fractionalize(epoch, keep_full=())  # every range modulo 1 ms
    fix = pipeline_with_nav(NAV).on_epoch(replace(fractional, time_unc_s=time_unc_s)).fix
    assert fix.ok and fix.method == "coarse_time"
    assert np.linalg.norm(np.subtract(fix.x_ecef_m, spp.x_ecef_m)) <= 1e-3
    assert len(fix.recovered_pr_m) == len(epoch)
    for prn, pr in fix.recovered_pr_m.items():
        assert pr == pytest.approx(epoch.pr_m[epoch.prn.index(prn)], abs=1e-3)
    file_tag = pipeline_with_nav(NAV).on_epoch(fractional).fix
    assert file_tag.ok and file_tag.method == "coarse_time" and not file_tag.recovered_pr_m
    assert 1e-3 < np.linalg.norm(np.subtract(file_tag.x_ecef_m, spp.x_ecef_m)) < 1.0
