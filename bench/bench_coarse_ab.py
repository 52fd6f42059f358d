"""Benchmark: the coarse-time first fix (service/engine/coarse.py) of two source trees on the
same corpora, each tree in its own interpreter, alternately: whether they decide the same
and how long each takes.

Corpora (as bench/bench_coarse.py and bench/bench_coarse_mc.py): HKSC 2021 restarted with
k = 0..3 GEOs full and every other range fractional, tags shifted 0 and +-2 s; the TST urban
drive, k = 0..3; a Monte Carlo of ``--trials`` (2000) globe-wide trials, seed 1, BeiDou
alone. Per epoch it compares what was decided (published or declined, the reason code, the
integers and whether they are absolute, the satellites used and left out, the candidate
count) and, where both published, the distance between the two positions and offsets.

Run: git -C . archive 9edc7dd | tar -x -C /tmp/before
     python bench/bench_coarse_ab.py /tmp/before [AFTER_TREE] [--rounds 2] [--trials 2000]
(AFTER_TREE defaults to this repository.) Prints, per corpus, the epochs whose decisions
differ (with the first few), the largest position and offset differences, and each tree's
CPU time per epoch (time.process_time, median and p99 over the rounds); no assertions.
"""

from __future__ import annotations

import argparse
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data"


def child(tree: str, out: str, trials: int) -> None:
    """Run the corpora with the tree's coarse-time fix; write the outcomes and times (JSON)."""
    sys.path.insert(0, tree)
    import service.engine.coarse as coarse_module
    from bench.bench_coarse import restarted
    from drivers.rinex import RinexObsReader
    from service.commands.solve import load_navigation
    from service.engine.coarse import CoarseConfig, CoarseResult, solve_coarse
    from service.engine.solver import IonoSet, SolverConfig, solve

    if not coarse_module.__file__ or not coarse_module.__file__.startswith(tree):
        raise SystemExit(f"{tree}: its service package was not the one imported")

    def record(res: CoarseResult) -> dict[str, Any]:
        f = res.fix
        return {
            "decision": (
                f.ok,
                f.reason_code,
                res.integers,
                res.absolute,
                f.used,
                dict(f.excluded),
                res.rows,
                res.candidates,
            ),
            "x": f.x_ecef_m,
            "offset": res.time_offset_s,
        }

    # the recordings beside this script's tree (a tree exported to /tmp has none beside it)
    hksc, tst = DATA / "hksc-2021", DATA / "hk-tst-urban-2019"
    tst_navs = [tst / "hksc1180.19b", tst / "hksc1180.19n"]
    cfg, ccfg = SolverConfig(), CoarseConfig()
    got: dict[str, list[dict[str, Any]]] = {}
    cpu: dict[str, list[float]] = {}
    corpora = (
        ("HKSC", hksc / "hksc1610.obs", [hksc / "hksc1610.nav"], (0.0, 2.0, -2.0)),
        ("TST", tst / "COM3_190428_124409.obs", tst_navs, (0.0,)),
    )
    for name, obs, navs, shifts in corpora:
        store, iono = load_navigation([str(n) for n in navs], systems="CGE")
        epochs = [
            e for e in RinexObsReader(obs, systems="CGE") if solve(e, store, iono, cfg, "spp").ok
        ]
        for k in (0, 1, 2, 3):
            for shift in shifts:
                key = f"{name} k={k} shift {shift:+.0f} s"
                got[key], cpu[key] = [], []
                for ep in epochs:
                    fe = restarted(ep, k, shift)
                    c0 = time.process_time()
                    res = solve_coarse(fe, store, iono, cfg, ccfg)
                    cpu[key].append(time.process_time() - c0)
                    got[key].append(record(res))
    if trials:
        import service.studies.coarse_mc as mc

        nav = DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f"
        store, iono = load_navigation([str(nav)], max_age_s=86_400.0, systems="C")
        iono = IonoSet(bds=iono.bds)
        key = f"MC {trials} trials"
        got[key], cpu[key] = [], []
        solve_mc = mc.solve_coarse

        def timed(*args: Any, **kw: Any) -> CoarseResult:
            c0 = time.process_time()
            res = solve_mc(*args, **kw)
            cpu[key].append(time.process_time() - c0)
            got[key].append(record(res))
            return res

        mc.solve_coarse = timed  # type: ignore[assignment]
        toe = [e.toe_sow_s for e in store.all() if e.prn.startswith("C")]
        mid = float(np.median(toe)) + 14.0  # BDT -> GPST
        mc.run(store, iono, 2333, (mid - 3600.0, mid + 3600.0), trials, 1)
    with open(out, "w") as fh:
        json.dump([got, cpu], fh)


def compare(a: list[dict[str, Any]], b: list[dict[str, Any]]) -> tuple[list[int], float, float]:
    """The epochs whose decisions differ, the largest position [m] and offset [s]
    differences where both published the same decision."""
    differ, dx, dt = [], 0.0, 0.0
    for i, (x, y) in enumerate(zip(a, b, strict=True)):
        if x["decision"] != y["decision"]:
            differ.append(i)
            continue
        if x["x"] is not None and y["x"] is not None:
            dx = max(dx, math.dist(x["x"], y["x"]))
        if x["offset"] is not None and y["offset"] is not None:
            dt = max(dt, abs(x["offset"] - y["offset"]))
    return differ, dx, dt


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("before")
    ap.add_argument("after", nargs="?", default=str(ROOT))
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--trials", type=int, default=2000)
    ap.add_argument("--child", nargs=2, metavar=("TREE", "OUT"))
    args = ap.parse_args()
    if args.child:
        child(args.child[0], args.child[1], args.trials)
        return
    trees = {"before": str(Path(args.before).resolve()), "after": str(Path(args.after).resolve())}
    runs: dict[str, list[tuple[dict, dict]]] = {t: [] for t in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for name, tree in trees.items():
                out = str(Path(tmp) / f"{name}-{r}.json")
                cmd = [sys.executable, __file__, tree, "--trials", str(args.trials)]
                subprocess.run([*cmd, "--child", tree, out], check=True, cwd=tmp)
                with open(out) as fh:
                    runs[name].append(tuple(json.load(fh)))
    before, after = runs["before"][0][0], runs["after"][0][0]
    for key in before:
        differ, dx, dt = compare(before[key], after[key])
        times = []
        for name in trees:
            ms = 1e3 * np.concatenate([np.asarray(c[key]) for _, c in runs[name]])
            times.append(f"{name} {np.median(ms):.2f}/{np.percentile(ms, 99):.2f}")
        first = [(i, before[key][i]["decision"][:2], after[key][i]["decision"][:2]) for i in differ]
        print(
            f"{key}: {len(before[key])} epochs, decisions differ {len(differ)} {first[:3]}; "
            f"max |dx| {dx:.3g} m, max |d offset| {dt:.3g} s; CPU ms p50/p99 {', '.join(times)}"
        )


if __name__ == "__main__":
    main()
