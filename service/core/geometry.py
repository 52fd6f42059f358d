"""Coordinates and geometry on CGCS2000: geodetic conversion, look angles, DOP.

All functions broadcast over leading batch dimensions, so the per-epoch engine and the batch
coverage study share them.
"""

from __future__ import annotations

import math

import numpy as np

from service.core.constants import A_CGCS2000_M, F_CGCS2000

_E2 = F_CGCS2000 * (2.0 - F_CGCS2000)
_GEODETIC_ITERATIONS = 5


def geodetic_to_ecef(
    lat_rad: np.ndarray | float, lon_rad: np.ndarray | float, alt_m: np.ndarray | float
) -> np.ndarray:
    """Geodetic latitude, longitude [rad] and ellipsoidal height [m] to ECEF [m] (..., 3)."""
    lat = np.asarray(lat_rad, dtype=float)
    lon = np.asarray(lon_rad, dtype=float)
    h = np.asarray(alt_m, dtype=float)
    sin_lat = np.sin(lat)
    n = A_CGCS2000_M / np.sqrt(1.0 - _E2 * sin_lat**2)
    x = (n + h) * np.cos(lat) * np.cos(lon)
    y = (n + h) * np.cos(lat) * np.sin(lon)
    z = (n * (1.0 - _E2) + h) * sin_lat
    return np.stack(np.broadcast_arrays(x, y, z), axis=-1)


