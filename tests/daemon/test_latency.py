"""The receiver loop's timing statistics (service.daemon.loop.LatencyStats) against numpy."""

from __future__ import annotations

import numpy as np

from service.daemon.loop import LatencyStats


def test_latency_quantiles_in_status_match_numpy_within_a_bin():
    """The STATUS loop-time quantiles (log bins of 5 %) against numpy on the same samples."""
    rng = np.random.default_rng(4)
    solve_s = rng.lognormal(np.log(5e-3), 0.6, 20_000)
    publish_s = rng.lognormal(np.log(1e-3), 1.0, 20_000)
    stats = LatencyStats()
    for a, b in zip(solve_s, publish_s, strict=True):
        stats.add(10.0, 10.0 + a, 10.0 + a + b)
    c = stats.counters()
    for key, x in (("loop", solve_s + publish_s), ("publish", publish_s)):
        for q in (50, 99):
            ref = 1e3 * np.percentile(x, q)
            assert ref / 1.06 <= c[f"epoch_{key}_p{q}_ms"] <= ref * 1.06, (key, q)
        assert c[f"epoch_{key}_max_ms"] == round(1e3 * x.max(), 3)
