"""Benchmark: `bdsfix coverage` with defaults, against a straightforward per-epoch numpy loop.

Run: python bench/bench_coverage.py   (prints figures; no assertions)

- The study runs as the CLI does, with default workers: one process per CPU.
- It is timed again in one process, to show what the vectorisation alone gains.
- The baseline handles every grid point at every epoch: einsum-built unit vectors and normal
  matrices, then batched numpy.linalg.inv. It runs on a subsample of epochs, and its time is
  extrapolated to the full 2304 epochs.
"""

from __future__ import annotations

import math
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.core.geometry import geodetic_to_ecef
from service.sim.constellation import positions_ecef, table1
from service.studies.coverage import CoverageConfig, run_coverage


def baseline_counts(sats: np.ndarray, cfg: CoverageConfig) -> tuple[np.ndarray, np.ndarray]:
    """Per-epoch (>= 4 GEOs, usable) counts of the straightforward loop, shape (alts, K)."""
    la, lo = np.meshgrid(np.radians(cfg.lats_deg()), np.radians(cfg.lons_deg()), indexing="ij")
    up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], -1).reshape(-1, 3)
    xs = [geodetic_to_ecef(la, lo, alt).reshape(-1, 3) for alt in cfg.altitudes_m]
    sin_mask = math.sin(math.radians(cfg.elmask_deg))
    n4 = np.zeros((len(xs), len(sats)), dtype=int)
    nu = np.zeros((len(xs), len(sats)), dtype=int)
    for k, pos in enumerate(sats):
        for ia, x in enumerate(xs):
            los = pos[None] - x[:, None]
            e = los / np.linalg.norm(los, axis=2)[..., None]
            vis = np.einsum("pk,psk->ps", up, e) >= sin_mask
            m = vis.sum(1) >= 4
            g = np.concatenate([-e[m], np.ones((int(m.sum()), len(pos), 1))], -1)
            g *= vis[m][..., None]
            d = np.einsum("psi,psj->pij", g, g)
            gd = np.sqrt(np.trace(np.linalg.inv(d), axis1=1, axis2=2))
            n4[ia, k] = int(m.sum())
            nu[ia, k] = int((gd < cfg.beta).sum())
    return n4, nu


def main() -> None:
    cfg = CoverageConfig()
    sats = positions_ecef(table1().geos(), np.arange(cfg.n_epochs) * cfg.step_s)
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    print(f"default study: {cfg.n_epochs} epochs x {181 * 360} points x 2 altitudes, {cpus} CPUs")
    print(f"load average before: {os.getloadavg()[0]:.2f}")

    t0 = time.perf_counter()
    res = run_coverage(cfg, sats)
    wall = time.perf_counter() - t0
    t0 = time.perf_counter()
    run_coverage(cfg, sats, workers=1)
    serial = time.perf_counter() - t0
    for r in res.altitudes:
        pct = r.pct
        print(
            f"  {r.altitude_m / 1e3:6.0f} km: max {np.nanmax(pct):.3f} % "
            f"min {np.nanmin(pct):.3f} % all {100 * r.n_usable.sum() / r.n_geo4.sum():.3f} %"
        )
    print(f"bdsfix coverage, default workers: {wall:.1f} s wall")
    print(f"bdsfix coverage, one process:     {serial:.1f} s wall")

    # the baseline on a sample that includes the worst epoch (+3.5 h = epoch 42)
    sample = np.arange(36, 36 + 12)
    t0 = time.perf_counter()
    b4, bu = baseline_counts(sats[sample], cfg)
    per_epoch = (time.perf_counter() - t0) / len(sample)
    base = per_epoch * cfg.n_epochs
    same = all(
        (r.n_geo4[sample] == b4[i]).all() and (r.n_usable[sample] == bu[i]).all()
        for i, r in enumerate(res.altitudes)
    )
    print(
        f"straightforward per-epoch numpy loop: {per_epoch:.3f} s/epoch, "
        f"{base:.0f} s extrapolated (counts on the sample identical: {same})"
    )
    print(f"speed-up: {base / wall:.1f}x (default workers), {base / serial:.1f}x (one process)")
    print(f"load average after: {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
