"""A decline is a value: one table (service.core.declines.DECLINES) holds the words of
every decline code, and the records, the summaries and the hints take them from it.

Read from the table: every reason in the golden records matches its code's template, every
decline line of the golden summaries names codes by their label, the summary of any code
gives its label and hint, the no-epoch lines are the table's, and no clause of the tables is
written in any string literal of another module of service/.
"""

from __future__ import annotations

import ast
import json
import re
import string
from pathlib import Path

import pytest

from service.commands.summary import decline_lines, no_epochs_hint
from service.core.declines import DECLINES, NO_EPOCHS, Decline, Declined, hint, label, reason
from service.core.types import Fix

ROOT = Path(__file__).resolve().parents[2]
GOLDEN = ROOT / "tests" / "golden"


def _pattern(template: str) -> re.Pattern[str]:
    """A regular expression matching what ``template`` formats to (any field values)."""
    out = []
    for text, name, _spec, _conv in string.Formatter().parse(template):
        out.append(re.escape(text))
        if name is not None:
            out.append(".+?")
    return re.compile("".join(out))


def test_every_code_has_a_label_and_a_reason():
    assert set(DECLINES) == set(Decline)
    for code, text in DECLINES.items():
        assert text.label and "" in text.templates, code
        assert label(code.value) == text.label
        assert hint(code.value) == text.hint
    assert label("not_a_code") == "not_a_code" and hint("not_a_code") is None


def test_reasons_are_formatted_from_the_table():
    assert reason(Decline.NO_EPHEMERIS, prns="C01, C02") == "no usable ephemeris for C01, C02"
    assert (
        reason(Decline.TOO_FEW_FULL, n_full=3, n_frac=7, need=4)
        == "too few full measurements: 3 full, 7 fractional (need at least 4 full)"
    )
    assert (
        reason(Decline.PDOP_GATE, pdop=12.345, pdop_max=10.0) == "PDOP gate failed: PDOP 12.3 > 10"
    )


def test_a_declined_fix_holds_a_value_and_makes_its_words_from_the_table():
    """A declined fix stores no words: its ``reason`` and ``reason_code`` are made from its
    :class:`Declined` (code, variant, figures) and the table, and a published fix has none."""
    why = Declined.of(Decline.GDOP_GATE, "unsettled", gdop=1234.56, beta=3000.0, iterations=12)
    fix = Fix(solver="fast", mode="none", gpst_week=2161, gpst_tow_s=1.0, decline=why)
    assert fix.reason_code == "gdop_gate" and fix.decline.figure("iterations") == 12
    # the template written out by hand from the paper's gate, not by the code under test
    assert (
        fix.reason
        == "GDOP gate failed: GDOP_full 1234.6 >= beta 3000 (no convergence after 12 iterations)"
    )
    assert (
        "reason" not in Fix.__dataclass_fields__ and "reason_code" not in Fix.__dataclass_fields__
    )
    published = Fix(solver="fast", mode="spp", gpst_week=2161, gpst_tow_s=1.0)
    assert published.decline is None and published.reason is None and published.reason_code is None
    # the same decline is the same value: one figure different is another decline
    assert why == Declined.of(
        Decline.GDOP_GATE, "unsettled", gdop=1234.56, beta=3000.0, iterations=12
    )
    assert why != Declined.of(
        Decline.GDOP_GATE, "unsettled", gdop=1234.56, beta=3000.0, iterations=13
    )


def test_golden_records_carry_the_table_words():
    seen: set[str] = set()
    n = 0
    for path in sorted(GOLDEN.glob("*.jsonl")):
        for line in path.read_text().splitlines():
            rec = json.loads(line)
            if rec.get("class") != "FIX" or rec.get("mode") != "none":
                continue
            code = Decline(rec["reason_code"])
            pats = [_pattern(t) for t in DECLINES[code].templates.values()]
            assert any(p.fullmatch(rec["reason"]) for p in pats), (path.name, rec["reason"])
            seen.add(code)
            n += 1
    assert n > 100 and {Decline.NO_TIME, Decline.NO_EPHEMERIS} <= seen


