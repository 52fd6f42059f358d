"""The broadcast clock terms, group delays and t_oc of an ephemeris set are bounded (read-only
review: one absurd af0 or a wrapped t_oc cost every epoch).

Bounds are the largest magnitudes each system's broadcast fields can carry, worked out here
from the ICDs' field widths and scale factors (two's complement: 2^(bits-1) LSB), never read
from the code under test: BDS ICD B1I 5.2.4.10 (a0 24 bits x 2^-33 s, a1 22 bits x 2^-50,
a2 11 bits x 2^-66) and 5.2.4.8 (TGD 10 bits x 0.1 ns); IS-GPS-200 20.3.3.3 (a_f0 22 bits x
2^-31 s, a_f1 16 bits x 2^-43, a_f2 8 bits x 2^-55, T_GD 8 bits x 2^-31 s); Galileo OS SIS
ICD 5.1.3 (af0 31 bits x 2^-34 s, af1 21 bits x 2^-46, af2 6 bits x 2^-59) and 5.1.5 (BGD
10 bits x 2^-32 s).

End to end, damaged copies of real recordings are written to tmp_path: the Leuven SBF with
G05's GPSNav a_f0 = 1e10 s or every GPSNav t_oc = 0xFFFFFFFF (block CRC recomputed), the HKSC
nav with every Galileo af0 = 1e10 s, the Hiroshima RTCM with every 1019 t_oc = 0xFFFF x 16 s
(CRC-24Q recomputed). Each must give a fix at every epoch the undamaged file gives one.
"""

from __future__ import annotations

import dataclasses
import json
import math
import subprocess
import sys
from pathlib import Path

import pytest
from pyrtcm import RTCMReader
from pysbf2 import SBFReader

from drivers.rinex import read_nav
from drivers.source import open_source
from service.core.ephemeris import EphemerisStore, ephemeris_problem
from service.core.timebase import gpst_sow_to_bdt_sow
from tests.support.captures import edit_rtcm_field, edit_sbf_field
from tests.support.paths import DATA, ROOT
from tests.support.replay import replay_with_status

HKSC_OBS = DATA / "hksc-2021/hksc1610.obs"
HKSC_NAV = DATA / "hksc-2021/hksc1610.nav"
LEUVEN_SBF = DATA / "leuven-septentrio-sbf-2025/log_0000.sbf"
HIROSHIMA = DATA / "hiroshima-oem729-rtcm-2022/20221213-010900.rtcm"
REAL_NAV = (
    "hksc-2021/hksc1610.nav",
    "hk-tst-urban-2019/hksc1180.19b",
    "hk-tst-urban-2019/hksc1180.19n",
    "hk-urban-3geo-2020/navigation_message.nav",
    "hk-polyu-f9p-ubx-2024/hksc269h.24f",
    "hk-polyu-f9p-ubx-2024/hksc269h.24n",
    "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx",
)

# (system letter, af0 bound [s], af1 bound [s/s], af2 bound [s/s^2], group delay bound [s])
ICD_BOUNDS = {
    "C": (2**23 * 2.0**-33, 2**21 * 2.0**-50, 2**10 * 2.0**-66, 2**9 * 1e-10),
    "G": (2**21 * 2.0**-31, 2**15 * 2.0**-43, 2**7 * 2.0**-55, 2**7 * 2.0**-31),
    "E": (2**30 * 2.0**-34, 2**20 * 2.0**-46, 2**5 * 2.0**-59, 2**9 * 2.0**-32),
}


@pytest.fixture(scope="module")
def sets():
    """A healthy real set of each system (HKSC 2021 nav)."""
    nav = read_nav(HKSC_NAV, systems=("C", "G", "E"))
    out = {}
    for letter in ICD_BOUNDS:
        out[letter] = next(
            e for prn, items in sorted(nav.ephemerides.items()) if prn[0] == letter
            for e in items if e.health == 0
        )  # fmt: skip
        assert ephemeris_problem(out[letter]) is None
    return out


def _check(eph):
    problem = ephemeris_problem(eph)
    return None if problem is None else problem.check


