"""``bdsfix coverage --first-fix``: where and when each method gives a fix at the first epoch.

Two methods, over the Earth's surface (height 0 on the CGCS2000 ellipsoid) and a span of
time, at every grid point and epoch:

- **the paper's method** (Zhao, Cui, Lu): at least four GEOs at or above the elevation
  mask, with GDOP_full < beta (eqs. 12, 20, 21; :func:`service.studies.coverage.geo_gdop`);
- **the coarse-time first fix** (:mod:`service.engine.coarse`): at least
  :func:`service.engine.coarse.min_rows` = 6 BeiDou satellites at or above the mask (five
  unknowns, redundancy 2 with the time prior's row), every one with
  a Doppler (the virtual receiver and the receivers bdsfix reads give one per tracked
  satellite). This is the method's *geometric condition*, the rule it declines
  ``too_few_rows`` by; whether it then fixes is measured by running :func:`solve_coarse`
  itself on simulated first epochs (:func:`solve_sample`).

Shares are of surface x time: each grid point weighs cos(latitude) (the area of its cell),
every epoch the same. Point-counted shares (the convention of the paper's Table 3) are given
beside them.

At the first epoch no satellite's time is known yet (a GEO's SOW decodes 0.12-0.6 s in):
the coarse-time method runs on fractional ranges alone (k = 0 full rows), which is how
:func:`solve_sample` simulates it; the paper's method needs the four GEO full ranges, so
its first fix comes once they decode.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.core.bds import is_geo
from service.core.ephemeris import EphemerisStore
from service.core.errors import ConfigError
from service.core.files import PLOT_HINT
from service.core.geometry import geodetic_to_ecef
from service.core.orbit import sat_pos_clock
from service.core.timebase import gpst_to_bdt, normalize
from service.engine.coarse import CoarseConfig, min_rows
from service.engine.solver import IonoSet, SolverConfig
from service.studies.coverage import geo_gdop

PROPAGATE_MAX_S = 86400.0
"""How far from its t_oe a broadcast set is propagated for this study (visibility only)."""


@dataclass(frozen=True, slots=True)
class FirstFixConfig:
    """The grid, span and thresholds of the study."""

    days: float = 1.0
    step_s: float = 600.0
    grid_deg: float = 2.0
    beta: float = 3000.0
    elmask_deg: float = 10.0  # the solver's default mask (SolverConfig.elmask_deg)
    min_sats: int = min_rows()

    @property
    def n_epochs(self) -> int:
        return max(1, math.floor(self.days * 86400.0 / self.step_s + 1e-9))

    def lats_deg(self) -> np.ndarray:
        return np.arange(-90.0, 90.0 + 1e-9, self.grid_deg)

    def lons_deg(self) -> np.ndarray:
        return np.arange(-180.0, 180.0 - 1e-9, self.grid_deg)


@dataclass(frozen=True, slots=True, eq=False)
class FirstFixResult:
    """Per grid point (lat, lon): the share of epochs each method fixes; per epoch the
    area-weighted shares of the surface."""

    lats_deg: np.ndarray
    lons_deg: np.ndarray
    paper: np.ndarray  # (lat, lon) fraction of epochs
    coarse: np.ndarray
    either: np.ndarray
    paper_t: np.ndarray  # (epochs,) area share of the surface
    coarse_t: np.ndarray
    either_t: np.ndarray
    min_sats_seen: int  # fewest satellites above the mask at any point and epoch
    prns: tuple[str, ...]
    cfg: FirstFixConfig

    def weights(self) -> np.ndarray:
        w = np.cos(np.radians(self.lats_deg))[:, None] * np.ones(len(self.lons_deg))[None, :]
        return w / w.sum()


def positions_from_store(
    store: EphemerisStore, start_gpst: tuple[int, float], t_s: np.ndarray
) -> tuple[tuple[str, ...], np.ndarray]:
    """Broadcast positions (len(t_s), n, 3) of every BeiDou satellite of ``store``, NaN where
    the store selects no set for that epoch (none within its max age; ICD 5.2.4.12)."""
    prns = tuple(p for p in store.prns if p.startswith("C"))
    out = np.full((len(t_s), len(prns), 3), np.nan)
    for k, dt in enumerate(t_s):
        week, tow = normalize(start_gpst[0], start_gpst[1] + float(dt))
        bw, bs = gpst_to_bdt(week, tow)
        sel = [(j, store.select(p, bw, bs)) for j, p in enumerate(prns)]
        have = [(j, e) for j, e in sel if e is not None]
        if not have:
            continue
        arr = store.arrays([e for _, e in have])
        pos, _ = sat_pos_clock(arr, np.full(len(have), bw), np.full(len(have), bs))
        out[k, [j for j, _ in have]] = pos
    return prns, out


def run_first_fix(
    cfg: FirstFixConfig, prns: Sequence[str], sats_ecef_m: np.ndarray
) -> FirstFixResult:
    """The study over satellite positions (epochs, n, 3) ``cfg.step_s`` apart (NaN: no
    ephemeris at that epoch, never counted)."""
    if cfg.days <= 0 or cfg.step_s <= 0 or cfg.grid_deg <= 0:
        raise ConfigError("--days, --step-s and --grid-deg must be positive")
    lats, lons = cfg.lats_deg(), cfg.lons_deg()
    la, lo = np.meshgrid(np.radians(lats), np.radians(lons), indexing="ij")
    x = geodetic_to_ecef(la, lo, 0.0).reshape(-1, 3)
    up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)
    up = up.reshape(-1, 3)
    w = np.cos(la).reshape(-1)
    w = w / w.sum()
    geo = np.array([is_geo(p) for p in prns])
    sin_mask = math.sin(math.radians(cfg.elmask_deg))
    n_pts = len(x)
    paper = np.zeros(n_pts)
    coarse = np.zeros(n_pts)
    either = np.zeros(n_pts)
    pt, ct, et = [], [], []
    fewest = 10**6
    for sats in sats_ecef_m:
        ok = np.isfinite(sats).all(axis=1)
        s = sats[ok]
        d = s[:, None, :] - x[None, :, :]  # (n, P, 3)
        r = np.linalg.norm(d, axis=2)
        sin_el = np.einsum("npk,pk->np", d, up) / r
        n_vis = (sin_el >= sin_mask).sum(axis=0)
        fewest = min(fewest, int(n_vis.min()))
        c_ok = n_vis >= cfg.min_sats
        g = s[geo[ok]]
        if len(g) >= 4:
            _, gdop = geo_gdop(g, x, up, cfg.elmask_deg)
            p_ok = gdop < cfg.beta
        else:
            p_ok = np.zeros(n_pts, dtype=bool)
        paper += p_ok
        coarse += c_ok
        either += p_ok | c_ok
        pt.append(float(w @ p_ok))
        ct.append(float(w @ c_ok))
        et.append(float(w @ (p_ok | c_ok)))
    k = len(sats_ecef_m)
    shape = (len(lats), len(lons))
    return FirstFixResult(
        lats,
        lons,
        (paper / k).reshape(shape),
        (coarse / k).reshape(shape),
        (either / k).reshape(shape),
        np.array(pt),
        np.array(ct),
        np.array(et),
        fewest,
        tuple(prns),
        cfg,
    )


# --------------------------------------------------------------------------- solve sample


@dataclass(frozen=True, slots=True)
class SampleOutcome:
    """solve_coarse on one simulated first epoch."""

    lat_deg: float
    lon_deg: float
    n_sats: int
    fixed: bool
    wrong: bool
    reason_code: str | None
    error_m: float | None


def solve_sample(
    store: EphemerisStore,
    iono: IonoSet,
    start_gpst: tuple[int, float],
    t_s: Sequence[float],
    grid_deg: float,
    seed: int = 1,
    cfg: SolverConfig | None = None,
    ccfg: CoarseConfig | None = None,
) -> list[SampleOutcome]:
    """Run :func:`service.engine.coarse.solve_coarse` on a simulated first epoch (static
    receiver at height 0, every range fractional, host clock error uniform within the time
    prior) at every point of a ``grid_deg`` grid (cell centres) and each time ``t_s`` after
    ``start_gpst``. Ranges and Doppler as :func:`service.studies.coarse_mc.simulate_and_solve`."""
    from service.studies.coarse_mc import simulate_and_solve

    cfg = cfg or SolverConfig()
    ccfg = ccfg or CoarseConfig()
    rng = np.random.default_rng(seed)
    lats = np.arange(-90.0 + grid_deg / 2, 90.0, grid_deg)
    lons = np.arange(-180.0 + grid_deg / 2, 180.0, grid_deg)
    out = []
    for dt in t_s:
        week, tow = normalize(start_gpst[0], start_gpst[1] + float(dt))
        for lat in lats:
            for lon in lons:
                trial = simulate_and_solve(
                    store,
                    iono,
                    week,
                    tow,
                    math.radians(float(lat)),
                    math.radians(float(lon)),
                    0.0,
                    np.zeros(3),
                    float(rng.uniform(-ccfg.time_prior_s, ccfg.time_prior_s)),
                    0,
                    rng,
                    cfg,
                    ccfg,
                )
                out.append(
                    SampleOutcome(
                        float(lat),
                        float(lon),
                        trial.n_sats,
                        trial.fixed,
                        trial.wrong,
                        trial.reason_code,
                        trial.error_m,
                    )
                )
    return out


def sample_figures(sample: Sequence[SampleOutcome], min_sats: int) -> dict[str, float | int]:
    """Area-weighted share fixed, over all points and over those meeting the condition."""
    if not sample:
        return {}
    w = np.array([math.cos(math.radians(s.lat_deg)) for s in sample])
    fixed = np.array([s.fixed for s in sample])
    cond = np.array([s.n_sats >= min_sats for s in sample])
    errs = [s.error_m for s in sample if s.fixed and s.error_m is not None]
    return {
        "solves": len(sample),
        "fixed": int(fixed.sum()),
        "wrong": sum(s.wrong for s in sample),
        "fixed_area_pct": round(100.0 * float(w @ fixed) / float(w.sum()), 2),
        "condition_area_pct": round(100.0 * float(w @ cond) / float(w.sum()), 2),
        "fixed_where_condition_pct": round(
            100.0 * float(w @ (fixed & cond)) / max(float(w @ cond), 1e-12), 2
        ),
        "fixed_without_condition": int((fixed & ~cond).sum()),
        "error_p50_m": round(float(np.median(errs)), 2) if errs else float("nan"),
        "error_max_m": round(float(np.max(errs)), 2) if errs else float("nan"),
    }


# --------------------------------------------------------------------------- output


def first_fix_document(res: FirstFixResult) -> dict[str, Any]:
    """The ``coverage --first-fix --json`` document."""
    w = res.weights()

    def row(grid: np.ndarray, per_t: np.ndarray) -> dict[str, float]:
        return {
            "area_time_pct": round(100.0 * float((w * grid).sum()), 3),
            "points_time_pct": round(100.0 * float(grid.mean()), 3),
            "area_min_epoch_pct": round(100.0 * float(per_t.min()), 3),
            "area_max_epoch_pct": round(100.0 * float(per_t.max()), 3),
            "area_first_epoch_pct": round(100.0 * float(per_t[0]), 3),
        }

    return {
        "paper": row(res.paper, res.paper_t),
        "coarse_time": row(res.coarse, res.coarse_t),
        "either": row(res.either, res.either_t),
        "satellites": list(res.prns),
        "fewest_above_mask": res.min_sats_seen,
        "elmask_deg": res.cfg.elmask_deg,
        "min_sats": res.cfg.min_sats,
        "beta": res.cfg.beta,
        "epochs": len(res.paper_t),
        "step_s": res.cfg.step_s,
        "grid_deg": res.cfg.grid_deg,
    }


LABELS = {
    "paper": "paper (>= 4 GEOs, GDOP_full < beta)",
    "coarse_time": "coarse time (>= 6 BDS above mask)",
    "either": "either",
}


def print_table(doc: dict[str, Any]) -> None:
    print(
        f"{'first-epoch fix':>36} {'area x time %':>14} {'points %':>9} "
        f"{'min epoch %':>12} {'max epoch %':>12}"
    )
    for key, label in LABELS.items():
        v = doc[key]
        print(
            f"{label:>36} {v['area_time_pct']:14.2f} {v['points_time_pct']:9.2f} "
            f"{v['area_min_epoch_pct']:12.2f} {v['area_max_epoch_pct']:12.2f}"
        )


def plot_first_fix(res: FirstFixResult, path: str) -> None:
    """Side-by-side maps: the share of the day each method fixes at each place."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise ConfigError(PLOT_HINT) from exc
    doc = first_fix_document(res)
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2), sharey=True)
    for ax, key, grid in zip(axes, ("paper", "coarse_time"), (res.paper, res.coarse), strict=True):
        im = ax.pcolormesh(
            res.lons_deg,
            res.lats_deg,
            100.0 * grid,
            vmin=0,
            vmax=100,
            cmap="viridis",
            shading="nearest",
        )
        v = doc[key]
        ax.set_title(f"{LABELS[key]}: {v['area_time_pct']:.1f} % of surface x time", fontsize=9)
        ax.set_xlabel("longitude [deg E]")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("latitude [deg N]")
    fig.colorbar(im, ax=axes, label="share of the time with a first-epoch fix [%]")
    fig.savefig(path, dpi=100)
    plt.close(fig)
