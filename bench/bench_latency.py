"""Benchmark: latency from the last byte of an epoch's UBX message to its NMEA on a socket.

The built-in scenario's UBX stream (a receiver restart near Beijing: fast fixes from about
1 s, conventional SPP from about 10 s) is written, epoch by epoch at 10 Hz, into one end of
a real pty; `bdsfix run` with its default outputs (NMEA TCP and ZeroMQ) reads the other
end through pyserial; a TCP client timestamps each GGA. Every epoch gives exactly one GGA
(quality 0 while there is no fix), so the n-th GGA belongs to the n-th epoch; a run whose
counts differ is reported as such, not measured.
Latency = GGA arrival - return of the write() that put the epoch's last byte in the pty.

Each epoch's solve time (the pipeline's ``on_epoch``) comes from the daemon itself
(``BDSFIX_EPOCH_TIMES``, :data:`service.daemon.loop.EPOCH_TIMES_ENV`, on the same monotonic
clock as this script's), so every epoch's latency splits into its parts [ms]:

- ``solve``: the pipeline's ``on_epoch``; ``nonsolve`` = ``latency`` - ``solve``;
- ``daemon``: write -> the daemon handed the GGA to its NMEA TCP sink (the kernel has it);
  ``d-nonsolve`` = ``daemon`` - ``solve``, the part of the non-solve time the daemon spends;
- ``wake+read``: write -> the daemon's read returned (its wake-up; only for a live source
  read in the loop's thread), ``decode+``: that read -> solve start (decoding, subframes),
  ``to GGA``: solve end -> GGA handed over, ``client``: GGA handed over -> this script's
  client has it (the client's wake-up: on a loaded machine, a scheduling delay of the
  client, not of bdsfix).

``--root DIR`` (repeatable) runs the daemon from another source tree (e.g. an export of
main plus this instrumentation): the runs alternate between the trees, A B A B..., so a
machine shared with other work loads them alike; the load average is printed per run.

``--line-rate BAUD`` writes each epoch as a receiver's serial line delivers it, in small
writes over its transmission time (the daemon decodes the epoch's first messages while the
rest is on the line), instead of in one write: the latency is still timed from the last
byte.

``--scenario hksc`` replaces the built-in scenario (BeiDou only, about 10 satellites) by a
multi-system stream of 34 satellites: the HKSC station's RINEX epochs
(../shared/data/hksc-2021, 16 BeiDou, 12 GPS and 6 Galileo in each of its 205 epochs) written
as UBX RXM-RAWX (BeiDou B1I, GPS L1 C/A, Galileo E1, every range full, the file's Doppler
and C/N0) at 10 Hz, the daemon run with ``--systems C,G,E`` and the file's navigation in its
ephemeris store (as a receiver that has run before): every epoch an SPP fix of three
clocks over the 34 rows (issue 19's goal: p99 <= 5 ms with 30 satellites in view).

``--http-clients N`` adds the status page (``--output http:127.0.0.1:PORT``) with N clients
reading its event stream (``/events``) to every other run, alternating with runs without
it, and compares the p99 of the epoch loop (``loop``: solve start -> every output handed
its records, from the daemon's own times) and of the latency (goal: within 10 %).

Run: python bench/bench_latency.py [--seconds 60] [--runs 3] [--root DIR ...] [--rt PRIO]
[--nice N] [--line-rate BAUD] [--tcp] [--http-clients 20] [--scenario builtin|hksc]
(prints per-run and pooled p50/p99/max, fast-fix and SPP epochs apart; no assertions)
"""

from __future__ import annotations

import argparse
import contextlib
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

