"""One daemon per state directory (issue 23): two real ``bdsfix run`` processes on one state
directory; the second exits 3 with one line naming the first's pid, the first runs on, and
once it has stopped a new daemon takes the directory. Timeouts only stop a hung run."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from service.daemon.statelock import LOCK_NAME
from tests.support.paths import ROOT

HANG_S = 60.0
BDSFIX = [sys.executable, "-m", "service"]


def _daemon(tty: str, state: Path, log: Path) -> subprocess.Popen[bytes]:
    """``bdsfix run`` reading a pty (it waits there), no output, logs to ``log``."""
    argv = [*BDSFIX, "run", "--source", tty, "--state-dir", str(state)]
    argv += ["--nmea-tcp", "", "--zmq", ""]
    with log.open("wb") as err:
        return subprocess.Popen(argv, cwd=ROOT, stdout=subprocess.DEVNULL, stderr=err)


def _wait_running(proc: subprocess.Popen[bytes], log: Path) -> None:
    deadline = time.monotonic() + HANG_S
    while "bdsfix running" not in log.read_text():
        assert proc.poll() is None, f"the daemon ended: {log.read_text()[-2000:]}"
        assert time.monotonic() < deadline, f"hung: not running within {HANG_S:.0f} s"
        time.sleep(0.05)


def _stop(proc: subprocess.Popen[bytes]) -> int:
    proc.send_signal(signal.SIGTERM)
    return proc.wait(timeout=HANG_S)


def test_a_second_daemon_on_the_same_state_directory_exits_3_in_one_line(tmp_path):
    state = tmp_path / "state"
    master, slave = os.openpty()
    tty = os.ttyname(slave)
    first = _daemon(tty, state, tmp_path / "first.log")
    try:
        _wait_running(first, tmp_path / "first.log")
        argv = ["run", "--source", tty, "--state-dir", str(state), "--nmea-tcp", "", "--zmq", ""]
        second = subprocess.run(
            [*BDSFIX, *argv],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=HANG_S,
        )
        assert second.returncode == 3, second.stderr
        lines = second.stderr.strip().splitlines()
        assert len(lines) == 1, lines
        assert "in use by another bdsfix" in lines[0] and f"pid {first.pid}" in lines[0]
        assert str(state) in lines[0]
        assert first.poll() is None  # the first runs on
        assert (state / LOCK_NAME).read_text().strip() == str(first.pid)
    finally:
        rc = _stop(first)
    assert rc == 0, (tmp_path / "first.log").read_text()[-2000:]
    # the first has gone: its lock went with it, and a new daemon takes the directory
    third = _daemon(tty, state, tmp_path / "third.log")
    try:
        _wait_running(third, tmp_path / "third.log")
    finally:
        assert _stop(third) == 0
        os.close(master)
        os.close(slave)


def test_a_killed_daemon_leaves_no_stale_lock(tmp_path):
    """SIGKILL (a crash): the kernel drops the flock with the process; the lock file stays,
    naming a dead pid, and does not keep the next daemon out."""
    state = tmp_path / "state"
    master, slave = os.openpty()
    tty = os.ttyname(slave)
    first = _daemon(tty, state, tmp_path / "first.log")
    try:
        _wait_running(first, tmp_path / "first.log")
    finally:
        first.kill()
        first.wait(timeout=HANG_S)
    assert (state / LOCK_NAME).exists()
    second = _daemon(tty, state, tmp_path / "second.log")
    try:
        _wait_running(second, tmp_path / "second.log")
        assert (state / LOCK_NAME).read_text().strip() == str(second.pid)
    finally:
        assert _stop(second) == 0
        os.close(master)
        os.close(slave)
