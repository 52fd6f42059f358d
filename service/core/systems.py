"""Satellite systems: which system a satellite ID names, and each system's constants.

A satellite ID is the RINEX 3 form (RINEX 3.04 section 3.5): one system letter and the PRN,
``"C06"`` (BeiDou), ``"G12"`` (GPS), ``"E11"`` (Galileo). Everything system-specific that the
engine needs (the gravitational constant and Earth rotation rate of the system's ICD, the
code period that makes a range fractional, the carrier that scales Doppler and the
ionosphere) is looked up here by :func:`system_of`, never written as a literal.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from functools import lru_cache

from service.core.constants import C_M_S
from service.core.errors import BdsfixError, ConfigError
from service.core.settings import setting


class GnssSystem(StrEnum):
    """A satellite system, by its RINEX 3 letter."""

    BDS = "C"
    GPS = "G"
    GAL = "E"
    GLO = "R"
    QZS = "J"
    SBAS = "S"
    IRN = "I"


@dataclass(frozen=True, slots=True)
class SystemConstants:
    """The constants a system's ICD fixes for its broadcast orbits and its open signal."""

    gm_m3_s2: float
    """Geocentric gravitational constant of the system's reference frame [m^3/s^2]."""
    omega_e_rad_s: float
    """Earth rotation rate of the system's ICD [rad/s]."""
    code_period_s: float
    """Primary code period of the open signal bdsfix uses: a range known only from the
    code phase is known modulo c times this [s]."""
    carrier_hz: float
    """Carrier frequency of that signal [Hz]."""
    signal: str
    """RINEX 3 name of that signal's band and code (without the leading observable type)."""
    f_rel_s_per_sqrt_m: float
    """Relativistic clock correction constant F = -2 sqrt(GM) / c^2 as the ICD prints it
    [s/sqrt(m)] (the printed value, not one recomputed from GM)."""
    prn_max: int
    """Highest PRN number of the system's RINEX 3 satellite IDs (``C63``, ``G32``)."""
    ahead_of_bdt_s: float
    """How far the system's time scale is ahead of BDT [s]: 14 s for GPST (BDS-SIS-ICD-B1I-3.0
    4.2) and for GST, which Galileo steers to GPST within tens of ns (OS SIS ICD 5.1.8: the
    GGTO, left to each system's receiver clock); 0 for BDT. Ephemerides are held on BDT
    (:class:`service.core.types.Ephemeris`); the orbit's Omega_e t_oe term takes t_oe back
    on the system's own scale with it."""


SYSTEM_CONSTANTS: dict[GnssSystem, SystemConstants] = {
    # BDS-SIS-ICD-B1I-3.0 3.2 (CGCS2000), 4.2 (B1I 1561.098 MHz), 4.3 (1 ms ranging code),
    # 5.2.4.10 (F); PRNs 1-63 (C01-C63)
    GnssSystem.BDS: SystemConstants(
        gm_m3_s2=3.986004418e14,
        omega_e_rad_s=7.2921150e-5,
        code_period_s=1e-3,
        carrier_hz=1_561.098e6,
        signal="2I",
        f_rel_s_per_sqrt_m=-4.442807309e-10,
        prn_max=63,
        ahead_of_bdt_s=0.0,
    ),
    # IS-GPS-200N 20.3.3.4.3 (WGS-84 values), 3.3.2 (C/A 1 ms), L1 1575.42 MHz,
    # 20.3.3.3.3.1 (F); PRNs 1-32
    GnssSystem.GPS: SystemConstants(
        gm_m3_s2=3.986005e14,
        omega_e_rad_s=7.2921151467e-5,
        code_period_s=1e-3,
        carrier_hz=1_575.42e6,
        signal="1C",
        f_rel_s_per_sqrt_m=-4.442807633e-10,
        prn_max=32,
        ahead_of_bdt_s=14.0,
    ),
    # Galileo OS SIS ICD 2.1, 5.1.1 (GM, Earth rate), 3.4 (E1-B/C primary code 4 ms),
    # 5.1.4 (F); PRNs 1-36
    GnssSystem.GAL: SystemConstants(
        gm_m3_s2=3.986004418e14,
        omega_e_rad_s=7.2921151467e-5,
        code_period_s=4e-3,
        carrier_hz=1_575.42e6,
        signal="1C",
        f_rel_s_per_sqrt_m=-4.442807309e-10,
        prn_max=36,
        ahead_of_bdt_s=14.0,
    ),
    # IS-QZSS-PNT 4.1.2 (GPS values), L1 C/A; RINEX 3 J01-J10 (PRN 193-202)
    GnssSystem.QZS: SystemConstants(
        gm_m3_s2=3.986005e14,
        omega_e_rad_s=7.2921151467e-5,
        code_period_s=1e-3,
        carrier_hz=1_575.42e6,
        signal="1C",
        f_rel_s_per_sqrt_m=-4.442807633e-10,
        prn_max=10,
        ahead_of_bdt_s=14.0,
    ),
}
"""Constants per system that bdsfix can position with (GLONASS, SBAS and NavIC: none yet)."""


