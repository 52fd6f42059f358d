"""How far an epoch's time tag is trusted: the fractional ranges of an epoch whose receiver
time is coarser than a millisecond stay out of the fix.

Used by the stream's pipeline (:mod:`service.engine.pipeline`) and by ``bdsfix solve``
alike; a module of its own so that the batch command does not import the pipeline (the
tracker, the coarse-time solver) to apply it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from service.core.types import MeasurementEpoch

COARSE_TIME_S = 1e-3
"""An epoch whose receiver time is less certain than this [s] (``time_unc_s``, e.g. a
phone's BiasUncertaintyNanos) keeps its fractional ranges out of the fix: the fast fix takes
the time tag as exact (a satellite's transmit time is the tag minus the flight time, its
integer milliseconds resolved at that tag), and a 1 ms error moves a satellite by at most
~4 m along its orbit. Full ranges are unaffected (their transmit time is in the
measurement; a tag error is common to all and goes into the clock). The coarse-time fix
(:mod:`service.engine.coarse`, time as a fifth unknown) uses them: with the tag as its prior
while ``time_unc_s`` is within ``time_prior_s``, else with the time the first decoded SOW
gives, and with neither it waits (declined ``coarse_time``)."""


def without_coarse_fractions(view: MeasurementEpoch) -> tuple[MeasurementEpoch, int]:
    """``view`` without its fractional ranges when its time is coarser than
    :data:`COARSE_TIME_S` (their ``frac_pr_m`` NaN), and how many were set aside."""
    if not view.time_unc_s > COARSE_TIME_S:
        return view, 0
    frac = ~np.isfinite(view.pr_m) & np.isfinite(view.frac_pr_m)
    n = int(frac.sum())
    if not n:
        return view, 0
    return replace(view, frac_pr_m=np.where(frac, np.nan, view.frac_pr_m)), n
