"""What every recording in ``../shared/data`` tells its user at the end, pinned as goldens.

Each file of the data directory is classified in :data:`RECORDINGS`: a capture replayed by
``test_replay_golden`` (whose ``.summary`` goldens pin the replay summary), a RINEX obs file
solved here (``solve-<name>.summary``), a file the service cannot read (its one error line,
``refused-<name>.summary``), or not a receiver stream (nav files, ground truth, sky masks).
A new recording fails :func:`test_every_recording_is_classified` until it is added, so no
recording goes without a golden of what a user is told about it.

``bdsfix run`` on a file source ends with the same summary as ``replay``; a few captures pin
it too (``run-<name>.summary``). ``pytest --regen-golden`` rewrites these files.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

import pytest

from service.commands.cli import main
from service.core.declines import Decline, hint
from tests.support.paths import DATA, GOLDEN
from tests.system.test_replay_golden import CASES as REPLAY_CASES


@dataclass(frozen=True)
class Solve:
    obs: str
    nav: str
    note: str


SOLVES = {
    "hksc-rinex": Solve(
        "hksc-2021/hksc1610.obs", "hksc-2021/hksc1610.nav", "reference station, 5 GEOs"
    ),
    "hksc-f9p": Solve(
        "hksc-2021/20210610.klt1.ublox.f9p.obs",
        "hksc-2021/hksc1610.nav",
        "u-blox F9P beside the station: SPP, some epochs over the PDOP gate",
    ),
    "polyu-f9p": Solve(
        "hk-polyu-f9p-ubx-2024/gnss_log_2024_09_25_15_24_49.24o",
        "hk-polyu-f9p-ubx-2024/hksc269h.24f",
        "F9P RINEX with fewer than 4 GEOs: SPP only, the fast fix declined too_few_full",
    ),
    "tst-urban": Solve(
        "hk-tst-urban-2019/COM3_190428_124409.obs",
        "hk-tst-urban-2019/hksc1180.19b",
        "urban drive: declines of every kind and fault exclusions",
    ),
    "urban-3geo": Solve(
        "hk-urban-3geo-2020/rover.obs",
        "hk-urban-3geo-2020/navigation_message.nav",
        "3 GEOs: SPP only",
    ),
}
"""RINEX obs files solved with ``--mode both`` (paths relative to ``../shared/data``)."""

REFUSED_SOLVES = {
    "twtf-wrong-nav": Solve(
        "twtf-septentrio-2023/TWTF00TWN_R_20232490000_01D_30S_MO.rnx",
        "hksc-2021/hksc1610.nav",
        "no nav of its day in the data: refused naming both dates",
    ),
}
"""RINEX obs files ``solve`` refuses with one line and exit 3 (with the nav file given)."""

REFUSED = {
    "android-beijing": "android-beijing-mi8-2022/gnss_log_2022_09_28_22_01_27.txt",
    "perth-nav-as-capture": "android-perth-s8-2017/PERT00AUS_R_20172780000_01D_MN.rnx",
}
"""Files ``replay`` refuses with one line and exit 3 (a GnssLogger log without ``--nav``:
the hint names its day's nav file, none of which is in the data; a nav file is not an
observation file)."""

AUXILIARY = {
    "README.md": "the data's description",
    "hk-polyu-f9p-ubx-2024/hksc269h.24m": "nav (mixed), unused: the .24f BDS nav is used",
    "hk-polyu-f9p-ubx-2024/hksc269h.24n": "nav (GPS)",
    "hk-tst-urban-2019/groundTruth_TST.csv": "ground truth (bench/bench_urban.py)",
    "hk-tst-urban-2019/hksc1180.19n": "nav (GPS)",
    "hk-urban-3geo-2020/skymask.csv": "sky mask",
}
"""Files that are not receiver streams and are not used as a nav file above."""

RUNS = ["hiroshima-rtcm", "polyu-f9p-ubx", "tiny-rawx"]
"""Replay cases also run through ``bdsfix run`` with the capture as its source."""


def _files_used() -> set[str]:
    used = {c.args[0] for c in REPLAY_CASES.values()}
    used |= {a for c in REPLAY_CASES.values() for a in c.args[1:] if "/" in a}
    solves = [*SOLVES.values(), *REFUSED_SOLVES.values()]
    used |= {s.obs for s in solves} | {s.nav for s in solves}
    return used | set(REFUSED.values()) | set(AUXILIARY)


def test_every_recording_is_classified():
    present = {str(p.relative_to(DATA)) for p in DATA.rglob("*") if p.is_file()}
    unclassified = sorted(present - _files_used())
    assert not unclassified, f"add these recordings to a golden table: {unclassified}"
    missing = sorted(_files_used() - present)
    assert not missing, f"recordings named in the tables but not in ../shared/data: {missing}"


def _block(stderr: str, command: str) -> str:
    """The ``bdsfix COMMAND: N epochs`` line and the indented lines after it."""
    lines = stderr.splitlines()
    start = next(i for i, x in enumerate(lines) if re.match(rf"bdsfix {command}: \d+ epochs", x))
    block = [lines[start], *(x for x in lines[start + 1 :] if x.startswith("  "))]
    return "\n".join(block) + "\n"


def _check(request, path, text: str) -> None:
    if request.config.getoption("--regen-golden"):
        path.write_text(text)
        pytest.skip(f"{path.name} regenerated")
    assert path.exists(), f"{path.name} missing: pytest --regen-golden"
    assert text == path.read_text(), f"{path.name} differs: regenerate and say why"


@pytest.mark.parametrize("name", sorted(SOLVES))
def test_solve_summary_matches_golden(name, request, capsys, tmp_path):
    case = SOLVES[name]
    args = ["solve", str(DATA / case.obs), str(DATA / case.nav), "--mode", "both"]
    assert main([*args, "--out", str(tmp_path / "out.jsonl")]) == 0
    summary = _block(capsys.readouterr().err, "solve")
    _check(request, GOLDEN / f"solve-{name}.summary", summary)
    # every solver that declined says why, in words, and what would help
    for solver in ("fast", "spp"):
        if f"{solver} solver declined:" in summary:
            assert f"{solver} solver hint:" in summary, summary


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_unreadable_recording_is_one_line_and_exit_3(name, request, capsys):
    path = DATA / REFUSED[name]
    assert main(["replay", str(path), "--max-speed"]) == 3
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("bdsfix replay: error: "), err
    _check(request, GOLDEN / f"refused-{name}.summary", err.replace(str(DATA), "DATA"))


@pytest.mark.parametrize("name", sorted(REFUSED_SOLVES))
def test_refused_solve_is_one_line_and_exit_3(name, request, capsys, tmp_path):
    case = REFUSED_SOLVES[name]
    args = ["solve", str(DATA / case.obs), str(DATA / case.nav), "--mode", "both"]
    assert main([*args, "--out", str(tmp_path / "out.jsonl")]) == 3
    err = capsys.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith("bdsfix solve: error: "), err
    _check(request, GOLDEN / f"refused-solve-{name}.summary", err.replace(str(DATA), "DATA"))


@pytest.mark.parametrize("name", RUNS)
def test_run_on_a_capture_ends_with_the_replay_summary(name, request, capsys, tmp_path):
    """``bdsfix run --source FILE`` reads the capture to its end and prints the summary
    ``replay`` prints, timeline included, from the same counters; a hint that names a flag
    of replay's names run's way instead (run has no ``--gps-week``)."""
    case = REPLAY_CASES[name]
    capture, *rest = [str(DATA / a) if "/" in a else a for a in case.args]
    args = ["run", "--source", capture, "--state-dir", str(tmp_path / "state")]
    args += ["--nmea-tcp", "", "--zmq", "", *rest]
    assert main(args) == 0
    summary = _block(capsys.readouterr().err, "run")
    _check(request, GOLDEN / f"run-{name}.summary", summary)
    replayed = (GOLDEN / f"{name}.summary").read_text().splitlines()
    own = {f"  hint: {hint(c)}": f"  hint: {hint(c, 'run')}" for c in Decline if hint(c)}
    want = [replayed[0].replace("replay", "run", 1), *(own.get(x, x) for x in replayed[1:])]
    assert summary.splitlines() == want
    assert "give --gps-week" not in summary
