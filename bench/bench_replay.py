"""Replay throughput: `bdsfix replay --max-speed` of a simulated 10 Hz UBX capture.

The virtual receiver (`bdsfix simulate`, near Beijing, warm start) writes N minutes of
10 Hz UBX to a file; `bdsfix replay FILE --max-speed` then runs it through the stream path
(driver, tracker, solver, outputs) with NMEA to /dev/null (the default output
kind, every sentence built) and, apart, with only JSONL. Prints epochs per second of wall
time and of CPU time (user + system of the replay process), median of the runs.

With --profile, one more replay runs under cProfile and the share of the main costs is
printed (NMEA sentences, solver, sky view, UBX decoding: a capture file at full speed is
read in the loop's own thread, so cProfile sees it all; its per-call overhead inflates
the shares of code made of many small calls).

Run: python bench/bench_replay.py [--minutes 60] [--runs 3] [--profile]
(prints figures; no assertions)
"""

from __future__ import annotations

import argparse
import os
import pstats
import re
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _bdsfix() -> list[str]:
    return [sys.executable, "-m", "service"]


def replay_once(capture: Path, outputs: list[str]) -> tuple[float, float, int]:
    """Wall [s], CPU [s] and epochs of one replay."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    proc = subprocess.run(
        [*_bdsfix(), "replay", str(capture), "--max-speed", *outputs],
        cwd=ROOT,
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    m = re.search(r"bdsfix replay: (\d+) epochs", proc.stderr)
    return wall, cpu, int(m.group(1)) if m else 0


def profile_shares(capture: Path, workdir: Path) -> None:
    prof = workdir / "replay.prof"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "cProfile",
            "-o",
            str(prof),
            "-m",
            "service",
            "replay",
            str(capture),
            "--max-speed",
            "--nmea-out",
            os.devnull,
        ],
        cwd=ROOT,
        check=True,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    stats = pstats.Stats(str(prof)).stats  # type: ignore[attr-defined]

    def cum(file_part: str, func: str) -> float:
        return sum(v[3] for k, v in stats.items() if file_part in k[0] and k[2] == func)

    total = cum("service/daemon/loop.py", "run")
    parts = {
        "NMEA sentences": cum("service/output/nmea.py", "lead_sentences")
        + cum("service/output/nmea.py", "sentences_after_gga"),
        "solver": cum("service/engine/solver.py", "solve")
        - cum("service/engine/solver.py", "sky_view"),
        "sky view (GSV)": cum("service/engine/solver.py", "sky_view"),
        "UBX decoding (drivers)": cum("drivers/source.py", "__iter__"),
    }
    print(f"  profile (cProfile of the main thread, {total:.1f} s in the stream loop):")
    for name, t in parts.items():
        print(f"    {name:<28} {100 * t / total:5.1f} %")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=60.0, help="length of the capture")
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--profile", action="store_true", help="also print the cost shares")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory(prefix="bench_replay.") as tmp:
        workdir = Path(tmp)
        capture = workdir / "sim.ubx"
        t0 = time.perf_counter()
        subprocess.run(
            [
                *_bdsfix(),
                "simulate",
                "--duration-s",
                str(args.minutes * 60.0),
                "--rate-hz",
                "10",
                "--out",
                str(capture),
            ],
            cwd=ROOT,
            check=True,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        print(
            f"bench_replay: {args.minutes:g} min of 10 Hz UBX ({capture.stat().st_size / 1e6:.1f} "
            f"MB, simulated in {time.perf_counter() - t0:.0f} s); {os.cpu_count()} CPUs, "
            f"load average {os.getloadavg()[0]:.1f}"
        )
        for label, outputs in (
            ("NMEA to /dev/null", ["--nmea-out", os.devnull]),
            ("JSONL only", ["--jsonl-out", os.devnull]),
        ):
            walls, cpus, n = [], [], 0
            for _ in range(args.runs):
                wall, cpu, n = replay_once(capture, outputs)
                walls.append(wall)
                cpus.append(cpu)
            w, c = statistics.median(walls), statistics.median(cpus)
            print(
                f"  {label:<18} {n} epochs: {n / w:6.0f} epochs/s of wall ({w:.1f} s), "
                f"{n / c:6.0f} epochs/s of CPU ({c:.1f} s); median of {args.runs}"
            )
        if args.profile:
            profile_shares(capture, workdir)
        print(f"load average {os.getloadavg()[0]:.1f} at the end")


if __name__ == "__main__":
    main()
