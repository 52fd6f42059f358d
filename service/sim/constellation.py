"""Keplerian constellations propagated directly: the paper's Table 1, two-body, ECI to ECEF.

The elements of Table 1 (Zhao, Cui & Lu, BDS at UTC 2015-05-19 04:00:00; values in
:data:`service.sim.keplerian.TABLE1`) are osculating classical elements whose RAAN is inertial.
Each orbit is propagated as a two-body Kepler ellipse in an inertial frame with the
CGCS2000 GM (BDS-SIS-ICD-B1I-3.0 3.2), and turned Earth-fixed by R_z(GMST) with the IAU 1982
GMST of the epoch (UT1 taken as UTC; |UT1 - UTC| < 0.9 s moves a GEO by < 0.004 deg).
Precession, nutation and polar motion are ignored (they move the Earth-fixed frame by well
under 0.01 deg over the study). With this conversion the GEOs sit at 140, 110.5, 160, 58.75
and 80 deg E, the slots the paper names.

Optional secular J2 rates (``j2=True``; Vallado, *Fundamentals of Astrodynamics*, 4th ed.,
eqs. 9-41) are only for sensitivity studies: the paper's study is two-body.

This is independent of :mod:`service.sim.keplerian`, which re-expresses the same elements as
broadcast ephemerides for the ICD orbit code; the tests check that the two agree.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from service.core.bds import is_geo
from service.core.constants import A_CGCS2000_M
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem
from service.core.timebase import gmst_rad
from service.sim.keplerian import TABLE1, TABLE1_EPOCH_UTC, mean_from_true_anomaly

J2_CGCS2000 = 1.082629832258e-3
"""CGCS2000 second zonal harmonic (unnormalised); only for the optional J2 secular rates."""


@dataclass(frozen=True, slots=True)
class KeplerElements:
    """Classical osculating elements at the constellation epoch; RAAN is inertial."""

    prn: str
    a_m: float
    e: float
    inc_rad: float
    raan_eci_rad: float
    argp_rad: float
    m0_rad: float


@dataclass(frozen=True, slots=True)
class Constellation:
    """Satellites' elements and the UTC epoch at which they hold."""

    epoch_utc: dt.datetime
    sats: tuple[KeplerElements, ...]

    @property
    def prns(self) -> tuple[str, ...]:
        return tuple(s.prn for s in self.sats)

    def only(self, prns: Sequence[str]) -> Constellation:
        """The satellites named in ``prns``, in that order."""
        by = {s.prn: s for s in self.sats}
        return Constellation(self.epoch_utc, tuple(by[p] for p in prns))

    def geos(self) -> Constellation:
        """The GEO satellites (C01-C05, C59-C63)."""
        return Constellation(self.epoch_utc, tuple(s for s in self.sats if is_geo(s.prn)))


def table1() -> Constellation:
    """The paper's Table 1 (G1, G3, G4, G5, G6 = C01, C03, C04, C05, C02; I1-I5 = C06-C10;
    M3-M6 = C11-C14); true anomalies converted to mean anomalies."""
    sats = []
    for prn, (a_km, e, inc, raan, argp, nu) in TABLE1.items():
        sats.append(
            KeplerElements(
                prn=prn,
                a_m=a_km * 1e3,
                e=e,
                inc_rad=math.radians(inc),
                raan_eci_rad=math.radians(raan),
                argp_rad=math.radians(argp),
                m0_rad=mean_from_true_anomaly(math.radians(nu), e),
            )
        )
    return Constellation(dt.datetime(*TABLE1_EPOCH_UTC), tuple(sats))


def _solve_kepler(m: np.ndarray, e: np.ndarray) -> np.ndarray:
    """Eccentric anomaly [rad] from mean anomaly by Newton iteration (converged for e < 0.1)."""
    ecc = m.copy()
    for _ in range(6):
        ecc = ecc - (ecc - e * np.sin(ecc) - m) / (1.0 - e * np.cos(ecc))
    return ecc


def positions_eci(const: Constellation, dt_s: np.ndarray | float, j2: bool = False) -> np.ndarray:
    """Inertial positions [m] (len(dt_s), n_sat, 3) at ``dt_s`` seconds after the epoch.

    The inertial frame is the equator/equinox frame in which the RAAN is given.
    """
    t = np.atleast_1d(np.asarray(dt_s, dtype=float))[:, None]
    shape = (t.shape[0], len(const.sats))
    a = np.array([s.a_m for s in const.sats])
    e = np.array([s.e for s in const.sats])
    inc = np.array([s.inc_rad for s in const.sats])
    raan = np.broadcast_to(np.array([s.raan_eci_rad for s in const.sats]), shape)
    argp = np.broadcast_to(np.array([s.argp_rad for s in const.sats]), shape)
    n = np.sqrt(SYSTEM_CONSTANTS[GnssSystem.BDS].gm_m3_s2 / a**3)
    m_rate = n
    if j2:
        p = a * (1.0 - e**2)
        k = 1.5 * J2_CGCS2000 * (A_CGCS2000_M / p) ** 2 * n
        ci, si2 = np.cos(inc), np.sin(inc) ** 2
        raan = raan - k * ci * t
        argp = argp + 0.5 * k * (4.0 - 5.0 * si2) * t
        m_rate = n + 0.5 * k * np.sqrt(1.0 - e**2) * (2.0 - 3.0 * si2)
    m0 = np.array([s.m0_rad for s in const.sats])
    ecc = _solve_kepler(m0 + m_rate * t, np.broadcast_to(e, shape))
    nu = np.arctan2(np.sqrt(1.0 - e**2) * np.sin(ecc), np.cos(ecc) - e)
    r = a * (1.0 - e * np.cos(ecc))
    u = argp + nu
    cu, su = np.cos(u), np.sin(u)
    co, so = np.cos(raan), np.sin(raan)
    ci, si = np.cos(inc), np.sin(inc)
    x = r * (co * cu - so * su * ci)
    y = r * (so * cu + co * su * ci)
    z = r * su * si
    return np.stack([x, y, z], axis=-1)


def positions_ecef(const: Constellation, dt_s: np.ndarray | float, j2: bool = False) -> np.ndarray:
    """Earth-fixed positions [m] (len(dt_s), n_sat, 3): :func:`positions_eci` rotated by
    R_z(GMST) of each instant."""
    t = np.atleast_1d(np.asarray(dt_s, dtype=float))
    eci = positions_eci(const, t, j2=j2)
    th = gmst_rad(const.epoch_utc, t)[:, None]
    c, s = np.cos(th), np.sin(th)
    x, y = eci[..., 0], eci[..., 1]
    return np.stack([c * x + s * y, -s * x + c * y, eci[..., 2]], axis=-1)
