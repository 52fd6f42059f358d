"""Benchmark: receiver set-up against the virtual receiver on a real pty, and the fix that
follows.

Per run: ``bdsfix simulate --pty --wait-config`` (Table 1, near Beijing, 10 Hz) starts
silent; ``bdsfix configure --model MODEL`` sets it up (the wall time of the whole command,
Python start included, and of the set-up alone from its INFO lines are printed); then
``bdsfix run`` with ``--configure true`` on the same pty (warm store) until its first
conventional fix: the data time of its first fast fix (``since_start_s``: data time since
the daemon's first measurement, the tracking having restarted at the set-up) and that
fix's horizontal distance from the true place.

Run: python bench/bench_configure.py [--runs 5] [--model f9]   (prints; no assertions)
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from service.core.ephemeris import EphemerisStore  # noqa: E402
from service.sim.scenario import BEIJING, broadcast_table1  # noqa: E402

BDSFIX = [sys.executable, "-m", "service"]


def _wait(pred, what: str, limit_s: float = 120.0) -> None:
    end = time.monotonic() + limit_s
    while not pred():
        if time.monotonic() > end:
            raise SystemExit(f"hung: {what}")
        time.sleep(0.01)


def _fixes(path: Path) -> list[dict]:
    if not path.exists():
        return []
    text = path.read_text()
    recs = [json.loads(x) for x in text.splitlines()[: text.count("\n")]]
    return [r for r in recs if r["class"] == "FIX" and r["mode"] != "none"]


def one_run(work: Path, model: str) -> tuple[float, float, float, float]:
    state = work / "state"
    state.mkdir(mode=0o700)
    store = EphemerisStore()
    store.add_all(broadcast_table1())
    store.save(state / "ephemeris.json")
    err = work / "sim.err"
    with err.open("wb") as fh:
        sim = subprocess.Popen(
            [*BDSFIX, "simulate", "--pty", "--wait-config", "--duration-s", "120"],
            cwd=ROOT,
            stderr=fh,
        )
    try:
        _wait(lambda: err.read_text().count("\n") >= 1, "pty")
        dev = err.read_text().splitlines()[0]
        t = time.monotonic()
        out = subprocess.run(
            [*BDSFIX, "configure", "--source", dev, "--model", model, "-v"],
            cwd=ROOT,
            capture_output=True,
            text=True,
        )
        wall_s = time.monotonic() - t
        if out.returncode:
            raise SystemExit(out.stderr)
        # the set-up alone: pyserial open to the last ACK, timed inside a second command
        t = time.monotonic()
        code = (
            "import time,sys;from drivers.ubx_setup import configure_device;"
            "from service.core.receiver_setup import ReceiverSetup;t=time.monotonic();"
            f"configure_device({dev!r},115200,ReceiverSetup(model={model!r}));"
            "print(time.monotonic()-t)"
        )
        setup_s = float(
            subprocess.run(
                [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, check=True
            ).stdout
        )
        jsonl = work / "fixes.jsonl"
        argv = [*BDSFIX, "run", "--source", dev, "--configure", "true"]
        argv += ["--configure-model", model, "--state-dir", str(state), "--nmea-tcp", ""]
        argv += ["--zmq", "", "--jsonl-out", str(jsonl), "--log-level", "warning"]
        run = subprocess.Popen(argv, cwd=ROOT)
        try:
            _wait(lambda: any(f["mode"] == "spp" for f in _fixes(jsonl)), "conventional fix")
        finally:
            run.terminate()
            run.wait(60)
    finally:
        sim.terminate()
        sim.wait(60)
    first = next(f for f in _fixes(jsonl) if f["mode"] == "fast")
    lat, lon, _ = BEIJING
    dn = (first["lat_deg"] - lat) * 111_000.0
    de = (first["lon_deg"] - lon) * 111_000.0 * math.cos(math.radians(lat))
    return wall_s, setup_s, first["since_start_s"], math.hypot(dn, de)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--model", choices=["m8", "f9", "x20"], default="f9")
    args = ap.parse_args()
    rows = []
    for k in range(args.runs):
        with tempfile.TemporaryDirectory() as d:
            row = one_run(Path(d), args.model)
        rows.append(row)
        print(
            f"run {k + 1}: configure command {row[0]:.2f} s (set-up alone {row[1] * 1000:.0f} ms), "
            f"first fast fix at t = {row[2]:.2f} s data time, {row[3]:.1f} m from the truth",
            flush=True,
        )
    print(
        f"{args.model}, {args.runs} runs: configure command {min(r[0] for r in rows):.2f}-"
        f"{max(r[0] for r in rows):.2f} s; set-up alone {min(r[1] for r in rows) * 1000:.0f}-"
        f"{max(r[1] for r in rows) * 1000:.0f} ms; first fast fix t = "
        f"{min(r[2] for r in rows):.2f}-{max(r[2] for r in rows):.2f} s; horizontal error "
        f"{min(r[3] for r in rows):.1f}-{max(r[3] for r in rows):.1f} m"
    )


if __name__ == "__main__":
    main()
