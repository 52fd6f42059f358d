"""Benchmark: the floor under bench_latency.py's non-solve time, on this machine.

``bench/bench_latency.py`` splits each epoch's latency (its last byte written into a pty ->
its GGA on a TCP client) into the solve and the rest, the non-solve time. Part of the rest
is not bdsfix's: the kernel hands the bytes through the pty, wakes the reader, carries the
GGA over loopback TCP and wakes the client. This script measures that part alone: the same
epochs (the built-in scenario's UBX bytes, one write each at 10 Hz, as bench_latency writes
them) go into a pty, and a Python process that does nothing else (one ``poll`` and one
``os.read`` per wake-up, as the daemon's serial read; no decoding, no solve) sends a fixed
GGA line to a TCP client once an epoch's bytes are all in. What it measures is the least
non-solve time any Python daemon can have here; bdsfix's decoding and NMEA come on top.

Run: python bench/bench_io_floor.py [--seconds 60] [--runs 3]
(prints p50/p90/p99 per run and pooled; no assertions)
"""

from __future__ import annotations

import argparse
import os
import socket
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.sim.keplerian import table1_ephemerides  # noqa: E402
from service.sim.scenario import scenario_config  # noqa: E402
from service.sim.simulator import Simulator  # noqa: E402

READER = r"""
import os, select, socket, sys, tty
fd = os.open(sys.argv[1], os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
tty.setraw(fd)
srv = socket.create_server(("127.0.0.1", 0))
print(srv.getsockname()[1], flush=True)
client = srv.accept()[0]
client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
poll = select.poll()
poll.register(fd, select.POLLIN)
gga = b"$GNGGA,000000.00,3954.00000,N,11624.00000,E,1,12,0.8,50.0,M,-8.0,M,,*00\r\n"
sizes = [int(n) for n in sys.stdin.readline().split()]
k = got = 0
while k < len(sizes):
    if not poll.poll(1000):
        continue
    got += len(os.read(fd, 65536))
    while k < len(sizes) and got >= sizes[k]:
        got -= sizes[k]
        k += 1
        client.sendall(gga)
"""


def one_run(epochs: list[bytes]) -> np.ndarray:
    """Latency [ms] of each epoch: its write's return -> the fixed GGA at the client."""
    master, slave = os.openpty()
    tty.setraw(master)
    proc = subprocess.Popen(
        [sys.executable, "-c", READER, os.ttyname(slave)],
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
    )
    assert proc.stdin is not None and proc.stdout is not None
    port = int(proc.stdout.readline())
    proc.stdin.write(" ".join(str(len(e)) for e in epochs) + "\n")
    proc.stdin.flush()
    client = socket.create_connection(("127.0.0.1", port))
    arrivals: list[float] = []

    def read() -> None:
        buf = b""
        while len(arrivals) < len(epochs):
            chunk = client.recv(65536)
            if not chunk:
                return
            now = time.perf_counter()
            buf += chunk
            while b"\n" in buf:
                _line, buf = buf.split(b"\n", 1)
                arrivals.append(now)

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    time.sleep(0.5)
    sent: list[float] = []
    for data in epochs:
        start = time.perf_counter()
        os.write(master, data)
        sent.append(time.perf_counter())
        time.sleep(max(0.0, start + 0.1 - time.perf_counter()))
    reader.join(5.0)
    proc.wait(5.0)
    client.close()
    os.close(master)
    os.close(slave)
    if len(arrivals) != len(sent):
        raise SystemExit(f"{len(sent)} epochs written, {len(arrivals)} lines received")
    return (np.array(arrivals) - np.array(sent)) * 1e3


def _line(name: str, x: np.ndarray) -> str:
    p50, p90, p99 = np.percentile(x, [50, 90, 99])
    return f"  {name}: n {len(x)}, p50 {p50:.3f} ms, p90 {p90:.3f} ms, p99 {p99:.3f} ms"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="scenario length (10 Hz)")
    ap.add_argument("--runs", type=int, default=3)
    args = ap.parse_args()
    sim = Simulator(table1_ephemerides(0.0), scenario_config(duration_s=args.seconds))
    epochs = [data for _ep, data in sim.ubx_epochs()]
    sizes = np.array([len(e) for e in epochs])
    print(f"{len(epochs)} epochs of {int(np.median(sizes))} bytes (median) at 10 Hz, per run")
    pooled = []
    for k in range(args.runs):
        x = one_run(epochs)
        pooled.append(x)
        print(_line(f"run {k + 1}", x))
    print(_line("pooled", np.concatenate(pooled)))
    print(f"load average at the end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")


if __name__ == "__main__":
    main()
