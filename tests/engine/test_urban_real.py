"""Multi-system SPP in a street canyon, against the drive's ground truth.

The Hong Kong TST u-blox drive (``../shared/data/hk-tst-urban-2019``: 485 epochs with a
SPAN ground truth, BeiDou + GPS with their nav files; its Galileo rows have no ephemeris)
solved epoch by epoch with the daemon's default settings and ``systems`` C, G, E, as
``bench/bench_urban.py --systems C,G,E`` does. The bounds are the figures measured on
this branch (docs/method.md, "Urban drive"), rounded outward: they hold the error model and
fault exclusion to what they achieve today, so that a change that loses accuracy,
availability or integrity in the canyon fails here. They are NOT the issue's targets
(availability >= 85 %, p50 <= 10 m, p95 <= 40 m), which today's snapshot SPP misses.
The second test runs rnx2rtkp (GPS + Galileo + BDS single point) on the same files and
holds bdsfix with settings near RTKLIB's to at least its availability and at most its RMS.

With height aiding and the prediction screen (service.engine.aiding: ``--height-aiding
true --screen-predicted-m 30``,
every epoch of the file solved in order, as ``bdsfix solve`` and the stream do) the drive
meets the issue's targets; the held height is checked against the truth's height, and the
stream (Pipeline) against ``bdsfix solve``'s path.
"""

from __future__ import annotations

import csv
import math
import subprocess
from collections.abc import Iterable
from functools import cache

import numpy as np
import pytest

from drivers.rinex import RinexObsReader
from service.commands.solve import BatchOptions, load_navigation, solve_epochs
from service.core.geometry import ecef_to_geodetic, enu_rotation, geodetic_to_ecef
from service.core.systems import parse_systems
from service.core.types import Fix
from service.engine.aiding import HeightAid
from service.engine.pipeline import Pipeline
from service.engine.solver import SolverConfig, solve
from tests.support.paths import DATA

TST = DATA / "hk-tst-urban-2019"
TRUTH_EPOCHS = 485
AVAILABILITY_MIN = 0.80  # measured 80.4 % (390 of 485)
P50_MAX_M = 15.5  # measured 14.8 m
P95_MAX_M = 112.0  # measured 109.5 m


NAVS = (TST / "hksc1180.19b", TST / "hksc1180.19n")
OBS = TST / "COM3_190428_124409.obs"
DEFAULTS = SolverConfig()
STRICT = SolverConfig(sigma_cn0_m=0.3, max_exclusions=1, p_fa=1e-3)
"""Settings near RTKLIB's single point (bench/bench_vs_rtklib.py STRICT)."""
AIDED = SolverConfig(height_aiding=True, screen_predicted_m=30.0)
"""Height aiding and the prediction screen (bench/bench_vs_rtklib.py AIDED)."""
AIDED_AVAILABILITY_MIN = 0.85  # the issue's targets; measured 90.5 % (439 of 485)
AIDED_P50_MAX_M = 10.0  # measured 8.6 m
AIDED_P95_MAX_M = 40.0  # measured 19.9 m (max 35.3 m)
RTKLIB_CONF = """\
pos1-posmode       =single
pos1-frequency     =l1
pos1-elmask        =10
pos1-ionoopt       =brdc
pos1-tropopt       =saas
pos1-sateph        =brdc
pos1-navsys        =41
pos1-posopt5       =on
out-solformat      =xyz
out-timesys        =gpst
out-timeform       =tow
"""
"""rnx2rtkp as bench/bench_vs_rtklib.py runs it: single point, GPS + Galileo + BDS (navsys
1 + 8 + 32), 10 deg mask, broadcast ionosphere, Saastamoinen, RAIM FDE."""


@cache
def _truth() -> dict[tuple[int, int], np.ndarray]:
    truth = {}
    with open(TST / "groundTruth_TST.csv", encoding="ascii") as f:
        for row in csv.reader(f):
            week, tow, lat, lon, h = (float(v) for v in row[:5])
            truth[(int(week), round(tow))] = geodetic_to_ecef(
                math.radians(lat), math.radians(lon), h
            )
    return truth


