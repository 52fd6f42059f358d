"""The ranges a fast fix recovers from fractional ones, and their integrity check against
the satellite's own full range, written once for the stream's pipeline
(:mod:`service.engine.pipeline`: once the satellite's SOW decodes) and ``bdsfix solve``
(against the file's full range) alike (:class:`RecoveredLedger`); a module of its own so
that the batch command imports the pipeline only for a file that needs the coarse-time
fix."""

from __future__ import annotations

import logging
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field

from service.core.constants import C_M_S
from service.core.counters import Counters
from service.core.timebase import diff_s
from service.core.types import Fix, MeasurementEpoch

log = logging.getLogger(__name__)

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


@dataclass(frozen=True, slots=True)
class IntegrityCheck:
    """A recovered pseudorange checked against the full one after the SOW arrived (in
    ``bdsfix solve``: the file's full range)."""

    prn: str
    gpst_week: int
    gpst_tow_s: float
    recovered_pr_m: float
    full_pr_m: float
    elapsed_s: float
    ok: bool
    clock_change_m: float = 0.0
    """What was taken out of the full range before comparing: what the receiver clock of
    the satellite's system moved from the fix that recovered the range to the fix of the
    check; for a relative integer, the receiver clock then and what the first full range of
    its fix and system was off by (whole periods and the recovering fix's clock)."""


@dataclass(slots=True)
class Recovered:
    """A recovered range waiting for its check (:class:`RecoveredLedger`)."""

    week: int
    tow_s: float
    pr_m: float
    period_s: float
    clock_m: float  # the recovering fix's clock of the satellite's system (NaN: none)
    relative: bool = False  # its integer only relative within its fix's system


