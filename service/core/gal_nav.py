"""Galileo navigation data: SISA, GST-GPS time offset (GGTO).

SISA (OS SIS ICD 5.1.12, Table 76) is the accuracy class of a Galileo set, held as
:attr:`~service.core.types.Ephemeris.ura_m` as URA is for BeiDou and GPS.

GGTO (OS SIS ICD 5.1.8, I/NAV word type 10, F/NAV page type 4; RINEX 3 ``TIME SYSTEM CORR``
``GAGP``; Septentrio SBF GALGstGps): GST - GPST = A0G + A1G (t - t0G + 604800 (WN - WN0G)),
with the week WN0G broadcast modulo 64. bdsfix solves one receiver clock per system
(:mod:`service.engine.layout`), so the offset between GST and GPST goes into Galileo's clock
and needs no correction; it is recorded (STATUS ``ggto_ns``) for the user to see.
"""

from __future__ import annotations

import math


def galileo_sisa_m(index: int) -> float:
    """SISA [m] of its index (Galileo OS SIS ICD 5.1.12, Table 76): 0-49 by 1 cm, 50-74 from
    0.5 m by 2 cm, 75-99 from 1 m by 4 cm, 100-125 from 2 m by 16 cm; 126-254 spare and 255
    NAPA (no accuracy prediction available): NaN, which the store refuses."""
    if 0 <= index < 50:
        return index * 0.01
    if index < 75:
        return 0.5 + (index - 50) * 0.02
    if index < 100:
        return 1.0 + (index - 75) * 0.04
    if index < 126:
        return 2.0 + (index - 100) * 0.16
    return math.nan


WN0G_MODULUS = 64
"""WN0G is broadcast in 6 bits (OS SIS ICD Table 71)."""


def week_near(broadcast: int, modulus: int, ref_week: int) -> int:
    """The full week of one broadcast modulo ``modulus`` nearest ``ref_week``."""
    return ref_week + ((broadcast - ref_week + modulus // 2) % modulus - modulus // 2)
