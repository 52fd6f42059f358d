"""The frame-sync tracker per system: a GPS satellite's time is known from the HOW (word 2) of
its first LNAV subframe after a restart, on GPST's 6 s subframe boundaries (IS-GPS-200
20.3.2, 20.3.3.2), which lie 2 s off BeiDou D1's BDT boundaries (GPST = BDT + 14 s).

Expected instants are worked out by hand from the ICD figures, and the boundaries checked on
the real subframes of the PolyU F9P capture (RXM-SFRBX HOW times), never taken from the code
under test. The replays use real captures: the Hiroshima OEM729 RTCM stream (7 GEOs, GPS
MSM7 and 1019) for the integrity checks of recovered GPS integers, the PolyU F9P UBX capture
(GPS SFRBX) for the ``subframe`` rule driven by decoded LNAV subframes.
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from service.commands.cli import main
from service.core.constants import C_M_S
from service.core.sow_rule import time_known_after_s
from service.core.timebase import diff_s
from service.core.types import MeasurementEpoch, NavSubframe
from service.engine.tracker import FrameSyncTracker, SubframeEmulator, message_of
from tests.support.paths import DATA

WEEK = 2240
RESTART_GPST_S = 1014.05  # BDT 1000.05
SYNC_S = 0.2


def test_gps_satellites_read_lnav():
    assert [message_of(p) for p in ("G05", "C01", "C20")] == ["LNAV", "D2", "D1"]
    assert time_known_after_s("LNAV", "sow") == pytest.approx(1.2)  # 60 bits at 50 bps
    assert time_known_after_s("LNAV", "subframe") == pytest.approx(6.0)


# G05, flight 0.075 s: the first synced bit left at GPST 1014.05 + 0.2 - 0.075 = 1014.175; the
# next LNAV preamble (multiple of 6 s of GPST) at 1020, seen at 1020.075; the HOW decoded
# 1.2 s later: 7.225 s after the restart (the end of the subframe: 12.025 s). A D1 satellite
# at the same instant and range: next BDT boundary 1002 (GPST 1016), 3.225 s.
@pytest.mark.parametrize(
    ("prn", "rule", "known_s"),
    [("G05", "sow", 7.225), ("G05", "subframe", 12.025), ("C20", "sow", 3.225)],
)
def test_emulated_restart_puts_gps_subframes_on_gpst(prn, rule, known_s):
    emu = SubframeEmulator(WEEK, RESTART_GPST_S, {prn: SYNC_S}, rule=rule)
    week, tow = emu.full_at_tow_s(prn, 0.075 * C_M_S)
    assert diff_s(week, tow, WEEK, RESTART_GPST_S) == pytest.approx(known_s, abs=1e-9)


def test_a_decoded_lnav_subframe_makes_the_gps_satellite_full_after_a_restart():
    """Under the ``subframe`` rule a stream with decoded subframes drives the tracker: G05 is
    fractional after the restart until its LNAV subframe arrives, whose SOW event gives the
    subframe's start (HOW time - 6 s, on GPST)."""
    tracker = FrameSyncTracker()
    pr_m = 0.075 * C_M_S
    ep0 = MeasurementEpoch.from_columns(WEEK, 1000.0, ["G05"], ["1C"], [pr_m])
    tracker.on_epoch(ep0)
    sf = NavSubframe("G05", "LNAV", 2, 1008, (0,) * 10, WEEK, 1000.5, signal="1C")
    tracker.on_subframe(sf)  # before the restart: forgotten by it
    emu = SubframeEmulator(WEEK, 1001.0, {}, rule="subframe")
    tracker.restart(WEEK, 1001.0, emu)
    view, _ = tracker.on_epoch(MeasurementEpoch.from_columns(WEEK, 1002.0, ["G05"], ["1C"], [pr_m]))
    assert not np.isfinite(view.pr_m[0])
    sf = NavSubframe("G05", "LNAV", 3, 1014, (0,) * 10, WEEK, 1014.0, signal="1C")
    [sow] = tracker.on_subframe(sf)
    assert (sow.event, sow.nav_type, sow.sow_s) == ("sow", "LNAV", 1008.0)
    view, events = tracker.on_epoch(
        MeasurementEpoch.from_columns(WEEK, 1014.0, ["G05"], ["1C"], [pr_m])
    )
    assert np.isfinite(view.pr_m[0])
    assert [(e.prn, e.event, e.nav_type) for e in events] == [("G05", "full", "LNAV")]


