"""Two-body Keplerian elements expressed as BDS broadcast ephemerides.

This lets a constellation given as classical elements (the paper's Table 1) run through the
same ICD orbit code as real broadcast data (BDS-SIS-ICD-B1I-3.0 5.2.4.12, Table 5-11).
With all harmonic corrections and rates zero, the ICD model is a pure Kepler ellipse:
- IGSO/MEO: Omega_k = Omega0 - Omega_e (t_k + t_oe), so Omega0 = Omega_ecef + Omega_e t_oe,
  where Omega_ecef is the inertial node measured from the Greenwich meridian at t_oe.
- GEO: X_ecef = R_z(Omega_e t_k) R_x(-5 deg) X_GK with X_GK a Kepler orbit in a fixed frame
  tilted by +5 deg about X from the Earth-fixed axes at t_oe; the elements are re-expressed
  in that frame (inclination, node and argument of perigee change; a, e, M do not).
"""

from __future__ import annotations

import math

import numpy as np

from service.constants import GEO_TILT_RAD, GM_M3_S2, OMEGA_E_RAD_S, is_geo
from service.types import Ephemeris


def mean_from_true_anomaly(nu_rad: float, e: float) -> float:
    """Mean anomaly [rad] from true anomaly via the eccentric anomaly."""
    ecc_anom = 2.0 * math.atan2(
        math.sqrt(1 - e) * math.sin(nu_rad / 2), math.sqrt(1 + e) * math.cos(nu_rad / 2)
    )
    return ecc_anom - e * math.sin(ecc_anom)


def _perifocal_axes(raan: float, inc: float, argp: float) -> tuple[np.ndarray, np.ndarray]:
    """Unit vectors to perigee (P) and orbit normal (W) for node, inclination, perigee."""
    co, so = math.cos(raan), math.sin(raan)
    ci, si = math.cos(inc), math.sin(inc)
    cw, sw = math.cos(argp), math.sin(argp)
    p = np.array([co * cw - so * sw * ci, so * cw + co * sw * ci, sw * si])
    w = np.array([so * si, -co * si, ci])
    return p, w


def _elements_from_axes(p: np.ndarray, w: np.ndarray) -> tuple[float, float, float]:
    """(node, inclination, argument of perigee) [rad] of an orbit with axes P, W."""
    inc = math.acos(max(-1.0, min(1.0, float(w[2]))))
    raan = math.atan2(float(w[0]), float(-w[1]))
    node = np.array([math.cos(raan), math.sin(raan), 0.0])
    argp = math.atan2(float(np.dot(np.cross(node, p), w)), float(np.dot(node, p)))
    return raan, inc, argp


def ephemeris_from_kepler(
    prn: str,
    a_m: float,
    e: float,
    inc_rad: float,
    raan_eci_rad: float,
    argp_rad: float,
    mean_anomaly_rad: float,
    gmst_rad: float,
    bdt_week: int,
    toe_sow_s: float,
    source: str = "kepler",
) -> Ephemeris:
    """Broadcast-form ephemeris of a two-body orbit whose elements hold at t_oe.

    ``raan_eci_rad`` is the inertial right ascension of the node; ``gmst_rad`` the Greenwich
    sidereal angle at t_oe that turns it into an Earth-fixed longitude.
    """
    raan_ecef = raan_eci_rad - gmst_rad
    if is_geo(prn):
        p, w = _perifocal_axes(raan_ecef, inc_rad, argp_rad)
        # v_GK = R_x(+5 deg) v_ecef, the inverse of the ICD's R_x(-5 deg)
        c, s = math.cos(-GEO_TILT_RAD), math.sin(-GEO_TILT_RAD)
        rx = np.array([[1.0, 0.0, 0.0], [0.0, c, s], [0.0, -s, c]])
        raan_ecef, inc_rad, argp_rad = _elements_from_axes(rx @ p, rx @ w)
    omega0 = math.remainder(raan_ecef + OMEGA_E_RAD_S * toe_sow_s, 2 * math.pi)
    return Ephemeris(
        prn=prn,
        week=bdt_week,
        toe_sow_s=toe_sow_s,
        toc_sow_s=toe_sow_s,
        af0_s=0.0,
        af1_s_s=0.0,
        af2_s_s2=0.0,
        sqrt_a_sqrt_m=math.sqrt(a_m),
        e=e,
        i0_rad=inc_rad,
        omega0_rad=omega0,
        omega_rad=argp_rad,
        m0_rad=math.remainder(mean_anomaly_rad, 2 * math.pi),
        delta_n_rad_s=0.0,
        omega_dot_rad_s=0.0,
        idot_rad_s=0.0,
        cuc_rad=0.0,
        cus_rad=0.0,
        crc_m=0.0,
        crs_m=0.0,
        cic_rad=0.0,
        cis_rad=0.0,
        source=source,
    )


def mean_motion_rad_s(a_m: float) -> float:
    """Two-body mean motion sqrt(GM / a^3) [rad/s] with the CGCS2000 GM."""
    return math.sqrt(GM_M3_S2 / a_m**3)