@dataclass
class RecoveredLedger:
    """The ranges fast fixes recovered, each kept until its satellite's own full range
    checks it: the one integrity rule of the stream (:mod:`service.engine.pipeline`, the
    full range once the satellite's SOW decodes) and of ``bdsfix solve`` (the file's full
    range).

    The rule: a fast fix recovers a fractional range's integer (paper eq. 11, fraction + N
    c T: :func:`recovered_ranges`; a coarse-time fix's relative integers,
    ``relative_ambiguity``, too: :meth:`keep`). Once the satellite is full (:meth:`due`)
    the recovered range is checked against its full range (:meth:`check`) at the first
    epoch with a fix giving the receiver clock of the satellite's system
    (:func:`system_clock_m`), what that clock moved since the recovering fix taken out
    (:func:`integer_agrees`: a clock step of the receiver would otherwise move every range
    by whole milliseconds); at the recovering fix's own epoch (``bdsfix solve``'s ranges
    made fractional, full in the file) nothing moved: no clock needed, but for a relative
    integer, whose offset holds one. A range recovered more than
    :data:`RECOVERED_MAX_AGE_S` before is dropped and counted ``integrity_unchecked``, and
    so are those pending when the receiver restarts (:meth:`forget`). A relative integer
    is compared with the first of its fix and system to be full: that one's offset from
    its full range (whole periods in doubt, the fix's clock) is every other's too, to
    within half its period (``integrity_relative_anchors`` counts the first ones). Counted
    in ``counters``: ``integrity_checks``, ``integrity_failures`` (each failure logged),
    ``integrity_unchecked`` and ``integrity_relative_anchors``. ``full_from``: where the
    full range came from, for the log."""

    counters: Counters = field(default_factory=Counters)
    full_from: str = "SOW"
    recovered: dict[str, Recovered] = field(default_factory=dict)
    """Recovered ranges whose satellite is not full yet."""
    pending: dict[str, Recovered] = field(default_factory=dict)
    """Those whose satellite is full: to check at the next fix with its system's clock."""
    # relative integers: (week, tow, system) of their fix -> what its first full range was
    # off by (whole periods, the receiver clock), which every other one must share
    _shifts: dict[tuple[int, float, str], float] = field(default_factory=dict)

    def keep(self, view: MeasurementEpoch, whole: MeasurementEpoch, fix: Fix) -> None:
        """The ranges ``fix`` recovered, if it is a fast fix: those of ``view``'s fractional
        rows (:func:`recovered_ranges`), and the relative ones of a coarse-time fix
        (``relative_ambiguity``: each system's common whole period in doubt) of ``whole``,
        the epoch with the fractional ranges it was solved from. A satellite's earlier
        recovered range, not full yet, is replaced."""
        if fix.mode != "fast":
            return
        for prn, pr_m in recovered_ranges(view, fix).items():
            i = view.prn.index(prn)
            clock = system_clock_m(fix, prn)
            self.recovered[prn] = Recovered(
                view.gpst_week,
                view.gpst_tow_s,
                pr_m,
                float(view.period_s[i]),
                math.nan if clock is None else clock,
            )
        for prn, pr_m in integer_ranges(whole, fix.relative_ambiguity).items():
            if not math.isfinite(pr_m):
                continue
            period_s = float(whole.period_s[whole.prn.index(prn)])
            # (its clock: the group's first full range's offset holds it, whatever it is)
            self.recovered[prn] = Recovered(
                whole.gpst_week, whole.gpst_tow_s, pr_m, period_s, 0.0, relative=True
            )

    def due(self, prns: Iterable[str]) -> None:
        """These satellites are full now: their recovered ranges are to be checked."""
        for prn in prns:
            rec = self.recovered.pop(prn, None)
            if rec is not None:
                self.pending[prn] = rec

    def check(self, view: MeasurementEpoch, fixes: Sequence[Fix]) -> list[IntegrityCheck]:
        """The checks :meth:`due` ranges get at ``view`` (its full ranges) with ``fixes``,
        the fixes of that epoch (the first giving the satellite's system's clock serves),
        by the rule of :class:`RecoveredLedger`; those not checked (no clock, no full range
        at this epoch) wait for the next epoch."""
        if not self.pending:
            return []
        checks = []
        for prn in list(self.pending):
            rec = self.pending[prn]
            dt = diff_s(view.gpst_week, view.gpst_tow_s, rec.week, rec.tow_s)
            if dt > RECOVERED_MAX_AGE_S:
                del self.pending[prn]
                self.counters["integrity_unchecked"] += 1
                log.info("integrity: %s recovered %.0f s ago, not checked", prn, dt)
                continue
            full = float(view.pr_m[view.prn.index(prn)]) if prn in view.prn else math.nan
            if dt == 0.0 and not rec.relative:  # its own epoch: the clock has not moved
                clock: float | None = rec.clock_m
            else:
                clocks = (system_clock_m(f, prn) for f in fixes)
                clock = next((c for c in clocks if c is not None), None)
            if clock is None or not math.isfinite(full):
                continue  # (the next epoch's fix, or its range)
            del self.pending[prn]
            change = clock - rec.clock_m if math.isfinite(rec.clock_m) else 0.0
            if rec.relative:  # what the first full one of its fix and system was off by
                key = (rec.week, rec.tow_s, prn[:1])
                shift = self._shifts.get(key)
                if shift is None:
                    self._keep_shift(key, full - change - rec.pr_m, view)
                    self.counters["integrity_relative_anchors"] += 1
                    continue  # (nothing to compare it with yet)
                change += shift
            ok = integer_agrees(rec.pr_m, full, rec.period_s, change)
            checks.append(
                IntegrityCheck(prn, view.gpst_week, view.gpst_tow_s, rec.pr_m, full, dt, ok, change)
            )
            self.counters["integrity_checks"] += 1
            if not ok:
                self.counters["integrity_failures"] += 1
                log.error(
                    "integrity: %s recovered %.1f m, %s gives %.1f m (%+.1f m taken out: the"
                    " receiver clock since, and for a relative integer its reference's offset)",
                    prn,
                    rec.pr_m,
                    self.full_from,
                    full,
                    change,
                )
        return checks

    def forget(self) -> None:
        """Drop every range not checked yet, counted ``integrity_unchecked`` (a receiver
        restart: its clock, and so every recovered range's, starts again)."""
        unchecked = len(self.recovered) + len(self.pending)
        if unchecked:
            self.counters["integrity_unchecked"] += unchecked
        self.recovered.clear()
        self.pending.clear()
        self._shifts.clear()

    def _keep_shift(
        self, key: tuple[int, float, str], shift_m: float, view: MeasurementEpoch
    ) -> None:
        """Keep a relative group's offset; those of fixes beyond the check's age go."""
        old = [
            k
            for k in self._shifts
            if diff_s(view.gpst_week, view.gpst_tow_s, k[0], k[1]) > RECOVERED_MAX_AGE_S
        ]
        for k in old:
            del self._shifts[k]
        self._shifts[key] = shift_m
