"""Integrity Monte Carlo: single and dual range faults of 10 m to 150 km on simulated epochs.

Each trial is one epoch of the virtual receiver (:class:`service.sim.simulator.Simulator`, real
2021 broadcast ephemerides of ../shared/data/hksc-2021, Klobuchar + Saastamoinen + 1.3 m
noise) at one of five places in the >= 4-GEO area (Beijing, Hong Kong, Singapore, Sydney,
Tokyo), a random time of the nav file's six hours and a random receiver clock offset.
Both solvers run with the daemon's defaults (10 deg mask, error model, chi-square test at
P_fa 1e-5, up to 2 exclusions, protection levels at P_md 1e-3):

- fast: a restart's view: GEOs full (D2 SOW decoded), each non-GEO full with a per-trial
  probability in [0, 0.5), the rest fractional (T = 1 ms);
- spp: every measurement full.

Each view is solved clean and with a fault: one satellite (single, 70 % of the trials) or
two (dual), chosen at random, each biased by a log-uniform magnitude with a random sign,
added before the receiver reduces a fractional range modulo c T.

Counted per solver and fault kind, against the simulator's truth (never the engine's):
- PL exceeded: a published fix whose horizontal error exceeds its HPL or whose vertical
  error exceeds its VPL (target 0 for single faults);
- wrong integer: a published fast fix with any integer different from
  round((pr_true - z) / cT), z the fractional value it solved with (target 0);
- availability lost: the clean epoch fixed, the faulted one was declined;
- faulty satellite excluded / used; false exclusions on the clean epochs.

Run: python bench/bench_integrity.py [--trials N] [--seed S] [--jobs J]   (prints figures)
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
import time
from collections import Counter
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.core.constants import C_M_S, is_geo  # noqa: E402
from service.core.ephemeris import EphemerisStore  # noqa: E402
from service.core.geometry import ecef_to_geodetic, enu_rotation  # noqa: E402
from service.core.timebase import bdt_to_gpst  # noqa: E402
from service.core.types import Ephemeris, Fix, KlobucharParams, MeasurementEpoch  # noqa: E402
from service.engine.solver import IonoSet, SolverConfig, solve  # noqa: E402
from service.sim.simulator import SimConfig, Simulator  # noqa: E402

NAV = ROOT.parent / "shared" / "data" / "hksc-2021" / "hksc1610.nav"
CT_M = C_M_S * 1e-3
FAULT_M = (10.0, 150e3)
BDT_WEEK = 805
SOW_SPAN_S = (349200.0, 363600.0)  # toes common to the GEOs in the nav file
PLACES = {
    "Beijing": (39.9, 116.4),
    "Hong Kong": (22.3, 114.2),
    "Singapore": (1.35, 103.8),
    "Sydney": (-33.9, 151.2),
    "Tokyo": (35.7, 139.7),
}
BINS_M = (10.0, 30.0, 100.0, 300.0, 1e3, 1e4, 150e3)
DUAL_SHARE = 0.3

Nav = tuple[list[Ephemeris], EphemerisStore, KlobucharParams | None]


@dataclass
class Tally:
    """One solver under one fault kind (single or dual)."""

    trials: int = 0
    clean_fixes: int = 0
    clean_false_exclusions: int = 0
    clean_pl_exceeded: int = 0
    fixes: int = 0
    untested_fixes: int = 0
    declines: int = 0
    availability_lost: int = 0
    pl_exceeded: int = 0
    wrong_integer: int = 0
    faulty_all_excluded: int = 0
    faulty_used: int = 0
    max_err_m: float = 0.0
    max_err_over_pl: float = 0.0
    fixes_by_bin: Counter[str] = field(default_factory=Counter)
    declines_by_bin: Counter[str] = field(default_factory=Counter)
    reasons: Counter[str] = field(default_factory=Counter)
    notes: list[str] = field(default_factory=list)

    def merge(self, other: Tally) -> None:
        for name, value in vars(other).items():
            mine = getattr(self, name)
            if name == "max_err_m" or name == "max_err_over_pl":
                setattr(self, name, max(mine, value))
            elif isinstance(value, Counter | list):
                mine += value  # type: ignore[operator]
            else:
                setattr(self, name, mine + value)


def load_nav() -> Nav:
    from drivers.rinex import read_nav

    nav = read_nav(NAV)
    ephs = [e for items in nav.ephemerides.values() for e in items if e.health == 0]
    store = EphemerisStore()
    store.add_all(ephs)
    return ephs, store, nav.iono_bds


def _view(prn: list[str], pr_m: np.ndarray, full: np.ndarray, week: int, tow: float):
    return MeasurementEpoch.from_columns(
        week,
        tow,
        prn,
        ["2I"] * len(prn),
        np.where(full, pr_m, np.nan),
        frac_pr_m=np.where(full, np.nan, np.mod(pr_m, CT_M)),
        period_s=0.001,
    )


def _bin(d_m: float) -> str:
    for lo, hi in itertools.pairwise(BINS_M):
        if lo <= abs(d_m) < hi:
            return f"{lo:g}-{hi:g} m"
    return f"{BINS_M[-2]:g}-{BINS_M[-1]:g} m"


def wrong_integers(fix: Fix, pr_true: np.ndarray, z: np.ndarray, prn: list[str]) -> list[str]:
    """Satellites whose published integer does not restore the true pseudorange."""
    return [
        p
        for p, n in fix.ambiguity.items()
        if n != round((pr_true[prn.index(p)] - z[prn.index(p)]) / CT_M)
    ]


def pl_ratio(fix: Fix, truth: np.ndarray) -> float:
    """max(horizontal error / HPL, |vertical error| / VPL) of a fix with finite levels."""
    lat, lon, _ = ecef_to_geodetic(truth)
    e = enu_rotation(lat, lon) @ np.subtract(fix.x_ecef_m, truth)
    return max(math.hypot(e[0], e[1]) / fix.hpl_m, abs(e[2]) / fix.vpl_m)  # type: ignore[operator]


def _judge(
    t: Tally,
    clean: Fix,
    fix: Fix,
    truth: np.ndarray,
    faulty: list[str],
    mags: list[float],
    pr_true: np.ndarray,
    z: np.ndarray,
    prn: list[str],
    label: str,
) -> None:
    t.trials += 1
    if clean.ok:
        t.clean_fixes += 1
        t.clean_false_exclusions += bool(clean.excluded)
        if clean.hpl_m is not None and math.isfinite(clean.hpl_m) and pl_ratio(clean, truth) > 1:
            t.clean_pl_exceeded += 1
    key = _bin(max(mags, key=abs))
    if not fix.ok:
        t.declines += 1
        t.declines_by_bin[key] += 1
        t.reasons[fix.reason_code or "?"] += 1
        t.availability_lost += clean.ok
        return
    t.fixes += 1
    t.fixes_by_bin[key] += 1
    err = float(np.linalg.norm(np.subtract(fix.x_ecef_m, truth)))
    t.max_err_m = max(t.max_err_m, err)
    if all(p in fix.excluded for p in faulty):
        t.faulty_all_excluded += 1
    if any(p in fix.used for p in faulty):
        t.faulty_used += 1
    if fix.chi2 is None:
        t.untested_fixes += 1
    elif fix.hpl_m is not None and math.isfinite(fix.hpl_m):
        ratio = pl_ratio(fix, truth)
        t.max_err_over_pl = max(t.max_err_over_pl, ratio)
        if ratio > 1.0:
            t.pl_exceeded += 1
            t.notes.append(
                f"{label}: PL exceeded x{ratio:.2f}: faults "
                f"{', '.join(f'{p} {m:+.0f} m' for p, m in zip(faulty, mags, strict=True))}; "
                f"excluded {sorted(fix.excluded)}; error {err:.1f} m"
            )
    bad = wrong_integers(fix, pr_true, z, prn)
    if bad:
        t.wrong_integer += 1
        t.notes.append(f"{label}: wrong integer on {','.join(bad)}; error {err:.0f} m")


def run_trials(
    n: int,
    seed: int = 1,
    nav: Nav | None = None,
    cfg: SolverConfig | None = None,
    dual_share: float = DUAL_SHARE,
) -> dict[str, Tally]:
    """``n`` trials; tallies keyed ``"<solver> <single|dual>"``."""
    ephs, store, iono = nav or load_nav()
    ionoset = IonoSet(bds=iono)
    cfg = cfg or SolverConfig()  # the daemon's defaults
    rng = np.random.default_rng(seed)
    out = {f"{s} {k}": Tally() for s in ("fast", "spp") for k in ("single", "dual")}
    names = sorted(PLACES)
    for k in range(n):
        place = names[int(rng.integers(len(names)))]
        lat, lon = PLACES[place]
        week, tow = bdt_to_gpst(BDT_WEEK, float(rng.uniform(*SOW_SPAN_S)))
        sim = Simulator(
            ephs,
            SimConfig(
                lat_deg=lat + float(rng.uniform(-1.0, 1.0)),
                lon_deg=lon + float(rng.uniform(-1.0, 1.0)),
                alt_m=float(rng.uniform(0.0, 500.0)),
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
        restart = np.array([is_geo(p) or bool(rng.random() < p_full) for p in prn])
        kind = "dual" if rng.random() < dual_share else "single"
        idx = rng.choice(len(prn), size=2 if kind == "dual" else 1, replace=False)
        mags = [
            math.exp(rng.uniform(*np.log(FAULT_M))) * float(rng.choice([-1.0, 1.0])) for _ in idx
        ]
        pr = pr_true.copy()
        pr[idx] += mags
        faulty = [prn[i] for i in idx]
        week_tag, tow_tag = ep.tag_gpst_week, ep.tag_gpst_tow_s
        for solver, full in (("fast", restart), ("spp", np.ones(len(prn), dtype=bool))):
            clean = solve(_view(prn, pr_true, full, week_tag, tow_tag), store, ionoset, cfg, solver)
            fix = solve(_view(prn, pr, full, week_tag, tow_tag), store, ionoset, cfg, solver)
            _judge(
                out[f"{solver} {kind}"],
                clean,
                fix,
                ep.truth_x_ecef_m,
                faulty,
                mags,
                pr_true,
                np.mod(pr, CT_M),
                prn,
                f"trial {k} {place} {solver}",
            )
    return out


def _chunk(args: tuple[int, int]) -> dict[str, Tally]:
    n, seed = args
    return run_trials(n, seed)


def run_parallel(n: int, seed: int, jobs: int) -> dict[str, Tally]:
    parts = [(n // jobs + (1 if j < n % jobs else 0), seed * 100 + j) for j in range(jobs)]
    with ProcessPoolExecutor(jobs) as pool:
        results = list(pool.map(_chunk, parts))
    total = results[0]
    for r in results[1:]:
        for key, tally in r.items():
            total[key].merge(tally)
    return total


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
                sys.executable, "-m", "service", "replay", str(hk / "hksc1610.obs"),
                "--nav", str(NAV), "--restart-at", str(t_s), "--seed", str(seed),
                "--max-speed", "--nmea-out", "/dev/null",
            ],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
        )  # fmt: skip
        m = re.search(r"fixes fast (\d+).*integrity checks (\d+), failures (\d+)", res.stderr)
        if m is None:
            raise RuntimeError(res.stderr)
        fast, checks, failures = map(int, m.groups())
        return t_s, fast, checks, failures

    with ThreadPoolExecutor(jobs) as pool:
        return list(pool.map(one, enumerate(instants_s)))


def report(tallies: dict[str, Tally]) -> None:
    for key, t in tallies.items():
        if not t.trials:
            continue
        print(
            f"  {key:<11} trials {t.trials:5d}: clean fixes {t.clean_fixes} (false exclusions "
            f"{t.clean_false_exclusions}, PL exceeded {t.clean_pl_exceeded}); faulted: fixes "
            f"{t.fixes} (untested {t.untested_fixes}), declines {t.declines}, availability lost "
            f"{t.availability_lost} ({100 * t.availability_lost / max(t.clean_fixes, 1):.1f} %)"
        )
        print(
            f"  {'':<11} PL exceeded {t.pl_exceeded}, wrong integer {t.wrong_integer}, faulty "
            f"satellite(s) excluded in {t.faulty_all_excluded} fixes, used in {t.faulty_used}; "
            f"max error {t.max_err_m:.1f} m, max error / PL {t.max_err_over_pl:.2f}"
        )
        bins = sorted(
            set(t.fixes_by_bin) | set(t.declines_by_bin), key=lambda s: float(s.split("-")[0])
        )
        print(
            f"  {'':<11} by largest fault: "
            + "; ".join(f"{b} {t.fixes_by_bin[b]}/{t.declines_by_bin[b]}" for b in bins)
            + " (fixes/declines)"
        )
        if t.reasons:
            print(f"  {'':<11} decline reasons: {dict(t.reasons)}")
        for line in t.notes[:10]:
            print(f"  {'':<11} NOTE {line}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10_000)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--no-hksc", action="store_true", help="skip the HKSC restart replays")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    tallies = run_parallel(a.trials, a.seed, a.jobs) if a.jobs > 1 else run_trials(a.trials, a.seed)
    dt = time.perf_counter() - t0
    print(
        f"bench_integrity: {a.trials} trials ({1 - DUAL_SHARE:.0%} single, {DUAL_SHARE:.0%} dual "
        f"faults of {FAULT_M[0]:g} m to {FAULT_M[1] / 1e3:g} km) at {', '.join(PLACES)}, "
        f"{dt:.1f} s on {a.jobs} process(es)"
    )
    report(tallies)
    if a.no_hksc:
        return
    runs = hksc_restarts([5.0 + 10.0 * i for i in range(19)])
    print(f"HKSC 2021 replay, restarts at {runs[0][0]:g}..{runs[-1][0]:g} s ({len(runs)} runs):")
    print(
        f"  total: fast fixes {sum(r[1] for r in runs)}, recovered integers confirmed "
        f"{sum(r[2] - r[3] for r in runs)} of {sum(r[2] for r in runs)}, mismatches "
        f"{sum(r[3] for r in runs)}"
    )


if __name__ == "__main__":
    main()
