"""Flood: the daemon's epoch loop with and without a flood of NMEA TCP connections.

`bdsfix run` (soft descriptor limit 1024, the default cap of 64 NMEA clients) reads a
simulated 20 Hz receiver over TCP, in real time (`bdsfix simulate --realtime` relayed by
the bench) or, with ``--full-speed``, a pre-simulated stream as fast as it reads it. One
healthy NMEA client connects first and counts GGA over the whole run. In the flood runs
this process opens up to ``--flood`` connections at a time (its RLIMIT_NOFILE raised to
the hard limit for them), holds them 0.2 s, closes them and starts again, wave after wave,
from before the stream starts until the healthy client has every GGA; the daemon refuses
whatever does not fit under the cap. Runs alternate, without and with the flood.

Figures per run: the epoch loop's p50/p99/max (solve + publish, the daemon's STATUS), GGA
received by the healthy client vs epochs, connections made and refused, accept errors,
waves; then the median p99 without and with the flood and their ratio (the goal: within
20 %).

The harness is tests/support/flood.py (shared with tests/system/test_flood.py).

Run: python bench/bench_flood.py [--seconds 120] [--repeats 2] [--flood 2000] [--full-speed]
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from tests.support.flood import FloodResult, run_flood  # noqa: E402
from tests.support.load import RATE_HZ, make_stream  # noqa: E402


def line(label: str, r: FloodResult) -> str:
    st = r.status
    p50, p99, mx = (st.get(f"epoch_loop_{q}_ms", float("nan")) for q in ("p50", "p99", "max"))
    text = (
        f"  {label:<9} loop p50 {p50:5.2f} ms, p99 {p99:5.2f} ms, max {mx:6.1f} ms; "
        f"GGA {r.gga}/{r.epochs_expected}; exit {r.daemon_rc}"
    )
    if r.flood_size:
        text += (
            f"; {r.waves} waves of {r.flood_size}: {r.flood_connected} connections "
            f"({r.flood_slow} slow, {r.flood_failed} failed), refused "
            f"{st.get('nmea_clients_refused', 0)}, accepted {st.get('nmea_clients_accepted', 0)}, "
            f"accept errors {st.get('nmea_accept_errors', 0)}"
        )
    return text


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=120.0, help="simulated data per run [s]")
    ap.add_argument("--repeats", type=int, default=2, help="pairs of runs (without, with)")
    ap.add_argument("--flood", type=int, default=2000, help="connections per wave")
    ap.add_argument("--max-clients", type=int, default=64, help="the daemon's cap")
    ap.add_argument(
        "--full-speed", action="store_true", help="send a pre-simulated stream at full speed"
    )
    a = ap.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="bdsfix-flood-"))
    epochs = round(a.seconds * RATE_HZ)
    stream = None
    if a.full_speed:
        stream = work / "stream.ubx"
        epochs = make_stream(stream, a.seconds / 60.0)
    pace = "full speed" if a.full_speed else "real time"
    print(
        f"bench_flood: {a.seconds:g} s at {RATE_HZ:g} Hz = {epochs} epochs per run ({pace}); "
        f"waves of up to {a.flood} connections; cap {a.max_clients}; {a.repeats} pairs"
    )
    p99: dict[bool, list[float]] = {False: [], True: []}
    complete = True
    try:
        for i in range(a.repeats):
            for flood in (False, True) if i % 2 == 0 else (True, False):
                run_dir = work / f"run{i}-{int(flood)}"
                run_dir.mkdir()
                r = run_flood(
                    epochs,
                    run_dir,
                    stream=stream,
                    realtime_s=0.0 if a.full_speed else a.seconds,
                    n_flood=a.flood,
                    max_clients=a.max_clients,
                    flood=flood,
                )
                print(line("flood" if flood else "no flood", r), flush=True)
                p99[flood].append(r.status.get("epoch_loop_p99_ms", float("nan")))
                complete &= r.gga == epochs and r.daemon_rc == 0
                if "Traceback" in r.daemon_stderr:
                    print(r.daemon_stderr[-3000:])
    finally:
        shutil.rmtree(work, ignore_errors=True)
    quiet, flooded = statistics.median(p99[False]), statistics.median(p99[True])
    ratio = flooded / quiet
    runs = {k: ", ".join(f"{v:.2f}" for v in vs) for k, vs in p99.items()}
    print(
        f"  loop p99 median: no flood {quiet:.2f} ms (runs {runs[False]}), "
        f"flood {flooded:.2f} ms (runs {runs[True]}); "
        f"ratio {ratio:.2f} ({'within' if abs(ratio - 1.0) <= 0.2 else 'NOT within'} 20 %)"
    )
    print(f"  healthy client got every GGA in every run: {'yes' if complete else 'NO'}")


if __name__ == "__main__":
    main()
