"""Propagation corrections for code ranges, vectorised over satellites.

- Sagnac (Earth rotation during signal flight): the satellite position at transmit time is
  rotated about Z by Omega_e * tau into the ECEF frame at receive time, with the Omega_e of
  each satellite's system.
- Ionosphere: the BDS broadcast Klobuchar model of BDS-SIS-ICD-B1I-3.0 section 5.2.4.7,
  which differs from the GPS one (IS-GPS-200 20.3.3.5.2.5): it uses a 375 km shell, the
  *geographic* latitude of the pierce point, |phi_M| in the polynomials, and gives the B1I
  delay. The GPS form gives the L1 delay (it serves files that only carry GPSA/GPSB). Both
  are scaled to the carrier of each row's signal by (f_model / f)^2, the first-order
  ionospheric dispersion (1 for B1I under the BDS model).
- Troposphere: Saastamoinen (1972) zenith delays with a standard atmosphere (1013.25 hPa,
  15 degC at sea level, 70 % humidity) and a 1/cos(z) mapping.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.constants import C_M_S
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem
from service.core.types import KlobucharParams

_SEMI = np.pi  # semicircles -> radians
_ONE_DEG_RAD = math.radians(1.0)
_F_B1I_HZ = SYSTEM_CONSTANTS[GnssSystem.BDS].carrier_hz
"""The carrier the BDS Klobuchar model gives its delay for (ICD 5.2.4.7)."""
_F_L1_HZ = SYSTEM_CONSTANTS[GnssSystem.GPS].carrier_hz
"""The carrier the GPS Klobuchar model gives its delay for (IS-GPS-200 20.3.3.5.2.5)."""


def sagnac_rotate(
    sat_ecef_m: np.ndarray, travel_time_s: np.ndarray, omega_e_rad_s: float | np.ndarray
) -> np.ndarray:
    """Rotate satellite positions (n, 3) by Omega_e * travel time into the receive-time
    frame; ``omega_e_rad_s`` is each satellite's system's Earth rotation rate
    (:attr:`service.core.orbit.EphemerisArrays.omega_e_rad_s`)."""
    ang = omega_e_rad_s * np.asarray(travel_time_s, dtype=float)
    c, s = np.cos(ang), np.sin(ang)
    x, y = sat_ecef_m[..., 0], sat_ecef_m[..., 1]
    out = np.array(sat_ecef_m, dtype=float)  # z unchanged
    out[..., 0] = c * x + s * y
    out[..., 1] = c * y - s * x
    return out


def _cubic(coeffs: tuple[float, ...] | list[float], x: np.ndarray) -> np.ndarray:
    """c0 + c1 x + c2 x^2 + c3 x^3 by Horner's rule (the Klobuchar amplitude and period)."""
    c0, c1, c2, c3 = coeffs  # (numbers: numpy takes each as a float64, as float() would)
    return ((c3 * x + c2) * x + c1) * x + c0


def klobuchar_bds_m(
    params: KlobucharParams,
    lat_rad: float | np.ndarray,
    lon_rad: float | np.ndarray,
    el_rad: np.ndarray,
    az_rad: np.ndarray,
    bdt_sow_s: float | np.ndarray,
    carrier_hz: float | np.ndarray,
) -> np.ndarray:
    """Ionospheric delay [m] on ``carrier_hz`` (per row), BDS Klobuchar form (ICD B1I 5.2.4.7).

    One receiver, or one per row when ``lat_rad``, ``lon_rad`` and ``bdt_sow_s`` are arrays
    that broadcast against ``el_rad`` (the batch solver's epochs x satellites).

    Pierce point on a 375 km shell (R = 6378 km), geographic latitude; vertical delay
    5 ns + A2 cos(2 pi (t - 50400) / A4) during the day, 5 ns at night; slant factor
    1 / sqrt(1 - (R cos E / (R + h))^2). The model's B1I delay is scaled to the carrier by
    (f_B1I / f)^2.
    """
    r_km, h_km = 6378.0, 375.0
    el = np.asarray(el_rad, dtype=float)
    az = np.asarray(az_rad, dtype=float)
    ratio = r_km / (r_km + h_km) * np.cos(el)
    psi = np.pi / 2 - el - np.arcsin(ratio)
    sin_lat, cos_lat = np.sin(lat_rad), np.cos(lat_rad)
    sin_psi = np.sin(psi)
    lat_m = np.arcsin(sin_lat * np.cos(psi) + cos_lat * sin_psi * np.cos(az))
    lon_m = lon_rad + np.arcsin(sin_psi * np.sin(az) / np.cos(lat_m))
    phi = np.abs(lat_m / _SEMI)
    a2 = np.maximum(_cubic(params.alpha, phi), 0.0)
    a4 = np.minimum(np.maximum(_cubic(params.beta, phi), 72000.0), 172800.0)  # np.clip
    t = np.mod(bdt_sow_s + lon_m * 43200.0 / np.pi, 86400.0)
    since = t - 50400.0
    day = np.abs(since) < a4 / 4.0
    iz = 5e-9 + np.where(day, a2 * np.cos(2 * np.pi * since / a4), 0.0)
    return C_M_S * iz / np.sqrt(1.0 - ratio**2) * (_F_B1I_HZ / np.asarray(carrier_hz)) ** 2


