"""``bdsfix solve`` and ``ttff`` read an Android GnssLogger log through the file registry."""

from __future__ import annotations

import json

from service.commands.cli import main
from tests.engine.test_android_periods import PERTH
from tests.support.fixes import without_since_start

LOG = PERTH / "SensorLog20171005.txt"
NAV = PERTH / "PERT00AUS_R_20172780000_01D_MN.rnx"


def test_solve_of_the_perth_log_gives_the_streams_fixes(tmp_path, capsys):
    """With the phone's own states (``--fractional none``) and every system (the command's
    default), the batch solver publishes the FIX records of the stream (``bdsfix replay``
    of the same log), byte for byte bar the stream's ``since_start_s``: all 445 epochs
    fixed, the first 12 by the coarse-time fix (every range fractional, the phone's time
    uncertain by 5.97 s: the prior 5 sigma of it, pipeline.wide_time_prior), the same
    decision in both (pipeline.coarse_time_fix). Its integrity checks are the stream's: the
    6 recovered ranges whose satellite's full range comes later in the log, none wrong."""
    out = tmp_path / "perth.jsonl"
    args = ["solve", str(LOG), str(NAV), "--fractional", "none", "--mode", "fast"]
    assert main([*args, "--format", "jsonl", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "445 epochs" in err and "fast solver coarse-time fixes 12 " in err
    assert "fast solver integrity checks 6 " in err and "failures 0" in err
    batch = out.read_text().splitlines()
    replayed = tmp_path / "replay.jsonl"
    args = ["replay", str(LOG), "--nav", str(NAV), "--max-speed", "--jsonl-out", str(replayed)]
    assert main(args) == 0
    capsys.readouterr()
    stream = [x for x in replayed.read_text().splitlines() if '"class":"FIX"' in x]
    assert len(batch) == len(stream) == 445
    assert [without_since_start(x) for x in stream] == batch
    records = [json.loads(x) for x in batch]
    assert all(r["mode"] != "none" for r in records)
    coarse = [k for k, r in enumerate(records) if r.get("method") == "coarse_time"]
    assert coarse == list(range(12))


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
