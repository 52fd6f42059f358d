"""Benchmark: `bdsfix coverage` with defaults, against a straightforward per-epoch numpy loop.

Run: python bench/bench_coverage.py   (prints figures; no assertions)
The baseline processes every grid point each epoch with einsum-built normal matrices and
batched numpy.linalg.inv; it is timed on a subsample of epochs and extrapolated.
"""

from __future__ import annotations

import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.coverage import CoverageConfig, run_coverage
from service.geometry import geodetic_to_ecef
from service.keplerian import table1_ephemerides
from service.orbit import EphemerisArrays, sat_pos_clock


def baseline_seconds(n_sample: int = 24) -> float:
    cfg = CoverageConfig()
    ephs = [e for e in table1_ephemerides(0.0) if e.prn in ("C01", "C02", "C03", "C04", "C05")]
    arr = EphemerisArrays.from_ephemerides(ephs)
    lats = np.radians(np.arange(-90.0, 90.1, 1.0))
    lons = np.radians(np.arange(-180.0, 180.0, 1.0))
    la, lo = np.meshgrid(lats, lons, indexing="ij")
    up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1).reshape(-1, 3)
    n_ep = int(cfg.days * 86400 / cfg.step_s)
    t0 = time.perf_counter()
    for k in range(n_sample):
        pos, _ = sat_pos_clock(arr, ephs[0].week, np.full(5, ephs[0].toe_sow_s + k * 300.0))
        for alt in cfg.altitudes_m:
            x = geodetic_to_ecef(la, lo, alt).reshape(-1, 3)
            los = pos[None] - x[:, None]
            e = los / np.linalg.norm(los, axis=2)[..., None]
            vis = np.einsum("pk,psk->ps", up, e) >= 0
            m = vis.sum(1) >= 4
            g = np.concatenate([-e[m], np.ones((int(m.sum()), 5, 1))], -1) * vis[m][..., None]
            d = np.einsum("psi,psj->pij", g, g)
            ok = np.linalg.cond(d) < 1e15
            gd = np.full(len(d), math.inf)
            gd[ok] = np.sqrt(np.trace(np.linalg.inv(d[ok]), axis1=1, axis2=2))
    return (time.perf_counter() - t0) / n_sample * n_ep


if __name__ == "__main__":
    t0 = time.perf_counter()
    run_coverage(CoverageConfig(), progress=False)
    ours = time.perf_counter() - t0
    base = baseline_seconds()
    print(f"bdsfix coverage (8 days, 300 s, 1 deg, 0 and 1000 km): {ours:.1f} s wall")
    print(f"straightforward per-epoch numpy loop (extrapolated): {base:.0f} s")
    print(f"speed-up: {base / ours:.1f}x")
