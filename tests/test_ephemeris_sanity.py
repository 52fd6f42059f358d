"""Ephemeris sanity on entry (issue 9, item 7): ``ephemeris_problem`` and ``EphemerisStore.add``.

Good sets are real ones (HKSC 2021 RINEX nav, the Hiroshima OEM729 RTCM 1042s); each bad set
is a real one with one field changed by ``dataclasses.replace``. Expected radii are worked by
hand from the Keplerian elements (at t_oe with M0 = 0 the eccentric anomaly is 0, so
r = a (1 - e) + C_rc when omega = 0), never by the code under test.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import warnings

import pytest
from pyrtcm import RTCMReader

from drivers.rinex import read_nav
from drivers.rtcm import ephemeris_from_1042
from service.ephemeris import EphemerisStore, ephemeris_problem
from service.pipeline import Pipeline
from service.types import Ephemeris
from tests._independent import DATA

REAL_NAV = (
    "hksc-2021/hksc1610.nav",
    "hk-tst-urban-2019/hksc1180.19b",
    "hk-urban-3geo-2020/navigation_message.nav",
    "hk-polyu-f9p-ubx-2024/hksc269h.24f",
    "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx",
)
HIROSHIMA_RTCM = DATA / "hiroshima-oem729-rtcm-2022/20221213-010900.rtcm"


@pytest.fixture(scope="module")
def nav():
    return read_nav(DATA / "hksc-2021/hksc1610.nav")


@pytest.fixture(scope="module")
def c08(nav):
    """A healthy IGSO set (C08, toe 03:00 BDT)."""
    return nav.ephemerides["C08"][0]


@pytest.fixture(scope="module")
def c01(nav):
    """A healthy GEO set."""
    return nav.ephemerides["C01"][0]


def _check(eph):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy RuntimeWarning would raise here
        problem = ephemeris_problem(eph)
    return None if problem is None else problem.check


@pytest.mark.parametrize("rel", REAL_NAV)
def test_every_real_rinex_set_passes_except_unhealthy_ones(rel):
    ephs = [e for items in read_nav(DATA / rel).ephemerides.values() for e in items]
    assert ephs
    got = {(e.prn, e.week, e.toe_sow_s): _check(e) for e in ephs}
    want = {(e.prn, e.week, e.toe_sow_s): (None if e.health == 0 else "unhealthy") for e in ephs}
    assert got == want


def _hiroshima_1042():
    with HIROSHIMA_RTCM.open("rb") as fh:
        return [
            msg
            for _raw, msg in RTCMReader(fh, quitonerror=0)
            if msg is not None and getattr(msg, "identity", None) == "1042"
        ]


def test_every_real_rtcm_1042_set_passes():
    ephs = [ephemeris_from_1042(msg) for msg in _hiroshima_1042()]
    assert len(ephs) == 41  # README: 41 BDS ephemerides in the stream
    assert [_check(e) for e in ephs] == [None] * len(ephs)


class _WithUrai:
    """A real pyrtcm 1042 message with DF490 (URAI) replaced."""

    def __init__(self, msg, urai):
        self._msg, self._urai = msg, urai

    def __getattr__(self, name):
        return self._urai if name == "DF490" else getattr(self._msg, name)


@pytest.mark.parametrize(("urai", "ura_m", "check"), [(14, 6144.0, None), (15, math.inf, "ura")])
def test_rtcm_1042_urai_15_is_refused(urai, ura_m, check):
    """ICD B1I 5.2.4.5: URAI 14 is 3072 < URA <= 6144 m, URAI 15 is URA > 6144 m."""
    msg = _hiroshima_1042()[0]
    eph = ephemeris_from_1042(_WithUrai(msg, urai))
    assert eph.ura_m == ura_m and _check(eph) == check


@pytest.mark.parametrize(
    ("change", "check"),
    [
        ({"sqrt_a_sqrt_m": 0.0}, "sqrt_a"),
        ({"sqrt_a_sqrt_m": -6493.83}, "sqrt_a"),
        ({"sqrt_a_sqrt_m": 4999.0}, "sqrt_a"),  # a = 24,990 km
        ({"sqrt_a_sqrt_m": 6701.0}, "sqrt_a"),  # a = 44,903 km
        ({"e": 2.0}, "eccentricity"),
        ({"e": 0.99}, "eccentricity"),
        ({"e": 0.1}, "eccentricity"),
        ({"e": -1e-3}, "eccentricity"),
        ({"i0_rad": math.radians(95.0)}, "inclination"),
        ({"i0_rad": math.radians(70.5)}, "inclination"),
        ({"i0_rad": -0.01}, "inclination"),
        ({"health": 1}, "unhealthy"),
        ({"ura_m": math.inf}, "ura"),  # URAI 15 as service.bds_nav decodes it
        ({"ura_m": 6145.0}, "ura"),
        ({"ura_m": math.nan}, "ura"),
        ({"ura_m": -1.0}, "ura"),
        ({"prn": "C64"}, "prn"),
        ({"prn": "CXY"}, "prn"),
        # r = a (1 - e) at perigee: 25,000 km * 0.91 = 22,750 km < 25,000 km
        ({"sqrt_a_sqrt_m": 5000.0, "e": 0.09, "m0_rad": 0.0, "crc_m": 0.0, "crs_m": 0.0}, "radius"),
        # r = a (1 + e) at apogee: 44,890 km * 1.09 = 48,930 km > 45,000 km
        (
            {"sqrt_a_sqrt_m": 6700.0, "e": 0.09, "m0_rad": math.pi, "crc_m": 0.0, "crs_m": 0.0},
            "radius",
        ),
        # a circular orbit with omega = M0 = 0: r = a + C_rc = 27,906 km + 30,000 km
        (
            {"e": 0.0, "m0_rad": 0.0, "omega_rad": 0.0, "crs_m": 0.0, "crc_m": 3e7},
            "radius",
        ),
    ],
)
def test_each_check_refuses_its_damage(c08, c01, change, check):
    for good in (c08, c01):
        assert _check(good) is None
        assert _check(dataclasses.replace(good, **change)) == check, (good.prn, change)


@pytest.mark.parametrize(
    "change",
    [
        {"ura_m": 0.0},  # RINEX/Table 1: not stated
        {"ura_m": 6144.0},  # URAI 14
        {"e": 0.0},
        # at t_oe with M0 = 0: r = a (1 - e) + C_rs sin 2w + C_rc cos 2w = 37,952 km + C08's
        # own harmonics (a few hundred metres)
        {"e": 0.0999, "m0_rad": 0.0},
        # e = M0 = omega = 0: r = a + C_rc = 25,000 km + 1 km, and 44,890 km
        {"sqrt_a_sqrt_m": 5000.0, "e": 0.0, "m0_rad": 0.0, "omega_rad": 0.0, "crc_m": 1e3},
        {"sqrt_a_sqrt_m": 6700.0, "e": 0.0, "m0_rad": 0.0, "omega_rad": 0.0, "crc_m": 0.0},
        {"i0_rad": 0.0},
        {"i0_rad": math.radians(70.0)},
    ],
)
def test_values_inside_the_windows_pass(c08, change):
    """C08 is an IGSO (a = 42,164 km); the radius does not depend on i0 or URA."""
    assert _check(dataclasses.replace(c08, **change)) is None


@pytest.mark.parametrize(
    "name",
    [
        f.name
        for f in dataclasses.fields(Ephemeris)
        if f.name not in ("prn", "source", "ura_m", "health")
    ],
)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, "1.0"])
def test_every_numeric_field_must_be_a_finite_number(c08, name, value):
    assert _check(dataclasses.replace(c08, **{name: value})) == "not_finite"


def test_non_finite_health_is_not_finite(c08):
    assert _check(dataclasses.replace(c08, health=math.nan)) == "not_finite"


def test_refused_set_never_replaces_the_good_one(c08):
    store = EphemerisStore()
    assert store.add(c08)
    same_set = dataclasses.replace(c08, sqrt_a_sqrt_m=0.0)
    nearer = dataclasses.replace(c08, e=0.99, toe_sow_s=c08.toe_sow_s + 600)
    assert not store.add(same_set) and not store.add(nearer)
    assert store.select("C08", c08.week, c08.toe_sow_s + 600) is c08
    assert len(store) == 1 and store.refused == 2
    assert dict(store.refused_by_reason) == {"sqrt_a": 1, "eccentricity": 1}


def test_refusal_log_is_one_line_per_satellite_and_check_rate_limited(c08, c01, caplog):
    now = [1000.0]
    store = EphemerisStore(clock=lambda: now[0])
    bad08 = dataclasses.replace(c08, sqrt_a_sqrt_m=0.0)
    with caplog.at_level(logging.INFO, logger="service.ephemeris"):
        for t in (1000.0, 1010.0, 1059.0):
            now[0] = t
            assert not store.add(bad08)
        assert len(caplog.records) == 1
        first = caplog.records[0]
        assert first.levelno == logging.WARNING
        assert "C08" in first.getMessage() and "sqrtA 0 " in first.getMessage()
        assert "more since" not in first.getMessage()
        # another check on the same satellite, and another satellite: a line each
        assert not store.add(dataclasses.replace(c08, e=2.0))
        assert not store.add(dataclasses.replace(c01, sqrt_a_sqrt_m=0.0))
        assert len(caplog.records) == 3
        now[0] = 1060.0  # 60 s after the first line: the next one says what it stood for
        assert not store.add(bad08)
        assert len(caplog.records) == 4
        assert "(2 more since the last line)" in caplog.records[3].getMessage()
        assert not store.add(dataclasses.replace(c01, health=1))
    assert caplog.records[4].levelno == logging.INFO
    assert "unhealthy (SatH1=1)" in caplog.records[4].getMessage()
    assert store.refused == 7
    assert dict(store.refused_by_reason) == {"sqrt_a": 5, "eccentricity": 1, "unhealthy": 1}


def test_pipeline_counts_refusals_by_check(c08):
    pipe = Pipeline(EphemerisStore())
    pipe.add_ephemeris(c08)
    pipe.add_ephemeris(dataclasses.replace(c08, sqrt_a_sqrt_m=-6493.83))
    pipe.add_ephemeris(dataclasses.replace(c08, e=math.nan))
    pipe.add_ephemeris(dataclasses.replace(c08, health=1))
    counts = {k: v for k, v in pipe.counters.items() if k.startswith("ephemeris")}
    assert counts == {
        "ephemeris_rinex": 1,
        "ephemeris_refused": 3,
        "ephemeris_refused_sqrt_a": 1,
        "ephemeris_refused_not_finite": 1,
        "ephemeris_refused_unhealthy": 1,
    }


def test_persisted_store_with_a_nan_set_keeps_the_rest(nav, tmp_path, caplog):
    store = EphemerisStore()
    for items in nav.ephemerides.values():
        store.add_all(items)
    path = tmp_path / "ephemeris.json"
    store.save(path)
    doc = json.loads(path.read_text())
    hit = [i for i, item in enumerate(doc["ephemerides"]) if item["prn"] == "C08"]
    for i in hit:
        doc["ephemerides"][i]["sqrt_a_sqrt_m"] = math.nan  # json writes NaN, and reads it
    path.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING, logger="service.ephemeris"):
        back = EphemerisStore.load(path)
    assert len(back) == len(store) - len(hit) and "C08" not in back.prns
    assert back.refused_by_reason == {"not_finite": len(hit)}
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "C08" in lines[0] and "sqrt_a_sqrt_m is nan" in lines[0]
