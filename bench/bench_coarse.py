"""The coarse-time first fix (service/engine/coarse.py) on real data, beside the plain chain.

HKSC 2021 (static, Leica GR50) and the TST urban drive (u-blox, 4-12 m/s, ground truth):
every epoch where SPP of the file's full ranges fixes is restarted with only k GEOs full
(k = 0..3, the first k GEOs of the epoch; fewer where fewer are tracked) and every other
range reduced modulo 1 ms (`fractionalize`); both also with the time tag shifted by +-2 s
(the tag and the full ranges together: a receiver clock 2 s wrong, on the drive a moving
receiver's; fractional ranges are unchanged by a whole-millisecond shift). Each fix is
checked against the file's full ranges: integers (absolute where the fix claims them, else
relative to the first fractional satellite), distance to SPP of the full ranges of the
satellites the fix kept (its fault exclusion may leave one out, and a tag 2 s off may find
no ephemeris for one at the edge of its age), and on the drive the horizontal error against
the ground truth and the fix's HPL.

The plain chain (Pocket SDR `pocket_snap.py`, van Diggelen): the same Doppler position
(height pseudo-observation 0), one rounding of every integer at it against the nearest
satellite, the same five-state least squares, published without a test.

The whole drive (`whole_drive`): every epoch where SPP of the file's full ranges fixes, k = 0,
the issue's availability denominator; the fixes and declines tabulated by the number of
satellites SPP used, wrong integers, and fixes with ground truth beyond their HPL.

Times: wall (perf_counter) and CPU (process_time) per epoch of solve_coarse, the search and,
with a full row, the SPP of the full ranges it makes; the machine is shared, so the wall
time's tail is mostly other processes (the CPU time is this process's own).

Systems: BeiDou, GPS and Galileo rows (each system's clock its own, GPS and Galileo ranges
reduced modulo their own code periods, 1 ms and 4 ms) with ``--systems CGE`` (the default;
the drive has no Galileo navigation file, so its Galileo rows go unused); ``--systems C``:
BeiDou alone. The whole drive's availability is given over both denominators: the epochs
where SPP of the file's full ranges fixes with the systems read, and with BeiDou alone
(the denominator of the BeiDou-only figures).

Run: python bench/bench_coarse.py [--quick] [--drive] [--systems CGE]   (prints figures; no
assertions; --drive: the whole drive only)
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.bench_urban import TST, ground_truth  # noqa: E402
from drivers.rinex import RinexObsReader  # noqa: E402
from service.commands.solve import load_navigation  # noqa: E402
from service.core.bds import is_geo  # noqa: E402
from service.core.constants import C_M_S  # noqa: E402
from service.core.declines import excluded_why  # noqa: E402
from service.core.geometry import ecef_to_geodetic, enu_rotation  # noqa: E402
from service.engine.coarse import CoarseConfig, plain_chain, solve_coarse  # noqa: E402
from service.engine.solver import SolverConfig, fractionalize, solve  # noqa: E402

HKSC = ROOT.parent / "shared" / "data" / "hksc-2021"
SYSTEMS = sys.argv[sys.argv.index("--systems") + 1] if "--systems" in sys.argv else "CGE"
TST_NAVS = [TST / "hksc1180.19b", *([TST / "hksc1180.19n"] if "G" in SYSTEMS else [])]


@dataclass
class Tally:
    epochs: int = 0
    fixes: int = 0
    wrong: int = 0
    absolute: int = 0
    beyond_hpl: int = 0
    eq_1mm: int = 0
    diff_m: list[float] = field(default_factory=list)
    err_h_m: list[float] = field(default_factory=list)
    ms: list[float] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)
    declines: dict[str, int] = field(default_factory=dict)
    plain_fixes: int = 0
    plain_wrong: int = 0
    plain_far: int = 0
    plain_err_km: list[float] = field(default_factory=list)


def restarted(ep, k: int, shift_s: float):
    """``ep`` with only its first k GEOs full, the tag and full ranges shifted."""
    geos = [p for p, v in zip(ep.prn, ep.pr_m, strict=True) if is_geo(p) and np.isfinite(v)][:k]
    fe = fractionalize(ep, keep_full=geos)
    if shift_s:
        fe = replace(fe, gpst_tow_s=fe.gpst_tow_s + shift_s, pr_m=fe.pr_m + shift_s * C_M_S)
    return fe


def true_integers(ep, fe, shift_s: float) -> dict[str, int]:
    """Each row's integer in units of its own code period (``fe.period_s``)."""
    full = dict(zip(ep.prn, ep.pr_m.tolist(), strict=True))
    rows = zip(fe.prn, fe.frac_pr_m.tolist(), fe.period_s.tolist(), strict=True)
    return {
        p: round((full[p] + shift_s * C_M_S - f) / (C_M_S * t))
        for p, f, t in rows
        if math.isfinite(t)
    }


