"""The daemon's saved ephemeris store keeps what can still be used: sets whose t_oe is more
than a day before the latest measurement are dropped when the store is saved."""

from __future__ import annotations

from dataclasses import replace
from itertools import islice

from drivers.rinex import RinexObsReader, read_nav
from service.core.ephemeris import EphemerisStore
from service.daemon.loop import Runner
from service.engine.pipeline import Pipeline
from service.output.publish import Publishers
from tests.support.paths import DATA

HK = DATA / "hksc-2021"


def test_saved_store_drops_sets_older_than_a_day_before_the_latest_epoch(tmp_path):
    nav = read_nav(HK / "hksc1610.nav")
    ephs = [e for sets in nav.ephemerides.values() for e in sets]
    # the same satellite's set, broadcast three days earlier (same week: no rollover here)
    first = min(ephs, key=lambda e: (e.week, e.toe_sow_s))
    old = replace(
        first, toe_sow_s=first.toe_sow_s - 3 * 86400.0, toc_sow_s=first.toc_sow_s - 3 * 86400.0
    )
    assert old.toe_sow_s > 0
    epochs = list(islice(RinexObsReader(HK / "hksc1610.obs"), 3))
    store_path = tmp_path / "ephemeris.json"
    pipeline = Pipeline(EphemerisStore())
    runner = Runner([old, *ephs, *epochs], pipeline, Publishers(), store_path=store_path)
    assert runner.run() == 3

    saved = EphemerisStore.load(store_path)
    kept = {(e.prn, e.week, e.toe_sow_s) for e in saved.all()}
    assert (old.prn, old.week, old.toe_sow_s) not in kept
    assert kept == {(e.prn, e.week, e.toe_sow_s) for e in ephs}
    assert pipeline.counters["ephemeris_pruned"] == 1
