"""A decline is a value: its code, and the one table of the words users see for it.

Every epoch the engine does not fix comes back as a :class:`service.core.types.Fix` with
``mode="none"`` and a :class:`Declined`: its code (a :class:`Decline`), the variant of the
code's reason template and the figures that fill it; the fix's ``reason_code`` and
``reason`` (what the records carry) are made from it and the template here, when asked.
The summaries of ``replay``, ``run`` and ``solve`` name each code by its label and give its
hint, from the same table; so do the reasons fault exclusion gives for a satellite it
removed (:data:`EXCLUSIONS`), and what a command says when it saw no epoch at all
(:data:`NO_EPOCHS`). No other module writes these words
(tests/engine/test_declines.py reads the tables, checks the summaries use them and scans
every string literal in service/ for their sentences).

The table lives in core, beside :class:`service.core.types.Fix`, which holds the value and
makes its words from it: the words are shared vocabulary (engine, output, commands).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum


class Decline(StrEnum):
    """Why an epoch has no fix (``Fix.reason_code``, the ``declined_<code>`` counters)."""

    NO_MEASUREMENTS = "no_measurements"
    NO_EPHEMERIS = "no_ephemeris"
    TOO_FEW_FULL = "too_few_full"
    SINGULAR = "singular"
    NO_CONVERGENCE = "no_convergence"
    GDOP_GATE = "gdop_gate"
    DIVERGED = "diverged"
    CHI2 = "chi2"
    IMPLAUSIBLE = "implausible"
    PDOP_GATE = "pdop_gate"
    NUMERICAL = "numerical"
    NO_TIME = "no_time"
    OUT_OF_ORDER = "out_of_order"
    COARSE_TIME = "coarse_time"
    TOO_FEW_ROWS = "too_few_rows"
    NO_DOPPLER = "no_doppler"
    AMBIGUOUS = "ambiguous"


@dataclass(frozen=True, slots=True)
class DeclineText:
    """The words of one decline code: ``label`` names it in the summaries, ``templates``
    make the record's ``reason`` (``str.format`` fields; ``""`` is the usual one, other keys
    name a variant), ``hint`` tells the user what to do about it (None: nothing to say),
    ``command_hints`` the hint where a command's own flags differ from replay's (``run`` has
    no ``--gps-week``; ``solve`` takes its nav file as an argument)."""

    label: str
    templates: dict[str, str] = field(default_factory=dict)
    hint: str | None = None
    command_hints: dict[str, str] = field(default_factory=dict)


_GIVE_EPHEMERIDES = "give the satellites' ephemerides: "
_WEEK_UNKNOWN = "the GPS week is not known yet: "

DECLINES: dict[Decline, DeclineText] = {
    Decline.NO_MEASUREMENTS: DeclineText(
        "no measurements",
        {"": "no measurements"},
        "the input has no BDS B1I pseudoranges",
    ),
    Decline.NO_EPHEMERIS: DeclineText(
        "no usable ephemeris",
        {"": "no usable ephemeris for {prns}"},
        _GIVE_EPHEMERIDES + "a RINEX 3 nav file of the same day (replay/run --nav NAV, solve's "
        "NAV argument), or a capture that carries them (UBX RXM-SFRBX, RTCM 1042)",
        {
            "solve": _GIVE_EPHEMERIDES + "a RINEX 3 nav file of the same day as the obs file "
            "(the NAV argument)",
        },
    ),
    Decline.TOO_FEW_FULL: DeclineText(
        "too few full measurements",
        {
            "": "too few full measurements: {n_full} full, {n_frac} fractional "
            "(need at least {need} full)",
            "mask": "too few full measurements above the {mask_deg:g} deg mask: {n_full}",
        },
        "fewer full pseudoranges than unknowns (the position and one clock per satellite "
        "system: 4 with BeiDou alone): the fast fix needs that many GEOs in view, SPP waits "
        "for each satellite's SOW",
    ),
    Decline.SINGULAR: DeclineText(
        "singular geometry", {"": "singular geometry in the fast-fix iteration"}
    ),
    Decline.NO_CONVERGENCE: DeclineText(
        "no convergence", {"": "no convergence after {iterations} iterations"}
    ),
    Decline.GDOP_GATE: DeclineText(
        "GEO-GDOP gate",
        {
            "": "GDOP gate failed: GDOP_full {gdop:.1f} >= beta {beta:.0f}",
            "unsettled": "GDOP gate failed: GDOP_full {gdop:.1f} >= beta {beta:.0f} "
            "(no convergence after {iterations} iterations)",
        },
        "GEO geometry too poor for the integer search (the paper's GDOP gate)",
    ),
    Decline.DIVERGED: DeclineText("solution diverged", {"": "solution diverged"}),
    Decline.CHI2: DeclineText(
        "chi-square test failed, no exclusion passes",
        {
            "": "chi-square test failed: {chi2:.1f} > {chi2_max:.1f} (redundancy "
            "{redundancy}; largest w-test {prn} {w:.1f})",
            "no_exclusion": "{reason}; no exclusion of up to {max_exclusions} satellites passes",
            "coarse": "coarse-time fix: none of {candidates} integer candidates passes the "
            "chi-square test",
        },
        "inconsistent pseudoranges that fault exclusion could not resolve",
    ),
    Decline.IMPLAUSIBLE: DeclineText(
        "implausible solution",
        {
            "": "implausible solution: altitude {alt_m:.4g} m (allowed {alt_min_m:g} to "
            "{alt_max_m:g}), receiver clock {clock_s:.4g} s (allowed +-{clock_max_s:g})"
        },
    ),
    Decline.PDOP_GATE: DeclineText(
        "PDOP gate",
        {"": "PDOP gate failed: PDOP {pdop:.1f} > {pdop_max:g}"},
        "poor geometry (PDOP above --pdop-max)",
    ),
    Decline.NUMERICAL: DeclineText(
        "numerical failure", {"": "numerical failure in the solver: {error}: {message}"}
    ),
    Decline.NO_TIME: DeclineText(
        "time unknown (no GPS week yet)",
        {"": "GPS week not known yet: the source gave only the time of week"},
        _WEEK_UNKNOWN + "give --gps-week N (RTCM without ephemerides)",
        {
            # run has no --gps-week: a live stream takes the week from the system clock
            "run": _WEEK_UNKNOWN
            + "a live stream takes it from the system clock until the receiver's time tag or "
            "ephemerides give it; a capture file has no clock: 'bdsfix replay FILE --gps-week N'",
            "solve": "the obs file's epochs carry no GPS time: check its header and epoch lines",
        },
    ),
    Decline.OUT_OF_ORDER: DeclineText(
        "epoch not after the previous one",
        {"": "epoch {what} the previous one (GPST {week} {tow_s:.3f})"},
    ),
    Decline.COARSE_TIME: DeclineText(
        "receiver time too coarse for fractional ranges",
        {
            "": "receiver time known to +-{time_unc_s:.3g} s only: {n_frac} fractional "
            "ranges set aside (a coarse-time fix is needed), {n_full} full (need at least "
            "{need})"
        },
        "the receiver does not know its time well enough (e.g. a phone before its first "
        "fix: BiasUncertaintyNanos) for the fast fix to use ranges known modulo a period; "
        "they wait until it is known within the coarse-time fix's time prior (time_prior_s) or "
        "for 4 full ranges",
    ),
    Decline.TOO_FEW_ROWS: DeclineText(
        "too few rows for the coarse-time fix",
        {"": "coarse-time fix: {rows} usable rows, need {need} (5 unknowns, redundancy 2)"},
        "fewer than 4 full GEO ranges and too few satellites for the coarse-time fix: "
        "wait for more satellites or their SOW",
    ),
    Decline.NO_DOPPLER: DeclineText(
        "no Doppler for the coarse-time fix",
        {"": "coarse-time fix: {rows} Doppler rows, no Doppler position"},
        "the coarse-time fix needs Doppler (RAWX doMes, RINEX D, MSM range rate)",
    ),
    Decline.AMBIGUOUS: DeclineText(
        "ambiguous integers",
        {
            "": "coarse-time fix: {passing} integer candidates pass, {rivals} rivals within "
            "the uniqueness margin",
            "exclusion": "fault exclusion: {passing} candidates pass, not all with the best "
            "fit's integers ({prn}: {n_taken} or {n_other} periods)",
        },
        "more than one integer set fits: the fix declines rather than guess",
    ),
}
"""The one table of decline words: label, reason templates and hint per code."""


@dataclass(frozen=True, slots=True)
class Declined:
    """A decline as a value: its ``code``, the ``variant`` of the code's reason template and
    the figures that fill it (``fields``, name-value pairs). Nothing is written out until a
    record or a summary asks: :attr:`reason` formats the template of :data:`DECLINES`, so a
    decline carries no words of its own (``Fix.decline``)."""

    code: Decline
    variant: str = ""
    fields: tuple[tuple[str, object], ...] = ()

    @classmethod
    def of(cls, code: Decline, variant: str = "", **fields: object) -> Declined:
        """The decline ``code`` with reason template ``variant`` and its figures ``fields``."""
        return cls(code, variant, tuple(fields.items()))

    @property
    def reason(self) -> str:
        """The record's ``reason``: the code's template (``variant``) filled with ``fields``."""
        return DECLINES[self.code].templates[self.variant].format(**dict(self.fields))

    def figure(self, name: str) -> object:
        """The figure ``name`` of this decline (KeyError: it has none)."""
        return dict(self.fields)[name]


def reason(code: Decline, variant: str = "", **fields: object) -> str:
    """The record's ``reason`` for ``code``: its template (``variant``) filled with
    ``fields``."""
    return Declined.of(code, variant, **fields).reason


def label(code: str) -> str:
    """The summaries' name of a decline code (the code itself when it is not one)."""
    try:
        return DECLINES[Decline(code)].label
    except ValueError:
        return code


