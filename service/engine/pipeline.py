"""The engine loop shared by replay and the daemon: events in, fixes and TRACK/STATUS out.

Per measurement epoch: the tracker decides which measurements are full, the engine solves
from all usable ones (the fast fix, which is SPP when everything is full; with fewer than
four full ranges the coarse-time fix of :mod:`service.engine.coarse`), and integrity
bookkeeping compares every recovered pseudorange with the full one that arrives once the
satellite's SOW decodes (:class:`service.engine.recovered.RecoveredLedger`, the rule of
``bdsfix solve`` too). A refused solution is passed on as ``mode="none"`` with its reason,
never as a position.

Two kinds of epoch are declined before the tracker and the solver see them, so that every
epoch a source delivers is published: one without a GPS week (``no_time``: the source gave
only a time of week, e.g. RTCM MSM before any ephemeris), and one that is not after the
previous epoch (``out_of_order``: a duplicate or a step back in time, which a relay or a
receiver restart can produce); neither changes the pipeline's state.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from functools import partial
from typing import Any

import numpy as np

from service.core.bds_nav import EphemerisAssembler
from service.core.constants import C_M_S
from service.core.counters import Counters
from service.core.declines import Decline, Declined
from service.core.ephemeris import EphemerisStore
from service.core.gal_nav import InavAssembler
from service.core.gps_nav import LnavAssembler
from service.core.sow_rule import DEFAULT_FULL_RULE
from service.core.timebase import diff_s, gpst_to_bdt
from service.core.types import (
    Ephemeris,
    Fix,
    KlobucharParams,
    MeasurementEpoch,
    NavSubframe,
    ReceiverFix,
    SatView,
    TimeOffset,
)
from service.engine.aiding import HeightAid, Predictor, with_screened
from service.engine.coarse import (
    TRIED_AFTER,
    CoarseConfig,
    solve_coarse,
    solve_coarse_at_sow,
    sow_time_shift,
)
from service.engine.layout import BDS_ONLY
from service.engine.recovered import IntegrityCheck, RecoveredLedger
from service.engine.solver import (
    IonoSet,
    SolverConfig,
    declined,
    sky_view,
    solve,
)
from service.engine.timetag import COARSE_TIME_S, without_coarse_fractions
from service.engine.tracker import FrameSyncTracker, SubframeEmulator, TrackEvent
from service.engine.velocity import with_velocity

log = logging.getLogger(__name__)

WARM_START_MAX_AGE_S = 30.0
"""A fix older than this [s, data time] is not used as the start of the next solve."""
SAME_EPOCH_S = 1e-6
"""Two epochs closer than this [s] are the same epoch (records carry 1 us)."""
REANCHOR_EPOCHS = 3
"""Epochs in a row, each after the one before it by at most :data:`REANCHOR_STEP_MAX_S`,
that all come before the latest epoch's time: the stream's time is taken from them again
(``time_reanchors``). One epoch tagged ahead (a damaged week or time of week) would
otherwise decline every later epoch ``out_of_order`` until the data time passed it: a week
for a week number off by one."""
REANCHOR_STEP_MAX_S = 60.0
"""The largest step [s] between two of the epochs held before the latest for them to count
as one run (a receiver's epochs, not two stray ones)."""
RECEIVER_FIX_MAX_AGE_S = 1.5
"""A receiver's own fix is carried on the results of epochs at most this far from it [s]
(at 1 Hz: the fix of the same or the previous second; an SBF PVTGeodetic follows the
MeasEpoch of its second, so the epoch carries the previous second's)."""


@dataclass(frozen=True, slots=True, eq=False)
class EpochResult:
    """Everything one measurement epoch produced.

    ``sky`` gives the satellites in view of ``fix`` on demand: the publishers ask for it
    once the GGA is out, so computing it does not delay the first sentence."""

    epoch: MeasurementEpoch
    fix: Fix
    since_start_s: float | None  # None while the time is unknown (no_time)
    track: tuple[TrackEvent, ...] = ()
    integrity: tuple[IntegrityCheck, ...] = ()
    sky: Callable[[Fix], tuple[SatView, ...]] | None = None
    restarted: bool = False
    """The emulated receiver restart (``restart_at_s``) happened at this epoch: what came
    before it (first fixes, decoded SOWs) belongs to the receiver before the restart."""
    receiver_fix: ReceiverFix | None = None
    """The receiver's own latest fix (an Android Fix row, an SBF PVTGeodetic) if it is at
    most :data:`RECEIVER_FIX_MAX_AGE_S` from this epoch, for comparison; never used."""


TIME_PRIOR_SIGMAS = 5.0
"""The coarse-time fix's time prior from an epoch's own time uncertainty: this many times
``time_unc_s`` (a phone's BiasUncertaintyNanos, one sigma)."""
TIME_PRIOR_MIN_S = 1e-6
"""The narrowest such prior [s] (a phone may say a few nanoseconds)."""
WIDE_PRIOR_MAX_S = 30.0
"""The widest time prior [s] the coarse-time fix takes from an epoch's own uncertainty
(:func:`wide_time_prior`): over 30 s a MEO satellite's range moves by up to 24 km, the
differences between two by 48 km, which with the grid's 58 km and the height's 20 km stays
inside the 150 km of half a millisecond (service.engine.coarse, step 2); the setting's
bound too."""


def wide_time_prior(view: MeasurementEpoch, coarse: CoarseConfig) -> CoarseConfig | None:
    """The coarse-time fix's settings for an epoch whose time is coarser than its
    ``time_prior_s`` (a phone before its first fix: BiasUncertaintyNanos of seconds) when
    no SOW has decoded yet: its prior :data:`TIME_PRIOR_SIGMAS` times ``time_unc_s`` when
    that is within :data:`WIDE_PRIOR_MAX_S`; None (wait for the first SOW) beyond it, or
    with no uncertainty said (NaN, inf)."""
    prior = TIME_PRIOR_SIGMAS * view.time_unc_s
    if not prior <= WIDE_PRIOR_MAX_S:
        return None
    return replace(coarse, time_prior_s=max(prior, coarse.time_prior_s))


def time_prior(view: MeasurementEpoch, coarse: CoarseConfig) -> CoarseConfig:
    """The coarse-time fix's settings for ``view``: its time prior narrowed to
    :data:`TIME_PRIOR_SIGMAS` times the epoch's ``time_unc_s`` where the epoch says its time
    that well, and no worse than :data:`COARSE_TIME_S` (the trust the fast fix already
    places in such a tag), else ``time_prior_s`` unchanged (the host clock's, a file's tag).
    Within ~0.1 ms the solved time leaves no doubt about the millisecond common to every
    range, and a fix with every range fractional is then SPP of the full ranges
    (service.engine.coarse, step 5; 5.7e-9 m on an HKSC epoch with a 0.1 ms prior)."""
    unc = view.time_unc_s
    if not unc <= COARSE_TIME_S:  # NaN (not said), inf, or coarser
        return coarse
    prior = max(TIME_PRIOR_SIGMAS * unc, TIME_PRIOR_MIN_S)
    return replace(coarse, time_prior_s=prior) if prior < coarse.time_prior_s else coarse


def count_fix(counters: Counters, fix: Fix) -> None:
    """The counters of one solver result: ``fix_<mode>``, ``declined_<reason_code>``,
    ``raim_untested`` (a fix at redundancy 0), ``fixes_with_exclusions`` and
    ``excluded_<PRN>`` per satellite that fault exclusion removed."""
    counters[f"fix_{fix.mode}"] += 1
    if not fix.ok:
        counters[f"declined_{fix.reason_code or 'other'}"] += 1
    elif fix.redundancy == 0:
        counters["raim_untested"] += 1
    if fix.excluded:
        counters["fixes_with_exclusions" if fix.ok else "declines_with_exclusions"] += 1
        for prn in fix.excluded:
            counters[f"excluded_{prn}"] += 1


def fix_with_velocity(fix: Fix, view: MeasurementEpoch, store: EphemerisStore) -> Fix:
    """``fix`` with its velocity from ``view``'s Doppler (the stream's and, for its
    coarse-time fixes, ``bdsfix solve``'s). A coarse-time fix with every range fractional
    is at the tag plus its solved offset (seconds, with a host clock off): its Doppler rows
    are taken at that receive time (the clock handed to them is -c x offset), so the
    satellites' positions and velocities are those of its solution, not up to seconds away
    along their orbits (1 m/s of range rate per second); the fix itself keeps its clock
    relative to the tag."""
    if fix.method != "coarse_time" or fix.full:
        return with_velocity(fix, view, store)
    if fix.time_offset_s is None or not math.isfinite(fix.time_offset_s):
        return fix
    at_rx = replace(fix, clock_bias_m=-C_M_S * fix.time_offset_s)
    return replace(fix, velocity=with_velocity(at_rx, view, store).velocity)


def coarse_time_fix(
    paper: Fix,
    whole: MeasurementEpoch,
    view: MeasurementEpoch,
    set_aside: int,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    coarse: CoarseConfig,
    counters: Counters,
) -> Fix:
    """The fix of an epoch after the paper's method gave ``paper``: the coarse-time fix
    (:mod:`service.engine.coarse`) where the paper's method declined for want of four full
    ranges (issue 20: the paper's method with >= 4 full GEO ranges, this one otherwise),
    else ``paper`` itself. The one decision of the stream (:class:`Pipeline`) and of
    ``bdsfix solve`` alike.

    ``whole``: the epoch with its fractional ranges; ``view``: the same without those
    :func:`~service.engine.timetag.without_coarse_fractions` set aside (``set_aside`` of
    them), the rows ``paper`` was solved from. Time prior: an epoch whose time is within
    ``coarse.time_prior_s`` takes :func:`time_prior`'s; one coarser (a phone before its
    first fix) is declined ``coarse_time`` (counted ``coarse_time_epochs``) and then tried
    at the time of its first decoded SOW (:func:`~service.engine.coarse.sow_time_shift`,
    :func:`~service.engine.coarse.solve_coarse_at_sow`), or with no SOW yet with
    :func:`wide_time_prior`'s prior where that is within :data:`WIDE_PRIOR_MAX_S`; else it
    waits. A coarse-time fix published is counted ``coarse_fixes``."""
    if set_aside and view.time_unc_s > coarse.time_prior_s:
        # the receiver's time is coarser than even the coarse-time fix's prior: its
        # fractional ranges wait for the first decoded SOW, whose full range gives the
        # time to ~10 ms (issue 20); with one, the coarse-time fix is tried at that time
        if paper.reason_code not in TRIED_AFTER:
            return paper
        counters["coarse_time_epochs"] += 1
        sow = (
            coarse.coarse_fix
            and paper.reason_code == Decline.TOO_FEW_FULL
            and sow_time_shift(whole, store) is not None
        )
        # the full ranges the solve needed (its layout's unknowns); with no row at all,
        # one system's position and clock
        figures = dict(paper.decline.fields) if paper.decline is not None else {}
        need = figures.get("need", BDS_ONLY.n_params)
        why = Declined.of(
            Decline.COARSE_TIME,
            time_unc_s=view.time_unc_s,
            n_frac=set_aside,
            n_full=int(np.isfinite(view.pr_m).sum()),
            need=need,
        )
        waits = declined(view, why)
        if sow:  # its decline, if it has no candidates, is this one
            return _coarse_fix(whole, waits, store, iono, cfg, coarse, counters, at_sow=True)
        wide = wide_time_prior(view, coarse) if coarse.coarse_fix else None
        if wide is not None:
            # no SOW yet: the phone's own uncertainty (5 sigma, <= 30 s) is the prior
            return _coarse_fix(whole, waits, store, iono, cfg, wide, counters)
        return waits
    if coarse.coarse_fix and (
        paper.reason_code == Decline.TOO_FEW_FULL
        or (set_aside and paper.reason_code == Decline.NO_MEASUREMENTS)
    ):
        return _coarse_fix(whole, paper, store, iono, cfg, time_prior(whole, coarse), counters)
    return paper


def _coarse_fix(
    view: MeasurementEpoch,
    paper: Fix,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    coarse: CoarseConfig,
    counters: Counters,
    at_sow: bool = False,
) -> Fix:
    """The coarse-time fix (:mod:`service.engine.coarse`) of an epoch the paper's method
    declined for want of four full ranges, with the settings ``coarse``: its fix, or its
    decline when it found candidates and none was safe to publish (``chi2``,
    ``ambiguous``, ``pdop_gate``); else (too few rows, no Doppler) the paper's decline
    stands, the reason to wait. ``at_sow``: the tag is no prior (``time_unc_s`` beyond
    ``time_prior_s``), the first decoded SOW is
    (:func:`service.engine.coarse.solve_coarse_at_sow`)."""
    if at_sow:
        result = solve_coarse_at_sow(view, store, iono, cfg, coarse)
    else:
        result = solve_coarse(view, store, iono, cfg, coarse)
    fix = result.fix
    if fix.ok:
        counters["coarse_fixes"] += 1
        return fix
    if fix.reason_code in {Decline.CHI2, Decline.AMBIGUOUS, Decline.PDOP_GATE}:
        return fix
    return paper


@dataclass
class Pipeline:
    """Stateful wiring of tracker, ephemeris store and engine (no I/O of its own)."""

    store: EphemerisStore
    iono: IonoSet = field(default_factory=IonoSet)
    cfg: SolverConfig = field(default_factory=SolverConfig)
    restart_at_s: float | None = None
    sync_seed: int = 0
    full_rule: str = DEFAULT_FULL_RULE  # when a restarted satellite is full (core.sow_rule)
    velocity: bool = True  # velocity from Doppler on each fix (off for studies of positions)
    coarse: CoarseConfig = field(default_factory=CoarseConfig)  # the fix with < 4 full ranges
    on_track: Callable[[TrackEvent], None] | None = None
    tracker: FrameSyncTracker = field(default_factory=FrameSyncTracker)
    counters: Counters = field(default_factory=Counters)
    _first: tuple[int, float] | None = None
    _latest: tuple[int, float] | None = None  # GPST of the latest measurement epoch
    _before_latest: tuple[int, float] | None = None  # GPST of the epoch before the latest
    _behind: list[tuple[int, float]] = field(default_factory=list)  # before _latest, in order
    _restarted_at: tuple[int, float] | None = None  # GPST of the emulated restart
    _restarted: bool = False
    _last_fix: tuple[int, float, tuple[float, float, float]] | None = None
    _ledger: RecoveredLedger = field(init=False)  # the ranges fast fixes recovered
    _assembler: EphemerisAssembler = field(default_factory=EphemerisAssembler)
    _lnav: LnavAssembler = field(default_factory=LnavAssembler)
    _inav: InavAssembler = field(default_factory=InavAssembler)
    _receiver_fix: ReceiverFix | None = None
    _cfg_settings: tuple[SolverConfig, dict[str, Any]] | None = None
    _height: HeightAid = field(default_factory=HeightAid)  # cfg.height_aiding's held height
    _predictor: Predictor = field(default_factory=Predictor)  # cfg.screen_predicted_m's
    ggto: TimeOffset | None = None
    """The latest broadcast GST - GPST offset (:mod:`service.core.gal_nav`): recorded, not
    applied (each system has its own receiver clock, which absorbs it)."""

    def __post_init__(self) -> None:
        self._ledger = RecoveredLedger(self.counters)

    # --- navigation data -----------------------------------------------------------------
    def add_ephemeris(self, eph: Ephemeris) -> None:
        """Offer ``eph`` to the store; counts ``ephemeris_<source>`` when kept, else
        ``ephemeris_refused`` and ``ephemeris_refused_<check>`` (see ephemeris_problem;
        ``inconsistent``: an outside set that the receiver's own contradicts);
        ``ephemeris_evicted`` counts the sets the store's count bound let go,
        ``ephemeris_dropped_inconsistent`` the outside sets held that the receiver's own set
        contradicted, ``ephemeris_dropped_unhealthy`` the held sets that came again marked
        unhealthy (service.core.ephemeris)."""
        evicted, dropped = self.store.evicted, self.store.dropped_inconsistent
        unhealthy = self.store.dropped_unhealthy
        if self.store.add(eph):
            self.counters[f"ephemeris_{eph.source}"] += 1
            if self.store.evicted != evicted:
                self.counters["ephemeris_evicted"] += self.store.evicted - evicted
            if self.store.dropped_inconsistent != dropped:
                self.counters["ephemeris_dropped_inconsistent"] += (
                    self.store.dropped_inconsistent - dropped
                )
        else:
            self.counters["ephemeris_refused"] += 1
            if self.store.last_refusal is not None:
                self.counters[f"ephemeris_refused_{self.store.last_refusal.check}"] += 1
            if self.store.dropped_unhealthy != unhealthy:
                self.counters["ephemeris_dropped_unhealthy"] += 1

    def prune_store(self) -> int:
        """Drop ephemerides a day older than the latest measurement and their satellite's
        newest set (:meth:`EphemerisStore.prune`; none before the first measurement: without
        a time, only the store's count bound applies); counted as ``ephemeris_pruned``."""
        if self._latest is None:
            return 0
        dropped = self.store.prune(*gpst_to_bdt(*self._latest))
        self.counters["ephemeris_pruned"] += dropped
        return dropped

    def set_iono(self, params: KlobucharParams) -> None:
        """Broadcast ionosphere coefficients (BDS, or GPS as the fallback) for the solver and
        the saved store."""
        self.iono = self.iono.with_params(params)
        self.store.iono = self.iono.preferred

    def set_time_offset(self, offset: TimeOffset) -> None:
        """A broadcast offset between system times (GGTO, ``GAGP``): kept as :attr:`ggto`
        (STATUS ``ggto_ns``, :meth:`ggto_ns`), counted ``ggto_<source>``; never applied to
        ranges: Galileo's own receiver clock absorbs it (docs/method.md)."""
        self.counters[f"ggto_{offset.source or 'broadcast'}"] += 1
        if offset.pair == "GAGP" and offset != self.ggto:
            if self.ggto is None:
                log.info(
                    "GGTO (GST - GPST) from %s: A0 %.3g s, A1 %.3g s/s at GPS week %d + %.0f s; "
                    "absorbed by Galileo's receiver clock",
                    offset.source,
                    offset.a0_s,
                    offset.a1_s_s,
                    offset.week,
                    offset.t_ref_s,
                )
            self.ggto = offset

    def ggto_ns(self) -> float | None:
        """GST - GPST [ns] at the latest measurement epoch (or the broadcast's reference time
        before one), None without a broadcast."""
        if self.ggto is None:
            return None
        week, tow = self._latest or (self.ggto.week, self.ggto.t_ref_s)
        return round(self.ggto.at_s(week, tow) * 1e9, 3)

    def on_receiver_fix(self, rf: ReceiverFix) -> None:
        """The receiver's own fix: kept for the next epochs' results (``receiver_fixes``)."""
        self.counters["receiver_fixes"] += 1
        self._receiver_fix = rf

    def _receiver_fix_near(self, epoch: MeasurementEpoch) -> ReceiverFix | None:
        rf = self._receiver_fix
        if rf is None:
            return None
        age = diff_s(epoch.gpst_week, epoch.gpst_tow_s, rf.gpst_week, rf.gpst_tow_s)
        return rf if abs(age) <= RECEIVER_FIX_MAX_AGE_S else None

    def on_subframe(self, sf: NavSubframe) -> list[TrackEvent]:
        self.counters["subframes"] += 1
        events = self.tracker.on_subframe(sf)
        self._feed_assembler(sf)
        self._emit(events)
        return events

    def _feed_assembler(self, sf: NavSubframe) -> None:
        items: list[Ephemeris | KlobucharParams | TimeOffset]
        if sf.nav_type == "LNAV":
            items = list(self._lnav.feed(sf.prn, sf.words, sf.gpst_week))
        elif sf.nav_type == "INAV":
            items = list(self._inav.feed(sf.prn, sf.words[0], sf.gpst_week))
        else:
            items = list(self._assembler.feed(sf.prn, sf.nav_type, sf.words))
        for item in items:
            if isinstance(item, Ephemeris):
                self.add_ephemeris(item)
            elif isinstance(item, KlobucharParams):
                self.set_iono(item)
            elif isinstance(item, TimeOffset):
                self.set_time_offset(item)

    # --- measurements ---------------------------------------------------------------------
    def on_epoch(self, epoch: MeasurementEpoch) -> EpochResult:
        self.counters["epochs"] += 1
        early = self._early_decline(epoch)
        if early is not None:
            if epoch.restarted:  # (the flag is the receiver's, whatever its epoch's time)
                self.counters["receiver_restarts"] += 1
                self._forget_fixes()
            count_fix(self.counters, early)
            since = None
            if epoch.week_known:
                since = self.tracker.since_start_s(epoch.gpst_week, epoch.gpst_tow_s)
            return EpochResult(epoch, early, since)
        if self._first is None:
            self._first = (epoch.gpst_week, epoch.gpst_tow_s)
        self._before_latest, self._latest = self._latest, (epoch.gpst_week, epoch.gpst_tow_s)
        if (
            self.restart_at_s is not None
            and not self._restarted
            and diff_s(epoch.gpst_week, epoch.gpst_tow_s, *self._first) >= self.restart_at_s
        ):
            self._restarted = restarted_now = True
            self._restarted_at = (epoch.gpst_week, epoch.gpst_tow_s)
            self.restart(epoch, np.random.default_rng(self.sync_seed))
        else:
            restarted_now = False
        if epoch.restarted:  # the receiver's clock restarted: its old fix is no start
            self.counters["receiver_restarts"] += 1
            self._forget_fixes()
        view, events = self.tracker.on_epoch(epoch)
        # their recovered ranges are checked with this epoch's fix, or later
        self._ledger.due(ev.prn for ev in events if ev.event == "full")
        whole = view  # with its fractional ranges, for the coarse-time fix
        view, set_aside = without_coarse_fractions(view)
        cfg = self._start_cfg(view)
        if self.cfg.height_aiding:  # the height of the last fixes as one more row
            cfg = self._height.cfg_for(epoch.gpst_week, epoch.gpst_tow_s, cfg)
        # the ranges longer than the last fix and its velocity predict: left out (reflected).
        # A coarse-time fix below replaces this fix with one of its own rows (every range
        # of the epoch, no aid: a first fix has no past) and its own exclusions
        rows, screened = self._predictor.screen(view, self.store, self.cfg)
        fix = solve(rows, self.store, self.iono, cfg, solver="fast")
        fix = with_screened(fix, screened, view, self.store)
        fix = coarse_time_fix(
            fix, whole, view, set_aside, self.store, self.iono, self.cfg, self.coarse, self.counters
        )
        if self.velocity:
            fix = fix_with_velocity(fix, view, self.store)
        count_fix(self.counters, fix)
        self._predictor.update(fix)
        if self.cfg.height_aiding:
            self._height.update(fix, self.cfg)
            if cfg.height_aid is not None and fix.ok:
                self.counters["height_aided_fixes"] += 1
        if fix.ok and fix.x_ecef_m is not None:
            self._last_fix = (epoch.gpst_week, epoch.gpst_tow_s, fix.x_ecef_m)
        checks = self._ledger.check(view, (fix,))
        self._ledger.keep(view, whole, fix)
        self._emit(events)
        since = self.tracker.since_start_s(epoch.gpst_week, epoch.gpst_tow_s)
        return EpochResult(
            view,
            fix,
            since,
            tuple(events),
            tuple(checks),
            partial(sky_view, view, self.store),
            restarted_now,
            self._receiver_fix_near(epoch),
        )

    def _early_decline(self, epoch: MeasurementEpoch) -> Fix | None:
        """The declined fix of an epoch without a week or not after the latest one, unless
        it is the :data:`REANCHOR_EPOCHS`-th in a row before the latest, each after the one
        before it and the first not before the epoch before the latest (the latest jumped
        ahead: epochs sent again, or captures that overlap, come before that one too), or a
        receiver restart's (its clock set back): then the stream goes on from this epoch
        (:meth:`_reanchor`)."""
        if not epoch.week_known:
            return declined(epoch, Declined.of(Decline.NO_TIME))
        last = self._latest
        if last is not None:
            step = diff_s(epoch.gpst_week, epoch.gpst_tow_s, *last)
            if step < SAME_EPOCH_S:
                if step <= -SAME_EPOCH_S:
                    self._hold_behind(epoch)
                    # (a receiver restart may set its clock back: its time is the new one)
                    if epoch.restarted or self._stray_latest():
                        self._reanchor(epoch, last)
                        return None
                what = "repeats" if step > -SAME_EPOCH_S else f"is {-step:.3f} s before"
                why = Declined.of(Decline.OUT_OF_ORDER, what=what, week=last[0], tow_s=last[1])
                return declined(epoch, why)
        self._behind.clear()
        return None

    def _hold_behind(self, epoch: MeasurementEpoch) -> None:
        """Hold ``epoch``, which is before the latest, with those held before it if it
        follows the last of them (by at most :data:`REANCHOR_STEP_MAX_S`), else alone."""
        if self._behind:
            step = diff_s(epoch.gpst_week, epoch.gpst_tow_s, *self._behind[-1])
            if not SAME_EPOCH_S <= step <= REANCHOR_STEP_MAX_S:
                self._behind.clear()
        self._behind.append((epoch.gpst_week, epoch.gpst_tow_s))

    def _stray_latest(self) -> bool:
        """Whether the epochs held before the latest show that the latest was tagged ahead:
        :data:`REANCHOR_EPOCHS` of them, the first not before the epoch before the latest
        (it may repeat that one's time: a stream's messages of one time can come as two
        epochs around the stray one)."""
        if len(self._behind) < REANCHOR_EPOCHS:
            return False
        before = self._before_latest
        return before is None or diff_s(*self._behind[0], *before) > -SAME_EPOCH_S

    def _reanchor(self, epoch: MeasurementEpoch, latest: tuple[int, float]) -> None:
        """The stream's time from ``epoch`` again, which is before ``latest``: what the
        fixes before left is dropped as after a receiver restart (the checks still due
        counted ``integrity_unchecked``), and an emulated restart at or after ``latest``
        is to be made again."""
        if epoch.restarted:
            log.warning(
                "the receiver restarted with its clock %.3f s before the latest epoch's "
                "(GPS week %d %.3f s): the stream's time goes on from its restart",
                -diff_s(epoch.gpst_week, epoch.gpst_tow_s, *latest),
                latest[0],
                latest[1],
            )
        else:
            self.counters["time_reanchors"] += 1
            log.warning(
                "%d epochs in a row before GPS week %d %.3f s and after the one before it: "
                "that epoch was tagged ahead; the stream's time goes on from week %d %.3f s",
                len(self._behind),
                latest[0],
                latest[1],
                epoch.gpst_week,
                epoch.gpst_tow_s,
            )
        self._behind.clear()
        self._latest = self._before_latest = None
        if self._first is not None and diff_s(epoch.gpst_week, epoch.gpst_tow_s, *self._first) < 0:
            self._first = None
        at = self._restarted_at
        if at is not None and diff_s(epoch.gpst_week, epoch.gpst_tow_s, *at) < 0:
            self._restarted, self._restarted_at = False, None
        self._forget_fixes()

    def restart(self, epoch: MeasurementEpoch, rng: np.random.Generator) -> None:
        """Emulate a receiver restart at ``epoch``: frame sync is lost, every satellite is
        fractional until its time is known again by ``full_rule`` (:class:`SubframeEmulator`
        with one bit-sync delay draw; under the ``subframe`` rule decoded subframes when the
        stream has them); no warm start."""
        emulator = SubframeEmulator.draw(
            epoch.gpst_week, epoch.gpst_tow_s, epoch.prn, rng, rule=self.full_rule
        )
        self.tracker.restart(epoch.gpst_week, epoch.gpst_tow_s, emulator)
        self._forget_fixes()

    def _forget_fixes(self) -> None:
        """Forget what the fixes so far leave for the next ones (a restart of the receiver,
        emulated or its own, or of the stream's time): recovered ranges not yet checked,
        the warm start, the held height and the prediction screen's last fix."""
        self._ledger.forget()
        self._last_fix = None
        self._height.reset()
        self._predictor.reset()

    def _start_cfg(self, view: MeasurementEpoch) -> SolverConfig:
        """The solver settings for ``view``: once every measurement is full (conventional
        SPP) the iteration starts at the position of the last fix of the past
        WARM_START_MAX_AGE_S, as receivers do; it converges to the same solution in fewer
        steps. Any epoch with a fractional measurement starts at the Earth's centre (the
        paper's a-priori-free fast fix), and so does every epoch without a recent fix."""
        last = self._last_fix
        if (
            self.cfg.x0_ecef_m is not None
            or last is None
            or not bool(np.isfinite(view.pr_m).all())
            or not 0.0
            <= diff_s(view.gpst_week, view.gpst_tow_s, last[0], last[1])
            <= WARM_START_MAX_AGE_S
        ):
            return self.cfg
        return self._cfg_from(last[2])

    def _cfg_from(self, x0_ecef_m: tuple[float, float, float]) -> SolverConfig:
        """``replace(self.cfg, x0_ecef_m=...)`` with the settings read once per ``cfg``
        (``replace`` reads all of them each time: a few microseconds an epoch)."""
        held = self._cfg_settings
        if held is None or held[0] is not self.cfg:
            cfg = self.cfg
            held = self._cfg_settings = (
                cfg,
                {f.name: getattr(cfg, f.name) for f in fields(cfg) if f.init},
            )
        return type(held[0])(**{**held[1], "x0_ecef_m": x0_ecef_m})

    def _emit(self, events: list[TrackEvent]) -> None:
        if self.on_track is not None:
            for ev in events:
                self.on_track(ev)
