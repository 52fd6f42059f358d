"""Epochs the pipeline declines before solving, on real captures: without a GPS week
(``no_time``) and not after the previous epoch (``out_of_order``). Each is still an epoch
with a FIX (mode none, a reason code) counted in STATUS, never a new position, and neither
changes what the other epochs give."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from jsonschema import Draft202012Validator

from drivers.framing import Framer
from drivers.protocols import PROTOCOLS
from drivers.rinex import RinexObsReader
from drivers.rtcm import message_number
from drivers.source import open_source
from service.commands.solve import load_navigation
from service.core.declines import DECLINES, Decline
from service.core.ephemeris import EphemerisStore
from service.core.types import UNKNOWN_WEEK, MeasurementEpoch
from service.daemon.loop import Runner
from service.engine.pipeline import EpochResult, Pipeline
from service.output.nmea import fix_utc, sentences_for_fix
from service.output.records import SCHEMAS, fix_record
from tests.support.paths import DATA

HIROSHIMA = DATA / "hiroshima-oem729-rtcm-2022" / "20221213-010900.rtcm"
HKSC = DATA / "hksc-2021"
VALIDATOR = Draft202012Validator(SCHEMAS["FIX"])


def test_epochs_without_a_week_are_declined_no_time_and_change_nothing():
    """HKSC RINEX with the week of its first 5 epochs withheld (as a stream that gives only
    a time of week): those are declined ``no_time`` (FIX without gpst_week, NMEA without
    time), counted, and the tracker starts at the first epoch with a week; every later fix
    is the fix of the run without them."""
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    epochs: list[MeasurementEpoch] = list(RinexObsReader(HKSC / "hksc1610.obs"))
    pipe = Pipeline(store, iono)
    clean = [pipe.on_epoch(e) for e in epochs[5:]]
    pipe = Pipeline(store, iono)
    blind = [replace(e, gpst_week=UNKNOWN_WEEK) for e in epochs[:5]]
    results = [pipe.on_epoch(e) for e in [*blind, *epochs[5:]]]
    assert [r.fix.reason_code for r in results[:5]] == ["no_time"] * 5
    assert pipe.counters["declined_no_time"] == 5 and pipe.counters["epochs"] == 205
    assert DECLINES[Decline.NO_TIME].label
    for r, e in zip(results[:5], epochs, strict=False):
        assert not r.fix.ok and r.since_start_s is None and not r.track
        rec = fix_record(r.fix, r.since_start_s)
        VALIDATOR.validate(rec)
        assert "gpst_week" not in rec and rec["gpst_tow_s"] == e.gpst_tow_s
        rmc, gga = sentences_for_fix(r.fix, utc=fix_utc(r.fix))
        assert gga.startswith(b"$GNGGA,,,") and b",0,0," in gga  # no time, quality 0
        assert rmc.startswith(b"$GNRMC,,V,")
    for r, c in zip(results[5:], clean, strict=True):
        assert (r.fix.mode, r.since_start_s, r.track) == (c.fix.mode, c.since_start_s, c.track)
        if r.fix.ok:
            assert np.allclose(r.fix.x_ecef_m, c.fix.x_ecef_m, atol=1e-6, rtol=0)
    # a record with a week still needs it
    bad = fix_record(results[10].fix)
    del bad["gpst_week"]
    assert not VALIDATOR.is_valid(bad)


class Recorder:
    """The loop's outputs, kept in memory."""

    def __init__(self) -> None:
        self.results: list[EpochResult] = []
        self.last_status: dict = {}

    def epoch(self, result: EpochResult) -> None:
        self.results.append(result)

    def track(self, event) -> None:
        pass

    def status(self, counters) -> None:
        self.last_status = dict(counters)

    def reopen(self) -> None:
        pass

    def gone(self) -> bool:
        return False

    def close(self) -> None:
        pass


def replay(path) -> tuple[list[EpochResult], dict]:
    """``path`` through the receiver loop (no --gps-week, no nav file): results, STATUS."""
    out = Recorder()
    with open_source(str(path)) as src:
        Runner(src, Pipeline(EphemerisStore()), out, source_counters=src.counters).run()
    return out.results, out.last_status


