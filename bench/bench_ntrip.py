"""Benchmark: `bdsfix run` with ephemerides from an NTRIP caster, wall-clock figures.

Run: python bench/bench_ntrip.py [--rounds N]   (prints figures; no assertions)

The set-up of tests/system/test_ntrip.py (pygnssutils' caster on loopback serving RTCM 1042
built from the HKSC nav once a second; the virtual receiver at Hong Kong on a pty, with no
ephemeris in its stream; no nav file), but here the receiver starts streaming as soon as the
daemon says it runs, without waiting for the caster, as a receiver switched on with the
daemon would. Per round it prints:

- wall time from the daemon's start (process spawn) to its first network ephemeris;
- the first fast fix in data time since the stream's first epoch;
- after a SIGKILL of the caster held down for ``outage_s``: wall time from the caster's
  restart to the daemon's reconnection (bounded by ntrip_reconnect_max_s, 4 s).
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.support.ntrip_caster import Caster
from tests.support.replay import LiveReplay
from tests.system.test_ntrip import PASSWORD, USER, _fix_at, _records, _scene, _wait


def one_round(tmp: Path, outage_s: float) -> tuple[float, float, float]:
    sim, rtcm, _sets = _scene(tmp, duration_s=20.0)
    epochs = list(sim.ubx_epochs())
    jsonl = tmp / "fixes.jsonl"
    master, slave = os.openpty()
    with Caster(rtcm, user=USER, password=PASSWORD) as caster:
        t_spawn = time.monotonic()
        args = ["run", "--source", os.ttyname(slave), "--nav", caster.url(USER, PASSWORD)]
        args += ["--state-dir", str(tmp / "state"), "--nmea-tcp", "", "--jsonl-out", str(jsonl)]
        with LiveReplay(args) as run:
            _wait(lambda: "bdsfix running" in run.stderr(), "start", run)
            t_first_eph = None
            for i, (_ep, data) in enumerate(epochs):
                if t_first_eph is None and "receiving ephemerides" in run.stderr():
                    t_first_eph = time.monotonic() - t_spawn
                if i == 100:
                    caster.kill()
                    time.sleep(outage_s)
                    caster.start()
                    t_back = time.monotonic()
                    _wait(lambda: "reconnected after" in run.stderr(), "reconnection", run)
                    reconnect_s = time.monotonic() - t_back
                os.write(master, data)
                time.sleep(1.0 / sim.cfg.rate_hz)
            _wait(lambda: _fix_at(jsonl, epochs[-1][0].tag_gpst_tow_s), "last fix", run)
            run.proc.terminate()
            run.finish()
    os.close(master)
    os.close(slave)
    fixes = [r for r in _records(jsonl) if r["class"] == "FIX"]
    first_fast = next(f["since_start_s"] for f in fixes if f["mode"] == "fast")
    return t_first_eph or float("nan"), first_fast, reconnect_s


def main() -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--rounds", type=int, default=3)
    args = p.parse_args()
    rows = []
    for k in range(args.rounds):
        outage_s = (1.0, 3.0, 6.0)[k % 3]
        with tempfile.TemporaryDirectory() as d:
            row = one_round(Path(d), outage_s)
        rows.append(row)
        print(
            f"round {k + 1}: first network ephemeris {row[0]:.2f} s after spawn (wall); "
            f"first fast fix {row[1]:.2f} s of stream (data); caster down {outage_s:.0f} s, "
            f"reconnected {row[2]:.2f} s after its restart (wall)",
            flush=True,
        )
    print(
        f"median over {len(rows)}: first ephemeris {statistics.median(r[0] for r in rows):.2f} s,"
        f" first fast fix {statistics.median(r[1] for r in rows):.2f} s, "
        f"reconnect {statistics.median(r[2] for r in rows):.2f} s"
    )


if __name__ == "__main__":
    main()
