"""Satellite IDs name their system; each supported system has its ICD's constants."""

import math
from pathlib import Path

import numpy as np
import pytest

from service.core.bds import is_geo, nav_type, orbit_class, subframe_period_s
from service.core.errors import BdsfixError
from service.core.systems import (
    SYSTEM_CONSTANTS,
    GnssSystem,
    constants_of,
    prn_number,
    sat_id,
    system_of,
)
from service.core.types import MeasurementEpoch
from tests.support.paths import DATA


@pytest.mark.parametrize(
    ("sat", "system"),
    [
        ("C06", GnssSystem.BDS),
        ("C 6", GnssSystem.BDS),
        ("G12", GnssSystem.GPS),
        ("E11", GnssSystem.GAL),
    ],
)
def test_system_of_reads_the_rinex_letter(sat, system):
    assert system_of(sat) == system


def test_unknown_letter_and_unsupported_system_are_clear_errors():
    with pytest.raises(BdsfixError, match="names no satellite system"):
        system_of("X01")
    with pytest.raises(BdsfixError, match="GLO satellites are not supported"):
        constants_of("R01")


def test_constants_differ_where_the_icds_differ():
    bds, gps, gal = (SYSTEM_CONSTANTS[s] for s in (GnssSystem.BDS, GnssSystem.GPS, GnssSystem.GAL))
    assert bds.omega_e_rad_s == 7.2921150e-5 and gps.omega_e_rad_s == 7.2921151467e-5
    assert gps.gm_m3_s2 == 3.986005e14 and bds.gm_m3_s2 == gal.gm_m3_s2 == 3.986004418e14
    assert (bds.code_period_s, gps.code_period_s, gal.code_period_s) == (1e-3, 1e-3, 4e-3)
    assert bds.carrier_hz == 1561.098e6 and gps.carrier_hz == gal.carrier_hz == 1575.42e6
    # F as each ICD prints it (BDS 5.2.4.10, IS-GPS-200 20.3.3.3.3.1, Galileo 5.1.4)
    assert bds.f_rel_s_per_sqrt_m == gal.f_rel_s_per_sqrt_m == -4.442807309e-10
    assert gps.f_rel_s_per_sqrt_m == -4.442807633e-10
    assert (bds.prn_max, gps.prn_max, gal.prn_max) == (63, 32, 36)


@pytest.mark.parametrize(
    ("sat", "geo"),
    [
        ("C01", True),
        ("C05", True),
        ("C59", True),
        ("C63", True),
        ("C 1", True),
        ("C06", False),
        ("C58", False),
        ("G01", False),  # GPS PRN 1 is a MEO: GEOs are BeiDou's alone
        ("G02", False),
        ("E01", False),
        ("J01", False),  # QZS-1's successor is an IGSO, J07 a GEO: not BeiDou's algorithm
        ("R01", False),
        ("S20", False),
    ],
)
def test_is_geo_is_true_for_beidou_geos_only(sat, geo):
    assert is_geo(sat) is geo


def test_bds_only_helpers_name_what_they_take():
    geos = [n for n in range(1, 64) if is_geo(sat_id(GnssSystem.BDS, n))]
    assert geos == [1, 2, 3, 4, 5, 59, 60, 61, 62, 63]
    assert (nav_type("C01"), nav_type("C60"), nav_type("C06")) == ("D2", "D2", "D1")
    assert (subframe_period_s("C03"), subframe_period_s("C30")) == (0.6, 6.0)


def test_satellite_ids_round_trip_through_their_system():
    for system in (GnssSystem.BDS, GnssSystem.GPS, GnssSystem.GAL):
        for n in (1, 9, 32):
            sat = sat_id(system, n)
            assert len(sat) == 3 and system_of(sat) is system and prn_number(sat) == n
    assert sat_id(GnssSystem.BDS, 6) == "C06" and prn_number("G 7") == 7


def test_an_epoch_without_periods_takes_each_systems_code_period():
    """``MeasurementEpoch.from_columns`` without ``period_s``: 1 ms for B1I and GPS C/A,
    4 ms for Galileo E1 (its primary code, OS SIS ICD 3.4), and the fractional ranges are
    the pseudoranges modulo c times that."""
    c = 299_792_458.0
    pr = np.array([21_000_123.456, 22_000_987.654, 23_456_789.012])
    ep = MeasurementEpoch.from_columns(2161, 345600.0, ["C06", "G12", "E11"], ["2I"] * 3, pr)
    assert ep.period_s.tolist() == [1e-3, 1e-3, 4e-3]
    for i, t in enumerate((1e-3, 1e-3, 4e-3)):
        assert ep.frac_pr_m[i] == pytest.approx(math.fmod(pr[i], c * t), abs=1e-6)


def _broadcast_orbits(path: Path) -> dict[str, tuple[float, float]]:
    """Semi-major axis [km] and inclination [deg] of each BeiDou satellite's first record in
    a RINEX 3 nav file, read here by column (RINEX 3.04 Table A8: sqrt(A) is the fourth
    field of broadcast orbit 2, i0 the first of orbit 4), not by the project's reader."""
    lines = path.read_text().splitlines()
    i = next(k for k, line in enumerate(lines) if "END OF HEADER" in line) + 1
    orbits: dict[str, tuple[float, float]] = {}
    while i < len(lines):
        if lines[i][:1] != "C":
            i += 1
            continue
        sqrt_a = float(lines[i + 2][61:80].replace("D", "E"))
        i0_rad = float(lines[i + 4][4:23].replace("D", "E"))
        orbits.setdefault(lines[i][:3], (sqrt_a**2 / 1e3, math.degrees(i0_rad)))
        i += 8
    return orbits


def test_orbit_classes_match_the_broadcast_orbits_of_the_2024_constellation():
    """GEO_PRNS and IGSO_PRNS against the orbits the satellites fly: the real 2024 nav
    file holds the whole BeiDou-2/-3 constellation (50 satellites). Geosynchronous means a
    semi-major axis near 42,164 km; a GEO's inclination is a few degrees, an IGSO's about
    55; the MEOs fly at about 27,906 km."""
    orbits = _broadcast_orbits(DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f")
    assert len(orbits) == 50
    for prn, (a_km, inc_deg) in orbits.items():
        if abs(a_km - 42164.0) < 100.0:
            flown = "GEO" if inc_deg < 10.0 else "IGSO"
        else:
            assert abs(a_km - 27906.0) < 100.0, prn
            flown = "MEO"
        assert orbit_class(prn) == flown, (prn, a_km, inc_deg)
        assert is_geo(prn) is (flown == "GEO")
        assert nav_type(prn) == ("D2" if flown == "GEO" else "D1")
