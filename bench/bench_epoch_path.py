"""Benchmark: where an epoch's non-solve time goes, stage by stage, in one process.

``bench/bench_latency.py`` times the daemon end to end (write -> read -> solve -> GGA on the
client) with its scheduling noise. This script runs the same stages of the receiver path
in one process, on the built-in scenario's UBX epochs (10 Hz, BeiDou, SFRBX + MEASX + RAWX),
and times each with :func:`time.perf_counter`:

- ``framing``: the framer finds the epoch's frames in its bytes (checksums included);
- ``decode``: the frames mapped to events (``decode_frame``: SFRBX, MEASX, then RAWX,
  whose arrival completes and builds the epoch);
- ``subframes``: the pipeline takes the subframes decoded before the epoch;
- ``solve``: the pipeline's ``on_epoch`` (what bench_latency calls the solve);
- ``utc``, ``lead``, ``send``: the fix's UTC, its RMC/VTG/GGA, and their ``send`` by the
  NMEA TCP sink to a client in another process (the kernel's loopback delivery and the
  client's wake-up are in the send);
- ``nonsolve``: all but the solve (the daemon's share of bench_latency's non-solve time;
  the pty's wake-up and read are not here).

The caches matter more than the operations: between two epochs a shared machine's other
processes (and an idle CPU) evict the path's code and data, and everything after the
wake-up refills them. ``--mode`` sets what happens between epochs: ``hot`` nothing,
``trashed`` 24 MiB written then 10 ms asleep, ``idle`` 100 ms asleep (a receiver's epoch
interval). ``--root DIR`` (repeatable, runs alternating) times another source tree, e.g. an
export of main, in a fresh interpreter each.

Run: python bench/bench_epoch_path.py [--mode hot|trashed|idle] [--seconds 30] [--runs 2]
[--root DIR ...]   (prints p50/p90/p99 per stage; no assertions)
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
STAGES = ("framing", "decode", "subframes", "solve", "utc", "lead", "send", "nonsolve")

CLIENT = """
import socket, sys
s = socket.create_connection(("127.0.0.1", int(sys.argv[1])))
while s.recv(65536):
    pass
"""


def measure(root: Path, mode: str, seconds: float) -> dict[str, list[float]]:
    """Per-epoch stage times [ms] with the modules of ``root`` (run in this process)."""
    import gc
    import socket
    import time

    sys.path.insert(0, str(root))
    from drivers.source import StreamDecoder
    from service.core.ephemeris import EphemerisStore
    from service.core.types import MeasurementEpoch
    from service.engine.pipeline import Pipeline
    from service.output.nmea import fix_utc, lead_sentences
    from service.output.sinks import OutputSpec, open_sinks
    from service.sim.keplerian import table1_ephemerides
    from service.sim.scenario import scenario_config
    from service.sim.simulator import Simulator

    sim = Simulator(table1_ephemerides(0.0), scenario_config(duration_s=seconds))
    epochs = [data for _ep, data in sim.ubx_epochs()]
    store = EphemerisStore()
    store.add_all(table1_ephemerides(0.0))
    pipeline = Pipeline(store)
    decoder = StreamDecoder(gps_week=1845)
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    sinks = open_sinks([OutputSpec("nmea-tcp", f"127.0.0.1:{port}")])
    client = subprocess.Popen([sys.executable, "-c", CLIENT, str(port)])
    try:
        while not sinks[0].n_clients:  # type: ignore[attr-defined]
            time.sleep(0.01)
        junk = bytearray(24 << 20)
        gc.collect()
        gc.freeze()
        gc.disable()  # collections between epochs, as the receiver loop makes them
        pc = time.perf_counter
        out: dict[str, list[float]] = {s: [] for s in STAGES}
        for k, data in enumerate(epochs):
            if mode == "trashed":
                junk[::64] = bytes(len(junk) // 64)
                time.sleep(0.01)
            elif mode == "idle":
                time.sleep(0.1)
            t0 = pc()
            frames = decoder.framer.feed(data)
            t1 = pc()
            events = [ev for frame in frames for ev in decoder.decode_frame(frame)]
            t2 = pc()
            epoch = None
            for ev in events:
                if isinstance(ev, MeasurementEpoch):
                    epoch = ev
                else:
                    pipeline.on_subframe(ev)
            t3 = pc()
            if epoch is None:
                continue
            fix = pipeline.on_epoch(epoch).fix
            t4 = pc()
            utc = fix_utc(fix)
            t5 = pc()
            lead = b"".join(lead_sentences(fix, utc=utc))
            t6 = pc()
            sinks[0].write_nmea(lead)
            t7 = pc()
            gc.collect(0)
            if k < 20:  # the scenario's first epochs: start-up
                continue
            for name, dt in zip(
                STAGES,
                (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4, t6 - t5, t7 - t6),
                strict=False,
            ):
                out[name].append(dt * 1e3)
            out["nonsolve"].append((t7 - t0 - (t4 - t3)) * 1e3)
        return out
    finally:
        for sink in sinks:
            sink.close()
        client.wait(5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--mode", choices=("hot", "trashed", "idle"), default="trashed")
    ap.add_argument("--seconds", type=float, default=30.0, help="scenario length (10 Hz)")
    ap.add_argument("--runs", type=int, default=2, help="runs per source tree")
    ap.add_argument("--root", type=Path, action="append", help="source tree (repeatable)")
    ap.add_argument("--child", type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child is not None:  # one run, in its own interpreter: its figures as JSON
        print(json.dumps(measure(args.child, args.mode, args.seconds)))
        return
    import numpy as np

    roots = [r.resolve() for r in args.root or [ROOT]]
    pooled: dict[Path, dict[str, list[float]]] = {r: {s: [] for s in STAGES} for r in roots}
    for k in range(args.runs):
        for root in roots:
            cmd = [sys.executable, __file__, "--child", str(root), "--mode", args.mode]
            cmd += ["--seconds", str(args.seconds)]
            got = json.loads(subprocess.run(cmd, check=True, capture_output=True).stdout)
            for name in STAGES:
                pooled[root][name] += got[name]
            x = np.array(got["nonsolve"])
            print(f"run {k + 1}/{args.runs} {root}: nonsolve p50 {np.median(x):.3f} ms")
    for root in roots:
        print(f"== {root} ({args.mode}, {args.runs} runs)")
        for name in STAGES:
            x = np.array(pooled[root][name])
            print(
                f"  {name:<10} p50 {np.median(x):6.3f}  p90 {np.percentile(x, 90):6.3f}  "
                f"p99 {np.percentile(x, 99):6.3f} ms"
            )


if __name__ == "__main__":
    main()
