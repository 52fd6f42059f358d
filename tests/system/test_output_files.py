"""Output files and the state directory through the real commands (as root a symlink at an
output path would let bdsfix truncate or append to any file; a umask of 000 would leave
world-writable outputs): a symlink is refused with one line and exit 3 and its target is
untouched; under umask 000 new outputs are 0644 and a new state directory 0700; an existing
state directory open to others is kept, with a warning."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.captures import ubx_poll_capture
from tests.support.paths import DATA, ROOT

BDSFIX = [sys.executable, "-m", "service"]
HK = DATA / "hksc-2021"
INPUT = 3  # README "Exit codes", written out rather than imported from the code under test
QUIET = ["--nmea-tcp", "", "--zmq", ""]


def _bdsfix(cwd: Path, *argv: str, mask: int | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [*BDSFIX, *argv],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
        preexec_fn=None if mask is None else (lambda: os.umask(mask)),
    )


@pytest.fixture
def capture(tmp_path: Path) -> Path:
    return ubx_poll_capture(tmp_path / "capture.ubx")


def _mode(p: Path) -> int:
    return stat.S_IMODE(p.stat().st_mode)


def _refused(proc: subprocess.CompletedProcess[str], link: Path) -> None:
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == INPUT, proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(lines) == 1 and "error:" in lines[0], proc.stderr
    assert str(link) in lines[0] and "symlink" in lines[0], lines[0]


def _planted(tmp_path: Path, name: str) -> tuple[Path, Path]:
    target = tmp_path / "precious"
    target.write_text("root's file\n")
    link = tmp_path / name
    link.symlink_to(target)
    return link, target


def test_replay_jsonl_out_through_a_symlink_is_refused(tmp_path, capture):
    link, target = _planted(tmp_path, "fixes.jsonl")
    proc = _bdsfix(tmp_path, "replay", str(capture), "--max-speed", "--jsonl-out", str(link))
    _refused(proc, link)
    assert target.read_text() == "root's file\n"


def test_solve_out_through_a_symlink_is_refused(tmp_path):
    link, target = _planted(tmp_path, "fixes.csv")
    obs, nav = str(HK / "hksc1610.obs"), str(HK / "hksc1610.nav")
    proc = _bdsfix(tmp_path, "solve", obs, nav, "--format", "csv", "--out", str(link))
    _refused(proc, link)
    assert target.read_text() == "root's file\n"


def test_run_nmea_out_through_a_symlink_is_refused(tmp_path, capture):
    link, target = _planted(tmp_path, "fixes.nmea")
    state = tmp_path / "state"
    proc = _bdsfix(
        tmp_path,
        "run",
        "--source",
        str(capture),
        *QUIET,
        "--state-dir",
        str(state),
        "--nmea-out",
        str(link),
    )
    _refused(proc, link)
    assert target.read_text() == "root's file\n"


def test_modes_under_umask_000(tmp_path, capture):
    """Outputs of run, replay and solve 0644; the daemon's new state directory 0700."""
    state = tmp_path / "deeper" / "state"
    run_argv = ["run", "--source", str(capture), *QUIET, "--state-dir", str(state)]
    run_out = [tmp_path / "run.nmea", tmp_path / "run.jsonl"]
    proc = _bdsfix(
        tmp_path,
        *run_argv,
        "--nmea-out",
        str(run_out[0]),
        "--jsonl-out",
        str(run_out[1]),
        "--log-level",
        "error",
        mask=0,
    )
    assert proc.returncode == 0, proc.stderr
    replay_out = [tmp_path / "replay.nmea", tmp_path / "replay.jsonl"]
    proc = _bdsfix(
        tmp_path,
        "replay",
        str(capture),
        "--max-speed",
        "--nmea-out",
        str(replay_out[0]),
        "--jsonl-out",
        str(replay_out[1]),
        mask=0,
    )
    assert proc.returncode == 0, proc.stderr
    solve_out = tmp_path / "solve.csv"
    obs, nav = str(HK / "hksc1610.obs"), str(HK / "hksc1610.nav")
    proc = _bdsfix(tmp_path, "solve", obs, nav, "--format", "csv", "--out", str(solve_out), mask=0)
    assert proc.returncode == 0, proc.stderr
    for p in [*run_out, *replay_out, solve_out]:
        assert p.is_file() and _mode(p) == 0o644, (p, oct(_mode(p)))
    assert _mode(state) == 0o700


def test_an_existing_wide_state_dir_is_kept_with_a_warning(tmp_path, capture):
    state = tmp_path / "state"
    state.mkdir()
    state.chmod(0o777)
    proc = _bdsfix(tmp_path, "run", "--source", str(capture), *QUIET, "--state-dir", str(state))
    assert proc.returncode == 0, proc.stderr
    assert _mode(state) == 0o777
    warned = [ln for ln in proc.stderr.splitlines() if "state directory" in ln]
    assert len(warned) == 1 and "0777" in warned[0] and "WARNING" in warned[0], proc.stderr
