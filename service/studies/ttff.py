"""``bdsfix ttff``: time to first fix, fast against conventional, on emulated restarts.

On real RINEX data each trial restarts at a random epoch with ephemerides held. After a
random bit-sync delay of 0.1-0.5 s each satellite waits for the next preamble and becomes
full by the SOW-decode rule (:mod:`service.core.sow_rule`): once words 1-2 of that subframe
have decoded, 0.12 s into a D2 subframe (GEOs, 0.6 s subframes), 1.2 s into a D1 subframe
(6 s); rule ``subframe``: at the end of that subframe. Subframe boundaries are taken from BDT
as in the real signal (:class:`service.engine.tracker.SubframeEmulator`); before that the
satellite is fractional (mod 1 ms). The one rule times the fast fix and the conventional
fix alike. Then, counted from the restart epoch:
- TTFF_fast: the first epoch with a published fast fix (any fix from the fast solver);
- TTFF_conventional: the first epoch at which the full measurements alone give an SPP fix
  with PDOP <= 10;
- geo_only: the first epoch with >= 4 full GEOs, solved by SPP from the GEOs alone, and its
  3D error against the SPP of all full measurements at that epoch.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any, Protocol

import numpy as np

from service.core.bds import is_geo
from service.core.ephemeris import EphemerisStore
from service.core.errors import ConfigError
from service.core.files import PLOT_HINT
from service.core.sow_rule import DEFAULT_FULL_RULE
from service.core.timebase import diff_s
from service.core.types import Fix, MeasurementEpoch
from service.engine.coarse import CoarseConfig
from service.engine.pipeline import Pipeline
from service.engine.solver import IonoSet, SolverConfig, solve


@dataclass(frozen=True, slots=True)
class Trial:
    restart_index: int
    fast_s: float | None
    conventional_s: float | None
    geo_only_s: float | None
    geo_only_err_m: float | None
    fast_vs_spp_m: float | None


def _distance_m(a: Fix, b: Fix) -> float:
    """3D distance between two fixes that have positions."""
    return float(np.linalg.norm(np.subtract(a.x_ecef_m or (0, 0, 0), b.x_ecef_m or (0, 0, 0))))


def run_trial(
    epochs: list[MeasurementEpoch],
    r: int,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    rng: np.random.Generator,
    horizon_s: float = 30.0,
    full_rule: str = DEFAULT_FULL_RULE,
) -> Trial:
    """Restart the receiver at ``epochs[r]`` (the stream pipeline with an emulated restart)
    and time, from there, the first fix of the pipeline (fast), the first conventional SPP of
    the same view (>= 4 full measurements) and the first GEO-only SPP."""
    t0 = epochs[r]
    # the paper's method and SPP: the coarse-time fix (< 4 full ranges) is not timed here
    off = CoarseConfig(coarse_fix=False)
    pipeline = Pipeline(store, iono, cfg, full_rule=full_rule, velocity=False, coarse=off)
    pipeline.restart(t0, rng)
    fast = conv = geo = geo_err = diff = None
    for ep in epochs[r:]:
        dt = diff_s(ep.gpst_week, ep.gpst_tow_s, t0.gpst_week, t0.gpst_tow_s)
        if dt > horizon_s:
            break
        result = pipeline.on_epoch(ep)
        view = result.epoch
        if fast is None:
            f = result.fix
            if f.ok:
                fast = dt
                ref = solve(ep, store, iono, cfg, solver="spp")
                if ref.ok:
                    diff = _distance_m(f, ref)
        if conv is None:
            c = solve(view, store, iono, cfg, solver="spp")
            if c.ok and c.pdop is not None and c.pdop <= 10.0:
                conv = dt
        if geo is None:
            geos = [i for i, p in enumerate(view.prn) if is_geo(p) and math.isfinite(view.pr_m[i])]
            if len(geos) >= 4:
                sub = MeasurementEpoch.from_columns(
                    ep.gpst_week,
                    ep.gpst_tow_s,
                    [ep.prn[i] for i in geos],
                    [ep.signal[i] for i in geos],
                    ep.pr_m[geos],
                )
                # the GEO-only solution is shown for its error: its PDOP (~100) is far
                # above the gate a published fix must pass
                g = solve(sub, store, iono, replace(cfg, pdop_max=math.inf), solver="spp")
                ref = solve(ep, store, iono, cfg, solver="spp")
                if g.ok and ref.ok:
                    geo = dt
                    geo_err = _distance_m(g, ref)
        if fast is not None and conv is not None and geo is not None:
            break
    return Trial(r, fast, conv, geo, geo_err, diff)


def _stats(values: list[float | None], n: int) -> dict[str, Any]:
    ok = [v for v in values if v is not None]
    out: dict[str, Any] = {"success_pct": round(100.0 * len(ok) / max(n, 1), 2)}
    if ok:
        out["median_s"] = round(float(np.median(ok)), 3)
        out["p95_s"] = round(float(np.percentile(ok, 95)), 3)
    return out


class TrialTimes(Protocol):
    """What a TTFF summary reads from a trial (RINEX :class:`Trial` or simulated)."""

    @property
    def fast_s(self) -> float | None: ...
    @property
    def conventional_s(self) -> float | None: ...
    @property
    def geo_only_s(self) -> float | None: ...
    @property
    def geo_only_err_m(self) -> float | None: ...
    @property
    def fast_vs_spp_m(self) -> float | None: ...


def summarize(trials: Sequence[TrialTimes]) -> dict[str, Any]:
    """The ``ttff --json`` document (docs/architecture.md)."""
    n = len(trials)
    doc: dict[str, Any] = {
        "trials": n,
        "fast": _stats([t.fast_s for t in trials], n),
        "conventional": _stats([t.conventional_s for t in trials], n),
        "geo_only": _stats([t.geo_only_s for t in trials], n),
    }
    errs = [t.geo_only_err_m for t in trials if t.geo_only_err_m is not None]
    if errs:
        doc["geo_only"]["median_err_m"] = round(float(np.median(errs)), 3)
    diffs = [t.fast_vs_spp_m for t in trials if t.fast_vs_spp_m is not None]
    if diffs:
        doc["fast"]["max_diff_to_spp_m"] = float(max(diffs))
    return doc


def plot_trials(trials: Sequence[TrialTimes], path: str) -> None:
    """Histograms of the trials' TTFFs, the three side by side in each bin so that none
    hides another (the fast fix and GEO-only SPP often fall in the same bins)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as exc:
        raise ConfigError(PLOT_HINT) from exc
    fig, ax = plt.subplots(figsize=(7, 4))
    data = {
        "fast fix": [t.fast_s for t in trials],
        "conventional SPP": [t.conventional_s for t in trials],
        "GEO-only SPP (no gate)": [t.geo_only_s for t in trials],
    }
    top = max((v for vals in data.values() for v in vals if v is not None), default=10.0)
    bins = [0.5 * k for k in range(int(2 * top) + 4)]
    ax.hist(
        [[v for v in vals if v is not None] for vals in data.values()],
        bins=bins,
        label=list(data),
    )
    ax.set_xlabel("time to first fix after restart [s]")
    ax.set_ylabel("trials")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
