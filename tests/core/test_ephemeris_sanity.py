"""Ephemeris sanity on entry (issue 9, item 7): ``ephemeris_problem`` and ``EphemerisStore.add``.

Good sets are real ones (HKSC 2021 RINEX nav, the Hiroshima OEM729 RTCM 1042s); each bad set
is a real one with one field changed by ``dataclasses.replace``. Expected radii are worked by
hand from the Keplerian elements (at t_oe with M0 = 0 the eccentric anomaly is 0, so
r = a (1 - e) + C_rc when omega = 0), never by the code under test.

End to end, ``bdsfix solve`` and ``bdsfix replay`` run in subprocesses on copies of the HKSC
nav file (tmp_path) in which every record of C08 has sqrt(A) = 0, negative, NaN, or e = 2 or
0.99. Expected: exit 0, a fix at each of the 205 epochs with exactly one satellite fewer
than the clean run (C08, absent from the NMEA sky view), one WARNING line naming C08 and the
reason, no other stderr output than the clean run's summary, and the refusals in STATUS.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest
from pyrtcm import RTCMReader

from drivers.rinex import read_nav
from drivers.rtcm import ephemeris_from_1042
from service.core.bds_nav import encode_d1_subframes
from service.core.ephemeris import EphemerisStore, ephemeris_problem
from service.core.types import Ephemeris, NavSubframe
from service.engine.pipeline import Pipeline
from tests.support.paths import DATA, ROOT
from tests.support.replay import replay_with_status

REAL_NAV = (
    "hksc-2021/hksc1610.nav",
    "hk-tst-urban-2019/hksc1180.19b",
    "hk-urban-3geo-2020/navigation_message.nav",
    "hk-polyu-f9p-ubx-2024/hksc269h.24f",
    "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx",
)
HIROSHIMA_RTCM = DATA / "hiroshima-oem729-rtcm-2022/20221213-010900.rtcm"


@pytest.fixture(scope="module")
def nav():
    return read_nav(DATA / "hksc-2021/hksc1610.nav")


@pytest.fixture(scope="module")
def c08(nav):
    """A healthy IGSO set (C08, toe 03:00 BDT)."""
    return nav.ephemerides["C08"][0]


@pytest.fixture(scope="module")
def c01(nav):
    """A healthy GEO set."""
    return nav.ephemerides["C01"][0]


def _check(eph):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a numpy RuntimeWarning would raise here
        problem = ephemeris_problem(eph)
    return None if problem is None else problem.check


@pytest.mark.parametrize("rel", REAL_NAV)
def test_every_real_rinex_set_passes_except_unhealthy_ones(rel):
    ephs = [e for items in read_nav(DATA / rel).ephemerides.values() for e in items]
    assert ephs
    got = {(e.prn, e.week, e.toe_sow_s): _check(e) for e in ephs}
    want = {(e.prn, e.week, e.toe_sow_s): (None if e.health == 0 else "unhealthy") for e in ephs}
    assert got == want


def _hiroshima_1042():
    with HIROSHIMA_RTCM.open("rb") as fh:
        return [
            msg
            for _raw, msg in RTCMReader(fh, quitonerror=0)
            if msg is not None and getattr(msg, "identity", None) == "1042"
        ]


def test_every_real_rtcm_1042_set_passes():
    ephs = [ephemeris_from_1042(msg) for msg in _hiroshima_1042()]
    assert len(ephs) == 41  # README: 41 BDS ephemerides in the stream
    assert [_check(e) for e in ephs] == [None] * len(ephs)


class _WithUrai:
    """A real pyrtcm 1042 message with DF490 (URAI) replaced."""

    def __init__(self, msg, urai):
        self._msg, self._urai = msg, urai

    def __getattr__(self, name):
        return self._urai if name == "DF490" else getattr(self._msg, name)


@pytest.mark.parametrize(("urai", "ura_m", "check"), [(14, 6144.0, None), (15, math.inf, "ura")])
def test_rtcm_1042_urai_15_is_refused(urai, ura_m, check):
    """ICD B1I 5.2.4.5: URAI 14 is 3072 < URA <= 6144 m, URAI 15 is URA > 6144 m."""
    msg = _hiroshima_1042()[0]
    eph = ephemeris_from_1042(_WithUrai(msg, urai))
    assert eph.ura_m == ura_m and _check(eph) == check


@pytest.mark.parametrize(
    ("change", "check"),
    [
        ({"sqrt_a_sqrt_m": 0.0}, "sqrt_a"),
        ({"sqrt_a_sqrt_m": -6493.83}, "sqrt_a"),
        ({"sqrt_a_sqrt_m": 4999.0}, "sqrt_a"),  # a = 24,990 km
        ({"sqrt_a_sqrt_m": 6701.0}, "sqrt_a"),  # a = 44,903 km
        ({"e": 2.0}, "eccentricity"),
        ({"e": 0.99}, "eccentricity"),
        ({"e": 0.1}, "eccentricity"),
        ({"e": -1e-3}, "eccentricity"),
        ({"i0_rad": math.radians(95.0)}, "inclination"),
        ({"i0_rad": math.radians(70.5)}, "inclination"),
        ({"i0_rad": -0.01}, "inclination"),
        ({"health": 1}, "unhealthy"),
        ({"ura_m": math.inf}, "ura"),  # URAI 15 as service.core.bds_nav decodes it
        ({"ura_m": 6145.0}, "ura"),
        ({"ura_m": math.nan}, "ura"),
        ({"ura_m": -1.0}, "ura"),
        ({"prn": "C64"}, "prn"),
        ({"prn": "CXY"}, "prn"),
        # r = a (1 - e) at perigee: 25,000 km * 0.91 = 22,750 km < 25,000 km
        ({"sqrt_a_sqrt_m": 5000.0, "e": 0.09, "m0_rad": 0.0, "crc_m": 0.0, "crs_m": 0.0}, "radius"),
        # r = a (1 + e) at apogee: 44,890 km * 1.09 = 48,930 km > 45,000 km
        (
            {"sqrt_a_sqrt_m": 6700.0, "e": 0.09, "m0_rad": math.pi, "crc_m": 0.0, "crs_m": 0.0},
            "radius",
        ),
        # a circular orbit with omega = M0 = 0: r = a + C_rc = 27,906 km + 30,000 km
        (
            {"e": 0.0, "m0_rad": 0.0, "omega_rad": 0.0, "crs_m": 0.0, "crc_m": 3e7},
            "radius",
        ),
    ],
)
def test_each_check_refuses_its_damage(c08, c01, change, check):
    for good in (c08, c01):
        assert _check(good) is None
        assert _check(dataclasses.replace(good, **change)) == check, (good.prn, change)


@pytest.mark.parametrize(
    "change",
    [
        {"ura_m": 0.0},  # RINEX/Table 1: not stated
        {"ura_m": 6144.0},  # URAI 14
        {"e": 0.0},
        # at t_oe with M0 = 0: r = a (1 - e) + C_rs sin 2w + C_rc cos 2w = 37,952 km + C08's
        # own harmonics (a few hundred metres)
        {"e": 0.0999, "m0_rad": 0.0},
        # e = M0 = omega = 0: r = a + C_rc = 25,000 km + 1 km, and 44,890 km
        {"sqrt_a_sqrt_m": 5000.0, "e": 0.0, "m0_rad": 0.0, "omega_rad": 0.0, "crc_m": 1e3},
        {"sqrt_a_sqrt_m": 6700.0, "e": 0.0, "m0_rad": 0.0, "omega_rad": 0.0, "crc_m": 0.0},
        {"i0_rad": 0.0},
        {"i0_rad": math.radians(70.0)},
    ],
)
def test_values_inside_the_windows_pass(c08, change):
    """C08 is an IGSO (a = 42,164 km); the radius does not depend on i0 or URA."""
    assert _check(dataclasses.replace(c08, **change)) is None


@pytest.mark.parametrize(
    "name",
    [
        f.name
        for f in dataclasses.fields(Ephemeris)
        if f.name not in ("prn", "source", "ura_m", "health")
    ],
)
@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf, "1.0"])
def test_every_numeric_field_must_be_a_finite_number(c08, name, value):
    assert _check(dataclasses.replace(c08, **{name: value})) == "not_finite"


def test_non_finite_health_is_not_finite(c08):
    assert _check(dataclasses.replace(c08, health=math.nan)) == "not_finite"


def test_add_all_keeps_and_refuses_as_add_one_by_one():
    """add_all runs the checks of a whole file at once (the radius one vectorised): the same
    sets kept, the same refusals by check and the same last refusal as add() of each set in
    turn, on a real mixed nav file (BDS, GPS, Galileo) with damaged copies of real sets of
    each check interleaved (the damaged values are the ones the tests above refuse)."""
    nav = read_nav(DATA / "hksc-2021/hksc1610.nav", ("C", "G", "E"))
    sets = [e for items in nav.ephemerides.values() for e in items]
    damage = (
        {"sqrt_a_sqrt_m": 0.0},
        {"e": 2.0},
        {"health": 1},
        {"m0_rad": math.nan},
        {"toe_sow_s": 700_000.0},
        {"e": 0.0, "m0_rad": 0.0, "omega_rad": 0.0, "crs_m": 0.0, "crc_m": 3e7},  # radius
        {"prn": "C99"},
    )
    mixed = list(sets)
    for k, change in enumerate(damage):
        mixed.insert(7 * k + 3, dataclasses.replace(sets[11 * k], **change))
    clean, one, every = EphemerisStore(), EphemerisStore(), EphemerisStore()
    for e in sets:  # the file's own refusals (its unhealthy sets)
        clean.add(e)
    kept_one = [one.add(e) for e in mixed]
    assert every.add_all(mixed) == sum(kept_one)
    assert one.all() == every.all() == clean.all()
    assert one.refused == every.refused == clean.refused + len(damage)
    assert one.refused_by_reason == every.refused_by_reason
    assert set(one.refused_by_reason) == {
        "eccentricity",
        "not_finite",
        "prn",
        "radius",
        "sqrt_a",
        "time_of_week",
        "unhealthy",
    }
    assert str(one.last_refusal) == str(every.last_refusal)


def test_refused_set_never_replaces_the_good_one(c08):
    store = EphemerisStore()
    assert store.add(c08)
    same_set = dataclasses.replace(c08, sqrt_a_sqrt_m=0.0)
    nearer = dataclasses.replace(c08, e=0.99, toe_sow_s=c08.toe_sow_s + 600)
    assert not store.add(same_set) and not store.add(nearer)
    assert store.select("C08", c08.week, c08.toe_sow_s + 600) is c08
    assert len(store) == 1 and store.refused == 2
    assert dict(store.refused_by_reason) == {"sqrt_a": 1, "eccentricity": 1}


def test_refusal_log_is_one_line_per_satellite_and_check_rate_limited(c08, c01, caplog):
    now = [1000.0]
    store = EphemerisStore(clock=lambda: now[0])
    bad08 = dataclasses.replace(c08, sqrt_a_sqrt_m=0.0)
    with caplog.at_level(logging.INFO, logger="service.core.ephemeris"):
        for t in (1000.0, 1010.0, 1059.0):
            now[0] = t
            assert not store.add(bad08)
        assert len(caplog.records) == 1
        first = caplog.records[0]
        assert first.levelno == logging.WARNING
        assert "C08" in first.getMessage() and "sqrtA 0 " in first.getMessage()
        assert "more since" not in first.getMessage()
        # another check on the same satellite, and another satellite: a line each
        assert not store.add(dataclasses.replace(c08, e=2.0))
        assert not store.add(dataclasses.replace(c01, sqrt_a_sqrt_m=0.0))
        assert len(caplog.records) == 3
        now[0] = 1060.0  # 60 s after the first line: the next one says what it stood for
        assert not store.add(bad08)
        assert len(caplog.records) == 4
        assert "(2 more since the last line)" in caplog.records[3].getMessage()
        assert not store.add(dataclasses.replace(c01, health=1))
    assert caplog.records[4].levelno == logging.INFO
    assert "unhealthy (SatH1=1)" in caplog.records[4].getMessage()
    assert store.refused == 7
    assert dict(store.refused_by_reason) == {"sqrt_a": 5, "eccentricity": 1, "unhealthy": 1}


def test_pipeline_counts_refusals_by_check(c08):
    pipe = Pipeline(EphemerisStore())
    pipe.add_ephemeris(c08)
    pipe.add_ephemeris(dataclasses.replace(c08, sqrt_a_sqrt_m=-6493.83))
    pipe.add_ephemeris(dataclasses.replace(c08, e=math.nan))
    pipe.add_ephemeris(dataclasses.replace(c08, health=1))
    counts = {k: v for k, v in pipe.counters.items() if k.startswith("ephemeris")}
    assert counts == {
        "ephemeris_rinex": 1,
        "ephemeris_refused": 3,
        "ephemeris_refused_sqrt_a": 1,
        "ephemeris_refused_not_finite": 1,
        "ephemeris_refused_unhealthy": 1,
        "ephemeris_dropped_unhealthy": 1,  # the same set flagged: the held copy goes too
    }
    assert len(pipe.store) == 0


@pytest.mark.parametrize(
    ("change", "check"),
    [({"sqrt_a_sqrt_m": 0.0}, "sqrt_a"), ({"e": 0.4}, "eccentricity"), ({"ura_m": 1e4}, "ura")],
)
def test_decoded_d1_set_is_refused_and_the_good_one_stays(c08, change, check):
    """Through the subframe path: real C08 encoded into D1 subframes 1-3 (ICD 5.2.3), then
    the same set damaged (fields the D1 message can carry: sqrt(A) >= 0, e < 0.5, URAI 15)."""
    pipe = Pipeline(EphemerisStore())
    sow = int(c08.toe_sow_s) - 1800
    bdt_week, gpst_week = c08.week, c08.week + 1356  # ICD 4.2: GPS week = BDS week + 1356

    def feed(eph, sow_s):
        for fra, words in enumerate(encode_d1_subframes(eph, sow_s)[:3], start=1):
            sf_sow = sow_s + 6 * (fra - 1)
            pipe.on_subframe(
                NavSubframe("C08", "D1", fra, sf_sow, tuple(words), gpst_week, sf_sow + 14.0)
            )

    feed(c08, sow)
    feed(dataclasses.replace(c08, **change), sow + 30)
    held = pipe.store.select("C08", bdt_week, c08.toe_sow_s)
    assert held is not None and held.source == "subframes"
    assert held.sqrt_a_sqrt_m == pytest.approx(c08.sqrt_a_sqrt_m, abs=2.0**-19)
    assert held.e == pytest.approx(c08.e, abs=2.0**-33) and held.ura_m == 2.4  # URAI 0
    counts = {k: v for k, v in pipe.counters.items() if k.startswith("ephemeris")}
    assert counts == {
        "ephemeris_subframes": 1,
        "ephemeris_refused": 1,
        f"ephemeris_refused_{check}": 1,
    }


def test_persisted_store_with_a_nan_set_keeps_the_rest(nav, tmp_path, caplog):
    store = EphemerisStore()
    for items in nav.ephemerides.values():
        store.add_all(items)
    path = tmp_path / "ephemeris.json"
    store.save(path)
    doc = json.loads(path.read_text())
    hit = [i for i, item in enumerate(doc["ephemerides"]) if item["prn"] == "C08"]
    for i in hit:
        doc["ephemerides"][i]["sqrt_a_sqrt_m"] = math.nan  # json writes NaN, and reads it
    path.write_text(json.dumps(doc))
    with caplog.at_level(logging.WARNING, logger="service.core.ephemeris"):
        back = EphemerisStore.load(path)
    assert len(back) == len(store) - len(hit) and "C08" not in back.prns
    assert back.refused_by_reason == {"not_finite": len(hit)}
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "C08" in lines[0] and "sqrt_a_sqrt_m is nan" in lines[0]


# --- the whole service on a damaged copy of the HKSC nav file ----------------------------------
#
# Every record of one satellite (C08, an IGSO at 70-76 deg elevation, used at every epoch of
# the clean run) gets one damaged field in a copy of hksc1610.nav written to tmp_path. RINEX
# 3.04 BDS record (Table A14): data lines are 4X,4D19.12; BROADCAST ORBIT - 2 is the record's
# third line, with e the second field and sqrt(A) the fourth.

REPO = ROOT
HKSC_OBS = DATA / "hksc-2021/hksc1610.obs"
HKSC_NAV = DATA / "hksc-2021/hksc1610.nav"
DAMAGED_PRN = "C08"
N_EPOCHS = 205  # DATA/README.md: 205 epochs, 1 Hz
FIELD_COLUMNS = {"e": slice(4 + 19, 4 + 2 * 19), "sqrt_a": slice(4 + 3 * 19, 4 + 4 * 19)}
LOG_LINE = re.compile(r"^(DEBUG|INFO|WARNING|ERROR|CRITICAL) [\w.]+: ")  # service/commands/cli.py
DAMAGE = {
    # case: (field, D19.12 text, what the warning says)
    "sqrt_a-zero": ("sqrt_a", " .000000000000D+00", "sqrtA 0 sqrt(m) outside [5000, 6700]"),
    "sqrt_a-negative": ("sqrt_a", "-.649383323860D+04", "sqrtA -6493.83 sqrt(m) outside"),
    "e-2": ("e", " .200000000000D+01", "e 2 outside [0, 0.1)"),
    "e-0.99": ("e", " .990000000000D+00", "e 0.99 outside [0, 0.1)"),
    "sqrt_a-nan": ("sqrt_a", "NaN", "sqrt_a_sqrt_m is nan, not a finite number"),
}
CHECK_OF_CASE = {
    "sqrt_a-zero": "sqrt_a",
    "sqrt_a-negative": "sqrt_a",
    "e-2": "eccentricity",
    "e-0.99": "eccentricity",
    "sqrt_a-nan": "not_finite",
}


def _damaged_nav(out: Path, prns: set[str], field: str, text: str) -> tuple[Path, int]:
    """Copy of the HKSC nav with ``field`` of every record of ``prns`` replaced by ``text``;
    returns the path and the number of distinct (PRN, toe) sets damaged."""
    lines = HKSC_NAV.read_text().splitlines(keepends=True)
    body = next(i for i, line in enumerate(lines) if "END OF HEADER" in line) + 1
    cut = FIELD_COLUMNS[field]
    sets = set()
    for i in range(body, len(lines)):
        if lines[i][:3] in prns:
            orbit2, orbit3 = lines[i + 2], lines[i + 3]
            old = float(orbit2[cut].replace("D", "E"))
            # the column really holds that field: e ~ 0.005, sqrt(A) ~ 5282.6 or 6493.4
            assert (0 < old < 0.02) if field == "e" else (5282 < old < 6494), (i, old)
            lines[i + 2] = orbit2[: cut.start] + text.rjust(19) + orbit2[cut.stop :]
            sets.add((lines[i][:3], float(orbit3[4:23].replace("D", "E"))))  # toe
    assert sets
    out.write_text("".join(lines))
    return out, len(sets)


def _unhealthy_gps_galileo_sets() -> set[tuple[str, float]]:
    """The (PRN, toe) sets of GPS and Galileo satellites whose SV health (RINEX 3 broadcast
    orbit 6, second field) is not 0 in the HKSC nav file, read by column: every system is
    read by default, and these are refused as unhealthy beside the damaged BDS sets."""
    lines = HKSC_NAV.read_text().splitlines()
    body = next(i for i, line in enumerate(lines) if "END OF HEADER" in line) + 1
    return {
        (lines[i][:3], float(lines[i + 3][4:23].replace("D", "E")))
        for i in range(body, len(lines))
        if lines[i][:1] in "GE"
        and lines[i][1:3].isdigit()
        and float(lines[i + 6][23:42].replace("D", "E")) != 0.0
    }


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run(
        [sys.executable, "-m", "service", *args],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _fixes(stdout: str) -> dict[tuple[int, float], dict]:
    recs = [json.loads(line) for line in stdout.splitlines()]
    return {(r["gpst_week"], r["gpst_tow_s"]): r for r in recs if r["class"] == "FIX"}


def _gsv_prns(nmea: str) -> list[set[int]]:
    """BDS satellite numbers listed in the GSV sentences, one set per epoch (per GGA)."""
    epochs: list[set[int]] = []
    for line in nmea.splitlines():
        body = line.split("*")[0].split(",")
        if body[0].endswith("GGA"):
            epochs.append(set())
        elif body[0] == "$GBGSV":
            n = (len(body) - 4) // 4  # NMEA 4.11: a trailing signal ID follows the blocks
            epochs[-1].update(int(body[4 + 4 * k]) for k in range(n) if body[4 + 4 * k])
    return epochs


def _stderr_lines(stderr: str) -> tuple[list[str], list[str]]:
    lines = stderr.splitlines()
    return [x for x in lines if LOG_LINE.match(x)], [x for x in lines if not LOG_LINE.match(x)]


@pytest.fixture(scope="module")
def clean():
    jsonl = _run("solve", str(HKSC_OBS), str(HKSC_NAV), "--mode", "spp")
    nmea = _run("solve", str(HKSC_OBS), str(HKSC_NAV), "--mode", "spp", "--format", "nmea")
    assert jsonl.returncode == 0 and nmea.returncode == 0
    fixes = _fixes(jsonl.stdout)
    assert len(fixes) == N_EPOCHS and all(f["mode"] == "spp" for f in fixes.values())
    sky = _gsv_prns(nmea.stdout)
    assert len(sky) == N_EPOCHS and all(8 in s for s in sky)  # C08 seen at every epoch
    logs, other = _stderr_lines(jsonl.stderr)
    assert logs == []
    return fixes, other


@pytest.mark.parametrize("case", DAMAGE)
def test_solve_refuses_the_damaged_satellite_and_fixes_every_epoch(case, clean, tmp_path):
    clean_fixes, clean_other = clean
    field, text, why = DAMAGE[case]
    nav, _ = _damaged_nav(tmp_path / f"{case}.nav", {DAMAGED_PRN}, field, text)
    run = _run("solve", str(HKSC_OBS), str(nav), "--mode", "spp")
    assert run.returncode == 0, run.stderr
    fixes = _fixes(run.stdout)
    assert fixes.keys() == clean_fixes.keys()
    assert all(f["mode"] == "spp" for f in fixes.values())
    # one satellite fewer at every epoch: C08 was used in all of them
    assert all(fixes[k]["n_full"] == clean_fixes[k]["n_full"] - 1 for k in fixes)
    # ... and it is C08: it has no ephemeris, so it is not in the sky view (GSV) either
    nmea = _run("solve", str(HKSC_OBS), str(nav), "--mode", "spp", "--format", "nmea")
    sky = _gsv_prns(nmea.stdout)
    assert len(sky) == N_EPOCHS and not any(8 in s for s in sky)
    # stderr: one log line, and otherwise only the summary the clean run prints too
    logs, other = _stderr_lines(run.stderr)
    assert len(logs) == 1, run.stderr
    assert logs[0].startswith(f"WARNING service.core.ephemeris: refused ephemeris {DAMAGED_PRN} ")
    assert why in logs[0]
    assert other == clean_other
    assert "Warning" not in run.stderr and "Traceback" not in run.stderr


@pytest.fixture(scope="module")
def clean_replay(tmp_path_factory):
    out = tmp_path_factory.mktemp("replay") / "clean.jsonl"
    run = _run(
        "replay", str(HKSC_OBS), "--nav", str(HKSC_NAV), "--max-speed", "--jsonl-out", str(out)
    )
    assert run.returncode == 0
    fixes = _fixes(out.read_text())
    assert len(fixes) == N_EPOCHS and all(f["mode"] != "none" for f in fixes.values())
    logs, other = _stderr_lines(run.stderr)
    assert logs == []
    return fixes, other


def _replay_with_status(nav: Path, workdir: Path) -> tuple[subprocess.CompletedProcess, dict]:
    """``bdsfix replay`` with a ZeroMQ STATUS subscriber; returns the run and its last
    STATUS, received without racing the exit (tests/support/replay.py)."""
    out = workdir / "fixes.jsonl"
    res = replay_with_status(HKSC_OBS, "--nav", str(nav), "--jsonl-out", str(out))
    stdout = out.read_text() if out.exists() else ""
    return subprocess.CompletedProcess([], res.rc, stdout, res.stderr), res.final


@pytest.mark.parametrize("case", DAMAGE)
def test_replay_refuses_the_damaged_satellite_and_fixes_every_epoch(case, clean_replay, tmp_path):
    clean_fixes, clean_other = clean_replay
    field, text, why = DAMAGE[case]
    nav, n_sets = _damaged_nav(tmp_path / f"{case}.nav", {DAMAGED_PRN}, field, text)
    run, status = _replay_with_status(nav, tmp_path)
    assert run.returncode == 0, run.stderr
    fixes = _fixes(run.stdout)
    assert fixes.keys() == clean_fixes.keys()
    assert all(f["mode"] != "none" for f in fixes.values())
    assert all(fixes[k]["n_full"] == clean_fixes[k]["n_full"] - 1 for k in fixes)
    logs, other = _stderr_lines(run.stderr)
    assert len(logs) == 1, run.stderr
    assert logs[0].startswith(f"WARNING service.core.ephemeris: refused ephemeris {DAMAGED_PRN} ")
    assert why in logs[0]

    # the same summary as the clean run (the lines naming the outputs and the pacing differ)
    def summary(lines: list[str]) -> list[str]:
        setup = ("bdsfix replay: outputs ", "bdsfix replay: reading ")
        return [x for x in lines if not x.startswith(setup)]

    assert summary(other) == summary(clean_other)
    assert "Warning" not in run.stderr and "Traceback" not in run.stderr
    counters = status["counters"]
    assert counters["ephemeris_refused"] == n_sets + len(_unhealthy_gps_galileo_sets())
    assert counters[f"ephemeris_refused_{CHECK_OF_CASE[case]}"] == n_sets


def test_a_nav_file_with_no_usable_set_is_a_clear_error(tmp_path):
    text = HKSC_NAV.read_text()
    prns = {line[:3] for line in text.splitlines() if line[:1] == "C" and line[1:3].isdigit()}
    nav, _ = _damaged_nav(tmp_path / "all.nav", prns, "sqrt_a", " .000000000000D+00")
    run = _run("solve", str(HKSC_OBS), str(nav), "--mode", "spp")
    assert run.returncode == 3  # InputError: the nav file cannot be used (EXIT_INPUT)
    assert run.stdout == ""
    logs, other = _stderr_lines(run.stderr)
    assert sorted(x.split()[4] for x in logs) == sorted(prns)  # one line per satellite
    assert all(x.startswith("WARNING service.core.ephemeris: refused ephemeris C") for x in logs)
    assert other == [f"bdsfix solve: error: no usable BDS ephemeris in {nav}"]
