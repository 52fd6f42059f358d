"""The ranges a fast fix recovered and their integrity check against the full ones, for the
stream's pipeline (:mod:`service.engine.pipeline`: once the satellite's SOW decodes) and
``bdsfix solve`` (against the file's full range) alike; a module of its own so that the
batch command imports the pipeline only for a file that needs the coarse-time fix."""

from __future__ import annotations

import math

from service.core.constants import C_M_S
from service.core.types import Fix, MeasurementEpoch


def recovered_ranges(view: MeasurementEpoch, fix: Fix) -> dict[str, float]:
    """The full ranges a fast fix recovered: ``recovered_pr_m`` (the systems solved with the
    GEOs' full rows), and for the other systems' fractional rows, whose integers the solver
    gives only in ``ambiguity`` (paper eq. 11 with the BeiDou clock), fraction + N c T."""
    out = dict(fix.recovered_pr_m)
    for prn, n in fix.ambiguity.items():
        if prn not in out and prn in view.prn:
            i = view.prn.index(prn)
            out[prn] = float(view.frac_pr_m[i] + n * C_M_S * view.period_s[i])
    return out


def integer_agrees(recovered_pr_m: float, full_pr_m: float, period_s: float) -> bool:
    """A recovered pseudorange's integer (paper eq. 11) is the full range's: the two within
    half an ambiguity, c T / 2 (150 km at 1 ms; the range moves by at most ~1 km/s in the
    meantime); False when the full range is not finite."""
    return bool(math.isfinite(full_pr_m)) and abs(full_pr_m - recovered_pr_m) < C_M_S * period_s / 2
