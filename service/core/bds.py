"""What is BeiDou's alone, named and kept in one place.

Everything else in :mod:`service.core` is keyed by the satellite ID's system
(:mod:`service.core.systems`); what only BeiDou has lives here, so that adding a system is
driver, orbit and configuration work that never touches it:

- the GEO satellites, C01-C05 (BDS-2) and C59-C63 (BDS-3) (BDS-SIS-ICD-B1I-3.0 3.1);
- their broadcast orbit algorithm (ICD 5.2.4.12, Table 5-11): the node without the Earth's
  rotation over t_k, then R_z(Omega_e t_k) R_x(-5 deg) (:data:`GEO_TILT_RAD`, applied in
  :func:`service.core.orbit.sat_pos_clock` to the rows whose satellite :func:`is_geo`);
- the navigation message types: D2 (500 bps, 0.6 s subframes) from the GEOs, D1 (50 bps,
  6 s subframes) from the IGSOs and MEOs (ICD 5.2, 5.3; :func:`nav_type`);
- BDT, GPST - 14 s with the week 1356 behind (ICD 4.2; the conversions are in
  :mod:`service.core.timebase`).
"""

from __future__ import annotations

import math
from typing import Literal

from service.core.bds_nav import D1_SUBFRAME_S, D2_SUBFRAME_S
from service.core.systems import GnssSystem, prn_number

GEO_TILT_RAD = math.radians(-5.0)
"""GEO orbit frame rotation about X before the Earth-rotation step (ICD 5.2.4.12, Table 5-11)."""

GEO_PRNS = frozenset([1, 2, 3, 4, 5, 59, 60, 61, 62, 63])
"""BDS PRN numbers of the GEO satellites, which broadcast D2 (BDS-2 C01-C05, BDS-3 C59-C63)."""


def is_geo(sat: str) -> bool:
    """True for the BeiDou GEO satellites C01-C05 and C59-C63 only; False for any other
    satellite ID, whatever its system (``is_geo("G01")`` is False). Sources that carry bare
    BeiDou numbers (u-blox svId, RTCM DF488) build the ID first:
    ``is_geo(sat_id(GnssSystem.BDS, n))``."""
    return sat[:1] == GnssSystem.BDS.value and prn_number(sat) in GEO_PRNS


IGSO_PRNS = frozenset([6, 7, 8, 9, 10, 13, 16, 31, 38, 39, 40, 56])
"""BDS PRN numbers of the inclined geosynchronous satellites (BDS-2 C06-C10, C13, C16; BDS-3
C38-C40; the BDS-3 test satellites C31 and C56), as the constellation status of the China
Satellite Navigation Office lists them; the other non-GEO PRNs are MEOs. The orbits broadcast
in a 2024 nav file of the whole constellation agree (tests/core/test_systems.py)."""


def orbit_class(sat: str) -> Literal["GEO", "IGSO", "MEO", ""]:
    """The orbit of a BeiDou satellite (``GEO``, ``IGSO`` or ``MEO``, by :data:`GEO_PRNS`
    and :data:`IGSO_PRNS`); ``""`` for a satellite of another system."""
    if sat[:1] != GnssSystem.BDS.value:
        return ""
    if prn_number(sat) in GEO_PRNS:
        return "GEO"
    return "IGSO" if prn_number(sat) in IGSO_PRNS else "MEO"


def nav_type(sat: str) -> Literal["D1", "D2"]:
    """The navigation message a BeiDou satellite broadcasts on B1I: D2 from the GEOs, D1
    from the IGSOs and MEOs (ICD 5.2, 5.3)."""
    return "D2" if is_geo(sat) else "D1"


def subframe_period_s(sat: str) -> float:
    """Subframe period of the navigation message a BeiDou satellite broadcasts [s]: 0.6 s
    (D2) from the GEOs, 6 s (D1) from the others (ICD 5.2.2, 5.3.2)."""
    return D2_SUBFRAME_S if is_geo(sat) else D1_SUBFRAME_S
