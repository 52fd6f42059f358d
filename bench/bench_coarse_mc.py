"""Monte Carlo of the coarse-time first fix over the whole globe (service/studies/coarse_mc.py):
receivers uniform on the sphere, 0-50 m/s (5 % aircraft at 250 m/s, 10 km), host clock
errors uniform within the +-2 s time prior, the real 2024 BeiDou-3 broadcast ephemerides of
../shared/data/hk-polyu-f9p-ubx-2024/hksc269h.24f (C01-C62), times within an hour of their
median t_oe (the generator and the solver use the same ephemerides).

With ``--systems CG`` the GPS satellites of the same hour's GPS nav file (hksc269h.24n, all
31) are generated and solved beside BeiDou (a random inter-system bias within +-100 ns on
the GPS rows; generator and solver on the BeiDou Klobuchar set, so that the ionosphere the
solver removes is the one generated).

``--time-prior S``: the coarse-time fix's prior (and the host clock errors' range) S seconds
instead of 2 (a phone's 5 sigma, up to 30 s: service.engine.pipeline.wide_time_prior).

Run: python bench/bench_coarse_mc.py [N] [SEED] [--systems CG] [--time-prior S]   (default
10000 trials, seed 1, BeiDou alone, 2 s; prints figures; no assertions)
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.commands.solve import load_navigation  # noqa: E402
from service.engine.coarse import CoarseConfig  # noqa: E402
from service.engine.solver import IonoSet  # noqa: E402
from service.studies.coarse_mc import run  # noqa: E402

NAV = ROOT.parent / "shared" / "data" / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f"
GPS_NAV = NAV.with_suffix(".24n")
GPST_WEEK = 2333  # BDT week 977 of the file


def main() -> None:
    args = sys.argv[1:]
    systems = "C"
    if "--systems" in args:
        i = args.index("--systems")
        systems = args[i + 1]
        del args[i : i + 2]
    ccfg = CoarseConfig()
    if "--time-prior" in args:
        i = args.index("--time-prior")
        ccfg = CoarseConfig(time_prior_s=float(args[i + 1]))
        del args[i : i + 2]
    n = int(args[0]) if args else 10_000
    seed = int(args[1]) if len(args) > 1 else 1
    navs = [str(NAV), *([str(GPS_NAV)] if "G" in systems else [])]
    store, iono = load_navigation(navs, max_age_s=86_400.0, systems=systems)
    iono = IonoSet(bds=iono.bds)
    bds = [e.toe_sow_s for e in store.all() if e.prn.startswith("C")]
    mid = float(np.median(bds)) + 14.0  # BDT -> GPST
    t0 = time.perf_counter()
    summary = run(store, iono, GPST_WEEK, (mid - 3600.0, mid + 3600.0), n, seed, ccfg=ccfg)
    wall = time.perf_counter() - t0
    print(
        f"bench_coarse_mc: {n} trials, seed {seed}, systems {systems}, time prior "
        f"{ccfg.time_prior_s:g} s, "
        f"{1e3 * wall / n:.1f} ms per trial"
    )
    for key, value in summary.figures().items():
        print(f"  {key:<16} {value:.4g}" if isinstance(value, float) else f"  {key:<16} {value}")
    print(f"  declines         {summary.declines()}")
    print("  satellites above the mask: trials / fixed / wrong / declines")
    for m in sorted({min(t.n_sats, 12) for t in summary.trials}):
        at = [t for t in summary.trials if min(t.n_sats, 12) == m]
        why: dict[str, int] = {}
        for t in at:
            if not t.fixed:
                why[t.reason_code or "?"] = why.get(t.reason_code or "?", 0) + 1
        fixed, wrong = sum(t.fixed for t in at), sum(t.wrong for t in at)
        print(f"  {m:>2}{'+' if m == 12 else ' '} {len(at):6d} {fixed:6d} {wrong:3d}  {why}")
    slow = [t for t in summary.trials if t.speed_m_s <= 50.0 and t.n_sats >= 7]
    print(f"  <= 50 m/s with >= 7 satellites: {sum(t.fixed for t in slow)}/{len(slow)} fixed")
    for t in summary.trials:
        far = t.error_m is not None and t.error_m > 100.0
        over = t.error_h_m is not None and t.hpl_m is not None and t.error_h_m > t.hpl_m
        if t.wrong or far or over:
            print(f"  {'WRONG' if t.wrong else 'far/over HPL'} {t}")


if __name__ == "__main__":
    main()
