"""The load harness of bench/bench_load.py and tests/system/test_load.py: `bdsfix run` fed a
simulated receiver over TCP at full speed, with many real peers in this process.

- 50 ZeroMQ SUB sockets (FIX + STATUS) that read everything;
- 20 NMEA TCP clients: 15 read everything (GGA counted), 5 never read (small receive
  buffer), which the daemon must drop (``nmea_clients_dropped_slow``);
- 1 SUB socket closed and reopened every ``reconnect_every`` FIX (20: 1 s of data) the
  first subscriber receives, for the whole run.

What it gathers (:class:`LoadResult`): FIX records received by each healthy subscriber and
the daemon's JSONL, GGA per healthy NMEA client, the daemon's last STATUS counters and its
RSS sampled from /proc/PID/status. Both the RSS samples and the reconnections follow the
run's progress, not the clock, so their number does not depend on the machine's speed. After
the daemon's exit every healthy peer is read to its end (the publisher's disconnect, the TCP
EOF), so the last STATUS and the last records are counted however loaded the machine is.
The timeouts here only stop a hung run (``HANG_S``); nothing is judged by the time it took.
"""

from __future__ import annotations

import contextlib
import json
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zmq
from zmq.utils.monitor import recv_monitor_message

from service.core.ephemeris import EphemerisStore
from service.sim.keplerian import table1_ephemerides
from tests.support.paths import ROOT

BDSFIX = [sys.executable, "-m", "service"]
RATE_HZ = 20.0
HANG_S = 60.0
"""No progress for this long (peers joining, fixes flowing, the end of a stream) is a hang."""


def make_stream(path: Path, minutes: float, rate_hz: float = RATE_HZ) -> int:
    """`bdsfix simulate` (Table 1 ephemerides, near Beijing) to ``path``; the epoch count."""
    subprocess.run(
        [
            *BDSFIX,
            "simulate",
            "--rate-hz",
            str(rate_hz),
            "--duration-s",
            str(60.0 * minutes),
            "--out",
            str(path),
        ],
        cwd=ROOT,
        check=True,
        stderr=subprocess.DEVNULL,
    )
    return round(60.0 * minutes * rate_hz)


@dataclass
class LoadResult:
    epochs_expected: int
    jsonl_fixes: int = 0
    sub_fixes: list[int] = field(default_factory=list)
    nmea_gga: list[int] = field(default_factory=list)
    status: dict[str, float] = field(default_factory=dict)
    rss_kb: list[tuple[float, int, int]] = field(default_factory=list)  # (t, kB, fixes seen)
    reconnects: int = 0
    reconnect_fixes: int = 0
    wall_s: float = 0.0
    daemon_rc: int | None = None
    daemon_stderr: str = ""

    def rss_growth_after_warmup(self, warmup_frac: float = 0.2) -> tuple[int, int, float]:
        """(reference kB at the end of warm-up, max kB after it, growth fraction)."""
        done = [s for s in self.rss_kb if s[2] >= warmup_frac * self.epochs_expected]
        if not done:
            return 0, 0, float("nan")
        ref = done[0][1]
        peak = max(s[1] for s in done)
        return ref, peak, peak / ref - 1.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status", encoding="ascii") as fh:
        for line in fh:
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    return 0


def _connect_tcp(port: int, rcvbuf: int | None, deadline: float) -> socket.socket:
    while True:
        s = socket.socket()
        if rcvbuf is not None:
            s.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        try:
            s.connect(("127.0.0.1", port))
            return s
        except OSError:
            s.close()
            if time.monotonic() > deadline:
                raise
            time.sleep(0.1)


def _read_to_the_end(
    subs: list[zmq.Socket],
    monitors: list[zmq.Socket],
    tcp: list[socket.socket],
    tails: list[bytes],
    res: LoadResult,
) -> None:
    """After the daemon's exit: every subscriber until the publisher's disconnect and every
    healthy NMEA client until EOF, counting what was still on its way."""
    deadline = time.monotonic() + HANG_S
    left = set(range(len(subs)))
    while left:
        assert time.monotonic() < deadline, f"no disconnect seen by subscribers {sorted(left)}"
        for i in list(left):
            if monitors[i].poll(0):
                recv_monitor_message(monitors[i])
                left.discard(i)
        for i, s in enumerate(subs):
            while s.poll(0):
                topic, body = s.recv_multipart()
                if topic == b"FIX":
                    res.sub_fixes[i] += 1
                elif i == 0:
                    res.status = json.loads(body)["counters"]
        time.sleep(0.01)
    for i, s in enumerate(subs):  # delivered before the disconnect event was seen
        while s.poll(100):
            topic, body = s.recv_multipart()
            if topic == b"FIX":
                res.sub_fixes[i] += 1
            elif i == 0:
                res.status = json.loads(body)["counters"]
    for k, s in enumerate(tcp):
        s.setblocking(True)
        s.settimeout(HANG_S)
        while data := s.recv(1 << 16):
            buf = tails[k] + data
            res.nmea_gga[k] += buf.count(b"GGA,")
            tails[k] = buf[-3:]


