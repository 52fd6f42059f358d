"""Geodetic conversion, look angles and the delay models against first principles."""

import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from service.core.constants import C_M_S
from service.core.corrections import klobuchar_bds_m, klobuchar_gps_m, saastamoinen_m, sagnac_rotate
from service.core.geometry import (
    ecef_to_geodetic,
    enu_rotation,
    enu_rotations_at,
    gdop,
    geodetic_to_ecef,
    look_angles,
)
from service.core.types import KlobucharParams

A, F = 6378137.0, 1 / 298.257222101
F_B1I_HZ = 1561.098e6  # BDS-SIS-ICD-B1I-3.0 4.2 (written here, not imported)
F_L1_HZ = 1575.42e6  # IS-GPS-200 3.3.1.1


@given(st.floats(-89.9, 89.9), st.floats(-180, 180), st.floats(-500, 2_000_000))
def test_geodetic_round_trip(lat, lon, h):
    x = geodetic_to_ecef(math.radians(lat), math.radians(lon), h)
    # independent forward formula
    e2 = F * (2 - F)
    n = A / math.sqrt(1 - e2 * math.sin(math.radians(lat)) ** 2)
    ref_z = (n * (1 - e2) + h) * math.sin(math.radians(lat))
    assert abs(x[2] - ref_z) < 1e-6
    la, lo, hh = ecef_to_geodetic(x)
    assert abs(math.degrees(la) - lat) < 1e-9
    assert abs(math.remainder(math.degrees(lo) - lon, 360)) < 1e-9
    assert abs(hh - h) < 1e-4


@given(
    st.lists(
        st.tuples(st.floats(-89.9, 89.9), st.floats(-180, 180), st.floats(-500, 2_000_000)),
        min_size=1,
        max_size=6,
    )
)
def test_enu_rotations_at_points_are_the_rotations_of_their_geodetic_coordinates(points):
    """One rotation per point, bit for bit enu_rotation of ecef_to_geodetic's latitude and
    longitude; orthonormal, its third row the ellipsoid normal of the geodetic latitude."""
    xs = np.array([geodetic_to_ecef(math.radians(a), math.radians(o), h) for a, o, h in points])
    rots = enu_rotations_at(xs)
    assert rots.shape == (len(points), 3, 3)
    for x, rot, (lat, lon, _h) in zip(xs, rots, points, strict=True):
        la, lo, _ = ecef_to_geodetic(x)
        assert np.array_equal(rot, enu_rotation(float(la), float(lo)))
        assert np.allclose(rot @ rot.T, np.eye(3), atol=1e-12)
        up = [
            math.cos(math.radians(lat)) * math.cos(math.radians(lon)),
            math.cos(math.radians(lat)) * math.sin(math.radians(lon)),
            math.sin(math.radians(lat)),
        ]
        assert np.allclose(rot[2], up, atol=1e-9)


def test_look_angles_zenith_and_horizon():
    rx = geodetic_to_ecef(math.radians(30.0), math.radians(100.0), 0.0)
    up = rx / np.linalg.norm(rx)  # near the normal (geocentric, not geodetic, ~0.17 deg off)
    el, _ = look_angles(rx, rx[None, :] + 2e7 * up[None, :])
    assert abs(math.degrees(el[0]) - 90) < 0.2
    north = np.array(
        [
            -math.sin(math.radians(30)) * math.cos(math.radians(100)),
            -math.sin(math.radians(30)) * math.sin(math.radians(100)),
            math.cos(math.radians(30)),
        ]
    )
    el, az = look_angles(rx, rx[None, :] + 1e5 * north[None, :])
    assert abs(math.degrees(el[0])) < 1.0
    assert abs(math.remainder(math.degrees(az[0]), 360.0)) < 1e-6


def test_gdop_of_a_textbook_geometry():
    # four satellites: zenith plus three at 0 deg elevation 120 deg apart (local frame)
    los = np.array(
        [[0, 0, 1], [1, 0, 0], [-0.5, math.sqrt(3) / 2, 0], [-0.5, -math.sqrt(3) / 2, 0]]
    )
    g = np.concatenate([-los, np.ones((4, 1))], axis=1)
    ref = math.sqrt(np.trace(np.linalg.inv(g.T @ g)))
    assert abs(float(gdop(los)) - ref) < 1e-9
    assert math.isinf(float(gdop(los[:3])))


def test_sagnac_rotation_magnitude():
    sat = np.array([[26_000e3, 0.0, 0.0]])
    rot = sagnac_rotate(sat, np.array([0.07]), 7.2921150e-5)
    # Omega_e * tau * r = 7.292115e-5 * 0.07 * 26e6 = 132.7 m, moving -y (Earth turns east)
    assert abs(-rot[0, 1] - 7.2921150e-5 * 0.07 * 26e6) < 1e-3


