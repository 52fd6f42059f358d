"""The connection-flood harness of bench/bench_flood.py and tests/system/test_flood.py:
`bdsfix run` fed a simulated receiver over TCP while this process floods its NMEA TCP port.

- the daemon runs with the usual soft descriptor limit (1024, set in the child), the NMEA
  TCP cap given (``--nmea-tcp-max-clients``), JSONL to a file and ZeroMQ for STATUS;
- one healthy NMEA client connects first and reads everything; its GGA are counted over the
  whole run (every epoch's GGA must arrive);
- a flood thread opens up to ``n_flood`` connections at once (this process's own
  RLIMIT_NOFILE raised to its hard limit for them; fewer if that limit is lower), holds
  them, closes them and starts again, wave after wave: the first wave before the stream
  starts, the last when the healthy client has every GGA;
- the stream is sent as fast as the daemon reads it, or in real time (`bdsfix simulate
  --realtime` relayed to the daemon) when ``realtime`` is set.

What it gathers (:class:`FloodResult`): GGA of the healthy client, the daemon's JSONL FIX
count, its last STATUS counters (``nmea_clients_refused``, ``nmea_accept_errors``,
``epoch_loop_p99_ms`` ...), the connections the flood made and the waves. Timeouts only
stop a hung run; nothing is judged by the time it took.
"""

from __future__ import annotations

import contextlib
import json
import resource
import signal
import socket
import subprocess
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zmq

from tests.support.load import BDSFIX, RATE_HZ, finish_daemon, start_daemon
from tests.support.paths import ROOT

DAEMON_NOFILE = 1024
"""The daemon's soft descriptor limit in these runs: the usual default, at which the daemon
without a cap failed (about 717 NMEA connections)."""
FD_MARGIN = 200
"""Descriptors this process keeps for itself (ZeroMQ, pipes, the healthy client ...)."""


@dataclass
class FloodResult:
    epochs_expected: int
    flood_size: int = 0  # connections per wave (n_flood, or what this process's limit allows)
    waves: int = 0
    flood_connected: int = 0
    flood_failed: int = 0  # connect refused or timed out
    flood_slow: int = 0  # connects that took over 0.5 s
    gga: int = 0  # GGA received by the healthy client over the whole run
    jsonl_fixes: int = 0
    status: dict[str, float] = field(default_factory=dict)
    wall_s: float = 0.0
    daemon_rc: int | None = None
    daemon_stderr: str = ""


