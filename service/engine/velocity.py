"""Receiver velocity and clock drift from Doppler: a second weighted least-squares problem
beside the position fix (docs/method.md, "Velocity").

A Doppler shift D [Hz] of a carrier of wavelength lambda is a pseudorange rate
rdot = -lambda D (every driver gives D positive for an approaching satellite: UBX RXM-RAWX
``doMes``, RINEX 3.04 5.3 ``D``, RTCM 3 MSM phase-range rate converted by the driver). With
the satellite's position s and velocity v_s at transmit time rotated into the receive-time
Earth frame (the same rotation as the pseudorange's Sagnac term), e the unit vector
receiver -> satellite, v the receiver's velocity and d = c * (receiver clock rate), the
observation equation is (Kaplan & Hegarty, *Understanding GPS/GNSS*, 3rd ed., 9.3; RTKLIB
``resdop``)

    rdot_i + c * dts_i/dt - e_i . v_s,i = -e_i . v + d,

linear in the unknowns (v, d): no iteration. The satellite terms come from the broadcast
ephemeris (:func:`service.core.orbit.sat_pos_vel_clock`, BDS-SIS-ICD-B1I-3.0 5.2.4.10 and
5.2.4.12 differentiated); the ionospheric and tropospheric delay rates (mm/s) are neglected.
In the rotating frame the Earth's rotation adds nothing to e . v_s: the inertial velocities
differ from the rotated ECEF ones by omega x s and omega x x, whose difference
omega x (s - x) is perpendicular to e.

The rows are weighted by 1/sigma_i^2 with sigma_i from elevation and C/N0
(:class:`VelocityConfig`); the covariance (H^T W H)^-1 gives the sigmas. With redundancy
r = rows - 4 >= 1, the residuals' weighted sum of squares is tested against the chi-square
quantile (as :mod:`service.engine.raim` tests the position); while it fails, the row with
the largest normalised residual (w-test, Baarda) is removed, up to ``max_exclusions``
times. A solution that still fails, or one without enough rows, is not reported (None).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from service.core.constants import C_M_S
from service.core.corrections import sagnac_rotate
from service.core.ephemeris import EphemerisStore
from service.core.geometry import ecef_to_geodetic, enu_rotation
from service.core.orbit import sat_pos_clock, sat_pos_vel_clock
from service.core.systems import constants_of
from service.core.timebase import gpst_to_bdt
from service.core.types import Ephemeris, Fix, MeasurementEpoch, Velocity
from service.engine.raim import chi2_threshold

log = logging.getLogger(__name__)

N_UNKNOWNS = 4
"""Velocity east, north, up and the clock drift."""

NOMINAL_FLIGHT_TIME_S = 0.075
"""First guess of the signal's flight time, refined once from the receiver position."""


@dataclass(frozen=True, slots=True)
class VelocityConfig:
    """Error model and test of the Doppler rows.

    sigma_i^2 = (sigma_a^2 + (sigma_b / sin E)^2) * 10^((cn0_ref - C/N0) / 10): a
    range-rate noise that grows at low elevation and with the inverse of the signal power
    (the carrier tracking loop's jitter, Kaplan & Hegarty 8.8); the defaults fit the static
    HKSC and urban TST recordings (tests/engine/test_velocity_real.py).
    """

    sigma_a_m_s: float = 0.03
    sigma_b_m_s: float = 0.03
    cn0_ref_dbhz: float = 45.0
    elmask_deg: float = 5.0
    p_fa: float = 1e-3
    max_exclusions: int = 4


@dataclass(frozen=True, slots=True, eq=False)
class DopplerRows:
    """The inputs of :func:`solve_velocity`: one row per satellite, all at one epoch.

    ``range_rate_m_s`` is -lambda * Doppler; satellite states are at transmit time, already
    rotated into the receive-time Earth frame; ``clock_drift_s_s`` is the satellite clock's
    rate (dts/dt)."""

    prn: tuple[str, ...]
    range_rate_m_s: np.ndarray
    cn0_dbhz: np.ndarray
    sat_ecef_m: np.ndarray
    sat_vel_ecef_m_s: np.ndarray
    sat_clock_drift_s_s: np.ndarray


@lru_cache(maxsize=256)
def wavelength_m(sat: str) -> float:
    """Carrier wavelength [m] of the signal bdsfix uses from ``sat``'s system."""
    return C_M_S / constants_of(sat).carrier_hz


