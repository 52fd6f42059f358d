"""A small Monte Carlo of the coarse-time first fix (service/studies/coarse_mc.py; the
10,000-trial run is bench/bench_coarse_mc.py): receivers anywhere on the globe, moving at
0-50 m/s (some at 250 m/s), host clocks up to 2 s wrong, measurements physically generated
from the real 2024 BeiDou-3 broadcast ephemerides; the truth is the generator's."""

from __future__ import annotations

import numpy as np

from service.commands.solve import load_navigation
from service.studies.coarse_mc import run
from tests.support.paths import DATA

NAV = DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f"


def test_no_wrong_fix_and_a_fix_wherever_redundancy_allows():
    store, iono = load_navigation([str(NAV)], max_age_s=86_400.0)
    mid = float(np.median([e.toe_sow_s for e in store.all()])) + 14.0
    summary = run(store, iono, 2333, (mid - 3600.0, mid + 3600.0), 300, seed=7)
    figures = summary.figures()
    print(figures, summary.declines())
    assert figures["wrong"] == 0
    slow = [t for t in summary.trials if t.speed_m_s <= 50.0 and t.n_sats >= 7]
    assert len(slow) >= 250
    assert sum(t.fixed for t in slow) >= 0.99 * len(slow)
    # the figure: success where >= 6 satellites are above the mask (six give
    # redundancy 2 with five unknowns and the time prior's row)
    six = [t for t in summary.trials if t.n_sats >= 6]
    assert sum(t.fixed for t in six) >= 0.98 * len(six)
    assert sum(t.fixed for t in summary.trials if t.n_sats == 6) >= 1
    # fewer cannot: declined
    assert all(not t.fixed for t in summary.trials if t.n_sats < 6)
    # the fixes are metres from the truth (2 m code noise, no multipath)
    assert figures["error_max_m"] < 50.0
