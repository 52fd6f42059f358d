"""An ephemeris week that disagrees with the stream's does not move the stream's week
(read-only review: DF289 + 1 in every RTCM 1046 stamped 25 fixes a week late, DF076 + 1 in
every 1019 cut 54 fixes to 10).

WeekContext keeps the stream's week once one is known: a report more than a day from it is
ignored (counted, logged rate-limited) unless reports say the new time consistently (three in
a row, none agreeing with the reference between them, and the latest reports of more kinds
of message saying the new time than the old). End to end, damaged copies of the Hiroshima
OEM729 RTCM are written to tmp_path (field positions from RTCM 10403.3 Tables 3.5-21 and
3.5-116, checked by pyrtcm's reading of the damaged file); the recording is GPS week 2240
(DATA/README.md: 2022-12-13).
"""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from pathlib import Path

import pytest
from pyrtcm import RTCMReader
from pysbf2 import SBFReader

from drivers.framing import WeekContext
from drivers.source import open_source
from tests.support.captures import edit_rtcm_field, edit_sbf_field
from tests.support.paths import DATA, ROOT
from tests.support.replay import replay_with_status

HIROSHIMA = DATA / "hiroshima-oem729-rtcm-2022/20221213-010900.rtcm"
WEEK = 2240  # DATA/README.md
TOW = 176_400.0
DAY_S = 86_400.0


def test_a_report_a_week_off_is_ignored_and_counted(caplog):
    wc = WeekContext()
    assert wc.set_approx(WEEK, TOW, "RTCM 1042")
    with caplog.at_level(logging.WARNING, logger="drivers.framing"):
        for _ in range(10):
            assert not wc.set_approx(WEEK + 1, TOW, "RTCM 1046")
            assert wc.set_approx(WEEK, TOW + 60.0, "RTCM 1019")
    assert wc.disagreements == 10
    assert wc.resolve(TOW + 100.0) == WEEK
    lines = [r for r in caplog.records if "ignored GPS week" in r.getMessage()]
    assert len(lines) == 1  # rate-limited per source
    assert "2241" in lines[0].getMessage() and "RTCM 1046" in lines[0].getMessage()


def test_hours_apart_agree():
    wc = WeekContext()
    assert wc.set_approx(WEEK, TOW, "RTCM 1042")
    assert wc.set_approx(WEEK, TOW + 7200.0, "RTCM 1019")  # a t_oe two hours on
    # the reference is now the latest report: a day before it, less a second, agrees
    assert wc.set_approx(WEEK, TOW + 7200.0 - DAY_S + 1.0, "RTCM 1046")
    assert not wc.set_approx(WEEK, TOW + 7200.0 + 2 * DAY_S, "RTCM 1046")
    assert wc.disagreements == 1


def test_one_kind_of_message_alone_never_moves_a_stream_of_several():
    """A burst of one system's messages (all damaged alike) is not consistency."""
    wc = WeekContext()
    assert wc.set_approx(WEEK, TOW, "RTCM 1042")
    assert wc.set_approx(WEEK, TOW, "RTCM 1019")
    for _ in range(32):
        assert not wc.set_approx(WEEK + 1, TOW, "RTCM 1019")
    assert wc.resolve(TOW) == WEEK


def test_consistent_reports_from_two_kinds_take_the_new_time(caplog):
    wc = WeekContext()
    assert wc.set_approx(WEEK, TOW, "RTCM 1042")
    assert wc.set_approx(WEEK, TOW, "RTCM 1019")
    with caplog.at_level(logging.WARNING, logger="drivers.framing"):
        assert not wc.set_approx(WEEK + 3, 1000.0, "RTCM 1019")
        assert not wc.set_approx(WEEK + 3, 1030.0, "RTCM 1042")
        assert wc.set_approx(WEEK + 3, 1060.0, "RTCM 1019")
    assert wc.resolve(1100.0) == WEEK + 3
    assert "replaces week 2240" in caplog.text
    assert wc.disagreements == 2


def test_an_agreeing_report_breaks_the_run():
    wc = WeekContext()
    assert wc.set_approx(WEEK, TOW, "RTCM 1042")
    for _ in range(5):
        assert not wc.set_approx(WEEK + 1, TOW, "RTCM 1046")
        assert not wc.set_approx(WEEK + 1, TOW, "RTCM 1019")
        assert wc.set_approx(WEEK, TOW, "RTCM 1045")  # the stream's week again
    assert wc.resolve(TOW) == WEEK


