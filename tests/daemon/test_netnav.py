"""Network ephemerides in the daemon: the age gate (service/daemon/netnav.py) and the loop's
network sources (service/daemon/loop.py), with real ephemerides (the paper's Table 1 sets,
broadcast as the simulator does) and the virtual receiver's UBX through the real driver."""

from __future__ import annotations

import dataclasses
import logging
import threading
from collections.abc import Iterator

import pytest

from drivers.source import StreamDecoder
from service.core.ephemeris import EphemerisStore
from service.core.errors import ConfigError, InputError
from service.core.timebase import bdt_to_gpst
from service.core.types import UNKNOWN_WEEK, Ephemeris, MeasurementEpoch
from service.daemon.config import load_config, nav_files, ntrip_sources
from service.daemon.loop import Runner
from service.daemon.netnav import MAX_HELD, NetNavGate
from service.engine.pipeline import EpochResult, Pipeline
from service.output.publish import Publishers
from service.sim.scenario import broadcast_table1, scenario_config
from service.sim.simulator import Simulator

MAX_AGE_S = 7200.0


def _sets() -> list[Ephemeris]:
    return broadcast_table1()


def _at(eph: Ephemeris, after_toe_s: float) -> tuple[int, float]:
    """GPST of ``after_toe_s`` after the set's t_oe (BDT = GPST - 14 s, ICD 3.1.2 / 5.2)."""
    week, tow = bdt_to_gpst(eph.week, eph.toe_sow_s)
    return week, tow + after_toe_s


def test_sets_are_held_until_the_receiver_gives_a_time_then_judged_by_it():
    gate = NetNavGate(MAX_AGE_S)
    sets = _sets()
    assert all(gate.offer(e) == [] for e in sets)
    assert gate.on_epoch(UNKNOWN_WEEK, 100.0) == []  # no week: no time yet
    taken = gate.on_epoch(*_at(sets[0], 600.0))
    assert sorted(e.prn for e in taken) == sorted(e.prn for e in sets)
    assert all(e.source == "ntrip" for e in taken)
    assert [dataclasses.replace(e, source=s.source) for e, s in zip(taken, sets, strict=True)] == (
        sets
    )
    assert gate.counters == {"ntrip_ephemerides": len(sets)}
    assert gate.on_epoch(*_at(sets[0], 700.0)) == []  # judged once


def test_stale_sets_are_refused_once_with_one_warning_and_repeats_are_skipped(caplog):
    caplog.set_level(logging.WARNING)
    gate = NetNavGate(MAX_AGE_S)
    eph = _sets()[0]
    gate.on_epoch(*_at(eph, 3 * 3600.0))  # the receiver is 3 h past the set's t_oe
    assert gate.offer(eph, "ntrip://***@h:2101/M") == []
    assert gate.offer(eph, "ntrip://***@h:2101/M") == []  # the caster repeats it
    assert gate.counters == {"ntrip_stale": 1, "ntrip_repeats": 1}
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1
    assert f"ephemeris {eph.prn}" in lines[0] and "3.0 h before" in lines[0]
    assert "refused as stale" in lines[0] and "ntrip://***@h:2101/M" in lines[0]
    # the next hour's set is current: taken
    nxt = dataclasses.replace(eph, toe_sow_s=eph.toe_sow_s + 3 * 3600.0)
    assert gate.offer(nxt) == [dataclasses.replace(nxt, source="ntrip")]
    # a set from the receiver's future beyond the limit is refused too
    future = dataclasses.replace(eph, toe_sow_s=eph.toe_sow_s + 6 * 3600.0)
    assert gate.offer(future) == []
    assert gate.counters["ntrip_stale"] == 2


def test_held_sets_are_bounded_per_satellite_newest_kept():
    gate = NetNavGate(1e9)
    eph = _sets()[0]
    hours = [dataclasses.replace(eph, toe_sow_s=eph.toe_sow_s + 3600.0 * h) for h in range(7)]
    for e in hours:
        gate.offer(e)
    gate.offer(hours[-1])  # a repeat while held replaces, not duplicates
    taken = gate.on_epoch(*_at(eph, 0.0))
    assert [e.toe_sow_s for e in taken] == [e.toe_sow_s for e in hours[-MAX_HELD:]]


def _receiver(duration_s: float) -> list:
    """The virtual receiver's events (UBX through the real driver): no ephemeris in them."""
    cfg = scenario_config(duration_s=duration_s)
    sim = Simulator(broadcast_table1(), cfg)
    dec = StreamDecoder(gps_week=cfg.start_gpst_week)
    events = [ev for _ep, data in sim.ubx_epochs() for ev in dec.feed(data)]
    events += dec.flush()
    assert not any(isinstance(ev, Ephemeris) for ev in events)
    return events


