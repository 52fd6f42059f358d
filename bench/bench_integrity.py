"""Integrity Monte Carlo figures (the study: :mod:`service.studies.integrity`), on the real
2021 broadcast ephemerides of hksc-2021, plus HKSC emulated restarts whose recovered integers
are checked at the D1 SOW.

Run: python bench/bench_integrity.py [--trials N] [--seed S] [--jobs J]   (prints figures)
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.studies.integrity import (  # noqa: E402
    DUAL_SHARE,
    FAULT_M,
    PLACES,
    Nav,
    Tally,
    prepare_nav,
    run_trials,
)

NAV = ROOT.parent / "shared" / "data" / "hksc-2021" / "hksc1610.nav"


def load_nav() -> Nav:
    from drivers.rinex import read_nav

    nav = read_nav(NAV)
    return prepare_nav((e for items in nav.ephemerides.values() for e in items), nav.iono_bds)


def _chunk(args: tuple[int, int]) -> dict[str, Tally]:
    n, seed = args
    return run_trials(n, load_nav(), seed)


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
    tallies = (
        run_parallel(a.trials, a.seed, a.jobs)
        if a.jobs > 1
        else run_trials(a.trials, load_nav(), a.seed)
    )
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
