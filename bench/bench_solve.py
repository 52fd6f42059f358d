"""Benchmark: per-epoch fast-fix and SPP solve time on HKSC, and `bdsfix solve` throughput.

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
from service.batch import load_navigation  # noqa: E402
from service.engine import fractionalize, solve  # noqa: E402

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


def throughput() -> None:
    cmd = [
        sys.executable,
        "-m",
        "service.cli",
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
    throughput()
