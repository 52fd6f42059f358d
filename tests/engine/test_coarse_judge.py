"""The coarse-time search's judgement of its candidates (service.engine.coarse, step 4):
what passes, and what counts as a rival that makes the epoch ``ambiguous``.

The safety of the search rests on the rivals: a candidate that cannot be ruled out must
stop a publication. A candidate without redundancy cannot be tested at all, so where it is
plausible it must count as a rival, never be ignored.
"""

from __future__ import annotations

import numpy as np

from service.engine.coarse import CoarseConfig, _judge, _Solved
from service.engine.raim import chi2_threshold
from service.engine.solver import SolverConfig


def solved(t_stat: list[float], dof: list[int], alt_m: list[float]) -> _Solved:
    k, n, p = len(t_stat), 8, 6
    return _Solved(
        x=np.zeros((k, 3)),
        b=np.zeros((k, 1)),
        dt=np.zeros(k),
        t_stat=np.asarray(t_stat, dtype=float),
        dof=np.asarray(dof),
        alt=np.asarray(alt_m, dtype=float),
        min_el_rad=np.full(k, 0.3),
        normal=np.broadcast_to(np.eye(p), (k, p, p)).copy(),
        design=np.zeros((k, n, p)),
        resid_m=np.zeros((k, n)),
        weight=np.ones((k, n)),
    )


def test_a_plausible_candidate_without_redundancy_is_a_rival_never_a_pass() -> None:
    cfg, ccfg = SolverConfig(), CoarseConfig()
    # 0: a good candidate; 1: no redundancy, plausible; 2: no redundancy, 100 km up
    ev = _judge(solved([1.0, 0.0, 0.0], [3, 0, 0], [50.0, 50.0, 100e3]), cfg, ccfg)
    assert ev.passing.tolist() == [True, False, False]
    assert ev.rivals.tolist() == [True, True, False]  # the winner and the untestable one
    assert np.isinf(ev.t_max[1:]).all()


def test_rivals_are_those_below_the_margin_times_their_threshold() -> None:
    cfg, ccfg = SolverConfig(), CoarseConfig()
    t = chi2_threshold(3, cfg.p_fa)
    stats = [0.5 * t, 0.99 * t, 1.01 * t, 0.999 * ccfg.uniqueness_margin * t]
    stats.append(1.001 * ccfg.uniqueness_margin * t)
    ev = _judge(solved(stats, [3] * 5, [50.0] * 5), cfg, ccfg)
    assert ev.passing.tolist() == [True, True, False, False, False]
    assert ev.rivals.tolist() == [True, True, True, True, False]
