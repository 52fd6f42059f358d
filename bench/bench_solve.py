"""Benchmark: per-epoch fast-fix and SPP solve time on HKSC, the cost of fault detection and
exclusion (FDE) with and without a fault, and `bdsfix solve` throughput.

Run: python bench/bench_solve.py   (prints figures; no assertions)
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.rinex import RinexObsReader  # noqa: E402
from service.commands.solve import load_navigation  # noqa: E402
from service.engine.solver import fractionalize, solve  # noqa: E402

HKSC = ROOT.parent / "shared" / "data" / "hksc-2021"


def per_epoch(repeats: int = 5) -> None:
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    epochs = list(RinexObsReader(HKSC / "hksc1610.obs"))
    frac = [fractionalize(e) for e in epochs]
    for name, data, solver in (("fast", frac, "fast"), ("spp", epochs, "spp")):
        times = []
        for _ in range(repeats):
            for ep in data:
                t0 = time.perf_counter()
                solve(ep, store, iono, solver=solver)
                times.append(time.perf_counter() - t0)
        ms = np.array(times) * 1e3
        print(
            f"{name:>4} solve per epoch: median {np.median(ms):.2f} ms, "
            f"p99 {np.percentile(ms, 99):.2f} ms over {len(ms)} solves "
            f"({len(epochs[0].prn)} sats in the first epoch)"
        )


def fde_cost(repeats: int = 3) -> None:
    """Solve time per epoch clean (the chi-square test runs, nothing is excluded) and with a
    1 km error on one GEO or one non-GEO (the test fails and every used satellite is
    excluded in turn), and clean with the test and exclusion off."""
    from dataclasses import replace

    from service.core.bds import is_geo
    from service.core.constants import C_M_S
    from service.engine.solver import SolverConfig

    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    epochs = list(RinexObsReader(HKSC / "hksc1610.obs"))

    def faulted(ep, geo: bool):
        i = next(k for k, p in enumerate(ep.prn) if is_geo(p) == geo)
        pr = ep.pr_m.copy()
        pr[i] += 1000.0
        return replace(ep, pr_m=pr, frac_pr_m=np.mod(pr, C_M_S * 1e-3))

    off = SolverConfig(p_fa=0.0, max_exclusions=0)
    cases = (
        ("clean, FDE off", None, off),
        ("clean, FDE on", None, SolverConfig()),
        ("1 km on a GEO", True, SolverConfig()),
        ("1 km on a non-GEO", False, SolverConfig()),
    )
    for solver in ("fast", "spp"):
        for label, geo, cfg in cases:
            times = []
            data = [e if geo is None else faulted(e, geo) for e in epochs[::4]]
            if solver == "fast":
                data = [fractionalize(e) for e in data]
            for _ in range(repeats):
                for ep in data:
                    t0 = time.perf_counter()
                    fix = solve(ep, store, iono, cfg, solver=solver)
                    times.append(time.perf_counter() - t0)
                    assert fix.ok, fix.reason
            ms = np.array(times) * 1e3
            print(
                f"{solver:>4} {label:<18}: median {np.median(ms):6.2f} ms, "
                f"p99 {np.percentile(ms, 99):6.2f} ms ({len(ms)} solves)"
            )


def throughput() -> None:
    cmd = [
        sys.executable,
        "-m",
        "service",
        "solve",
        str(HKSC / "hksc1610.obs"),
        str(HKSC / "hksc1610.nav"),
        "--mode",
        "both",
        "--out",
        "/dev/null",
    ]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, cwd=ROOT, capture_output=True)
    wall = time.perf_counter() - t0
    print(
        f"bdsfix solve --mode both on 205 HKSC epochs: {wall:.2f} s wall "
        f"({205 / wall:.0f} epochs/s incl. start-up)"
    )


if __name__ == "__main__":
    per_epoch()
    fde_cost()
    throughput()
