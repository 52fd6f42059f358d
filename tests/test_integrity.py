"""Integrity: no fix is published with a wrong integer ambiguity.

1. Monte Carlo on the virtual receiver (real 2021 broadcast ephemerides): a range outlier of
   50 m to 150 km on one satellite per epoch. The true integers come from the simulator's
   outlier-free pseudoranges (see bench/bench_integrity.py, which runs the large version).
2. The real HKSC replay with emulated restarts at several instants: every ambiguity the fast
   fix recovered is confirmed by the satellite's later D1 SOW (the pipeline's check), read
   from the STATUS counters a ZeroMQ subscriber receives from `bdsfix replay`.
"""

from __future__ import annotations

import json
import re
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import zmq

from bench.bench_integrity import load_nav, run_trials
from service.engine import SolverConfig
from tests._independent import DATA

ROOT = Path(__file__).resolve().parents[1]
HK = DATA / "hksc-2021"


@pytest.fixture(scope="module")
def nav():
    return load_nav()


def test_monte_carlo_outliers_never_publish_a_wrong_ambiguity(nav):
    t = run_trials(400, seed=3, nav=nav)
    assert t.trials == 400
    assert t.clean_fixes >= 0.95 * t.trials  # the scenario is one where the fast fix works
    assert t.clean_wrong_ambiguity == 0
    assert t.outlier_wrong_ambiguity == 0, t.wrong
    # not vacuous: outliers were both absorbed into published fixes and refused, on full
    # and on fractional satellites, small and large
    assert t.outlier_fixes > 50 and t.outlier_refusals > 50
    for kind in ("full", "frac"):
        assert t.by_bin[f"fix {kind} 50-300 m"] > 0
        assert t.by_bin[f"refused {kind} 30000-150000 m"] > 0
    assert t.outlier_fixes + t.outlier_refusals == t.trials


def test_monte_carlo_counts_wrong_ambiguities_when_the_residual_check_is_off(nav):
    """The counter is live: without the residual check, outliers do yield wrong integers."""
    t = run_trials(300, seed=11, nav=nav, cfg=SolverConfig(resid_max_m=1e12))
    assert t.outlier_refusals < 0.05 * t.trials
    assert t.outlier_wrong_ambiguity >= 3, t.wrong


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


RESTARTS = [(5.0, 0), (40.0, 1), (80.0, 2), (120.0, 3), (160.0, 4), (185.0, 5)]


def test_hksc_restarts_every_recovered_ambiguity_confirmed_by_d1_sow():
    ctx = zmq.Context()
    runs = []
    for restart_s, seed in RESTARTS:
        endpoint = f"tcp://127.0.0.1:{_free_port()}"
        sub = ctx.socket(zmq.SUB)
        sub.setsockopt(zmq.LINGER, 0)
        sub.setsockopt(zmq.SUBSCRIBE, b"STATUS")
        sub.connect(endpoint)  # before the replay binds: no STATUS is missed
        proc = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "service.cli",
                "replay",
                str(HK / "hksc1610.obs"),
                "--nav",
                str(HK / "hksc1610.nav"),
                "--restart-at",
                str(restart_s),
                "--seed",
                str(seed),
                "--speed",
                "100",
                "--zmq",
                endpoint,
                "--nmea-out",
                "/dev/null",
                "--status-interval-s",
                "0.2",
            ],
            cwd=ROOT,
            stderr=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
        )
        runs.append((restart_s, sub, proc, []))
    try:
        deadline = time.monotonic() + 120
        while any(p.poll() is None for _, _, p, _ in runs) and time.monotonic() < deadline:
            for _, sub, _, got in runs:
                while sub.poll(10):
                    _topic, body = sub.recv_multipart()
                    got.append(json.loads(body)["counters"])
        time.sleep(0.3)
        for _, sub, _, got in runs:
            while sub.poll(100):
                got.append(json.loads(sub.recv_multipart()[1])["counters"])
    finally:
        for _, sub, proc, _ in runs:
            proc.kill()
            sub.close(0)
        ctx.term()
    total_checks = 0
    for restart_s, _, proc, got in runs:
        err = proc.stderr.read().decode() if proc.stderr else ""
        assert proc.wait() == 0, err
        assert got, f"restart {restart_s}: no STATUS received"
        final = got[-1]
        summary = re.search(r"fixes fast (\d+).*integrity checks (\d+), failures (\d+)", err)
        assert summary, err
        fast, checks, failures = map(int, summary.groups())
        assert final.get("fix_fast", 0) == fast > 0, (restart_s, final)
        assert final.get("integrity_checks", 0) == checks > 0, (restart_s, final)
        assert final.get("integrity_failures", 0) == failures == 0, (restart_s, final)
        # every non-GEO whose integer was recovered after the restart was checked
        assert checks >= 5, (restart_s, checks)
        total_checks += checks
    assert total_checks >= 6 * 5


def test_hksc_restart_jsonl_integers_match_the_full_pseudoranges(tmp_path):
    """Independently of the pipeline's check: every integer of every fast fix, applied to
    the epoch's fractional value, gives the RINEX full pseudorange within c T / 2."""
    import georinex

    out = tmp_path / "fixes.jsonl"
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "service.cli",
            "replay",
            str(HK / "hksc1610.obs"),
            "--nav",
            str(HK / "hksc1610.nav"),
            "--restart-at",
            "60",
            "--max-speed",
            "--jsonl-out",
            str(out),
        ],
        cwd=ROOT,
        capture_output=True,
        timeout=120,
    )
    assert res.returncode == 0, res.stderr
    fixes = [
        r
        for r in map(json.loads, out.read_text().splitlines())
        if r["class"] == "FIX" and r["mode"] == "fast"
    ]
    assert fixes
    obs = georinex.load(HK / "hksc1610.obs", use="C", meas=["C2I"])
    row_of = {round(_tow(t)): i for i, t in enumerate(obs.time.values)}
    svs = [str(s) for s in obs.sv.values]
    c2i = obs["C2I"].values  # (time, sv)
    ct = 299_792_458.0 * 1e-3
    n_checked = 0
    for f in fixes:
        row = row_of[round(f["gpst_tow_s"])]
        for prn, n in f["ambiguity"].items():
            pr = float(c2i[row, svs.index(prn)])
            z = pr % ct  # the fractional value the replay solved with
            assert round((pr - z) / ct) == n, (f["gpst_tow_s"], prn, n)
            n_checked += 1
    assert n_checked >= 20


def _tow(t64) -> float:
    import numpy as np

    gps0 = np.datetime64("1980-01-06T00:00:00", "ns")
    ns = (np.datetime64(t64, "ns") - gps0) / np.timedelta64(1, "ns")
    return float(ns / 1e9) % 604800.0
