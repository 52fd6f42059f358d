"""A long ephemeris history, as a receiver running for days or a year would see it.

Each satellite of a real navigation file (the first healthy set per PRN of the HK 2024
file: 44 BDS satellites) is broadcast again every hour, its t_oe and t_oc shifted by an hour
each time (ICD B1I 5.2.4.9: hourly updates), so the history ends with the real sets at a
common t_oe. One measurement epoch follows each hour's sets, so the daemon's pruning has a
time to prune by. Shared by tests/daemon/test_store_bound.py and bench/bench_store.py.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import replace

from service.core.ephemeris import ephemeris_problem
from service.core.timebase import bdt_to_gpst, normalize
from service.core.types import Ephemeris, MeasurementEpoch
from tests.support.paths import DATA

NAV_2024 = DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f"
HOUR_S = 3600.0
EPOCH_AFTER_SETS_S = 1200.0
"""Each hour's epoch is this long [s] after the hour's t_oe."""


def base_sets(nav_path=NAV_2024, prns: Sequence[str] | None = None) -> list[Ephemeris]:
    """The first healthy set of each satellite (or of ``prns``), all moved to the t_oe of the
    first one: the sets the history ends with."""
    from drivers.rinex import read_nav

    nav = read_nav(nav_path)
    sets = [
        next(e for e in nav.ephemerides[p] if ephemeris_problem(e) is None)
        for p in sorted(prns or nav.ephemerides)
        if any(ephemeris_problem(e) is None for e in nav.ephemerides[p])
    ]
    week, toe = sets[0].week, sets[0].toe_sow_s
    return [replace(e, week=week, toe_sow_s=toe, toc_sow_s=toe) for e in sets]


def shifted(eph: Ephemeris, dt_s: float) -> Ephemeris:
    """``eph`` with t_oe and t_oc moved by ``dt_s`` (BDT week carried)."""
    week, toe = normalize(eph.week, eph.toe_sow_s + dt_s)
    return replace(eph, week=week, toe_sow_s=toe, toc_sow_s=toe)


def time_tag(eph: Ephemeris, after_s: float = EPOCH_AFTER_SETS_S) -> MeasurementEpoch:
    """A measurement epoch without satellites, ``after_s`` after ``eph``'s t_oe (GPST)."""
    week, tow = bdt_to_gpst(eph.week, eph.toe_sow_s + after_s)
    return MeasurementEpoch.from_columns(week, tow, [], [], [])


def history(bases: Sequence[Ephemeris], hours: int) -> Iterator[Ephemeris | MeasurementEpoch]:
    """``hours`` hours of hourly sets of every satellite in ``bases``, ending with ``bases``
    themselves; each hour's sets are followed by a time-tag epoch."""
    for k in range(hours - 1, -1, -1):
        sets = [shifted(e, -k * HOUR_S) for e in bases]
        yield from sets
        yield time_tag(sets[0])
