"""Months unattended: the daemon's ephemeris store is bounded by design. A year of hourly
sets fed through the loop as a receiver would deliver them leaves the same store as one
day does (each satellite's last 24 sets), and the store never holds more than
MAX_SETS_PER_PRN sets of a satellite on the way (bench/bench_store.py times it)."""

from __future__ import annotations

from service.core.ephemeris import MAX_SETS_PER_PRN, EphemerisStore
from service.daemon.loop import Runner
from service.engine.pipeline import Pipeline
from service.output.publish import Publishers
from tests.support.history import base_sets, history

PRNS = ("C01", "C11", "C38")  # a GEO, a MEO and an IGSO keep the year quick


def _run(hours: int, tmp_path) -> tuple[EphemerisStore, Pipeline, int]:
    bases = base_sets(prns=PRNS)
    assert [e.prn for e in bases] == list(PRNS)
    path = tmp_path / f"{hours}h" / "ephemeris.json"
    pipeline = Pipeline(EphemerisStore())
    most = 0

    def watch(_result) -> None:
        nonlocal most
        most = max(most, len(pipeline.store))

    runner = Runner(history(bases, hours), pipeline, Publishers(), store_path=path, on_result=watch)
    assert runner.run() == hours
    return EphemerisStore.load(path), pipeline, most


def test_a_year_of_hourly_sets_leaves_the_store_a_day_leaves(tmp_path):
    day, day_pipe, _ = _run(24, tmp_path)
    year, year_pipe, most = _run(365 * 24, tmp_path)
    assert len(year) == len(day) == 24 * len(PRNS)
    keys = {(e.prn, e.week, e.toe_sow_s) for e in day.all()}
    assert {(e.prn, e.week, e.toe_sow_s) for e in year.all()} == keys
    assert most <= MAX_SETS_PER_PRN * len(PRNS)  # bounded all along, not only when saved
    fed = 365 * 24 * len(PRNS)
    assert year_pipe.counters["ephemeris_rinex"] == fed
    assert year_pipe.counters["ephemeris_evicted"] + year_pipe.counters[
        "ephemeris_pruned"
    ] == fed - len(year)
    assert day_pipe.counters["ephemeris_pruned"] == 0