def ecef_to_geodetic(x_ecef_m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ECEF [m] (..., 3) to geodetic latitude, longitude [rad] and height [m] (iterative).

    One point (shape (3,)) takes a scalar path with :mod:`math` (the receiver loop converts
    one position per iteration, where numpy's per-call cost is most of the time); the
    iteration is the same.
    """
    r = np.asarray(x_ecef_m, dtype=float)
    if r.shape == (3,):
        lat_f, lon_f, h_f = _ecef_to_geodetic_point(float(r[0]), float(r[1]), float(r[2]))
        return np.asarray(lat_f), np.asarray(lon_f), np.asarray(h_f)
    x, y, z = r[..., 0], r[..., 1], r[..., 2]
    p = np.hypot(x, y)
    lon = np.arctan2(y, x)
    lat = np.arctan2(z, p * (1.0 - _E2))
    h = np.zeros_like(p)
    for _ in range(_GEODETIC_ITERATIONS):
        sin_lat = np.sin(lat)
        n = A_CGCS2000_M / np.sqrt(1.0 - _E2 * sin_lat**2)
        h = np.where(
            np.abs(np.cos(lat)) > 1e-9,
            p / np.maximum(np.cos(lat), 1e-300) - n,
            np.abs(z) - n * (1.0 - _E2),
        )
        lat = np.arctan2(z, p * (1.0 - _E2 * n / (n + h)))
    return lat, lon, h


def _ecef_to_geodetic_point(x: float, y: float, z: float) -> tuple[float, float, float]:
    """:func:`ecef_to_geodetic` of one point, in floats (NaN for the Earth's centre, where
    the iteration divides by zero, as numpy's array path gives)."""
    try:
        return _geodetic_of_point(x, y, z)
    except ZeroDivisionError:
        return math.nan, math.nan, math.nan


def _geodetic_of_point(x: float, y: float, z: float) -> tuple[float, float, float]:
    p = math.hypot(x, y)
    lon = math.atan2(y, x)
    lat = math.atan2(z, p * (1.0 - _E2))
    h = 0.0
    for _ in range(_GEODETIC_ITERATIONS):
        sin_lat = math.sin(lat)
        n = A_CGCS2000_M / math.sqrt(1.0 - _E2 * sin_lat**2)
        cos_lat = math.cos(lat)
        h = p / max(cos_lat, 1e-300) - n if abs(cos_lat) > 1e-9 else abs(z) - n * (1.0 - _E2)
        lat = math.atan2(z, p * (1.0 - _E2 * n / (n + h)))
    return lat, lon, h


def _enu_rows(lat_rad: float, lon_rad: float) -> list[list[float]]:
    """:func:`enu_rotation` of one point as nested lists of floats."""
    sl, cl = math.sin(lat_rad), math.cos(lat_rad)
    so, co = math.sin(lon_rad), math.cos(lon_rad)
    return [[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]]


def geodetic_points(
    x_ecef_m: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Geodetic latitude, longitude [rad], height [m] (n,) and :func:`enu_rotation`
    (n, 3, 3) of each of the ECEF points ``x_ecef_m`` (n, 3): each point by the scalar path
    of :func:`ecef_to_geodetic`, in plain floats, so a point's numbers are the same bits
    however many points are converted together (a few per call in the receiver, a chunk of
    epochs in ``bdsfix solve``: numpy's per-call cost, not the arithmetic, was the time)."""
    lat, lon, alt, rows = [], [], [], []
    for x, y, z in np.asarray(x_ecef_m, dtype=float).reshape(-1, 3).tolist():
        la, lo, h = _ecef_to_geodetic_point(x, y, z)
        lat.append(la)
        lon.append(lo)
        alt.append(h)
        for row in _enu_rows(la, lo):
            rows += row
    rot = np.array(rows, dtype=float).reshape(-1, 3, 3)
    lla = np.array((lat, lon, alt), dtype=float).reshape(3, -1)  # (one array: three cost more)
    return lla[0], lla[1], lla[2], rot


def enu_rotations_at(x_ecef_m: np.ndarray) -> np.ndarray:
    """The :func:`enu_rotation` (n, 3, 3) at each of the ECEF points ``x_ecef_m`` (n, 3)
    (:func:`geodetic_points`)."""
    return geodetic_points(x_ecef_m)[3]


def enu_rotation(lat_rad: np.ndarray | float, lon_rad: np.ndarray | float) -> np.ndarray:
    """Rotation (..., 3, 3) whose rows are the local east, north and up unit vectors in ECEF."""
    lat = np.asarray(lat_rad, dtype=float)
    lon = np.asarray(lon_rad, dtype=float)
    if lat.ndim == 0 and lon.ndim == 0:  # one point: no per-call numpy cost per element
        return np.array(_enu_rows(float(lat), float(lon)))
    sl, cl = np.sin(lat), np.cos(lat)
    so, co = np.sin(lon), np.cos(lon)
    zero = np.zeros_like(sl * so)
    east = np.stack(np.broadcast_arrays(-so, co, zero), axis=-1)
    north = np.stack(np.broadcast_arrays(-sl * co, -sl * so, cl), axis=-1)
    up = np.stack(np.broadcast_arrays(cl * co, cl * so, sl), axis=-1)
    return np.stack([east, north, up], axis=-2)


def look_angles(
    rx_ecef_m: np.ndarray,
    sat_ecef_m: np.ndarray,
    lat_lon_rad: tuple[np.ndarray | float, np.ndarray | float] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Elevation and azimuth [rad] of satellites (..., n, 3) seen from receivers (..., 3).

    ``lat_lon_rad`` saves the geodetic conversion when the caller already has it.
    """
    rx = np.asarray(rx_ecef_m, dtype=float)
    if lat_lon_rad is None:
        lat, lon, _ = ecef_to_geodetic(rx)
    else:
        lat, lon = np.asarray(lat_lon_rad[0]), np.asarray(lat_lon_rad[1])
    rot = enu_rotation(lat, lon)
    d = np.asarray(sat_ecef_m, dtype=float) - rx[..., None, :]
    enu = d @ rot.T if rot.ndim == 2 else np.einsum("...ij,...nj->...ni", rot, d)
    horiz = np.hypot(enu[..., 0], enu[..., 1])
    el = np.arctan2(enu[..., 2], horiz)
    az = np.mod(np.arctan2(enu[..., 0], enu[..., 1]), 2 * np.pi)
    return el, az


def dop_matrix(los_unit: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """D = G^T G with G rows [-e^T, 1] (paper eq. 12); ``los_unit`` is (..., n, 3).

    ``weight`` (..., n) of 0/1 masks rows out, so batches with different satellite counts
    share one array shape.
    """
    e = np.asarray(los_unit, dtype=float)
    g = np.concatenate([-e, np.ones((*e.shape[:-1], 1))], axis=-1)
    if weight is not None:
        g = g * np.asarray(weight, dtype=float)[..., None]
    return np.einsum("...ni,...nj->...ij", g, g)


def gdop(los_unit: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """GDOP = sqrt(trace(D^-1)) = sqrt(sum 1/lambda_k) (paper eq. 20); inf where singular."""
    d = dop_matrix(los_unit, weight)
    eig = np.linalg.eigvalsh(d)
    floor = 1e-12 * np.max(eig, axis=-1, keepdims=True)  # rank-deficient: singular
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(eig > floor, 1.0 / eig, np.inf)
    return np.sqrt(np.sum(inv, axis=-1))
