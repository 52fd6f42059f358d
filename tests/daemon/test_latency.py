"""The receiver loop's timing statistics (service.daemon.loop.LatencyStats) against numpy,
and where its garbage collections happen (between events, not inside one)."""

from __future__ import annotations

import gc

import numpy as np

from drivers.source import open_source
from service.core.ephemeris import EphemerisStore
from service.daemon.loop import GC_SAFETY_THRESHOLD, LatencyStats, Runner, collect_when_idle
from service.engine.pipeline import Pipeline
from service.output.publish import Publishers
from tests.support.paths import DATA

CAPTURE = DATA / "hk-polyu-f9p-ubx-2024" / "COM18___9600_240925_072456.ubx"
NAV = DATA / "hk-polyu-f9p-ubx-2024" / "hksc269h.24f"


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


def test_idle_collection_is_the_one_the_thresholds_call_for():
    """collect_when_idle makes no collection below the thresholds, a young one past the
    first, an intermediate one past the second (young passes since the last one)."""
    seen: list[int] = []

    def started(phase: str, info: dict) -> None:
        if phase == "start":
            seen.append(info["generation"])

    was_enabled = gc.isenabled()
    gc.disable()  # no automatic collection between the counts and the calls
    gc.callbacks.append(started)
    try:
        gc.collect()
        seen.clear()
        collect_when_idle((100, 10, 10))
        assert seen == []
        kept = [[] for _ in range(150)]  # 150 new tracked containers pending
        collect_when_idle((100, 10, 10))
        assert seen == [0] and gc.get_count()[0] < 100
        for _ in range(11):
            gc.collect(0)
        seen.clear()
        collect_when_idle((100, 10, 10))
        assert seen == [1] and gc.get_count()[1] == 0
        assert kept
    finally:
        gc.callbacks.remove(started)
        if was_enabled:
            gc.enable()


def test_the_loop_holds_the_automatic_collection_back_while_it_runs(tmp_path):
    """While a Runner runs, the collector's automatic trigger is GC_SAFETY_THRESHOLD (the
    loop collects when caught up); the caller's thresholds are back afterwards."""
    before = gc.get_threshold()
    during: list[tuple[int, ...]] = []
    with open_source(str(CAPTURE), nav=str(NAV)) as src:
        runner = Runner(
            src,
            Pipeline(EphemerisStore()),
            Publishers(),
            source_counters=src.counters,
            inline=True,
            on_result=lambda _r: during.append(gc.get_threshold()),
        )
        n = runner.run()
    assert n == len(during) > 0
    assert set(during) == {(max(GC_SAFETY_THRESHOLD, before[0]), *before[1:])}
    assert gc.get_threshold() == before