def test_sagnac_rotation_takes_each_rows_earth_rate():
    """Two rows, BDS (CGCS2000) and GPS (WGS-84, IS-GPS-200 20.3.3.4.3) Earth rates: each row
    turns by its own rate (at 26,000 km and 0.07 s the two differ by 27 um)."""
    sat = np.array([[26_000e3, 0.0, 0.0], [26_000e3, 0.0, 0.0]])
    omega = np.array([7.2921150e-5, 7.2921151467e-5])
    rot = sagnac_rotate(sat, np.array([0.07, 0.07]), omega)
    for k in range(2):
        ang = omega[k] * 0.07
        assert abs(rot[k, 0] - 26e6 * math.cos(ang)) < 1e-9
        assert abs(rot[k, 1] + 26e6 * math.sin(ang)) < 1e-9
    assert rot[0, 1] != rot[1, 1]


def test_bds_klobuchar_night_floor_at_zenith():
    """At night the BDS model gives 5 ns vertically; at zenith the slant factor is
    1/sqrt(1 - (R/(R+h))^2 cos^2 90) = 1 (ICD B1I 5.2.4.7)."""
    p = KlobucharParams(alpha=(1e-8, 0, 0, 0), beta=(90000.0, 0, 0, 0))
    lon = math.radians(0.0)
    d = klobuchar_bds_m(p, 0.5, lon, np.array([math.pi / 2]), np.array([0.0]), 0.0, F_B1I_HZ)
    assert abs(d[0] - 5e-9 * C_M_S) < 1e-9


def test_bds_klobuchar_slant_factor_and_daytime_peak():
    p = KlobucharParams(alpha=(2e-8, 0, 0, 0), beta=(100000.0, 0, 0, 0))
    # 14:00 local time at the pierce point: cos term = 1 -> 5 ns + 20 ns vertical
    el = math.radians(30.0)
    r, h = 6378.0, 375.0
    slant = 1 / math.sqrt(1 - (r / (r + h) * math.cos(el)) ** 2)
    d = klobuchar_bds_m(p, 0.0, 0.0, np.array([math.pi / 2]), np.array([0.0]), 50400.0, F_B1I_HZ)
    assert abs(d[0] - 25e-9 * C_M_S) < 1e-6
    # at 30 deg elevation toward north the pierce point moves, but stays within +/- 1 h LT
    d30 = klobuchar_bds_m(p, 0.0, 0.0, np.array([el]), np.array([0.0]), 50400.0, F_B1I_HZ)
    assert abs(d30[0] - 25e-9 * C_M_S * slant) < 1e-6


def test_klobuchar_delays_scale_to_each_rows_carrier():
    """The first-order ionospheric delay goes as 1/f^2: the BDS model gives B1I's delay and
    the GPS model L1's (IS-GPS-200 20.3.3.5.2.5); a row on the other carrier gets it scaled
    by (f_model / f)^2. At night at zenith: BDS 5 ns; GPS 5 ns times the obliquity
    1 + 16 (0.53 - 0.5)^3."""
    zenith, north = np.array([math.pi / 2, math.pi / 2]), np.array([0.0, 0.0])
    carriers = np.array([F_B1I_HZ, F_L1_HZ])
    p = KlobucharParams(alpha=(1e-8, 0, 0, 0), beta=(90000.0, 0, 0, 0))
    bds = klobuchar_bds_m(p, 0.5, 0.0, zenith, north, 0.0, carriers)
    assert abs(bds[0] - 5e-9 * C_M_S) < 1e-9
    assert abs(bds[1] - 5e-9 * C_M_S * (F_B1I_HZ / F_L1_HZ) ** 2) < 1e-9
    gps_p = KlobucharParams(alpha=(1e-8, 0, 0, 0), beta=(90000.0, 0, 0, 0), system="GPS")
    gps = klobuchar_gps_m(gps_p, 0.5, 0.0, zenith, north, 0.0, carriers)
    l1_m = 5e-9 * (1 + 16 * (0.53 - 0.5) ** 3) * C_M_S
    assert abs(gps[1] - l1_m) < 1e-9
    assert abs(gps[0] - l1_m * (F_L1_HZ / F_B1I_HZ) ** 2) < 1e-9
    assert gps[0] > gps[1]  # B1I is the lower frequency: more delay


def test_saastamoinen_zenith_delay_is_about_2_4_m():
    z = saastamoinen_m(math.radians(45), 0.0, np.array([math.pi / 2]))[0]
    assert 2.3 < z < 2.6
    low = saastamoinen_m(math.radians(45), 0.0, np.array([math.radians(10)]))[0]
    assert 5.0 * z < low < 6.5 * z
    assert saastamoinen_m(0.0, 2e6, np.array([1.0]))[0] == 0.0
