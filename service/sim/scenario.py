"""The built-in scenario of ``bdsfix replay`` with no file: a virtual receiver near Beijing.

Warm start: the ephemerides (the paper's Table 1 constellation, at its epoch
2015-05-19 04:00 UTC) are held before the receiver starts. The simulator's UBX bytes go
through the real driver (``bdsfix replay`` decodes them), so the stream exercises the same
path as a receiver on a serial port.
"""

from __future__ import annotations

import datetime as dt
from collections import Counter
from collections.abc import Iterator, Sequence

from service.core.ephemeris import EphemerisStore
from service.core.sow_rule import DEFAULT_FULL_RULE
from service.core.timebase import bdt_to_gpst, gpst_from_utc
from service.core.types import Ephemeris
from service.engine.solver import IonoSet
from service.sim.keplerian import TABLE1_EPOCH_UTC, table1_ephemerides
from service.sim.simulator import SimConfig, Simulator

BEIJING = (39.9, 116.4, 50.0)


def scenario_config(
    seed: int = 0,
    duration_s: float = 60.0,
    rate_hz: float = 10.0,
    lat_deg: float = BEIJING[0],
    lon_deg: float = BEIJING[1],
    alt_m: float = BEIJING[2],
    start_offset_s: float = 0.0,
    full_rule: str = DEFAULT_FULL_RULE,
    start_gpst: tuple[int, float] | None = None,
    systems: str = "C",
) -> SimConfig:
    if start_gpst is None:
        start = dt.datetime(*TABLE1_EPOCH_UTC) + dt.timedelta(seconds=start_offset_s)
        week, tow = gpst_from_utc(start)
    else:
        week, tow = start_gpst
    return SimConfig(
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        alt_m=alt_m,
        start_gpst_week=week,
        start_gpst_tow_s=tow,
        duration_s=duration_s,
        rate_hz=rate_hz,
        seed=seed,
        full_rule=full_rule,
        systems=systems,
    )


def builtin_scenario(
    seed: int = 0,
    duration_s: float = 60.0,
    full_rule: str = DEFAULT_FULL_RULE,
    nav: tuple[Sequence[Ephemeris], IonoSet] | None = None,
    systems: str = "C",
) -> tuple[Iterator[bytes], int, EphemerisStore, IonoSet, float, str]:
    """The UBX byte chunks, the GPS week of the stream, the held ephemeris store,
    ionosphere, first-epoch offset [s] and a summary. Each satellite's prMes is valid once
    its time is known by ``full_rule`` (:mod:`service.core.sow_rule`).

    ``nav`` (the sets and ionosphere of a real nav file) replaces Table 1: the scenario
    starts 10 min after the t_oe most of its BeiDou satellites share
    (:func:`default_start_gpst`), and the GPS and Galileo satellites of ``systems`` join, on
    their own LNAV / I/NAV message timing (:mod:`service.sim.simulator`)."""
    if nav is None:
        cfg = scenario_config(seed=seed, duration_s=duration_s, full_rule=full_rule)
        ephs: list[Ephemeris] = table1_ephemerides(0.0)
        iono, what = IonoSet(), "Table 1"
        sim = Simulator(ephs, cfg)
    else:
        ephs, iono = list(nav[0]), nav[1]
        start = default_start_gpst([e for e in ephs if e.prn[0] == "C"] or ephs)
        cfg = scenario_config(
            seed=seed,
            duration_s=duration_s,
            full_rule=full_rule,
            start_gpst=start,
            systems=systems,
        )
        sim = Simulator(ephs, cfg, iono.bds, iono.gps if systems != "C" else None)
        what = "the nav file's"
    store = EphemerisStore()
    store.add_all(ephs)
    info = (
        f"virtual receiver at {cfg.lat_deg} N {cfg.lon_deg} E, {cfg.rate_hz:g} Hz, "
        f"{cfg.duration_s:g} s, warm start with {what} ephemerides, "
        f"{len(sim.prns)} satellites in view ({', '.join(sim.prns)})"
    )
    chunks = (data for _ep, data in sim.ubx_epochs())
    return chunks, cfg.start_gpst_week, store, iono, 1.0 / cfg.rate_hz, info


def default_start_gpst(ephs: Sequence[Ephemeris] | None) -> tuple[int, float]:
    """Where a simulation starts by default: 10 min after the t_oe most satellites of a nav
    file share (every one of them has a fresh set there), else Table 1's epoch."""
    if ephs:
        (week, toe), _ = Counter((e.week, e.toe_sow_s) for e in ephs).most_common(1)[0]
        return bdt_to_gpst(week, toe + 600.0)
    return gpst_from_utc(dt.datetime(*TABLE1_EPOCH_UTC))


def broadcast_table1() -> list[Ephemeris]:
    """Table 1 as broadcast ephemerides: propagated to the first t_oe at or after its epoch
    that the broadcast can carry (a multiple of 8 s: ICD 5.2.4.12, RTCM DF505), so that the
    sets a simulated stream carries are the ones it was made with."""
    toe = table1_ephemerides(0.0)[0].toe_sow_s
    return table1_ephemerides((-toe) % 8.0)
