"""``bdsfix solve``: batch per-epoch fast and SPP solutions from an observation file (any
registered file format: RINEX 3 obs, an Android GnssLogger log) + RINEX nav files.

With ``--fractional non-geo`` (the default) every non-GEO pseudorange is reduced modulo c*T
before the fast solver sees it, as in the paper's real-data experiment; the SPP solver always
gets the full pseudoranges of the same epoch.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import itertools
import logging
import sys
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from typing import IO, TYPE_CHECKING, Literal

from service.core.counters import Counters, skipped_input
from service.core.ephemeris import EphemerisStore
from service.core.errors import InputError
from service.core.files import open_output
from service.core.systems import DEFAULT_SYSTEMS
from service.core.types import Fix, MeasurementEpoch
from service.engine.aiding import HeightAid, Predictor, SatSide, sat_side, with_screened
from service.engine.recovered import RecoveredLedger
from service.engine.solver import (
    CHUNK_EPOCHS,
    EpochAids,
    IonoSet,
    SolverConfig,
    fractionalize,
    sky_view,
    solve_many,
)
from service.engine.timetag import without_coarse_fractions
from service.engine.velocity import with_velocities

if TYPE_CHECKING:
    from service.engine.coarse import CoarseConfig

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class BatchOptions:
    """What ``bdsfix solve`` computes per epoch."""

    mode: Literal["fast", "spp", "both"] = "both"
    fractional: Literal["non-geo", "none"] = "non-geo"
    period_s: float | None = None
    """T of the fractional ranges; None: each satellite's system's code period."""
    cfg: SolverConfig = field(default_factory=SolverConfig)
    with_sky: bool = True
    """Attach the sky view to each fix (only the NMEA output shows it: GSV)."""
    coarse: CoarseConfig | None = None
    """The coarse-time fix's settings (None: its defaults; ``coarse_fix=False``: none), for
    the fast solver's epochs with too few full ranges, as the stream
    (:func:`service.engine.pipeline.coarse_time_fix`)."""


def load_navigation(
    paths: list[str],
    max_age_s: float = 7200.0,
    first: tuple[int, float] | None = None,
    systems: Iterable[str] = DEFAULT_SYSTEMS,
) -> tuple[EphemerisStore, IonoSet]:
    """Ephemeris store and broadcast ionosphere from one or more RINEX 3 nav files, refused
    (exit 3) without a BDS ephemeris or, given the observations' ``first`` epoch (GPST
    week, tow), when they are of another day (:mod:`service.commands.navcheck`)."""
    from service.commands.navcheck import anchor_systems, check_navigation, read_navigation

    navs = read_navigation(paths, systems)
    check_navigation(paths, navs, first, systems)
    store = EphemerisStore(max_age_s=max_age_s)
    params = []
    for nav in navs:  # every set of a file in one add_all (its checks vectorised)
        store.add_all(e for ephs in nav.ephemerides.values() for e in ephs)
        params += [nav.iono_bds, nav.iono_gps]
    anchor = anchor_systems(systems)
    if not any(prn[:1] in anchor for prn in store.prns):
        # every BDS set refused by the store's sanity checks (with BeiDou selected, GPS and
        # Galileo sets do not stand in for them, as in check_navigation)
        what = "BDS" if anchor == {"C"} else "/".join(sorted(anchor))
        raise InputError(f"no usable {what} ephemeris in {', '.join(paths)}")
    iono = IonoSet.of(params)
    if iono.bds is None and iono.gps is not None:
        log.warning(
            "no BDSA/BDSB ionosphere coefficients in %s: using GPSA/GPSB scaled "
            "to B1I by (f_L1/f_B1I)^2",
            ", ".join(paths),
        )
    store.iono = iono.preferred
    return store, iono


def solve_epochs(
    epochs: Iterator[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet,
    opts: BatchOptions,
    counters: Counters | None = None,
) -> Iterator[tuple[MeasurementEpoch, list[Fix]]]:
    """Yield each epoch with its fixes (fast first, then SPP, as the mode asks).

    The epochs are read and solved :data:`~service.engine.solver.CHUNK_EPOCHS` at a time by
    :func:`~service.engine.solver.solve_many` (the one solver kernel, a chunk of epochs at
    a time), so a file of any length streams through in bounded memory. Each fix
    with a position gets its velocity from the epoch's Doppler, a chunk at a time
    (:func:`~service.engine.velocity.with_velocities`). With height aiding or the
    prediction screen each epoch's inputs depend on the fixes before it: :func:`solve_aided`
    solves them in batches until those inputs settle. The fast solver's epochs with too few
    full ranges get the stream's coarse-time fix (:func:`with_coarse_fixes`), and the ranges
    its fixes recover are checked against the file's full ones (:func:`_checked`), counted
    in ``counters`` (``integrity_checks``, ``integrity_failures``, ``integrity_unchecked``,
    ``integrity_relative_anchors``) when given."""
    counters = Counters() if counters is None else counters
    read: deque[MeasurementEpoch] = deque()  # as read, until _checked takes them
    if opts.mode != "spp":
        epochs = _kept(epochs, read)
    if opts.cfg.height_aiding or opts.cfg.screen_predicted_m > 0.0:
        solved = solve_aided(epochs, store, iono, opts)
    else:
        solved = _solve_plain(epochs, store, iono, opts)
    if opts.mode == "spp":
        yield from solved
    else:
        yield from _checked(solved, read, opts, counters)


def _kept(
    epochs: Iterator[MeasurementEpoch], read: deque[MeasurementEpoch]
) -> Iterator[MeasurementEpoch]:
    """``epochs``, each also appended to ``read`` as it is read."""
    for epoch in epochs:
        read.append(epoch)
        yield epoch


def _solve_plain(
    epochs: Iterator[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet,
    opts: BatchOptions,
) -> Iterator[tuple[MeasurementEpoch, list[Fix]]]:
    """:func:`solve_epochs` without height aiding or the prediction screen."""
    while chunk := list(itertools.islice(epochs, CHUNK_EPOCHS)):
        read = chunk
        # a receiver time coarser than 1 ms (a phone before its first fix): no fractional
        # range enters the fix (service.engine.timetag.COARSE_TIME_S)
        chunk = [without_coarse_fractions(e)[0] for e in chunk]
        per_solver: list[list[Fix]] = []
        if opts.mode in ("fast", "both"):
            # (a time coarser than 1 ms: the ranges made fractional set aside too)
            fast_in = [_fast_view(e, opts) for e in read]
            fast = solve_many(fast_in, store, iono, opts.cfg, "fast", opts.with_sky)
            per_solver.append(with_coarse_fixes(fast, read, store, iono, opts))
        if opts.mode in ("spp", "both"):
            per_solver.append(solve_many(chunk, store, iono, opts.cfg, "spp", opts.with_sky))
        # the velocities of every solver's fixes in one computation (each fix's the same as
        # alone: with_velocities)
        pairs = [pair for fixes in per_solver for pair in zip(fixes, chunk, strict=True)]
        moving = _velocities(pairs, store, opts)
        per_solver = [moving[k : k + len(chunk)] for k in range(0, len(moving), len(chunk))]
        for k, epoch in enumerate(chunk):
            yield epoch, [fixes[k] for fixes in per_solver]


def _checked(
    solved: Iterator[tuple[MeasurementEpoch, list[Fix]]],
    read: deque[MeasurementEpoch],
    opts: BatchOptions,
    counters: Counters,
) -> Iterator[tuple[MeasurementEpoch, list[Fix]]]:
    """``solved`` as it is, each range a fast fix recovered (paper eq. 11, or the
    coarse-time fix's integers, relative ones too) checked by the stream's rule
    (:class:`service.engine.recovered.RecoveredLedger`) against the file's full range of
    the satellite: that of the same epoch where the file has it (every non-GEO range with
    ``--fractional non-geo``), else a later one (a phone's range fractional in the file),
    with the clock of any of the epoch's fixes. Counted in ``counters``
    (``integrity_checks``, ``integrity_failures``, ``integrity_unchecked``,
    ``integrity_relative_anchors``). ``read``: the epochs as read, in the order solved (a
    coarse-time fix's relative integers are of the fractional ranges of a receiver time
    coarser than 1 ms, which the solved epochs have set aside)."""
    ledger = RecoveredLedger(counters, full_from="the file")
    for epoch, fixes in solved:
        as_read = read.popleft()
        if epoch.restarted:  # the receiver's clock restarted: nothing recovered before
            ledger.forget()  # it is checked after it
        full = [p for p, pr in zip(epoch.prn, epoch.pr_m, strict=True) if pr == pr]
        ledger.due(full)  # those recovered at an earlier epoch
        ledger.check(epoch, fixes)
        if fixes[0].mode == "fast":
            ledger.keep(_fast_view(epoch, opts), _fast_whole(as_read, opts), fixes[0])
        ledger.due(full)  # and this epoch's own
        ledger.check(epoch, fixes)
        yield epoch, fixes


def _fast_view(epoch: MeasurementEpoch, opts: BatchOptions) -> MeasurementEpoch:
    """The rows of ``epoch`` the fast solver (the paper's method) is given: those of
    :func:`_fast_whole` without the fractional ranges of a receiver time coarser than 1 ms
    (:func:`~service.engine.timetag.without_coarse_fractions`)."""
    return without_coarse_fractions(_fast_whole(epoch, opts))[0]


def _fast_whole(epoch: MeasurementEpoch, opts: BatchOptions) -> MeasurementEpoch:
    """``epoch`` as the fast solver takes it, before the fractional ranges of a coarse time
    are set aside: its non-GEO ranges fractional with ``--fractional non-geo``."""
    if opts.fractional == "non-geo":
        return fractionalize(epoch, opts.period_s)
    return epoch


def with_coarse_fixes(
    fixes: list[Fix],
    epochs: list[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet,
    opts: BatchOptions,
    memo: dict[int, tuple[MeasurementEpoch, Fix, Fix]] | None = None,
) -> list[Fix]:
    """The fast solver's ``fixes`` of ``epochs`` (as read: their fractional ranges, those
    of ``--fractional non-geo`` too, are the coarse-time fix's rows), the coarse-time fix
    in place of the declines after which the stream tries it:
    the stream's own decision and time prior rules
    (:func:`service.engine.pipeline.coarse_time_fix`), an epoch at a time (the epochs
    with too few full ranges; none on a file whose every epoch has four GEOs). The
    solver's settings are ``opts.cfg`` without an epoch's aid, as the stream's; with
    ``opts.with_sky`` a fix gets its sky view as the kernel's do. (Its counters are not
    kept: the aided path solves an epoch more than once; the summary counts the coarse-time
    fixes written.) ``memo`` (the aided path's, for a chunk): an epoch solved again with the
    same decline of the paper's method gets the same fix without a second search (the
    coarse-time fix has no aid and no screen: its inputs are the epoch as read)."""
    from service.engine.coarse import TRIED_AFTER, CoarseConfig  # (loaded by solve's flags)

    todo = [k for k, fix in enumerate(fixes) if fix.reason_code in TRIED_AFTER]
    if not todo:
        return fixes
    from service.engine.pipeline import coarse_time_fix

    coarse = opts.coarse or CoarseConfig()
    out = list(fixes)
    for k in todo:
        seen = None if memo is None else memo.get(id(epochs[k]))
        if seen is not None and seen[0] is epochs[k] and _same_decline(seen[1], fixes[k]):
            # (the paper's decline itself where the search left it: this solve's)
            out[k] = fixes[k] if seen[2] is seen[1] else seen[2]
            continue
        whole = _fast_whole(epochs[k], opts)
        view, set_aside = without_coarse_fractions(whole)
        fix = coarse_time_fix(
            fixes[k], whole, view, set_aside, store, iono, opts.cfg, coarse, Counters()
        )
        if opts.with_sky and fix.ok and fix is not fixes[k]:
            fix = replace(fix, sky=sky_view(view, store, fix))
        if memo is not None:
            memo[id(epochs[k])] = (epochs[k], fixes[k], fix)
        out[k] = fix
    return out


def _same_decline(a: Fix, b: Fix) -> bool:
    """Whether the paper's method declined ``a`` and ``b`` alike: all that
    :func:`service.engine.pipeline.coarse_time_fix` reads of the paper's fix (its code and
    figures) besides returning it."""
    return a.reason_code == b.reason_code and a.decline == b.decline


def _velocities(
    pairs: list[tuple[Fix, MeasurementEpoch]], store: EphemerisStore, opts: BatchOptions
) -> list[Fix]:
    """The fixes of ``pairs`` with their velocities: the coarse-time fixes' as the stream
    gives them (:func:`service.engine.pipeline.fix_with_velocity`: an all-fractional one at
    its solved receive time, from the rows the fast solver had: the satellites' transmit
    times from its fractional ranges), the others computed together
    (:func:`~service.engine.velocity.with_velocities`: each the same as alone), each once."""
    coarse = [j for j, (fix, _) in enumerate(pairs) if fix.method == "coarse_time"]
    if not coarse:
        return with_velocities(pairs, store)
    from service.engine.pipeline import fix_with_velocity

    out: list[Fix | None] = [None] * len(pairs)
    taken = set(coarse)
    rest = [j for j in range(len(pairs)) if j not in taken]
    for j, fix in zip(rest, with_velocities([pairs[j] for j in rest], store), strict=True):
        out[j] = fix
    for j in coarse:
        fix, epoch = pairs[j]
        out[j] = fix_with_velocity(fix, _fast_view(epoch, opts), store)
    return [fix for fix in out if fix is not None]  # (every index set once)


def solve_aided(
    epochs: Iterator[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet,
    opts: BatchOptions,
) -> Iterator[tuple[MeasurementEpoch, list[Fix]]]:
    """:func:`solve_epochs` with height aiding or the prediction screen
    (:mod:`service.engine.aiding`): each epoch's aid and screen come from the fixes before
    it, as the stream solves them, one epoch at a time in the order read. Both solvers of
    an epoch get the same ranges (those the screen keeps, of the full epoch) and the same
    aid (one row more for each): the fast fix of the same rows is still SPP's solution. Aid
    and prediction follow the SPP fixes when SPP runs (the all-full solution, which the
    stream's fix is once every satellite's time is known), else the fast fixes.

    The epochs are nevertheless solved several at a time, by a fixed point over each chunk
    of :data:`~service.engine.solver.CHUNK_EPOCHS`: the epochs from the first not final
    (the front) to :data:`AIDED_WINDOW` on get their aid and screen (their inputs) from the
    fixes as last solved (an epoch not solved yet: the last fix moved on by its velocity,
    :meth:`~service.engine.aiding.Predictor.guess`), and those whose inputs
    differ from the ones they were solved with (or not solved yet) are solved together
    (:func:`_solve_inputs`; each epoch its own aid, :class:`~service.engine.solver.EpochAids`).
    The epochs before the front being final, the first one's inputs are exact, so the
    front moves on with every pass; an epoch solved with the inputs its final predecessors
    give is final. The result is that of solving each epoch alone, to the output's bytes
    (the kernel solving several epochs together differs from one alone in the last bits of
    a float; the aid, given to a step of
    :data:`~service.engine.aiding.AID_QUANTUM_M`,
    does not pass such bits on), except where such a last bit falls on a boundary: a held
    height or sigma half a step from a rounding, a range's residual at the screen's limit
    (not met on the TST drive or HKSC, whose outputs the tests compare byte for byte).
    Each chunk's passes and solves are logged (debug)."""
    held, predictor = HeightAid(), Predictor()
    while chunk := list(itertools.islice(epochs, CHUNK_EPOCHS)):
        views = [without_coarse_fractions(e)[0] for e in chunk]
        n = len(views)
        moved: list[list[Fix] | None] = [None] * n  # the fixes (with velocities), unscreened
        coarse = [False] * n  # whether the fast fix is the coarse-time fix's (not screened)
        used: list[_Inputs | None] = [None] * n  # the inputs each was solved with
        want: list[_Inputs | None] = [None] * n  # the inputs from the fixes as last solved
        cache: dict[int, tuple[object, MeasurementEpoch, dict[str, str]]] = {}
        sides: dict[int, SatSide | None] = {}
        searched: dict[int, tuple[MeasurementEpoch, Fix, Fix]] = {}  # (with_coarse_fixes)
        front = passes = resolved = 0  # the epochs before the front are final
        done: list[list[Fix]] = []  # their fixes
        while front < n:
            h, p = held.copy(), predictor.copy()  # (the state at the front: final)
            todo: dict[int, _Inputs] = {}
            for k in range(front, min(n, front + AIDED_WINDOW)):
                inputs = want[k] = _inputs(k, views[k], h, p, store, opts.cfg, cache, sides)
                if used[k] != inputs:
                    todo[k] = inputs
                fixes = moved[k]
                if fixes is not None:
                    guess: Fix | None = _finished(fixes, inputs, views[k], store, coarse[k])[-1]
                else:  # not solved yet: the last fix moved on by its velocity stands in
                    guess = p.guess(views[k].gpst_week, views[k].gpst_tow_s)
                if guess is not None:
                    h.update(guess, opts.cfg)
                    p.update(guess)
            # the epochs up to the first solved with other inputs are final: the front
            # moves past them
            stop = next(iter(todo), min(n, front + AIDED_WINDOW))
            for k in range(front, stop):
                fixes, final = moved[k], want[k]
                if fixes is None or final is None:  # (solved with its inputs, or in todo)
                    raise RuntimeError(f"aided epoch {k} has no fixes")
                done.append(_finished(fixes, final, views[k], store, coarse[k]))
                held.update(done[-1][-1], opts.cfg)
                predictor.update(done[-1][-1])
            front = stop
            if not todo:
                continue
            passes += 1
            resolved += len(todo)
            solved, from_coarse = _solve_inputs(views, todo, store, iono, opts, chunk, searched)
            for k, fixes in solved.items():
                moved[k], used[k], coarse[k] = fixes, todo[k], k in from_coarse
        log.debug(
            "aided chunk of %d epochs: %d passes, %d epochs solved (%d again)",
            n,
            passes,
            resolved,
            resolved - n,
        )
        yield from zip(views, done, strict=True)


AIDED_WINDOW = 16
"""How many epochs from the first not final :func:`solve_aided` solves together: further
ones would be solved from poorer guesses, and again; fewer make more, smaller kernel calls
(TST + HKSC, --mode both, 1965 epochs: window 4: 2366 solves in 1089 calls, CPU 10.8 s;
8: 2795 in 617, 7.9 s; 16: 3304 in 360, 7.6 s; 32: 4031 in 215, 8.4 s; 64: 5575 in 145,
10.4 s; one run each on a shared machine)."""


@dataclass(frozen=True, slots=True)
class _Inputs:
    """What an epoch's solve of :func:`solve_aided` is given beyond its ranges: the aid
    (None: none) and the ranges the screen leaves out (with why: ``Fix.excluded``); two
    epochs' inputs are equal when their solves are (the reasons' wording aside)."""

    aid: tuple[float, float] | None
    rows: MeasurementEpoch = field(compare=False)
    screened: dict[str, str] = field(compare=False)
    left_out: frozenset[str]


def _inputs(
    k: int,
    view: MeasurementEpoch,
    held: HeightAid,
    predictor: Predictor,
    store: EphemerisStore,
    cfg: SolverConfig,
    cache: dict[int, tuple[object, MeasurementEpoch, dict[str, str]]],
    sides: dict[int, SatSide | None],
) -> _Inputs:
    """Epoch ``k``'s aid and screen from the state of the fixes before it (the screen of
    the same prediction as last time from ``cache``; the satellites' side of the epoch's
    predicted ranges computed once, ``sides``)."""
    aid = held.prior(view.gpst_week, view.gpst_tow_s, cfg) if cfg.height_aiding else None
    key = predictor.key()
    got = cache.get(k)
    if got is None or got[0] != key:
        if key is not None and cfg.screen_predicted_m > 0.0 and k not in sides:
            sides[k] = sat_side(view, store)
        rows, screened = predictor.screen(view, store, cfg, sides.get(k))
        got = cache[k] = (key, rows, screened)
    _, rows, screened = got
    return _Inputs(aid, rows, screened, frozenset(screened))


def _solve_inputs(
    views: list[MeasurementEpoch],
    todo: dict[int, _Inputs],
    store: EphemerisStore,
    iono: IonoSet,
    opts: BatchOptions,
    read: list[MeasurementEpoch],
    searched: dict[int, tuple[MeasurementEpoch, Fix, Fix]] | None = None,
) -> tuple[dict[int, list[Fix]], set[int]]:
    """The fixes (with velocities, without the screen's reasons) of the epochs ``todo``
    given their inputs, solved together: the epochs without an aid in one batch, those
    with one in others (each epoch its own aid, :class:`EpochAids`; no two of one time in
    a batch). A fast fix declined for too few full ranges: the coarse-time fix of the
    epoch as ``read`` (:func:`with_coarse_fixes`, unscreened and without an aid, as the
    stream's); the second value, the epochs whose fast fix the coarse-time fix replaced."""
    batches: list[tuple[list[int], SolverConfig]] = [([], opts.cfg)]
    aids: list[dict[tuple[int, float], tuple[float, float]]] = []
    for k, inputs in todo.items():
        if inputs.aid is None:
            batches[0][0].append(k)
            continue
        t = (views[k].gpst_week, views[k].gpst_tow_s)
        g = next((i for i, seen in enumerate(aids) if t not in seen), None)
        if g is None:
            aids.append({})
            batches.append(([], replace(opts.cfg, height_aid=EpochAids(aids[-1]))))
            g = len(aids) - 1
        aids[g][t] = inputs.aid
        batches[g + 1][0].append(k)
    out: dict[int, list[Fix]] = {}
    from_coarse: set[int] = set()
    for batch, cfg in batches:
        if not batch:
            continue
        rows = [todo[k].rows for k in batch]
        per_solver: list[list[Fix]] = []
        if opts.mode in ("fast", "both"):
            # (a time coarser than 1 ms: the ranges made fractional set aside too)
            fast_in = [_fast_view(r, opts) for r in rows]
            paper = solve_many(fast_in, store, iono, cfg, "fast", opts.with_sky)
            fast = with_coarse_fixes(paper, [read[k] for k in batch], store, iono, opts, searched)
            from_coarse.update(k for k, a, b in zip(batch, paper, fast, strict=True) if a is not b)
            per_solver.append(fast)
        if opts.mode in ("spp", "both"):
            per_solver.append(solve_many(rows, store, iono, cfg, "spp", opts.with_sky))
        for j, k in enumerate(batch):
            out[k] = [fixes[j] for fixes in per_solver]
    return _with_velocities(out, views, store, opts), from_coarse


def _with_velocities(
    fixes: dict[int, list[Fix]],
    views: list[MeasurementEpoch],
    store: EphemerisStore,
    opts: BatchOptions,
) -> dict[int, list[Fix]]:
    """The fixes of each epoch (the same number each) with their velocities, computed
    together (:func:`~service.engine.velocity.with_velocities`: each the same as alone;
    the aid and the prediction use them)."""
    ks = list(fixes)
    m = len(fixes[ks[0]]) if ks else 0
    pairs = [(f, views[k]) for k in ks for f in fixes[k]]
    moving = _velocities(pairs, store, opts)
    return {k: moving[j * m : (j + 1) * m] for j, k in enumerate(ks)}


def _finished(
    fixes: list[Fix],
    inputs: _Inputs,
    view: MeasurementEpoch,
    store: EphemerisStore,
    coarse: bool = False,
) -> list[Fix]:
    """The fixes of an epoch with the ranges the screen left out (and the sky: every
    satellite of the epoch, the screened ones unused); ``coarse``: the first (the fast
    solver's) is the coarse-time fix, solved from every range of the epoch: no range was
    screened out of it (the stream screens the paper's fix, which the coarse-time fix then
    replaces with its own rows and exclusions)."""
    return [
        f if coarse and j == 0 else with_screened(f, inputs.screened, view, store)
        for j, f in enumerate(fixes)
    ]


@contextlib.contextmanager
def batch_gc() -> Iterator[None]:
    """The cyclic garbage collector set for a batch run (restored after): the objects made
    so far (the modules, the navigation) frozen out of its passes, and its automatic passes
    off; the caller runs :func:`gc.collect` once per chunk instead.

    A solve makes millions of short-lived objects, nearly all without cycles (reference
    counting frees them); the automatic passes, one every 700 allocations over the young
    ones and now and then over every object, were 4-7 % of the CPU time of ``bdsfix
    solve`` (HKSC and the urban drive, with --systems C,G,E), and a pass per chunk keeps
    what cycles there are bounded (the urban drive's peak memory is the same either way)."""
    enabled = gc.isenabled()
    gc.freeze()
    gc.disable()
    try:
        yield
    finally:
        gc.unfreeze()
        if enabled:
            gc.enable()


@contextlib.contextmanager
def _open_out(path: str) -> Iterator[IO[str]]:
    if path == "-":
        yield sys.stdout
        return
    with open_output(path, encoding="ascii", newline="") as fh:  # InputError (exit 3)
        yield fh


def main_solve(args: argparse.Namespace) -> int:
    from drivers.source import file_epochs
    from service.commands.options import coarse_config, solver_config, systems_of
    from service.commands.summary import (
        decline_lines,
        no_epochs_hint,
        skipped_line,
        unchecked_text,
    )
    from service.output.records import csv_header, fix_csv_row, fix_json_line

    if args.format == "nmea":  # pynmeagps only when asked for (start-up)
        from service.output.nmea import fix_utc, sentences_for_fix

    cfg = solver_config(args)
    opts = BatchOptions(
        mode=args.mode,
        fractional=args.fractional,
        period_s=None if args.period_ms is None else args.period_ms * 1e-3,
        cfg=cfg,
        with_sky=args.format == "nmea",
        coarse=coarse_config(args),
    )
    systems = systems_of(args)
    events, read_counters = file_epochs(args.obs, systems=systems)
    epochs = (e for e in events if isinstance(e, MeasurementEpoch))
    head, _ = file_epochs(args.obs, lenient=True)  # the first epoch only
    with contextlib.closing(head):  # type: ignore[type-var]
        first = next(
            ((e.gpst_week, e.gpst_tow_s) for e in head if isinstance(e, MeasurementEpoch)), None
        )
    store, iono = load_navigation(list(args.nav), first=first, systems=systems)
    counts, excluded, engine = Counters(), Counters(), Counters()
    declined = {"fast": Counters(), "spp": Counters()}
    n_epochs = 0
    with _open_out(args.out) as out, batch_gc():
        if args.format == "csv":
            out.write(csv_header() + "\n")
        for _epoch, fixes in solve_epochs(epochs, store, iono, opts, engine):
            n_epochs += 1
            if n_epochs % CHUNK_EPOCHS == 0:
                gc.collect()
            for fix in fixes:
                counts[f"{fix.solver}:{fix.mode}"] += 1
                if fix.ok and fix.method == "coarse_time":
                    engine["coarse_fixes"] += 1
                if fix.reason_code:
                    declined[fix.solver][f"declined_{fix.reason_code}"] += 1
                for prn in fix.excluded:
                    excluded[f"{fix.solver} {prn}"] += 1
                if args.format == "jsonl":
                    out.write(fix_json_line(fix) + "\n")
                elif args.format == "csv":
                    out.write(fix_csv_row(fix) + "\n")
            if args.format == "nmea":
                best = next((f for f in fixes if f.ok), fixes[0])
                for sentence in sentences_for_fix(best, utc=fix_utc(best), time_known=True):
                    out.write(sentence.decode("ascii"))
    parts = []
    for solver in ("fast", "spp"):
        ran = sum(n for k, n in counts.items() if k.startswith(f"{solver}:"))
        if ran:
            modes = ", ".join(
                f"{k.split(':')[1]} {n}"
                for k, n in sorted(counts.items())
                if k.startswith(f"{solver}:") and not k.endswith(":none")
            )
            n_fixes = ran - counts[f"{solver}:none"]
            parts.append(f"{solver} solver {n_fixes} fixes ({modes or 'none'})")
    print("; ".join([f"bdsfix solve: {n_epochs} epochs", *parts]), file=sys.stderr)
    if engine["integrity_checks"]:
        print(
            f"  fast solver integrity checks {engine['integrity_checks']} (recovered "
            "ranges against the file's full ones), failures "
            f"{engine['integrity_failures']}{unchecked_text(engine)}",
            file=sys.stderr,
        )
    if engine["coarse_fixes"]:
        print(
            f"  fast solver coarse-time fixes {engine['coarse_fixes']} (fewer full "
            "ranges than the paper's method needs: Doppler prior, coarse time)",
            file=sys.stderr,
        )
    for solver, c in declined.items():
        for line in decline_lines(c, indent=f"  {solver} solver ", command="solve"):
            print(line, file=sys.stderr)
    if excluded:
        parts_ex = ", ".join(f"{k} {n}" for k, n in excluded.most_common())
        print(f"  excluded by fault detection: {parts_ex}", file=sys.stderr)
    for line in skipped_line(skipped_input(read_counters)):
        print(line, file=sys.stderr)
    if n_epochs == 0:
        print(f"  {no_epochs_hint('solve')}", file=sys.stderr)
    return 0
