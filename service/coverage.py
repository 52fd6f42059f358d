"""``bdsfix coverage``: where and when the fast fix is usable (the paper's Table 3, Figs. 3-5).

At every epoch and grid point, the GEOs at or above the mask are the full measurements. Where
at least four are visible, GDOP_full = sqrt(trace(D^-1)) with D = G^T G over their rows
[-e^T, 1] (paper eqs. 12, 20), and the point is usable when GDOP_full < beta (eq. 21).
Per epoch and altitude the usable share is usable / (>= 4-GEO points), counted over grid
points as the paper does; "all" pools every epoch. The grid is regular in latitude and
longitude, so polar points count as much as equatorial ones.

The default constellation is the paper's Table 1 propagated as two-body orbits
(:func:`service.keplerian.table1_ephemerides`), its inertial RAAN turned Earth-fixed with
GMST. Vectorised over points and epochs: the 4x4 normal matrices are accumulated from the
(at most ten) GEOs and trace(D^-1) comes from closed-form cofactors, so no per-point loop or
LAPACK call remains.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import logging
import math
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.constants import is_geo
from service.errors import BdsfixError, ConfigError
from service.geometry import geodetic_to_ecef
from service.keplerian import TABLE1_EPOCH_UTC, table1_ephemerides
from service.orbit import EphemerisArrays, sat_pos_clock
from service.timebase import gpst_from_utc, gpst_to_bdt, normalize
from service.types import Ephemeris

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class CoverageConfig:
    days: float = 8.0
    step_s: float = 300.0
    grid_deg: float = 1.0
    altitudes_m: tuple[float, ...] = (0.0, 1_000_000.0)
    beta: float = 3000.0
    elmask_deg: float = 0.0


@dataclass(frozen=True, slots=True, eq=False)
class AltitudeResult:
    altitude_m: float
    n_geo4: np.ndarray  # per epoch: points with >= 4 GEOs
    n_usable: np.ndarray  # per epoch: of those, GDOP_full < beta
    area: dict[str, float]  # extent of the >= 4-GEO area at the first epoch
    geo4_first: np.ndarray  # bool grid (lat, lon) at the first epoch
    usable_worst: np.ndarray  # bool grid at the worst epoch
    worst_epoch: int

    @property
    def pct(self) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return 100.0 * self.n_usable / self.n_geo4


def trace_inverse_sym4(
    a00: np.ndarray,
    a01: np.ndarray,
    a02: np.ndarray,
    a03: np.ndarray,
    a11: np.ndarray,
    a12: np.ndarray,
    a13: np.ndarray,
    a22: np.ndarray,
    a23: np.ndarray,
    a33: np.ndarray,
) -> np.ndarray:
    """trace(D^-1) of symmetric 4x4 matrices given by their ten distinct elements.

    Laplace expansion by complementary 2x2 minors of rows (0, 1) and (2, 3); the diagonal
    of the inverse is cofactor / det. Singular matrices give inf (or a huge value).
    """
    s0 = a00 * a11 - a01 * a01
    s1 = a00 * a12 - a01 * a02
    s2 = a00 * a13 - a01 * a03
    s3 = a01 * a12 - a11 * a02
    s4 = a01 * a13 - a11 * a03
    s5 = a02 * a13 - a12 * a03
    c5 = a22 * a33 - a23 * a23
    c4 = a12 * a33 - a13 * a23
    c3 = a12 * a23 - a13 * a22
    c2 = a02 * a33 - a03 * a23
    c1 = a02 * a23 - a03 * a22
    c0 = a02 * a13 - a03 * a12
    det = s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0
    num = (a11 * c5 - a12 * c4 + a13 * c3) + (a00 * c5 - a02 * c2 + a03 * c1)
    num = num + (a03 * s4 - a13 * s2 + a33 * s0) + (a02 * s3 - a12 * s1 + a22 * s0)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = num / det
    return np.where(det > 0, out, np.inf)


def _geo_positions(
    ephs: Sequence[Ephemeris], t_s: np.ndarray, start: tuple[int, float], rebuild_daily: bool
) -> np.ndarray:
    """GEO ECEF positions (epochs, n_geo, 3) at times ``t_s`` after ``start`` (BDT)."""
    out = np.empty((len(t_s), len(ephs), 3))
    day = 86400.0
    for d0 in np.unique(np.floor(t_s / day)):
        sel = np.flatnonzero(np.floor(t_s / day) == d0)
        if rebuild_daily:  # two-body elements re-expressed each day: t_k stays small
            cur = [e for e in table1_ephemerides(float(d0 * day)) if is_geo(e.prn)]
            base = d0 * day
        else:
            cur, base = list(ephs), 0.0
        arr = EphemerisArrays.from_ephemerides(cur)
        for k in sel:
            week, sow = normalize(start[0], start[1] + float(t_s[k]))
            if rebuild_daily:
                sow = cur[0].toe_sow_s + float(t_s[k] - base)
                week = cur[0].week
            pos, _ = sat_pos_clock(arr, week, np.full(len(cur), sow))
            out[k] = pos
    return out


def _study_altitude(
    alt: float,
    sats: np.ndarray,
    lats: np.ndarray,
    lons: np.ndarray,
    cfg: CoverageConfig,
    progress: bool,
) -> AltitudeResult:
    """One altitude over all epochs; ``sats`` is (epochs, n_geo, 3)."""
    from tqdm import tqdm

    n_ep = len(sats)
    la, lo = np.meshgrid(np.radians(lats), np.radians(lons), indexing="ij")
    x = geodetic_to_ecef(la, lo, alt).reshape(-1, 3)
    up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1).reshape(
        -1, 3
    )
    sin_mask = math.sin(math.radians(cfg.elmask_deg))

    def unit_los(
        k: int, px: np.ndarray, pu: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Unit vectors to each GEO and visibility, satellite-major (n_geo, points)."""
        lx = sats[k, :, 0, None] - px[None, :, 0]
        ly = sats[k, :, 1, None] - px[None, :, 1]
        lz = sats[k, :, 2, None] - px[None, :, 2]
        inv = 1.0 / np.sqrt(lx * lx + ly * ly + lz * lz)
        lx *= inv
        ly *= inv
        lz *= inv
        vis = pu[None, :, 0] * lx + pu[None, :, 1] * ly + pu[None, :, 2] * lz >= sin_mask
        return lx, ly, lz, vis

    # Points that can see 4 GEOs at some time: the GEO geometry repeats daily, so one day
    # sampled every 30 min with a 1 deg margin on the mask finds them all.
    sin_mask_margin = math.sin(math.radians(cfg.elmask_deg - 1.0))
    cand = np.zeros(len(x), dtype=bool)
    for k in range(
        0, min(n_ep, max(1, round(86400 / cfg.step_s))), max(1, round(1800 / cfg.step_s))
    ):
        ex, ey, ez, _ = unit_los(k, x, up)
        vis = up[None, :, 0] * ex + up[None, :, 1] * ey + up[None, :, 2] * ez >= sin_mask_margin
        cand |= vis.sum(axis=0) >= 4
    idx = np.flatnonzero(cand)
    xc, upc = x[idx], up[idx]
    n_geo4 = np.zeros(n_ep, dtype=np.int64)
    n_use = np.zeros(n_ep, dtype=np.int64)
    packed: list[np.ndarray] = []
    geo4_first = np.zeros(len(x), dtype=bool)
    bar = tqdm(
        range(n_ep),
        desc=f"coverage {alt / 1e3:.0f} km",
        unit="epoch",
        disable=not progress,
        file=sys.stderr,
    )
    for k in bar:
        ex, ey, ez, vis = unit_los(k, xc, upc)
        m = np.flatnonzero(vis.sum(axis=0) >= 4)
        w = vis[:, m].astype(float)
        ex, ey, ez = ex[:, m] * w, ey[:, m] * w, ez[:, m] * w  # rows of masked GEOs vanish
        # D = sum_s w_s [-e_s, 1][-e_s, 1]^T (eq. 12), from its ten distinct elements
        tr = trace_inverse_sym4(
            (ex * ex).sum(0),
            (ex * ey).sum(0),
            (ex * ez).sum(0),
            -ex.sum(0),
            (ey * ey).sum(0),
            (ey * ez).sum(0),
            -ey.sum(0),
            (ez * ez).sum(0),
            -ez.sum(0),
            w.sum(0),
        )
        usable = tr < cfg.beta**2  # GDOP_full < beta (eqs. 20-21)
        n_geo4[k] = len(m)
        n_use[k] = int(usable.sum())
        grid = np.zeros(len(x), dtype=bool)
        grid[idx[m[usable]]] = True
        packed.append(np.packbits(grid))
        if k == 0:
            geo4_first[idx[m]] = True
    with np.errstate(invalid="ignore", divide="ignore"):
        share = np.where(n_geo4 > 0, n_use / np.maximum(n_geo4, 1), np.nan)
    worst = int(np.nanargmin(share))
    shape = (len(lats), len(lons))
    usable_worst = np.unpackbits(packed[worst])[: len(x)].astype(bool).reshape(shape)
    g4 = geo4_first.reshape(shape)
    lat_any, lon_any = lats[g4.any(axis=1)], lons[g4.any(axis=0)]
    area = {
        "lon_min_deg": float(lon_any.min()) if lon_any.size else math.nan,
        "lon_max_deg": float(lon_any.max()) if lon_any.size else math.nan,
        "lat_min_deg": float(lat_any.min()) if lat_any.size else math.nan,
        "lat_max_deg": float(lat_any.max()) if lat_any.size else math.nan,
    }
    return AltitudeResult(alt, n_geo4, n_use, area, g4, usable_worst, worst)


