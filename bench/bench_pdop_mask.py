"""The PDOP mask's trade-off: fixes published and their 3D error against the mask (pdop_max).

Each file is solved by ``bdsfix solve``'s path (:func:`service.commands.solve.solve_epochs`,
default settings but ``pdop_max``) once per mask: SPP (all full ranges) and the fast fix (non-GEO
ranges reduced modulo 1 ms). Truth:

- HKSC 2021-06-10 (Leica GR50 reference station, 5 GEOs, 205 epochs): the surveyed position;
- TST 2019-04-28 (u-blox drive in an urban canyon, 1760 epochs): groundTruth_TST.csv, at the
  epochs it has a row for;
- F9P 2021-06-10 (u-blox rover near HKSC, no GEOs, 205 epochs): it moves (a loop of a few
  hundred metres) and has no ground truth, so fixes only.

Errors are 3D, p50/p99/max over the fixes published at that mask that have a truth
("scored"; TST's ground truth covers 485 of its epochs); "new vs 10" = fixes the mask adds
over the 10 it replaces as default, "max new" the largest error among the scored ones.

Run: python bench/bench_pdop_mask.py   (prints a table; no assertions)
"""

from __future__ import annotations

import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.rinex import RinexObsReader  # noqa: E402
from service.commands.solve import BatchOptions, load_navigation, solve_epochs  # noqa: E402
from service.engine.solver import SolverConfig  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_urban import ground_truth  # noqa: E402  (the TST truth reader, one place)

DATA = ROOT.parent / "shared" / "data"
MASKS = (6.0, 10.0, 15.0, 20.0, 25.0, 30.0)
OLD_DEFAULT = 10.0
HKSC_TRUTH_ECEF_M = np.array([-2414266.9197, 5386768.9868, 2407460.0314])  # header, surveyed


def fixes(obs: Path, nav: Path, pdop_max: float, mode: str) -> dict[tuple[int, int], np.ndarray]:
    """(week, whole TOW) -> ECEF of each published fix of ``mode`` ("spp" or "fast")."""
    store, iono = load_navigation([str(nav)])
    opts = BatchOptions(mode=mode, cfg=replace(SolverConfig(), pdop_max=pdop_max), with_sky=False)  # type: ignore[arg-type]
    out = {}
    for ep, (fix,) in solve_epochs(iter(RinexObsReader(obs)), store, iono, opts):
        if fix.ok and fix.x_ecef_m is not None:
            out[(ep.gpst_week, round(ep.gpst_tow_s))] = np.asarray(fix.x_ecef_m)
    return out


def main() -> None:
    hksc, tst = DATA / "hksc-2021", DATA / "hk-tst-urban-2019"
    truth_tst = ground_truth()

    def truth_hksc(_: tuple[int, int]) -> np.ndarray | None:
        return HKSC_TRUTH_ECEF_M

    def no_truth(_: tuple[int, int]) -> np.ndarray | None:
        return None

    cases = [
        ("HKSC", hksc / "hksc1610.obs", hksc / "hksc1610.nav", truth_hksc),
        ("TST", tst / "COM3_190428_124409.obs", tst / "hksc1180.19b", truth_tst.get),
        ("F9P", hksc / "20210610.klt1.ublox.f9p.obs", hksc / "hksc1610.nav", no_truth),
    ]
    print("bench_pdop_mask: fixes and 3D error [m] against the PDOP mask (pdop_max)")
    print(
        f"{'file':<5} {'solver':<5} {'mask':>5} {'epochs':>6} {'fixes':>6} {'scored':>6} "
        f"{'p50':>7} {'p99':>7}"
        f" {'max':>7} {'new vs 10':>9} {'max new':>8}"
    )
    for name, obs, nav, truth in cases:
        n_epochs = sum(1 for _ in RinexObsReader(obs))
        for mode in ("spp", "fast"):
            runs = {m: fixes(obs, nav, m, mode) for m in (*MASKS, math.inf)}
            base = runs[OLD_DEFAULT]
            if mode == "fast" and all(r.keys() == base.keys() for r in runs.values()):
                print(f"{name:<5} fast  the same {len(base)} fixes at every mask")
                continue
            for m in (*MASKS, math.inf):
                err = {
                    k: float(np.linalg.norm(x - t))
                    for k, x in runs[m].items()
                    if (t := truth(k)) is not None
                }
                e = np.array(list(err.values()))
                p50, p99, mx = (*np.percentile(e, [50, 99]), e.max()) if e.size else (math.nan,) * 3
                new = [v for k, v in err.items() if k not in base]
                print(
                    f"{name:<5} {mode:<5} {m:>5g} {n_epochs:>6} {len(runs[m]):>6} {len(err):>6} "
                    f"{p50:>7.1f} "
                    f"{p99:>7.1f} {mx:>7.1f} {len(runs[m]) - len(base):>+9d} "
                    f"{max(new) if new else math.nan:>8.1f}"
                )


if __name__ == "__main__":
    main()
