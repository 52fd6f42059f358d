"""Physical constants and the values every supported system shares.

What differs between systems (GM, Earth rotation rate, relativistic constant F, code period,
carrier) is in :data:`service.core.systems.SYSTEM_CONSTANTS`, looked up by the satellite ID;
what only BeiDou has (GEOs, D1/D2) is in :mod:`service.core.bds`.
"""

import math

C_M_S = 299_792_458.0
"""Speed of light in vacuum [m/s]."""

A_CGCS2000_M = 6_378_137.0
"""CGCS2000 semi-major axis [m] (the geodetic conversions' ellipsoid; WGS-84 has the same
semi-major axis and a flattening that moves heights by 0.1 mm)."""

F_CGCS2000 = 1.0 / 298.257222101
"""CGCS2000 flattening."""

WEEK_S = 604_800
NOMINAL_FLIGHT_TIME_S = 0.075
"""Typical signal flight time [s] (BDS MEO ~0.072, GEO/IGSO ~0.12 at the horizon; GPS
0.067-0.086), used where no pseudorange gives the real one."""
ICD_PI = 3.1415926535898
"""pi as the ICDs define it for semicircle conversion (BDS ICD 5.2.4.12, IS-GPS-200
20.3.3.4.3)."""

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
"""URAI -> URA [m], the upper bound of each index's interval (BDS ICD 5.2.4.5; the GPS URA
index of IS-GPS-200 20.3.3.3.1.3 has the same bounds).

URAI 15 means URA > 6144 m (no accuracy prediction) and decodes as infinity, so that it
encodes back to 15."""
