"""Broadcast orbit and clock checked against an independent scalar transcription of the ICD,
against continuity between consecutive ephemerides, and against GEO nominal longitudes."""

import dataclasses
import itertools
import math

import numpy as np
import pytest

from service.core.bds import is_geo
from service.core.geometry import ecef_to_geodetic
from service.core.orbit import EphemerisArrays, sat_pos_clock, sat_pos_vel_clock
from tests.support.independent import eph_from_georinex as _eph
from tests.support.independent import georinex_bds_ephemerides, icd_position
from tests.support.paths import DATA

NAV = DATA / "hksc-2021" / "hksc1610.nav"


@pytest.fixture(scope="module")
def records():
    # The file repeats some records verbatim; georinex renames the repeats "C01_1" and
    # misaligns their fields, so keep the first occurrence only.
    return [r for r in georinex_bds_ephemerides(NAV) if "_" not in r["prn"]]


def test_positions_match_scalar_icd_transcription(records):
    """Every BDS record, at toe and +-30 min: vectorised == scalar ICD to 1 mm."""
    worst = 0.0
    for rec in records:
        arr = EphemerisArrays.from_ephemerides([_eph(rec)])
        for dt_s in (-1800.0, 0.0, 1800.0):
            t = rec["Toe"] + dt_s
            pos, _ = sat_pos_clock(arr, int(rec["BDTWeek"]), np.array([t]))
            ref = icd_position(rec, t, is_geo(rec["prn"]))
            worst = max(worst, float(np.linalg.norm(pos[0] - ref)))
    assert worst < 1e-3, worst


def test_consecutive_ephemerides_agree_between_toes(records):
    """Two hourly sets evaluated at the half hour between their toes agree to a few metres.

    A wrong GEO node or a missing -5 deg rotation puts GEOs km to thousands of km apart.
    """
    by_prn: dict[str, list[dict]] = {}
    for rec in records:
        by_prn.setdefault(rec["prn"], []).append(rec)
    checked = {"geo": 0, "non-geo": 0}
    for prn, recs in by_prn.items():
        recs.sort(key=lambda r: (r["BDTWeek"], r["Toe"]))
        for a, b in itertools.pairwise(recs):
            if b["Toe"] - a["Toe"] != 3600 or b["BDTWeek"] != a["BDTWeek"]:
                continue
            t = np.array([a["Toe"] + 1800.0])
            pa, _ = sat_pos_clock(EphemerisArrays.from_ephemerides([_eph(a)]), int(a["BDTWeek"]), t)
            pb, _ = sat_pos_clock(EphemerisArrays.from_ephemerides([_eph(b)]), int(b["BDTWeek"]), t)
            assert np.linalg.norm(pa - pb) < 10.0, (prn, float(np.linalg.norm(pa - pb)))
            checked["geo" if is_geo(prn) else "non-geo"] += 1
    assert checked["geo"] >= 10 and checked["non-geo"] >= 20, checked


def test_geos_stay_at_their_slot_longitudes(records):
    """Each GEO stays within 0.2 deg of one longitude over the file's five hourly sets.

    The slots seen in June 2021 are 144.5, 84, 110.5, 160 and 58.75 deg E for C01-C05.
    """
    slots = {"C01": 144.5, "C02": 84.0, "C03": 110.5, "C04": 160.0, "C05": 58.75}
    for prn, slot in slots.items():
        lons = []
        for rec in (r for r in records if r["prn"] == prn):
            arr = EphemerisArrays.from_ephemerides([_eph(rec)])
            for dt_s in (0.0, 1200.0, 2400.0):
                pos, _ = sat_pos_clock(arr, int(rec["BDTWeek"]), np.array([rec["Toe"] + dt_s]))
                lat, lon, alt = ecef_to_geodetic(pos[0])
                lons.append(math.degrees(lon))
                assert abs(math.degrees(lat)) < 3.0
                assert abs(alt - 35_786e3) < 100e3
        assert len(lons) >= 12
        assert max(lons) - min(lons) < 0.2, (prn, min(lons), max(lons))
        assert abs(np.mean(lons) - slot) < 0.6


