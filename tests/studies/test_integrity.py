"""Integrity: no published fix is wrong beyond its protection level, and none carries a
wrong integer ambiguity.

1. Monte Carlo on the virtual receiver (real 2021 broadcast ephemerides, five places in the
   >= 4-GEO area): single and dual range faults of 10 m to 150 km. The truth (position and
   integers) comes from the simulator, never from the engine (service.studies.integrity;
   bench/bench_integrity.py runs the large version and prints the figures).
2. The real HKSC replay with emulated restarts at several instants: every ambiguity the fast
   fix recovered is confirmed by the satellite's later D1 SOW (the pipeline's check), read
   from the STATUS counters a ZeroMQ subscriber receives from `bdsfix replay`.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

from drivers.rinex import read_nav
from service.core.types import Fix
from service.engine.solver import SolverConfig
from service.studies.integrity import pl_ratio, prepare_nav, run_trials, wrong_integers
from tests.support.paths import DATA, ROOT
from tests.support.replay import LiveReplay, StatusRun

HK = DATA / "hksc-2021"


@pytest.fixture(scope="module")
def nav():
    nav = read_nav(HK / "hksc1610.nav")
    return prepare_nav((e for items in nav.ephemerides.values() for e in items), nav.iono_bds)


@pytest.mark.slow
def test_monte_carlo_faults_stay_within_protection_levels(nav):
    tallies = run_trials(500, seed=3, nav=nav)
    for key, t in tallies.items():
        assert t.trials > 100, key
        assert t.wrong_integer == 0, (key, t.notes)
        assert t.clean_fixes >= 0.97 * t.trials, key  # places where the fast fix works
        assert t.clean_false_exclusions <= 0.005 * t.clean_fixes, key
        assert t.clean_pl_exceeded == 0, key
        # not vacuous: faults were excluded and published fixes were judged against levels
        assert t.faulty_all_excluded > 0.5 * t.fixes and t.max_err_over_pl > 0.0, key
    for solver in ("fast", "spp"):
        single = tallies[f"{solver} single"]
        assert single.pl_exceeded == 0, single.notes
        assert single.availability_lost <= 0.05 * single.clean_fixes, solver
        # faults of every size were drawn, small ones published (absorbed), large ones
        # excluded
        assert single.fixes_by_bin["10-30 m"] > 0 and single.fixes_by_bin["10000-150000 m"] > 0


def test_monte_carlo_counts_wrong_integers_when_the_test_is_off(nav):
    """The counter is live: without the chi-square test, faults do yield wrong integers."""
    tallies = run_trials(600, seed=11, nav=nav, cfg=SolverConfig(p_fa=0.0))
    assert tallies["fast single"].wrong_integer + tallies["fast dual"].wrong_integer >= 2


def test_monte_carlo_judges_against_the_truth():
    truth = np.array([-2414266.9197, 5386768.9868, 2407460.0314])
    up = truth / np.linalg.norm(truth)
    fix = Fix(
        solver="spp", mode="spp", gpst_week=0, gpst_tow_s=0.0,
        x_ecef_m=tuple(truth + 12.0 * up), hpl_m=5.0, vpl_m=6.0,
    )  # fmt: skip
    assert pl_ratio(fix, truth) == pytest.approx(2.0, rel=1e-3)  # 12 m up against VPL 6 m
    ct = 299_792_458.0 * 1e-3
    pr = np.array([21_000_123.4, 25_500_987.6])
    z = np.mod(pr, ct)
    ok = Fix(solver="fast", mode="fast", gpst_week=0, gpst_tow_s=0.0, ambiguity={"C06": 85})
    assert wrong_integers(ok, pr, z, ["C01", "C06"]) == []
    bad = Fix(solver="fast", mode="fast", gpst_week=0, gpst_tow_s=0.0, ambiguity={"C06": 84})
    assert wrong_integers(bad, pr, z, ["C01", "C06"]) == ["C06"]


RESTARTS = [(5.0, 0), (40.0, 1), (80.0, 2), (120.0, 3), (160.0, 4), (185.0, 5)]


def test_hksc_restarts_every_recovered_ambiguity_confirmed_by_d1_sow():
    def replay(restart_s: float, seed: int) -> StatusRun:
        args = ["replay", str(HK / "hksc1610.obs"), "--nav", str(HK / "hksc1610.nav")]
        args += ["--restart-at", str(restart_s), "--seed", str(seed), "--speed", "100"]
        with LiveReplay([*args, "--nmea-out", "/dev/null"]) as run:
            return run.finish()

    with ThreadPoolExecutor(max_workers=len(RESTARTS)) as pool:
        runs = list(pool.map(lambda rs: replay(*rs), RESTARTS))
    total_checks = 0
    for (restart_s, _), run in zip(RESTARTS, runs, strict=True):
        err = run.stderr
        assert run.rc == 0, err
        final = run.final["counters"]
        summary = re.search(r"fixes fast (\d+).*integrity checks (\d+), failures (\d+)", err)
        assert summary, err
        fast, checks, failures = map(int, summary.groups())
        assert final.get("fix_fast", 0) == fast > 0, (restart_s, final)
        assert final.get("integrity_checks", 0) == checks > 0, (restart_s, final)
        assert final.get("integrity_failures", 0) == failures == 0, (restart_s, final)
        # every non-GEO whose integer was recovered after the restart was checked
        assert checks >= 5, (restart_s, checks)
        total_checks += checks
    assert total_checks >= 6 * 5


def test_hksc_restart_jsonl_integers_match_the_full_pseudoranges(tmp_path):
    """Independently of the pipeline's check: every integer of every BeiDou fast fix,
    applied to the epoch's fractional value, gives the RINEX full pseudorange within
    c T / 2 (georinex's B1I C2I; the integers of every system, each with its own code
    period, are checked in tests/commands/test_solve_real.py)."""
    import georinex

    out = tmp_path / "fixes.jsonl"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "service",
            "replay",
            str(HK / "hksc1610.obs"),
            "--nav",
            str(HK / "hksc1610.nav"),
            "--restart-at",
            "60",
            "--systems",
            "C",
            "--max-speed",
            "--jsonl-out",
            str(out),
        ],
        cwd=ROOT,
        capture_output=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    fixes = [
        r
        for r in map(json.loads, out.read_text().splitlines())
        if r["class"] == "FIX" and r["mode"] == "fast"
    ]
    assert fixes
    obs = georinex.load(HK / "hksc1610.obs", use="C", meas=["C2I"])
    row_of = {round(_tow(t)): i for i, t in enumerate(obs.time.values)}
    svs = [str(s) for s in obs.sv.values]
    c2i = obs["C2I"].values  # (time, sv)
    ct = 299_792_458.0 * 1e-3
    n_checked = 0
    for f in fixes:
        row = row_of[round(f["gpst_tow_s"])]
        # a coarse-time fix of all-fractional ranges claims no absolute integer
        for prn, n in f.get("ambiguity", {}).items():
            pr = float(c2i[row, svs.index(prn)])
            z = pr % ct  # the fractional value the replay solved with
            assert round((pr - z) / ct) == n, (f["gpst_tow_s"], prn, n)
            n_checked += 1
    assert n_checked >= 20


def _tow(t64) -> float:
    import numpy as np

    gps0 = np.datetime64("1980-01-06T00:00:00", "ns")
    ns = (np.datetime64(t64, "ns") - gps0) / np.timedelta64(1, "ns")
    return float(ns / 1e9) % 604800.0