def test_the_only_kind_of_a_stream_moves_it_after_three_in_a_row():
    """A BDS-only stream whose first 1042 was wrong: the following ones correct it."""
    wc = WeekContext()
    assert wc.set_approx(WEEK + 1, TOW, "RTCM 1042")
    assert not wc.set_approx(WEEK, TOW, "RTCM 1042")
    assert not wc.set_approx(WEEK, TOW + 30.0, "RTCM 1042")
    assert wc.set_approx(WEEK, TOW + 60.0, "RTCM 1042")
    assert wc.resolve(TOW + 61.0) == WEEK


def test_a_damaged_first_report_is_corrected_by_the_other_kinds():
    """The stream's first ephemeris a damaged 1046 (week + 1), the 1046s all damaged alike,
    the other kinds right: once two kinds say the right week against one, three in a row
    take it, and the damaged kind never takes it back."""
    wc = WeekContext()
    assert wc.set_approx(WEEK + 1, TOW, "RTCM 1046")
    assert not wc.set_approx(WEEK, TOW, "RTCM 1045")
    assert wc.set_approx(WEEK + 1, TOW, "RTCM 1046")  # agrees with the (wrong) reference
    assert not wc.set_approx(WEEK, TOW + 10.0, "RTCM 1019")
    assert not wc.set_approx(WEEK, TOW + 20.0, "RTCM 1019")
    assert wc.set_approx(WEEK, TOW + 30.0, "RTCM 1019")  # 1019 and 1045 against 1046
    assert wc.resolve(TOW + 31.0) == WEEK
    for k in range(20):
        assert not wc.set_approx(WEEK + 1, TOW + 40.0 + k, "RTCM 1046")
    assert wc.resolve(TOW + 100.0) == WEEK


def test_a_hint_still_gives_way_to_the_stream():
    wc = WeekContext(WEEK + 100)
    assert wc.set_approx(WEEK, TOW, "RTCM 1042")
    assert wc.resolve(TOW) == WEEK and wc.disagreements == 0


def test_the_receivers_own_time_is_compared_never_replaced(caplog):
    """Once a receiver time tag has set the week (UBX RAWX, SBF MeasEpoch), an ephemeris
    report a week off is counted and logged as one against the stream's week is (before:
    True, never counted), and the receiver's time stays."""
    wc = WeekContext()
    wc.set_exact(WEEK, TOW)
    with caplog.at_level(logging.WARNING, logger="drivers.framing"):
        assert wc.set_approx(WEEK, TOW + 3_600.0, "RTCM 1019")  # t_oe an hour ahead
        assert not wc.set_approx(WEEK + 1, TOW, "RTCM 1042")
    assert wc.disagreements == 1 and wc.exact and wc.resolve(TOW) == WEEK
    assert any("RTCM 1042" in r.getMessage() for r in caplog.records)


# --- end to end ------------------------------------------------------------------------------


def _fields(path: Path, number: str, name: str) -> list[int]:
    with path.open("rb") as fh:
        return [
            int(getattr(m, name)) for _raw, m in RTCMReader(fh, quitonerror=0)
            if m is not None and m.identity == number
        ]  # fmt: skip


