"""Where the stream's solves start: the Earth's centre while any measurement is fractional
(the paper's a-priori-free fast fix), the last fix once all are full (conventional SPP).

Checked on the real HKSC RINEX replayed through the pipeline with an emulated restart:
every solve is repeated from the Earth's centre with the engine alone, and the two must be
the same fix (same mode, integers and used satellites; position within 1e-6 m).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

import service.engine.pipeline as pipeline_mod
from drivers.rinex import RinexObsReader
from service.commands.solve import load_navigation
from service.engine.coarse import CoarseConfig
from service.engine.pipeline import Pipeline
from service.engine.solver import solve
from tests.support.paths import DATA

HKSC = DATA / "hksc-2021"


def test_warm_started_spp_equals_the_solve_from_the_earths_centre(monkeypatch):
    store, iono = load_navigation([str(HKSC / "hksc1610.nav")])
    # the paper's method alone (the coarse-time fix of epochs with < 4 full ranges is
    # tests/engine/test_coarse_pipeline.py's)
    pipe = Pipeline(store, iono, restart_at_s=60.0, sync_seed=3, coarse=CoarseConfig(False))
    starts: list[tuple[float, float, float] | None] = []
    real_solve = pipeline_mod.solve

    def spy(view, store_, iono_, cfg, solver="fast"):
        starts.append(cfg.x0_ecef_m)
        return real_solve(view, store_, iono_, cfg, solver=solver)

    monkeypatch.setattr(pipeline_mod, "solve", spy)
    warm = cold = 0
    for epoch in RinexObsReader(HKSC / "hksc1610.obs"):
        result = pipe.on_epoch(epoch)
        x0 = starts[-1]
        view, fix = result.epoch, result.fix
        if not bool(np.isfinite(view.pr_m).all()):
            assert x0 is None  # a fractional measurement: the paper's start
        ref = solve(view, store, iono, replace(pipe.cfg, x0_ecef_m=None), solver="fast")
        assert (fix.mode, fix.ambiguity, fix.used) == (ref.mode, ref.ambiguity, ref.used)
        if fix.ok:
            d = np.subtract(fix.x_ecef_m, ref.x_ecef_m)
            assert float(np.linalg.norm(d)) < 1e-6
        warm += x0 is not None
        cold += x0 is None
    # the restart at 60 s makes fast epochs (from the centre) between SPP epochs (warm)
    assert warm > 100 and cold >= 5
    assert pipe.counters["fix_fast"] > 0 and pipe.counters["fix_spp"] > 100