def hint(code: str, command: str = "replay") -> str | None:
    """What the user of ``command`` can do about a decline code, naming only that command's
    own flags (None: no hint)."""
    try:
        text = DECLINES[Decline(code)]
    except ValueError:
        return None
    return text.command_hints.get(command, text.hint)


EXCLUSIONS: dict[str, str] = {
    "gross": "pseudorange {dev_km:.4g} km from the epoch's median: impossible",
    "chi2": "chi-square test failed ({chi2:.1f} > {chi2_max:.1f}), w-test {w:.1f}",
    "coarse": "coarse-time fix: no integer candidate passes with it, one passes without",
    "predicted": "{res_m:.1f} m longer than predicted from the last fix and its velocity "
    "(> {limit_m:.0f} m): a reflected signal",
}
"""Why fault exclusion removed a satellite (``Fix.excluded``): an impossible range, the coarse-time
fix's exclusion (service.engine.coarse), the
failed test and the satellite's w-test, or the prediction screen (service.engine.aiding)."""


NO_REASON = "declined without a reason"
"""A record's ``reason`` for a declined fix that carries no :class:`Declined` (no engine
builder makes one; the records still never leave a declined fix without words)."""


def excluded_why(kind: str, **fields: object) -> str:
    """The reason a satellite was excluded (:data:`EXCLUSIONS`)."""
    return EXCLUSIONS[kind].format(**fields)


