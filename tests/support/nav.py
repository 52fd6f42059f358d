"""Broadcast ephemerides of the recordings, read once per test session."""

from __future__ import annotations

import functools

from drivers.rinex import read_nav
from service.core.ephemeris import EphemerisStore
from service.core.types import Ephemeris
from service.engine.pipeline import Pipeline
from tests.support.paths import DATA

HKSC_2021_NAV = DATA / "hksc-2021" / "hksc1610.nav"


@functools.cache
def hksc_2021_ephemerides() -> tuple[Ephemeris, ...]:
    """Every BeiDou, GPS and Galileo set of the HKSC 2021 nav file (:data:`HKSC_2021_NAV`)."""
    nav = read_nav(HKSC_2021_NAV, "CGE")
    return tuple(e for items in nav.ephemerides.values() for e in items)


def pipeline_with_nav(nav, systems: tuple[str, ...] = ("C",)) -> Pipeline:
    """A pipeline (the stream's) holding the nav file's ephemerides of ``systems`` and its
    ionosphere, as replay's stream head gives them."""
    pipe = Pipeline(EphemerisStore())
    data = read_nav(nav, systems)
    for ephs in data.ephemerides.values():
        for eph in ephs:
            pipe.add_ephemeris(eph)
    for params in (data.iono_gps, data.iono_bds):  # BDS last: preferred when both
        if params is not None:
            pipe.set_iono(params)
    return pipe