def test_the_bounds_are_the_icd_field_ranges():
    # af0 is 2^-10 s for BDS and GPS, 2^-4 s for Galileo (the brief's figures)
    assert ICD_BOUNDS["C"][0] == ICD_BOUNDS["G"][0] == 2.0**-10
    assert ICD_BOUNDS["E"][0] == 2.0**-4
    assert ICD_BOUNDS["C"][3] == pytest.approx(51.2e-9)


@pytest.mark.parametrize("letter", sorted(ICD_BOUNDS))
@pytest.mark.parametrize(
    ("field", "index", "check"),
    [
        ("af0_s", 0, "clock"),
        ("af1_s_s", 1, "clock"),
        ("af2_s_s2", 2, "clock"),
        ("tgd1_s", 3, "group_delay"),
        ("tgd2_s", 3, "group_delay"),
    ],
)
def test_each_clock_term_passes_at_its_bound_and_is_refused_beyond(
    sets, letter, field, index, check
):
    eph, bound = sets[letter], ICD_BOUNDS[letter][index]
    for sign in (1.0, -1.0):
        assert _check(dataclasses.replace(eph, **{field: sign * bound})) is None
        assert _check(dataclasses.replace(eph, **{field: sign * bound * 1.001})) == check
    assert _check(dataclasses.replace(eph, **{field: 1e10})) == check


@pytest.mark.parametrize("rel", REAL_NAV)
def test_every_real_set_of_every_system_passes_the_new_checks(rel):
    ephs = [
        e for items in read_nav(DATA / rel, systems=("C", "G", "E")).ephemerides.values()
        for e in items
    ]  # fmt: skip
    assert ephs
    checks = {_check(e) for e in ephs}
    assert checks <= {None, "unhealthy"}, checks


def test_gpst_time_of_week_to_bdt_wraps_only_a_time_of_the_week():
    assert gpst_sow_to_bdt_sow(100.0) == 86.0
    assert gpst_sow_to_bdt_sow(5.0) == 604_791.0  # the end of BDT's previous week
    assert gpst_sow_to_bdt_sow(604_799.0) == 604_785.0
    # beyond the week: as it is (16 bits x 16 s reach 1,048,560 s), for the store to refuse
    for t in (604_800.0, 604_810.0, 1_048_560.0, 4_294_967_295.0, -1.0):
        assert gpst_sow_to_bdt_sow(t) == t
    assert math.isnan(gpst_sow_to_bdt_sow(math.nan))


def test_toc_hours_from_toe_is_refused_across_the_week_end_too(sets):
    eph = sets["G"]
    toe = eph.toe_sow_s
    assert _check(dataclasses.replace(eph, toc_sow_s=toe + 4 * 3600.0)) is None
    assert _check(dataclasses.replace(eph, toc_sow_s=toe + 4 * 3600.0 + 16.0)) == "toc_toe"
    assert _check(dataclasses.replace(eph, toc_sow_s=toe - 5 * 3600.0)) == "toc_toe"
    near_end = dataclasses.replace(eph, toe_sow_s=604_000.0, toc_sow_s=604_000.0)
    assert _check(near_end) is None
    assert _check(dataclasses.replace(near_end, toc_sow_s=800.0)) is None  # 1600 s on
    assert _check(dataclasses.replace(near_end, toc_sow_s=20_000.0)) == "toc_toe"
    assert _check(dataclasses.replace(near_end, toc_sow_s=604_800.0)) == "time_of_week"


def test_a_refused_clock_never_replaces_the_held_set(sets):
    store = EphemerisStore()
    eph = sets["E"]
    assert store.add(eph)
    assert not store.add(dataclasses.replace(eph, af0_s=1e10))
    assert store.refused_by_reason["clock"] == 1
    assert store.select(eph.prn, eph.week, eph.toe_sow_s) is eph


# --- end to end on damaged copies of real recordings -------------------------------------------


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "service", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )


def _fixes(path: Path) -> dict[tuple[int, float], dict]:
    recs = [json.loads(line) for line in path.read_text().splitlines()]
    return {
        (r["gpst_week"], r["gpst_tow_s"]): r
        for r in recs
        if r["class"] == "FIX" and r.get("x_ecef_m") is not None
    }


