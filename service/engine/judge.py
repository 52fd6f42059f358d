"""The judgement of a solution and the :class:`~service.core.types.Fix` it becomes, for the
one solver kernel (:mod:`service.engine.solver`), so that a decision and the words of a
decline are written once.

A converged, weighted solution is judged in this order: the chi-square test of its
residuals (:mod:`service.engine.raim`, docs/method.md), the plausible shell (altitude,
receiver clock), the PDOP gate. Its first failure is the decline (:func:`verdict`); a
decline's words come from the one table (:mod:`service.core.declines`). Fault exclusion
ranks candidate solutions by :func:`fit_ratio`, in the one exclusion loop (:func:`exclude`),
which the kernel feeds every candidate of every failed epoch of a stage in one chunk.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Literal, Protocol, TypeVar

import numpy as np

from service.core.constants import C_M_S
from service.core.declines import Decline, Declined, excluded_why
from service.core.systems import GnssSystem
from service.core.types import Fix
from service.engine.raim import Integrity

Solver = Literal["fast", "spp"]


class Gates(Protocol):
    """The settings a judgement reads (:class:`service.engine.solver.SolverConfig`'s,
    named here without importing the solver, which imports this module)."""

    @property
    def alt_min_m(self) -> float: ...
    @property
    def alt_max_m(self) -> float: ...
    @property
    def clock_max_s(self) -> float: ...
    @property
    def pdop_max(self) -> float: ...


def decline_fix(
    solver: Solver,
    gpst_week: int,
    gpst_tow_s: float,
    prn: Sequence[str],
    frac: Sequence[bool],
    why: Declined,
    **fields: object,
) -> Fix:
    """The declined fix (``mode="none"``) of a solve over rows ``prn`` (``frac``: which of
    them are fractional), declined for ``why``, with the figures ``fields`` of the fix."""
    return Fix(
        solver=solver,
        mode="none",
        gpst_week=gpst_week,
        gpst_tow_s=gpst_tow_s,
        full=tuple(p for p, f in zip(prn, frac, strict=True) if not f),
        fractional=tuple(p for p, f in zip(prn, frac, strict=True) if f),
        decline=why,
        **fields,  # type: ignore[arg-type]
    )


def verdict(
    integ: Integrity,
    used: Sequence[str],
    alt_m: float,
    clock_m: float,
    pdop: float,
    cfg: Gates,
    slots: Sequence[int] | None = None,
) -> Declined | None:
    """The decline of a solution (None: it is published): a failed chi-square test (the
    reason names the used satellite ``used[k]`` with the largest w-test, ``integ.w[k]``, or
    ``integ.w[slots[k]]`` where the w-tests cover a batch's slots), it lies outside the
    plausible shell (altitude ``alt_m``, receiver clock ``clock_m``: the one furthest from
    zero), or its PDOP is above the gate."""
    if integ.chi2 is not None and not integ.passed:
        # numpy.nanargmax(|w|) where any w is finite, else the first row (as plain floats:
        # a batch judges thousands of failed candidates)
        w_all: list[float] = integ.w.tolist()
        wl = w_all if slots is None else [w_all[i] for i in slots]
        worst = 0
        if any(math.isfinite(v) for v in wl):
            size = [abs(v) if v == v else -math.inf for v in wl]  # NaN: never the largest
            worst = size.index(max(size))
        return Declined.of(
            Decline.CHI2,
            chi2=integ.chi2,
            chi2_max=integ.chi2_max,
            redundancy=integ.redundancy,
            prn=used[worst],
            w=wl[worst],
        )
    if not (cfg.alt_min_m <= alt_m <= cfg.alt_max_m) or abs(clock_m) > cfg.clock_max_s * C_M_S:
        return implausible(alt_m, clock_m, cfg)
    if not pdop <= cfg.pdop_max:
        return Declined.of(Decline.PDOP_GATE, pdop=pdop, pdop_max=cfg.pdop_max)
    return None


def implausible(alt_m: float, clock_m: float, cfg: Gates) -> Declined:
    """The decline of a solution outside the plausible shell (altitude, receiver clock)."""
    return Declined.of(
        Decline.IMPLAUSIBLE,
        alt_m=alt_m,
        alt_min_m=cfg.alt_min_m,
        alt_max_m=cfg.alt_max_m,
        clock_s=clock_m / C_M_S,
        clock_max_s=cfg.clock_max_s,
    )


def no_exclusion(fix: Fix, max_exclusions: int) -> Fix:
    """``fix`` (a failed test's decline) declined because no exclusion of up to
    ``max_exclusions`` satellites resolves it."""
    why = Declined.of(
        Decline.CHI2, "no_exclusion", reason=fix.reason, max_exclusions=max_exclusions
    )
    return replace(fix, decline=why)


def ambiguous_exclusion(fix: Fix, passing: int, clash: tuple[str, int, int]) -> Fix:
    """``fix`` (a failed test's decline) declined because of the ``passing`` candidates of
    fault exclusion, one has another integer than the best-fitting one: ``clash`` is the
    satellite and its integer in the best-fitting candidate and in the other
    (:func:`integer_clash`)."""
    prn, n_taken, n_other = clash
    why = Declined.of(
        Decline.AMBIGUOUS,
        "exclusion",
        passing=passing,
        prn=prn,
        n_taken=n_taken,
        n_other=n_other,
    )
    return replace(fix, decline=why)


def integer_clash(
    taken: Mapping[str, int], others: Sequence[Mapping[str, int]]
) -> tuple[str, int, int] | None:
    """The first satellite (in PRN order) whose integer (paper eq. 11: whole periods of a
    fractional range) differs between ``taken`` and one of ``others``, with both integers;
    None when every satellite the candidates share has one integer."""
    for other in others:
        for prn in sorted(taken.keys() & other.keys()):
            if taken[prn] != other[prn]:
                return prn, taken[prn], other[prn]
    return None


def fit_ratio(chi2: float | None, chi2_max: float | None) -> float:
    """chi2 / threshold of a candidate solution of fault exclusion (inf: no test): the
    smallest ranks first."""
    return chi2 / chi2_max if chi2 is not None and chi2_max else math.inf


TIE_RTOL = 1e-9
"""Fault exclusion's candidates whose chi2 / threshold differ by less than this fraction are
equals (the first is taken): two satellites whose removal leaves the same solution (the only
other row of a system, whose clock then absorbs it) give the same chi2 but for the last
bits, which depend on what else is solved with them in a batch."""


def _better(ratio: float, best: float) -> bool:
    """A candidate's :func:`fit_ratio` ranks before the best so far (not merely equal to
    it within :data:`TIE_RTOL`)."""
    if math.isinf(best):  # no test so far (inf - inf would be NaN: nothing could win)
        return ratio < best
    return ratio < best - TIE_RTOL * abs(best)


@dataclass(frozen=True, slots=True)
class Failed:
    """A solution that failed the chi-square test: what fault exclusion needs."""

    chi2: float
    chi2_max: float
    redundancy: int
    kept: tuple[str, ...]  # the satellites the solution used, in row order
    wtest: tuple[float, ...]  # their w-tests
    fix: Fix  # the solution's decline (reason_code chi2)
    # where its exclusion candidates start phase 1: the solution, when every row is full
    # and it lies near the Earth (no integers to resolve, so phase 1 converges to the same
    # fixed point from there as from the Earth's centre, in 2-3 iterations instead of 6-8);
    # None: the Earth's centre
    warm_start: tuple[float, float, float] | None = None

    def why(self, k: int) -> str:
        """Why satellite ``kept[k]`` goes when it is excluded: the test and its w-test."""
        return excluded_why("chi2", chi2=self.chi2, chi2_max=self.chi2_max, w=self.wtest[k])


Outcome = Fix | Failed | None
"""What solving one set of rows gives: a fix or a decline, or a failed chi-square test (None:
not solved yet; a candidate whose outcome is None leaves its solution undecided)."""

Key = TypeVar("Key")
State = TypeVar("State")


def exclude(
    failed: Mapping[Key, tuple[Failed, State]],
    without: Callable[[State, str], State],
    solve: Callable[[list[State]], list[tuple[Outcome, State]]],
    max_exclusions: int,
) -> tuple[dict[Key, Fix], set[Key]]:
    """Fault exclusion (docs/method.md): up to ``max_exclusions`` satellites, one at a time,
    for every solution of ``failed`` (its failed test and the rows it came from, ``State``:
    what ``without(state, prn)`` removes a satellite from and ``solve`` solves, in one call
    for every candidate of every solution of a stage, giving each candidate's outcome and
    the state its own candidates are made from).

    At each stage every used satellite is excluded in turn and the rest re-solved (phase 1
    included: a fault on a full row can corrupt every integer). Of the candidates that pass
    the chi-square test and the other checks, the one with the smallest chi2 / threshold
    (:func:`fit_ratio`; the first of equals, :data:`TIE_RTOL`) is taken; when none passes,
    the best-fitting failed candidate is the start of the next stage. An exclusion must
    leave a testable solution (redundancy >= 1 after it), so it needs redundancy >= 2
    before. Why a satellite went is its w-test in the failed solution (:meth:`Failed.why`).
    A fast fix's candidates each resolve the integers again: when a passing candidate of a
    stage has another integer than the best-fitting one for a satellite both use, one of
    the two passed with a wrong integer and nothing tells which, so the solution is
    declined (:func:`ambiguous_exclusion`) rather than the best-fitting one published.

    Returns the fixes of the solutions an exclusion resolved (``excluded`` says which
    satellites went and why) and the keys with none (their fix is :func:`no_exclusion` of
    the failed solution's); a key with a candidate whose outcome is None is in neither."""
    current: dict[Key, tuple[Failed, State, dict[str, str]]] = {
        key: (f, state, {}) for key, (f, state) in failed.items()
    }
    out: dict[Key, Fix] = {}
    hopeless: set[Key] = set()
    for _stage in range(max_exclusions):
        cands: list[State] = []
        owner: list[tuple[Key, int]] = []  # (solution, index in its failed.kept)
        for key, (f, state, _) in current.items():
            if f.redundancy >= 2:  # an exclusion must leave a testable solution
                for k, prn in enumerate(f.kept):
                    cands.append(without(state, prn))
                    owner.append((key, k))
        if not cands:
            break  # every solution left has redundancy < 2: hopeless (below)
        results = solve(cands)
        passed: dict[Key, tuple[float, Fix, int]] = {}
        passing_ints: dict[Key, list[dict[str, int]]] = {}  # each passing candidate's
        failing: dict[Key, tuple[float, Failed, int, State]] = {}
        unsure: set[Key] = set()
        for (key, k), (res, after) in zip(owner, results, strict=True):
            if res is None:
                unsure.add(key)
            elif isinstance(res, Fix):
                if res.ok:
                    passing_ints.setdefault(key, []).append(res.ambiguity)
                    ratio = fit_ratio(res.chi2, res.chi2_max)
                    if key not in passed or _better(ratio, passed[key][0]):
                        passed[key] = (ratio, res, k)
            else:
                ratio = fit_ratio(res.chi2, res.chi2_max)
                if key not in failing or _better(ratio, failing[key][0]):
                    failing[key] = (ratio, res, k, after)
        nxt: dict[Key, tuple[Failed, State, dict[str, str]]] = {}
        for key, (f, _, removed) in current.items():
            if key in unsure:
                continue
            if f.redundancy < 2:
                hopeless.add(key)
            elif key in passed:
                _, fix, k = passed[key]
                clash = integer_clash(fix.ambiguity, passing_ints[key])
                if clash is not None:
                    out[key] = ambiguous_exclusion(f.fix, len(passing_ints[key]), clash)
                else:
                    out[key] = replace(fix, excluded=removed | {f.kept[k]: f.why(k)})
            elif key in failing:
                _, f2, k, after = failing[key]
                nxt[key] = (f2, after, removed | {f.kept[k]: f.why(k)})
            else:
                hopeless.add(key)
        current = nxt
    hopeless |= current.keys()  # every stage done, none passed
    return out, hopeless


def solution_fix(
    *,
    solver: Solver,
    gpst_week: int,
    gpst_tow_s: float,
    x: Sequence[float] | np.ndarray,
    clocks: Sequence[float] | np.ndarray,
    systems: Sequence[GnssSystem],
    lat_deg: float,
    lon_deg: float,
    alt_m: float,
    gdop_full: float | None,
    pdop: float,
    hdop: float,
    vdop: float,
    cov: list[list[float]],
    integ: Integrity,
    resid_rms_m: float,
    iterations: int,
    used: tuple[str, ...],
    frac: Sequence[bool],
    ambiguity: dict[str, int],
    recovered_pr_m: dict[str, float],
) -> Fix:
    """The published fix of a solution that passed :func:`verdict`: position ``x``, the
    receiver clocks ``clocks`` [m] of ``systems`` (``Fix.clock_bias_m`` is the first;
    ``clocks_m`` names each when there is more than one), DOPs, the east-north-up
    covariance ``cov`` and the integrity figures ``integ``, over the rows ``used`` (``frac``:
    which are fractional; mode ``fast`` when any is)."""
    full = tuple([p for p, f in zip(used, frac, strict=True) if not f])
    c0, c1, c2 = cov[0], cov[1], cov[2]
    return Fix(
        solver=solver,
        mode="fast" if len(full) < len(used) else "spp",
        gpst_week=gpst_week,
        gpst_tow_s=gpst_tow_s,
        gdop_full=gdop_full,
        iterations=iterations,
        resid_rms_m=resid_rms_m,
        redundancy=integ.redundancy,
        chi2=integ.chi2,
        chi2_max=integ.chi2_max,
        x_ecef_m=(float(x[0]), float(x[1]), float(x[2])),
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        alt_m=alt_m,
        clock_bias_m=float(clocks[0]),
        clocks_m=(
            {s.value: float(c) for s, c in zip(systems, clocks, strict=True)}
            if len(systems) > 1
            else {}
        ),
        pdop=pdop,
        hdop=hdop,
        vdop=vdop,
        # correctly rounded square roots, as numpy's
        std_enu_m=(
            math.sqrt(max(c0[0], 0.0)),
            math.sqrt(max(c1[1], 0.0)),
            math.sqrt(max(c2[2], 0.0)),
        ),
        cov_enu_m2=((c0[0], c0[1], c0[2]), (c1[0], c1[1], c1[2]), (c2[0], c2[1], c2[2])),
        hpl_m=integ.hpl_m,
        vpl_m=integ.vpl_m,
        used=used,
        full=full,
        fractional=tuple([p for p, f in zip(used, frac, strict=True) if f]),
        ambiguity=ambiguity,
        recovered_pr_m=recovered_pr_m,
    )
