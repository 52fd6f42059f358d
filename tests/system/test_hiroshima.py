"""The one real receiver stream with >= 4 BDS GEOs: NovAtel OEM729 RTCM from Hiroshima
(7 GEOs, every range full, BDS ephemerides only as in-stream RTCM 1042).

- Every one of its 60 BDS MSM epochs is replayed and published. The epochs that do not fix
  are exactly those before the stream has said what it needs, read here from the message
  order with pyrtcm: before the first message that carries a week (here Galileo 1045/1046)
  the time is unknown (``no_time``); with BeiDou alone (``--systems C``), before the first
  BDS 1042 there is no ephemeris (``no_ephemeris``); a live receiver could not fix them
  either. Every later epoch is SPP. With every system (the default) the Galileo sets that
  bring the week fix every epoch from there on.
- Emulated restarts through the stream path (``replay --restart-at``) at 10 instants: every
  satellite fractional again until its SOW by the SOW-decode rule, so fast fixes come while
  the IGSO/MEO are fractional; each equals the SPP fix of the same epoch in the replay
  without a restart (all ranges full) within 1 mm, and every recovered integer is confirmed
  by the full range that arrives later. A coarse-time fix (service/engine/coarse.py, which
  takes the BeiDou rows only) is compared with the SPP fix of the BeiDou rows alone.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest

from service.commands.cli import main
from tests.support.paths import DATA

CAPTURE = DATA / "hiroshima-oem729-rtcm-2022" / "20221213-010900.rtcm"
BDS_MSM = {"1121", "1122", "1123", "1124", "1125", "1126", "1127"}
WEEK_CARRIERS = {"1019", "1042", "1044", "1045", "1046"}
RESTARTS_S = [15.0, 17.5, 20.0, 23.0, 26.5, 29.0, 32.0, 35.5, 39.0, 43.0]


def _stream_order() -> tuple[int, int, int, int]:
    """From the raw stream: the number of BDS MSM epochs, after how many of them the first
    week-carrying ephemeris and the first BDS 1042 arrive, and how many Galileo sets
    (1045/1046) have arrived before the epoch after the first week carrier."""
    from pyrtcm import RTCMReader

    epochs, first_week, first_1042 = 0, None, None
    gal_sets = 0
    last_tow = None
    with open(CAPTURE, "rb") as f:
        for _raw, msg in RTCMReader(f, quitonerror=0):
            if msg is None:
                continue
            ident = msg.identity
            if ident in BDS_MSM and last_tow != msg.DF427:
                epochs, last_tow = epochs + 1, msg.DF427
            if ident in {"1045", "1046"} and (first_week is None or epochs == first_week):
                gal_sets += 1
            if ident in WEEK_CARRIERS and first_week is None:
                first_week = epochs
            if ident == "1042" and first_1042 is None:
                first_1042 = epochs
    assert first_week is not None and first_1042 is not None
    return epochs, first_week, first_1042, gal_sets


def _replay(tmp_path: Path, name: str, *extra: str) -> tuple[list[dict], int]:
    out = tmp_path / f"{name}.jsonl"
    args = ["replay", str(CAPTURE), "--max-speed", "--nmea-out", "/dev/null"]
    rc = main([*args, "--jsonl-out", str(out), "--status-interval-s", "1000", *extra])
    return [json.loads(line) for line in out.read_text().splitlines()], rc


def _fixes(records: list[dict]) -> list[dict]:
    return [r for r in records if r["class"] == "FIX"]


def test_all_60_epochs_replayed_and_only_those_before_week_and_1042_decline(tmp_path):
    n, first_week, first_1042, _ = _stream_order()
    assert (n, first_week, first_1042) == (60, 6, 11)  # the stream as it is
    records, rc = _replay(tmp_path, "plain", "--systems", "C")
    assert rc == 0
    fixes = _fixes(records)
    assert len(fixes) == n
    modes = [f["mode"] if f["mode"] != "none" else f["reason_code"] for f in fixes]
    assert modes == (
        ["no_time"] * first_week
        + ["no_ephemeris"] * (first_1042 - first_week)
        + ["spp"] * (n - first_1042)
    )


def test_every_system_fixes_from_the_galileo_sets_that_bring_the_week(tmp_path):
    """By default (every system) the epochs between the week and the first BDS 1042 fix
    too: the Galileo 1045/1046 that bring the week are sets of 9 satellites, more than the
    position and one clock need."""
    n, first_week, _, gal_sets = _stream_order()
    assert gal_sets >= 2 * 5  # I/NAV and F/NAV of at least 5 satellites
    records, rc = _replay(tmp_path, "plain")
    assert rc == 0
    fixes = _fixes(records)
    assert len(fixes) == n
    modes = [f["mode"] if f["mode"] != "none" else f["reason_code"] for f in fixes]
    assert modes == ["no_time"] * first_week + ["spp"] * (n - first_week)
    assert {"C", "E"} <= set(fixes[-1]["used_by_system"])


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """SPP of every epoch of the replay without a restart (all ranges full)."""
    records, rc = _replay(tmp_path_factory.mktemp("ref"), "ref")
    assert rc == 0
    return {f["gpst_tow_s"]: f for f in _fixes(records) if f["mode"] == "spp"}


@pytest.mark.parametrize("restart_s", RESTARTS_S)
def test_restart_fast_fixes_equal_spp(tmp_path, capsys, reference, restart_s):
    records, rc = _replay(
        tmp_path, "restart", "--restart-at", str(restart_s), "--seed", str(int(restart_s * 10))
    )
    assert rc == 0
    fixes = _fixes(records)
    assert len(fixes) == 60
    first_tow = min(f["gpst_tow_s"] for f in fixes if "gpst_week" in f)  # the week known
    restart_tow = min(f["gpst_tow_s"] for f in fixes if f["gpst_tow_s"] - first_tow >= restart_s)
    # the coarse-time fix (fewer than four full ranges: service/engine/coarse.py) may fix the
    # restart epoch itself, from every system's rows (BeiDou, GPS, Galileo, a clock each):
    # all ranges fractional, the common millisecond is not observable, so it is the
    # coarse-time solution, within decimetres of SPP of every system's full ranges
    # (measured 1.6-7.0 cm); with a few full rows its integers are absolute and it is that
    # SPP (measured 0.0 at the JSONL's 0.1 mm)
    coarse = [f for f in fixes if f.get("method") == "coarse_time"]
    for f in coarse:
        assert 0.0 <= f["gpst_tow_s"] - restart_tow <= 6.0 + 1.2 + 1.0
        ref = reference[f["gpst_tow_s"]]
        diff_m = float(np.linalg.norm(np.subtract(f["x_ecef_m"], ref["x_ecef_m"])))
        assert diff_m <= 0.5 if "ambiguity" not in f else diff_m <= 1e-3
    fast = [f for f in fixes if f["mode"] == "fast" and "method" not in f]
    assert fast, f"no fast fix after the restart at {restart_s} s"
    for f in fast:
        # fast fixes only after the restart, while some IGSO/MEO are still fractional ...
        assert 0.0 < f["gpst_tow_s"] - restart_tow <= 6.0 + 1.2 + 1.0
        assert f["n_frac"] > 0
        # ... and each is the SPP fix of the same epoch with every range full
        ref = reference[f["gpst_tow_s"]]
        diff_m = float(np.linalg.norm(np.subtract(f["x_ecef_m"], ref["x_ecef_m"])))
        assert diff_m <= 1e-3, (restart_s, f["gpst_tow_s"], diff_m)
    # the GEOs know their time within 0.5 s sync + 0.6 s + 0.12 s + flight: fixed at 1 or 2 s
    assert min(f["gpst_tow_s"] for f in fast) - restart_tow <= 2.0
    # every epoch where the restarted replay fixes, the plain one does too
    assert all(f["gpst_tow_s"] in reference for f in fixes if f["mode"] != "none")
    # every integer recovered after the restart was confirmed by the full range after its SOW
    err = capsys.readouterr().err
    checks = re.search(r"integrity checks (\d+), failures (\d+)", err)
    assert checks, err
    assert int(checks.group(1)) > 0 and int(checks.group(2)) == 0
