"""The RINEX nav files a command is given, checked before any epoch is solved.

One rule for ``solve``, ``replay`` and ``run``: a nav file set without a single BDS
ephemeris, or whose BDS ephemerides are all more than a day from the observations' first
epoch (a nav file of another day), is refused with one line naming what is wrong (both
dates for the second) and exit 3; otherwise every epoch would be declined ``no_ephemeris``
and the command would still look successful.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from service.core.errors import InputError
from service.core.systems import DEFAULT_SYSTEMS
from service.core.timebase import bdt_to_gpst, datetime_from_gpst, diff_s
from service.core.types import UNKNOWN_WEEK, MeasurementEpoch

if TYPE_CHECKING:
    from drivers.rinex import NavData

NAV_DAY_S = 86_400.0
"""The largest gap [s] between the observations' first epoch and the nearest BDS ephemeris
(its t_oe) for a nav file to count as the observations' day."""
FIRST_EPOCH_EVENTS = 100_000
"""How many events of a non-RINEX capture are read to find its first dated epoch."""
NAV_HINT = (
    "give a RINEX 3 nav file with BDS ('C') records of the observations' day "
    "(e.g. a daily mixed '_MN' or BDS '_CN' file)"
)


def nav_hint(anchor: set[str]) -> str:
    """What to give when the nav files lack the sets of ``anchor``: :data:`NAV_HINT` for
    BeiDou, else the same for the systems asked for."""
    if anchor == {"C"}:
        return NAV_HINT
    letters = "/".join(f"'{s}'" for s in sorted(anchor))
    return (
        f"give a RINEX 3 nav file with {letters} records of the observations' day "
        "(e.g. a daily mixed '_MN' file)"
    )


def check_navigation(
    paths: Sequence[str | Path],
    navs: Sequence[NavData],
    first: tuple[int, float] | None,
    systems: Iterable[str] = DEFAULT_SYSTEMS,
) -> None:
    """Refuse (:class:`InputError`, exit 3) nav files with no BDS ephemeris, or whose BDS
    ephemerides are all more than :data:`NAV_DAY_S` from ``first`` (GPST week, tow of the
    observations' first dated epoch; None: unknown, not checked). Only the BDS sets count
    (the ones the message names): a mixed file's GPS and Galileo sets, read when those
    systems are selected, include sets of odd weeks from satellites marked unhealthy. With
    BeiDou not among ``systems`` (RINEX letters, e.g. ``--systems G,E``) the sets of the
    selected systems count instead (:func:`anchor_systems`)."""
    names = ", ".join(str(p) for p in paths)
    anchor = anchor_systems(systems)
    toes = [
        bdt_to_gpst(e.week, e.toe_sow_s)
        for nav in navs
        for prn, ephs in nav.ephemerides.items()
        if prn[:1] in anchor
        for e in ephs
    ]
    if not toes:
        what = "BDS" if anchor == {"C"} else "/".join(sorted(anchor))
        raise InputError(f"no usable {what} ephemeris in {names}: {nav_hint(anchor)}")
    if first is None or first[0] == UNKNOWN_WEEK:
        return
    if min(abs(diff_s(*first, *toe)) for toe in toes) <= NAV_DAY_S:
        return
    days = sorted({datetime_from_gpst(*toe).date() for toe in toes})
    span = str(days[0]) if len(days) == 1 else f"{days[0]} to {days[-1]}"
    start = datetime_from_gpst(*first).replace(microsecond=0)
    what = "BDS" if anchor == {"C"} else "/".join(sorted(anchor))
    raise InputError(
        f"{names}: {what} ephemerides of {span} (GPST), but the observations start "
        f"{start:%Y-%m-%d %H:%M:%S} GPST: {nav_hint(anchor)}"
    )


def anchor_systems(systems: Iterable[str]) -> set[str]:
    """The systems whose sets a nav file must hold to be used: BeiDou where it is selected
    (bdsfix is BeiDou-first; the fast fix needs its GEOs), else every selected system."""
    selected = set(systems)
    return {"C"} if "C" in selected else selected


def read_navigation(
    paths: Sequence[str | Path], systems: Iterable[str] = DEFAULT_SYSTEMS
) -> list[NavData]:
    """The nav files read, with the ephemerides of ``systems`` (RINEX letters)
    (:func:`drivers.rinex.read_nav`; a malformed one raises)."""
    from drivers.rinex import read_nav

    return [read_nav(p, systems) for p in paths]


def first_epoch_time(path: str | Path, gps_week: int | None = None) -> tuple[int, float] | None:
    """GPST (week, tow) of the first measurement epoch with a known week in a capture file
    (RINEX obs, UBX, RTCM, ...), or None if none comes within the first
    :data:`FIRST_EPOCH_EVENTS` events (an RTCM file without ephemerides, for instance)."""
    from drivers.source import open_source

    with open_source(str(path), gps_week=gps_week) as src:
        for ev in itertools.islice(src, FIRST_EPOCH_EVENTS):
            if isinstance(ev, MeasurementEpoch) and ev.gpst_week != UNKNOWN_WEEK:
                return ev.gpst_week, ev.gpst_tow_s
    return None