def klobuchar_gps_m(
    params: KlobucharParams,
    lat_rad: float | np.ndarray,
    lon_rad: float | np.ndarray,
    el_rad: np.ndarray,
    az_rad: np.ndarray,
    gpst_tow_s: float | np.ndarray,
    carrier_hz: float | np.ndarray,
) -> np.ndarray:
    """Ionospheric delay [m] on ``carrier_hz`` (per row) from GPS Klobuchar coefficients
    (IS-GPS-200 20.3.3.5.2.5).

    One receiver, or one per row as in :func:`klobuchar_bds_m`.

    Geomagnetic latitude, 350 km shell, obliquity 1 + 16 (0.53 - E)^3 (semicircles); the L1
    delay is scaled to the carrier by (f_L1 / f)^2 (to B1I for BeiDou rows).
    """
    el_sc = np.asarray(el_rad, dtype=float) / _SEMI
    az = np.asarray(az_rad, dtype=float)
    psi = 0.0137 / (el_sc + 0.11) - 0.022
    lat_i = np.clip(lat_rad / _SEMI + psi * np.cos(az), -0.416, 0.416)
    lon_i = lon_rad / _SEMI + psi * np.sin(az) / np.cos(lat_i * _SEMI)
    lat_m = lat_i + 0.064 * np.cos((lon_i - 1.617) * _SEMI)
    t = np.mod(43200.0 * lon_i + gpst_tow_s, 86400.0)
    f = 1.0 + 16.0 * (0.53 - el_sc) ** 3
    amp = np.maximum(_cubic(params.alpha, lat_m), 0.0)
    per = np.maximum(_cubic(params.beta, lat_m), 72000.0)
    x = 2 * np.pi * (t - 50400.0) / per
    night = np.abs(x) >= 1.57
    delay = f * (5e-9 + np.where(night, 0.0, amp * (1 - x**2 / 2 + x**4 / 24)))
    return C_M_S * delay * (_F_L1_HZ / np.asarray(carrier_hz)) ** 2


def saastamoinen_zenith_m(lat_rad: float, alt_m: float, humidity: float = 0.7) -> float:
    """Saastamoinen's zenith delay [m] (hydrostatic + wet, standard atmosphere) of one
    receiver; 0 outside -100 m to 10 km. Plain floats: a receiver's figure is the same bits
    however many receivers are computed together (:func:`saastamoinen_m`)."""
    if alt_m < -100.0 or alt_m > 1e4:
        return 0.0
    if not math.isfinite(lat_rad):
        return math.nan
    h = min(max(alt_m, 0.0), 1e4)
    pres_hpa = 1013.25 * (1.0 - 2.2557e-5 * h) ** 5.2568
    temp_k = 15.0 - 6.5e-3 * h + 273.16
    e_hpa = 6.108 * humidity * math.exp((17.15 * temp_k - 4684.0) / (temp_k - 38.45))
    hydro = 0.0022768 * pres_hpa / (1.0 - 0.00266 * math.cos(2 * lat_rad) - 0.00028 * h / 1e3)
    wet = 0.002277 * (1255.0 / temp_k + 0.05) * e_hpa
    return hydro + wet


def saastamoinen_m(
    lat_rad: float | np.ndarray,
    alt_m: float | np.ndarray,
    el_rad: np.ndarray,
    humidity: float = 0.7,
) -> np.ndarray:
    """Slant tropospheric delay [m], Saastamoinen model with a standard atmosphere
    (:func:`saastamoinen_zenith_m`) and a 1/cos(z) mapping (elevation floored at 1 deg, 0
    below the horizon); 0 for a receiver outside -100 m to 10 km. One receiver, or one per
    row when ``lat_rad`` and ``alt_m`` are arrays that broadcast against ``el_rad``."""
    el = np.asarray(el_rad, dtype=float)
    one = isinstance(alt_m, float) and isinstance(lat_rad, float)  # (np.ndim costs more)
    if one or (np.ndim(alt_m) == 0 and np.ndim(lat_rad) == 0):
        zenith: float | np.ndarray = saastamoinen_zenith_m(float(lat_rad), float(alt_m), humidity)
    else:  # each receiver alone
        lat_a, alt_a = np.asarray(lat_rad, dtype=float), np.asarray(alt_m, dtype=float)
        if lat_a.shape != alt_a.shape:
            lat_a, alt_a = np.broadcast_arrays(lat_a, alt_a)
        flat = [
            saastamoinen_zenith_m(la, h, humidity)
            for la, h in zip(lat_a.ravel().tolist(), alt_a.ravel().tolist(), strict=True)
        ]
        zenith = np.array(flat).reshape(alt_a.shape)
    cos_z = np.cos(np.pi / 2 - np.maximum(el, _ONE_DEG_RAD))
    return np.where(el > 0, zenith / cos_z, 0.0)
