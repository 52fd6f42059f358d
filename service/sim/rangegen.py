"""Physically generated pseudoranges for a receiver at a known place and time.

Used by the simulation tests and the virtual receiver. For a true receive time t (GPST) and a
receiver clock offset dt_r, each satellite's signal left at t - tau, where tau solves the
light-time equation with the satellite position at transmit time rotated into the
receive-time Earth frame (Sagnac), each with its system's constants. The pseudorange is
c tau + c (dt_r - dt_sv) + I + T + noise, and the receiver's time tag is t + dt_r, so that
tag and ranges carry the same clock offset (docs/method.md).

The carrier's range rate (what a Doppler measures: D = -rate / lambda) is the time
derivative of rho - c dt_sv + T - I (the ionosphere advances the carrier phase as much as it
delays the code), taken by a central difference of the same light-time solution and delay
models over +-:data:`RATE_STEP_S`; the receiver clock's rate is zero (its offset is
constant).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.core.constants import C_M_S, NOMINAL_FLIGHT_TIME_S
from service.core.corrections import klobuchar_bds_m, klobuchar_gps_m, saastamoinen_m, sagnac_rotate
from service.core.geometry import ecef_to_geodetic, look_angles
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.timebase import gpst_to_bdt, normalize
from service.core.types import KlobucharParams


@dataclass(frozen=True, slots=True, eq=False)
class TrueRanges:
    """Generated measurements; ``pr_m`` already includes clock offset, delays and noise."""

    prn: tuple[str, ...]
    tag_gpst_week: int
    tag_gpst_tow_s: float
    pr_m: np.ndarray
    geometric_m: np.ndarray
    sat_ecef_m: np.ndarray
    el_rad: np.ndarray
    az_rad: np.ndarray
    transmit_bdt_sow_s: np.ndarray
    carrier_rate_m_s: np.ndarray  # what a Doppler measures: D = -carrier_rate / lambda


RATE_STEP_S = 0.01
"""Half-width [s] of the central difference that gives the carrier's range rate."""


def _delays_m(
    x: np.ndarray,
    sat: np.ndarray,
    bdt_sow: float,
    gpst_tow_s: float,
    iono: KlobucharParams | None,
    tropo: bool,
    carrier_hz: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Ionospheric (group delay at each row's ``carrier_hz``) and tropospheric delays [m] of
    satellites at ``sat`` seen from ``x`` (zeros for a model not applied)."""
    el, az = look_angles(x, sat)
    lat, lon, alt = (float(v) for v in ecef_to_geodetic(x))
    iono_m = np.zeros(len(sat))
    tropo_m = np.zeros(len(sat))
    if iono is not None:
        if iono.system == "BDS":
            iono_m = klobuchar_bds_m(iono, lat, lon, el, az, bdt_sow, carrier_hz)
        else:
            iono_m = klobuchar_gps_m(iono, lat, lon, el, az, gpst_tow_s, carrier_hz)
    if tropo:
        tropo_m = saastamoinen_m(lat, alt, el)
    return iono_m, tropo_m


def _carrier_rate_m_s(
    eph: EphemerisArrays,
    x: np.ndarray,
    bdt_week: int,
    bdt_sow: float,
    gpst_tow_s: float,
    tau: np.ndarray,
    iono: KlobucharParams | None,
    tropo: bool,
) -> np.ndarray:
    """d/dt (rho - c dt_sv + T - I) [m/s] at receive time ``bdt_sow``: the carrier phase's
    range rate (the ionosphere advances the phase as much as it delays the code). The
    light-time solution at both ends of the step is refined twice from the flight times
    ``tau`` at the middle (they differ by < 1e-7 s; each refinement shrinks the error by
    |rate|/c < 3e-6)."""
    ends = []
    for h in (-RATE_STEP_S, RATE_STEP_S):
        tau_h = tau
        for _ in range(2):
            sat, clk_s = sat_pos_clock(eph, bdt_week, bdt_sow + h - tau_h)
            sat = sagnac_rotate(sat, tau_h, eph.omega_e_rad_s)
            tau_h = np.linalg.norm(sat - x, axis=1) / C_M_S
        iono_m, tropo_m = _delays_m(
            x, sat, bdt_sow + h, gpst_tow_s + h, iono, tropo, eph.carrier_hz
        )
        ends.append(C_M_S * tau_h - C_M_S * clk_s + tropo_m - iono_m)
    return (ends[1] - ends[0]) / (2 * RATE_STEP_S)


def true_ranges(
    eph: EphemerisArrays,
    rx_ecef_m: np.ndarray,
    gpst_week: int,
    gpst_tow_s: float,
    clock_offset_s: float = 0.0,
    *,
    iono: KlobucharParams | None = None,
    tropo: bool = False,
    noise_m: float = 0.0,
    rng: np.random.Generator | None = None,
) -> TrueRanges:
    """Pseudoranges of the satellites in ``eph`` received at true GPST time (week, tow)."""
    x = np.asarray(rx_ecef_m, dtype=float)
    bdt_week, bdt_sow = gpst_to_bdt(gpst_week, gpst_tow_s)
    tau = np.full(len(eph), NOMINAL_FLIGHT_TIME_S)
    for _ in range(6):
        sat, clk_s = sat_pos_clock(eph, bdt_week, bdt_sow - tau)
        sat = sagnac_rotate(sat, tau, eph.omega_e_rad_s)
        rho = np.linalg.norm(sat - x, axis=1)
        tau = rho / C_M_S
    el, az = look_angles(x, sat)
    iono_m, tropo_m = _delays_m(x, sat, bdt_sow, gpst_tow_s, iono, tropo, eph.carrier_hz)
    delay = np.zeros(len(eph))
    delay += iono_m
    delay += tropo_m
    noise = np.zeros(len(eph))
    if noise_m > 0:
        noise = (rng or np.random.default_rng()).normal(0.0, noise_m, len(eph))
    pr = rho + C_M_S * (clock_offset_s - clk_s) + delay + noise
    tag_week, tag_tow = normalize(gpst_week, gpst_tow_s + clock_offset_s)
    return TrueRanges(
        prn=eph.prn,
        tag_gpst_week=tag_week,
        tag_gpst_tow_s=tag_tow,
        pr_m=pr,
        geometric_m=rho,
        sat_ecef_m=sat,
        el_rad=el,
        az_rad=az,
        transmit_bdt_sow_s=bdt_sow - tau,
        carrier_rate_m_s=_carrier_rate_m_s(eph, x, bdt_week, bdt_sow, gpst_tow_s, tau, iono, tropo),
    )