def relative_wrong(ints: dict[str, int], truth: dict[str, int]) -> bool:
    """Integers known only relative within each system (a whole period of a system without
    a full row is in its clock): wrong if a difference to the system's first row is."""
    first: dict[str, str] = {}
    for p in ints:
        first.setdefault(p[:1], p)
    return any(ints[p] - ints[first[p[:1]]] != truth[p] - truth[first[p[:1]]] for p in ints)


def integers_wrong(result, truth: dict[str, int]) -> bool:
    ints = result.integers or {}
    if result.absolute:
        return any(ints[p] != truth[p] for p in ints)
    return relative_wrong(ints, truth)


def run(name, obs, navs, k, shift_s, truth_of=None, quick=False) -> Tally:
    store, iono = load_navigation([str(n) for n in navs], systems=SYSTEMS)
    cfg, ccfg = SolverConfig(), CoarseConfig()
    t = Tally()
    for i, ep in enumerate(RinexObsReader(obs, systems=SYSTEMS)):
        if quick and i % 10:
            continue
        truth = truth_of(ep) if truth_of else None
        if truth_of and truth is None:
            continue
        ref = solve(ep, store, iono, cfg, "spp")
        if not ref.ok:
            continue
        t.epochs += 1
        fe = restarted(ep, k, shift_s)
        tru = true_integers(ep, fe, shift_s)
        c0, t0 = time.process_time(), time.perf_counter()
        res = solve_coarse(fe, store, iono, cfg, ccfg)
        t.ms.append(1e3 * (time.perf_counter() - t0))
        t.cpu_ms.append(1e3 * (time.process_time() - c0))
        plain = plain_chain(fe, store, iono, cfg, ccfg)
        if plain is not None:
            t.plain_fixes += 1
            x_p, ints_p = plain
            t.plain_wrong += relative_wrong(ints_p, tru)
            e_km = float(np.linalg.norm(x_p - np.asarray(ref.x_ecef_m))) / 1e3
            t.plain_err_km.append(e_km)
            t.plain_far += e_km > 1.0
        fix = res.fix
        if not fix.ok:
            code = fix.reason_code or "?"
            t.declines[code] = t.declines.get(code, 0) + 1
            continue
        t.fixes += 1
        t.absolute += res.absolute
        t.wrong += integers_wrong(res, tru)
        left_out = [p for p, why in fix.excluded.items() if why == excluded_why("coarse")]
        left_out += [p for p in ep.prn if p not in res.rows]  # (BeiDou alone: the fallback)
        if left_out:  # SPP of the full ranges of the satellites the fix kept
            kept = [i for i, p in enumerate(ep.prn) if p not in left_out]
            sub = replace(
                ep,
                prn=tuple(ep.prn[i] for i in kept),
                signal=tuple(ep.signal[i] for i in kept),
                pr_m=ep.pr_m[kept],
                frac_pr_m=ep.frac_pr_m[kept],
                period_s=ep.period_s[kept],
                cn0_dbhz=ep.cn0_dbhz[kept],
                doppler_hz=ep.doppler_hz[kept],
                lock_s=ep.lock_s[kept],
            )
            ref = solve(sub, store, iono, cfg, "spp")
        if ref.ok:  # (SPP of the kept satellites may itself decline)
            d = float(np.linalg.norm(np.subtract(fix.x_ecef_m, ref.x_ecef_m)))
            t.diff_m.append(d)
            t.eq_1mm += d <= 1e-3
        if truth is not None:
            lat, lon, _ = ecef_to_geodetic(truth)
            e = enu_rotation(lat, lon) @ np.subtract(fix.x_ecef_m, truth)
            eh = math.hypot(e[0], e[1])
            t.err_h_m.append(eh)
            t.beyond_hpl += fix.hpl_m is not None and eh > fix.hpl_m
    d = np.asarray(t.diff_m) if t.diff_m else np.asarray([math.nan])
    ms, cpu = np.asarray(t.ms), np.asarray(t.cpu_ms)
    pe = np.asarray(t.plain_err_km) if t.plain_err_km else np.asarray([math.nan])
    print(
        f"{name:6} k={k} shift {shift_s:+.0f} s: {t.fixes}/{t.epochs} fixed "
        f"({100 * t.fixes / max(t.epochs, 1):.1f} %), wrong integers {t.wrong}, absolute "
        f"{t.absolute}, = SPP <= 1 mm {t.eq_1mm}, |fix - SPP| p50 {np.median(d):.3g} max "
        f"{d.max():.3g} m; declines {t.declines}; wall {np.median(ms):.1f} ms p50, "
        f"{np.percentile(ms, 99):.1f} ms p99; CPU {np.median(cpu):.1f} ms p50, "
        f"{np.percentile(cpu, 99):.1f} ms p99"
    )
    if t.err_h_m:
        eh = np.asarray(t.err_h_m)
        print(
            f"        horizontal error vs truth p50 {np.median(eh):.1f} p95 "
            f"{np.percentile(eh, 95):.1f} max {eh.max():.1f} m; beyond HPL {t.beyond_hpl}"
        )
    print(
        f"        plain chain: {t.plain_fixes} published, wrong integers {t.plain_wrong}, "
        f">1 km from SPP {t.plain_far}, error p50 {np.median(pe):.3g} max {pe.max():.3g} km"
    )
    return t


