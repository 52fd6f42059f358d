"""Physical and system constants for BeiDou (BDS-SIS-ICD-B1I-3.0, sections 3.2 and 5.2.4).

CGCS2000 values are used throughout; the GPS (WGS-84) values differ and must not be reused.
"""

import math

C_M_S = 299_792_458.0
"""Speed of light in vacuum [m/s]."""

GM_M3_S2 = 3.986004418e14
"""CGCS2000 geocentric gravitational constant [m^3/s^2] (ICD 3.2)."""

OMEGA_E_RAD_S = 7.2921150e-5
"""CGCS2000 Earth rotation rate [rad/s] (ICD 3.2)."""

A_CGCS2000_M = 6_378_137.0
"""CGCS2000 semi-major axis [m]."""

F_CGCS2000 = 1.0 / 298.257222101
"""CGCS2000 flattening."""

F_REL_S_PER_SQRT_M = -4.442807309e-10
"""Relativistic clock correction constant F = -2 sqrt(GM)/c^2 [s/sqrt(m)] (ICD 5.2.4.10)."""

GEO_TILT_RAD = math.radians(-5.0)
"""GEO orbit frame rotation about X before the Earth-rotation step (ICD 5.2.4.12, Table 5-11)."""

F_B1I_HZ = 1_561.098e6
F_GPS_L1_HZ = 1_575.42e6

GEO_PRNS = frozenset([1, 2, 3, 4, 5, 59, 60, 61, 62, 63])
"""BDS PRNs that are GEO satellites and broadcast D2 (BDS-2 C01-C05, BDS-3 C59-C63)."""

WEEK_S = 604_800
NOMINAL_FLIGHT_TIME_S = 0.075
"""Typical signal flight time from a BDS satellite [s] (MEO ~0.072, GEO/IGSO ~0.12 at the
horizon), used where no pseudorange gives the real one."""
MS_RANGE_M = C_M_S * 1e-3
"""Distance light travels in one B1I code period (1 ms) [m]."""

ICD_PI = 3.1415926535898
"""pi as the ICD defines it for semicircle conversion (5.2.4.12)."""

URA_M = (
    2.4,
    3.4,
    4.85,
    6.85,
    9.65,
    13.65,
    24.0,
    48.0,
    96.0,
    192.0,
    384.0,
    768.0,
    1536.0,
    3072.0,
    6144.0,
    math.inf,
)
"""URAI -> URA [m], the upper bound of each index's interval (ICD 5.2.4.5).

URAI 15 means URA > 6144 m (no accuracy prediction) and decodes as infinity, so that it
encodes back to 15."""


def prn_number(prn: str) -> int:
    """PRN number of an ID like ``"C06"``, ``"C 6"`` or ``"C6"``."""
    return int(prn[1:].strip())


def prn_id(number: int) -> str:
    """Canonical BDS satellite ID, ``"C06"``."""
    return f"C{number:02d}"


def is_geo(prn: str | int) -> bool:
    """True for BDS GEO satellites C01-C05 and C59-C63."""
    n = prn if isinstance(prn, int) else prn_number(prn)
    return n in GEO_PRNS
