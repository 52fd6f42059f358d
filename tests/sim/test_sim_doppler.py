"""The virtual receiver's Doppler is the derivative of its own ranges.

Without noise, -lambda * D at an epoch must equal the carrier's range rate, which the test
takes from the simulator's pseudoranges of the neighbouring epochs (a central difference
over +-5 s, independent of how the simulator computes D): with the ionosphere off the
code and the carrier move together (the troposphere is in both). The UBX encoding carries
D to the driver with the sign of RXM-RAWX ``doMes`` (positive for an approaching
satellite), and a replay of the scenario's stream gives a static receiver's speed.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from service.commands.run import decode_chunks
from service.core.constants import C_M_S
from service.core.types import MeasurementEpoch
from service.engine.pipeline import Pipeline
from service.sim.keplerian import table1_ephemerides
from service.sim.scenario import builtin_scenario, scenario_config
from service.sim.simulator import Simulator

LAMBDA_M = C_M_S / 1_561.098e6  # B1I carrier 1561.098 MHz, BDS-SIS-ICD-B1I-3.0 4.2
HALF_SPAN_S = 5.0


def _noise_free(duration_s: float = 3.0):
    cfg = replace(scenario_config(duration_s=duration_s), noise_m=0.0, doppler_noise_hz=0.0)
    sim = Simulator(table1_ephemerides(0.0), cfg)
    return sim, list(sim.epochs())


def test_doppler_is_minus_the_range_rate_of_the_pseudoranges():
    sim, eps = _noise_free(12.0)
    k = round(HALF_SPAN_S * sim.cfg.rate_hz)
    checked = 0
    for before, now, after in zip(eps, eps[k:], eps[2 * k :], strict=False):
        common = [p for p in now.prn if p in before.prn and p in after.prn]
        for prn in common:
            pr_b = before.pr_m[before.prn.index(prn)]
            pr_a = after.pr_m[after.prn.index(prn)]
            rate_from_ranges = (pr_a - pr_b) / (2 * HALF_SPAN_S)  # central difference [m/s]
            rate_from_doppler = -LAMBDA_M * now.doppler_hz[now.prn.index(prn)]
            # the ranges are quantised to the MEASX code-phase step (c * 2^-21 ms, 0.143 m):
            # two of them differ by at most one step, over 10 s 0.0143 m/s; the difference's
            # truncation error (h^2/6 times the range's third derivative) is below 1e-3 m/s
            assert abs(rate_from_ranges - rate_from_doppler) < 0.0153, (prn, now.t_s)
            checked += 1
    assert checked > 200
    # the satellites move: Dopplers of hundreds of Hz for the non-GEOs, a few for the GEOs
    d = np.abs(eps[10].doppler_hz)
    assert d.max() > 500 and d.min() < 50


def test_ubx_frames_carry_the_doppler_to_the_driver_with_its_sign():
    sim, eps = _noise_free(1.0)
    week = eps[0].tag_gpst_week
    decoded = [
        ev
        for ev in decode_chunks((sim.encode(ep) for ep in eps), week)
        if isinstance(ev, MeasurementEpoch)
    ]
    by_tow = {round(ev.gpst_tow_s, 6): ev for ev in decoded}
    checked = 0
    for ep in eps:
        ev = by_tow[round(ep.tag_gpst_tow_s, 6)]
        for prn, d in zip(ep.prn, ep.doppler_hz, strict=True):
            # RAWX doMes is a float32: 7 significant digits
            assert abs(ev.doppler_hz[ev.prn.index(prn)] - d) <= 1e-6 * abs(d) + 1e-6
            checked += 1
    assert checked > 50


def test_the_scenario_replayed_gives_a_static_receivers_speed():
    """The built-in scenario (static, Doppler noise 0.05 Hz) through the driver and the
    pipeline: every fix has a velocity, a coarse-time fix with every range fractional too
    (its Doppler rows at its solved receive time); median speed <= 0.05 m/s, p95 <= 0.2 m/s,
    and every coarse-time fix's speed <= 0.2 m/s (a gpsd client differencing the first
    fixes' positions would otherwise see tens of m/s)."""
    chunks, week, store, iono, _, _ = builtin_scenario(duration_s=20.0)
    pipe = Pipeline(store, iono)
    speeds = []
    n_fix = n_coarse = 0
    for ev in decode_chunks(chunks, week):
        if isinstance(ev, MeasurementEpoch):
            fix = pipe.on_epoch(ev).fix
            if fix.ok and fix.method == "coarse_time" and not fix.full:
                # the scenario's first 0.6 s, before any GEO SOW
                assert fix.velocity is not None, fix.gpst_tow_s
                assert fix.velocity.speed_m_s <= 0.2, fix.velocity
                n_coarse += 1
            elif fix.ok:
                n_fix += 1
                assert fix.velocity is not None, fix.gpst_tow_s
                speeds.append(fix.velocity.speed_m_s)
    assert n_fix > 150 and 1 <= n_coarse <= 6
    assert np.median(speeds) <= 0.05 and np.percentile(speeds, 95) <= 0.2
