"""Benchmark: the per-epoch solve on HKSC (fast and SPP, from the Earth's centre) of two
source trees in one sitting, each timed in its own interpreter, alternately, so that both
see the same machine.

Run: git -C . archive f379b48 | tar -x -C /tmp/before
     python bench/bench_solve_ab.py /tmp/before [AFTER_TREE] [--rounds 8] [--repeats 3]
(AFTER_TREE defaults to this repository.) Prints the median and p99 per epoch of CPU time
(time.process_time, the steadier figure on a shared machine) and wall time, each round's
CPU median, and the load averages; no assertions.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HKSC = ROOT.parent / "shared" / "data" / "hksc-2021"


def child(tree: str, repeats: int) -> None:
    """Time every HKSC epoch ``repeats`` times with the tree's solver; print JSON."""
    sys.path.insert(0, tree)
    from drivers.rinex import RinexObsReader
    from service.commands.solve import load_navigation
    from service.engine.solver import fractionalize, solve

    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    epochs = list(RinexObsReader(HKSC / "hksc1610.obs"))
    out: dict[str, dict[str, list[float]]] = {}
    for name, data in (("fast", [fractionalize(e) for e in epochs]), ("spp", epochs)):
        for ep in data[:20]:  # warm the caches (ephemeris columns, orbit constants)
            solve(ep, store, iono, solver=name)
        cpu, wall = [], []
        for _ in range(repeats):
            for ep in data:
                c0, w0 = time.process_time(), time.perf_counter()
                solve(ep, store, iono, solver=name)
                w1, c1 = time.perf_counter(), time.process_time()
                cpu.append(c1 - c0)
                wall.append(w1 - w0)
        out[name] = {"cpu": cpu, "wall": wall}
    print(json.dumps(out))


def _pct(values: list[float], q: float) -> float:
    s = sorted(values)
    k = (len(s) - 1) * q / 100.0
    lo = int(k)
    hi = min(lo + 1, len(s) - 1)
    return (s[lo] + (s[hi] - s[lo]) * (k - lo)) * 1e3


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("before", nargs="?")
    ap.add_argument("after", nargs="?", default=str(ROOT))
    ap.add_argument("--rounds", type=int, default=8)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args.child, args.repeats)
        return
    if args.before is None:
        ap.error("the tree to compare with is missing")
    trees = {"before": args.before, "after": args.after}
    env = dict(os.environ, OPENBLAS_NUM_THREADS="1", OMP_NUM_THREADS="1")
    times = {t: {s: {"cpu": [], "wall": []} for s in ("fast", "spp")} for t in trees}
    rounds: dict[str, dict[str, list[float]]] = {t: {"fast": [], "spp": []} for t in trees}
    loads = [os.getloadavg()]
    for r in range(args.rounds):
        for t in list(trees) if r % 2 == 0 else list(trees)[::-1]:
            cmd = [sys.executable, __file__, "--child", trees[t], "--repeats", str(args.repeats)]
            run = subprocess.run(cmd, env=env, capture_output=True, text=True, check=True)
            got = json.loads(run.stdout)
            for s, figures in got.items():
                for k, v in figures.items():
                    times[t][s][k] += v
                rounds[t][s].append(_pct(figures["cpu"], 50))
        loads.append(os.getloadavg())
    for s in ("fast", "spp"):
        for t in trees:
            c, w = times[t][s]["cpu"], times[t][s]["wall"]
            per_round = " ".join(f"{v:.3f}" for v in rounds[t][s])
            print(
                f"{s:>4} {t:>6}: CPU median {_pct(c, 50):.3f} p99 {_pct(c, 99):.3f} ms, "
                f"wall median {_pct(w, 50):.3f} p99 {_pct(w, 99):.3f} ms ({len(c)} solves; "
                f"CPU median per round {per_round})"
            )
    print("load average (1/5/15 min) before each round and at the end:")
    print("  " + " ".join(f"{a:.2f}/{b:.2f}/{c:.2f}" for a, b, c in loads))


if __name__ == "__main__":
    main()