def run_coverage(
    cfg: CoverageConfig,
    ephs: Sequence[Ephemeris] | None = None,
    start_bdt: tuple[int, float] | None = None,
    progress: bool = True,
    workers: int | None = None,
) -> tuple[list[AltitudeResult], np.ndarray, np.ndarray]:
    """The study; returns per-altitude results and the latitude/longitude grids [deg].

    Altitudes run in parallel processes (one per core, at most one per altitude).
    """
    import os
    from concurrent.futures import ProcessPoolExecutor

    table1 = ephs is None
    if table1:
        ephs = [e for e in table1_ephemerides(0.0) if is_geo(e.prn)]
        start_bdt = (ephs[0].week, ephs[0].toe_sow_s)
    if ephs is None or start_bdt is None:
        raise ConfigError("a broadcast constellation needs its start time")
    geo_ephs = [e for e in ephs if is_geo(e.prn)]
    if len(geo_ephs) < 4:
        raise ConfigError(f"the constellation has {len(geo_ephs)} GEOs; the study needs 4")
    n_ep = math.floor(cfg.days * 86400.0 / cfg.step_s)
    t_s = np.arange(n_ep) * cfg.step_s
    sats = _geo_positions(geo_ephs, t_s, start_bdt, rebuild_daily=table1)
    lats = np.arange(-90.0, 90.0 + 1e-9, cfg.grid_deg)
    lons = np.arange(-180.0, 180.0 - 1e-9, cfg.grid_deg)
    n_workers = min(len(cfg.altitudes_m), workers or os.cpu_count() or 1)
    if n_workers <= 1:
        results = [_study_altitude(a, sats, lats, lons, cfg, progress) for a in cfg.altitudes_m]
    else:
        with ProcessPoolExecutor(max_workers=n_workers) as pool:
            futures = [
                pool.submit(_study_altitude, a, sats, lats, lons, cfg, progress and i == 0)
                for i, a in enumerate(cfg.altitudes_m)
            ]
            results = [f.result() for f in futures]
    return results, lats, lons


