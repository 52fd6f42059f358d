"""The ranges a fast fix recovered and their integrity check against the full ones, for the
stream's pipeline (:mod:`service.engine.pipeline`: once the satellite's SOW decodes) and
``bdsfix solve`` (against the file's full range) alike; a module of its own so that the
batch command imports the pipeline only for a file that needs the coarse-time fix."""

from __future__ import annotations

import math
from collections.abc import Mapping

from service.core.constants import C_M_S
from service.core.types import Fix, MeasurementEpoch

RECOVERED_MAX_AGE_S = 60.0
"""A recovered range is checked against the full one within this long of its fix [s, data
time]: the satellite's own range moves by at most ~1 km/s, so 60 s keeps the check well
inside half an ambiguity (150 km at 1 ms) once the receiver clock's change is taken out. A
satellite that is full only later (lost, then tracked again) has its recovered range
dropped unchecked (``integrity_unchecked``)."""


def recovered_ranges(view: MeasurementEpoch, fix: Fix) -> dict[str, float]:
    """The full ranges a fast fix recovered: ``recovered_pr_m`` (the systems solved with the
    GEOs' full rows), and for the other systems' fractional rows, whose integers the solver
    gives only in ``ambiguity`` (paper eq. 11 with the BeiDou clock), fraction + N c T."""
    out = dict(fix.recovered_pr_m)
    for prn, pr_m in integer_ranges(view, fix.ambiguity).items():
        out.setdefault(prn, pr_m)
    return out


def integer_ranges(view: MeasurementEpoch, integers: Mapping[str, int]) -> dict[str, float]:
    """The ranges that ``integers`` (units of each row's period) make of the fractional
    ranges of ``view``'s rows, fraction + N c T (paper eq. 11), for those it has."""
    out = {}
    for prn, n in integers.items():
        if prn in view.prn:
            i = view.prn.index(prn)
            out[prn] = float(view.frac_pr_m[i] + n * C_M_S * view.period_s[i])
    return out


def integer_agrees(
    recovered_pr_m: float, full_pr_m: float, period_s: float, clock_change_m: float = 0.0
) -> bool:
    """A recovered pseudorange's integer (paper eq. 11) is the full range's: the two within
    half an ambiguity, c T / 2 (150 km at 1 ms; the range moves by at most ~1 km/s in the
    meantime) once ``clock_change_m``, what the receiver's clock moved between the two
    epochs, is taken from the full one (a u-blox receiver steps its clock by whole
    milliseconds, which moves every range by 300 km each); False when the full range or
    the change is not finite."""
    diff = full_pr_m - clock_change_m - recovered_pr_m
    return bool(math.isfinite(diff)) and abs(diff) < C_M_S * period_s / 2


def system_clock_m(fix: Fix, prn: str) -> float | None:
    """The receiver clock [m] of ``fix`` for the system of satellite ``prn``: its entry in
    ``clocks_m`` on a fix of several systems, else ``clock_bias_m`` (a fix of one system:
    that of ``prn`` if it used any of its satellites); None for a declined fix or a system
    it did not solve, or a coarse-time fix whose integers are relative (its clocks hold
    whole periods in doubt: no receiver clock to check against)."""
    if not fix.ok or fix.relative_ambiguity:
        return None
    if fix.clocks_m:
        return fix.clocks_m.get(prn[:1])
    return fix.clock_bias_m if any(p[:1] == prn[:1] for p in fix.used) else None