def whole_drive(truth: dict, quick: bool = False) -> None:
    """Every epoch of the TST drive where SPP fixes, k = 0 (module docstring)."""
    store, iono = load_navigation([str(n) for n in TST_NAVS], systems=SYSTEMS)
    cfg, ccfg = SolverConfig(), CoarseConfig()
    n = fixed = wrong = with_truth = beyond = 0
    n_bds = fixed_bds = 0  # over the epochs where BeiDou-alone SPP fixes
    bds = [p for p in ("C",) if p in SYSTEMS]
    epochs: dict[int, int] = {}
    fixes: dict[int, int] = {}
    declines: dict[tuple[str, int], int] = {}
    for i, ep in enumerate(RinexObsReader(TST / "COM3_190428_124409.obs", systems=SYSTEMS)):
        if quick and i % 10:
            continue
        ref = solve(ep, store, iono, cfg, "spp")
        only = [j for j, p in enumerate(ep.prn) if p[:1] in bds]
        bds_ok = solve(ep.rows(only), store, iono, cfg, "spp").ok if only else False
        n_bds += bds_ok
        if not ref.ok:
            continue
        n += 1
        m = min(len(ref.used), 12)
        epochs[m] = epochs.get(m, 0) + 1
        fe = restarted(ep, 0, 0.0)
        res = solve_coarse(fe, store, iono, cfg, ccfg)
        if not res.fix.ok:
            key = (res.fix.reason_code or "?", m)
            declines[key] = declines.get(key, 0) + 1
            continue
        fixed += 1
        fixed_bds += bds_ok
        fixes[m] = fixes.get(m, 0) + 1
        wrong += integers_wrong(res, true_integers(ep, fe, 0.0))
        x_true = truth.get((ep.gpst_week, round(ep.gpst_tow_s)))
        if x_true is not None:
            with_truth += 1
            lat, lon, _ = ecef_to_geodetic(x_true)
            e = enu_rotation(lat, lon) @ np.subtract(res.fix.x_ecef_m, x_true)
            beyond += res.fix.hpl_m is not None and math.hypot(e[0], e[1]) > res.fix.hpl_m
    print(
        f"TST whole drive k=0: {fixed}/{n} fixed ({100 * fixed / max(n, 1):.1f} %), wrong "
        f"integers {wrong}, {beyond} of {with_truth} fixes with truth beyond HPL (systems "
        f"{SYSTEMS}); over the {n_bds} epochs where BeiDou-alone SPP fixes: {fixed_bds} fixed "
        f"({100 * fixed_bds / max(n_bds, 1):.1f} %)"
    )
    print("  satellites SPP used: epochs / fixed / declines")
    for m in sorted(epochs):
        why = {c: k for (c, mm), k in sorted(declines.items()) if mm == m}
        print(f"  {m:>2}{'+' if m == 12 else ' '} {epochs[m]:5d} {fixes.get(m, 0):5d}  {why}")


def main() -> None:
    quick = "--quick" in sys.argv
    truth = ground_truth()
    whole_drive(truth, quick)
    if "--drive" in sys.argv:
        return

    def tst_truth(ep):
        return truth.get((ep.gpst_week, round(ep.gpst_tow_s)))

    for k in (0, 1, 2, 3):
        for shift in (0.0, 2.0, -2.0):
            run("HKSC", HKSC / "hksc1610.obs", [HKSC / "hksc1610.nav"], k, shift, quick=quick)
    for k in (0, 1, 2, 3):
        for shift in (0.0, 2.0, -2.0):
            run(
                "TST",
                TST / "COM3_190428_124409.obs",
                TST_NAVS,
                k,
                shift,
                tst_truth,
                quick=quick,
            )


if __name__ == "__main__":
    main()
