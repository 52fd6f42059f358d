"""``bdsfix coverage``: where and when the fast fix is usable (the paper's Table 3, Figs. 3-5).

At every epoch and grid point the GEOs at or above the elevation mask give the full
measurements. Where at least four are visible, GDOP_full = sqrt(trace(D^-1)) with
D = G^T G over their rows [-e^T, 1] (paper eqs. 12, 20), and the point is usable when
GDOP_full < beta (eq. 21).

- Shares are **counted over grid points**, without a cos(latitude) area weight, as the
  paper's Fig. 4 caption says ("proportion of points"). Per epoch and altitude the share is
  usable / (>= 4-GEO points); "all" pools every epoch (sum usable / sum >= 4-GEO).
  Point counting reproduces Table 3: min 76.61 / 75.90 / 76.27 % (surface, 1000 km, both)
  and all 99.38 / 99.37 / 99.37 %, against the paper's 76.7 / 75.9 / 76.3 and 99.4.
  Area weighting would give min 77.69 / 77.04 / 77.37 %.
- The grid is latitude -90..90 and longitude -180..(180 - step) in ``grid_deg`` steps on
  the CGCS2000 ellipsoid; elevations are measured from the ellipsoid normal.
- The >= 4-GEO area reported is its latitude/longitude extent at the study's first epoch,
  the instant of the paper's Figs. 1 and 3. For Table 1 that is 59-161 E, 78 S-78 N at the
  surface and 60-159 E, 76 S-77 N at 1000 km. The paper gives 79 N for the surface; with the
  GEOs' daily motion the north edge alternates between 78 and 79 N, and from 04:15 UTC all
  eight of the paper's extents match.
- The worst epoch (+3.5 h) is a plateau of about 8 minutes. East of about 140 E the
  58.6 E GEO has set, and the remaining four GEOs lie almost in one plane. So the minimum
  depends on where that GEO sets: moving it 0.1 deg east raises the surface minimum by
  0.08 points. Neither secular J2, a spherical Earth, geocentric verticals nor half-degree
  cell centres bring all three minima closer to the paper than plain two-body does.

The default constellation is the paper's Table 1, propagated two-body in inertial space and
turned Earth-fixed with GMST (:mod:`service.sim.constellation`). ``--nav`` uses a RINEX file's
broadcast GEO ephemerides instead (BDS-SIS-ICD-B1I-3.0 5.2.4.12 via :mod:`service.core.orbit`),
with the set of nearest t_oe at each epoch.

How it is made fast:
- Only points that can ever see four GEOs are kept. A visibility pre-pass finds them, with
  a margin derived from the GEOs' Earth-fixed speed.
- For each epoch and block of points, one small matrix product gives s.x and s.up.
- A second product, of per-satellite weights (1/r and 1/r^2, zero when masked) with the
  satellite coordinates, gives D's blocks expanded about the point.
- trace(D^-1) is compared with beta^2 through its Schur complement, in closed form and
  without a division.
- Epoch ranges run in worker processes.
"""

from __future__ import annotations

import logging
import math
import os
import sys
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from service.core.bds import is_geo
from service.core.constants import WEEK_S
from service.core.errors import ConfigError
from service.core.files import PLOT_HINT
from service.core.geometry import geodetic_to_ecef
from service.core.types import Ephemeris

log = logging.getLogger(__name__)

_POINT_BLOCK = 8192  # points per kernel call: keeps the (n_geo, block) temporaries in cache


@dataclass(frozen=True, slots=True)
class CoverageConfig:
    days: float = 8.0
    step_s: float = 300.0
    grid_deg: float = 1.0
    altitudes_m: tuple[float, ...] = (0.0, 1_000_000.0)
    beta: float = 3000.0
    elmask_deg: float = 0.0

    @property
    def n_epochs(self) -> int:
        return max(1, math.floor(self.days * 86400.0 / self.step_s + 1e-9))

    def lats_deg(self) -> np.ndarray:
        return np.arange(-90.0, 90.0 + 1e-9, self.grid_deg)

    def lons_deg(self) -> np.ndarray:
        return np.arange(-180.0, 180.0 - 1e-9, self.grid_deg)