def _replay(source: Path, out: Path, *extra: str) -> dict[tuple[int, float], dict]:
    run = _run(
        "replay", str(source), *extra, "--max-speed", "--nmea-out", "/dev/null",
        "--systems", "C,G,E", "--jsonl-out", str(out),
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert "Traceback" not in run.stderr
    return _fixes(out)


GPSNAV = 5891
GPSNAV_PRN, GPSNAV_TOC, GPSNAV_AF0 = 14, 32, 44  # byte offsets in the block (SBF reference)


def _damaged_sbf(out: Path, prn: int | None, fmt: str, offset: int, value: float) -> int:
    """Copy of the Leuven SBF with ``value`` packed at ``offset`` of the GPSNav blocks of
    ``prn`` (None: all), CRC recomputed; returns the number of blocks damaged."""
    only = None if prn is None else (lambda block: block[GPSNAV_PRN] == prn)
    return edit_sbf_field(LEUVEN_SBF, out, GPSNAV, offset, fmt, lambda _old: value, only)


def _gpsnav_fields(path: Path) -> list[tuple[int, float, float]]:
    """(PRN, a_f0, t_oc) of each GPSNav block as pysbf2 reads it (the offsets' witness)."""
    with path.open("rb") as fh:
        return [
            (int(m.PRN), float(m.a_f0), float(m.t_oc))
            for _raw, m in SBFReader(fh, quitonerror=0)
            if m is not None and m.identity == "GPSNav"
        ]


@pytest.fixture(scope="module")
def clean_sbf(tmp_path_factory):
    fixes = _replay(LEUVEN_SBF, tmp_path_factory.mktemp("sbf") / "clean.jsonl")
    assert len(fixes) == 12  # DATA/README.md: 12 MeasEpoch
    return fixes


@pytest.mark.parametrize(
    ("case", "prn", "fmt", "offset", "value", "counter"),
    [
        ("G05 a_f0 1e10 s", 5, "<f", GPSNAV_AF0, 1e10, "ephemeris_refused_clock"),
        # no time of week: no set, as RTCM 1019 (drivers.sbf; before: the store's
        # ephemeris_refused_time_of_week)
        ("every t_oc 0xFFFFFFFF", None, "<I", GPSNAV_TOC, 0xFFFFFFFF, "source_eph_bad_toe"),
    ],
)
def test_sbf_damaged_gps_set_is_refused_and_every_epoch_still_fixes(
    clean_sbf, tmp_path, case, prn, fmt, offset, value, counter
):
    damaged = tmp_path / "damaged.sbf"
    n = _damaged_sbf(damaged, prn, fmt, offset, value)
    assert n >= 1
    before = _gpsnav_fields(LEUVEN_SBF)
    after = _gpsnav_fields(damaged)
    assert len(before) == len(after) == 18  # DATA/README.md: GPSNav x18
    hit = [a for a in after if prn is None or a[0] == prn]
    assert len(hit) == n
    field = 1 if offset == GPSNAV_AF0 else 2
    assert all(a[field] == pytest.approx(value) for a in hit)
    fixes = _replay(damaged, tmp_path / "damaged.jsonl")
    assert fixes.keys() == clean_sbf.keys()
    run = replay_with_status(damaged, "--systems", "C,G,E", "--nmea-out", "/dev/null")
    assert run.rc == 0, run.stderr
    counters = run.final["counters"]
    assert counters[counter] == n


def test_rinex_every_galileo_af0_1e10_is_refused_and_every_epoch_still_fixes(tmp_path):
    clean = _replay(HKSC_OBS, tmp_path / "clean.jsonl", "--nav", str(HKSC_NAV))
    assert len(clean) == 205  # DATA/README.md: 205 epochs
    lines = HKSC_NAV.read_text().splitlines(keepends=True)
    body = next(i for i, line in enumerate(lines) if "END OF HEADER" in line) + 1
    n = 0
    for i in range(body, len(lines)):
        if lines[i][:1] == "E" and lines[i][1:3].isdigit():
            # RINEX 3.04 SV / EPOCH / SV CLK: A1,I2.2,1X,I4,5(1X,I2.2), then 3D19.12 (af0 first)
            lines[i] = lines[i][:23] + " 1.000000000000D+10" + lines[i][42:]
            n += 1
    assert n > 0
    nav = tmp_path / "damaged.nav"
    nav.write_text("".join(lines))
    assert {e.af0_s for items in read_nav(nav, systems=("E",)).ephemerides.values()
            for e in items} == {1e10}  # fmt: skip
    fixes = _replay(HKSC_OBS, tmp_path / "damaged.jsonl", "--nav", str(nav))
    assert fixes.keys() == clean.keys()


def test_rtcm_1019_toc_beyond_the_week_gives_no_set_and_every_epoch_still_fixes(tmp_path):
    clean = _replay(HIROSHIMA, tmp_path / "clean.jsonl")
    assert len(clean) == 54
    damaged = tmp_path / "toc.rtcm"
    # 1019 (RTCM 10403.3 Table 3.5-21): number 12, DF009 6, DF076 10, DF077 4, DF078 2,
    # DF079 14, DF071 8 bits, then DF081 (t_oc, 16 bits x 16 s) at bit 56
    n = edit_rtcm_field(HIROSHIMA, damaged, 1019, 56, 16, lambda _: 0xFFFF)
    assert n == 22  # DATA/README.md's GPS ephemerides: 22 x 1019
    with damaged.open("rb") as fh:
        tocs = {
            float(m.DF081) for _raw, m in RTCMReader(fh, quitonerror=0)
            if m is not None and m.identity == "1019"
        }  # fmt: skip
    assert tocs == {0xFFFF * 16.0}
    fixes = _replay(damaged, tmp_path / "damaged.jsonl")
    assert fixes.keys() == clean.keys()
    run = replay_with_status(damaged, "--systems", "C,G,E", "--nmea-out", "/dev/null")
    counters = run.final["counters"]
    # once per message, though it is looked at for the week and for the set (driver counters
    # are published with the source_ prefix; before: 2 * n)
    assert counters["source_eph_bad_toe"] == n
    assert counters.get("source_ephemerides_rtcm_G", 0) == 0
    assert counters.get("source_eph_week_1019", 0) == 0


@pytest.mark.parametrize("systems", ["C", "C,G,E"])
def test_rtcm_one_1019_toe_beyond_the_week_is_counted_once(tmp_path, systems):
    """One 1019 with t_oe = 0xFFFF x 16 s: ``eph_bad_toe`` 1 (before: 2 when GPS is asked
    for, the message read for the stream's week and again for the set), that set alone
    missing, and no week from it."""
    damaged = tmp_path / "toe.rtcm"
    changed: list[int] = []

    def first_only(old: int) -> int:
        changed.append(old)
        return 0xFFFF if len(changed) == 1 else old

    # 1019 (RTCM 10403.3 Table 3.5-21): DF081 (t_oc) 16 bits at 56, DF082 8, DF083 16,
    # DF084 22, DF085 10, DF086 16, DF087 16, DF088 32, DF089 16, DF090 32, DF091 16,
    # DF092 32, then DF093 (t_oe, 16 bits x 16 s) at bit 288
    assert edit_rtcm_field(HIROSHIMA, damaged, 1019, 288, 16, first_only) == 22
    with damaged.open("rb") as fh:
        toes = [
            float(m.DF093) for _raw, m in RTCMReader(fh, quitonerror=0)
            if m is not None and m.identity == "1019"
        ]  # fmt: skip
    assert toes[0] == 0xFFFF * 16.0 and all(0 <= t < 604_800 for t in toes[1:])
    counts = {}
    for path in (HIROSHIMA, damaged):
        src = open_source(str(path), systems=frozenset(systems.split(",")))
        for _event in src:
            pass
        counts[path] = src.counters
    clean, hurt = counts[HIROSHIMA], counts[damaged]
    assert clean["eph_bad_toe"] == 0 and hurt["eph_bad_toe"] == 1
    assert hurt["eph_week_1019"] == clean["eph_week_1019"] - 1 == 21
    if "G" in systems:
        assert hurt["ephemerides_rtcm_G"] == clean["ephemerides_rtcm_G"] - 1 == 21
