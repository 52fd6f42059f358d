"""`bdsfix coverage --first-fix`: the paper's method beside the coarse-time first fix.

Checked independently: the per-point shares against a plain loop with the geometry module's
ENU elevations and numpy.linalg.inv for GDOP; on the real 2024 BeiDou-3 nav file, the
coarse-time solver itself run on simulated first epochs (no wrong integer, no fix where fewer
than 6 satellites are above the mask).
"""

from __future__ import annotations

import json
import math

import numpy as np

from service.commands.cli import main
from service.core.bds import is_geo
from service.core.geometry import geodetic_to_ecef, look_angles
from service.sim.constellation import positions_ecef, table1
from service.studies.first_fix_coverage import FirstFixConfig, run_first_fix
from tests.support.paths import DATA

NAV_2024 = DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f"


def test_shares_match_a_per_point_loop():
    cfg = FirstFixConfig(days=0.25, step_s=3600.0, grid_deg=15.0, elmask_deg=10.0)
    const = table1()
    t_s = np.arange(cfg.n_epochs) * cfg.step_s
    sats = positions_ecef(const, t_s)
    res = run_first_fix(cfg, const.prns, sats)
    geo = np.array([is_geo(p) for p in const.prns])
    for i, lat in enumerate(cfg.lats_deg()):
        for j, lon in enumerate(cfg.lons_deg()):
            x = geodetic_to_ecef(math.radians(lat), math.radians(lon), 0.0)
            n_paper = n_coarse = 0
            for s in sats:
                el, _ = look_angles(x, s)
                vis = el >= math.radians(cfg.elmask_deg)
                n_coarse += int(vis.sum() >= 6)
                g = s[geo & vis]
                if len(g) >= 4:
                    e = (g - x) / np.linalg.norm(g - x, axis=1)[:, None]
                    h = np.hstack([-e, np.ones((len(g), 1))])
                    d = h.T @ h
                    if np.linalg.cond(d) < 1e15:
                        n_paper += int(math.sqrt(np.trace(np.linalg.inv(d))) < cfg.beta)
            assert res.coarse[i, j] == n_coarse / len(sats), (lat, lon)
            assert res.paper[i, j] == n_paper / len(sats), (lat, lon)


def test_cli_nav_first_fix_with_the_solver(tmp_path, capsys):
    out = tmp_path / "ff.json"
    args = ["coverage", "--first-fix", "--nav", str(NAV_2024), "--grid-deg", "10"]
    args += ["--step-s", "3600", "--solve-grid-deg", "45", "--solve-epochs", "1"]
    assert main([*args, "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert "coarse time" in capsys.readouterr().out
    # the real 2024 constellation: the coarse-time condition covers most of the globe, the
    # paper's four GEOs only the Asia-Pacific
    assert doc["coarse_time"]["area_time_pct"] > 85.0
    assert doc["paper"]["area_time_pct"] < 40.0
    assert doc["either"]["area_time_pct"] >= doc["coarse_time"]["area_time_pct"]
    s = doc["solve_sample"]
    assert s["solves"] == 4 * 8
    assert s["wrong"] == 0
    assert s["fixed_without_condition"] == 0  # it never fixes with fewer than 6 satellites
    assert s["fixed_where_condition_pct"] >= 95.0
    assert s["error_max_m"] < 100.0