@cache
def _errors(cfg: SolverConfig = DEFAULTS) -> tuple[int, np.ndarray, int]:
    """(epochs with truth, 3D errors of the published fixes, fixes outside their HPL)."""
    truth = _truth()
    systems = parse_systems("C,G,E")
    store, iono = load_navigation([str(p) for p in NAVS], systems=systems)
    fixes = (
        solve(ep, store, iono, cfg, "spp")
        for ep in RinexObsReader(OBS, systems=systems)
        if (ep.gpst_week, round(ep.gpst_tow_s)) in truth
    )
    n, errs, outside, _ = _scored(fixes)
    return n, np.asarray(errs), outside


def _scored(fixes: Iterable[Fix]) -> tuple[int, list[float], int, int]:
    """Of ``fixes``, those of the epochs with a truth: how many, the 3D errors of the
    published ones, and how many of those lie outside their HPL (horizontally) and VPL."""
    truth = _truth()
    n, errs, outside, outside_v = 0, [], 0, 0
    for fix in fixes:
        t = truth.get((fix.gpst_week, round(fix.gpst_tow_s)))
        if t is None:
            continue
        n += 1
        if not fix.ok:
            continue
        d = np.subtract(fix.x_ecef_m, t)
        errs.append(float(np.linalg.norm(d)))
        lat, lon, _ = ecef_to_geodetic(t)
        enu = enu_rotation(lat, lon) @ d
        assert fix.hpl_m is not None and fix.vpl_m is not None
        outside += math.hypot(enu[0], enu[1]) > fix.hpl_m
        outside_v += abs(enu[2]) > fix.vpl_m
    return n, errs, outside, outside_v


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


def _rms(errs: np.ndarray) -> float:
    return math.sqrt(float(np.mean(np.square(errs))))


@pytest.mark.slow
@pytest.mark.needs("rnx2rtkp")
def test_strict_settings_fix_as_often_as_rnx2rtkp_and_closer(tmp_path):
    """With settings near RTKLIB's, bdsfix fixes at least as many of the drive's truth
    epochs as rnx2rtkp with GPS + Galileo + BDS and its 3D RMS is no larger (measured:
    199 fixes, 19.24 m against 198, 19.97 m); the defaults publish twice as many fixes with
    a larger RMS (docs/method.md, "Urban drive")."""
    conf, pos = tmp_path / "gec.conf", tmp_path / "gec.pos"
    conf.write_text(RTKLIB_CONF, encoding="ascii")
    cmd = ["rnx2rtkp", "-x", "0", "-k", str(conf), "-o", str(pos), str(OBS), *map(str, NAVS)]
    subprocess.run(cmd, check=True, capture_output=True)
    truth, rtk = _truth(), []
    for line in pos.read_text(encoding="ascii").splitlines():
        if line.startswith("%") or not line.strip():
            continue
        f = line.split()
        t = truth.get((int(f[0]), round(float(f[1]))))
        if t is not None:
            rtk.append(float(np.linalg.norm(np.array([float(v) for v in f[2:5]]) - t)))
    n, mine, _ = _errors(STRICT)
    figures = (len(mine), _rms(mine), len(rtk), _rms(np.asarray(rtk)))
    assert n == TRUTH_EPOCHS and len(rtk) > 0.3 * n, figures
    assert len(mine) >= len(rtk) and _rms(mine) <= _rms(np.asarray(rtk)), figures


@cache
def _aided_fixes() -> tuple[Fix, ...]:
    """``bdsfix solve``'s path (solve_epochs, SPP) with :data:`AIDED`: every epoch of the
    file, in order (the held height needs the fixes before the truth's first epoch too)."""
    systems = parse_systems("C,G,E")
    store, iono = load_navigation([str(p) for p in NAVS], systems=systems)
    opts = BatchOptions(mode="spp", cfg=AIDED, with_sky=False)
    epochs = iter(RinexObsReader(OBS, systems=systems))
    return tuple(fixes[0] for _, fixes in solve_epochs(epochs, store, iono, opts))