@dataclass
class Daemon:
    """A ``bdsfix run`` reading a local TCP source, with ZeroMQ, NMEA TCP and JSONL outputs."""

    proc: subprocess.Popen[bytes]
    rx: socket.socket  # the listening source: the daemon connects to it
    nmea_port: int
    endpoint: str  # ZeroMQ PUB
    jsonl: Path
    err_path: Path
    err_fh: Any


def start_daemon(
    workdir: Path, extra: Sequence[str] = (), preexec_fn: Callable[[], None] | None = None
) -> Daemon:
    """Start ``bdsfix run`` warm (Table 1 ephemerides held in its state directory) on a
    local TCP source, STATUS every 0.5 s; ``extra`` flags are appended."""
    state = workdir / "state"
    state.mkdir(mode=0o700, exist_ok=True)
    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    store.save(state / "ephemeris.json")  # warm start, as on a receiver host
    jsonl = workdir / "fixes.jsonl"
    rx = socket.create_server(("127.0.0.1", 0))
    zport, nport = _free_port(), _free_port()
    endpoint = f"tcp://127.0.0.1:{zport}"
    err_path = workdir / "daemon.err"
    err_fh = err_path.open("wb")
    argv = [*BDSFIX, "run", "--source", f"tcp:127.0.0.1:{rx.getsockname()[1]}"]
    argv += ["--state-dir", str(state), "--zmq", endpoint, "--nmea-tcp", f"127.0.0.1:{nport}"]
    argv += ["--jsonl-out", str(jsonl), "--status-interval-s", "0.5", "--log-level", "warning"]
    proc = subprocess.Popen(
        [*argv, *extra],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=err_fh,
        preexec_fn=preexec_fn,  # only setrlimit (flood), before exec
    )
    return Daemon(proc, rx, nport, endpoint, jsonl, err_path, err_fh)


def finish_daemon(d: Daemon) -> tuple[str, int]:
    """Kill the daemon if it still runs, close its source and log; its stderr and the
    number of FIX records in its JSONL."""
    if d.proc.poll() is None:
        d.proc.kill()
        d.proc.wait()
    d.err_fh.close()
    d.rx.close()
    fixes = sum(1 for x in d.jsonl.read_text().splitlines() if x.startswith('{"class":"FIX"'))
    return d.err_path.read_text(errors="replace"), fixes


