"""``bdsfix sub`` with no publisher: says what it waits for, idles, and SIGTERM ends it
with 0 (tests/system/test_service_io.py covers it with a publisher)."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

from tests.support.paths import ROOT


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu_s(pid: int) -> float:
    stat = Path(f"/proc/{pid}/stat").read_text(encoding="ascii")
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def test_sub_without_publisher_says_so_idles_and_exits_0_on_sigterm():
    endpoint = f"tcp://127.0.0.1:{_free_port()}"
    proc = subprocess.Popen(
        [sys.executable, "-m", "service", "sub", endpoint],
        cwd=ROOT,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        line = proc.stderr.readline()  # blocks until the notice (or the process dies)
        assert "no message from" in line and endpoint in line and "bdsfix replay --zmq" in line
        cpu0 = _cpu_s(proc.pid)
        time.sleep(2.0)  # sample its CPU time over a while: not a deadline
        assert _cpu_s(proc.pid) - cpu0 < 0.2  # idles: no busy polling or reconnect storm
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.stdout.read() == ""
