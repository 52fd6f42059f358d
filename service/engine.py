"""The positioning engine: the Zhao-Cui-Lu fast fix and conventional SPP, as pure functions.

The fast fix follows the paper's eqs. (1)-(16): unknowns [x, y, z, b, N_1..N_m] start at zero;
fractional rows z_j = |X_j - x| + b - N_j c T_j get a -c T_j column (eq. 11); x and b take the
least-squares step (eq. 10) while each N_j takes round(dN_j) (eq. 13); transmit times use
z_j + N_j c T_j (eq. 5); iteration stops when the position/clock step is below theta and every
rounded dN is zero (eq. 14). The GEO-GDOP eigenvalue gate (eqs. 12, 20-21) is then evaluated
over the full rows at the converged position, and the state is corrected with the integers
fixed (eqs. 15-16). With every measurement full there are no N columns and the procedure is
conventional single-point positioning, which is how :func:`solve_spp` is built.

Two phases, so that fast and SPP share one fixed point:
1. From the Earth's centre with no corrections and no elevation mask (they mean nothing
   before the position does): the paper's iteration, gate and final correction.
2. From that position: elevation mask (a masked fractional satellite loses its row; its
   integer is already fixed), Klobuchar and Saastamoinen corrections, elevation weights,
   iterated to convergence. A post-fit residual check then refuses any solution whose
   residuals betray a wrong integer set or an outlier.

With every measurement full and an approximate position given (``x0_ecef_m``), phase 1 has
nothing to resolve and phase 2 starts there: conventional SPP, the same solution.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from service.constants import C_M_S, is_geo
from service.corrections import klobuchar_bds_m, klobuchar_gps_m, saastamoinen_m, sagnac_rotate
from service.ephemeris import EphemerisStore
from service.geometry import ecef_to_geodetic, enu_rotation, gdop, look_angles
from service.orbit import EphemerisArrays, sat_pos_clock
from service.timebase import gpst_to_bdt
from service.types import Ephemeris, Fix, KlobucharParams, MeasurementEpoch, SatView

log = logging.getLogger(__name__)

IonoChoice = Literal["auto", "bds", "gps", "off"]


@dataclass(frozen=True, slots=True)
class SolverConfig:
    """Solver settings. ``beta=None`` derives the gate from T and ``range_error_m``."""

    elmask_deg: float = 10.0
    beta: float | None = None
    range_error_m: float = 50.0
    iono: IonoChoice = "auto"
    tropo: bool = True
    weighted: bool = True
    max_iter: int = 30
    theta_m: float = 1e-3
    conv_m: float = 1e-4
    resid_max_m: float = 1000.0
    sigma_a_m: float = 0.3
    sigma_b_m: float = 0.3
    # A known approximate position (a reference in studies, the last fix in a stream).
    # With every measurement full the solve is then conventional SPP from it (phase 2
    # alone); with fractional rows phase 1 starts there. None: the paper's start, the
    # Earth's centre (eq. 3). Either way the least-squares solution is the same.
    x0_ecef_m: tuple[float, float, float] | None = None


def derive_beta(period_s: float, range_error_m: float) -> float:
    """Gate threshold beta = alpha / max|d rho| with alpha = c T / 2 (paper eq. 21).

    For T = 1 ms and a 50 m 3-sigma range error this is 2998, the paper's 3000.
    """
    return C_M_S * period_s / 2.0 / range_error_m


@dataclass(frozen=True, slots=True, eq=False)
class _Rows:
    """Measurement rows of one solve, aligned with their ephemerides."""

    prn: tuple[str, ...]
    z_m: np.ndarray  # full pseudorange, or fractional value in [0, cT)
    ct_m: np.ndarray  # c*T for fractional rows, 0 for full rows
    cn0_dbhz: np.ndarray
    eph: EphemerisArrays
    # satellite positions and clocks at the transmit times of eqs. (4)-(5): those depend on
    # the receive time and z + N cT only, not on the receiver state, so iterations that keep
    # N reuse them (key: :func:`_orbit_key`)
    orbit_cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def frac(self) -> np.ndarray:
        return self.ct_m > 0

    def take(self, idx: np.ndarray) -> _Rows:
        """Rows ``idx``; the cached satellite states come along."""
        cache = {}
        for key, (sat, clk) in self.orbit_cache.items():
            n_int, when = np.frombuffer(key[: -_TIME_KEY.size]), key[-_TIME_KEY.size :]
            cache[n_int[idx].tobytes() + when] = (sat[idx], clk[idx])
        return _Rows(
            tuple(self.prn[i] for i in idx),
            self.z_m[idx],
            self.ct_m[idx],
            self.cn0_dbhz[idx],
            self.eph.take(idx),
            cache,
        )


_TIME_KEY = struct.Struct("<id")


def _orbit_key(n_int: np.ndarray, bdt_week: int, bdt_sow_s: float) -> bytes:
    """Key of :attr:`_Rows.orbit_cache`: the integers' bytes, then the receive time's."""
    return n_int.tobytes() + _TIME_KEY.pack(bdt_week, bdt_sow_s)


@dataclass(slots=True)
class _Geometry:
    los: np.ndarray  # unit vectors receiver -> satellite (n, 3)
    pred_m: np.ndarray  # predicted pseudorange without the receiver clock and N terms
    sat_ecef_m: np.ndarray

    def take(self, idx: np.ndarray) -> _Geometry:
        return _Geometry(self.los[idx], self.pred_m[idx], self.sat_ecef_m[idx])


def _geometry(
    rows: _Rows, bdt_week: int, bdt_sow_s: float, x: np.ndarray, n_int: np.ndarray
) -> _Geometry:
    """Satellite positions at transmit time (paper eqs. 4-5) and geometric ranges."""
    key = _orbit_key(n_int, bdt_week, bdt_sow_s)
    cached = rows.orbit_cache.get(key)
    if cached is None:
        if len(rows.orbit_cache) > 64:
            rows.orbit_cache.clear()
        eph = rows.eph
        t1 = bdt_sow_s - (rows.z_m + n_int * rows.ct_m) / C_M_S
        t_tx = t1 - (eph.af0_s + eph.af1_s_s * (t1 - eph.toc_sow_s))
        cached = rows.orbit_cache[key] = sat_pos_clock(eph, bdt_week, t_tx)
    sat, clk_s = cached
    d = sat - x
    sat = sagnac_rotate(sat, np.sqrt(np.einsum("ij,ij->i", d, d)) / C_M_S)
    d = sat - x
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    return _Geometry(los=d / rho[:, None], pred_m=rho - C_M_S * clk_s, sat_ecef_m=sat)


def _full_cost(rows: _Rows, geo: _Geometry, b: float, full_idx: np.ndarray) -> float:
    """Sum of squared residuals of the full rows (no corrections): the line-search merit."""
    r = rows.z_m[full_idx] - geo.pred_m[full_idx] - b
    return float(r @ r)


def _lsq(h: np.ndarray, dz: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """The (weighted) least-squares step (H^T W H)^-1 H^T W dz (paper eqs. 10 and 16).

    Solved through the normal equations: a handful of unknowns, where an SVD per iteration
    costs more than the rest of the iteration; a singular system falls back to numpy's
    minimum-norm least squares (raising LinAlgError only where that fails too)."""
    ht = h.T if w is None else h.T * w
    try:
        return np.linalg.solve(ht @ h, ht @ dz)
    except np.linalg.LinAlgError:
        if w is not None:
            sw = np.sqrt(w)
            h, dz = h * sw[:, None], dz * sw
        step, *_ = np.linalg.lstsq(h, dz, rcond=None)
        return np.asarray(step)


def _design(los: np.ndarray) -> np.ndarray:
    return np.concatenate([-los, np.ones((len(los), 1))], axis=1)


def _iono_model(
    store_iono: KlobucharParams | None, gps_iono: KlobucharParams | None, choice: IonoChoice
) -> KlobucharParams | None:
    if choice == "off":
        return None
    if choice == "bds":
        return store_iono if store_iono is not None and store_iono.system == "BDS" else None
    if choice == "gps":
        return gps_iono
    return store_iono if store_iono is not None else gps_iono


@dataclass(frozen=True, slots=True)
class IonoSet:
    """Broadcast ionosphere coefficients available to the solver."""

    bds: KlobucharParams | None = None
    gps: KlobucharParams | None = None


def _plausible(x: np.ndarray) -> bool:
    r = float(np.linalg.norm(x))
    return 6.0e6 < r < 8.5e6


class _Decline(Exception):
    def __init__(self, reason: str, **info: object) -> None:
        super().__init__(reason)
        self.reason = reason
        self.info = info


def _phase1(
    rows: _Rows, bdt_week: int, bdt_sow: float, n_int: np.ndarray, cfg: SolverConfig, base: Fix
) -> Fix | tuple[np.ndarray, float, np.ndarray, _Geometry, float, int]:
    """Phase 1: the paper's iteration (eqs. 3-14) from the Earth's centre (or
    ``cfg.x0_ecef_m``) without corrections, the GEO-GDOP gate (eqs. 12, 20-21) and the
    fixed-integer correction (eqs. 15-16). Returns ``base`` with a reason when it declines,
    else the position, clock bias, integers, geometry, GDOP_full and iteration count."""
    x = np.zeros(3) if cfg.x0_ecef_m is None else np.array(cfg.x0_ecef_m, dtype=float)
    b = 0.0
    frac = rows.frac
    n_frac = int(frac.sum())
    frac_idx = np.flatnonzero(frac)
    full_idx = np.flatnonzero(~frac)
    converged = False
    it = 0
    geo = _geometry(rows, bdt_week, bdt_sow, x, n_int)
    cost = _full_cost(rows, geo, b, full_idx)
    for it in range(1, cfg.max_iter + 1):
        dz = rows.z_m + n_int * rows.ct_m - geo.pred_m - b  # eqs. (7)-(8)
        h = _design(geo.los)
        if n_frac:
            # eq. (11) with the ambiguity in metres (column -1 instead of -cT) for conditioning
            hn = np.zeros((len(rows.prn), n_frac))
            hn[frac_idx, np.arange(n_frac)] = -1.0
            h = np.concatenate([h, hn], axis=1)
        try:
            step = _lsq(h, dz)  # eq. (10)
        except np.linalg.LinAlgError:
            return replace(base, reason="singular geometry in the fast-fix iteration")
        # Backtracking: the float ambiguities absorb the fractional rows, so x and b move on
        # the full rows alone; from the Earth's centre, near-equatorial GEOs make the plain
        # step overshoot (beyond GEO altitude, then divergence). A step that increases the
        # full-row residual is halved; where the plain step helps it is taken unchanged.
        lam = 1.0
        while True:
            x_new = x + lam * step[:3]
            b_new = b + lam * step[3]
            dn = np.rint(lam * step[4:] / rows.ct_m[frac_idx]) if n_frac else np.zeros(0)
            n_new = n_int.copy()
            n_new[frac_idx] += dn  # eq. (13)
            geo_new = _geometry(rows, bdt_week, bdt_sow, x_new, n_new)
            cost_new = _full_cost(rows, geo_new, b_new, full_idx)
            if cost_new <= cost or lam < 1e-3 or not np.isfinite(cost):
                break
            lam /= 2.0
        x, b, n_int, geo, cost = x_new, b_new, n_new, geo_new, cost_new
        if np.linalg.norm(lam * step[:4]) < cfg.theta_m and not np.any(dn):  # eq. (14)
            converged = True
            break
    if not np.all(np.isfinite(x)):
        return replace(base, iterations=it, reason=f"no convergence after {it} iterations")

    # eqs. (12), (20)-(21): GEO-GDOP gate over the full rows, evaluated at the converged
    # phase-1 position (or at the last iterate when the iteration did not settle)
    gd = float(gdop(geo.los[~frac]))
    beta = cfg.beta
    if beta is None:
        t_min = float(np.min(rows.ct_m[frac]) / C_M_S) if n_frac else 1e-3
        beta = derive_beta(t_min, cfg.range_error_m)
    if n_frac and not gd < beta:
        settled = "" if converged else f" (no convergence after {it} iterations)"
        return replace(
            base,
            gdop_full=gd,
            iterations=it,
            reason=f"GDOP gate failed: GDOP_full {gd:.1f} >= beta {beta:.0f}{settled}",
        )
    if not converged:
        return replace(
            base, gdop_full=gd, iterations=it, reason=f"no convergence after {it} iterations"
        )

    # eqs. (15)-(16): integers fixed, correct [x, b] over all rows (iterated to convergence)
    x, b, geo, it2 = _fixed_iterations(rows, bdt_week, bdt_sow, x, b, n_int, geo, cfg, None, False)
    it += it2
    return x, b, n_int, geo, gd, it


def _solve_rows(
    rows: _Rows,
    gpst_week: int,
    gpst_tow_s: float,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
) -> Fix:
    bdt_week, bdt_sow = gpst_to_bdt(gpst_week, gpst_tow_s)
    frac = rows.frac
    n_full, n_frac = int((~frac).sum()), int(frac.sum())
    base = Fix(
        solver=solver,
        mode="none",
        gpst_week=gpst_week,
        gpst_tow_s=gpst_tow_s,
        full=tuple(p for p, f in zip(rows.prn, frac, strict=True) if not f),
        fractional=tuple(p for p, f in zip(rows.prn, frac, strict=True) if f),
    )
    if n_full < 4:
        reason = (
            f"too few full measurements: {n_full} full, {n_frac} fractional (need at least 4 full)"
        )
        return replace(base, reason=reason)

    n_int = np.zeros(len(rows.prn))
    frac_idx = np.flatnonzero(frac)
    gd: float | None = None
    if cfg.x0_ecef_m is not None and not n_frac:
        # every measurement full and a position known: conventional SPP, phase 2 alone (the
        # same solution as from the Earth's centre, see SolverConfig.x0_ecef_m)
        x, b, it = np.array(cfg.x0_ecef_m, dtype=float), 0.0, 0
        geo = _geometry(rows, bdt_week, bdt_sow, x, n_int)
    else:
        first = _phase1(rows, bdt_week, bdt_sow, n_int, cfg, base)
        if isinstance(first, Fix):
            return first
        x, b, n_int, geo, gd, it = first

    # ---- phase 2: mask, corrections, weights ---------------------------------------------
    meaningful = _plausible(x)
    if meaningful:
        keep = np.flatnonzero(_local(x, geo.sat_ecef_m).el_rad >= np.radians(cfg.elmask_deg))
    else:
        keep = np.arange(len(rows.prn))
    kept = rows if len(keep) == len(rows.prn) else rows.take(keep)
    n_int_k = n_int[keep]
    kfrac = kept.frac
    if int((~kfrac).sum()) < 4:
        return replace(
            base,
            gdop_full=gd,
            iterations=it,
            reason=(
                f"too few full measurements above the {cfg.elmask_deg:g} deg "
                f"mask: {int((~kfrac).sum())}"
            ),
        )
    model = _iono_model(iono.bds, iono.gps, cfg.iono) if meaningful else None
    x, b, geo, it3 = _fixed_iterations(
        kept,
        bdt_week,
        bdt_sow,
        x,
        b,
        n_int_k,
        geo if kept is rows else geo.take(keep),
        cfg,
        model,
        meaningful,
    )
    it += it3
    if not np.all(np.isfinite(x)):
        return replace(base, iterations=it, reason="solution diverged")

    # ---- integrity: post-fit residuals -----------------------------------------------------
    loc = _local(x, geo.sat_ecef_m)
    corr = _corrections(loc, bdt_sow, model, cfg) if meaningful else np.zeros(len(kept.prn))
    v = kept.z_m + n_int_k * kept.ct_m - geo.pred_m - b - corr
    vmax_i = int(np.argmax(np.abs(v)))
    resid_rms = float(np.sqrt(np.mean(v**2)))
    gd_final = float(gdop(geo.los[~kfrac]))
    ambiguity = {rows.prn[i]: int(n_int[i]) for i in frac_idx}
    recovered = {rows.prn[i]: float(rows.z_m[i] + n_int[i] * rows.ct_m[i]) for i in frac_idx}
    if abs(v[vmax_i]) > cfg.resid_max_m:
        return replace(
            base,
            gdop_full=gd_final,
            iterations=it,
            resid_rms_m=resid_rms,
            ambiguity=ambiguity,
            reason=(
                f"residual check failed: |v| = {abs(v[vmax_i]):.1f} m on "
                f"{kept.prn[vmax_i]} > {cfg.resid_max_m:g} m"
            ),
        )

    lat_r, lon_r, alt_m = loc.lat_rad, loc.lon_rad, loc.alt_m
    a = _design(geo.los)
    rot = enu_rotation(lat_r, lon_r)
    q = np.linalg.inv(a.T @ a)[:3, :3]
    q_enu = rot @ q @ rot.T
    w = _weights(loc, cfg) if meaningful else np.ones(len(kept.prn))
    qw = np.linalg.inv((a * w[:, None]).T @ a)[:3, :3]
    std = np.sqrt(np.diag(rot @ qw @ rot.T))
    mode: Literal["fast", "spp"] = "fast" if bool(np.any(kfrac)) else "spp"
    return replace(
        base,
        mode=mode,
        x_ecef_m=(float(x[0]), float(x[1]), float(x[2])),
        lat_deg=float(np.degrees(lat_r)),
        lon_deg=float(np.degrees(lon_r)),
        alt_m=alt_m,
        clock_bias_m=float(b),
        gdop_full=gd_final if solver == "fast" else None,
        pdop=float(np.sqrt(np.trace(q_enu))),
        hdop=float(np.sqrt(q_enu[0, 0] + q_enu[1, 1])),
        vdop=float(np.sqrt(q_enu[2, 2])),
        std_enu_m=(float(std[0]), float(std[1]), float(std[2])),
        used=kept.prn,
        full=tuple(p for p, f in zip(kept.prn, kfrac, strict=True) if not f),
        fractional=tuple(p for p, f in zip(kept.prn, kfrac, strict=True) if f),
        ambiguity=ambiguity,
        recovered_pr_m=recovered,
        resid_rms_m=resid_rms,
        iterations=it,
    )


@dataclass(frozen=True, slots=True, eq=False)
class _Local:
    """Receiver geodetic position and satellite look angles at one iterate."""

    lat_rad: float
    lon_rad: float
    alt_m: float
    el_rad: np.ndarray
    az_rad: np.ndarray


def _local(x: np.ndarray, sat_ecef_m: np.ndarray) -> _Local:
    lat, lon, alt = (float(v) for v in ecef_to_geodetic(x))
    el, az = look_angles(x, sat_ecef_m, (lat, lon))
    return _Local(lat, lon, alt, el, az)


def _weights(loc: _Local, cfg: SolverConfig) -> np.ndarray:
    """Elevation weights 1 / (a^2 + b^2 / sin^2 E) [1/m^2]."""
    if not cfg.weighted:
        return np.ones(len(loc.el_rad))
    s = np.maximum(np.sin(loc.el_rad), 0.05)
    return 1.0 / (cfg.sigma_a_m**2 + cfg.sigma_b_m**2 / s**2)


def _corrections(
    loc: _Local, bdt_sow: float, model: KlobucharParams | None, cfg: SolverConfig
) -> np.ndarray:
    """Ionospheric and tropospheric delays [m] for the rows at this iterate."""
    corr = np.zeros(len(loc.el_rad))
    if model is not None and loc.alt_m < 100e3:
        if model.system == "BDS":
            corr += klobuchar_bds_m(
                model, loc.lat_rad, loc.lon_rad, loc.el_rad, loc.az_rad, bdt_sow
            )
        else:
            gpst_tow = bdt_sow + 14.0
            corr += klobuchar_gps_m(
                model, loc.lat_rad, loc.lon_rad, loc.el_rad, loc.az_rad, gpst_tow
            )
    if cfg.tropo:
        corr += saastamoinen_m(loc.lat_rad, loc.alt_m, loc.el_rad)
    return corr


def _fixed_iterations(
    rows: _Rows,
    bdt_week: int,
    bdt_sow: float,
    x: np.ndarray,
    b: float,
    n_int: np.ndarray,
    geo: _Geometry,
    cfg: SolverConfig,
    model: KlobucharParams | None,
    meaningful: bool,
) -> tuple[np.ndarray, float, _Geometry, int]:
    """Least squares on [x, y, z, b] with the integers held (paper eqs. 15-16), iterated
    from ``x`` and its geometry ``geo``.

    When the position is ``meaningful`` the rows get elevation weights and the delays.
    """
    it = 0
    for it in range(1, cfg.max_iter + 1):
        dz = rows.z_m + n_int * rows.ct_m - geo.pred_m - b
        w = None
        if meaningful:
            loc = _local(x, geo.sat_ecef_m)
            dz = dz - _corrections(loc, bdt_sow, model, cfg)
            w = _weights(loc, cfg)
        step = _lsq(_design(geo.los), dz, w)
        x = x + step[:3]
        b += float(step[3])
        geo = _geometry(rows, bdt_week, bdt_sow, x, n_int)
        if np.linalg.norm(step) < cfg.conv_m:
            break
    return x, b, geo, it


def sky_view(epoch: MeasurementEpoch, store: EphemerisStore, fix: Fix) -> tuple[SatView, ...]:
    """Satellites of ``epoch`` with an ephemeris, seen from the fix (empty without one)."""
    if fix.x_ecef_m is None:
        return ()
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    ephs, idx = [], []
    for i, prn in enumerate(epoch.prn):
        e = store.select(prn, bdt_week, bdt_sow)
        if e is not None:
            ephs.append(e)
            idx.append(i)
    if not ephs:
        return ()
    arr = store.arrays(ephs)
    pos, _ = sat_pos_clock(arr, bdt_week, np.full(len(ephs), bdt_sow - 0.075))
    el, az = look_angles(np.asarray(fix.x_ecef_m), pos)
    used = set(fix.used)
    return tuple(
        SatView(
            prn=epoch.prn[i],
            el_deg=float(np.degrees(el[k])),
            az_deg=float(np.degrees(az[k])),
            cn0_dbhz=float(epoch.cn0_dbhz[i]),
            used=epoch.prn[i] in used,
            full=bool(np.isfinite(epoch.pr_m[i])),
            signal=epoch.signal[i],
        )
        for k, i in enumerate(idx)
    )


def select_rows(
    epoch: MeasurementEpoch, store: EphemerisStore, solver: Literal["fast", "spp"]
) -> tuple[_Rows | None, list[str]]:
    """Rows usable by ``solver`` (SPP: full only; fast: full and fractional) with ephemerides.

    Returns the rows and the PRNs dropped for want of a usable ephemeris.
    """
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    full = np.isfinite(epoch.pr_m)
    fracok = ~full & np.isfinite(epoch.frac_pr_m) & np.isfinite(epoch.period_s)
    use = full | fracok if solver == "fast" else full
    idx: list[int] = []
    ephs: list[Ephemeris] = []
    missing: list[str] = []
    for i in np.flatnonzero(use):
        e = store.select(epoch.prn[i], bdt_week, bdt_sow)
        if e is None:
            missing.append(epoch.prn[i])
            continue
        idx.append(int(i))
        ephs.append(e)
    if not idx:
        return None, missing
    ii = np.asarray(idx)
    z = np.where(full[ii], epoch.pr_m[ii], epoch.frac_pr_m[ii])
    ct = np.where(full[ii], 0.0, C_M_S * epoch.period_s[ii])
    rows = _Rows(
        prn=tuple(epoch.prn[i] for i in idx),
        z_m=z,
        ct_m=ct,
        cn0_dbhz=epoch.cn0_dbhz[ii],
        eph=store.arrays(ephs),
    )
    return rows, missing


def solve(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
    solver: Literal["fast", "spp"] = "fast",
    with_sky: bool = False,
) -> Fix:
    """Solve one epoch; never raises for bad geometry, returns ``mode="none"`` with a reason."""
    cfg = cfg or SolverConfig()
    iono = iono or IonoSet()
    rows, missing = select_rows(epoch, store, solver)
    if rows is None:
        why = "no measurements" if not missing else f"no usable ephemeris for {len(missing)} sats"
        return Fix(
            solver=solver,
            mode="none",
            gpst_week=epoch.gpst_week,
            gpst_tow_s=epoch.gpst_tow_s,
            reason=why,
        )
    fix = _solve_rows(rows, epoch.gpst_week, epoch.gpst_tow_s, iono, cfg, solver)
    if with_sky and fix.ok:
        fix = replace(fix, sky=sky_view(epoch, store, fix))
    return fix


def solve_spp(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
) -> Fix:
    """Conventional SPP: the same iteration over full pseudoranges only."""
    return solve(epoch, store, iono, cfg, solver="spp")


def fractionalize(
    epoch: MeasurementEpoch, period_s: float = 1e-3, keep_full: Sequence[str] | None = None
) -> MeasurementEpoch:
    """Reduce pseudoranges modulo c*T except for ``keep_full`` PRNs (default: the GEOs).

    ``numpy.mod`` keeps z + N c T equal to the original to floating-point precision.
    """
    keep = set(keep_full) if keep_full is not None else {p for p in epoch.prn if is_geo(p)}
    mask = np.array([p not in keep for p in epoch.prn], dtype=bool)
    ct = C_M_S * period_s
    pr = np.where(mask, np.nan, epoch.pr_m)
    frac = np.where(mask, np.mod(epoch.pr_m, ct), epoch.frac_pr_m)
    per = np.where(mask, period_s, epoch.period_s)
    return replace(epoch, pr_m=pr, frac_pr_m=frac, period_s=per)
