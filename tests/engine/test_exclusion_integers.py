"""Fault exclusion of a fast fix never publishes when its passing candidates disagree on an
integer (service.engine.judge.exclude, integer_clash): each candidate resolves the integers
again (paper eq. 11), and two that pass with different integers for one satellite mean that
one of them passed with a wrong integer, which nothing tells apart.

The rule's two branches are driven with stated candidates (the judgement of what the kernel
gives, not the kernel itself); the TST drive shows what it costs on real data: the fast fix
with the drive's BeiDou and GPS non-GEO ranges made fractional (as ``bdsfix solve
--fractional non-geo --systems C,G``) publishes 76 fixes of the paper's method after
excluding satellites (in 27 of those stages more than one candidate passed, with integers
to compare), and on this drive every stage's passing candidates agree, so no fix is lost
to the rule. (Its coarse-time fixes exclude in an all-full solve: no integers there.)
"""

from __future__ import annotations

from drivers.rinex import RinexObsReader
from service.commands.solve import BatchOptions, load_navigation, solve_epochs
from service.core.declines import Decline
from service.core.systems import parse_systems
from service.core.types import Fix
from service.engine.judge import Failed, exclude, integer_clash
from tests.support.paths import DATA

TST = DATA / "hk-tst-urban-2019"
OBS = TST / "COM3_190428_124409.obs"
NAVS = (TST / "hksc1180.19b", TST / "hksc1180.19n")


def _fix(ambiguity: dict[str, int], chi2: float, *, ok: bool = True) -> Fix:
    return Fix(
        solver="fast",
        mode="fast" if ok else "none",
        gpst_week=2051,
        gpst_tow_s=46800.0,
        x_ecef_m=(-2419240.0, 5385470.0, 2405336.0) if ok else None,
        used=tuple(sorted(ambiguity)),
        ambiguity=dict(ambiguity),
        redundancy=2,
        chi2=chi2,
        chi2_max=10.0,
    )


def _excluded_with(candidates: dict[str, Fix]) -> tuple[dict[str, Fix], set[str]]:
    """One failed fast solution over C01-C03 (full) and C06, C09, C11 (fractional),
    redundancy 2; excluding a satellite gives ``candidates[prn]`` (a failing solution where
    none is stated)."""
    kept = ("C01", "C02", "C03", "C06", "C09", "C11")
    declined = _fix({}, 40.0, ok=False)
    failed = Failed(40.0, 10.0, 2, kept, (1.0,) * len(kept), declined)

    def without(state: tuple[str, ...], prn: str) -> tuple[str, ...]:
        return tuple(p for p in state if p != prn)

    def solve(states: list[tuple[str, ...]]) -> list[tuple[object, tuple[str, ...]]]:
        out: list[tuple[object, tuple[str, ...]]] = []
        for state in states:
            gone = next(p for p in kept if p not in state)
            got = candidates.get(gone)
            if got is None:  # still failing, with no redundancy left for a second stage
                got = Failed(30.0, 10.0, 1, state, (1.0,) * len(state), declined)
            out.append((got, state))
        return out

    return exclude({"e": (failed, kept)}, without, solve, 2)  # type: ignore[arg-type]


def test_passing_candidates_with_one_integer_each_publish_the_best_fitting():
    agree = {"C06": 71, "C09": 80}
    fixes, hopeless = _excluded_with(
        {"C11": _fix(agree, 2.0), "C02": _fix(agree | {"C11": 75}, 3.0)}
    )
    assert not hopeless
    fix = fixes["e"]
    assert fix.ok and fix.chi2 == 2.0 and list(fix.excluded) == ["C11"]


def test_passing_candidates_with_different_integers_decline():
    fixes, hopeless = _excluded_with(
        {
            "C11": _fix({"C06": 71, "C09": 80}, 2.0),  # the best fit
            "C03": _fix({"C06": 71, "C09": 81, "C11": 75}, 3.0),  # C09 one period apart
        }
    )
    assert not hopeless
    fix = fixes["e"]
    assert not fix.ok
    assert fix.reason_code == Decline.AMBIGUOUS
    assert fix.reason == (
        "fault exclusion: 2 candidates pass, not all with the best fit's integers "
        "(C09: 80 or 81 periods)"
    )
    assert integer_clash({"C06": 71}, [{"C09": 80}]) is None  # nothing shared: no clash


def test_on_the_urban_drive_no_fast_fix_is_lost_to_the_rule():
    systems = parse_systems("C,G")
    store, iono = load_navigation([str(p) for p in NAVS], systems=systems)
    opts = BatchOptions(mode="fast", fractional="non-geo", with_sky=False)
    epochs = iter(RinexObsReader(OBS, systems=systems))
    fixes = [fixes[0] for _, fixes in solve_epochs(epochs, store, iono, opts)]
    with_exclusions = [
        f
        for f in fixes
        if f.ok
        and f.method is None  # the paper's method: its candidates resolve integers
        and f.fractional
        and any("chi-square" in w for w in f.excluded.values())
    ]
    ambiguous = [f for f in fixes if f.decline is not None and f.decline.variant == "exclusion"]
    assert len(with_exclusions) >= 70, len(with_exclusions)
    assert ambiguous == []
