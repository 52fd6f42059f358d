"""``bdsfix solve`` and ``ttff`` read an Android GnssLogger log through the file registry."""

from __future__ import annotations

import json

import numpy as np

from drivers.source import open_source
from service.commands.cli import main
from service.core.types import MeasurementEpoch
from tests.engine.test_android_periods import PERTH, _pipeline

LOG = PERTH / "SensorLog20171005.txt"
NAV = PERTH / "PERT00AUS_R_20172780000_01D_MN.rnx"


def test_solve_of_the_perth_log_gives_the_streams_fixes(tmp_path, capsys):
    """With the phone's own states (``--fractional none``) and every system (the command's
    default), the batch solver fixes 433 epochs (418 with BeiDou alone), each one the stream
    (replay's pipeline) fixes too, at the same positions within 1 mm (the record keeps
    0.1 mm; the stream warm-starts its SPP at the last fix). The stream fixes 12 more: the
    coarse-time fixes of the first 12 epochs (every range fractional, the phone's time
    uncertain by 5.97 s), which the batch solver, without a coarse-time fix, declines."""
    out = tmp_path / "perth.jsonl"
    args = ["solve", str(LOG), str(NAV), "--fractional", "none", "--mode", "fast"]
    assert main([*args, "--format", "jsonl", "--out", str(out)]) == 0
    assert "445 epochs" in capsys.readouterr().err
    batch = [json.loads(x) for x in out.read_text().splitlines()]
    every = ("C", "G", "E")
    pipe = _pipeline(NAV, every)
    with open_source(str(LOG), systems=frozenset(every)) as src:
        stream = [pipe.on_epoch(e).fix for e in src if isinstance(e, MeasurementEpoch)]
    assert len(batch) == len(stream) == 445
    assert sum(r["mode"] != "none" for r in batch) == 433
    assert sum(f.ok for f in stream) == 445
    coarse = 0
    for rec, fix in zip(batch, stream, strict=True):
        if fix.method == "coarse_time":
            coarse += 1
            assert rec["mode"] == "none"
            continue
        assert rec["mode"] == fix.mode
        if fix.ok:
            assert np.linalg.norm(np.subtract(rec["x_ecef_m"], fix.x_ecef_m)) < 1e-3
    assert coarse == 12


def test_ttff_runs_emulated_restarts_on_the_perth_log(capsys):
    assert main(["ttff", str(LOG), str(NAV), "--trials", "5", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["conventional"]["success_pct"] > 0


def test_replay_takes_a_format_named_by_its_scheme(tmp_path, capsys):
    """``gnsslogger:PATH`` reaches the GnssLogger reader through replay's checks (the file
    exists, its day's nav) as a plain path does: the same 445 FIX records."""
    outs = []
    for spec in (str(LOG), f"gnsslogger:{LOG}"):
        out = tmp_path / f"{len(outs)}.jsonl"
        args = ["replay", spec, "--nav", str(NAV), "--max-speed", "--jsonl", str(out)]
        assert main(args) == 0
        outs.append([x for x in out.read_text().splitlines() if '"FIX"' in x])
    capsys.readouterr()
    assert len(outs[0]) == 445 and outs[0] == outs[1]