def test_rtcm_epochs_before_the_week_are_declined_no_time_then_positioned():
    """OEM729 RTCM without --gps-week: all 60 epochs reach the outputs; the 6 before the
    first ephemeris are declined ``no_time`` (counted in STATUS), the rest solve from the
    stream's own 1042 ephemerides as soon as they arrive."""
    results, status = replay(HIROSHIMA)
    assert len(results) == 60 and status["epochs"] == 60
    codes = [r.fix.reason_code for r in results]
    assert codes[:6] == ["no_time"] * 6 and "no_time" not in codes[6:]
    assert status["declined_no_time"] == 6
    assert status["fix_spp"] + status.get("fix_fast", 0) == sum(r.fix.ok for r in results) >= 45
    for r in results[:6]:
        assert r.since_start_s is None and not r.track
        rec = fix_record(r.fix, r.since_start_s)
        VALIDATOR.validate(rec)
        assert "gpst_week" not in rec and rec["gpst_tow_s"] == r.epoch.gpst_tow_s
    # data time starts at the first epoch with a week
    assert results[6].since_start_s == 0.0 and results[-1].since_start_s == 53.0


def _rtcm_with(frames_after: dict[int, list[bytes]]) -> bytes:
    """The OEM729 stream with extra frames inserted after given frame indices."""
    framer = Framer(PROTOCOLS)
    frames = framer.feed(HIROSHIMA.read_bytes()) + framer.flush()
    out = []
    for i, f in enumerate(frames):
        out.append(f.raw)
        out += frames_after.get(i, [])
    return b"".join(out)


def test_repeated_and_backward_rtcm_epochs_are_declined_out_of_order(tmp_path):
    """The OEM729 stream with the BDS MSM frames of epoch 20 sent again at once (a relay's
    duplicate) and those of epoch 30 again after epoch 32 (a step back): 62 epochs, the two
    extra ones declined ``out_of_order`` and counted, every other fix as without them."""
    framer = Framer(PROTOCOLS)
    frames = framer.feed(HIROSHIMA.read_bytes()) + framer.flush()
    bds = [i for i, f in enumerate(frames) if message_number(f.raw) == 1127]
    assert len(bds) == 180  # 1127 x 3 (multiple message bit set), then 1137 ends the epoch
    last = [bds[3 * k + 2] + 1 for k in range(60)]
    assert all(message_number(frames[i].raw) == 1137 for i in last)
    epoch = [[frames[i].raw for i in [*bds[3 * k : 3 * k + 3], last[k]]] for k in range(60)]
    path = tmp_path / "reordered.rtcm"
    path.write_bytes(_rtcm_with({last[20]: epoch[20], last[32]: epoch[30]}))

    clean, _ = replay(HIROSHIMA)
    results, status = replay(path)
    assert len(results) == 62 and status["epochs"] == 62
    odd = [k for k, r in enumerate(results) if r.fix.reason_code == "out_of_order"]
    assert odd == [21, 34] and status["declined_out_of_order"] == 2
    assert results[21].epoch.gpst_tow_s == results[20].epoch.gpst_tow_s
    assert "repeats the previous one" in results[21].fix.reason
    assert results[34].epoch.gpst_tow_s == clean[30].epoch.gpst_tow_s
    assert "is 2.000 s before the previous one" in results[34].fix.reason
    assert not results[21].fix.ok and not results[34].fix.ok
    rest = [r for k, r in enumerate(results) if k not in odd]
    for a, b in zip(rest, clean, strict=True):
        assert (a.epoch.gpst_tow_s, a.fix.mode, a.fix.reason_code) == (
            b.epoch.gpst_tow_s,
            b.fix.mode,
            b.fix.reason_code,
        )
        if a.fix.ok:
            assert np.allclose(a.fix.x_ecef_m, b.fix.x_ecef_m, atol=1e-6, rtol=0)


def test_out_of_order_rinex_epochs_leave_the_other_fixes_unchanged():
    """HKSC RINEX through the pipeline with epoch 50 given twice and epochs 100/101 swapped:
    the repeat and the late epoch 100 are declined; every fix published is the fix of the
    clean run at that time (a declined epoch changes no state)."""
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    epochs: list[MeasurementEpoch] = list(RinexObsReader(HKSC / "hksc1610.obs"))
    pipe = Pipeline(store, iono)
    clean = {e.gpst_tow_s: pipe.on_epoch(e).fix for e in epochs}
    order = [*epochs[:51], epochs[50], *epochs[51:100], epochs[101], epochs[100], *epochs[102:]]
    pipe = Pipeline(store, iono)
    fixes = [pipe.on_epoch(e).fix for e in order]
    declined = [k for k, f in enumerate(fixes) if f.reason_code == "out_of_order"]
    assert declined == [51, 102]
    assert pipe.counters["declined_out_of_order"] == 2 and pipe.counters["epochs"] == 206
    for k, f in enumerate(fixes):
        if k in declined:
            assert not f.ok and f.x_ecef_m is None
            continue
        ref = clean[f.gpst_tow_s]
        assert f.mode == ref.mode
        if f.ok:
            assert np.allclose(f.x_ecef_m, ref.x_ecef_m, atol=1e-4, rtol=0)
    assert sum(f.ok for f in fixes) == sum(f.ok for f in clean.values()) - 1  # epoch 100