def run_load(
    stream: Path,
    epochs: int,
    workdir: Path,
    *,
    n_zmq: int = 50,
    n_nmea: int = 20,
    n_slow: int = 5,
    rss_samples: int = 40,
    reconnect_every: int = 20,
    timeout_s: float = 3600.0,
) -> LoadResult:
    res = LoadResult(epochs_expected=epochs)
    d = start_daemon(workdir)
    daemon, rx, nport, endpoint = d.proc, d.rx, d.nmea_port, d.endpoint
    ctx = zmq.Context()
    subs: list[zmq.Socket] = []
    tcp: list[socket.socket] = []
    slow: list[socket.socket] = []
    again: zmq.Socket | None = None
    monitors: list[zmq.Socket] = []
    fixes_seen = [0]
    try:
        rx.settimeout(HANG_S)
        receiver, _ = rx.accept()  # the daemon's source connection
        deadline = time.monotonic() + HANG_S
        for i in range(n_nmea):
            if i < n_slow:
                slow.append(_connect_tcp(nport, 4096, deadline))
            else:
                tcp.append(_connect_tcp(nport, None, deadline))
        for _ in range(n_zmq):
            s = ctx.socket(zmq.SUB)
            s.setsockopt(zmq.LINGER, 0)
            s.setsockopt(zmq.RCVHWM, 0)  # a healthy reader: whatever arrives is kept
            s.setsockopt(zmq.SUBSCRIBE, b"FIX")
            s.setsockopt(zmq.SUBSCRIBE, b"STATUS")
            monitors.append(s.get_monitor_socket(zmq.EVENT_DISCONNECTED))
            s.connect(endpoint)
            subs.append(s)
        # join: every subscriber has a STATUS and the daemon counts every NMEA client
        joined = [False] * n_zmq
        while not all(joined) or res.status.get("nmea_clients", 0) < n_nmea:
            if time.monotonic() > deadline:
                raise RuntimeError(f"peers did not join: {sum(joined)} subs, {res.status}")
            for i, s in enumerate(subs):
                while s.poll(0):
                    topic, body = s.recv_multipart()
                    if topic == b"STATUS":
                        joined[i] = True
                        if i == 0:
                            res.status = json.loads(body)["counters"]
            time.sleep(0.02)

        res.sub_fixes = [0] * n_zmq
        res.nmea_gga = [0] * len(tcp)
        tails = [b""] * len(tcp)
        for s in tcp:
            s.setblocking(False)

        def send_all() -> None:
            with stream.open("rb") as fh:
                while chunk := fh.read(1 << 16):
                    try:
                        receiver.sendall(chunk)
                    except OSError:
                        return

        sender = threading.Thread(target=send_all, daemon=True)
        t_start = time.monotonic()
        sender.start()

        poller = zmq.Poller()
        for s in subs:
            poller.register(s, zmq.POLLIN)
        for s in tcp:
            poller.register(s, zmq.POLLIN)
        tcp_of = {s.fileno(): k for k, s in enumerate(tcp)}
        next_cycle = 0  # FIX count at which the reconnecting subscriber cycles
        last_progress = (time.monotonic(), -1)
        stopping_at: float | None = None
        rss_step = max(1, epochs // rss_samples)
        next_rss = rss_step
        while True:
            now = time.monotonic()
            if fixes_seen[0] >= next_cycle:  # the subscriber that leaves and comes back
                if again is not None:
                    poller.unregister(again)
                    again.close(0)
                again = ctx.socket(zmq.SUB)
                again.setsockopt(zmq.LINGER, 0)
                again.setsockopt(zmq.SUBSCRIBE, b"FIX")
                again.connect(endpoint)
                poller.register(again, zmq.POLLIN)
                res.reconnects += 1
                next_cycle = fixes_seen[0] + reconnect_every
            for sock, _ev in poller.poll(50):
                if isinstance(sock, zmq.Socket):
                    i = subs.index(sock) if sock is not again else -1
                    while True:
                        try:
                            topic, body = sock.recv_multipart(zmq.NOBLOCK)
                        except zmq.Again:
                            break
                        if topic == b"FIX":
                            if i >= 0:
                                res.sub_fixes[i] += 1
                            else:
                                res.reconnect_fixes += 1
                        elif i == 0:
                            res.status = json.loads(body)["counters"]
                else:
                    k = tcp_of[sock]
                    try:
                        data = tcp[k].recv(1 << 16)
                    except BlockingIOError:
                        continue
                    buf = tails[k] + data
                    res.nmea_gga[k] += buf.count(b"GGA,")
                    tails[k] = buf[-3:]
            fixes_seen[0] = res.sub_fixes[0]
            # RSS sampled by progress (every epochs/rss_samples fixes), not by the clock, so
            # the number of samples does not depend on how fast this machine is
            if fixes_seen[0] >= next_rss and daemon.poll() is None:
                with contextlib.suppress(OSError):
                    res.rss_kb.append((now - t_start, _rss_kb(daemon.pid), fixes_seen[0]))
                next_rss = fixes_seen[0] + rss_step
            if fixes_seen[0] != last_progress[1]:
                last_progress = (now, fixes_seen[0])
            finished = fixes_seen[0] >= epochs or (
                not sender.is_alive() and now - last_progress[0] > HANG_S
            )
            if stopping_at is None and (finished or now - t_start > timeout_s):
                res.wall_s = now - t_start
                daemon.send_signal(signal.SIGTERM)  # its last STATUS comes after this
                stopping_at = now
            if stopping_at is not None and daemon.poll() is not None:
                break
            if stopping_at is not None and now - stopping_at > HANG_S:
                daemon.kill()
                break
        res.daemon_rc = daemon.wait(timeout=HANG_S)
        _read_to_the_end(subs, monitors, tcp, tails, res)
    finally:
        for s in [*monitors, *subs, *([again] if again is not None else [])]:
            s.close(0)
        ctx.term()
        for t in [*tcp, *slow]:
            t.close()
        res.daemon_stderr, res.jsonl_fixes = finish_daemon(d)
    return res
