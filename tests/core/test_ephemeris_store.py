"""Ephemeris selection by toe, health and age, and the atomically persisted store."""

import dataclasses
import json
import logging
import os
import stat

import numpy as np
import pytest

from drivers.rinex import read_nav
from service.core.ephemeris import STORE_FILE_MODE, EphemerisStore
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


def test_select_span_holds_select_s_answer_and_ends_where_it_changes(nav):
    """Inside the span select() returns the same set; just past either end (or at the
    hourly midpoint between two t_oe) it returns another set or None."""
    store = EphemerisStore(max_age_s=7200)
    for items in nav.ephemerides.values():
        store.add_all(items)
    week = 805
    for prn in ("C01", "C11"):
        for sow in (4 * 86400 + 3 * 3600 + 35 * 60 + 40.0, 4 * 86400 + 12000.0):
            eph, lo, hi = store.select_span(prn, week, sow)
            assert eph is store.select(prn, week, sow)
            assert lo < week * 604800 + sow < hi
            for t in np.linspace(lo, hi, 41)[1:-1]:
                assert store.select(prn, 0, float(t)) is eph
            for t in (lo - 1e-3, hi + 1e-3):
                assert store.select(prn, 0, float(t)) is not eph
    assert store.select_span("C99", week, 4 * 86400.0)[0] is None


def test_remembered_selection_follows_new_sets_age_limit_and_pruning(nav):
    """select() answers from the satellite's last span while nothing changes; a set added,
    a different max_age_s or a prune is seen at once."""
    store = EphemerisStore(max_age_s=7200)
    first = nav.ephemerides["C08"][0]
    store.add(first)
    t = first.toe_sow_s + 1500.0
    assert store.select("C08", first.week, t) is first
    assert store.select("C08", first.week, t + 1.0) is first  # from the span
    newer = dataclasses.replace(first, toe_sow_s=first.toe_sow_s + 3600.0)
    store.add(newer)
    assert store.select("C08", first.week, t + 1.0) is first  # 1501 s vs 2099 s away
    assert store.select("C08", first.week, t + 400.0) is newer  # past the midpoint
    store.max_age_s = 600.0
    assert store.select("C08", first.week, t + 400.0) is None  # 1700 s: too old now
    store.max_age_s = 7200.0
    assert store.select("C08", first.week, t + 400.0) is newer
    assert store.select("C08", first.week, t) is first
    store.prune(first.week, newer.toe_sow_s, keep_s=1800.0)  # drops the first set
    assert store.select("C08", first.week, t) is newer


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