def test_one_epoch_tagged_a_week_ahead_does_not_stop_the_stream():
    """HKSC RINEX with epoch 10 tagged a week later (a damaged week number): the epochs after
    it are before the latest time; the first two are declined ``out_of_order``, the third
    makes the stream's time its own again (``time_reanchors``), and every later fix is the
    clean run's. Without that, every epoch after the stray one was declined: a daemon would
    publish nothing for a week."""
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    epochs: list[MeasurementEpoch] = list(RinexObsReader(HKSC / "hksc1610.obs"))
    pipe = Pipeline(store, iono)
    clean = [pipe.on_epoch(e).fix for e in epochs]
    damaged = [*epochs[:10], replace(epochs[10], gpst_week=epochs[10].gpst_week + 1)]
    damaged += epochs[11:]
    pipe = Pipeline(store, iono)
    fixes = [pipe.on_epoch(e).fix for e in damaged]
    assert [k for k, f in enumerate(fixes) if f.reason_code == "out_of_order"] == [11, 12]
    assert pipe.counters["time_reanchors"] == 1
    for f, ref in zip(fixes[13:], clean[13:], strict=True):
        assert (f.gpst_week, f.gpst_tow_s, f.mode) == (ref.gpst_week, ref.gpst_tow_s, ref.mode)
        if f.ok:
            assert np.allclose(f.x_ecef_m, ref.x_ecef_m, atol=1e-4, rtol=0)
    assert sum(f.ok for f in fixes[13:]) == 192


def test_a_receiver_restart_setting_its_clock_back_is_taken_at_once():
    """A receiver restart (``restarted``) whose clock starts 5 s before the latest epoch: the
    stream's time is the restarted receiver's at once (no epoch declined), and the restart
    is counted; a restart flag on an epoch declined for repeating the latest is counted
    too."""
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    epochs: list[MeasurementEpoch] = list(RinexObsReader(HKSC / "hksc1610.obs"))
    pipe = Pipeline(store, iono)
    for e in epochs[:20]:
        pipe.on_epoch(e)
    back = pipe.on_epoch(replace(epochs[15], restarted=True))
    assert back.fix.ok and back.fix.gpst_tow_s == epochs[15].gpst_tow_s
    assert pipe.counters["receiver_restarts"] == 1
    assert pipe.counters["time_reanchors"] == 0  # (a restart, not an epoch tagged ahead)
    again = pipe.on_epoch(replace(epochs[15], restarted=True))
    assert again.fix.reason_code == "out_of_order"
    assert pipe.counters["receiver_restarts"] == 2
    assert all(pipe.on_epoch(e).fix.ok for e in epochs[16:30])


def test_epochs_sent_again_are_no_reason_to_take_the_streams_time_back():
    """HKSC RINEX with epochs 24-29 sent again after epoch 29 (captures that overlap, or a
    relay's resend after a reconnect): each is before the latest and after the one before
    it, but they start before the epoch before the latest, so the latest was not tagged
    ahead: all six declined ``out_of_order``, no re-anchor, and the stream goes on with
    epoch 30 as the clean run."""
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    epochs: list[MeasurementEpoch] = list(RinexObsReader(HKSC / "hksc1610.obs"))
    pipe = Pipeline(store, iono)
    clean = [pipe.on_epoch(e).fix for e in epochs[:40]]
    pipe = Pipeline(store, iono)
    fixes = [pipe.on_epoch(e).fix for e in [*epochs[:30], *epochs[24:40]]]
    assert [k for k, f in enumerate(fixes) if f.reason_code == "out_of_order"] == list(
        range(30, 36)
    )
    assert pipe.counters["time_reanchors"] == 0
    for f, ref in zip(fixes[36:], clean[30:], strict=True):
        assert (f.gpst_tow_s, f.mode) == (ref.gpst_tow_s, ref.mode)
        assert np.allclose(f.x_ecef_m, ref.x_ecef_m, atol=1e-4, rtol=0)
