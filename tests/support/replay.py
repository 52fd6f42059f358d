"""``bdsfix replay`` in a subprocess with a ZeroMQ STATUS subscriber that gets every STATUS,
the last one (sent at shutdown) included, whatever the machine's load.

A PUB socket drops what it sends before a subscription has reached it, and a short replay
at full speed can be over before a subscriber connected. So:

- a binary capture goes through the replay's stdin: the replay publishes STATUS while it
  waits for its first byte, and the capture is written only once a STATUS has arrived: the
  subscription is in place before any data (and so before the last STATUS);
- RINEX, which the replay reads from a file only, is paced (``--speed``), so the run lasts
  seconds rather than the milliseconds a subscription takes; :attr:`StatusRun.final` fails
  with a clear message if not a single STATUS arrived;
- at exit the publisher flushes what it sent (``ZmqPublisher.close``), and the subscriber
  reads until its socket monitor reports the publisher's disconnect: everything sent before
  the exit has then been read.

Timeouts here only stop a hung run; nothing is judged by the time it took.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zmq
from zmq.utils.monitor import recv_monitor_message

from tests.support.paths import ROOT

HANG_S = 120.0
"""How long a replay may run (or keep a subscriber waiting) before it counts as hung."""
STATUS_INTERVAL_S = 0.1
RINEX_SPEED = 100.0
"""Pace of a RINEX replay with a subscriber: a 1 Hz file of 200 epochs lasts 2 s."""


@dataclass
class StatusRun:
    rc: int
    stdout: str
    stderr: str
    statuses: list[dict] = field(default_factory=list)
    records: list[tuple[str, dict]] = field(default_factory=list)

    @property
    def final(self) -> dict:
        """The STATUS sent at shutdown (the last one received: none is lost after the first)."""
        assert self.statuses, (
            "no STATUS received: the subscription never reached the replay before it ended\n"
            + self.stderr[-2000:]
        )
        return self.statuses[-1]


def is_rinex_obs(path: Path) -> bool:
    return re.search(r"\.(obs|rnx|\d\do)$", path.name.lower()) is not None


class LiveReplay:
    """``python -m service ARGS --zmq ipc://... --status-interval-s 0.1`` with a subscriber.

    ``stdin=True``: the source is ``-`` and :meth:`feed` writes it. ``topics``: what the
    subscriber takes (STATUS; ``b""`` for every record), kept in :attr:`records`. Use as a
    context manager (the process is killed and the sockets closed on the way out).
    """

    def __init__(
        self, args: list[str], *, stdin: bool = False, topics: tuple[bytes, ...] = (b"STATUS",)
    ) -> None:
        self._dir = Path(tempfile.mkdtemp(prefix="bdsfix-st-"))  # short: ipc paths <= 107 B
        endpoint = f"ipc://{self._dir / 'pub'}"
        self.statuses: list[dict] = []
        self.records: list[tuple[str, dict]] = []
        self._connects = self._disconnects = 0  # of the subscriber to the replay
        ctx = zmq.Context.instance()
        self._sub = ctx.socket(zmq.SUB)
        self._sub.setsockopt(zmq.LINGER, 0)
        self._sub.setsockopt(zmq.RECONNECT_IVL, 5)  # connects as soon as the replay binds
        self._sub.setsockopt(zmq.RCVHWM, 0)
        for topic in topics:
            self._sub.setsockopt(zmq.SUBSCRIBE, topic)
        self._mon = self._sub.get_monitor_socket(zmq.EVENT_CONNECTED | zmq.EVENT_DISCONNECTED)
        self._sub.connect(endpoint)
        self._out = (self._dir / "stdout").open("wb")
        self._err = (self._dir / "stderr").open("wb")
        argv = [sys.executable, "-m", "service", *args, "--zmq", endpoint]
        argv += ["--status-interval-s", str(STATUS_INTERVAL_S)]
        self.proc = subprocess.Popen(
            argv,
            cwd=ROOT,
            stdin=subprocess.PIPE if stdin else subprocess.DEVNULL,
            stdout=self._out,
            stderr=self._err,
        )
        self._writer: threading.Thread | None = None

    def __enter__(self) -> LiveReplay:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()
        if self._writer is not None:
            self._writer.join(timeout=10)
        self._sub.disable_monitor()
        self._mon.close(0)
        self._sub.close(0)
        self._out.close()
        self._err.close()
        shutil.rmtree(self._dir, ignore_errors=True)

    def stderr(self) -> str:
        return (self._dir / "stderr").read_text(errors="replace")

    def _pump(self, timeout_ms: int) -> None:
        """Take in the STATUS records and monitor events that arrive within ``timeout_ms``."""
        poller = zmq.Poller()
        poller.register(self._sub, zmq.POLLIN)
        poller.register(self._mon, zmq.POLLIN)
        for sock, _ in poller.poll(timeout_ms):
            if sock is self._mon:
                while self._mon.poll(0):
                    event = recv_monitor_message(self._mon)["event"]
                    self._connects += event == zmq.EVENT_CONNECTED
                    self._disconnects += event == zmq.EVENT_DISCONNECTED
            else:
                while self._sub.poll(0):
                    topic, body = self._sub.recv_multipart()
                    rec = json.loads(body)
                    self.records.append((topic.decode("ascii"), rec))
                    if topic == b"STATUS":
                        self.statuses.append(rec)

    def wait_status(self, pred: Callable[[dict], Any], what: str) -> dict:
        """The first STATUS (from now on) for which ``pred`` holds; fails if the process ends
        or nothing comes for ``HANG_S``."""
        seen = len(self.statuses)
        deadline = time.monotonic() + HANG_S
        while True:
            for rec in self.statuses[seen:]:
                if pred(rec):
                    return rec
            seen = len(self.statuses)
            if self.proc.poll() is not None:
                self._drain()  # everything it sent before it ended
                for rec in self.statuses[seen:]:
                    if pred(rec):
                        return rec
                raise AssertionError(
                    f"the replay ended (exit {self.proc.returncode}) before {what}:\n"
                    + self.stderr()[-2000:]
                )
            assert time.monotonic() < deadline, f"hung: no {what} within {HANG_S:.0f} s"
            self._pump(100)

    def feed(self, data: bytes) -> None:
        """Write ``data`` to the replay's stdin (a thread) and close it: the end of the input."""
        stdin = self.proc.stdin
        assert stdin is not None

        def write() -> None:
            try:
                stdin.write(data)
                stdin.close()
            except BrokenPipeError:  # the replay stopped reading; its exit status tells why
                pass

        self._writer = threading.Thread(target=write, daemon=True)
        self._writer.start()

    def _drain(self) -> None:
        """After the exit: read until the publisher's connection has closed, so that all it
        sent has been read (the stream delivers every message before the close)."""
        deadline = time.monotonic() + HANG_S
        self._pump(100)
        # a STATUS received means a connection, whose events may still be on their way
        while self._disconnects < max(self._connects, bool(self.statuses)):
            assert time.monotonic() < deadline, "the publisher's disconnect never arrived"
            self._pump(100)
        while self._sub.poll(100):
            self._pump(0)

    def finish(self) -> StatusRun:
        """Wait for the exit, then read until the publisher's disconnect: every STATUS."""
        deadline = time.monotonic() + HANG_S
        while self.proc.poll() is None:
            if time.monotonic() > deadline:
                self.proc.kill()
                raise AssertionError(f"replay hung (> {HANG_S:.0f} s):\n{self.stderr()[-2000:]}")
            self._pump(100)
        self._drain()
        self._out.flush()
        self._err.flush()
        return StatusRun(
            self.proc.returncode,
            (self._dir / "stdout").read_text(errors="replace"),
            self.stderr(),
            list(self.statuses),
            list(self.records),
        )


def replay_with_status(source: Path, *args: str) -> StatusRun:
    """``bdsfix replay SOURCE ARGS`` with every STATUS it publishes (see the module doc):
    binary captures through stdin at full speed, RINEX from the file paced at
    ``RINEX_SPEED``."""
    if is_rinex_obs(source):
        with LiveReplay(["replay", str(source), *args, "--speed", str(RINEX_SPEED)]) as run:
            return run.finish()
    with LiveReplay(["replay", "-", *args, "--max-speed"], stdin=True) as run:
        run.wait_status(lambda rec: True, "a STATUS before the data")
        run.feed(source.read_bytes())
        return run.finish()
