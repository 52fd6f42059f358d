"""Broadcast ephemerides of the recordings, read once per test session."""

from __future__ import annotations

import functools

from drivers.rinex import read_nav
from service.core.types import Ephemeris
from tests.support.paths import DATA

HKSC_2021_NAV = DATA / "hksc-2021" / "hksc1610.nav"


@functools.cache
def hksc_2021_ephemerides() -> tuple[Ephemeris, ...]:
    """Every BeiDou, GPS and Galileo set of the HKSC 2021 nav file (:data:`HKSC_2021_NAV`)."""
    nav = read_nav(HKSC_2021_NAV, "CGE")
    return tuple(e for items in nav.ephemerides.values() for e in items)
