"""Benchmark: the ephemeris store after a day and after a year unattended.

A simulated history (tests/support/history.py: the 44 healthy BDS satellites of the HK 2024
navigation file, a new set of each every hour as ICD B1I 5.2.4.9 has it) is fed through the
pipeline as the daemon feeds it: every set through ``Pipeline.add_ephemeris`` (entry
checks, the count bound), one measurement epoch an hour (``Pipeline.on_epoch``), and a
store save every simulated day as ``Runner.save_store`` does it (prune, snapshot, hand the
snapshot to the ``StoreWriter`` thread). Then, for 1 day and 1 year of history:

- store size: sets held and bytes on disk;
- save: the loop's share (prune + snapshot + submit: what blocks the receiver loop), the
  writer thread's write, the longest stall of a busy main-thread loop while the thread
  writes (the interpreter lock), and the same write done synchronously (``write_store``);
- per-solve cost: ``service.engine.solver.solve`` (fast fix) on one epoch of pseudoranges
  generated from the sets the store selects (HK receiver, 10 deg mask, GEOs full).

Prints the figures and the year/day ratios; size and solve cost must agree within 10 %, and
the loop's share of a save must stay under 50 ms.

Run: python bench/bench_store.py [--days 365] [--solves 400] [--saves 30]
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import tempfile
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.core.ephemeris import EphemerisStore, write_store  # noqa: E402
from service.core.geometry import geodetic_to_ecef  # noqa: E402
from service.core.orbit import EphemerisArrays  # noqa: E402
from service.core.timebase import gpst_to_bdt  # noqa: E402
from service.core.types import Ephemeris, MeasurementEpoch  # noqa: E402
from service.daemon.loop import SWITCH_INTERVAL_S  # noqa: E402
from service.daemon.store_writer import StoreWriter  # noqa: E402
from service.engine.pipeline import Pipeline  # noqa: E402
from service.engine.solver import fractionalize, solve  # noqa: E402
from service.sim.rangegen import true_ranges  # noqa: E402
from tests.support.history import base_sets, history, time_tag  # noqa: E402

HK_LAT_DEG, HK_LON_DEG, HK_ALT_M = 22.30, 114.18, 60.0
ELMASK_DEG = 10.0
HOURS_PER_SAVE = 24
LOOP_SHARE_MAX_S = 0.050
AGREE = 0.10


@dataclass(frozen=True, slots=True)
class Figures:
    label: str
    fed: int
    held: int
    file_bytes: int
    feed_s: float
    feed_save_s: list[float]
    loop_save_s: list[float]
    write_s: list[float]
    stall_s: list[float]
    sync_write_s: list[float]


def _save(pipeline: Pipeline, writer: StoreWriter) -> float:
    """What Runner.save_store does in the loop; returns its duration [s]."""
    t0 = time.perf_counter()
    pipeline.prune_store()
    writer.submit(pipeline.store.snapshot())
    return time.perf_counter() - t0


def _stall_during_write(pipeline: Pipeline, writer: StoreWriter) -> tuple[float, float, float]:
    """One save: the loop's share, the thread's write and the longest gap [s] between two
    steps of a busy main-thread loop while the thread writes."""
    loop_s = _save(pipeline, writer)
    t0 = last = time.perf_counter()
    stall = 0.0
    done = threading.Event()
    threading.Thread(target=lambda: done.set() if writer.idle() else None, daemon=True).start()
    while not done.is_set():
        now = time.perf_counter()
        stall = max(stall, now - last)
        last = now
    return loop_s, time.perf_counter() - t0, stall


def _epoch(store: EphemerisStore, gpst_week: int, gpst_tow_s: float) -> MeasurementEpoch:
    """Pseudoranges at an HK receiver from the sets the store selects (GEOs full)."""
    bw, bs = gpst_to_bdt(gpst_week, gpst_tow_s)
    picked = [store.select(p, bw, bs) for p in store.prns]
    ephs: list[Ephemeris] = [e for e in picked if e is not None]
    rx = geodetic_to_ecef(math.radians(HK_LAT_DEG), math.radians(HK_LON_DEG), HK_ALT_M)
    tr = true_ranges(
        EphemerisArrays.from_ephemerides(ephs), rx, gpst_week, gpst_tow_s, 1e-4, tropo=True
    )
    vis = np.flatnonzero(tr.el_rad >= math.radians(ELMASK_DEG))
    prns = [tr.prn[i] for i in vis]
    epoch = MeasurementEpoch.from_columns(
        tr.tag_gpst_week,
        tr.tag_gpst_tow_s,
        prns,
        ["B1I"] * len(prns),
        tr.pr_m[vis],
        cn0_dbhz=np.full(len(prns), 42.0),
    )
    return fractionalize(epoch)


def run_history(label: str, days: int, saves: int, state: Path) -> tuple[Figures, Pipeline]:
    bases = base_sets()
    pipeline = Pipeline(EphemerisStore())
    path = state / label / "ephemeris.json"
    writer = StoreWriter(path)
    feed_save_s: list[float] = []
    fed = hours = 0
    t0 = time.perf_counter()
    for ev in history(bases, days * 24):
        if isinstance(ev, MeasurementEpoch):
            pipeline.on_epoch(ev)
            hours += 1
            if hours % HOURS_PER_SAVE == 0:
                feed_save_s.append(_save(pipeline, writer))
        else:
            pipeline.add_ephemeris(ev)
            fed += 1
    feed_s = time.perf_counter() - t0
    writer.idle()
    loop_save_s, write_s, stall_s, sync_s = [], [], [], []
    for _ in range(saves):
        loop_s, w_s, st_s = _stall_during_write(pipeline, writer)
        loop_save_s.append(loop_s)
        write_s.append(w_s)
        stall_s.append(st_s)
        t1 = time.perf_counter()
        write_store(path, pipeline.store.snapshot())
        sync_s.append(time.perf_counter() - t1)
    writer.close()
    held, size = len(pipeline.store), path.stat().st_size
    figures = Figures(
        label, fed, held, size, feed_s, feed_save_s, loop_save_s, write_s, stall_s, sync_s
    )
    return figures, pipeline


def solve_costs(
    pipes: dict[str, Pipeline], solves: int
) -> tuple[dict[str, list[float]], dict[str, tuple[int, str]]]:
    """Per-solve times [s] for each store, interleaved so machine load hits both alike."""
    t = time_tag(base_sets()[0])  # the last hour's epoch
    epochs = {k: _epoch(p.store, t.gpst_week, t.gpst_tow_s) for k, p in pipes.items()}
    info = {}
    for k, p in pipes.items():
        fix = solve(epochs[k], p.store, solver="fast")
        info[k] = (len(epochs[k]), f"{fix.mode}/{fix.reason_code or 'ok'}")
    times: dict[str, list[float]] = {k: [] for k in pipes}
    for _ in range(solves):
        for k, p in pipes.items():
            t0 = time.perf_counter()
            solve(epochs[k], p.store, solver="fast")
            times[k].append(time.perf_counter() - t0)
    return times, info


def _ms(values: list[float]) -> str:
    return f"median {1e3 * statistics.median(values):7.2f} ms, max {1e3 * max(values):7.2f} ms"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=int, default=365, help="the long history [days]")
    ap.add_argument("--solves", type=int, default=400, help="timed solves per store")
    ap.add_argument("--saves", type=int, default=30, help="timed saves per store")
    args = ap.parse_args()
    sys.setswitchinterval(SWITCH_INTERVAL_S)  # as the daemon's loop runs
    with tempfile.TemporaryDirectory() as tmp:
        state = Path(tmp)
        figs, pipes = {}, {}
        for label, days in (("1 day", 1), (f"{args.days} days", args.days)):
            figs[label], pipes[label] = run_history(label, days, args.saves, state)
        times, info = solve_costs(pipes, args.solves)
    day, year = figs.values()
    print(f"history: {len(base_sets())} satellites, a new set of each every hour")
    for f in (day, year):
        sats, fix = info[f.label]
        print(f"{f.label}:")
        print(
            f"  fed {f.fed} sets in {f.feed_s:.1f} s; held {f.held} sets, "
            f"{f.file_bytes / 1024:.0f} KiB on disk"
        )
        print(f"  {len(f.feed_save_s)} daily saves while fed, loop's share: {_ms(f.feed_save_s)}")
        print(f"  save, loop's share (prune + snapshot + submit): {_ms(f.loop_save_s)}")
        print(f"  save, writer thread's write:                    {_ms(f.write_s)}")
        print(f"  save, longest loop stall during that write:     {_ms(f.stall_s)}")
        print(f"  save, the same write done synchronously:        {_ms(f.sync_write_s)}")
        print(f"  solve (fast fix, {sats} sats, {fix}):  {_ms(times[f.label])}")
    ratios = {
        "sets held": year.held / day.held,
        "file size": year.file_bytes / day.file_bytes,
        "save write (median)": statistics.median(year.write_s) / statistics.median(day.write_s),
        "save loop share (median)": statistics.median(year.loop_save_s)
        / statistics.median(day.loop_save_s),
        "solve (median)": statistics.median(times[year.label])
        / statistics.median(times[day.label]),
    }
    print(f"ratios {year.label} / {day.label}:")
    for name, r in ratios.items():
        print(f"  {name:<26} {r:.3f}")
    worst_loop = max(max(f.loop_save_s + f.feed_save_s) for f in figs.values())
    ok = (
        abs(ratios["sets held"] - 1) <= AGREE
        and abs(ratios["solve (median)"] - 1) <= AGREE
        and worst_loop < LOOP_SHARE_MAX_S
    )
    print(
        f"{'OK' if ok else 'NOT MET'}: size and solve cost within {AGREE:.0%}, "
        f"loop's share of a save at most {1e3 * worst_loop:.2f} ms "
        f"(limit {1e3 * LOOP_SHARE_MAX_S:.0f} ms)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
