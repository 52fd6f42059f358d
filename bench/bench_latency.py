"""Benchmark: latency from the last byte of an epoch's UBX message to its NMEA on a socket.

The built-in scenario's UBX stream is written, epoch by epoch at 10 Hz, into one end of a
real pty; `bdsfix run` reads the other end through pyserial and serves NMEA over TCP; a
client timestamps each GGA. Latency = GGA arrival - write of the epoch's last byte.
Run: python bench/bench_latency.py   (prints p50/p99; no assertions)
"""

from __future__ import annotations

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

from service.ephemeris import EphemerisStore  # noqa: E402
from service.keplerian import table1_ephemerides  # noqa: E402
from service.scenario import scenario_config  # noqa: E402
from service.simulator import Simulator  # noqa: E402


def main(duration_s: float = 30.0) -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    tmp = Path(tempfile.mkdtemp())
    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    store.save(tmp / "ephemeris.json")
    sim = Simulator(table1_ephemerides(0.0), scenario_config(duration_s=duration_s))
    epochs = [data for _ep, data in sim.ubx_epochs()]
    master, slave = os.openpty()
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "service.cli",
            "run",
            "--source",
            os.ttyname(slave),
            "--state-dir",
            str(tmp),
            "--zmq",
            "",
            "--nmea-tcp",
            f"127.0.0.1:{port}",
            "--log-level",
            "warning",
        ],
        cwd=ROOT,
    )
    time.sleep(2.0)
    client = socket.create_connection(("127.0.0.1", port))
    arrivals: list[float] = []

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
    n = min(len(sent), len(arrivals))
    lat = (np.array(arrivals[:n]) - np.array(sent[:n])) * 1e3
    print(f"epochs written {len(sent)}, GGA received {len(arrivals)}")
    print(
        f"latency last byte -> NMEA on socket: p50 {np.median(lat):.1f} ms, "
        f"p99 {np.percentile(lat, 99):.1f} ms, max {lat.max():.1f} ms (goal p99 <= 5 ms)"
    )


if __name__ == "__main__":
    main()