def _replay(source: Path, out: Path) -> dict[tuple[int, float], dict]:
    run = subprocess.run(
        [sys.executable, "-m", "service", "replay", str(source), "--max-speed",
         "--nmea-out", "/dev/null", "--systems", "C,G,E", "--jsonl-out", str(out)],
        cwd=ROOT, capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    recs = [json.loads(line) for line in out.read_text().splitlines()]
    return {
        (r["gpst_week"], r["gpst_tow_s"]): r
        for r in recs
        if r["class"] == "FIX" and r.get("x_ecef_m") is not None
    }


def _first_msm_tow_after(numbers: set[str]) -> float:
    """GPST tow [s] of the first GPS/Galileo MSM epoch at or after the first message of
    ``numbers`` in the stream (DF004 / DF248: ms of the GPS / Galileo week; GST = GPST)."""
    seen = False
    with HIROSHIMA.open("rb") as fh:
        for _raw, m in RTCMReader(fh, quitonerror=0):
            if m is None:
                continue
            seen = seen or m.identity in numbers
            if seen and m.identity in ("1077", "1097"):
                return int(m.DF004 if m.identity == "1077" else m.DF248) / 1000.0
    raise AssertionError(f"no {numbers} in the stream")


@pytest.fixture(scope="module")
def clean(tmp_path_factory):
    fixes = _replay(HIROSHIMA, tmp_path_factory.mktemp("clean") / "clean.jsonl")
    assert len(fixes) == 54 and {w for w, _t in fixes} == {WEEK}
    return fixes


def test_gps_week_plus_one_in_every_1019_changes_nothing(clean, tmp_path):
    damaged = tmp_path / "gps_week.rtcm"
    # 1019: number 12 bits, DF009 6, then DF076 (GPS week mod 1024, 10 bits) at bit 18
    n = edit_rtcm_field(HIROSHIMA, damaged, 1019, 18, 10, lambda week: week + 1)
    assert n == 22
    assert set(_fields(damaged, "1019", "DF076")) == {(WEEK + 1) % 1024}
    fixes = _replay(damaged, tmp_path / "gps_week.jsonl")
    assert fixes.keys() == clean.keys()
    run = replay_with_status(damaged, "--systems", "C,G,E", "--nmea-out", "/dev/null")
    counters = run.final["counters"]
    assert counters["source_eph_week_disagrees"] == n
    assert counters.get("source_eph_week_1019", 0) == 0


def test_galileo_week_plus_one_in_every_1046_keeps_the_week(clean, tmp_path):
    damaged = tmp_path / "gal_week.rtcm"
    # 1046: number 12 bits, DF252 6, then DF289 (GST week, 12 bits) at bit 18
    n = edit_rtcm_field(HIROSHIMA, damaged, 1046, 18, 12, lambda week: week + 1)
    assert n == 45
    assert set(_fields(damaged, "1046", "DF289")) == {WEEK - 1024 + 1}
    fixes = _replay(damaged, tmp_path / "gal_week.jsonl")
    assert {w for w, _t in fixes} == {WEEK}  # before: 25 fixes stamped 2241
    assert fixes.keys() <= clean.keys()
    # the Galileo sets (all damaged) are the only ones before the first 1019/1042: the
    # epochs before those arrive are the only ones lost
    first_other = _first_msm_tow_after({"1019", "1042"})
    lost = clean.keys() - fixes.keys()
    assert all(t < first_other for _w, t in lost), (sorted(lost), first_other)
    run = replay_with_status(damaged, "--systems", "C,G,E", "--nmea-out", "/dev/null")
    counters = run.final["counters"]
    assert counters["source_eph_week_disagrees"] == n
    assert counters.get("source_eph_week_1046", 0) == 0


F9R = DATA / "ublox-logs/ublox-zed-f9r.log"
LEUVEN_SBF = DATA / "leuven-septentrio-sbf-2025/log_0000.sbf"


def _driver_counters(path: Path) -> dict[str, int]:
    with open_source(str(path), systems=frozenset("CGE")) as src:
        for _event in src:
            pass
        return dict(src.counters)


@pytest.mark.parametrize(
    ("number", "start", "length", "dfield", "made"),
    [
        # RTCM 10403.3: after the number (12 bits) and the satellite ID (6 bits) comes the
        # week: 1042 DF489 (BDT, 13 bits), 1019 DF076 (mod 1024), 1046 DF289 (GST, 12 bits)
        (1042, 18, 13, "DF489", "ephemerides_rtcm"),
        (1019, 18, 10, "DF076", "ephemerides_rtcm_G"),
        (1046, 18, 12, "DF289", "ephemerides_rtcm_E"),
    ],
)
def test_rtcm_week_plus_one_beside_the_receivers_own_time_is_counted(
    tmp_path, number, start, length, dfield, made
):
    """The u-blox F9R capture carries the receiver's time (the week is exact: no
    ``eph_week_<number>`` is taken) and RTCM ephemerides: each of them a week late is counted
    ``eph_week_disagrees`` (before: 0 on this path, the week never compared), the sets still
    passed on as on the RTCM-only path."""
    damaged = tmp_path / "week.log"
    n = edit_rtcm_field(F9R, damaged, number, start, length, lambda week: week + 1)
    assert n == {1042: 19, 1019: 19, 1046: 15}[number]  # DATA/README.md: 1042 x 19
    before, after = _fields(F9R, str(number), dfield), _fields(damaged, str(number), dfield)
    assert [a - b for a, b in zip(after, before, strict=True)] == [1] * n
    clean, hurt = _driver_counters(F9R), _driver_counters(damaged)
    assert not any(k.startswith("eph_week") for k in clean)  # the receiver's own week
    assert hurt["eph_week_disagrees"] == n
    assert hurt[made] == clean[made]


@pytest.mark.parametrize(
    ("block", "number", "offset", "made"),
    [
        # WNt_oe (u2) byte offsets, checked by pysbf2 below: GPSNav (mod 1024) and BDSNav
        # after WNt_oc at 136, GALNav (GPS weeks) before WNt_oc at 126
        ("GPSNav", 5891, 138, "ephemerides_sbf_G"),
        ("GALNav", 4002, 124, "ephemerides_sbf_E"),
        ("BDSNav", 4081, 138, "ephemerides_sbf"),
    ],
)
def test_sbf_nav_week_plus_one_is_counted(tmp_path, block, number, offset, made):
    """Every GPSNav, GALNav or BDSNav of the Leuven SBF with WNt_oe + 1 (CRC made again):
    each is counted ``eph_week_disagrees`` (before: 0 for all three, the MeasEpoch week being
    the receiver's own; GPSNav's and GALNav's never even compared), as RTCM's are."""
    damaged = tmp_path / "week.sbf"
    n = edit_sbf_field(LEUVEN_SBF, damaged, number, offset, "<H", lambda week: week + 1)
    assert n == {"GPSNav": 18, "GALNav": 16, "BDSNav": 20}[block]  # DATA/README.md

    def weeks(path: Path) -> list[int]:
        with path.open("rb") as fh:
            return [
                int(m.WNt_oe) for _raw, m in SBFReader(fh, quitonerror=0)
                if m is not None and m.identity == block
            ]  # fmt: skip

    assert [a - b for a, b in zip(weeks(damaged), weeks(LEUVEN_SBF), strict=True)] == [1] * n
    clean, hurt = _driver_counters(LEUVEN_SBF), _driver_counters(damaged)
    assert clean.get("eph_week_disagrees", 0) == 0
    assert hurt["eph_week_disagrees"] == n
    assert hurt[made] == clean[made]


def _1019s_at(tmp_path: Path, toe_s: float) -> list:
    """The F9R capture's 1019s with t_oe and t_oc (DF093 at payload bit 288, DF081 at bit 56,
    16 bits of 16 s each: RTCM 10403.3 Table 3.5-21) set to ``toe_s``, CRC made again; as
    pyrtcm reads them."""
    at_toc, at_both = tmp_path / "toc.log", tmp_path / "both.log"
    raw = int(toe_s) // 16
    assert edit_rtcm_field(F9R, at_toc, 1019, 56, 16, lambda _v: raw) == 19
    assert edit_rtcm_field(at_toc, at_both, 1019, 288, 16, lambda _v: raw) == 19
    with at_both.open("rb") as fh:
        msgs = [m for _raw, m in RTCMReader(fh, quitonerror=0) if m and m.identity == "1019"]
    assert {(float(m.DF093), float(m.DF081)) for m in msgs} == {(toe_s, toe_s)}
    return msgs


@pytest.mark.parametrize(
    ("stream_tow_s", "toe_s", "toe_week_step"),
    [
        (603_000.0, 0.0, 1),  # Saturday 23:30, for Sunday 00:00: the next week's
        (1_800.0, 604_000.0, -1),  # Sunday 00:30, for Saturday 23:46: the last week's
    ],
)
def test_a_1019_at_the_week_handover_is_held_in_its_toes_week(
    tmp_path, caplog, stream_tow_s, toe_s, toe_week_step
):
    """A GPS set is broadcast around its t_oe, and DF076 is the week of transmission
    (subframe 1's WN, IS-GPS-200 20.3.3.3.1.1): at the end of a week the sets of the next
    one's first hours come with this week's number (the review found every 1019 of the
    Hiroshima stream about 50 minutes ahead of its time). Such a set is held in its t_oe's
    week, counted ``eph_week_handovers``, with no disagreement and no warning; before, it
    was held a week off (and, beside the receiver's time, warned of as damage)."""
    from drivers.rtcm import RtcmMapper

    msgs = _1019s_at(tmp_path, toe_s)
    week = 2000 + (int(msgs[0].DF076) - 2000) % 1024  # the capture's week, from its DF076
    wc = WeekContext()
    wc.set_exact(week, stream_tow_s)  # the receiver's own time, at the week's end (start)
    mapper = RtcmMapper(week=wc, systems="CG")
    with caplog.at_level(logging.WARNING, logger="drivers"):
        sets = [eph for m in msgs for eph in mapper.on_message(m)]
    assert len(sets) == 19
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING]
    # GPST (week + step, t_oe) on BDT: week - 1356, 14 s earlier
    bdt = (week + toe_week_step - 1356, toe_s - 14.0)
    expected = bdt if bdt[1] >= 0.0 else (bdt[0] - 1, bdt[1] + 604_800.0)
    assert {(e.week, e.toe_sow_s) for e in sets} == {expected}
    assert mapper.counters["eph_week_handovers"] == 19
    assert "eph_week_disagrees" not in mapper.counters


def test_a_1019_a_week_off_mid_week_is_no_handover(tmp_path):
    """The handover is only at a week's boundary: mid-week, a 1019 whose week is one more
    than the receiver's time still disagrees (the damage the tests above count)."""
    from drivers.rtcm import RtcmMapper

    msgs = _1019s_at(tmp_path, 302_400.0)
    week = 2000 + (int(msgs[0].DF076) - 2000) % 1024
    wc = WeekContext()
    wc.set_exact(week - 1, 302_400.0)
    mapper = RtcmMapper(week=wc, systems="CG")
    for m in msgs:
        mapper.on_message(m)
    assert mapper.counters["eph_week_disagrees"] == 19
    assert "eph_week_handovers" not in mapper.counters
