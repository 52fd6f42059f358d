"""`bdsfix run` tells the journal when its first fast and first conventional fix came, and
ends with the timeline `replay` prints (issue 23: a new user saw no line at the first fix
and no timeline at exit)."""

import json
import logging
import re

from service.commands.cli import main


def test_run_logs_its_first_fixes_and_prints_the_timeline(tmp_path, caplog, capsys):
    ubx, jsonl = tmp_path / "sim.ubx", tmp_path / "fixes.jsonl"
    assert main(["simulate", "--duration-s", "15", "--out", str(ubx)]) == 0
    caplog.set_level(logging.INFO)
    args = ["run", "--source", str(ubx), "--state-dir", str(tmp_path / "state")]
    assert main([*args, "--nmea-tcp", "", "--zmq", "", "--jsonl-out", str(jsonl)]) == 0
    err = capsys.readouterr().err
    fixes = [r for r in map(json.loads, jsonl.read_text().splitlines()) if r["class"] == "FIX"]
    first = {
        "fast": next(f for f in fixes if f["mode"] == "fast"),
        "conventional": next(f for f in fixes if f["mode"] == "spp"),
    }
    logged = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO]
    for kind, fix in first.items():
        lines = [m for m in logged if m.startswith(f"first {kind} fix: ")]
        assert len(lines) == 1, logged  # once, at the first one only
        t_s = float(re.search(r"t = ([0-9.]+) s", lines[0]).group(1))
        assert abs(t_s - fix["since_start_s"]) < 0.005, (lines[0], fix)
        assert f"tow {fix['gpst_tow_s']:.3f} s" in lines[0]
        # and the timeline at stop says the same
        shown = re.search(rf"  first {kind} fix +t = +([0-9.]+) s", err)
        assert shown is not None, err
        assert abs(float(shown.group(1)) - fix["since_start_s"]) < 0.005
    assert "  timeline (t: data time since the first measurement):" in err
    assert first["fast"]["since_start_s"] < first["conventional"]["since_start_s"]