NO_EPOCHS: dict[str, str] = {
    "replay": "no measurement epoch in the input: it needs BDS raw measurements (UBX "
    "RXM-RAWX/MEASX, RTCM3 MSM 1124-1127, SBF MeasEpoch, a RINEX 3 obs file with C2I/C1I, or "
    "GnssLogger Raw rows); for RTCM without ephemerides give --gps-week",
    # run has no --gps-week (the system clock gives a live stream its week)
    "run": "no measurement epoch from the source: it needs BDS raw measurements (UBX "
    "RXM-RAWX/MEASX or RTCM3 MSM 1124-1127); 'bdsfix configure' sets a u-blox receiver up",
    "run_never_opened": "the source never opened ({failures} attempts, see the WARNING "
    "lines): is the receiver plugged in, or the server listening?",
    # an epoch record without a BDS pseudorange is still an epoch (solve declines it): none
    # at all means the file has no epoch after its header
    "solve": "no measurement epoch in the file: a RINEX 3 obs file needs epoch records "
    "after its header, a GnssLogger log Raw rows",
}
"""What a command says when it saw no measurement epoch at all (no decline then: no epoch
was solved), in that command's own flags; ``run_never_opened``: ``run``'s source never
opened (``{failures}``: its attempts)."""


def no_epochs(command: str, open_failures: int = 0) -> str:
    """The :data:`NO_EPOCHS` hint of ``command`` (``replay`` for a command without its own);
    ``open_failures``: how often ``run`` failed to open a source that never opened."""
    if command == "run" and open_failures:
        return NO_EPOCHS["run_never_opened"].format(failures=open_failures)
    return NO_EPOCHS.get(command, NO_EPOCHS["replay"])
