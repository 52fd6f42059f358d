"""Benchmark: what a misbehaving NTRIP caster costs the daemon (issue 23), wall-clock figures.

Run: python bench/bench_ntrip_faults.py [--seconds S]   (prints figures; no assertions)

For each fault, an NTRIP source (``open_ntrip`` with the daemon's defaults: backoff from
0.25 s to 4 s, header timeout 10 s) reads a real TCP server on loopback for ``S`` seconds
(default 20) and the script prints the connections the server accepted, the source's log
lines by level (the journal the daemon would write) and its counters:

- ``200-and-close``: answers ``HTTP/1.1 200 OK`` and closes, every time;
- ``bad-chunk``: answers 200 with chunked coding and a chunk size that is not hex;
- ``garbage``: answers 200, then sends random bytes (no RTCM 3 frame) as fast as it can.
"""

from __future__ import annotations

import argparse
import logging
import random
import socket
import sys
import threading
import time
from collections import Counter
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.ntrip import open_ntrip
from service.core.ntripurl import parse_ntrip_url

OK_200 = b"HTTP/1.1 200 OK\r\nNtrip-Version: Ntrip/2.0\r\nContent-Type: gnss/data\r\n\r\n"
CHUNKED = OK_200.replace(b"\r\n\r\n", b"\r\nTransfer-Encoding: chunked\r\n\r\nzz\r\n")


class Server:
    def __init__(self, kind: str) -> None:
        self.kind = kind
        self.accepted = 0
        self.stop = threading.Event()
        self.sock = socket.create_server(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.port = self.sock.getsockname()[1]
        self.garbage = random.Random(23).randbytes(1 << 20)
        threading.Thread(target=self.serve, daemon=True).start()

    def serve(self) -> None:
        while not self.stop.is_set():
            try:
                conn, _ = self.sock.accept()
            except TimeoutError:
                continue
            self.accepted += 1
            with conn:
                try:
                    conn.recv(4096)
                    if self.kind == "200-and-close":
                        conn.sendall(OK_200)
                    elif self.kind == "bad-chunk":
                        conn.sendall(CHUNKED)
                    else:
                        conn.sendall(OK_200)
                        while not self.stop.is_set():
                            conn.sendall(self.garbage)
                except OSError:
                    pass


class Lines(logging.Handler):
    def __init__(self) -> None:
        super().__init__(logging.DEBUG)
        self.by_level: Counter[str] = Counter()

    def emit(self, record: logging.LogRecord) -> None:
        self.by_level[record.levelname] += 1


def run(kind: str, seconds: float) -> None:
    server = Server(kind)
    lines = Lines()
    root = logging.getLogger()
    root.addHandler(lines)
    root.setLevel(logging.DEBUG)
    src = open_ntrip(parse_ntrip_url(f"ntrip://u:p@127.0.0.1:{server.port}/EPH"))
    t0 = time.monotonic()
    done = threading.Event()

    def read() -> None:
        for _ in src:
            if done.is_set():
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    time.sleep(seconds)
    done.set()
    src.close()
    reader.join(10)
    elapsed = time.monotonic() - t0
    server.stop.set()
    root.removeHandler(lines)
    c = src.counters
    keys = ("connects", "reconnects", "disconnects", "drops_before_data", "no_rtcm_streams")
    print(
        f"{kind:14s} {elapsed:5.1f} s: {server.accepted} connections "
        f"({server.accepted / elapsed:.2f}/s); log lines "
        + ", ".join(f"{lvl} {n}" for lvl, n in sorted(lines.by_level.items()))
        + "; "
        + " ".join(f"{k}={c.get(k, 0)}" for k in keys)
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--seconds", type=float, default=20.0)
    args = ap.parse_args()
    for kind in ("200-and-close", "bad-chunk", "garbage"):
        run(kind, args.seconds)


if __name__ == "__main__":
    main()