@dataclass(frozen=True, slots=True, eq=False)
class AltitudeResult:
    """One altitude: per-epoch counts and the grids the map shows ((lat, lon) booleans)."""

    altitude_m: float
    n_geo4: np.ndarray  # per epoch: points with >= 4 GEOs visible
    n_usable: np.ndarray  # per epoch: of those, GDOP_full < beta
    geo4_first: np.ndarray  # >= 4 GEOs at the first epoch
    geo4_any: np.ndarray  # >= 4 GEOs at some epoch
    usable_worst: np.ndarray  # GDOP_full < beta at the worst epoch
    worst_epoch: int

    @property
    def pct(self) -> np.ndarray:
        """Usable share per epoch [%] (NaN where no point sees four GEOs)."""
        with np.errstate(invalid="ignore", divide="ignore"):
            return 100.0 * self.n_usable / self.n_geo4


@dataclass(frozen=True, slots=True, eq=False)
class CoverageResult:
    altitudes: tuple[AltitudeResult, ...]
    lats_deg: np.ndarray
    lons_deg: np.ndarray
    step_s: float


# --------------------------------------------------------------------------- kernel


def _normal_cofactors(
    sat_ecef_m: np.ndarray,
    x_t: np.ndarray,
    up_t: np.ndarray,
    xx: np.ndarray,
    ux: np.ndarray,
    sin_mask: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Visible count n, and q, det with trace(D^-1) = q / det + 1/n, for one epoch.

    ``sat_ecef_m`` (n_geo, 3); ``x_t``/``up_t`` (3, P) point positions and ellipsoid
    normals; ``xx`` = |x|^2 and ``ux`` = up.x (P,). D (eq. 12) = sum_s w_s [-e_s; 1][-e_s; 1]^T
    with e_s = (s - x)/r_s and w_s = 1 when the GEO is at or above the mask. Its blocks
    M = sum w e e^T, b = sum w e and n = sum w are expanded about x so that two small
    matrix products over the GEOs give them for all points at once.
    """
    r = sat_ecef_m @ x_t  # s.x
    sin_el = sat_ecef_m @ up_t  # s.up
    r *= -2.0
    r += np.einsum("ij,ij->i", sat_ecef_m, sat_ecef_m)[:, None]
    r += xx
    np.sqrt(r, out=r)
    np.reciprocal(r, out=r)  # 1/range
    sin_el -= ux
    sin_el *= r  # up.e = sin(elevation)
    vis = sin_el >= sin_mask
    q1 = np.multiply(r, vis, out=sin_el)  # w/r
    q2 = np.multiply(q1, r, out=r)  # w/r^2
    n_vis = vis.sum(axis=0, dtype=np.int8)
    sx, sy, sz = sat_ecef_m.T
    a = np.stack([sx * sx, sx * sy, sx * sz, sy * sy, sy * sz, sz * sz, sx, sy, sz]) @ q2
    c = q2.sum(axis=0)
    bb = sat_ecef_m.T @ q1
    f = q1.sum(axis=0)
    x0, x1, x2 = x_t
    u0 = a[6] - x0 * c
    u1 = a[7] - x1 * c
    u2 = a[8] - x2 * c
    # sum w e_i e_j = A_ij - x_i B_j - x_j B_i + x_i x_j C = A_ij - x_i u_j - x_j B_i
    m00 = a[0] - x0 * u0 - x0 * a[6]
    m01 = a[1] - x0 * u1 - x1 * a[6]
    m02 = a[2] - x0 * u2 - x2 * a[6]
    m11 = a[3] - x1 * u1 - x1 * a[7]
    m12 = a[4] - x1 * u2 - x2 * a[7]
    m22 = a[5] - x2 * u2 - x2 * a[8]
    b0 = bb[0] - x0 * f  # sum w e
    b1 = bb[1] - x1 * f
    b2 = bb[2] - x2 * f
    q, det = _schur_parts(m00, m01, m02, m11, m12, m22, b0, b1, b2, n_vis.astype(float))
    return n_vis, q, det


def _schur_parts(
    m00: np.ndarray,
    m01: np.ndarray,
    m02: np.ndarray,
    m11: np.ndarray,
    m12: np.ndarray,
    m22: np.ndarray,
    b0: np.ndarray,
    b1: np.ndarray,
    b2: np.ndarray,
    n: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """trace(D^-1) of D = [[M, -b], [-b^T, n]] as q / det + 1/n, by the Schur complement.

    With g = b/n and S = M - b g^T (the scatter of the unit vectors about their mean),
    D^-1 has S^-1 top left and 1/n + g^T S^-1 g bottom right, so
    trace(D^-1) = [tr adj(S) + g^T adj(S) g] / det(S) + 1/n. In float64 this keeps GDOP
    near 3000 to about 1e-9 relative, as LAPACK's inverse does; a 4x4 cofactor expansion
    loses a factor of 20.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        g0, g1, g2 = b0 / n, b1 / n, b2 / n
    s00 = m00 - b0 * g0
    s01 = m01 - b0 * g1
    s02 = m02 - b0 * g2
    s11 = m11 - b1 * g1
    s12 = m12 - b1 * g2
    s22 = m22 - b2 * g2
    c00 = s11 * s22 - s12 * s12
    c11 = s00 * s22 - s02 * s02
    c22 = s00 * s11 - s01 * s01
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    c12 = s01 * s02 - s00 * s12
    det = s00 * c00 + s01 * c01 + s02 * c02
    q = c00 * (1.0 + g0 * g0) + c11 * (1.0 + g1 * g1) + c22 * (1.0 + g2 * g2)
    q += 2.0 * (g0 * g1 * c01 + g0 * g2 * c02 + g1 * g2 * c12)
    return q, det


def trace_inverse_normal(d: np.ndarray) -> np.ndarray:
    """trace(D^-1) of GDOP normal matrices D (..., 4, 4) = G^T G, G rows [-e^T, 1] (eq. 20).

    Closed form (:func:`_schur_parts`); inf where D is singular.
    """
    d = np.asarray(d, dtype=float)
    q, det = _schur_parts(
        d[..., 0, 0],
        d[..., 0, 1],
        d[..., 0, 2],
        d[..., 1, 1],
        d[..., 1, 2],
        d[..., 2, 2],
        -d[..., 0, 3],
        -d[..., 1, 3],
        -d[..., 2, 3],
        d[..., 3, 3],
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        return np.where(det > 0, q / det + 1.0 / d[..., 3, 3], np.inf)


def _points(
    lats_deg: np.ndarray, lons_deg: np.ndarray, alt_m: float
) -> tuple[np.ndarray, np.ndarray]:
    """Grid positions and ellipsoid normals, (P, 3) each, latitude-major."""
    la, lo = np.meshgrid(np.radians(lats_deg), np.radians(lons_deg), indexing="ij")
    x = geodetic_to_ecef(la, lo, alt_m).reshape(-1, 3)
    up = np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)
    return x, up.reshape(-1, 3)


def geo_gdop(
    sat_ecef_m: np.ndarray, x_ecef_m: np.ndarray, up_ecef: np.ndarray, elmask_deg: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Visible GEO count and GDOP_full (eq. 20; inf below four GEOs) at points (P, 3).

    ``sat_ecef_m`` (n, 3) are the GEOs at one epoch; ``up_ecef`` the points' unit normals.
    """
    x_t = np.ascontiguousarray(np.asarray(x_ecef_m, dtype=float).T)
    up_t = np.ascontiguousarray(np.asarray(up_ecef, dtype=float).T)
    n_vis, q, det = _normal_cofactors(
        np.asarray(sat_ecef_m, dtype=float),
        x_t,
        up_t,
        np.einsum("ip,ip->p", x_t, x_t),
        np.einsum("ip,ip->p", up_t, x_t),
        math.sin(math.radians(elmask_deg)),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        g = np.sqrt(np.where((n_vis >= 4) & (det > 0), q / det + 1.0 / n_vis, np.inf))
    return n_vis, g


# --------------------------------------------------------------------------- study


@dataclass(frozen=True, slots=True, eq=False)
class _Block:
    """Candidate points of one altitude, transposed for the kernel."""

    x_t: np.ndarray
    up_t: np.ndarray
    xx: np.ndarray
    ux: np.ndarray
    index: np.ndarray  # into the full grid

    @classmethod
    def of(cls, x: np.ndarray, up: np.ndarray, index: np.ndarray) -> _Block:
        x_t = np.ascontiguousarray(x[index].T)
        up_t = np.ascontiguousarray(up[index].T)
        return cls(
            x_t,
            up_t,
            np.einsum("ip,ip->p", x_t, x_t),
            np.einsum("ip,ip->p", up_t, x_t),
            index,
        )

    def parts(self) -> Iterator[_Block]:
        n = self.x_t.shape[1]
        for p0 in range(0, n, _POINT_BLOCK):
            s = slice(p0, p0 + _POINT_BLOCK)
            yield _Block(self.x_t[:, s], self.up_t[:, s], self.xx[s], self.ux[s], self.index[s])


def _epoch_usable(
    sats_k: np.ndarray, blk: _Block, beta: float, sin_mask: float
) -> tuple[np.ndarray, np.ndarray]:
    """(>= 4 GEOs, GDOP_full < beta) booleans over the block's points at one epoch."""
    b2 = beta * beta
    g4_parts, use_parts = [], []
    for part in blk.parts():
        n_vis, q, det = _normal_cofactors(sats_k, part.x_t, part.up_t, part.xx, part.ux, sin_mask)
        g4 = n_vis >= 4
        g4_parts.append(g4)
        # trace(D^-1) = q/det + 1/n < beta^2 (eqs. 20, 21), without a division
        use_parts.append(g4 & (det > 0) & (q < (b2 - 1.0 / np.maximum(n_vis, 1)) * det))
    return np.concatenate(g4_parts), np.concatenate(use_parts)


def _count_range(
    sats: np.ndarray, blk: _Block, beta: float, sin_mask: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-epoch counts over ``sats`` (K, n, 3), and which points ever see four GEOs."""
    n4 = np.zeros(len(sats), dtype=np.int64)
    nu = np.zeros(len(sats), dtype=np.int64)
    ever = np.zeros(blk.x_t.shape[1], dtype=bool)
    for k in range(len(sats)):
        g4, use = _epoch_usable(sats[k], blk, beta, sin_mask)
        n4[k] = np.count_nonzero(g4)
        nu[k] = np.count_nonzero(use)
        ever |= g4
    return n4, nu, ever


def _candidates(
    sats: np.ndarray, x: np.ndarray, up: np.ndarray, step_s: float, elmask_deg: float
) -> np.ndarray:
    """Indices of grid points that may see >= 4 GEOs at some study epoch.

    Visibility is sampled at most every 3600 s over the whole study (last epoch included)
    with the mask lowered by the largest angle a GEO's line of sight can turn in half a
    sample interval (its Earth-fixed speed times the interval over the shortest range) plus
    0.1 deg. For Table 1 that is 0.26 deg, and the candidates are about 22 % of the grid.
    """
    every = max(1, math.floor(3600.0 / step_s))
    ks = np.unique(np.append(np.arange(0, len(sats), every), len(sats) - 1))
    steps_m = np.linalg.norm(np.diff(sats, axis=0), axis=-1)
    speed = float(steps_m.max()) / step_s if steps_m.size else 0.0
    r_min = max(1.0, float(np.linalg.norm(sats, axis=-1).min() - np.linalg.norm(x, axis=1).max()))
    turn_deg = math.degrees(speed * every * step_s / 2.0 / r_min)
    sin_mask = math.sin(math.radians(max(-90.0, elmask_deg - turn_deg - 0.1)))
    blk = _Block.of(x, up, np.arange(len(x)))
    ever = np.zeros(len(x), dtype=bool)
    for k in ks:
        for part in blk.parts():
            r = sats[k] @ part.x_t
            r *= -2.0
            r += np.einsum("ij,ij->i", sats[k], sats[k])[:, None]
            r += part.xx
            sin_el = sats[k] @ part.up_t - part.ux
            ever[part.index] |= (sin_el >= sin_mask * np.sqrt(r)).sum(axis=0) >= 4
    return np.flatnonzero(ever)


def _work(
    task: tuple[int, int, int], sats: np.ndarray, blocks: Sequence[_Block], cfg: CoverageConfig
) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray]:
    ia, k0, k1 = task
    n4, nu, ever = _count_range(
        sats[k0:k1], blocks[ia], cfg.beta, math.sin(math.radians(cfg.elmask_deg))
    )
    return ia, k0, n4, nu, ever


_SHARED: dict[str, Any] = {}


def _work_shared(task: tuple[int, int, int]) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray]:
    return _work(task, _SHARED["sats"], _SHARED["blocks"], _SHARED["cfg"])


def _init_shared(sats: np.ndarray, blocks: Sequence[_Block], cfg: CoverageConfig) -> None:
    _SHARED.update(sats=sats, blocks=blocks, cfg=cfg)


def run_coverage(
    cfg: CoverageConfig,
    sats_ecef_m: np.ndarray | None = None,
    progress: bool | None = False,
    workers: int | None = None,
) -> CoverageResult:
    """The study over GEO positions ``sats_ecef_m`` (epochs, n_geo, 3), one row per epoch
    ``cfg.step_s`` apart; default: the paper's Table 1 from its epoch.

    ``progress``: tqdm bar on stderr (None: only on a terminal). ``workers``: processes
    (default: the CPUs this process may use).
    """
    from tqdm import tqdm

    if cfg.days <= 0 or cfg.step_s <= 0 or cfg.grid_deg <= 0 or not cfg.altitudes_m:
        raise ConfigError("--days, --step-s and --grid-deg must be positive, with an altitude")
    if sats_ecef_m is None:
        sats_ecef_m = table1_geo_positions(np.arange(cfg.n_epochs) * cfg.step_s)
    sats = np.ascontiguousarray(sats_ecef_m, dtype=float)
    if sats.ndim != 3 or sats.shape[1] < 4:
        raise ConfigError(f"the study needs at least 4 GEOs, got positions {sats.shape}")
    n_ep = len(sats)
    lats, lons = cfg.lats_deg(), cfg.lons_deg()
    grids = [_points(lats, lons, a) for a in cfg.altitudes_m]
    blocks = [
        _Block.of(x, up, _candidates(sats, x, up, cfg.step_s, cfg.elmask_deg)) for x, up in grids
    ]
    if workers is None:
        workers = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else 1
    n_chunks = max(1, min(n_ep, 8 * workers)) if workers > 1 else max(1, min(n_ep, 64))
    edges = np.linspace(0, n_ep, n_chunks + 1).round().astype(int)
    tasks = [
        (ia, int(edges[j]), int(edges[j + 1]))
        for j in range(n_chunks)
        for ia in range(len(blocks))
        if edges[j + 1] > edges[j]
    ]
    n4 = np.zeros((len(blocks), n_ep), dtype=np.int64)
    nu = np.zeros((len(blocks), n_ep), dtype=np.int64)
    ever = [np.zeros(b.index.size, dtype=bool) for b in blocks]
    bar = tqdm(
        total=n_ep * len(blocks),
        desc="coverage",
        unit="epoch",
        disable=None if progress is None else not progress,
        file=sys.stderr,
    )

    def collect(out: tuple[int, int, np.ndarray, np.ndarray, np.ndarray]) -> None:
        ia, k0, c4, cu, ev = out
        n4[ia, k0 : k0 + len(c4)] = c4
        nu[ia, k0 : k0 + len(cu)] = cu
        ever[ia] |= ev
        bar.update(len(c4))

    with bar:
        if workers <= 1:
            for t in tasks:
                collect(_work(t, sats, blocks, cfg))
        else:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor, as_completed

            # fork: the workers inherit the arrays and the parent's malloc state (spawned
            # workers were twice as slow here, in page faults from fresh heaps)
            method = "fork" if "fork" in mp.get_all_start_methods() else "spawn"
            ctx = mp.get_context(method)
            with ProcessPoolExecutor(
                max_workers=workers,
                mp_context=ctx,
                initializer=_init_shared,
                initargs=(sats, blocks, cfg),
            ) as pool:
                for fut in as_completed([pool.submit(_work_shared, t) for t in tasks]):
                    collect(fut.result())

    shape = (len(lats), len(lons))
    sin_mask = math.sin(math.radians(cfg.elmask_deg))
    results = []
    for ia, (alt, blk) in enumerate(zip(cfg.altitudes_m, blocks, strict=True)):
        with np.errstate(invalid="ignore", divide="ignore"):
            share = np.where(n4[ia] > 0, nu[ia] / np.maximum(n4[ia], 1), np.inf)
        worst = int(np.argmin(share))
        g4_first, _ = _epoch_usable(sats[0], blk, cfg.beta, sin_mask)
        _, use_worst = _epoch_usable(sats[worst], blk, cfg.beta, sin_mask)
        results.append(
            AltitudeResult(
                altitude_m=float(alt),
                n_geo4=n4[ia],
                n_usable=nu[ia],
                geo4_first=_scatter(blk.index, g4_first, shape),
                geo4_any=_scatter(blk.index, ever[ia], shape),
                usable_worst=_scatter(blk.index, use_worst, shape),
                worst_epoch=worst,
            )
        )
    return CoverageResult(tuple(results), lats, lons, cfg.step_s)


def _scatter(index: np.ndarray, values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    out = np.zeros(shape[0] * shape[1], dtype=bool)
    out[index] = values
    return out.reshape(shape)


# --------------------------------------------------------------------------- constellations


def table1_geo_positions(t_s: np.ndarray) -> np.ndarray:
    """ECEF positions [m] (len(t_s), 5, 3) of Table 1's GEOs ``t_s`` after its epoch."""
    from service.sim.constellation import positions_ecef, table1

    return positions_ecef(table1().geos(), t_s)


def nav_geo_positions(
    ephemerides: Mapping[str, Sequence[Ephemeris]],
    start_bdt: tuple[int, float],
    t_s: np.ndarray,
    max_age_s: float = 4 * 3600.0,
) -> tuple[tuple[str, ...], np.ndarray]:
    """Broadcast GEO positions (len(t_s), n_geo, 3) at ``t_s`` seconds after ``start_bdt``.

    At each epoch every GEO uses its set with the nearest t_oe (ICD 5.2.4.12) among those
    :func:`service.core.ephemeris.ephemeris_problem` accepts (healthy and sane).
    Broadcast sets are fits to a few hours of orbit, so a GEO whose nearest set is more than
    ``max_age_s`` from some study epoch is left out with a warning.
    """
    from service.core.ephemeris import ephemeris_problem
    from service.core.orbit import EphemerisArrays, sat_pos_clock

    prns, cols, spans = [], [], []
    for prn in sorted(p for p in ephemerides if is_geo(p)):
        sets = [e for e in ephemerides[prn] if ephemeris_problem(e) is None]
        if not sets:
            log.warning("%s: no healthy ephemeris that passes the entry checks: left out", prn)
            continue
        toe = np.array(
            [(e.week - start_bdt[0]) * WEEK_S + e.toe_sow_s - start_bdt[1] for e in sets]
        )
        spans.append((toe.min(), toe.max()))
        pick = np.abs(t_s[:, None] - toe[None, :]).argmin(axis=1)
        age = float(np.abs(t_s - toe[pick]).max())
        if age > max_age_s:
            log.warning(
                "%s: some study epochs are %.1f h from its nearest ephemeris (limit %.1f h): "
                "left out",
                prn,
                age / 3600,
                max_age_s / 3600,
            )
            continue
        arr = EphemerisArrays.from_ephemerides([sets[i] for i in pick])
        pos, _ = sat_pos_clock(arr, np.full(len(t_s), start_bdt[0]), start_bdt[1] + t_s)
        prns.append(prn)
        cols.append(pos)
    if len(prns) < 4:
        span = (
            f"healthy GEO t_oe from {min(a for a, _ in spans) / 3600:+.1f} h to "
            f"{max(b for _, b in spans) / 3600:+.1f} h of the study start"
            if spans
            else "no healthy GEO ephemeris"
        )
        raise ConfigError(
            f"only {len(prns)} GEOs have ephemerides within {max_age_s / 3600:.0f} h of every "
            f"study epoch (0 to {float(t_s[-1]) / 3600:.1f} h; the file has {span}); "
            "the study needs 4: choose --start and --days inside the file's span"
        )
    return tuple(prns), np.stack(cols, axis=1)


# --------------------------------------------------------------------------- output


def _summary(n_geo4: np.ndarray, n_use: np.ndarray) -> dict[str, float]:
    ok = n_geo4 > 0
    if not ok.any():
        return {"max_pct": 0.0, "min_pct": 0.0, "all_pct": 0.0}
    pct = 100.0 * n_use[ok] / n_geo4[ok]
    return {
        "max_pct": round(float(pct.max()), 3),
        "min_pct": round(float(pct.min()), 3),
        "all_pct": round(float(100.0 * n_use.sum() / n_geo4.sum()), 3),
    }


def _extent(mask: np.ndarray, lats: np.ndarray, lons: np.ndarray) -> dict[str, float]:
    lat_any, lon_any = lats[mask.any(axis=1)], lons[mask.any(axis=0)]
    if not lat_any.size:
        return {}
    return {
        "lon_min_deg": float(lon_any.min()),
        "lon_max_deg": float(lon_any.max()),
        "lat_min_deg": float(lat_any.min()),
        "lat_max_deg": float(lat_any.max()),
    }


def coverage_document(res: CoverageResult) -> dict[str, Any]:
    """The ``coverage --json`` contract (altitude keys in whole metres)."""
    doc: dict[str, Any] = {"altitudes": {}}
    for r in res.altitudes:
        doc["altitudes"][str(round(r.altitude_m))] = {
            **_summary(r.n_geo4, r.n_usable),
            "area": _extent(r.geo4_first, res.lats_deg, res.lons_deg),
        }
    doc["all"] = _summary(
        np.sum([r.n_geo4 for r in res.altitudes], axis=0),
        np.sum([r.n_usable for r in res.altitudes], axis=0),
    )
    doc["epochs"] = len(res.altitudes[0].n_geo4)
    doc["points"] = len(res.lats_deg) * len(res.lons_deg)
    return doc


def plot_coverage(res: CoverageResult, path: str, beta: float) -> None:
    """A map like the paper's Figs. 3 and 5 (matplotlib, from the ``plot`` extra)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise ConfigError(PLOT_HINT) from exc
    lats, lons = res.lats_deg, res.lons_deg
    fig, ax = plt.subplots(figsize=(10, 5.5))
    r0 = res.altitudes[0]
    ax.contourf(
        lons,
        lats,
        r0.usable_worst.astype(float),
        levels=[0.5, 1.5],
        colors=["tab:orange"],
        alpha=0.45,
    )
    ax.plot(
        [],
        [],
        color="tab:orange",
        alpha=0.45,
        lw=8,
        label=(
            f"GDOP_full < {beta:g} at the worst epoch, {r0.altitude_m / 1e3:.0f} km "
            f"(+{r0.worst_epoch * res.step_s / 3600:.2f} h, {r0.pct[r0.worst_epoch]:.1f} %)"
        ),
    )
    colors = ["tab:red", "tab:blue", "tab:green", "tab:purple"]
    for r, col in zip(res.altitudes, colors, strict=False):
        ax.contour(lons, lats, r.geo4_first.astype(float), levels=[0.5], colors=[col])
        ax.plot(
            [], [], color=col, label=f">= 4 GEOs at the first epoch, {r.altitude_m / 1e3:.0f} km"
        )
    ax.set_xlim(0, 220)
    ax.set_ylim(-90, 90)
    ax.set_xlabel("longitude [deg E]")
    ax.set_ylabel("latitude [deg N]")
    ax.grid(alpha=0.3)
    ax.set_title("Where the BDS fast fix is usable (>= 4 GEOs, GDOP_full < beta)")
    ax.legend(loc="lower left", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
