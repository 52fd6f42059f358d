"""Two-body elements as broadcast ephemerides: the ICD orbit code (GEO branch included) must
reproduce a direct inertial Kepler propagation rotated by the Earth's spin."""

import math

import numpy as np
import pytest

from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.sim.keplerian import ephemeris_from_kepler, mean_from_true_anomaly

GM_M3_S2 = 3.986004418e14  # CGCS2000, BDS-SIS-ICD-B1I-3.0 3.2 (written here, not imported)
OMEGA_E_RAD_S = 7.2921150e-5  # CGCS2000, ICD 3.2


def _direct_ecef(a, e, inc, raan, argp, m0, gmst0, dt):
    """Independent two-body propagation in ECI, then rotation by GMST + Omega_e dt."""
    m = m0 + math.sqrt(GM_M3_S2 / a**3) * dt
    ecc_anom = m
    for _ in range(60):
        ecc_anom = m + e * math.sin(ecc_anom)
    nu = math.atan2(math.sqrt(1 - e * e) * math.sin(ecc_anom), math.cos(ecc_anom) - e)
    r = a * (1 - e * math.cos(ecc_anom))
    u = argp + nu
    x = r * (math.cos(raan) * math.cos(u) - math.sin(raan) * math.sin(u) * math.cos(inc))
    y = r * (math.sin(raan) * math.cos(u) + math.cos(raan) * math.sin(u) * math.cos(inc))
    z = r * math.sin(u) * math.sin(inc)
    th = gmst0 + OMEGA_E_RAD_S * dt
    return np.array([math.cos(th) * x + math.sin(th) * y, -math.sin(th) * x + math.cos(th) * y, z])


# Rows of the paper's Table 1: a [km], e, i, RAAN, argument of perigee, true anomaly [deg]
ROWS = {
    "C01": (42_167.046, 0.000385, 1.660, 14.091, 166.081, 256.057),
    "C02": (42_165.779, 0.000097, 0.216, 47.928, 22.396, 306.033),
    "C06": (42_157.559, 0.004004, 54.293, 200.802, 210.089, 1.845),
    "C11": (27_907.553, 0.002132, 55.838, 79.515, 207.483, 152.594),
    "C60": (42_165.839, 0.000550, 0.787, 41.955, 155.089, 259.219),
}


@pytest.mark.parametrize("prn", sorted(ROWS))
def test_broadcast_form_matches_direct_propagation(prn):
    a_km, e, inc, raan, argp, nu = ROWS[prn]
    a = a_km * 1e3
    inc, raan, argp, nu = (math.radians(v) for v in (inc, raan, argp, nu))
    m0 = mean_from_true_anomaly(nu, e)
    gmst0, toe = 2.345, 200_000.0
    eph = ephemeris_from_kepler(prn, a, e, inc, raan, argp, m0, gmst0, 900, toe)
    arr = EphemerisArrays.from_ephemerides([eph])
    for dt in (0.0, 0.6, 600.0, 3600.0, 43_200.0, 86_400.0, 250_000.0):
        pos, _ = sat_pos_clock(arr, 900, np.array([toe + dt]))
        ref = _direct_ecef(a, e, inc, raan, argp, m0, gmst0, dt)
        assert np.linalg.norm(pos[0] - ref) < 1e-3, (prn, dt)


def test_mean_anomaly_round_trip():
    for e in (0.0, 0.001, 0.1):
        for nu in np.linspace(-3.0, 3.0, 13):
            m = mean_from_true_anomaly(float(nu), e)
            ecc_anom = m
            for _ in range(80):
                ecc_anom = m + e * math.sin(ecc_anom)
            back = 2 * math.atan2(
                math.sqrt(1 + e) * math.sin(ecc_anom / 2), math.sqrt(1 - e) * math.cos(ecc_anom / 2)
            )
            assert abs(back - nu) < 1e-9
