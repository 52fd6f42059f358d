"""``bdsfix sub`` with no publisher: says what it waits for, idles, and SIGTERM ends it
with 0 (tests/system/test_service_io.py covers it with bdsfix as the publisher); its
topics, ``--json`` and endpoint checks against a real PUB socket."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

from tests.support.paths import ROOT

HANG_S = 120.0
"""Only a hung ``sub`` reaches this."""


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


class _Publisher:
    """A real ZeroMQ PUB socket on a loopback port, sending a FIX and a SKY record every
    20 ms from a thread until closed (a subscriber joins whenever it connects)."""

    def __init__(self) -> None:
        import zmq

        self.ctx = zmq.Context()
        self.sock = self.ctx.socket(zmq.PUB)
        self.sock.setsockopt(zmq.LINGER, 0)
        self.endpoint = self.sock.bind_to_random_port("tcp://127.0.0.1")
        self.stop = threading.Event()
        self.sent: list[dict] = []
        self.thread = threading.Thread(target=self._send, daemon=True)
        self.thread.start()

    def _send(self) -> None:
        k = 0
        while not self.stop.wait(0.02):
            fix = {"class": "FIX", "mode": "fast", "seq": k}
            sky = {"class": "SKY", "seq": k}
            self.sent += [fix, sky]
            self.sock.send_multipart([b"FIX", json.dumps(fix).encode()])
            self.sock.send_multipart([b"SKY", json.dumps(sky).encode()])
            k += 1

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.sock.close()
        self.ctx.term()


def _sub(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "service", "sub", *args],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=HANG_S,
    )


def test_sub_takes_a_topic_in_any_case_and_json_prints_lines_for_jq():
    """``--topic fix`` (lower case) gets the FIX records (it waited forever: issue 23);
    ``--json`` prints each record alone, one JSON object per line."""
    pub = _Publisher()
    try:
        got = _sub(f"tcp://127.0.0.1:{pub.endpoint}", "--topic", "fix", "--count", "3", "--json")
        tagged = _sub(f"tcp://127.0.0.1:{pub.endpoint}", "--topic", "Sky", "--count", "1")
    finally:
        pub.close()
    assert got.returncode == 0, got.stderr
    lines = got.stdout.splitlines()
    assert len(lines) == 3
    records = [json.loads(line) for line in lines]  # each line a whole JSON object
    assert all(r["class"] == "FIX" for r in records)
    assert all(r in pub.sent for r in records)
    assert tagged.returncode == 0, tagged.stderr
    topic, body = tagged.stdout.splitlines()[0].split(" ", 1)
    assert topic == "SKY" and json.loads(body)["class"] == "SKY"


def test_sub_refuses_an_unknown_topic_with_the_list():
    run = _sub("tcp://127.0.0.1:9", "--topic", "fixes", "--count", "1")
    assert run.returncode == 2
    assert "'fixes'" in run.stderr and "FIX, SKY, TRACK, STATUS" in run.stderr
    assert len(run.stderr.splitlines()) == 1


def test_sub_without_a_transport_suggests_tcp():
    run = _sub("127.0.0.1:10111", "--count", "1")
    assert run.returncode == 2
    assert "tcp://127.0.0.1:10111" in run.stderr and "Invalid argument" not in run.stderr
