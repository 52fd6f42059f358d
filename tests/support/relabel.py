"""HKSC's BeiDou rows and broadcast orbits relabelled as another system's ("G<n>"), with a
known inter-system bias on their ranges: physically real rows that need a receiver clock of
their own (tests of the layout and of the solver kernel)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from service.core.bds import is_geo
from service.core.constants import C_M_S
from service.core.ephemeris import EphemerisStore
from service.core.orbit import EphemerisArrays
from service.core.types import Ephemeris, MeasurementEpoch

ISB_M = 123.456
"""The inter-system bias put on the relabelled rows [m]."""


GPS_OMEGA_E_RAD_S = 7.2921151467e-5  # IS-GPS-200N 20.3.3.4.3
GPST_AHEAD_OF_BDT_S = 14.0  # BDS-SIS-ICD-B1I-3.0 4.2


class Relabelled:
    """An ephemeris store that answers "G<n>" with BeiDou satellite "C<n>"'s broadcast set
    under the other name (the solver asks ``select`` and ``arrays`` only). A GPS set is
    held on BDT and its Omega_e t_oe term takes t_oe on GPST, 14 s later: Omega_0 gets
    Omega_e 14 s back, so that the node is the BeiDou set's."""

    def __init__(self, store: EphemerisStore) -> None:
        self.store = store

    def select(self, prn: str, bdt_week: int, bdt_sow_s: float) -> Ephemeris | None:
        e = self.store.select("C" + prn[1:], bdt_week, bdt_sow_s)
        if e is None or prn[0] == "C":
            return e
        omega0 = e.omega0_rad + GPS_OMEGA_E_RAD_S * GPST_AHEAD_OF_BDT_S
        return replace(e, prn=prn, omega0_rad=omega0)

    def arrays(self, ephs: list[Ephemeris]) -> EphemerisArrays:
        return EphemerisArrays.from_ephemerides(ephs)


def relabel(ep: MeasurementEpoch, take: int) -> MeasurementEpoch:
    """``ep`` with its first ``take`` non-GEO satellites named "G<n>" and ``ISB_M`` added
    to their pseudoranges."""
    others = [i for i, p in enumerate(ep.prn) if not is_geo(p)][:take]
    prn = tuple("G" + p[1:] if i in others else p for i, p in enumerate(ep.prn))
    pr = ep.pr_m.copy()
    pr[others] += ISB_M
    return replace(ep, prn=prn, pr_m=pr, frac_pr_m=np.mod(pr, C_M_S * 1e-3))