def _replay(capsys, tmp_path, capture, *args):
    out = tmp_path / "out.jsonl"
    rc = main(["replay", "--max-speed", "--jsonl-out", str(out), *args, str(capture)])
    assert rc == 0
    err = capsys.readouterr().err
    checks = re.search(r"integrity checks (\d+), failures (\d+)", err)
    assert checks is not None, err
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    return recs, int(checks.group(1)), int(checks.group(2))


def test_hiroshima_restart_confirms_recovered_gps_integers(capsys, tmp_path):
    """Hiroshima OEM729, restart 20 s in, BeiDou + GPS: a coarse-time fix at 0 s, then the
    paper's fast fixes at 1-3 s, which hold 9 GPS
    integers recovered from the GEOs' fix; the GPS satellites become full at 8 s (the next
    GPST subframe boundary at 6 s after the 0.1-0.5 s sync, + 1.2 s), and every recovered
    integer is confirmed then: 23 checks (14 BeiDou IGSO/MEO + 9 GPS), 0 failures, and 4
    more of the coarse-time fix's relative integers (of satellites the fast fixes after it
    did not recover again). BeiDou alone (``--systems C``: no coarse-time fix) gives the 14
    BeiDou checks; every system (the default) 36, the 9 Galileo satellites' integers
    confirmed too."""
    rtcm = DATA / "hiroshima-oem729-rtcm-2022" / "20221213-010900.rtcm"
    recs, n, bad = _replay(capsys, tmp_path, rtcm, "--systems", "C,G", "--restart-at", "20")
    assert (n, bad) == (23 + 4, 0)
    first = [r for r in recs if r["class"] == "FIX" and r["mode"] == "fast"]
    # at 0 s, before four GEOs are full: the coarse-time fix (BeiDou and GPS rows)
    assert [r["since_start_s"] for r in first if r.get("method") == "coarse_time"] == [0.0]
    fast = [r for r in first if r.get("method") is None]  # the paper's fast fix
    assert [r["since_start_s"] for r in fast] == [1.0, 2.0, 3.0]
    assert all(r["used_by_system"]["G"] == 9 for r in fast)
    restart_tow = fast[0]["gpst_tow_s"] - 1.0
    gps_full = {
        r["since_start_s"]
        for r in recs
        if r["class"] == "TRACK"
        and r["prn"].startswith("G")
        and r["event"] == "full"
        and r["gpst_tow_s"] >= restart_tow
    }
    assert gps_full == {8.0}
    assert restart_tow % 6 == 0  # GPST 176988: boundary 176994, HOW known ~176995.3
    _, n, bad = _replay(capsys, tmp_path, rtcm, "--systems", "C", "--restart-at", "20")
    assert (n, bad) == (14, 0)
    _, n, bad = _replay(capsys, tmp_path, rtcm, "--restart-at", "20")
    assert (n, bad) == (14 + 9 + 9 + 4, 0)


def test_polyu_restart_under_the_subframe_rule_follows_the_lnav_subframes(capsys, tmp_path):
    """PolyU F9P, restart 60 s in, ``--full-rule subframe``: each GPS satellite becomes full
    at the first epoch after its first decoded LNAV subframe after the restart (the SFRBX
    follows the RAWX of the epoch it completes in, and takes its time tag), none before."""
    capture = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"
    recs, _, bad = _replay(
        capsys,
        tmp_path,
        capture,
        "--systems",
        "C,G",
        "--restart-at",
        "60",
        "--full-rule",
        "subframe",
    )
    assert bad == 0
    first = recs[0]["gpst_tow_s"]
    restart = first + 60.0
    full = {
        r["prn"]: r["gpst_tow_s"]
        for r in recs
        if r["class"] == "TRACK"
        and r["event"] == "full"
        and r["prn"].startswith("G")
        and r["gpst_tow_s"] >= restart
    }
    sow: dict[str, float] = {}
    for r in recs:
        if r["class"] == "TRACK" and r["event"] == "sow" and r["gpst_tow_s"] >= restart:
            assert r["nav_type"] == ("LNAV" if r["prn"].startswith("G") else "D1")
            sow.setdefault(r["prn"], r["gpst_tow_s"])
            if r["prn"].startswith("G"):
                assert r["sow_s"] % 6 == 0
    assert len(full) == 8
    for prn, t in full.items():
        assert t == sow[prn] + 1.0, prn