def raise_nofile(want: int) -> int:
    """Raise this process's soft RLIMIT_NOFILE towards ``want`` (at most the hard limit);
    the soft limit now in force."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    target = want if hard == resource.RLIM_INFINITY else min(want, hard)
    if target > soft:
        resource.setrlimit(resource.RLIMIT_NOFILE, (target, hard))
        soft = target
    return soft


def _daemon_limits() -> None:  # in the child, before exec
    _, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    resource.setrlimit(resource.RLIMIT_NOFILE, (min(DAEMON_NOFILE, hard), hard))


class Flood(threading.Thread):
    """Waves of ``size`` connections to ``port``: open them all, hold ``hold_s``, close.
    ``first_wave`` is set once the first wave is open."""

    def __init__(self, port: int, size: int, hold_s: float = 0.2) -> None:
        super().__init__(name="flood", daemon=True)
        self.port, self.size, self.hold_s = port, size, hold_s
        self.stop = threading.Event()
        self.first_wave = threading.Event()
        self.waves = self.connected = self.failed = 0
        self.slow = 0  # connects that took over 0.5 s (a SYN retried: the backlog was full)

    def run(self) -> None:
        while not self.stop.is_set():
            held: list[socket.socket] = []
            try:
                for _ in range(self.size):
                    if self.stop.is_set():
                        break
                    s = socket.socket()
                    s.settimeout(5.0)
                    t0 = time.monotonic()
                    try:
                        s.connect(("127.0.0.1", self.port))
                        self.slow += time.monotonic() - t0 > 0.5
                    except OSError:
                        s.close()
                        self.failed += 1
                        continue
                    held.append(s)
                    self.connected += 1
                self.waves += 1
                self.first_wave.set()
                self.stop.wait(self.hold_s)
            finally:
                for s in held:
                    s.close()


def _sender(receiver: socket.socket, stream: Path | None, sim_argv: list[str] | None) -> None:
    """The receiver's bytes to the daemon: a file as fast as it reads, or `bdsfix simulate
    --realtime` relayed as it comes."""
    if sim_argv is None:
        assert stream is not None
        with stream.open("rb") as fh:
            while chunk := fh.read(1 << 16):
                try:
                    receiver.sendall(chunk)
                except OSError:
                    return
        return
    sim = subprocess.Popen(sim_argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert sim.stdout is not None
    try:
        while chunk := sim.stdout.read1(1 << 16):
            receiver.sendall(chunk)
    except OSError:
        pass
    finally:
        sim.kill()
        sim.wait()


def run_flood(
    epochs: int,
    workdir: Path,
    *,
    stream: Path | None = None,
    realtime_s: float = 0.0,
    n_flood: int = 2000,
    max_clients: int = 64,
    flood: bool = True,
    timeout_s: float = 1800.0,
) -> FloodResult:
    """One run: ``stream`` (a UBX file) sent at full speed, or ``realtime_s`` seconds of the
    simulated receiver in real time; the flood on or off."""
    res = FloodResult(epochs_expected=epochs)
    if flood:
        res.flood_size = max(0, min(n_flood, raise_nofile(n_flood + FD_MARGIN) - FD_MARGIN))
    d = start_daemon(
        workdir,
        ["--nmea-tcp-max-clients", str(max_clients)],
        preexec_fn=_daemon_limits,  # only setrlimit, before exec
    )
    daemon, rx, nport, endpoint = d.proc, d.rx, d.nmea_port, d.endpoint
    ctx = zmq.Context()
    sub = ctx.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"STATUS")
    sub.connect(endpoint)
    healthy: socket.socket | None = None
    flooder: Flood | None = None
    try:
        rx.settimeout(30)
        receiver, _ = rx.accept()  # the daemon's source connection
        deadline = time.monotonic() + 30
        while healthy is None:
            try:
                healthy = socket.create_connection(("127.0.0.1", nport), timeout=1)
            except OSError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.1)
        while res.status.get("nmea_clients", 0) < 1:  # the daemon serves the healthy client
            if time.monotonic() > deadline:
                raise RuntimeError(f"the healthy client was not served: {res.status}")
            if sub.poll(100):
                res.status = json.loads(sub.recv_multipart()[1])["counters"]
        healthy.setblocking(False)
        sim_argv = None
        if realtime_s > 0:
            sim_argv = [
                *BDSFIX,
                "simulate",
                "--rate-hz",
                str(RATE_HZ),
                "--duration-s",
                str(realtime_s),
                "--realtime",
                "--out",
                "-",
            ]
        sender = threading.Thread(
            target=_sender, args=(receiver, stream, sim_argv), name="sender", daemon=True
        )
        if flood and res.flood_size:  # the first wave is in before the stream starts
            flooder = Flood(nport, res.flood_size)
            flooder.start()
            if not flooder.first_wave.wait(timeout=120):
                raise RuntimeError("the flood's first wave did not get in")
        t_start = time.monotonic()
        sender.start()
        poller = zmq.Poller()
        poller.register(sub, zmq.POLLIN)
        poller.register(healthy, zmq.POLLIN)
        tail = b""
        last_progress = (time.monotonic(), -1)
        stopping_at: float | None = None
        while True:
            now = time.monotonic()
            for sock, _ev in poller.poll(50):
                if sock is sub:
                    while True:
                        try:
                            _topic, body = sub.recv_multipart(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        res.status = json.loads(body)["counters"]
                else:
                    with contextlib.suppress(BlockingIOError):
                        data = healthy.recv(1 << 16)
                        buf = tail + data
                        res.gga += buf.count(b"GGA,")
                        tail = buf[-3:]
            if res.gga != last_progress[1]:
                last_progress = (now, res.gga)
            finished = res.gga >= epochs or (
                not sender.is_alive() and now - last_progress[0] > 10.0
            )
            if stopping_at is None and (finished or now - t_start > timeout_s):
                res.wall_s = now - t_start
                if flooder is not None:
                    flooder.stop.set()
                    flooder.join(timeout=30)
                daemon.send_signal(signal.SIGTERM)  # its last STATUS comes after this
                stopping_at = now
            if stopping_at is not None and daemon.poll() is not None and now - stopping_at > 1:
                break
            if stopping_at is not None and now - stopping_at > 30:
                daemon.kill()
                break
        res.daemon_rc = daemon.wait(timeout=30)
        while sub.poll(200):  # the STATUS sent on the way out
            res.status = json.loads(sub.recv_multipart()[1])["counters"]
    finally:
        if flooder is not None:
            flooder.stop.set()
            flooder.join(timeout=30)
            res.waves, res.flood_connected = flooder.waves, flooder.connected
            res.flood_failed, res.flood_slow = flooder.failed, flooder.slow
        sub.close(0)
        ctx.term()
        if healthy is not None:
            healthy.close()
        res.daemon_stderr, res.jsonl_fixes = finish_daemon(d)
    return res
