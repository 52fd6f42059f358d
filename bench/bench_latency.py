"""Benchmark: latency from the last byte of an epoch's UBX message to its NMEA on a socket.

The built-in scenario's UBX stream (a receiver restart near Beijing: fast fixes from about
1 s, conventional SPP from about 10 s) is written, epoch by epoch at 10 Hz, into one end of
a real pty; `bdsfix run` with its default outputs (NMEA TCP and ZeroMQ) reads the other
end through pyserial; a TCP client timestamps each GGA. Every epoch gives exactly one GGA
(quality 0 while there is no fix), so the n-th GGA belongs to the n-th epoch; a run whose
counts differ is reported as such, not measured.
Latency = GGA arrival - return of the write() that put the epoch's last byte in the pty.

Run: python bench/bench_latency.py [--seconds 60] [--runs 3]
(prints per-run and pooled p50/p99/max, fast-fix and SPP epochs apart; no assertions)
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.core.ephemeris import EphemerisStore  # noqa: E402
from service.sim.keplerian import table1_ephemerides  # noqa: E402
from service.sim.scenario import scenario_config  # noqa: E402
from service.sim.simulator import Simulator  # noqa: E402

GOAL_P99_MS = 5.0


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def one_run(epochs: list[bytes]) -> tuple[np.ndarray, list[bytes]] | None:
    """Latencies [ms] of one daemon run and the GGA sentences, or None if GGAs went missing."""
    port, zmq_port = _free_port(), _free_port()
    tmp = Path(tempfile.mkdtemp())
    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    store.save(tmp / "ephemeris.json")
    master, slave = os.openpty()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service",
            "run",
            "--source",
            os.ttyname(slave),
            "--state-dir",
            str(tmp),
            "--zmq",
            f"tcp://127.0.0.1:{zmq_port}",
            "--nmea-tcp",
            f"127.0.0.1:{port}",
            "--log-level",
            "warning",
        ],
        cwd=ROOT,
    )
    client = None
    for _ in range(100):  # the daemon binds after start-up
        try:
            client = socket.create_connection(("127.0.0.1", port))
            break
        except OSError:
            time.sleep(0.1)
    if client is None:
        proc.kill()
        raise SystemExit("bdsfix run did not open its NMEA port")
    time.sleep(0.5)
    arrivals: list[float] = []
    ggas: list[bytes] = []

    def read() -> None:
        buf = b""
        while True:
            try:
                chunk = client.recv(65536)
            except OSError:
                return
            if not chunk:
                return
            now = time.perf_counter()
            buf += chunk
            while b"\n" in buf:
                line, buf = buf.split(b"\n", 1)
                if b"GGA," in line:
                    arrivals.append(now)
                    ggas.append(line)

    t = threading.Thread(target=read, daemon=True)
    t.start()
    sent: list[float] = []
    for data in epochs:
        os.write(master, data)
        sent.append(time.perf_counter())
        time.sleep(0.1)
    time.sleep(1.0)
    proc.terminate()
    proc.wait(10)
    client.close()
    os.close(master)
    os.close(slave)
    print(f"  epochs written {len(sent)}, GGA received {len(arrivals)}")
    if len(sent) != len(arrivals):
        return None
    return (np.array(arrivals) - np.array(sent)) * 1e3, ggas


def _line(name: str, ms: np.ndarray) -> str:
    return (
        f"{name}: n {len(ms)}, p50 {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms, "
        f"max {ms.max():.2f} ms"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="scenario length (10 Hz)")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    sim = Simulator(table1_ephemerides(0.0), scenario_config(duration_s=args.seconds))
    epochs = [data for _ep, data in sim.ubx_epochs()]
    pooled, fast, spp = [], [], []
    for k in range(args.runs):
        print(f"run {k + 1}/{args.runs}")
        got = one_run(epochs)
        if got is None:
            print("  GGA count differs from the epoch count: run not measured")
            continue
        lat, ggas = got
        # GGA quality: 0 no fix, 1 a fix (fast or SPP); the scenario's fixes before its
        # first non-GEO SOW are fast fixes, SPP after the first fix of all-full epochs
        quality = np.array([int(g.split(b",")[6] or 0) for g in ggas])
        print("  " + _line("all epochs", lat))
        pooled.append(lat)
        fixed = np.flatnonzero(quality > 0)
        if len(fixed):
            first = fixed[0]
            fast.append(lat[first : first + 80])  # 8 s of fast fixes after the first one
            spp.append(lat[first + 120 :])  # from 12 s after the first fix: SPP
    if not pooled:
        raise SystemExit("no run could be measured")
    allms = np.concatenate(pooled)
    print(_line(f"pooled over {len(pooled)} runs", allms))
    if fast:
        print(_line("  fast-fix epochs (first 8 s of fixes)", np.concatenate(fast)))
        print(_line("  SPP epochs (12 s after the first fix on)", np.concatenate(spp)))
    p99s = [float(np.percentile(x, 99)) for x in pooled]
    print(
        f"latency last byte -> NMEA GGA on socket: pooled p50 {np.median(allms):.2f} ms, "
        f"p99 {np.percentile(allms, 99):.2f} ms; per-run p99 "
        + ", ".join(f"{v:.2f}" for v in p99s)
        + f" ms (goal p99 <= {GOAL_P99_MS:g} ms)"
    )


if __name__ == "__main__":
    main()
