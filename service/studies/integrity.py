"""Integrity Monte Carlo: single and dual range faults of 10 m to 150 km on simulated epochs.

Each trial is one epoch of the virtual receiver (:class:`service.sim.simulator.Simulator` on
the broadcast ephemerides given, e.g. the real 2021 ones of hksc-2021; Klobuchar +
Saastamoinen + 1.3 m noise) at one of five places in the >= 4-GEO area (Beijing, Hong Kong,
Singapore, Sydney, Tokyo), a random time of the nav file's six hours and a random receiver
clock offset. Both solvers run with the daemon's defaults (10 deg mask, error model,
chi-square test at P_fa 1e-5, up to 2 exclusions, protection levels at P_md 1e-3):

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

The study takes the ephemerides as data (reading files is the caller's: bench/bench_integrity.py
prints the figures, tests/studies/test_integrity.py checks a short run).
"""

from __future__ import annotations

import itertools
import math
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Literal

import numpy as np

from service.core.bds import is_geo
from service.core.constants import C_M_S
from service.core.ephemeris import EphemerisStore
from service.core.geometry import ecef_to_geodetic, enu_rotation
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem
from service.core.timebase import bdt_to_gpst
from service.core.types import Ephemeris, Fix, KlobucharParams, MeasurementEpoch
from service.engine.solver import IonoSet, SolverConfig, solve_many
from service.sim.simulator import SimConfig, Simulator

PERIOD_S = SYSTEM_CONSTANTS[GnssSystem.BDS].code_period_s
"""B1I code period: the simulated fractional ranges are known modulo c times this [s]."""
CT_M = C_M_S * PERIOD_S
FAULT_M = (10.0, 150e3)
BDT_WEEK = 805  # of hksc1610.nav (2021-06-10)
SOW_SPAN_S = (349200.0, 363600.0)  # toes common to the GEOs in hksc1610.nav
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
                mine += value
            else:
                setattr(self, name, mine + value)


def prepare_nav(ephemerides: Iterable[Ephemeris], iono: KlobucharParams | None) -> Nav:
    """The healthy ephemerides, a store holding them and the BDS Klobuchar parameters."""
    ephs = [e for e in ephemerides if e.health == 0]
    store = EphemerisStore()
    store.add_all(ephs)
    return ephs, store, iono


def _view(prn: list[str], pr_m: np.ndarray, full: np.ndarray, week: int, tow: float):
    return MeasurementEpoch.from_columns(
        week,
        tow,
        prn,
        ["2I"] * len(prn),
        np.where(full, pr_m, np.nan),
        frac_pr_m=np.where(full, np.nan, np.mod(pr_m, CT_M)),
        period_s=PERIOD_S,
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
    if fix.x_ecef_m is None or fix.hpl_m is None or fix.vpl_m is None:
        raise ValueError("pl_ratio needs a fix with a position and protection levels")
    lat, lon, _ = ecef_to_geodetic(truth)
    e = enu_rotation(lat, lon) @ np.subtract(fix.x_ecef_m, truth)
    return max(math.hypot(e[0], e[1]) / fix.hpl_m, abs(e[2]) / fix.vpl_m)


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
    if not fix.ok or fix.x_ecef_m is None:
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
    nav: Nav,
    seed: int = 1,
    cfg: SolverConfig | None = None,
    dual_share: float = DUAL_SHARE,
) -> dict[str, Tally]:
    """``n`` trials on ``nav`` (:func:`prepare_nav`); tallies keyed ``"<solver> <single|dual>"``."""
    ephs, store, iono = nav
    ionoset = IonoSet(bds=iono)
    cfg = cfg or SolverConfig()  # the daemon's defaults
    rng = np.random.default_rng(seed)
    out = {f"{s} {k}": Tally() for s in ("fast", "spp") for k in ("single", "dual")}
    names = sorted(PLACES)
    trials: dict[Literal["fast", "spp"], list[tuple]] = {"fast": [], "spp": []}
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
        views: tuple[tuple[Literal["fast", "spp"], np.ndarray], ...] = (
            ("fast", restart),
            ("spp", np.ones(len(prn), dtype=bool)),
        )
        for solver, full in views:
            trials[solver].append(
                (
                    _view(prn, pr_true, full, week_tag, tow_tag),
                    _view(prn, pr, full, week_tag, tow_tag),
                    (kind, ep.truth_x_ecef_m, faulty, mags, pr_true, np.mod(pr, CT_M), prn),
                    f"trial {k} {place} {solver}",
                )
            )
    # every trial's clean and faulted epochs solved in batches by the one engine
    for solver, items in trials.items():
        cleans = solve_many([t[0] for t in items], store, ionoset, cfg, solver)
        fixes = solve_many([t[1] for t in items], store, ionoset, cfg, solver)
        for (_, _, (kind_, truth, faulty_, mags_, true_, z, prn_), label), clean, fix in zip(
            items, cleans, fixes, strict=True
        ):
            _judge(
                out[f"{solver} {kind_}"], clean, fix, truth, faulty_, mags_, true_, z, prn_, label
            )
    return out