def test_c59_to_c63_use_the_geo_algorithm(records):
    """A GEO ephemeris relabelled C59..C63 gives the same position as under C01 (GEO)."""
    rec = next(r for r in records if r["prn"] == "C01")
    base = _eph(rec)
    t = np.array([rec["Toe"] + 900.0])
    ref, _ = sat_pos_clock(EphemerisArrays.from_ephemerides([base]), base.week, t)
    for n in range(59, 64):
        relabelled = dataclasses.replace(base, prn=f"C{n}")
        pos, _ = sat_pos_clock(EphemerisArrays.from_ephemerides([relabelled]), base.week, t)
        assert np.allclose(pos, ref, atol=1e-6)
    as_meo = dataclasses.replace(base, prn="C30")
    pos, _ = sat_pos_clock(EphemerisArrays.from_ephemerides([as_meo]), base.week, t)
    assert np.linalg.norm(pos - ref) > 1e5


def test_clock_includes_relativity_and_tgd1(records):
    rec = next(r for r in records if r["prn"] == "C08")
    e = _eph(rec)
    t = rec["Toe"] + 600.0
    _, clk = sat_pos_clock(EphemerisArrays.from_ephemerides([e]), e.week, np.array([t]))
    dt = t - e.toc_sow_s
    poly = e.af0_s + e.af1_s_s * dt + e.af2_s_s2 * dt * dt
    # relativity: F e sqrt(A) sin(E); |term| <= 4.4e-10 * 0.01 * 6493 ~ 3e-8 s for IGSO
    rel = clk[0] - (poly - e.tgd1_s)
    assert abs(rel) < 4.45e-10 * e.e * e.sqrt_a_sqrt_m + 1e-15
    assert abs(rel) > 0.0


def test_velocities_match_the_derivative_of_the_scalar_icd_transcription(records):
    """sat_pos_vel_clock's velocity == the scalar ICD position (tests/support/independent.py)
    differenced over +-0.5 s, to 1 mm/s, for every record at toe and +-30 min; its position
    is sat_pos_clock's to 1 mm; the clock drift is a1 + 2 a2 (t - toc) up to the rate of
    the relativistic term F e sqrt(A) sin E (ICD 5.2.4.10), at most |F| e sqrt(A) n / (1 - e)."""
    worst_v = worst_p = worst_d = 0.0
    for rec in records:
        eph = _eph(rec)
        arr = EphemerisArrays.from_ephemerides([eph])
        for dt_s in (-1800.0, 0.0, 1800.0):
            t = rec["Toe"] + dt_s
            week = int(rec["BDTWeek"])
            pos, vel, _, drift = sat_pos_vel_clock(arr, week, np.array([t]))
            geo = is_geo(rec["prn"])
            ref_v = np.subtract(icd_position(rec, t + 0.5, geo), icd_position(rec, t - 0.5, geo))
            worst_v = max(worst_v, float(np.linalg.norm(vel[0] - ref_v)))
            p0, _ = sat_pos_clock(arr, week, np.array([t]))
            worst_p = max(worst_p, float(np.linalg.norm(pos[0] - p0[0])))
            want = eph.af1_s_s + 2 * eph.af2_s_s2 * (t - eph.toc_sow_s)
            n = math.sqrt(3.986004418e14 / eph.sqrt_a_sqrt_m**6) + eph.delta_n_rad_s
            rel = 4.442807309e-10 * eph.e * eph.sqrt_a_sqrt_m * n / (1 - eph.e)
            worst_d = max(worst_d, abs(float(drift[0]) - want) - rel)
    assert worst_v < 1e-3, worst_v
    assert worst_p < 1e-3, worst_p
    assert worst_d < 1e-14, worst_d


def test_inertial_speeds_obey_vis_viva(records):
    """|v_ECEF + omega x r|^2 = GM (2/r - 1/a) (Kepler energy; the harmonic corrections
    move it by < 0.1 %): a velocity in the wrong frame (for a GEO: 3 km/s instead of a few
    m/s in ECEF) fails by far."""
    gm, we = 3.986004418e14, 7.2921150e-5  # BDS-SIS-ICD-B1I-3.0 3.2
    for rec in records:
        arr = EphemerisArrays.from_ephemerides([_eph(rec)])
        pos, vel, _, _ = sat_pos_vel_clock(arr, int(rec["BDTWeek"]), np.array([rec["Toe"]]))
        r = pos[0]
        v_inertial = vel[0] + np.cross([0.0, 0.0, we], r)
        want = math.sqrt(gm * (2 / np.linalg.norm(r) - 1 / rec["sqrtA"] ** 2))
        assert abs(np.linalg.norm(v_inertial) / want - 1) < 1e-3, rec["prn"]
