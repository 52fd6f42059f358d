"""Urban real data: 3D error percentiles, availability and protection-level exceedances on the
Hong Kong TST u-blox drive (../shared/data/hk-tst-urban-2019, with its ground truth).

Every epoch with a ground-truth row is solved by SPP (all full) and by the fast fix (non-GEO
ranges reduced modulo 1 ms, as `bdsfix solve` does), with the daemon's defaults and, for
comparison, with fault exclusion off (detection only) and with the chi-square test off.

With ``--systems C,G`` (or ``C,G,E``) the drive's GPS rows join (its GPS nav file beside the
BDS one; it has no Galileo nav file, so Galileo rows go unused), each system with its clock.

The sequential modes (service.engine.aiding: height aiding, the prediction screen) solve
every epoch of the file in order, as ``bdsfix solve`` does (solve_epochs), and are scored
on the same truth epochs; their rows also give |held height - true height| / sigma (68th
and 95th percentiles, largest) where the aid was given.

Run: python bench/bench_urban.py [--systems C,G]   (prints figures; no assertions)
"""

from __future__ import annotations

import csv
import math
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from drivers.rinex import RinexObsReader  # noqa: E402
from service.commands.solve import BatchOptions, load_navigation, solve_epochs  # noqa: E402
from service.core.geometry import ecef_to_geodetic, enu_rotation, geodetic_to_ecef  # noqa: E402
from service.engine.aiding import HeightAid  # noqa: E402
from service.engine.solver import SolverConfig, fractionalize, solve  # noqa: E402

TST = ROOT.parent / "shared" / "data" / "hk-tst-urban-2019"


def ground_truth() -> dict[tuple[int, int], np.ndarray]:
    """(GPS week, whole TOW) -> ECEF truth, from groundTruth_TST.csv (week, TOW, lat, lon, h)."""
    out = {}
    with open(TST / "groundTruth_TST.csv", encoding="ascii") as f:
        for row in csv.reader(f):
            try:
                week, tow, lat, lon, h = (float(v) for v in row[:5])
            except ValueError:
                continue
            out[(int(week), round(tow))] = geodetic_to_ecef(math.radians(lat), math.radians(lon), h)
    return out


def main() -> None:
    import argparse

    from service.core.systems import parse_systems

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--systems", default="C", help="RINEX letters, e.g. C,G (default C)")
    systems = parse_systems(ap.parse_args().systems)
    truth = ground_truth()
    navs = [str(TST / "hksc1180.19b")] + ([str(TST / "hksc1180.19n")] if "G" in systems else [])
    store, iono = load_navigation(navs, systems=systems)
    epochs = [
        ep
        for ep in RinexObsReader(TST / "COM3_190428_124409.obs", systems=systems)
        if (ep.gpst_week, round(ep.gpst_tow_s)) in truth
    ]
    every = list(RinexObsReader(TST / "COM3_190428_124409.obs", systems=systems))
    aided = SolverConfig(height_aiding=True)
    sequential = {
        "height aiding, 2 exclusions": aided,
        "height aiding, 3 exclusions": replace(aided, max_exclusions=3),
        "prediction screen 30 m": SolverConfig(screen_predicted_m=30.0),
        "height aiding + screen 30 m": replace(aided, screen_predicted_m=30.0),
        "aiding + screen, 3 exclusions": replace(aided, screen_predicted_m=30.0, max_exclusions=3),
    }
    configs = {
        "defaults (FDE, 2 exclusions)": SolverConfig(),
        "detection only": SolverConfig(max_exclusions=0),
        "no test (PDOP gate only)": SolverConfig(p_fa=0.0),
    }
    print(f"bench_urban: {len(epochs)} TST epochs with ground truth, systems {sorted(systems)}")
    for solver in ("spp", "fast"):
        for name, cfg in {**configs, **sequential}.items():
            errs, over, over_h = [], 0, 0
            if name in sequential:
                opts = BatchOptions(mode=solver, cfg=cfg, with_sky=False)  # type: ignore[arg-type]
                fixes = [f[0] for _, f in solve_epochs(iter(every), store, iono, opts)]
                aid_ratios = _aid_ratios(every, fixes, truth, cfg)
                fixes = [f for f in fixes if (f.gpst_week, round(f.gpst_tow_s)) in truth]
            else:
                fixes = [
                    solve(fractionalize(ep) if solver == "fast" else ep, store, iono, cfg, solver)
                    for ep in epochs
                ]
                aid_ratios = ""
            for ep, fix in zip(epochs, fixes, strict=True):
                if not fix.ok:
                    continue
                t = truth[(ep.gpst_week, round(ep.gpst_tow_s))]
                errs.append(float(np.linalg.norm(np.subtract(fix.x_ecef_m, t))))
                if fix.hpl_m is not None and math.isfinite(fix.hpl_m):
                    lat, lon, _ = ecef_to_geodetic(t)
                    e = enu_rotation(lat, lon) @ np.subtract(fix.x_ecef_m, t)
                    beyond_h = math.hypot(e[0], e[1]) > fix.hpl_m
                    over_h += beyond_h
                    over += beyond_h or abs(e[2]) > fix.vpl_m
            e = np.asarray(errs)
            p50, p95, p99 = np.percentile(e, [50, 95, 99]) if e.size else (math.nan,) * 3
            rms = math.sqrt(float(np.mean(e**2))) if e.size else math.nan
            print(
                f"  {solver:>4} {name:<29} availability {100 * len(e) / len(epochs):5.1f} %  3D "
                f"error p50 {p50:6.1f}  p95 {p95:6.1f}  p99 {p99:6.1f}  max "
                f"{e.max() if e.size else math.nan:6.1f}  RMS {rms:6.1f}"
                f" m; beyond HPL {over_h} ({100 * over_h / max(len(e), 1):.1f} %), HPL/VPL {over}"
                f"{aid_ratios}"
            )


def _aid_ratios(every: list, fixes: list, truth: dict, cfg: SolverConfig) -> str:
    """|held height - true height| / sigma of the aid each truth epoch got (the held height
    of the fixes before it, as solve_epochs keeps it): its 68th / 95th percentiles and
    largest, as text ("" without aiding)."""
    if not cfg.height_aiding:
        return ""
    held, ratios = HeightAid(), []
    for ep, fix in zip(every, fixes, strict=True):
        aid = held.prior(ep.gpst_week, ep.gpst_tow_s, cfg)
        held.update(fix, cfg)
        t = truth.get((ep.gpst_week, round(ep.gpst_tow_s)))
        if aid is not None and t is not None:
            ratios.append(abs(aid[0] - float(ecef_to_geodetic(t)[2])) / aid[1])
    if not ratios:
        return "; no aid"
    p68, p95 = np.percentile(ratios, [68, 95])
    return f"; aid error / sigma p68 {p68:.2f} p95 {p95:.2f} max {max(ratios):.2f}"


if __name__ == "__main__":
    main()