def range_rate_m_s(prn: tuple[str, ...] | list[str], doppler_hz: np.ndarray) -> np.ndarray:
    """-lambda * D with each satellite system's carrier (:func:`constants_of`)."""
    lam = np.array([wavelength_m(p) for p in prn])
    return -lam * np.asarray(doppler_hz, dtype=float)


def solve_velocity(
    rows: DopplerRows, x_ecef_m: np.ndarray, cfg: VelocityConfig | None = None
) -> Velocity | None:
    """Velocity and clock drift of a receiver at ``x_ecef_m`` (module docstring), or None
    when fewer than four rows remain above the mask or the residual test fails after
    ``cfg.max_exclusions`` exclusions."""
    cfg = cfg or VelocityConfig()
    x = np.asarray(x_ecef_m, dtype=float)
    d = rows.sat_ecef_m - x
    rho = np.sqrt(np.einsum("ij,ij->i", d, d))
    e = d / rho[:, None]
    lat, lon, _ = (float(v) for v in ecef_to_geodetic(x))
    rot = enu_rotation(lat, lon)
    sin_el = e @ rot[2]
    y = (
        rows.range_rate_m_s
        + C_M_S * rows.sat_clock_drift_s_s
        - np.einsum("ij,ij->i", e, rows.sat_vel_ecef_m_s)
    )
    s = np.maximum(sin_el, 0.05)
    cn0 = np.where(np.isfinite(rows.cn0_dbhz), rows.cn0_dbhz, cfg.cn0_ref_dbhz)
    var = (cfg.sigma_a_m_s**2 + (cfg.sigma_b_m_s / s) ** 2) * 10.0 ** (
        (cfg.cn0_ref_dbhz - cn0) / 10.0
    )
    keep = np.isfinite(y) & (sin_el >= math.sin(math.radians(cfg.elmask_deg)))
    h = np.concatenate([-e, np.ones((len(y), 1))], axis=1)
    w = 1.0 / var
    excluded: list[str] = []
    for _ in range(cfg.max_exclusions + 1):
        idx = np.flatnonzero(keep)
        n = len(idx)
        if n < N_UNKNOWNS:
            return None
        hk, yk, wk = h[idx], y[idx], w[idx]
        normal = hk.T @ (hk * wk[:, None])
        try:
            cov = np.linalg.inv(normal)
        except np.linalg.LinAlgError:
            return None
        sol = cov @ (hk.T @ (wk * yk))
        resid = yk - hk @ sol
        redundancy = n - N_UNKNOWNS
        if redundancy == 0:
            chi2 = chi2_max = None
            break
        chi2 = float(resid @ (wk * resid))
        chi2_max = chi2_threshold(redundancy, cfg.p_fa)
        if chi2 <= chi2_max:
            break
        # w-test: residual over its own standard deviation, sigma_i^2 - (H Q H^T)_ii
        q_v = 1.0 / wk - np.einsum("ij,jk,ik->i", hk, cov, hk)
        wtest = np.abs(resid) / np.sqrt(np.maximum(q_v, 1e-12))
        worst = int(idx[int(np.argmax(wtest))])
        keep[worst] = False
        excluded.append(rows.prn[worst])
    else:
        log.debug("velocity: Doppler residuals fail the test after %d exclusions", len(excluded))
        return None
    if not np.all(np.isfinite(sol)):
        return None
    v_enu = rot @ sol[:3]
    q_enu = rot @ cov[:3, :3] @ rot.T
    ve, vn = float(v_enu[0]), float(v_enu[1])
    speed = math.hypot(ve, vn)
    qee, qnn, qen = float(q_enu[0, 0]), float(q_enu[1, 1]), float(q_enu[0, 1])
    if speed > 0.0:
        var_speed = (ve * ve * qee + vn * vn * qnn + 2 * ve * vn * qen) / speed**2
        var_course = (vn * vn * qee + ve * ve * qnn - 2 * ve * vn * qen) / speed**4
        std_course = min(math.degrees(math.sqrt(max(var_course, 0.0))), 180.0)
    else:
        var_speed, std_course = (qee + qnn) / 2, 180.0
    return Velocity(
        v_enu_m_s=(ve, vn, float(v_enu[2])),
        std_v_enu_m_s=tuple(float(math.sqrt(max(q_enu[k, k], 0.0))) for k in range(3)),  # type: ignore[arg-type]
        speed_m_s=speed,
        std_speed_m_s=math.sqrt(max(var_speed, 0.0)),
        course_deg=math.degrees(math.atan2(ve, vn)) % 360.0,
        std_course_deg=std_course,
        clock_drift_m_s=float(sol[3]),
        std_clock_drift_m_s=math.sqrt(max(float(cov[3, 3]), 0.0)),
        used=tuple(rows.prn[i] for i in np.flatnonzero(keep)),
        excluded=tuple(excluded),
        redundancy=redundancy,
        chi2=chi2,
        chi2_max=chi2_max,
    )


