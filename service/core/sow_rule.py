"""When a receiver learns a satellite's time after a (re)start: the SOW-decode rule.

A B1I subframe is 300 bits in ten 30-bit words (BDS-SIS-ICD-B1I-3.0 5.1.3). D1 (IGSO/MEO) is
sent at 50 bps: a subframe lasts 6 s (5.2.2, D1 frame structure); D2 (GEO) at 500 bps: a
subframe lasts 0.6 s (5.3.1, D2 frame structure). Every subframe opens with the preamble,
FraID and SOW: the preamble and FraID in word 1, the SOW's 8 MSBs at bits 19-26 (word 1) and
its 12 LSBs at bits 31-42 (word 2) (5.2.3 for D1, 5.3.2 for D2). A receiver therefore knows
the satellite's transmit time, and with it the full pseudorange, as soon as words 1-2 (60
bits) of a subframe whose preamble it saw after bit sync have decoded:

- D2: 60 bits / 500 bps = 0.12 s into the subframe;
- D1: 60 bits / 50 bps = 1.2 s into the subframe.

Bit sync: a receiver that reaches bit sync in the middle of a subframe has not seen that
subframe's preamble and cannot frame it; it waits for the next preamble (the next subframe
boundary of BDT transmit time, a multiple of 0.6 s or 6 s) and knows the time 0.12 s or 1.2 s
after it, plus the signal's flight time.

GPS L1 C/A LNAV (IS-GPS-200 20.3.2, 20.3.3.2) has the same timing as D1: 300-bit subframes at
50 bps, the time of week in the HOW (word 2), so 1.2 s into a subframe (``time_known_after_s``
of ``"LNAV"``); its subframe boundaries are on GPST (service.engine.tracker).

Galileo I/NAV (OS SIS ICD 4.3.2.2, 4.3.5) gives the time of week in whole 2 s pages of word
types 0, 5 and 6, whose TOW field ends in the odd part and is checked by the page's CRC at its
end: ``time_known_after_s("INAV")`` is the page, 2 s, under both rules (which pages carry it:
:data:`service.core.gal_nav.E1B_TOW_PAGE_STARTS_S`).

``sow`` is this rule, the default everywhere a time to first fix is made or measured (the
virtual receiver's RAWX prMes validity, emulated restarts of ``replay --restart-at`` and
``ttff``, the built-in scenario). ``subframe``, the rule used before, waits for the end of that
whole subframe (0.6 s / 6 s after its preamble), as a receiver that reads a subframe
completely before trusting its SOW would; it is kept for comparison.
"""

from __future__ import annotations

from dataclasses import dataclass

from service.core.settings import setting

WORD_BITS = 30
"""Bits per navigation-message word (ICD 5.1.3)."""
SOW_WORDS = 2
"""Words to read before the SOW is known: word 1 (preamble, FraID, SOW MSBs), word 2 (SOW LSBs)."""
SUBFRAME_WORDS = 10
D1_BIT_RATE_BPS = 50.0
D2_BIT_RATE_BPS = 500.0
D1_SOW_DECODED_S = SOW_WORDS * WORD_BITS / D1_BIT_RATE_BPS
"""1.2 s: the SOW of a D1 subframe is known this long after its preamble's first bit."""
D2_SOW_DECODED_S = SOW_WORDS * WORD_BITS / D2_BIT_RATE_BPS
"""0.12 s: the SOW of a D2 subframe is known this long after its preamble's first bit."""

INAV_PAGE_S = 2.0
"""A Galileo I/NAV page, even and odd part (OS SIS ICD 4.3.2.2)."""

FULL_RULES = ("sow", "subframe")
DEFAULT_FULL_RULE = "sow"


def time_known_after_s(nav_type: str, rule: str = DEFAULT_FULL_RULE) -> float:
    """Seconds after the first bit of a subframe (whose preamble the receiver saw after bit
    sync) at which the receiver knows the satellite's time: the SOW decoded (``sow``: D2
    0.12 s, D1 and GPS LNAV 1.2 s) or the whole subframe read (``subframe``: D2 0.6 s, D1
    and LNAV 6 s)."""
    if rule not in FULL_RULES:
        raise ValueError(f"unknown full rule {rule!r}: one of {', '.join(FULL_RULES)}")
    if nav_type == "INAV":
        return INAV_PAGE_S
    rate = D2_BIT_RATE_BPS if nav_type == "D2" else D1_BIT_RATE_BPS
    words = SOW_WORDS if rule == "sow" else SUBFRAME_WORDS
    return words * WORD_BITS / rate


@dataclass(frozen=True, slots=True)
class FullRuleConfig:
    """The one user setting of the rule (flag ``--full-rule``)."""

    full_rule: str = setting(
        DEFAULT_FULL_RULE,
        "when a restarted receiver knows a satellite's time (its pseudorange becomes full): "
        "sow = once the SOW (words 1-2) of a subframe whose preamble came after bit sync has "
        "decoded (GEO/D2 0.12 s, IGSO/MEO/D1 1.2 s into it); subframe = at the end of that "
        "subframe (0.6 s, 6 s)",
        kind="str",
        choices=FULL_RULES,
    )
