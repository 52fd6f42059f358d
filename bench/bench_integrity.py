"""Integrity Monte Carlo: range outliers of 50 m to 150 km on one satellite at a random epoch.

Each trial is one epoch of the virtual receiver (:class:`service.simulator.Simulator`, real
2021 broadcast ephemerides of ../shared/data/hksc-2021, Klobuchar + Saastamoinen + noise) at
a random place in the GEO service area, a random time of the nav file's six hours and a
random receiver clock offset. The receiver view is a restart's: GEOs full (D2 SOW decoded),
each non-GEO full with a per-trial probability in [0, 0.5) (the rest fractional, T = 1 ms).
The epoch is solved by :func:`service.engine.solve` with the daemon's default settings twice:
clean, and with an outlier of log-uniform magnitude (random sign) added to one random
satellite's pseudorange before the receiver reduces it modulo c T.

The true integer of a fractional satellite is the one that brings its measured fractional
value nearest the simulator's outlier-free pseudorange, round((pr_true - z) / cT): known
from the simulator, not from the engine. A published fix (mode fast/spp) with any integer
different from that is a wrong-ambiguity fix (target 0). Availability lost = epochs whose
clean version fixed but whose outlier version was refused.

Run: python bench/bench_integrity.py [--trials N] [--seed S]   (prints figures)
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.constants import C_M_S, is_geo  # noqa: E402
from service.engine import IonoSet, SolverConfig, solve  # noqa: E402
from service.ephemeris import EphemerisStore  # noqa: E402
from service.simulator import SimConfig, Simulator  # noqa: E402
from service.timebase import bdt_to_gpst  # noqa: E402
from service.types import Ephemeris, KlobucharParams, MeasurementEpoch  # noqa: E402

NAV = ROOT.parent / "shared" / "data" / "hksc-2021" / "hksc1610.nav"
CT_M = C_M_S * 1e-3
OUTLIER_M = (50.0, 150e3)
BDT_WEEK = 805
SOW_SPAN_S = (349200.0, 363600.0)  # toes common to the GEOs in the nav file
BINS_M = (50.0, 300.0, 1e3, 5e3, 30e3, 150e3)


@dataclass
class Tally:
    trials: int = 0
    clean_fixes: int = 0
    clean_wrong_ambiguity: int = 0
    outlier_fixes: int = 0
    outlier_wrong_ambiguity: int = 0
    outlier_refusals: int = 0
    availability_lost: int = 0  # clean fixed, outlier refused
    max_err_clean_m: float = 0.0
    max_err_outlier_m: float = 0.0
    err_outlier_m: list[float] = field(default_factory=list)
    by_bin: Counter[str] = field(default_factory=Counter)
    reasons: Counter[str] = field(default_factory=Counter)
    wrong: list[str] = field(default_factory=list)


def load_nav() -> tuple[list[Ephemeris], EphemerisStore, KlobucharParams | None]:
    from drivers.rinex import read_nav

    nav = read_nav(NAV)
    ephs = [e for items in nav.ephemerides.values() for e in items if e.health == 0]
    store = EphemerisStore()
    store.add_all(ephs)
    return ephs, store, nav.iono_bds


def _view(prn: list[str], pr_m: np.ndarray, full: np.ndarray, week: int, tow: float):
    frac = np.mod(pr_m, CT_M)
    return MeasurementEpoch.from_columns(
        week,
        tow,
        prn,
        ["2I"] * len(prn),
        np.where(full, pr_m, np.nan),
        frac_pr_m=np.where(full, np.nan, frac),
        period_s=0.001,
    )


def _bin(d_m: float) -> str:
    for lo, hi in itertools.pairwise(BINS_M):
        if lo <= abs(d_m) < hi:
            return f"{lo:g}-{hi:g} m"
    return f"{BINS_M[-2]:g}-{BINS_M[-1]:g} m"


def _wrong(fix, pr_true: np.ndarray, z: np.ndarray, prn: list[str]) -> list[str]:
    bad = []
    for p, n in fix.ambiguity.items():
        i = prn.index(p)
        if n != round((pr_true[i] - z[i]) / CT_M):
            bad.append(p)
    return bad


def run_trials(
    n: int,
    seed: int = 1,
    nav: tuple[list[Ephemeris], EphemerisStore, KlobucharParams | None] | None = None,
    cfg: SolverConfig | None = None,
) -> Tally:
    ephs, store, iono = nav or load_nav()
    ionoset = IonoSet(bds=iono)
    cfg = cfg or SolverConfig()  # the daemon's defaults: 10 deg mask, derived beta, corrections
    rng = np.random.default_rng(seed)
    t = Tally()
    for k in range(n):
        week, tow = bdt_to_gpst(BDT_WEEK, float(rng.uniform(*SOW_SPAN_S)))
        sim = Simulator(
            ephs,
            SimConfig(
                lat_deg=float(rng.uniform(-10.0, 50.0)),
                lon_deg=float(rng.uniform(85.0, 145.0)),
                alt_m=float(rng.uniform(0.0, 2000.0)),
                start_gpst_week=week,
                start_gpst_tow_s=tow,
                duration_s=1.0,
                rate_hz=1.0,
                clock_offset_s=float(rng.uniform(-0.5, 0.5)),
                seed=seed * 1_000_003 + k,
            ),
            iono,
        )
        ep = next(iter(sim.epochs()))
        prn = list(ep.prn)
        pr_true = np.asarray(ep.pr_m, dtype=float)
        p_full = float(rng.uniform(0.0, 0.5))
        full = np.array([is_geo(p) or bool(rng.random() < p_full) for p in prn])
        t.trials += 1
        clean = solve(
            _view(prn, pr_true, full, ep.tag_gpst_week, ep.tag_gpst_tow_s), store, ionoset, cfg
        )
        truth = ep.truth_x_ecef_m
        if clean.ok:
            t.clean_fixes += 1
            t.max_err_clean_m = max(
                t.max_err_clean_m, float(np.linalg.norm(np.subtract(clean.x_ecef_m, truth)))
            )
            if _wrong(clean, pr_true, np.mod(pr_true, CT_M), prn):
                t.clean_wrong_ambiguity += 1
        j = int(rng.integers(len(prn)))
        d = math.exp(rng.uniform(*np.log(OUTLIER_M))) * float(rng.choice([-1.0, 1.0]))
        pr = pr_true.copy()
        pr[j] += d
        fix = solve(_view(prn, pr, full, ep.tag_gpst_week, ep.tag_gpst_tow_s), store, ionoset, cfg)
        kind = "full" if full[j] else "frac"
        if fix.ok:
            t.outlier_fixes += 1
            t.by_bin[f"fix {kind} {_bin(d)}"] += 1
            err = float(np.linalg.norm(np.subtract(fix.x_ecef_m, truth)))
            t.max_err_outlier_m = max(t.max_err_outlier_m, err)
            t.err_outlier_m.append(err)
            bad = _wrong(fix, pr_true, np.mod(pr, CT_M), prn)
            if bad:
                t.outlier_wrong_ambiguity += 1
                t.wrong.append(
                    f"trial {k}: outlier {d:+.0f} m on {prn[j]} ({kind}); wrong N on "
                    f"{','.join(bad)}; error {err:.0f} m, resid rms {fix.resid_rms_m:.1f} m"
                )
        else:
            t.outlier_refusals += 1
            t.by_bin[f"refused {kind} {_bin(d)}"] += 1
            t.reasons[(fix.reason or "").split(":")[0]] += 1
            if clean.ok:
                t.availability_lost += 1
    return t


def hksc_restarts(instants_s: list[float], jobs: int = 2) -> list[tuple[float, int, int, int]]:
    """`bdsfix replay` of the real HKSC capture restarted at each instant (seed = index):
    (instant, fast fixes, D1 SOW integrity checks, failures) from the run's counters."""
    import re
    import subprocess
    from concurrent.futures import ThreadPoolExecutor

    hk = NAV.parent

    def one(item: tuple[int, float]) -> tuple[float, int, int, int]:
        seed, t_s = item
        res = subprocess.run(
            [
                sys.executable,
                "-m",
                "service.cli",
                "replay",
                str(hk / "hksc1610.obs"),
                "--nav",
                str(NAV),
                "--restart-at",
                str(t_s),
                "--seed",
                str(seed),
                "--max-speed",
                "--nmea-out",
                "/dev/null",
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        )
        m = re.search(r"fixes fast (\d+).*integrity checks (\d+), failures (\d+)", res.stderr)
        if m is None:
            raise RuntimeError(res.stderr)
        fast, checks, failures = map(int, m.groups())
        return t_s, fast, checks, failures

    with ThreadPoolExecutor(jobs) as pool:
        return list(pool.map(one, enumerate(instants_s)))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=20000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--no-hksc", action="store_true", help="skip the HKSC restart replays")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    t = run_trials(a.trials, a.seed)
    dt = time.perf_counter() - t0
    print(f"bench_integrity: {t.trials} trials in {dt:.1f} s ({1e3 * dt / t.trials:.1f} ms each)")
    print(
        f"  clean epochs: {t.clean_fixes} fixes ({100 * t.clean_fixes / t.trials:.1f} %), "
        f"wrong-ambiguity {t.clean_wrong_ambiguity}, max error {t.max_err_clean_m:.1f} m"
    )
    print(
        f"  with outlier: {t.outlier_fixes} fixes published, wrong-ambiguity "
        f"{t.outlier_wrong_ambiguity}, refusals {t.outlier_refusals}, availability lost "
        f"{t.availability_lost} ({100 * t.availability_lost / max(t.clean_fixes, 1):.1f} % of "
        f"clean fixes), max error of published fixes {t.max_err_outlier_m:.1f} m"
    )
    e = np.asarray(t.err_outlier_m)
    if e.size:
        print(
            f"  position error of fixes published with an outlier: p50 {np.median(e):.1f} m, "
            f"p99 {np.percentile(e, 99):.1f} m; > 100 m: {int((e > 100).sum())}, "
            f"> 1 km: {int((e > 1000).sum())}"
        )
    print("  by outlier magnitude (satellite full or fractional):")
    for key in sorted(t.by_bin, key=lambda s: (s.split()[1], float(s.split()[2].split("-")[0]))):
        print(f"    {key:<28} {t.by_bin[key]}")
    print(f"  refusal reasons: {dict(t.reasons)}")
    for line in t.wrong[:20]:
        print("  WRONG " + line)
    if a.no_hksc:
        return
    runs = hksc_restarts([5.0 + 10.0 * i for i in range(19)])
    print(f"HKSC 2021 replay, restarts at {runs[0][0]:g}..{runs[-1][0]:g} s ({len(runs)} runs):")
    for t_s, fast, checks, failures in runs:
        print(
            f"  restart {t_s:5.0f} s: fast fixes {fast:3d}, D1 SOW checks {checks:3d}, "
            f"mismatches {failures}"
        )
    print(
        f"  total: fast fixes {sum(r[1] for r in runs)}, recovered integers confirmed "
        f"{sum(r[2] - r[3] for r in runs)} of {sum(r[2] for r in runs)}, mismatches "
        f"{sum(r[3] for r in runs)}"
    )


if __name__ == "__main__":
    main()
