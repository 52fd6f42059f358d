"""The judgement of a solution and the :class:`~service.core.types.Fix` it becomes: written
once for the per-epoch solver (:mod:`service.engine.solver`) and the batch
(:mod:`service.engine.batch`), so that the two cannot differ in what they decide or in how a
decline is recorded.

A converged, weighted solution is judged in the order of docs/method.md: the chi-square
test of its residuals (:mod:`service.engine.raim`), the plausible shell (altitude, receiver
clock), the PDOP gate. Its first failure is the decline (:func:`verdict`); a decline's words
come from the one table (:mod:`service.core.declines`). Fault exclusion ranks candidate
solutions by :func:`fit_ratio`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Literal, Protocol

import numpy as np

from service.core.constants import C_M_S
from service.core.declines import Decline, Declined
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


def fit_ratio(chi2: float | None, chi2_max: float | None) -> float:
    """chi2 / threshold of a candidate solution of fault exclusion (inf: no test): the
    smallest ranks first."""
    return chi2 / chi2_max if chi2 is not None and chi2_max else math.inf


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
