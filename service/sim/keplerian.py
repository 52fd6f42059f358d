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

from service.core.bds import GEO_TILT_RAD, is_geo
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem
from service.core.types import Ephemeris

_BDS = SYSTEM_CONSTANTS[GnssSystem.BDS]
"""The simulated constellation is BeiDou's: CGCS2000 GM and Earth rate (ICD 3.2)."""


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
    omega0 = math.remainder(raan_ecef + _BDS.omega_e_rad_s * toe_sow_s, 2 * math.pi)
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
        omega_rad=math.remainder(argp_rad, 2 * math.pi),
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
    return math.sqrt(_BDS.gm_m3_s2 / a_m**3)


# The paper's Table 1 (Zhao, Cui & Lu): BDS elements at UTC 2015-05-19 04:00:00.
# a [km], e, i [deg], RAAN (inertial) [deg], argument of perigee [deg], true anomaly [deg].
# G1..G6 are C01, C03, C04, C05, C02 (slots 140, 110.5, 160, 58.75 and 80 deg E);
# I1..I5 are C06..C10; M3..M6 are C11..C14.
TABLE1_EPOCH_UTC = (2015, 5, 19, 4, 0, 0)
TABLE1: dict[str, tuple[float, float, float, float, float, float]] = {
    "C01": (42_167.046, 0.000385, 1.660, 14.091, 166.081, 256.057),
    "C03": (42_168.221, 0.000371, 1.580, 31.719, 312.433, 62.552),
    "C04": (42_165.839, 0.000550, 0.787, 41.955, 155.089, 259.219),
    "C05": (42_164.381, 0.000110, 1.158, 29.645, 72.196, 253.240),
    "C02": (42_165.779, 0.000097, 0.216, 47.928, 22.396, 306.033),
    "C06": (42_157.559, 0.004004, 54.293, 200.802, 210.089, 1.845),
    "C07": (42_170.380, 0.003126, 53.938, 319.904, 196.870, 255.448),
    "C08": (42_144.000, 0.002785, 57.010, 80.717, 193.820, 86.116),
    "C09": (42_162.302, 0.003603, 54.608, 203.045, 203.863, 344.311),
    "C10": (42_166.206, 0.002972, 54.031, 319.350, 195.436, 235.874),
    "C11": (27_907.553, 0.002132, 55.838, 79.515, 207.483, 152.594),
    "C12": (27_905.796, 0.002440, 55.773, 78.992, 199.825, 206.342),
    "C13": (27_905.263, 0.003448, 54.728, 199.113, 170.282, 33.123),
    "C14": (27_905.161, 0.001848, 54.831, 198.716, 214.969, 26.118),
}


TOE_LSB_S = 8.0
"""t_oe is broadcast in units of 8 s (ICD B1I 5.2.4.12, Table 5-11; RTCM DF505)."""


def table1_ephemerides(offset_s: float = 0.0) -> list[Ephemeris]:
    """Table 1 propagated two-body by ``offset_s`` from its epoch, then on to the next t_oe a
    broadcast can carry (a multiple of TOE_LSB_S), as ephemerides with that t_oe: the same
    orbits, and the set the virtual receiver broadcasts (D1/D2, RTCM 1042) is the one its
    ranges were made with. (With the t_oe of the epoch itself, 2 s past a multiple of 8 s,
    the broadcast set, its t_oe rounded, put the satellites up to 8 km off: the receiver's
    own sets disagreed with the held ones.)"""
    import datetime as dt

    from service.core.timebase import gmst_rad, gpst_from_utc, gpst_to_bdt

    utc = dt.datetime(*TABLE1_EPOCH_UTC) + dt.timedelta(seconds=offset_s)
    bdt_week, bdt_sow = gpst_to_bdt(*gpst_from_utc(utc))
    late_s = (-bdt_sow) % TOE_LSB_S
    if late_s:
        offset_s += late_s
        utc += dt.timedelta(seconds=late_s)
        bdt_week, bdt_sow = gpst_to_bdt(*gpst_from_utc(utc))
    gmst = float(gmst_rad(utc))
    out = []
    for prn, (a_km, e, inc, raan, argp, nu) in TABLE1.items():
        a = a_km * 1e3
        m = mean_from_true_anomaly(math.radians(nu), e) + mean_motion_rad_s(a) * offset_s
        out.append(
            ephemeris_from_kepler(
                prn,
                a,
                e,
                math.radians(inc),
                math.radians(raan),
                math.radians(argp),
                m,
                gmst,
                bdt_week,
                bdt_sow,
                source="table1",
            )
        )
    return out