def test_runner_takes_only_ephemerides_from_a_network_source_and_reads_on_after_it_fails(
    caplog,
):
    """A network source gives a stale set, the current sets and a base station's epoch,
    then fails (a refused caster): the receiver (no ephemeris in its stream) gets fast fixes
    from the network's current sets, the base station's epoch is never solved, the failure
    is one ERROR line and the loop reads its receiver to the end."""
    caplog.set_level(logging.INFO)
    sets = _sets()
    receiver = _receiver(8.0)
    first = next(ev for ev in receiver if isinstance(ev, MeasurementEpoch))
    base_epoch = dataclasses.replace(first, gpst_tow_s=first.gpst_tow_s - 3600.0)
    stale = dataclasses.replace(sets[0], toe_sow_s=sets[0].toe_sow_s - 4 * 3600.0)
    nav_done = threading.Event()

    def network() -> Iterator[object]:
        try:
            yield stale
            yield from sets
            yield base_epoch
            raise InputError("nav ntrip://***@h:2101/M: the caster refused the credentials")
        finally:
            nav_done.set()

    def receiver_after_network() -> Iterator[object]:
        nav_done.wait(timeout=60)  # every network event is queued before the receiver's
        yield from receiver

    results: list[EpochResult] = []
    store = EphemerisStore()
    runner = Runner(
        receiver_after_network(),
        Pipeline(store),
        Publishers(),
        on_result=results.append,
        nav_sources=[("ntrip://***@h:2101/M", network(), {"connects": 1})],
    )
    n = runner.run()
    assert n == len(results) == sum(isinstance(ev, MeasurementEpoch) for ev in receiver)
    assert all(r.fix.gpst_tow_s != base_epoch.gpst_tow_s for r in results)
    fast = [r for r in results if r.fix.mode == "fast"]
    assert fast, "no fast fix from the network's ephemerides"
    c = runner.counters()
    assert c["ntrip_ignored"] == 1
    assert c["ntrip_stale"] == 1
    assert c["ntrip_ephemerides"] == c["ephemeris_ntrip"] == len(sets)
    assert c["ntrip_connects"] == 1
    errors = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert [r.getMessage() for r in errors] == [
        "nav ntrip://***@h:2101/M: the caster refused the credentials"
    ]
    assert len(store) == len(sets)


def test_config_nav_holds_rinex_files_and_ntrip_sources(tmp_path):
    toml = tmp_path / "bdsfix.toml"
    toml.write_text(
        'nav = ["hksc1610.nav", "ntrip://alice:pw-1@caster.example:2102/EPH"]\n'
        "ntrip_max_age_s = 3600.0\nntrip_reconnect_max_s = 2.5\nntrip_header_timeout_s = 3.0\n"
    )
    cfg = load_config(toml)
    assert nav_files(cfg) == ["hksc1610.nav"]
    (url,) = ntrip_sources(cfg)
    assert (url.host, url.port, url.mount, url.user, url.password) == (
        "caster.example",
        2102,
        "EPH",
        "alice",
        "pw-1",
    )
    assert (cfg.ntrip_max_age_s, cfg.ntrip_reconnect_max_s) == (3600.0, 2.5)
    assert cfg.ntrip_header_timeout_s == 3.0


@pytest.mark.parametrize(
    ("overrides", "words"),
    [
        ({"nav": ["ntrip://alice:pw-1@caster.example"]}, "no mountpoint"),
        ({"ntrip_reconnect_max_s": 0.0}, "--ntrip-reconnect-max-s"),
        ({"ntrip_reconnect_max_s": 301.0}, "--ntrip-reconnect-max-s"),
        ({"ntrip_max_age_s": 0.0}, "--ntrip-max-age-s"),
        ({"ntrip_header_timeout_s": 0.0}, "--ntrip-header-timeout-s"),
    ],
)
def test_config_refuses_bad_ntrip_settings(overrides, words):
    with pytest.raises(ConfigError) as err:
        load_config(None, overrides)
    assert words in str(err.value)
    assert "pw-1" not in str(err.value)


def test_replay_nav_is_a_file_not_an_ntrip_source(tmp_path):
    from drivers.source import open_source
    from tests.support.captures import ubx_poll_capture

    capture = ubx_poll_capture(tmp_path / "poll.ubx")
    with pytest.raises(ConfigError, match="read by 'bdsfix run'") as err:
        open_source(str(capture), nav="ntrip://alice:pw-1@h/M")
    assert "pw-1" not in str(err.value)