DATA = ROOT.parent / "shared" / "data"
HKSC = DATA / "hksc-2021"
GOAL_P99_MS = 5.0
GOAL_NONSOLVE_P50_MS, GOAL_NONSOLVE_P99_MS = 0.5, 2.0
LINE_CHUNK_BYTES = 32  # --line-rate: bytes a write, as a UART's FIFO hands them on


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def one_run(
    epochs: list[bytes],
    root: Path,
    rt_priority: int = 0,
    line_rate: int = 0,
    tcp: bool = False,
    http_clients: int = 0,
    store: EphemerisStore | None = None,
    extra: tuple[str, ...] = (),
) -> tuple[dict[str, np.ndarray], list[bytes]] | None:
    """Per-epoch times [ms] of one daemon run (``latency``, ``solve``, ``nonsolve``,
    ``before``, ``after``) and the GGA sentences, or None if GGAs or epochs went missing."""
    port, zmq_port = _free_port(), _free_port()
    tmp = Path(tempfile.mkdtemp())
    times_path = tmp / "epoch-times.txt"
    if store is None:
        store = EphemerisStore()
        store.add_all(table1_ephemerides(0.0))
    store.save(tmp / "ephemeris.json")
    master, slave = os.openpty()
    server = socket.create_server(("127.0.0.1", 0)) if tcp else None
    source = f"tcp:127.0.0.1:{server.getsockname()[1]}" if server else os.ttyname(slave)
    chrt = ["chrt", "--fifo", str(rt_priority)] if rt_priority else []
    http_port = _free_port()
    http = ["--output", f"http:127.0.0.1:{http_port}"] if http_clients else []
    proc = subprocess.Popen(
        [
            *chrt,
            sys.executable,
            "-m",
            "service",
            "run",
            "--source",
            source,
            "--state-dir",
            str(tmp),
            "--zmq",
            f"tcp://127.0.0.1:{zmq_port}",
            "--nmea-tcp",
            f"127.0.0.1:{port}",
            "--log-level",
            "warning",
            *http,
            *extra,
        ],
        cwd=root,
        env={**os.environ, "BDSFIX_EPOCH_TIMES": str(times_path)},
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
    conn = None
    if server is not None:
        server.settimeout(10.0)
        conn = server.accept()[0]  # the daemon's connection
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def write(data: bytes) -> None:
        if conn is not None:
            conn.sendall(data)
        else:
            os.write(master, data)

    try:
        readers = [SseReader(http_port) for _ in range(http_clients)]  # it binds after NMEA
    except BaseException:
        proc.kill()
        raise
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
    chunk = LINE_CHUNK_BYTES if line_rate else 1 << 30
    chunk_s = chunk * 10 / line_rate if line_rate else 0.0  # 8N1: 10 bits a byte
    for data in epochs:
        start = time.perf_counter()
        for k in range(0, len(data), chunk):
            if k:
                time.sleep(max(0.0, start + (k // chunk) * chunk_s - time.perf_counter()))
            write(data[k : k + chunk])
        sent.append(time.perf_counter())
        time.sleep(max(0.0, start + 0.1 - time.perf_counter()))
    time.sleep(1.0)
    proc.terminate()
    proc.wait(10)
    client.close()
    if readers:
        got = [r.close() for r in readers]
        print(
            f"  {len(readers)} status-page event streams: fix events per reader "
            f"min {min(got)}, max {max(got)}"
        )
    os.close(master)
    os.close(slave)
    if server is not None and conn is not None:
        conn.close()
        server.close()
    times = np.loadtxt(times_path, ndmin=2) if times_path.exists() else np.zeros((0, 5))
    print(
        f"  epochs written {len(sent)}, GGA received {len(arrivals)}, "
        f"epochs timed by the daemon {len(times)}"
    )
    if not (len(sent) == len(arrivals) == len(times)):
        return None
    if times.shape[1] == 3:  # the first form of BDSFIX_EPOCH_TIMES: solve start/end, end
        nan = np.full(len(times), np.nan)
        times = np.column_stack([nan, times[:, 0], times[:, 1], nan, times[:, 2]])
    t_sent, t_arrived = np.array(sent), np.array(arrivals)
    t_read, t_solve, t_solved, t_gga, t_done = (times[:, k] for k in range(5))
    ms = {
        "latency": (t_arrived - t_sent) * 1e3,
        "solve": (t_solved - t_solve) * 1e3,
        "daemon": (t_gga - t_sent) * 1e3,
        "wake+read": (t_read - t_sent) * 1e3,
        "decode+": (t_solve - t_read) * 1e3,
        "to GGA": (t_gga - t_solved) * 1e3,
        "client": (t_arrived - t_gga) * 1e3,
        "loop": (t_done - t_solve) * 1e3,  # the epoch loop: solve and every output
    }
    ms["nonsolve"] = ms["latency"] - ms["solve"]
    ms["d-nonsolve"] = ms["daemon"] - ms["solve"]
    return ms, ggas


def hksc_scenario() -> tuple[list[bytes], EphemerisStore]:
    """The HKSC station's epochs as UBX RXM-RAWX (every system of the file, every range
    full) and its navigation file in a store: ``--scenario hksc``."""
    from drivers.source import file_epochs
    from service.commands.solve import load_navigation
    from service.core.bds import is_geo
    from service.core.types import MeasurementEpoch
    from service.sim.ubx import RawxMeas, rawx_frame

    gnss_id = {"G": 0, "E": 2, "C": 3}  # u-blox gnssId
    systems = ("C", "G", "E")
    events, _ = file_epochs(HKSC / "hksc1610.obs", systems=systems)
    frames = []
    for ep in events:
        if not isinstance(ep, MeasurementEpoch):
            continue
        meas = [
            RawxMeas(
                pr_m=float(ep.pr_m[i]),
                gnss_id=gnss_id[p[0]],
                sv_id=int(p[1:]),
                sig_id=1 if is_geo(p) else 0,  # B1I D2 / D1; L1 C/A and E1 C: 0
                locktime_ms=int(min(ep.lock_s[i], 60.0) * 1e3) if np.isfinite(ep.lock_s[i]) else 0,
                cn0_dbhz=int(ep.cn0_dbhz[i]) if np.isfinite(ep.cn0_dbhz[i]) else 0,
                pr_std_index=5,
                pr_valid=bool(np.isfinite(ep.pr_m[i])),
                doppler_hz=float(ep.doppler_hz[i]) if np.isfinite(ep.doppler_hz[i]) else 0.0,
            )
            for i, p in enumerate(ep.prn)
        ]
        frames.append(rawx_frame(ep.gpst_tow_s, ep.gpst_week, 18, meas))
    store, _ = load_navigation([str(HKSC / "hksc1610.nav")], systems=systems)
    return frames, store


class SseReader:
    """One status-page client: reads ``/events`` in a thread and counts the fix events."""

    def __init__(self, port: int) -> None:
        for _ in range(100):  # the daemon opens its outputs in turn
            try:
                self.sock = socket.create_connection(("127.0.0.1", port))
                break
            except OSError:
                time.sleep(0.1)
        else:
            raise SystemExit("bdsfix run did not open its status page")
        self.sock.sendall(b"GET /events HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
        self.fixes = 0
        self.thread = threading.Thread(target=self._read, daemon=True)
        self.thread.start()

    def _read(self) -> None:
        tail = b""
        while True:
            try:
                chunk = self.sock.recv(65536)
            except OSError:
                return
            if not chunk:
                return
            data = tail + chunk
            self.fixes += data.count(b"event: fix\n")
            tail = data[-16:]
            self.fixes -= tail.count(b"event: fix\n")  # counted again with the next chunk

    def close(self) -> int:
        with contextlib.suppress(OSError):
            self.sock.shutdown(socket.SHUT_RDWR)
        self.sock.close()
        self.thread.join(timeout=5)
        return self.fixes


def _line(name: str, ms: np.ndarray) -> str:
    return (
        f"{name}: n {len(ms)}, p50 {np.median(ms):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms, "
        f"max {ms.max():.2f} ms"
    )


PARTS = (
    "latency",
    "loop",
    "solve",
    "nonsolve",
    "daemon",
    "d-nonsolve",
    "wake+read",
    "decode+",
    "to GGA",
    "client",
)


def _report(label: str, runs: list[dict[str, np.ndarray]], fast: list, spp: list) -> None:
    """Pooled figures of one source tree's runs."""
    print(f"== {label}: pooled over {len(runs)} runs")
    for part in PARTS:
        ms = np.concatenate([r[part] for r in runs])
        if np.isfinite(ms).all():
            print("  " + _line(f"{part:<10}", ms))
    for name, sel in (("fast-fix epochs (first 8 s of fixes)", fast), ("SPP epochs", spp)):
        if sel:
            print(f"  {name}:")
            for part in ("latency", "solve", "nonsolve", "d-nonsolve"):
                ms = np.concatenate([x[part] for x in sel])
                if len(ms) and np.isfinite(ms).all():  # a short run has no SPP epochs
                    print("    " + _line(f"{part:<10}", ms))
    lat = np.concatenate([r["latency"] for r in runs])
    print(
        f"  latency last byte -> NMEA GGA on the client: p50 {np.median(lat):.2f} ms, "
        f"p99 {np.percentile(lat, 99):.2f} ms (goal p99 <= {GOAL_P99_MS:g} ms)"
    )
    for part in ("nonsolve", "d-nonsolve"):
        rest = np.concatenate([r[part] for r in runs])
        if not np.isfinite(rest).all():
            continue
        print(
            f"  {part}: p50 {np.median(rest):.2f} ms, p99 {np.percentile(rest, 99):.2f} ms "
            f"(goal <= {GOAL_NONSOLVE_P50_MS:g} / {GOAL_NONSOLVE_P99_MS:g} ms); per run "
            + ", ".join(f"{np.median(r[part]):.2f}/{np.percentile(r[part], 99):.2f}" for r in runs)
        )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=60.0, help="scenario length (10 Hz)")
    ap.add_argument("--runs", type=int, default=3, help="runs per source tree")
    ap.add_argument(
        "--root",
        type=Path,
        action="append",
        help="source tree to run the daemon from (repeatable; runs alternate); default: this one",
    )
    ap.add_argument(
        "--rt",
        type=int,
        default=0,
        metavar="PRIO",
        help="run the daemon (chrt --fifo) and this script's writer and client at this "
        "SCHED_FIFO priority, as a unit with CPUSchedulingPolicy=fifo would (needs root or "
        "CAP_SYS_NICE); 0: normal scheduling",
    )
    ap.add_argument(
        "--tcp",
        action="store_true",
        help="serve the UBX on a TCP socket the daemon connects to (tcp:HOST:PORT), not a pty",
    )
    ap.add_argument(
        "--nice",
        type=int,
        default=0,
        help="run the daemon at this niceness, as a unit with Nice= would, and this script "
        "too (below 0 needs root or CAP_SYS_NICE): a writer at a lower priority than the "
        "daemon's would be preempted between its write() and its time stamp",
    )
    ap.add_argument(
        "--line-rate",
        type=int,
        default=0,
        metavar="BAUD",
        help="write each epoch as a serial line at BAUD carries it (8N1, "
        f"{LINE_CHUNK_BYTES}-byte writes), the latency still timed from its last byte; "
        "0: each epoch in one write",
    )
    ap.add_argument(
        "--http-clients",
        type=int,
        default=0,
        metavar="N",
        help="also run each case with the status page (--output http:...) and N clients "
        "reading its event stream, alternating with runs without it; compares the epoch "
        "loop's p99 (goal: within 10 %%)",
    )
    ap.add_argument(
        "--scenario",
        choices=("builtin", "hksc"),
        default="builtin",
        help="builtin: the built-in BeiDou scenario (--seconds long); hksc: the HKSC "
        "station's 34 satellites of three systems as UBX RAWX (205 epochs)",
    )
    args = ap.parse_args()
    if args.nice:
        os.nice(args.nice)  # the daemon, started later, inherits it
    if args.rt:
        # this thread (the writer) and the client thread it starts later inherit it
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(args.rt))
    roots: list[Path] = [r.resolve() for r in args.root or [ROOT]]
    store: EphemerisStore | None = None
    extra: tuple[str, ...] = ()
    if args.scenario == "hksc":
        epochs, store = hksc_scenario()
        extra = ("--systems", "C,G,E")
        print(f"scenario hksc: {len(epochs)} epochs of 34 satellites (C, G, E) as UBX RXM-RAWX")
    else:
        sim = Simulator(table1_ephemerides(0.0), scenario_config(duration_s=args.seconds))
        epochs = [data for _ep, data in sim.ubx_epochs()]
    if args.line_rate and max(map(len, epochs)) * 10 / args.line_rate > 0.1:
        raise SystemExit(f"--line-rate {args.line_rate}: an epoch does not fit in 0.1 s")
    cases = [
        (f"{root}" + (f" + status page, {n} clients" if n else ""), root, n)
        for root in roots
        for n in ([0, args.http_clients] if args.http_clients else [0])
    ]
    runs: dict[str, list[dict[str, np.ndarray]]] = {c[0]: [] for c in cases}
    fast: dict[str, list[dict[str, np.ndarray]]] = {c[0]: [] for c in cases}
    spp: dict[str, list[dict[str, np.ndarray]]] = {c[0]: [] for c in cases}
    for k in range(args.runs):
        for label, root, n_http in cases:
            load = " ".join(f"{x:.2f}" for x in os.getloadavg())
            print(f"run {k + 1}/{args.runs} of {label} (load average {load})")
            got = one_run(epochs, root, args.rt, args.line_rate, args.tcp, n_http, store, extra)
            if got is None:
                print("  a count differs from the epoch count: run not measured")
                continue
            ms, ggas = got
            # GGA quality: 0 no fix, 1 a fix (fast or SPP); the scenario's fixes before its
            # first non-GEO SOW are fast fixes, SPP after the first fix of all-full epochs
            quality = np.array([int(g.split(b",")[6] or 0) for g in ggas])
            for part in ("latency", "loop", "solve", "nonsolve", "d-nonsolve"):
                if np.isfinite(ms[part]).all():
                    print("  " + _line(f"{part:<10}", ms[part]))
            runs[label].append(ms)
            fixed = np.flatnonzero(quality > 0)
            used = [int(g.split(b",")[7] or 0) for g in ggas]
            print(
                f"  epochs with a fix {len(fixed)} of {len(ggas)}; satellites used (GGA) "
                f"median {np.median(used):.0f}, min {min(used)}"
            )
            if len(fixed) and args.scenario == "builtin":
                first = fixed[0]
                # 8 s of fast fixes after the first one; SPP from 12 s after it on
                fast[label].append({p: v[first : first + 80] for p, v in ms.items()})
                spp[label].append({p: v[first + 120 :] for p, v in ms.items()})
    load = " ".join(f"{x:.2f}" for x in os.getloadavg())
    print(f"load average at the end: {load}")
    for label, _root, _n in cases:
        if not runs[label]:
            print(f"== {label}: no run could be measured")
            continue
        _report(label, runs[label], fast[label], spp[label])
    if args.http_clients:
        for root in roots:
            base, page = runs[f"{root}"], runs[f"{root} + status page, {args.http_clients} clients"]
            if not (base and page):
                continue
            print(f"== {root}: the status page with {args.http_clients} event-stream clients")
            for part in ("loop", "latency"):
                a = np.percentile(np.concatenate([r[part] for r in base]), 99)
                b = np.percentile(np.concatenate([r[part] for r in page]), 99)
                print(
                    f"  {part} p99: {a:.2f} ms without, {b:.2f} ms with "
                    f"({100 * (b - a) / a:+.1f} %; goal within 10 %)"
                )


if __name__ == "__main__":
    main()
