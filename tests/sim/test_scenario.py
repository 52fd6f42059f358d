"""The built-in scenario of `bdsfix replay`: first fast fix near 1 s, conventional after 6 s,
every fast fix equal to an SPP from the simulator's own full pseudoranges."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np

from service.commands.run import decode_chunks
from service.core.ephemeris import EphemerisStore
from service.core.types import MeasurementEpoch
from service.engine.solver import solve
from service.sim.keplerian import table1_ephemerides
from service.sim.scenario import builtin_scenario, scenario_config
from service.sim.simulator import Simulator
from tests.support.paths import ROOT


def test_replay_without_arguments_prints_the_timeline(tmp_path):
    out = tmp_path / "fixes.jsonl"
    proc = subprocess.run(
        [sys.executable, "-m", "service", "replay", "--jsonl-out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
        check=True,
    )
    times = {}
    for line in proc.stderr.splitlines():
        if "t =" in line:
            key, val = line.split("t =")
            times[key.strip()] = float(val.split()[0])
    assert times["first fast fix"] <= 1.2
    assert times["first conventional fix"] >= 6.0
    fixes = [json.loads(x) for x in out.read_text().splitlines()]
    assert any(f["class"] == "TRACK" and f["event"] == "sow" for f in fixes)


def test_scenario_fast_fixes_equal_spp_of_the_true_full_ranges():
    ephs = table1_ephemerides(0.0)
    cfg = scenario_config(duration_s=12.0)
    sim = Simulator(ephs, cfg)
    store = EphemerisStore()
    store.add_all(ephs)
    truth = {round(ep.tag_gpst_tow_s, 6): ep for ep in sim.epochs()}
    chunks, week, store2, iono, _, _ = builtin_scenario(duration_s=12.0)
    events = decode_chunks(chunks, week)
    from service.engine.pipeline import Pipeline

    pipe = Pipeline(store2, iono)
    n_fast = 0
    for ev in events:
        if not isinstance(ev, MeasurementEpoch):
            continue
        r = pipe.on_epoch(ev)
        if r.fix.mode != "fast":
            continue
        ep = truth[round(ev.gpst_tow_s, 6)]
        full = MeasurementEpoch.from_columns(
            ep.tag_gpst_week,
            ep.tag_gpst_tow_s,
            list(ep.prn),
            ["2I"] * len(ep.prn),
            ep.pr_m,
            cn0_dbhz=ep.cn0_dbhz,  # the same signal quality, so the same weights
        )
        spp = solve(full, store, solver="spp")
        assert np.linalg.norm(np.subtract(r.fix.x_ecef_m, spp.x_ecef_m)) <= 1e-3
        err = np.linalg.norm(np.subtract(r.fix.x_ecef_m, ep.truth_x_ecef_m))
        assert err <= 5 * 1.3 * r.fix.pdop
        n_fast += 1
    assert n_fast >= 50
