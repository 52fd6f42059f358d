"""``bdsfix solve`` takes the stream's coarse-time fix where the paper's method has too few
full ranges (issue 20: the paper's method with >= 4 GEO full ranges, this method otherwise),
on a real RINEX file with no GEO: the u-blox F9P beside the HKSC station."""

from __future__ import annotations

import itertools
import json
import math
import os
import re
import statistics
from dataclasses import replace

from drivers.rinex import RinexObsReader
from service.commands.cli import main
from service.engine.solver import fractionalize
from service.output.records import fix_json_line
from tests.support.fixes import without_since_start
from tests.support.nav import pipeline_with_nav
from tests.support.paths import DATA

OBS = DATA / "hksc-2021" / "20210610.klt1.ublox.f9p.obs"
NAV = DATA / "hksc-2021" / "hksc1610.nav"


def test_solve_gives_the_streams_coarse_time_fixes_of_a_file_without_geos(tmp_path, capsys):
    """The stream after a receiver restart (``replay --restart-at 0``) has every range
    fractional until the first SOWs decode: its first epochs are coarse-time fixes. ``solve
    --fractional non-geo`` gives the fast solver the same rows (no GEO in the file: every
    range fractional) at every epoch: the same FIX records, byte for byte bar the stream's
    ``since_start_s``, at those epochs, and a coarse-time fix at every epoch (the paper's
    method declined them all for too few full ranges before). The receiver clock is 9.7 ms
    off, so the millisecond common to every range stays in doubt: each fix is the
    coarse-time solution itself (coarse.py step 5; no absolute integer, so no range to
    check against the file's full one, in the stream neither), within 10 m of SPP of the
    file's full ranges (median under 1 m)."""
    out = tmp_path / "solve.jsonl"
    assert main(["solve", str(OBS), str(NAV), "--mode", "both", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert "205 epochs; fast solver 205 fixes" in err
    assert "fast solver coarse-time fixes 205 " in err
    lines = out.read_text().splitlines()
    fast = [x for x in lines if '"solver":"fast"' in x]
    spp = [json.loads(x) for x in lines if '"solver":"spp"' in x]
    records = [json.loads(x) for x in fast]
    assert all(r["method"] == "coarse_time" and not r.get("ambiguity") for r in records)
    assert all(r["mode"] == "spp" for r in spp)
    apart_m = [math.dist(r["x_ecef_m"], s["x_ecef_m"]) for r, s in zip(records, spp, strict=True)]
    assert max(apart_m) < 10.0 and statistics.median(apart_m) < 1.0
    replayed = tmp_path / "replay.jsonl"
    args = ["replay", str(OBS), "--nav", str(NAV), "--restart-at", "0", "--max-speed"]
    assert main([*args, "--jsonl-out", str(replayed)]) == 0
    capsys.readouterr()
    stream = [x for x in replayed.read_text().splitlines() if '"class":"FIX"' in x]
    assert len(stream) == len(fast) == 205
    coarse = [k for k, x in enumerate(stream) if '"method":"coarse_time"' in x]
    assert coarse == [0, 1, 2, 3]
    assert [without_since_start(stream[k]) for k in coarse] == [fast[k] for k in coarse]


def test_solve_checks_the_coarse_time_fixes_integers_against_the_files_full_ranges(capsys):
    """A real urban receiver with 3 GEOs (hk-urban-3geo-2020): the paper's method declines
    every epoch (too few full ranges), the coarse-time fix gives one at each, its integers
    absolute (the GEOs' full rows anchor them): every range it recovers is checked against
    the file's full range of the same epoch (2834 of them) and none is wrong. Where its
    fault exclusion left out the same satellites as SPP's, the fix is SPP of the full
    ranges to the bit (coarse.py step 5)."""
    obs = DATA / "hk-urban-3geo-2020" / "rover.obs"
    nav = DATA / "hk-urban-3geo-2020" / "navigation_message.nav"
    assert main(["solve", str(obs), str(nav), "--mode", "both"]) == 0
    captured = capsys.readouterr()
    assert "fast solver 300 fixes" in captured.err
    assert "fast solver coarse-time fixes 300 " in captured.err
    assert "fast solver integrity checks 2834 " in captured.err
    assert "failures 0" in captured.err
    records = [json.loads(x) for x in captured.out.splitlines()]
    fast = [r for r in records if r["solver"] == "fast"]
    spp = [r for r in records if r["solver"] == "spp"]
    assert all(r["method"] == "coarse_time" and r["ambiguity"] for r in fast)
    same = [
        (f, s)
        for f, s in zip(fast, spp, strict=True)
        if s["mode"] == "spp" and f.get("excluded") == s.get("excluded")
    ]
    assert len(same) > 100
    assert all(f["x_ecef_m"] == s["x_ecef_m"] for f, s in same)


def test_solve_coarse_fix_false_leaves_the_papers_declines(capsys):
    """``--coarse-fix false`` (the stream's flag, now also solve's): the same 3-GEO file's
    fast solver publishes no fix (the paper's method has three full ranges, it needs four)
    and every fast record is the paper's decline, too few full ranges."""
    obs = DATA / "hk-urban-3geo-2020" / "rover.obs"
    nav = DATA / "hk-urban-3geo-2020" / "navigation_message.nav"
    assert main(["solve", str(obs), str(nav), "--mode", "fast", "--coarse-fix", "false"]) == 0
    captured = capsys.readouterr()
    assert "fast solver 0 fixes" in captured.err
    records = [json.loads(x) for x in captured.out.splitlines()]
    assert len(records) == 300
    assert all(r["reason_code"] == "too_few_full" for r in records)


def test_aided_solve_of_coarse_time_fixes_equals_the_stream(capsys):
    """Height aiding and the prediction screen on (a car's settings), the 3-GEO urban file
    with GPS and Galileo: ``bdsfix solve`` (batched, the aided fixed point) publishes the
    fast records of the stream's own pipeline fed the same epochs one at a time (non-GEO
    ranges fractional, as ``--fractional non-geo`` gives them), JSON line for JSON line.
    Every one is a coarse-time fix (three GEOs): solved from every range of the epoch, so
    it names no range as screened, as in the stream, whose screen acts on the paper's fix
    that the coarse-time fix replaces."""
    obs = DATA / "hk-urban-3geo-2020" / "rover.obs"
    nav = DATA / "hk-urban-3geo-2020" / "navigation_message.nav"
    aided = ["--height-aiding", "true", "--screen-predicted-m", "30"]
    args = ["solve", str(obs), str(nav), "--mode", "fast", "--systems", "C,G,E", *aided]
    assert main(args) == 0
    solved = capsys.readouterr().out.splitlines()
    pipe = pipeline_with_nav(nav, ("C", "G", "E"))
    pipe.cfg = replace(pipe.cfg, height_aiding=True, screen_predicted_m=30.0)
    streamed = [
        fix_json_line(pipe.on_epoch(fractionalize(ep, None)).fix)
        for ep in RinexObsReader(obs, systems="CGE")
    ]
    assert len(solved) == len(streamed) == 300
    assert all('"method":"coarse_time"' in line for line in streamed)
    assert solved == streamed


def test_solve_checks_the_relative_integers_and_fails_a_wrong_one(monkeypatch, capsys, caplog):
    """The F9P file (no GEO): every fast fix is a coarse-time fix whose integers are relative
    (each system's whole period in doubt), and ``solve`` checks them as the stream does
    (recovered.RecoveredLedger): per fix and system the first full range gives the shift,
    every other range must share it, against the file's full range of the same epoch (3448
    checks, none wrong). With one GPS integer of the 100th fix one period more (a wrong
    integer, 1 ms), the same checks are made and that fix's GPS checks fail: its own, or,
    were it the anchor of the shift, every other GPS satellite's; no other check fails."""
    import service.commands.solve as solve_mod

    target = next(itertools.islice(RinexObsReader(OBS), 99, None))
    target_t = (target.gpst_week, target.gpst_tow_s)
    wrong: list[str] = []
    coarse_fixes = solve_mod.with_coarse_fixes

    def with_one_wrong(fixes, read, *args, **kwargs):
        out = coarse_fixes(fixes, read, *args, **kwargs)
        for k, (fix, epoch) in enumerate(zip(out, read, strict=True)):
            if (epoch.gpst_week, epoch.gpst_tow_s) == target_t and not wrong:
                n = fix.relative_ambiguity
                wrong.append(min(p for p in n if p[0] == "G"))
                out[k] = replace(fix, relative_ambiguity={**n, wrong[0]: n[wrong[0]] + 1})
        return out

    def checks() -> tuple[int, int]:
        assert main(["solve", str(OBS), str(NAV), "--mode", "both", "--out", os.devnull]) == 0
        line = next(x for x in capsys.readouterr().err.splitlines() if "integrity" in x)
        found = re.search(r"integrity checks (\d+) .*failures (\d+)", line)
        assert found, line
        return int(found[1]), int(found[2])

    assert checks() == (3448, 0)
    monkeypatch.setattr(solve_mod, "with_coarse_fixes", with_one_wrong)
    with caplog.at_level("ERROR", logger="service.engine.recovered"):
        n_checks, n_failed = checks()
    assert len(wrong) == 1 and n_checks == 3448
    failed = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert n_failed == len(failed) >= 1
    assert all(m.startswith("integrity: G") and "the file gives" in m for m in failed)