def _summary(n_geo4: np.ndarray, n_use: np.ndarray) -> dict[str, float]:
    ok = n_geo4 > 0
    pct = 100.0 * n_use[ok] / n_geo4[ok]
    return {
        "max_pct": round(float(pct.max()), 3),
        "min_pct": round(float(pct.min()), 3),
        "all_pct": round(float(100.0 * n_use.sum() / n_geo4.sum()), 3),
    }


def coverage_document(results: Sequence[AltitudeResult], n_points: int) -> dict[str, Any]:
    """The ``coverage --json`` contract."""
    doc: dict[str, Any] = {"altitudes": {}}
    for r in results:
        doc["altitudes"][str(round(r.altitude_m))] = {
            **_summary(r.n_geo4, r.n_usable),
            "area": r.area,
        }
    doc["all"] = _summary(
        np.sum([r.n_geo4 for r in results], axis=0), np.sum([r.n_usable for r in results], axis=0)
    )
    doc["epochs"] = len(results[0].n_geo4)
    doc["points"] = n_points
    return doc


def plot_coverage(
    results: Sequence[AltitudeResult],
    lats: np.ndarray,
    lons: np.ndarray,
    path: str,
    beta: float,
    step_s: float,
) -> None:
    """A map like the paper's Figs. 3 and 5 (matplotlib, from the ``plot`` extra)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise BdsfixError("--plot needs matplotlib: pip install 'bdsfix[plot]'") from exc
    fig, ax = plt.subplots(figsize=(10, 5.5))
    colors = ["tab:red", "tab:blue", "tab:green", "tab:purple"]
    for r, col in zip(results, colors, strict=False):
        ax.contour(
            lons, lats, r.geo4_first.astype(float), levels=[0.5], colors=[col], linewidths=1.5
        )
        ax.plot([], [], color=col, label=f">= 4 GEOs, {r.altitude_m / 1e3:.0f} km")
    r0 = results[0]
    ax.contourf(
        lons,
        lats,
        r0.usable_worst.astype(float),
        levels=[0.5, 1.5],
        colors=["tab:orange"],
        alpha=0.4,
    )
    ax.plot(
        [],
        [],
        color="tab:orange",
        alpha=0.4,
        lw=8,
        label=(
            f"GDOP_full < {beta:g} at the worst epoch "
            f"(+{r0.worst_epoch * step_s / 3600:.2f} h, {r0.pct[r0.worst_epoch]:.1f} %)"
        ),
    )
    ax.set_xlim(0, 220)
    ax.set_ylim(-90, 90)
    ax.set_xlabel("longitude [deg]")
    ax.set_ylabel("latitude [deg]")
    ax.grid(alpha=0.3)
    ax.set_title("Where the BDS fast fix is usable (>= 4 GEOs, GDOP_full < beta)")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main_coverage(args: argparse.Namespace) -> int:
    cfg = CoverageConfig(
        days=args.days,
        step_s=args.step_s,
        grid_deg=args.grid_deg,
        altitudes_m=tuple(args.altitudes_m),
        beta=args.beta,
        elmask_deg=args.elmask_deg,
    )
    if cfg.days <= 0 or cfg.step_s <= 0 or cfg.grid_deg <= 0:
        raise ConfigError("--days, --step-s and --grid-deg must be positive")
    ephs = None
    start = None
    if args.nav:
        from drivers.rinex import read_nav

        if not args.epoch:
            raise ConfigError("--nav needs --epoch ISO (UTC start of the study)")
        try:
            utc = dt.datetime.fromisoformat(args.epoch.replace("Z", ""))
        except ValueError as exc:
            raise ConfigError(f"--epoch {args.epoch!r} is not an ISO date-time") from exc
        start = gpst_to_bdt(*gpst_from_utc(utc))
        nav = read_nav(args.nav)
        ephs = []
        for items in nav.ephemerides.values():
            best = min(
                items, key=lambda e: abs((e.week - start[0]) * 604800 + e.toe_sow_s - start[1])
            )
            if best.health == 0:
                ephs.append(best)
        log.warning("--nav: broadcast orbits are extrapolated over %.1f days", cfg.days)
    elif args.epoch:
        raise ConfigError(f"--epoch applies to --nav; Table 1 is at {TABLE1_EPOCH_UTC}")
    results, lats, lons = run_coverage(cfg, ephs, start, progress=not args.no_progress)
    doc = coverage_document(results, len(lats) * len(lons))
    if args.json_out:
        text = json.dumps(doc, indent=2)
        if args.json_out == "-":
            print(text)
        else:
            with open(args.json_out, "w", encoding="utf-8") as fh:
                fh.write(text + "\n")
    if args.json_out != "-":
        print(f"{'':>16} {'max %':>8} {'min %':>8} {'all %':>8}  >=4-GEO area (first epoch)")
        for key, v in doc["altitudes"].items():
            a = v["area"]
            print(
                f"{float(key) / 1e3:>13.0f} km {v['max_pct']:8.1f} {v['min_pct']:8.1f} "
                f"{v['all_pct']:8.1f}  {a['lon_min_deg']:.0f}..{a['lon_max_deg']:.0f} E, "
                f"{a['lat_min_deg']:.0f}..{a['lat_max_deg']:.0f} N"
            )
        a = doc["all"]
        print(f"{'all':>16} {a['max_pct']:8.1f} {a['min_pct']:8.1f} {a['all_pct']:8.1f}")
    if args.plot:
        plot_coverage(results, lats, lons, args.plot, cfg.beta, cfg.step_s)
    return 0