@pytest.mark.slow
def test_height_aided_drive_meets_the_issue_targets():
    n, errs, outside, outside_v = _scored(_aided_fixes())
    availability = len(errs) / n
    p50, p95 = np.percentile(errs, [50, 95])
    figures = (availability, p50, p95, max(errs), outside, outside_v)
    assert n == TRUTH_EPOCHS
    assert availability >= AIDED_AVAILABILITY_MIN, figures
    assert p50 <= AIDED_P50_MAX_M and p95 <= AIDED_P95_MAX_M, figures
    assert outside <= 0.01 * len(errs) and outside_v <= 0.01 * len(errs), figures
    # the defaults (snapshot SPP) publish fewer fixes on the same epochs, further off
    _, plain, _ = _errors()
    assert len(plain) < len(errs), figures
    assert p50 < np.percentile(plain, 50) and p95 < np.percentile(plain, 95), figures
    # a fix with a range the screen left out says so
    assert any(
        "longer than predicted" in why for f in _aided_fixes() for why in f.excluded.values()
    )


@pytest.mark.slow
def test_the_held_height_is_honest_against_the_truth():
    """The aid each epoch got (the held height of the fixes before it, as solve_epochs
    keeps it), against the truth's ellipsoidal height, in units of its sigma: measured 68 %
    within 1.17 sigma, 95 % within 1.73, all within 2.02."""
    truth = _truth()
    systems = parse_systems("C,G,E")
    held, ratios = HeightAid(), []
    for ep, fix in zip(RinexObsReader(OBS, systems=systems), _aided_fixes(), strict=True):
        aid = held.prior(ep.gpst_week, ep.gpst_tow_s, AIDED)
        held.update(fix, AIDED)
        t = truth.get((ep.gpst_week, round(ep.gpst_tow_s)))
        if t is not None and aid is not None:
            ratios.append(abs(aid[0] - float(ecef_to_geodetic(t)[2])) / aid[1])
    assert len(ratios) >= 0.95 * TRUTH_EPOCHS, len(ratios)
    p68, p95 = np.percentile(ratios, [68, 95])
    assert p68 <= 1.3 and p95 <= 2.0 and max(ratios) <= 3.0, (p68, p95, max(ratios))


@pytest.mark.slow
def test_the_stream_holds_the_same_height_as_bdsfix_solve():
    """The daemon's Pipeline with height aiding gives the fixes of ``bdsfix solve --mode
    spp`` (every RINEX range is full, so its fast fix is SPP) on every epoch."""
    systems = parse_systems("C,G,E")
    store, iono = load_navigation([str(p) for p in NAVS], systems=systems)
    pipe = Pipeline(store, iono, cfg=AIDED)
    batch = _aided_fixes()
    n = 0
    for ep, ref in zip(RinexObsReader(OBS, systems=systems), batch, strict=True):
        fix = pipe.on_epoch(ep).fix
        # (as many rows: where a system keeps one row, which of its satellites that is has
        # no redundancy to choose by, and the stream's rows come in another order)
        assert fix.ok == ref.ok and len(fix.used) == len(ref.used), (ep.gpst_tow_s, fix.reason)
        if fix.ok:
            assert np.linalg.norm(np.subtract(fix.x_ecef_m, ref.x_ecef_m)) < 1e-6
            n += 1
    assert pipe.counters["height_aided_fixes"] >= n - 10


@pytest.mark.slow
def test_the_batched_aided_solve_is_the_one_epoch_at_a_time_solve_on_the_drive():
    """``bdsfix solve`` solves the aided epochs in batches (solve_aided's fixed point): on
    the drive with :data:`AIDED` (the screen leaving ranges out, fault exclusion at work),
    both solvers, every field of every fix is the one of solving each epoch alone from the
    fixes before it, to the output's bytes (the kernel solving several epochs together
    differs from one alone in the last bits of a float: numpy's stacked products sum in
    another order; the aid, given to 10 cm, does not pass such bits on)."""
    from tests.support.aided import batched_and_alone

    systems = parse_systems("C,G,E")
    store, iono = load_navigation([str(p) for p in NAVS], systems=systems)
    opts = BatchOptions(mode="both", cfg=AIDED, with_sky=False)
    epochs = list(RinexObsReader(OBS, systems=systems))
    got, ref = batched_and_alone(epochs, store, iono, opts)
    assert len(got) == 2 * len(epochs)
    assert got == ref
    assert sum("longer than predicted" in f for f in got) > 10