def system_of(sat: str) -> GnssSystem:
    """The system of a satellite ID such as ``"C06"``, ``"C 6"`` or ``"G12"``.

    Raises :class:`BdsfixError` for an ID whose first letter names no system."""
    system = _BY_LETTER.get(sat[:1])
    if system is None:
        raise BdsfixError(f"satellite ID {sat!r} names no satellite system")
    return system


_BY_LETTER: dict[str, GnssSystem] = {s.value: s for s in GnssSystem}
"""GnssSystem by letter: the lookup GnssSystem(letter) makes, without the enum call's cost
(asked for every satellite of every epoch)."""


def prn_number(sat: str) -> int:
    """PRN number of a satellite ID like ``"C06"``, ``"C 6"`` or ``"G6"`` (any system);
    each ID's worked out once (:data:`_PRN_NUMBERS`: the NMEA of an epoch asks for each
    satellite's several times)."""
    n = _PRN_NUMBERS.get(sat)
    if n is None:
        n = int(sat[1:].strip())
        if len(_PRN_NUMBERS) >= _PRN_NUMBERS_MAX:
            _PRN_NUMBERS.clear()
        _PRN_NUMBERS[sat] = n
    return n


_PRN_NUMBERS: dict[str, int] = {}
""":func:`prn_number` of the satellite IDs seen (at most :data:`_PRN_NUMBERS_MAX`)."""
_PRN_NUMBERS_MAX = 1024


def sat_id(system: GnssSystem, number: int) -> str:
    """Canonical RINEX 3 satellite ID of a system's PRN number: ``sat_id(GnssSystem.BDS, 6)``
    is ``"C06"``."""
    return f"{system.value}{number:02d}"


def constants_of(sat: str) -> SystemConstants:
    """The constants of the system a satellite ID names (:data:`SYSTEM_CONSTANTS`)."""
    system = system_of(sat)
    try:
        return SYSTEM_CONSTANTS[system]
    except KeyError:
        raise BdsfixError(f"{system.name} satellites are not supported ({sat!r})") from None


@lru_cache(maxsize=256)
def wavelength_m(sat: str) -> float:
    """Carrier wavelength [m] of the signal bdsfix uses from ``sat``'s system: what turns a
    Doppler [Hz] into a range rate (-lambda D)."""
    return C_M_S / constants_of(sat).carrier_hz


POSITIONING_SYSTEMS = (GnssSystem.BDS, GnssSystem.GPS, GnssSystem.GAL)
"""The systems whose measurements and ephemerides the readers give (RINEX 3 so far)."""
DEFAULT_SYSTEMS = "C"
"""The systems of a library call that names none (readers, nav loading): BeiDou alone."""
EVERY_SYSTEM = ",".join(s.value for s in POSITIONING_SYSTEMS)
"""The default of the ``systems`` setting (flag ``--systems``, TOML key ``systems``): every
system the input carries among :data:`POSITIONING_SYSTEMS` (issue 19, "Selection"); a
system the input lacks simply gives no rows, and ``--systems C`` is BeiDou alone."""


@dataclass(frozen=True, slots=True)
class SystemsConfig:
    """The one user setting of the systems positioned with (flag ``--systems``, TOML key
    ``systems``)."""

    systems: str = setting(
        EVERY_SYSTEM,
        "satellite systems to position with, RINEX letters separated by commas: C (BeiDou "
        "B1I), G (GPS L1 C/A), E (Galileo E1); each gets its own receiver clock",
        kind="str",
    )


def parse_systems(text: str) -> frozenset[str]:
    """The RINEX letters of a ``systems`` setting (``"C,G,E"``, ``"CGE"``, ``"c, g"``);
    ConfigError names what is not one of :data:`POSITIONING_SYSTEMS`."""
    letters = [x for x in text.upper().replace(",", " ").split() for x in x]
    known = {s.value for s in POSITIONING_SYSTEMS}
    bad = sorted(set(letters) - known)
    if bad or not letters:
        raise ConfigError(
            f"systems {text!r}: expected letters among {', '.join(sorted(known))} "
            "(C BeiDou, G GPS, E Galileo)"
        )
    return frozenset(letters)
