"""Satellite IDs name their system; each supported system has its ICD's constants."""

import pytest

from service.core.errors import BdsfixError
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem, constants_of, system_of


@pytest.mark.parametrize(
    ("sat", "system"),
    [
        ("C06", GnssSystem.BDS),
        ("C 6", GnssSystem.BDS),
        ("G12", GnssSystem.GPS),
        ("E11", GnssSystem.GAL),
    ],
)
def test_system_of_reads_the_rinex_letter(sat, system):
    assert system_of(sat) == system


def test_unknown_letter_and_unsupported_system_are_clear_errors():
    with pytest.raises(BdsfixError, match="names no satellite system"):
        system_of("X01")
    with pytest.raises(BdsfixError, match="GLO satellites are not supported"):
        constants_of("R01")


def test_constants_differ_where_the_icds_differ():
    bds, gps, gal = (SYSTEM_CONSTANTS[s] for s in (GnssSystem.BDS, GnssSystem.GPS, GnssSystem.GAL))
    assert bds.omega_e_rad_s == 7.2921150e-5 and gps.omega_e_rad_s == 7.2921151467e-5
    assert gps.gm_m3_s2 == 3.986005e14 and bds.gm_m3_s2 == gal.gm_m3_s2 == 3.986004418e14
    assert (bds.code_period_s, gps.code_period_s, gal.code_period_s) == (1e-3, 1e-3, 4e-3)
    assert bds.carrier_hz == 1561.098e6 and gps.carrier_hz == gal.carrier_hz == 1575.42e6
