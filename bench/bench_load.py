"""Load: the daemon fed a simulated 20 Hz receiver at full speed, with many slow and fast peers.

`bdsfix simulate` writes a UBX stream (default 1 hour at 20 Hz). The bench plays the
receiver: `bdsfix run` connects to it over TCP (``--source tcp:``), and once every peer has
joined the bench writes the whole stream as fast as the daemon reads it. Peers, all real
sockets in this process:

- 50 ZeroMQ SUB sockets (FIX + STATUS) that read everything;
- 20 NMEA TCP clients: 15 read everything (GGA counted), 5 never read (small receive
  buffer), which the daemon must drop (``nmea_clients_dropped_slow``);
- 1 SUB socket closed and reopened every 0.2 s for the whole run.

Figures: epoch loop time p50/p99/max (solve + publish, from the daemon's STATUS, so a
publisher that blocked would show here), publish time alone, slow clients dropped, FIX
records received by each healthy subscriber vs the daemon's JSONL, GGA per healthy NMEA
client, the daemon's RSS sampled from /proc/PID/status and its growth after warm-up.

Run: python bench/bench_load.py [--minutes 60] [--zmq-subs 50] [--nmea 20] [--slow 5]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import zmq

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


from service.core.ephemeris import EphemerisStore  # noqa: E402
from service.sim.keplerian import table1_ephemerides  # noqa: E402

BDSFIX = [sys.executable, "-m", "service"]
RATE_HZ = 20.0


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


def run_load(
    stream: Path,
    epochs: int,
    workdir: Path,
    *,
    n_zmq: int = 50,
    n_nmea: int = 20,
    n_slow: int = 5,
    rss_samples: int = 40,
    timeout_s: float = 3600.0,
) -> LoadResult:
    res = LoadResult(epochs_expected=epochs)
    state = workdir / "state"
    state.mkdir(exist_ok=True)
    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    store.save(state / "ephemeris.json")  # warm start, as on a receiver host
    jsonl = workdir / "fixes.jsonl"
    rx = socket.create_server(("127.0.0.1", 0))
    zport, nport = _free_port(), _free_port()
    endpoint = f"tcp://127.0.0.1:{zport}"
    err_path = workdir / "daemon.err"
    err_fh = err_path.open("wb")
    daemon = subprocess.Popen(
        [
            *BDSFIX,
            "run",
            "--source",
            f"tcp:127.0.0.1:{rx.getsockname()[1]}",
            "--state-dir",
            str(state),
            "--zmq",
            endpoint,
            "--nmea-tcp",
            f"127.0.0.1:{nport}",
            "--jsonl-out",
            str(jsonl),
            "--status-interval-s",
            "0.5",
            "--log-level",
            "warning",
        ],
        cwd=ROOT,
        stdout=subprocess.DEVNULL,
        stderr=err_fh,
    )
    ctx = zmq.Context()
    subs: list[zmq.Socket] = []
    tcp: list[socket.socket] = []
    slow: list[socket.socket] = []
    again: zmq.Socket | None = None
    fixes_seen = [0]
    try:
        rx.settimeout(30)
        receiver, _ = rx.accept()  # the daemon's source connection
        deadline = time.monotonic() + 30
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
        next_cycle = time.monotonic()
        last_progress = (time.monotonic(), -1)
        stopping_at: float | None = None
        rss_step = max(1, epochs // rss_samples)
        next_rss = rss_step
        while True:
            now = time.monotonic()
            if now >= next_cycle:  # the subscriber that keeps leaving and coming back
                if again is not None:
                    poller.unregister(again)
                    again.close(0)
                again = ctx.socket(zmq.SUB)
                again.setsockopt(zmq.LINGER, 0)
                again.setsockopt(zmq.SUBSCRIBE, b"FIX")
                again.connect(endpoint)
                poller.register(again, zmq.POLLIN)
                res.reconnects += 1
                next_cycle = now + 0.2
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
                not sender.is_alive() and now - last_progress[0] > 10.0
            )
            if stopping_at is None and (finished or now - t_start > timeout_s):
                res.wall_s = now - t_start
                daemon.send_signal(signal.SIGTERM)  # its last STATUS comes after this
                stopping_at = now
            if stopping_at is not None and daemon.poll() is not None and now - stopping_at > 1:
                break
            if stopping_at is not None and now - stopping_at > 30:
                daemon.kill()
                break
        res.daemon_rc = daemon.wait(timeout=30)
    finally:
        if daemon.poll() is None:
            daemon.kill()
            daemon.wait()
        err_fh.close()
        for s in [*subs, *([again] if again is not None else [])]:
            s.close(0)
        ctx.term()
        for t in [*tcp, *slow]:
            t.close()
        rx.close()
    res.daemon_stderr = err_path.read_text(errors="replace")
    res.jsonl_fixes = sum(
        1 for line in jsonl.read_text().splitlines() if line.startswith('{"class":"FIX"')
    )
    return res


def report(res: LoadResult) -> None:
    st = res.status
    print(
        f"  epochs {res.epochs_expected}, JSONL FIX records {res.jsonl_fixes}, wall "
        f"{res.wall_s:.1f} s ({res.jsonl_fixes / max(res.wall_s, 1e-9):.0f} epochs/s)"
    )
    print(
        "  epoch loop (solve + publish) p50 {:.2f} ms, p99 {:.2f} ms, max {:.1f} ms; "
        "publish alone p50 {:.2f} ms, p99 {:.2f} ms, max {:.1f} ms".format(
            *(
                st.get(f"epoch_{k}_{q}_ms", float("nan"))
                for k in ("loop", "publish")
                for q in ("p50", "p99", "max")
            )
        )
    )
    print(
        f"  NMEA clients accepted {st.get('nmea_clients_accepted', 0)}, dropped as slow "
        f"{st.get('nmea_clients_dropped_slow', 0)}, left {st.get('nmea_clients', 0)}"
    )
    s = res.sub_fixes
    print(
        f"  ZeroMQ: {len(s)} subscribers got FIX min {min(s)} max {max(s)} "
        f"(published {st.get('zmq_FIX', 0)}, JSONL {res.jsonl_fixes}); "
        f"{sum(x == res.jsonl_fixes for x in s)} complete; zmq_dropped {st.get('zmq_dropped', 0)}"
    )
    g = res.nmea_gga
    print(
        f"  NMEA: {len(g)} healthy clients got GGA min {min(g)} max {max(g)}; "
        f"{sum(x == res.jsonl_fixes for x in g)} complete"
    )
    print(f"  reconnecting subscriber: {res.reconnects} connections, {res.reconnect_fixes} FIX")
    ref, peak, growth = res.rss_growth_after_warmup()
    step = max(1, len(res.rss_kb) // 20)
    series = ", ".join(f"{t:.0f}s:{kb / 1024:.1f}" for t, kb, _ in res.rss_kb[::step])
    print(f"  daemon RSS [MiB] over time: {series}")
    print(
        f"  RSS after warm-up (20 % of epochs): {ref / 1024:.1f} MiB -> peak {peak / 1024:.1f} "
        f"MiB ({100 * growth:+.1f} %)"
    )
    print(f"  daemon exit {res.daemon_rc}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="simulated data [min]")
    ap.add_argument("--zmq-subs", type=int, default=50)
    ap.add_argument("--nmea", type=int, default=20)
    ap.add_argument("--slow", type=int, default=5)
    ap.add_argument("--keep", action="store_true", help="keep the work directory")
    a = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bdsfix-load-"))
    stream = work / "stream.ubx"
    t0 = time.perf_counter()
    n = make_stream(stream, a.minutes)
    print(
        f"bench_load: {a.minutes:g} min at {RATE_HZ:g} Hz = {n} epochs, "
        f"{stream.stat().st_size / 1e6:.1f} MB UBX (simulated in {time.perf_counter() - t0:.0f} s)"
    )
    res = run_load(stream, n, work, n_zmq=a.zmq_subs, n_nmea=a.nmea, n_slow=a.slow)
    report(res)
    if not a.keep:
        for p in sorted(work.rglob("*"), reverse=True):
            p.unlink() if p.is_file() else p.rmdir()
        work.rmdir()
    else:
        print(f"  work directory: {work}")
    if "Traceback" in res.daemon_stderr:
        print(res.daemon_stderr[-3000:])


if __name__ == "__main__":
    main()