def doppler_rows(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    x_ecef_m: np.ndarray,
    clock_bias_m: float = 0.0,
    prns: tuple[str, ...] | None = None,
    pr_m: dict[str, float] | None = None,
) -> DopplerRows | None:
    """The Doppler rows of ``epoch`` (those of ``prns`` when given) that have a Doppler and
    an ephemeris, with the satellites' states at transmit time for a receiver at
    ``x_ecef_m`` whose clock is ``clock_bias_m`` ahead; None when there are none.

    The flight time is the pseudorange (the epoch's, else ``pr_m``: the fast fix's
    recovered ones) less the receiver clock, over c; a satellite without one is first
    placed :data:`NOMINAL_FLIGHT_TIME_S` back and its flight time taken from that position.
    A flight time wrong by 1 ms moves a range rate by < 1 mm/s."""
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    bias_m = clock_bias_m if math.isfinite(clock_bias_m) else 0.0
    t_rx = bdt_sow - bias_m / C_M_S
    wanted = None if prns is None else set(prns)
    recovered = pr_m or {}
    idx: list[int] = []
    ephs: list[Ephemeris] = []
    for i in np.flatnonzero(np.isfinite(epoch.doppler_hz)):
        sat = epoch.prn[i]
        if wanted is not None and sat not in wanted:
            continue
        eph = store.select(sat, bdt_week, bdt_sow)
        if eph is not None:
            idx.append(int(i))
            ephs.append(eph)
    if not idx:
        return None
    arr = store.arrays(ephs)
    x = np.asarray(x_ecef_m, dtype=float)
    ii = np.asarray(idx)
    prn = tuple(epoch.prn[i] for i in idx)
    pr = epoch.pr_m[ii]
    if not np.isfinite(pr).all():
        pr = np.array([recovered.get(p, v) for p, v in zip(prn, pr.tolist(), strict=True)])
    tau = (pr - bias_m) / C_M_S
    lost = ~np.isfinite(tau)
    if lost.any():
        first, _ = sat_pos_clock(arr, bdt_week, np.full(len(idx), t_rx - NOMINAL_FLIGHT_TIME_S))
        tau = np.where(lost, np.linalg.norm(first - x, axis=1) / C_M_S, tau)
    pos, vel, _, drift = sat_pos_vel_clock(arr, bdt_week, t_rx - tau)
    return DopplerRows(
        prn=prn,
        range_rate_m_s=range_rate_m_s(prn, epoch.doppler_hz[ii]),
        cn0_dbhz=epoch.cn0_dbhz[ii],
        sat_ecef_m=sagnac_rotate(pos, tau),
        sat_vel_ecef_m_s=sagnac_rotate(vel, tau),
        sat_clock_drift_s_s=drift,
    )


def with_velocity(
    fix: Fix, epoch: MeasurementEpoch, store: EphemerisStore, cfg: VelocityConfig | None = None
) -> Fix:
    """``fix`` with its :class:`Velocity` from ``epoch``'s Doppler (the satellites the fix
    used), or ``fix`` itself when it has no position or the velocity is not trusted."""
    if not fix.ok or fix.x_ecef_m is None or not fix.used:
        return fix
    try:
        with np.errstate(all="ignore"):
            x = np.asarray(fix.x_ecef_m, dtype=float)
            bias = fix.clock_bias_m if fix.clock_bias_m is not None else 0.0
            rows = doppler_rows(epoch, store, x, bias, fix.used, fix.recovered_pr_m)
            vel = None if rows is None else solve_velocity(rows, x, cfg)
    except (np.linalg.LinAlgError, ArithmeticError, ValueError):
        log.debug("velocity failure at GPST %d %.3f", fix.gpst_week, fix.gpst_tow_s, exc_info=True)
        return fix
    if vel is None:
        return fix
    return replace(fix, velocity=vel)