def test_golden_summaries_name_declines_by_their_label():
    labels = sorted((t.label for t in DECLINES.values()), key=len, reverse=True)
    one = "(?:" + "|".join(re.escape(x) for x in labels) + r") \d+"
    declined = re.compile(rf"{one}(?:, {one})*(?:, and \d+ other reasons?)?")
    hints = {t.hint for t in DECLINES.values() if t.hint}
    hints |= {h for t in DECLINES.values() for h in t.command_hints.values()}
    n_lines = n_hints = 0
    for path in sorted(GOLDEN.glob("*.summary")):
        for line in path.read_text().splitlines():
            if "declined: " in line:
                assert declined.fullmatch(line.split("declined: ", 1)[1]), (path.name, line)
                n_lines += 1
            if re.match(r"\s+(?:\w+ solver )?hint: ", line):
                assert line.split("hint: ", 1)[1] in hints, (path.name, line)
                n_hints += 1
    assert n_lines >= 5 and n_hints >= 5


@pytest.mark.parametrize("code", list(Decline))
def test_summary_of_each_code_uses_its_label_and_hint(code):
    lines = decline_lines({f"declined_{code.value}": 7})
    assert lines[0] == f"  declined: {DECLINES[code].label} 7"
    if DECLINES[code].hint is None:
        assert len(lines) == 1
    else:
        assert lines[1] == f"  hint: {DECLINES[code].hint}"


_CLAUSE = re.compile(r"[:;,.?!]\s|\{[^}]*\}|[()]")
"""Where a user-facing text splits into clauses: punctuation and format fields."""


def _literals(path: Path) -> list[str]:
    """The string constants of a module that a user can see: every one but the docstrings
    (of the module, classes, functions and attributes), with implicitly concatenated pieces
    joined as the parser joins them, and the fixed parts of f-strings."""
    tree = ast.parse(path.read_text())
    docs = {
        id(n.value)
        for n in ast.walk(tree)
        if isinstance(n, ast.Expr) and isinstance(n.value, ast.Constant)
    }
    return [
        n.value
        for n in ast.walk(tree)
        if isinstance(n, ast.Constant) and isinstance(n.value, str) and id(n) not in docs
    ]


def test_no_decline_words_are_written_twice_in_service():
    """Every clause of 20 characters or more in the tables' strings (labels, reason templates,
    hints, exclusion reasons, no-epoch hints) appears in no string literal of any other module
    of service/: each reason and hint is written once, in the table."""
    table = ROOT / "service" / "core" / "declines.py"
    clauses = {
        c.strip() for s in _literals(table) for c in _CLAUSE.split(s) if len(c.strip()) >= 20
    }
    assert len(clauses) > 40  # the tables' words, not an empty scan
    for text in [t.hint for t in DECLINES.values() if t.hint] + list(NO_EPOCHS.values()):
        assert any(c in text for c in clauses), text
    others = {p: _literals(p) for p in (ROOT / "service").rglob("*.py") if p != table}
    assert sum(map(len, others.values())) > 1000
    for clause in sorted(clauses):
        where = [
            p.relative_to(ROOT) for p, lits in others.items() if any(clause in s for s in lits)
        ]
        assert not where, (clause, where)


def test_the_no_epoch_lines_of_the_summaries_come_from_the_table():
    n = 0
    for path in sorted(GOLDEN.glob("*.summary")):
        for line in path.read_text().splitlines():
            if "no measurement epoch" in line:
                assert line.strip() in NO_EPOCHS.values(), (path.name, line)
                n += 1
    assert n >= 2
    assert no_epochs_hint("replay") == NO_EPOCHS["replay"]
    assert no_epochs_hint("solve") == NO_EPOCHS["solve"]
    assert no_epochs_hint("run") == NO_EPOCHS["run"]
    never = no_epochs_hint("run", {"source_open_failures": 3})
    assert _pattern(NO_EPOCHS["run_never_opened"]).fullmatch(never) and "(3 attempts" in never
    # a source that opened once and then failed to reopen did open
    assert (
        no_epochs_hint("run", {"source_open_failures": 3, "source_events": 1}) == NO_EPOCHS["run"]
    )


def test_exclusion_ranks_a_tested_candidate_before_an_untested_one():
    """Fault exclusion's ranking (judge._better): equal within TIE_RTOL is no better, a
    smaller chi2 / threshold is, and any tested candidate beats one without a test (its
    ratio inf: inf - TIE_RTOL x inf is NaN, which had let nothing win)."""
    import math

    from service.engine.judge import TIE_RTOL, _better, fit_ratio

    assert _better(0.5, 0.9) and not _better(0.9, 0.5)
    assert not _better(0.7 * (1 - TIE_RTOL / 10), 0.7)
    assert fit_ratio(None, 3.0) == math.inf
    assert _better(1.0, math.inf) and _better(50.0, fit_ratio(2.0, 0.0))
    assert not _better(math.inf, math.inf)