def _hourly(eph, hours):
    """``eph`` re-issued every hour for ``hours`` hours from its t_oe (BDT week carried)."""
    out = []
    for k in range(hours):
        t_s = eph.toe_sow_s + 3600.0 * k
        week = eph.week + int(t_s // 604800.0)
        sow = t_s % 604800.0
        out.append(dataclasses.replace(eph, week=week, toe_sow_s=sow, toc_sow_s=sow))
    return out


def test_each_satellite_holds_at_most_max_sets_oldest_go_first(nav):
    sets = _hourly(nav.ephemerides["C11"][0], 100)
    store = EphemerisStore(max_sets_per_prn=64)
    assert store.add_all(sets) == 100
    assert len(store) == 64 and store.evicted == 36
    kept = [(e.week, e.toe_sow_s) for e in store.all()]
    assert kept == [(e.week, e.toe_sow_s) for e in sets[36:]]
    last = sets[-1]
    assert store.select("C11", last.week, last.toe_sow_s + 100.0) is last


def test_prune_keeps_each_satellites_last_day(nav):
    c11 = _hourly(nav.ephemerides["C11"][0], 60)
    c12 = _hourly(nav.ephemerides["C12"][0], 12)  # stopped 48 h before the end
    store = EphemerisStore()
    store.add_all(c11 + c12)
    end = c11[-1]
    dropped = store.prune(end.week, end.toe_sow_s + 1800.0)
    held = {p: [e.toe_sow_s for e in store.all() if e.prn == p] for p in store.prns}
    assert held["C11"] == [e.toe_sow_s for e in c11[-24:]]  # less than a day before
    assert held["C12"] == [e.toe_sow_s for e in c12]  # its newest day, though old
    assert dropped == 36
    # a time tag a week in the past drops nothing: each satellite keeps its newest day
    assert store.prune(end.week - 1, end.toe_sow_s) == 0
    assert len(store) == 36


def test_selection_is_nearest_toe_earliest_received_on_a_tie(nav):
    a, b = _hourly(nav.ephemerides["C11"][0], 2)
    store = EphemerisStore()
    store.add_all([b, a])
    mid = a.toe_sow_s + 1800.0
    assert store.select("C11", a.week, mid) is b  # equally near: the first received
    assert store.select("C11", a.week, mid - 1e-3) is a
    assert store.select("C11", a.week, mid + 1e-3) is b


@pytest.mark.parametrize("umask", [0o000, 0o077, 0o277])
def test_saved_store_mode_is_fixed_whatever_the_umask(nav, tmp_path, umask):
    store = EphemerisStore()
    store.add_all(nav.ephemerides["C11"])
    path = tmp_path / "ephemeris.json"
    old = os.umask(umask)
    try:
        store.save(path)
        store.save(path)  # over an existing file too
    finally:
        os.umask(old)
    assert stat.S_IMODE(path.stat().st_mode) == STORE_FILE_MODE
    assert len(EphemerisStore.load(path)) == len(store)


def test_saving_never_follows_a_symlink_planted_as_its_temp_file(nav, tmp_path):
    store = EphemerisStore()
    store.add_all(nav.ephemerides["C11"])
    victim = tmp_path / "victim"
    victim.write_text("keep")
    path = tmp_path / "ephemeris.json"
    (tmp_path / ".ephemeris.json.planted").symlink_to(victim)
    store.save(path)
    assert victim.read_text() == "keep"
    assert len(EphemerisStore.load(path)) == len(store)


def _good_doc(nav):
    store = EphemerisStore()
    store.add_all(nav.ephemerides["C11"])
    store.iono = nav.iono_bds
    return {
        "version": 1,
        "ephemerides": [dataclasses.asdict(e) for e in store.all()],
        "iono": dataclasses.asdict(store.iono),
    }


def _bad_docs(nav):
    doc = _good_doc(nav)
    item = doc["ephemerides"][0]
    return {
        "list": [1, 2],
        "number": 5,
        "ephemerides number": {"version": 1, "ephemerides": 5},
        "no version": {"ephemerides": 5},
        "no ephemerides": {"version": 1},
        "item a list": {**doc, "ephemerides": [[1, 2]]},
        "week a string": {**doc, "ephemerides": [{**item, "week": "805"}]},
        "e null": {**doc, "ephemerides": [{**item, "e": None}]},
        "health true": {**doc, "ephemerides": [{**item, "health": True}]},
        "prn a number": {**doc, "ephemerides": [{**item, "prn": 11}]},
        "field missing": {**doc, "ephemerides": [{k: v for k, v in item.items() if k != "e"}]},
        "field unknown": {**doc, "ephemerides": [{**item, "extra": 1}]},
        "iono a string": {**doc, "iono": "BDS"},
        "iono short": {**doc, "iono": {**doc["iono"], "alpha": [0.0]}},
    }


def test_wrongly_shaped_stores_are_damage(nav, tmp_path):
    path = tmp_path / "ephemeris.json"
    path.write_text(json.dumps(_good_doc(nav)))
    assert len(EphemerisStore.load(path)) == len(nav.ephemerides["C11"])
    for name, doc in _bad_docs(nav).items():
        path.write_text(json.dumps(doc))
        with pytest.raises(EphemerisError) as err:
            EphemerisStore.load(path)
        assert "ephemeris store" in str(err.value) or "version" in str(err.value), name
    # well shaped, but a value no float holds: that set is refused, the rest load
    doc = _good_doc(nav)
    doc["ephemerides"][0]["af0_s"] = 10**400
    path.write_text(json.dumps(doc))
    assert len(EphemerisStore.load(path)) == len(doc["ephemerides"]) - 1
    for raw in (b"", b"\xff\xfe\x00garbage", b"[" * 100_000, b'{"version": 1, "ephem'):
        path.write_bytes(raw)
        with pytest.raises(EphemerisError):
            EphemerisStore.load(path)


def test_a_damaged_store_is_moved_aside_with_one_warning(tmp_path, caplog):
    path = tmp_path / "ephemeris.json"
    path.write_text("[1, 2]")
    with caplog.at_level(logging.WARNING, logger="service.core.ephemeris"):
        try:
            EphemerisStore.load(path)
        except EphemerisError as exc:
            target = EphemerisStore.set_aside(path, exc)
    assert target is not None and not path.exists()
    assert target.name.startswith("ephemeris.json.corrupt-") and target.read_text() == "[1, 2]"
    assert len(caplog.records) == 1 and "\n" not in caplog.records[0].getMessage()
    assert caplog.records[0].levelno == logging.WARNING
    path.write_text("{}")
    assert EphemerisStore.set_aside(path, "again") != target  # the same second: a new name


@pytest.mark.parametrize("prn_system", ["E", "G", "C"])
def test_a_set_broadcast_again_as_unhealthy_is_no_longer_used(prn_system):
    """Galileo flags a satellite in I/NAV word type 5 without a new IODnav (and GPS/BeiDou
    may re-send a set with its health raised): the same (PRN, week, t_oe) arriving
    unhealthy takes the held copy out of use, through the pipeline's counter too; a later
    healthy set of another t_oe is taken again."""
    from service.engine.pipeline import Pipeline

    nav = read_nav(DATA / "hksc-2021" / "hksc1610.nav", "CGE")
    prn, sets = next((p, s) for p, s in sorted(nav.ephemerides.items()) if p[0] == prn_system)
    eph = next(e for e in sets if e.health == 0)
    pipe = Pipeline(store=EphemerisStore(max_age_s=7200.0))
    pipe.add_ephemeris(eph)
    assert pipe.store.select(prn, eph.week, eph.toe_sow_s) == eph
    pipe.add_ephemeris(dataclasses.replace(eph, health=1))
    assert pipe.store.select(prn, eph.week, eph.toe_sow_s) is None
    assert pipe.counters["ephemeris_dropped_unhealthy"] == 1
    assert pipe.counters["ephemeris_refused_unhealthy"] == 1
    later = next((e for e in sets if e.health == 0 and e.toe_sow_s != eph.toe_sow_s), None)
    if later is not None:
        pipe.add_ephemeris(later)
        assert pipe.store.select(prn, later.week, later.toe_sow_s) == later
