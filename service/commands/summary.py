"""What a run tells its user at the end, in words: fixes by solver, the top decline
reasons with a hint of the fix, what input was skipped (replay, run and solve share it)."""

from __future__ import annotations

from collections.abc import Mapping

from service.core.declines import hint, label, no_epochs

TOP_REASONS = 3


def decline_lines(
    counters: Mapping[str, int | float], indent: str = "  ", command: str = "replay"
) -> list[str]:
    """The top decline reasons (``declined_<code>`` counters) in words with counts, and a
    hint for the commonest when it has one (in ``command``'s words)."""
    declined = {k[9:]: int(v) for k, v in counters.items() if k.startswith("declined_") and v}
    if not declined:
        return []
    ranked = sorted(declined.items(), key=lambda i: (-i[1], i[0]))
    parts = ", ".join(f"{label(code)} {n}" for code, n in ranked[:TOP_REASONS])
    more = len(ranked) - TOP_REASONS
    if more > 0:
        parts += f", and {more} other reason{'s' if more > 1 else ''}"
    lines = [f"{indent}declined: {parts}"]
    top = hint(ranked[0][0], command)
    if top is not None:
        lines.append(f"{indent}hint: {top}")
    return lines


def excluded_lines(counters: Mapping[str, int | float], indent: str = "  ") -> list[str]:
    """The satellites fault exclusion removed (``excluded_<PRN>``), commonest first."""
    excluded = {k[9:]: int(v) for k, v in counters.items() if k.startswith("excluded_") and v}
    if not excluded:
        return []
    parts = ", ".join(f"{p} {n}" for p, n in sorted(excluded.items(), key=lambda i: -i[1]))
    n_fixes = int(counters.get("fixes_with_exclusions", 0))
    return [f"{indent}excluded by fault detection: {parts} (in {n_fixes} published fixes)"]


def skipped_line(skipped: Mapping[str, int], indent: str = "  ") -> list[str]:
    """One line naming the skipped input counters, or none."""
    if not skipped:
        return []
    return [f"{indent}skipped input: " + ", ".join(f"{k} {v}" for k, v in skipped.items())]


def stream_lines(
    command: str, n_epochs: int, counters: Mapping[str, int | float], skipped: Mapping[str, int]
) -> list[str]:
    """The end-of-stream summary of ``replay`` and ``run``: epochs and fixes by mode, the
    integrity checks, excluded satellites, the top decline reasons with a hint, the skipped
    input, and what to do when there was no epoch at all."""
    c = counters
    lines = [
        f"bdsfix {command}: {n_epochs} epochs; fixes fast {int(c.get('fix_fast', 0))}, "
        f"spp {int(c.get('fix_spp', 0))}, none {int(c.get('fix_none', 0))}; integrity checks "
        f"{int(c.get('integrity_checks', 0))}, failures {int(c.get('integrity_failures', 0))}"
        + unchecked_text(c)
    ]
    lines += [*excluded_lines(c), *decline_lines(c, command=command), *skipped_line(skipped)]
    if n_epochs == 0:
        lines.append(f"  {no_epochs_hint(command, c)}")
    return lines


def unchecked_text(counters: Mapping[str, int | float]) -> str:
    """``", unchecked N"`` when recovered ranges went unchecked (their satellite full too
    late, or a receiver restart: ``integrity_unchecked``), else nothing."""
    n = int(counters.get("integrity_unchecked", 0))
    return f", unchecked {n}" if n else ""


def no_epochs_hint(command: str, counters: Mapping[str, int | float] | None = None) -> str:
    """What to do when ``command`` saw no measurement epoch, in that command's own flags
    (:data:`service.core.declines.NO_EPOCHS`); ``run`` says when its source never opened
    (open failures and no source event in ``counters``)."""
    c = counters or {}
    failures = int(c.get("source_open_failures", 0))
    return no_epochs(command, 0 if c.get("source_events") else failures)
