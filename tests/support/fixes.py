"""Realistic hand-built fixes and a sky view at HKSC, for the output tests (records, NMEA,
publishers, security). Positions are converted by formulas written here, never by the code
under test."""

from __future__ import annotations

import math
import re

from service.core.declines import Decline, Declined
from service.core.types import Fix, SatView

# HKSC (Hong Kong SatRef) survey coordinates, CGCS2000/ITRF ECEF in metres
HKSC_ECEF_M = (-2414266.9197, 5386768.9868, 2407460.0314)
A_M, F = 6378137.0, 1.0 / 298.257222101  # CGCS2000 ellipsoid


def geodetic_deg_m(x: float, y: float, z: float) -> tuple[float, float, float]:
    """ECEF to latitude/longitude [deg] and ellipsoidal height [m], fixed-point iteration on
    the latitude (Hofmann-Wellenhof et al., GNSS, eq. 2.14-2.16); written for these tests."""
    e2 = F * (2.0 - F)
    p = math.hypot(x, y)
    lat = math.atan2(z, p * (1.0 - e2))
    h = 0.0
    for _ in range(20):
        n = A_M / math.sqrt(1.0 - e2 * math.sin(lat) ** 2)
        h = p / math.cos(lat) - n
        lat = math.atan2(z, p * (1.0 - e2 * n / (n + h)))
    return math.degrees(lat), math.degrees(math.atan2(y, x)), h


def ecef_m(lat_deg: float, lon_deg: float, h_m: float) -> tuple[float, float, float]:
    """Geodetic to ECEF (closed form), for fixes built at other places."""
    e2 = F * (2.0 - F)
    la, lo = math.radians(lat_deg), math.radians(lon_deg)
    n = A_M / math.sqrt(1.0 - e2 * math.sin(la) ** 2)
    return (
        (n + h_m) * math.cos(la) * math.cos(lo),
        (n + h_m) * math.cos(la) * math.sin(lo),
        (n * (1.0 - e2) + h_m) * math.sin(la),
    )


SKY = (
    SatView("C01", 47.3, 123.4, 47.0, True, True),
    SatView("C06", 58.1, 316.2, 39.0, True, False),
    SatView("C09", 54.4, 294.0, 41.0, True, False),
    SatView("C16", 59.2, 333.7, 41.0, True, False),
    SatView("C23", 82.0, 321.0, 46.0, True, True),
    SatView("C32", 42.1, 331.0, 44.0, True, True),
    SatView("C37", 35.0, 229.6, 41.0, True, True),
    SatView("C38", 53.0, 180.2, 42.0, True, True),
    SatView("C39", 56.0, 349.0, float("nan"), False, True),
)


def hksc_fix(
    solver: str = "fast",
    gpst_week: int = 2161,
    gpst_tow_s: float = 444954.0,
    x_ecef_m: tuple[float, float, float] = HKSC_ECEF_M,
    **changes: object,
) -> Fix:
    """A fast fix at HKSC with realistic values (lat/lon/alt by the formula above)."""
    lat, lon, alt = geodetic_deg_m(*x_ecef_m)
    fields: dict[str, object] = {
        "solver": solver,
        "mode": solver,
        "gpst_week": gpst_week,
        "gpst_tow_s": gpst_tow_s,
        "x_ecef_m": x_ecef_m,
        "lat_deg": lat,
        "lon_deg": lon,
        "alt_m": alt,
        "clock_bias_m": 123456.789012,
        "gdop_full": 2.4567 if solver == "fast" else None,
        "pdop": 1.4612,
        "hdop": 0.8437,
        "vdop": 1.1926,
        "std_enu_m": (0.338, 0.341, 0.792),
        "used": tuple(s.prn for s in SKY if s.used),
        "full": ("C01", "C23", "C32", "C37", "C38"),
        "fractional": ("C06", "C09", "C16") if solver == "fast" else (),
        "ambiguity": {"C16": 71, "C06": 69, "C09": 74} if solver == "fast" else {},
        "resid_rms_m": 1.0321,
        "sky": SKY,
        "redundancy": 4,
        "chi2": 2.7183,
        "chi2_max": 28.4733,
        "hpl_m": 14.25,
        "vpl_m": 21.5,
    }
    fields.update(changes)
    return Fix(**fields)  # type: ignore[arg-type]


def declined_fix(**changes: object) -> Fix:
    fields: dict[str, object] = {
        "solver": "fast",
        "mode": "none",
        "gpst_week": 2161,
        "gpst_tow_s": 444955.0,
        "full": ("C01", "C23", "C32"),
        "fractional": ("C06", "C09"),
        "gdop_full": 4812.3,
        # reason "GDOP gate failed: GDOP_full 4812.3 >= beta 3000"
        "decline": Declined.of(Decline.GDOP_GATE, gdop=4812.3, beta=3000.0, iterations=9),
    }
    fields.update(changes)
    return Fix(**fields)  # type: ignore[arg-type]


def without_since_start(line: str) -> str:
    """A stream's FIX JSON line without its ``since_start_s`` (the time since the stream's
    first epoch, which ``bdsfix solve`` does not write): the same bytes as solve's record
    of the same fix."""
    return re.sub(r',"since_start_s":[^,}]*', "", line)
