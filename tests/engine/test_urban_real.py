"""Multi-system SPP in a street canyon, against the drive's ground truth.

The Hong Kong TST u-blox drive (``../shared/data/hk-tst-urban-2019``: 485 epochs with a
SPAN ground truth, BeiDou + GPS with their nav files; its Galileo rows have no ephemeris)
solved epoch by epoch with the daemon's default settings and ``systems`` C, G, E, as
``bench/bench_urban.py --systems C,G,E`` does. The bounds are the figures measured on
this branch (docs/method.md, "Urban drive"), rounded outward: they hold the error model and
fault exclusion to what they achieve today, so that a change that loses accuracy,
availability or integrity in the canyon fails here. They are NOT the issue's targets
(availability >= 85 %, p50 <= 10 m, p95 <= 40 m), which today's snapshot SPP misses.
"""

from __future__ import annotations

import csv
import math
from functools import cache

import numpy as np
import pytest

from drivers.rinex import RinexObsReader
from service.commands.solve import load_navigation
from service.core.geometry import ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from service.core.systems import parse_systems
from service.engine.solver import SolverConfig, solve
from tests.support.paths import DATA

TST = DATA / "hk-tst-urban-2019"
TRUTH_EPOCHS = 485
AVAILABILITY_MIN = 0.80  # measured 80.4 % (390 of 485)
P50_MAX_M = 15.5  # measured 14.8 m
P95_MAX_M = 112.0  # measured 109.5 m


@cache
def _errors() -> tuple[int, np.ndarray, int]:
    """(epochs with truth, 3D errors of the published fixes, fixes outside their HPL)."""
    truth = {}
    with open(TST / "groundTruth_TST.csv", encoding="ascii") as f:
        for row in csv.reader(f):
            week, tow, lat, lon, h = (float(v) for v in row[:5])
            truth[(int(week), round(tow))] = geodetic_to_ecef(
                math.radians(lat), math.radians(lon), h
            )
    systems = parse_systems("C,G,E")
    navs = [str(TST / "hksc1180.19b"), str(TST / "hksc1180.19n")]
    store, iono = load_navigation(navs, systems=systems)
    cfg = SolverConfig()
    n, errs, outside = 0, [], 0
    for ep in RinexObsReader(TST / "COM3_190428_124409.obs", systems=systems):
        t = truth.get((ep.gpst_week, round(ep.gpst_tow_s)))
        if t is None:
            continue
        n += 1
        fix = solve(ep, store, iono, cfg, "spp")
        if not fix.ok:
            continue
        d = np.subtract(fix.x_ecef_m, t)
        errs.append(float(np.linalg.norm(d)))
        lat, lon, _ = ecef_to_geodetic(t)
        enu = enu_rotation(lat, lon) @ d
        assert fix.hpl_m is not None
        outside += math.hypot(enu[0], enu[1]) > fix.hpl_m
    return n, np.asarray(errs), outside


@pytest.mark.slow
def test_urban_drive_availability_accuracy_and_protection_levels():
    n, errs, outside = _errors()
    assert n == TRUTH_EPOCHS
    availability = len(errs) / n
    p50, p95 = np.percentile(errs, [50, 95])
    figures = (availability, p50, p95, outside)
    assert availability >= AVAILABILITY_MIN, figures
    assert p50 <= P50_MAX_M and p95 <= P95_MAX_M, figures
    assert outside <= 0.01 * len(errs), figures
