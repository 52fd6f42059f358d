"""Epochs the pipeline declines before solving, on real captures: without a GPS week
(``no_time``) and not after the previous epoch (``out_of_order``). Each is still an epoch
with a FIX (mode none, a reason code) counted in STATUS, never a new position, and neither
changes what the other epochs give."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from jsonschema import Draft202012Validator

from drivers.rinex import RinexObsReader
from service.commands.solve import load_navigation
from service.core.types import UNKNOWN_WEEK, MeasurementEpoch
from service.engine.pipeline import Pipeline
from service.engine.solver import REASONS
from service.output.nmea import fix_utc, sentences_for_fix
from service.output.records import SCHEMAS, fix_record
from tests.support.paths import DATA

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
    assert REASONS["no_time"]
    for r, e in zip(results[:5], epochs, strict=False):
        assert not r.fix.ok and r.since_start_s is None and not r.track
        rec = fix_record(r.fix, r.since_start_s)
        VALIDATOR.validate(rec)
        assert "gpst_week" not in rec and rec["gpst_tow_s"] == e.gpst_tow_s
        gga, rmc = sentences_for_fix(r.fix, utc=fix_utc(r.fix))
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
