"""Ephemeris selection by toe, health and age, and the atomically persisted store."""

import dataclasses
import json
import logging

import pytest

from drivers.rinex import read_nav
from service.core.ephemeris import EphemerisStore
from service.core.errors import EphemerisError
from tests.support.paths import DATA


@pytest.fixture(scope="module")
def nav():
    return read_nav(DATA / "hksc-2021/hksc1610.nav")


def test_nearest_toe_within_age(nav):
    store = EphemerisStore(max_age_s=7200)
    for items in nav.ephemerides.values():
        store.add_all(items)
    # 03:35:40 BDT on Thursday: the 04:00 set (24 min away) beats the 03:00 one (36 min)
    sow = 4 * 86400 + 3 * 3600 + 35 * 60 + 40.0
    e = store.select("C01", 805, sow)
    assert e is not None and e.toe_sow_s == 4 * 86400 + 4 * 3600
    assert store.select("C01", 805, sow - 86400) is None  # a day earlier: too old
    assert store.select("C99", 805, sow) is None


def test_unhealthy_sets_are_refused_with_a_log_line(nav, caplog):
    store = EphemerisStore()
    good = nav.ephemerides["C08"][0]
    bad = dataclasses.replace(good, health=1, toe_sow_s=good.toe_sow_s + 3600)
    with caplog.at_level(logging.INFO, logger="service.core.ephemeris"):
        assert store.add(good) and not store.add(bad)
    assert store.refused == 1 and "unhealthy" in caplog.text
    assert store.select("C08", good.week, bad.toe_sow_s).toe_sow_s == good.toe_sow_s


def test_persisted_store_round_trips_and_damage_is_reported(nav, tmp_path):
    store = EphemerisStore()
    for items in nav.ephemerides.values():
        store.add_all(items)
    store.iono = nav.iono_bds
    path = tmp_path / "state" / "ephemeris.json"
    store.save(path)
    back = EphemerisStore.load(path)
    assert len(back) == len(store) and back.iono == nav.iono_bds
    a = store.select("C11", 805, 4 * 86400 + 12000.0)
    b = back.select("C11", 805, 4 * 86400 + 12000.0)
    assert dataclasses.replace(b, source="rinex") == a and b.source == "store"
    assert not list(path.parent.glob(".ephemeris.json.*"))  # no temp files left
    path.write_text(path.read_text()[:100])
    with pytest.raises(EphemerisError, match="cannot read ephemeris store"):
        EphemerisStore.load(path)
    path.write_text(json.dumps({"version": 99, "ephemerides": []}))
    with pytest.raises(EphemerisError, match="unsupported store version"):
        EphemerisStore.load(path)
