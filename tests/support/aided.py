"""The definition ``bdsfix solve``'s batched height aiding and prediction screen
(service.commands.solve.solve_aided) must meet: every epoch solved alone, in order, its aid
and screen from the fixes before it (as the daemon's Pipeline solves a stream), a fast fix
declined for too few full ranges replaced as the stream's (pipeline.coarse_time_fix)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from dataclasses import replace

from service.commands.solve import BatchOptions
from service.core.counters import Counters
from service.core.ephemeris import EphemerisStore
from service.core.types import Fix, MeasurementEpoch
from service.engine.aiding import HeightAid, Predictor, with_screened
from service.engine.coarse import CoarseConfig
from service.engine.pipeline import coarse_time_fix, fix_with_velocity
from service.engine.solver import IonoSet, fractionalize, sky_view, solve_many
from service.engine.timetag import without_coarse_fractions
from service.engine.velocity import with_velocities


def aided_one_at_a_time(
    epochs: Iterable[MeasurementEpoch], store: EphemerisStore, iono: IonoSet, opts: BatchOptions
) -> Iterator[tuple[MeasurementEpoch, list[Fix]]]:
    """Each epoch's fixes (fast, then SPP, as ``opts.mode`` asks) solved alone, in order."""
    held, predictor = HeightAid(), Predictor()
    coarse = opts.coarse or CoarseConfig()
    for epoch in epochs:
        view = without_coarse_fractions(epoch)[0]
        cfg = held.cfg_for(view.gpst_week, view.gpst_tow_s, opts.cfg)
        rows, screened = predictor.screen(view, store, opts.cfg)
        fixes: list[Fix] = []
        fast_view = view
        if opts.mode in ("fast", "both"):
            fast_in = fractionalize(rows, opts.period_s) if opts.fractional == "non-geo" else rows
            fast_in = without_coarse_fractions(fast_in)[0]
            (fast,) = solve_many((fast_in,), store, iono, cfg, "fast", opts.with_sky)
            fast = with_screened(fast, screened, view, store)  # (the stream's order)
            # too few full ranges: the stream's coarse-time fix, of every range of the epoch
            # (unscreened), without the aid (the stream's solver settings)
            whole = fractionalize(epoch, opts.period_s) if opts.fractional == "non-geo" else epoch
            fast_view, set_aside = without_coarse_fractions(whole)
            fast = coarse_time_fix(
                fast, whole, fast_view, set_aside, store, iono, opts.cfg, coarse, Counters()
            )
            if opts.with_sky and fast.method == "coarse_time" and fast.ok:
                fast = replace(fast, sky=sky_view(fast_view, store, fast))
            fixes.append(fast)
        if opts.mode in ("spp", "both"):
            (spp,) = solve_many((rows,), store, iono, cfg, "spp", opts.with_sky)
            fixes.append(with_screened(spp, screened, view, store))
        fixes = [
            fix_with_velocity(f, fast_view, store)
            if f.method == "coarse_time"
            else with_velocities([(f, view)], store)[0]
            for f in fixes
        ]
        held.update(fixes[-1], opts.cfg)
        predictor.update(fixes[-1])
        yield view, fixes


def batched_and_alone(
    epochs: list[MeasurementEpoch], store: EphemerisStore, iono: IonoSet, opts: BatchOptions
) -> tuple[list[str], list[str]]:
    """The JSON lines of every fix of ``bdsfix solve``'s batched aided solve
    (:func:`service.commands.solve.solve_epochs`) and of :func:`aided_one_at_a_time`, in
    order: what the two must give byte for byte."""
    from service.commands.solve import solve_epochs
    from service.output.records import fix_json_line

    got = [fix_json_line(f) for _, fx in solve_epochs(iter(epochs), store, iono, opts) for f in fx]
    ref = [fix_json_line(f) for _, fx in aided_one_at_a_time(epochs, store, iono, opts) for f in fx]
    return got, ref
