"""Satellite position and clock from broadcast Keplerian ephemerides, vectorised over satellites.

Implements BDS-SIS-ICD-B1I-3.0 section 5.2.4.12 (Table 5-11, user algorithm for BDS ephemeris),
which for IGSO/MEO is the algorithm of IS-GPS-200 20.3.3.4.3 (Table 20-IV) and Galileo OS SIS
ICD 5.1.1: the node Omega_k = Omega0 + (Omega_dot - Omega_e) t_k - Omega_e t_oe. Each row
takes GM, Omega_e and F of its satellite's system (:data:`service.core.systems.SYSTEM_CONSTANTS`
by the satellite ID). BeiDou GEOs only (C01-C05 and C59-C63, :func:`service.core.bds.is_geo`)
use Omega_k = Omega0 + Omega_dot t_k - Omega_e t_oe, then the position is rotated by
R_z(Omega_e t_k) R_x(-5 deg). Every set is held on BDT (:class:`service.core.types.Ephemeris`):
t_k and the clock's t - t_oc are differences, the same on any scale, while the term Omega_e t_oe
takes t_oe on the satellite's own scale (GPST for GPS, IS-GPS-200 20.3.3.4.3; GST for
Galileo, OS SIS ICD 5.1.1), that is the BDT t_oe plus
:attr:`service.core.systems.SystemConstants.ahead_of_bdt_s`, within its week. The clock
follows BDS ICD 5.2.4.10 (IS-GPS-200 20.3.3.3.3.1; Galileo OS SIS ICD 5.1.4): polynomial
plus relativistic term F e sqrt(A) sin E_k, less the group delay of the signal in use
(B1I: T_GD1, ICD 5.2.4.11; GPS L1 C/A: T_GD, IS-GPS-200 20.3.3.3.3.2; Galileo E1 with the
I/NAV clock: BGD(E1,E5b), OS SIS ICD 5.1.5).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, fields

import numpy as np

from service.core.bds import GEO_TILT_RAD, is_geo
from service.core.constants import WEEK_S
from service.core.systems import GnssSystem, constants_of, system_of
from service.core.types import Ephemeris

_HALF_WEEK_S = WEEK_S / 2

_ARRAY_FIELDS = (
    "week",
    "toe_sow_s",
    "toc_sow_s",
    "af0_s",
    "af1_s_s",
    "af2_s_s2",
    "sqrt_a_sqrt_m",
    "e",
    "i0_rad",
    "omega0_rad",
    "omega_rad",
    "m0_rad",
    "delta_n_rad_s",
    "omega_dot_rad_s",
    "idot_rad_s",
    "cuc_rad",
    "cus_rad",
    "crc_m",
    "crs_m",
    "cic_rad",
    "cis_rad",
    "tgd1_s",
)


@dataclass(frozen=True, slots=True, eq=False)
class EphemerisArrays:
    """Ephemerides of n satellites as numpy columns (one row per satellite, same order), with
    the constants of each satellite's system (``gm_m3_s2`` ... ``carrier_hz``, from
    :func:`service.core.systems.constants_of`), whether it is a BeiDou satellite (``bds``)
    and a BeiDou GEO (``geo``)."""

    prn: tuple[str, ...]
    geo: np.ndarray
    bds: np.ndarray
    gm_m3_s2: np.ndarray
    omega_e_rad_s: np.ndarray
    f_rel_s_per_sqrt_m: np.ndarray
    carrier_hz: np.ndarray
    ahead_of_bdt_s: np.ndarray
    week: np.ndarray
    toe_sow_s: np.ndarray
    toc_sow_s: np.ndarray
    af0_s: np.ndarray
    af1_s_s: np.ndarray
    af2_s_s2: np.ndarray
    sqrt_a_sqrt_m: np.ndarray
    e: np.ndarray
    i0_rad: np.ndarray
    omega0_rad: np.ndarray
    omega_rad: np.ndarray
    m0_rad: np.ndarray
    delta_n_rad_s: np.ndarray
    omega_dot_rad_s: np.ndarray
    idot_rad_s: np.ndarray
    cuc_rad: np.ndarray
    cus_rad: np.ndarray
    crc_m: np.ndarray
    crs_m: np.ndarray
    cic_rad: np.ndarray
    cis_rad: np.ndarray
    tgd1_s: np.ndarray

    @classmethod
    def from_ephemerides(cls, ephs: Sequence[Ephemeris]) -> EphemerisArrays:
        cols = {
            name: np.array([getattr(e, name) for e in ephs], dtype=float) for name in _ARRAY_FIELDS
        }
        systems = [constants_of(e.prn) for e in ephs]
        return cls(
            prn=tuple(e.prn for e in ephs),
            geo=np.array([is_geo(e.prn) for e in ephs], dtype=bool),
            bds=np.array([system_of(e.prn) is GnssSystem.BDS for e in ephs], dtype=bool),
            gm_m3_s2=np.array([k.gm_m3_s2 for k in systems], dtype=float),
            omega_e_rad_s=np.array([k.omega_e_rad_s for k in systems], dtype=float),
            f_rel_s_per_sqrt_m=np.array([k.f_rel_s_per_sqrt_m for k in systems], dtype=float),
            carrier_hz=np.array([k.carrier_hz for k in systems], dtype=float),
            ahead_of_bdt_s=np.array([k.ahead_of_bdt_s for k in systems], dtype=float),
            **cols,
        )

    @classmethod
    def concatenate(cls, sets: Sequence[EphemerisArrays]) -> EphemerisArrays:
        """The rows of ``sets``, one after the other."""
        kw = {
            f.name: np.concatenate([getattr(s, f.name) for s in sets])
            for f in fields(cls)
            if f.name != "prn"
        }
        return cls(prn=tuple(p for s in sets for p in s.prn), **kw)

    def take(self, index: np.ndarray | Sequence[int]) -> EphemerisArrays:
        """Rows ``index`` as a new set."""
        idx = np.asarray(index, dtype=int)
        kw = {f.name: getattr(self, f.name)[idx] for f in fields(self) if f.name != "prn"}
        return EphemerisArrays(prn=tuple(self.prn[i] for i in idx), **kw)

    def __len__(self) -> int:
        return len(self.prn)


def _wrap_half_week(dt_s: np.ndarray) -> np.ndarray:
    """Account for week crossover (ICD 5.2.4.12 note on t_k)."""
    if np.abs(dt_s).max(initial=0.0) <= _HALF_WEEK_S:  # none to wrap: dt - 0, the same bits
        return dt_s + 0.0
    return dt_s - WEEK_S * np.round(dt_s / WEEK_S) * (np.abs(dt_s) > _HALF_WEEK_S)


_COS_TILT, _SIN_TILT = np.cos(GEO_TILT_RAD), np.sin(GEO_TILT_RAD)


@dataclass(frozen=True, slots=True, eq=False)
class _OrbitConstants:
    """The terms of :func:`sat_pos_clock` that depend on the ephemerides alone (the same
    expressions, evaluated once per set instead of once per call)."""

    a_m: np.ndarray  # sqrt(A)^2
    n_rad_s: np.ndarray  # sqrt(GM / A^3) + delta_n
    sqrt_1_e2: np.ndarray  # sqrt(1 - e^2)
    omega_dot_rel_rad_s: np.ndarray  # Omega_dot - Omega_e (IGSO/MEO node rate)
    omega_e_toe_rad: np.ndarray  # Omega_e t_oe, t_oe on the satellite's own time scale
    f_e_sqrt_a: np.ndarray  # F e sqrt(A), the relativistic clock term over sin E
    any_geo: bool


def _own_toe_s(eph: EphemerisArrays) -> np.ndarray:
    """t_oe on each satellite's own time scale [s of its week]: BDT t_oe as it is for
    BeiDou, plus ``ahead_of_bdt_s`` within the week for the others (a GPS t_oe of 0 is held
    as BDT week - 1, 604786 s)."""
    own = np.mod(eph.toe_sow_s + eph.ahead_of_bdt_s, WEEK_S)
    return np.where(eph.ahead_of_bdt_s != 0.0, own, eph.toe_sow_s)


_CONSTANTS: dict[int, tuple[EphemerisArrays, _OrbitConstants]] = {}
_CONSTANTS_MAX = 64


def _constants(eph: EphemerisArrays) -> _OrbitConstants:
    """:class:`_OrbitConstants` of ``eph``, memoised by identity for the sets in use (the
    ephemeris store hands out the same arrays for the same sets)."""
    hit = _CONSTANTS.get(id(eph))
    if hit is not None and hit[0] is eph:
        return hit[1]
    a = eph.sqrt_a_sqrt_m**2
    k = _OrbitConstants(
        a_m=a,
        n_rad_s=np.sqrt(eph.gm_m3_s2 / a**3) + eph.delta_n_rad_s,
        sqrt_1_e2=np.sqrt(1.0 - eph.e**2),
        omega_dot_rel_rad_s=eph.omega_dot_rad_s - eph.omega_e_rad_s,
        omega_e_toe_rad=eph.omega_e_rad_s * _own_toe_s(eph),
        f_e_sqrt_a=eph.f_rel_s_per_sqrt_m * eph.e * eph.sqrt_a_sqrt_m,
        any_geo=bool(eph.geo.any()),
    )
    if len(_CONSTANTS) >= _CONSTANTS_MAX:
        _CONSTANTS.clear()
    _CONSTANTS[id(eph)] = (eph, k)
    return k


def sat_pos_clock(
    eph: EphemerisArrays, bdt_week: int | np.ndarray, bdt_sow_s: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray]:
    """ECEF position [m] (n, 3) and clock offset [s] (n,) of the signal in use at transmit
    times given in the ephemerides' week and time of week (BDT for BDS sets).

    The clock offset includes the relativistic term and subtracts the group delay ``tgd1_s``
    (B1I: T_GD1), so that the predicted pseudorange is rho - c * clock_s (ICD 5.2.4.10,
    5.2.4.11).
    """
    t_sow = np.asarray(bdt_sow_s, dtype=float)
    dweek = (np.asarray(bdt_week, dtype=float) - eph.week) * WEEK_S
    tk = _wrap_half_week(dweek + (t_sow - eph.toe_sow_s))

    k = _constants(eph)
    a = k.a_m
    mk = eph.m0_rad + k.n_rad_s * tk
    ek = mk.copy()
    for _ in range(5):  # Kepler's equation by Newton (quadratic); e < 0.1 (ephemeris.py)
        ek = ek - (ek - eph.e * np.sin(ek) - mk) / (1.0 - eph.e * np.cos(ek))
    sin_e, cos_e = np.sin(ek), np.cos(ek)
    nu = np.arctan2(k.sqrt_1_e2 * sin_e, cos_e - eph.e)
    phi = nu + eph.omega_rad
    two_phi = 2 * phi
    s2, c2 = np.sin(two_phi), np.cos(two_phi)
    u = phi + eph.cus_rad * s2 + eph.cuc_rad * c2
    r = a * (1.0 - eph.e * cos_e) + eph.crs_m * s2 + eph.crc_m * c2
    inc = eph.i0_rad + eph.idot_rad_s * tk + eph.cis_rad * s2 + eph.cic_rad * c2
    xp, yp = r * np.cos(u), r * np.sin(u)

    node = (
        eph.omega0_rad
        + np.where(eph.geo, eph.omega_dot_rad_s * tk, k.omega_dot_rel_rad_s * tk)
        - k.omega_e_toe_rad
    )
    cn, sn, ci, si = np.cos(node), np.sin(node), np.cos(inc), np.sin(inc)
    y_ci = yp * ci
    x = xp * cn - y_ci * sn
    y = xp * sn + y_ci * cn
    z = yp * si

    if k.any_geo:
        # GEO: R_z(Omega_e t_k) R_x(-5 deg) applied to the inertial-like frame position
        ct, st = _COS_TILT, _SIN_TILT
        yg = ct * y + st * z
        zg = -st * y + ct * z
        ang = eph.omega_e_rad_s * tk
        ca, sa = np.cos(ang), np.sin(ang)
        xr = ca * x + sa * yg
        yr = -sa * x + ca * yg
        x = np.where(eph.geo, xr, x)
        y = np.where(eph.geo, yr, y)
        z = np.where(eph.geo, zg, z)

    dtc = _wrap_half_week(dweek + (t_sow - eph.toc_sow_s))
    clock_s = (
        eph.af0_s + eph.af1_s_s * dtc + eph.af2_s_s2 * dtc**2 + k.f_e_sqrt_a * sin_e - eph.tgd1_s
    )
    pos = np.empty((*x.shape, 3))  # (np.stack's per-call cost is several times this)
    pos[..., 0], pos[..., 1], pos[..., 2] = x, y, z
    return pos, clock_s


VELOCITY_STEP_S = 0.01
"""Half-width [s] of the central difference in :func:`sat_pos_vel_clock`: the truncation
error (h^2/6 times the orbit's third derivative, ~1e-5 m/s^3) is far below 1e-6 m/s, the
rounding error (1e-8 m over 2 h) a few 1e-7 m/s."""


_STEPS_S = np.array([[-VELOCITY_STEP_S], [VELOCITY_STEP_S]])
_STEPS_S.flags.writeable = False  # shared by every call


def sat_pos_vel_clock(
    eph: EphemerisArrays, bdt_week: int | np.ndarray, bdt_sow_s: np.ndarray | float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """ECEF position [m] (n, 3), velocity [m/s] (n, 3), B1I clock offset [s] (n,) and clock
    drift [s/s] (n,) at BDT transmit times.

    The velocity and drift are the time derivatives of the user algorithm of
    BDS-SIS-ICD-B1I-3.0 5.2.4.12 (orbit, including the GEO rotation R_z(Omega_e t_k)) and
    5.2.4.10 (clock polynomial a1 + 2 a2 dt plus the derivative of the relativistic term),
    taken by a central difference of :func:`sat_pos_clock` over +-:data:`VELOCITY_STEP_S`,
    as RTKLIB's ``ephpos`` takes them by a forward one; the velocity is in the rotating
    Earth frame (ECEF). The position and clock are the means of the two evaluations (within
    1e-4 m and 1e-15 s of those at the time itself).
    """
    t = np.asarray(bdt_sow_s, dtype=float)
    if t.shape != (len(eph),):
        t = np.broadcast_to(t, (len(eph),))
    h = VELOCITY_STEP_S
    # both evaluations in one call: times (2, n) broadcast against the (n,) ephemerides,
    # t + (-h) and t + h (t - h is t + (-h), the same bits)
    pos, clk = sat_pos_clock(eph, bdt_week, t + _STEPS_S)
    vel = (pos[1] - pos[0]) / (2 * h)
    drift = (clk[1] - clk[0]) / (2 * h)
    return (pos[0] + pos[1]) / 2, vel, (clk[0] + clk[1]) / 2, drift
