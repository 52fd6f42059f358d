"""A first fix without four full GEO ranges: Doppler prior, coarse time, validated integers.

The paper's fast fix (:mod:`service.engine.solver`) needs four full GEO ranges to fix the
position and clock before any integer millisecond is known (Zhao, Cui, Lu, eqs. 1-16). This
module does without them, after coarse-time navigation (van Diggelen, *A-GPS*, ch. 4: a
prior within half an ambiguity, c T / 2 = 150 km, and a fifth unknown for the time):

1. **Doppler position** (:func:`doppler_position`). The pseudorange rate of satellite i is
   rdot_i = e_i . (V_i - v) + d - c dts_i/dt (Kaplan & Hegarty 9.3, as
   :mod:`service.engine.velocity`); the unknowns are the position x, the clock drift d and
   the receiver velocity v, solved by Gauss-Newton from the Earth's centre with
   d(e_i . (V_i - v))/dx = -((V_i - v) - (e_i . (V_i - v)) e_i) / rho_i, a height
   pseudo-observation (h = 0 +- ``height_sigma_m``) and a velocity prior
   (``speed_sigma_m_s`` horizontal, ``vertical_speed_sigma_m_s`` vertical): first at rest
   (v = 0), then with v, backtracking a step that raises the cost. An unmodelled velocity
   biases the position by about |v| / 2e-4 s^-1 (50 km at 10 m/s); modelling it makes the
   covariance say so, and the prior is still not good enough to round integers once.
2. **Candidate integer sets** (:func:`solve_coarse`). A hexagonal grid of prior hypotheses on
   the ellipsoid, spacing ``grid_step_m``, over the ellipse of ``search_sigmas`` sigmas of
   the Doppler position's horizontal covariance, never beyond ``search_radius_m``
   (:func:`hypotheses`); at each point the nearest-satellite rule predicts every range and rounds
   N_j = round((rho_j + b_s - z_j) / (c T_j)), each in units of its own period T_j (1 ms
   B1I and GPS C/A, 4 ms Galileo E1, or a phone's longer one), b_s the clock of the row's
   system s taken from its full rows, or (none) from its nearest satellite. A system with
   no full row has a null space: its clock absorbs a shift of all its ranges by its
   longest period L (each N_j by L / T_j at once), so its integers are taken relative to
   its reference row, the row of that period (one integer fixed per system:
   :func:`_relative`; BeiDou alone, the millisecond common to every range). A hypothesis
   within step / sqrt(3) of the truth rounds every integer right: the range differences
   (within a system) it predicts are wrong by at most |e_j - e_r| |dx| <= 2 * 29 km, plus
   20 km of height and 3.2 km of a 2 s time error, well inside c T / 2. The distinct
   integer vectors are the candidates.
3. **Coarse-time solve** of each candidate: unknowns x, one clock b_s per system (BeiDou's,
   GPS's, Galileo's: each inter-system bias unknown; the layout's, ``Layout(systems,
   coarse_time=True)``) and the receive-time offset dt (true receive time = tag + dt), rows
   [-e_j^T, one-hot of the row's clock, rdot_j] with rdot_j = e_j . V_j the
   satellite's range rate (van Diggelen's coarse-time row), the satellites at
   tag + dt - rho_j / c (each one's position interpolated to second order over the time
   prior), Klobuchar and Saastamoinen delays and the weights of the solver's error model
   (:func:`service.engine.solver.measurement_sigma_m`), and the time prior
   dt = 0 +- ``time_prior_s`` as one more row (a pseudo-observation:
   :func:`service.engine.solver.time_prior_row`). The iteration is the kernel's
   (:func:`service.engine.solver.iterate_fixed` with its ``weighted_rows`` and
   ``lsq_step``): only the geometry (the orbits again at each iterate's receive time) and
   the convergence (group by group for fault exclusion's row subsets) are this module's.
4. **Validation.** A candidate passes when its redundancy (rows + the time prior's row -
   the layout's parameters, 3 + systems + 1) is at least
   ``min_redundancy`` and its weighted residuals pass the chi-square test at the solver's
   ``p_fa`` (:func:`service.engine.raim.chi2_threshold`), at a plausible place: height in
   [``alt_min_m``, ``alt_max_m``], |dt| <= 1.5 times the prior, every tracked satellite above
   ``-horizon_deg``. It is published only if no other plausible candidate has a statistic
   below ``uniqueness_margin`` times its own threshold (a plausible candidate without
   redundancy, whose residuals cannot be tested, always counts as such a rival); else the
   epoch is declined ``ambiguous`` (integer sets compared system by system, relative
   within a system without a full row: :func:`_agree`). With several systems and no
   candidate passing (``chi2``), BeiDou's rows alone are solved and judged the same way.
5. **The fix.** Only a winner that passed steps 3-4 (or their fault exclusion) is
   published. When its integers are absolute (a full row anchors them, or the solved time
   leaves no doubt about the millisecond common to every range; a further system through
   its clock's difference to an absolute one, the inter-system bias, within ``isb_max_m``:
   :func:`_absolute`), they make full ranges and
   the fix is the solver's own SPP of them (:func:`spp_at_receive_time`: all of
   :func:`service.engine.solver.solve`'s corrections, FDE and protection levels) with tag
   and ranges moved together to the receive time, the coarse solution's clock first, then
   SPP's own clock while that is above 1 km (never, on the recordings), SPP's phase 2
   alone from the winner's position: the fix is SPP of the true full ranges at a correct
   tag (1e-7 m on HKSC, tags +-2 s off), and the offset is SPP's, to nanoseconds. Else
   (every range fractional, the common millisecond in doubt) the fix is the coarse-time
   solution itself: SPP needs the transmit times to the microsecond, and a wrong
   millisecond moves them by 1 ms.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from service.core.constants import C_M_S, NOMINAL_FLIGHT_TIME_S
from service.core.corrections import sagnac_rotate
from service.core.declines import Decline, Declined, excluded_why
from service.core.ephemeris import EphemerisStore, select_rows
from service.core.geometry import (
    ecef_to_geodetic,
    enu_rotation,
    geodetic_points,
    geodetic_to_ecef,
)
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.settings import setting
from service.core.systems import GnssSystem, system_of
from service.core.timebase import gpst_to_bdt, normalize
from service.core.types import Fix, MeasurementEpoch
from service.engine.layout import Layout
from service.engine.raim import assess, chi2_threshold
from service.engine.solver import (
    IonoSet,
    LsqStep,
    SolverConfig,
    cn0_variance_m2,
    declined,
    iterate_fixed,
    normal_matrix,
    pseudo_rows,
    ranges,
    solve,
    time_prior_row,
    weighted_rows,
)
from service.engine.velocity import range_rate_m_s

log = logging.getLogger(__name__)

COARSE_TIME = "coarse_time"
"""``Fix.method`` of a fix made here (the paper's fast fix and SPP leave it None)."""
COARSE_LAYOUT = Layout(coarse_time=True)
"""The layout of a BeiDou-only candidate: x, y, z, the clock and the coarse-time offset."""

TRIED_AFTER = frozenset({Decline.TOO_FEW_FULL, Decline.NO_MEASUREMENTS})
"""The declines of the paper's method after which this method is tried (issue 20: the
paper's method with >= 4 full GEO ranges, this one otherwise): too few full ranges, or
none left once the fractional ranges of a coarse receiver time are set aside (the one
rule of the stream's :func:`service.engine.pipeline.coarse_time_fix` and of ``bdsfix
solve``)."""

N_PARAMS = COARSE_LAYOUT.n_params
"""Unknowns of a BeiDou-only candidate's solve: x, y, z, the clock and the coarse-time
offset; with GPS or Galileo rows, one clock more per extra system
(:attr:`service.engine.layout.Layout.n_params` of the rows' coarse-time layout)."""
PRIOR_ROWS = 1
"""Pseudo-observations of a candidate's solve: the time prior dt = 0 +- ``time_prior_s``
(the host clock's tag, an observation with its own sigma). Its term is in the chi-square
statistic, so it counts in the redundancy: rows + PRIOR_ROWS - parameters."""
CODED_SYSTEMS = frozenset({GnssSystem.BDS, GnssSystem.GPS, GnssSystem.GAL})
"""The systems whose rows the coarse-time fix takes (a clock each)."""


def min_rows(ccfg: CoarseConfig | None = None, layout: Layout = COARSE_LAYOUT) -> int:
    """Range rows the coarse-time fix needs with the coarse-time ``layout``: redundancy
    ``min_redundancy`` with the time prior's row (6 satellites at the default 2 for
    BeiDou alone, one more per extra system)."""
    return layout.n_params + (ccfg or CoarseConfig()).min_redundancy - PRIOR_ROWS


@dataclass(frozen=True, slots=True)
class CoarseConfig:
    """Settings of the coarse-time first fix (module docstring)."""

    coarse_fix: bool = setting(
        True,
        "coarse-time first fix when fewer ranges are full than the paper's fast fix needs "
        "(Doppler prior, coarse time, validated integer search)",
        kind="bool",
    )
    time_prior_s: float = setting(
        2.0,
        "coarse fix: uncertainty of the epoch's time tag (host clock) [s]",
        kind="float",
        low=0.0,
        low_open=True,
        high=30.0,
    )
    search_radius_m: float = setting(
        1_500e3,
        "coarse fix: largest distance of a prior hypothesis from the Doppler position [m] "
        "(the search covers search_sigmas of the Doppler position's covariance within it)",
        kind="float",
        low=0.0,
        high=5_000e3,
    )
    search_sigmas: float = 4.5
    speed_sigma_m_s: float = setting(
        25.0,
        "coarse fix: prior 1-sigma of the receiver's speed on each horizontal axis [m/s] "
        "(25: 50 m/s at 2 sigma)",
        kind="float",
        low=0.0,
    )
    vertical_speed_sigma_m_s: float = 2.0
    grid_step_m: float = 50e3
    uniqueness_margin: float = setting(
        10.0,
        "coarse fix: a rival integer set must have a chi-square statistic above this many "
        "times its threshold, else the epoch is declined ambiguous",
        kind="float",
        low=1.0,
    )
    min_redundancy: int = 2
    coarse_max_exclusions: int = setting(
        1,
        "coarse fix: rows fault exclusion may leave out when no candidate passes (0 or 1)",
        kind="int",
        low=0,
        high=1,
    )
    height_sigma_m: float = 2_000.0
    doppler_sigma_m_s: float = 0.5
    alt_min_m: float = -2_000.0
    alt_max_m: float = 15_000.0
    horizon_deg: float = 5.0
    iterations: int = 7
    multi_system: bool = True
    """Take GPS and Galileo rows beside BeiDou (a clock each); False: BeiDou alone."""
    isb_max_m: float = 3_000.0
    """Largest inter-system bias [m] (10 us) with which an extra system's whole code
    period is resolved against the anchor system's clock (module docstring, step 5)."""


@dataclass(frozen=True, slots=True)
class DopplerPrior:
    """A Doppler position: ECEF [m], clock drift [m/s], the horizontal covariance of the
    position and the rows used."""

    x_ecef_m: np.ndarray
    drift_m_s: float
    q_en_m2: np.ndarray  # horizontal (east, north) covariance [m^2]
    n_rows: int
    cost: float = math.nan
    """Weighted squared residuals at the solution (Doppler rows and the height and velocity
    pseudo-observations)."""

    @property
    def sigma_h_m(self) -> float:
        """1-sigma of the covariance's larger horizontal axis [m]."""
        return math.sqrt(max(float(np.linalg.eigvalsh(self.q_en_m2)[-1]), 0.0))


@dataclass(frozen=True, slots=True)
class CoarseResult:
    """What :func:`solve_coarse` found: the published fix (or the decline), the winning
    candidate's time offset [s] and integers, and the search's figures."""

    fix: Fix
    time_offset_s: float | None = None
    integers: dict[str, int] | None = None
    prior: DopplerPrior | None = None
    candidates: int = 0
    passing: int = 0
    absolute: bool = False
    """The integers are absolute (full rows anchor them, or the solved time resolved the
    common millisecond): the fix is SPP of the full ranges they make. Else ``integers`` are
    each system's relative to its reference row (its fractional row of the longest period,
    the first such; integer 0) and the fix is the coarse-time solution."""
    rows: tuple[str, ...] = ()
    """The satellites whose rows the search solved (before its fault exclusion): every
    system's, or BeiDou's alone when that was the fallback (module docstring, step 4)."""


@dataclass(slots=True, eq=False)
class _Sats:
    """The rows of one epoch with their satellites' states, as second-order polynomials of
    time about ``t0`` (BDT sow): position, velocity and clock; ``layout`` (one clock per
    system, coarse time) and ``clk``, each row's clock index in it."""

    prn: tuple[str, ...]
    z_m: np.ndarray
    ct_m: np.ndarray
    cn0_dbhz: np.ndarray
    doppler_hz: np.ndarray
    eph: EphemerisArrays
    t0: float
    p0: np.ndarray
    p1: np.ndarray
    p2: np.ndarray
    c0: np.ndarray
    c1: np.ndarray
    c2: np.ndarray
    drift_s_s: np.ndarray
    layout: Layout = COARSE_LAYOUT
    clk: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.intp))
    groups: list[tuple[int, np.ndarray, bool, int, float]] | None = None
    """:meth:`systems`, computed once (the rows never change)."""

    def at(self, tau_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions (..., n, 3), velocities and clocks (..., n) at t0 + ``tau_s`` (..., n)."""
        t = tau_s[..., None]
        pos = self.p0 + (self.p1 + self.p2 * t) * t
        vel = self.p1 + 2.0 * self.p2 * t
        clk = self.c0 + (self.c1 + self.c2 * tau_s) * tau_s
        return pos, vel, clk

    def systems(self) -> list[tuple[int, np.ndarray, bool, int, float]]:
        """Per clock of the layout that has rows: its index, its rows, whether one of
        them is full, its reference row (the fractional row of the longest period, the
        first such) and that period times c [m] (0 with a full row): the system's
        whole-period null space when none is full (module docstring, step 2)."""
        if self.groups is None:
            self.groups = _groups(self.clk, self.ct_m, self.layout.n_clocks)
        return self.groups


def _groups(
    clk: np.ndarray, ct_m: np.ndarray, n_clocks: int
) -> list[tuple[int, np.ndarray, bool, int, float]]:
    """:meth:`_Sats.systems` of rows with clock indices ``clk`` and periods times c
    ``ct_m`` (0: full)."""
    out = []
    frac = ct_m > 0
    for s in range(n_clocks):
        rows = np.flatnonzero(clk == s)
        if not len(rows):
            continue
        has_full = bool((~frac[rows]).any())
        ref = int(rows[np.argmax(ct_m[rows])])
        out.append((s, rows, has_full, ref, 0.0 if has_full else float(ct_m[ref])))
    return out


def _relative(sats: _Sats, n_int: np.ndarray) -> np.ndarray:
    """Integer vectors ``n_int`` (..., n) with the null space of each system without a full
    row removed: its clock absorbs a shift of its rows by a whole reference period c L
    (every integer N_j by L / T_j at once), so each such system's integers are taken
    relative to its reference row (that row's integer 0): one integer fixed per system."""
    return _relative_in(sats.systems(), sats.ct_m, n_int)


def _relative_in(
    groups: list[tuple[int, np.ndarray, bool, int, float]], ct_m: np.ndarray, n_int: np.ndarray
) -> np.ndarray:
    """:func:`_relative` with the rows' ``groups`` (:func:`_groups`) and ``ct_m``."""
    out = np.array(n_int, dtype=float)
    for _, rows, has_full, ref, ct_ref in groups:
        if has_full:
            continue
        scale = np.round(ct_ref / ct_m[rows])
        out[..., rows] = out[..., rows] - out[..., ref : ref + 1] * scale
    return out


def _median(a: np.ndarray) -> np.ndarray:
    """``np.median(a, axis=1)`` of ``a`` (m, c), the same values (the middle element, or
    the mean (lo + hi) / 2 of the middle two) without its per-call cost."""
    c = a.shape[1]
    if c == 0 or np.isnan(a).any():
        return np.asarray(np.median(a, axis=1))
    if c == 1:
        return a[:, 0].copy()
    srt = np.sort(a, axis=1)
    h = c // 2
    return srt[:, h] if c % 2 else (srt[:, h - 1] + srt[:, h]) / 2.0


def _sats(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    bdt_week: int,
    bdt_sow: float,
    span_s: float,
    multi_system: bool = True,
) -> _Sats | None:
    """The rows of ``epoch`` with an ephemeris and a full or fractional range: BeiDou's, and
    with ``multi_system`` GPS's and Galileo's, of each system that has two rows or more (a
    system's single row only sets its own clock). A fractional row whose period does not
    divide its system's longest is left out (its integer has no whole-period relation to
    the reference row's)."""
    full = np.isfinite(epoch.pr_m)
    frac = ~full & np.isfinite(epoch.frac_pr_m) & np.isfinite(epoch.period_s)
    letters = {GnssSystem.BDS.value}
    if multi_system:
        letters = {s.value for s in CODED_SYSTEMS}
    rows = [i for i in np.flatnonzero(full | frac).tolist() if epoch.prn[i][:1] in letters]
    ephs, idx = select_rows(store, epoch.prn, rows, bdt_week, bdt_sow)
    # the longest period of each system's fractional rows; rows of a period not dividing it
    # out, then systems of a single row out
    longest: dict[str, float] = {}
    for i in idx:
        if frac[i]:
            p = epoch.prn[i][:1]
            longest[p] = max(longest.get(p, 0.0), float(epoch.period_s[i]))
    keep = []
    for i, e in zip(idx, ephs, strict=True):
        if frac[i]:
            ratio = longest[epoch.prn[i][:1]] / float(epoch.period_s[i])
            if abs(ratio - round(ratio)) > 1e-6:
                continue
        keep.append((i, e))
    count: dict[str, int] = {}
    for i, _ in keep:
        count[epoch.prn[i][:1]] = count.get(epoch.prn[i][:1], 0) + 1
    keep = [(i, e) for i, e in keep if count[epoch.prn[i][:1]] >= 2]
    if not keep:
        return None
    idx = [i for i, _ in keep]
    ephs = [e for _, e in keep]
    ii = np.asarray(idx)
    arr = store.arrays(ephs)
    t0 = bdt_sow - NOMINAL_FLIGHT_TIME_S
    h = max(span_s, 0.5)
    # the three times in one call (the ephemeris' arrays broadcast over the first axis)
    pos3, clk3 = sat_pos_clock(arr, bdt_week, t0 + h * np.array([-1.0, 0.0, 1.0])[:, None])
    (pm, pz, pp), (cm, cz, cp) = pos3, clk3
    prn = tuple(epoch.prn[i] for i in idx)
    present = {system_of(p[:1]) for p in prn}
    layout = Layout(tuple(s for s in GnssSystem if s in present), coarse_time=True)
    return _Sats(
        prn=prn,
        z_m=np.where(full[ii], epoch.pr_m[ii], epoch.frac_pr_m[ii]),
        ct_m=np.where(full[ii], 0.0, C_M_S * epoch.period_s[ii]),
        cn0_dbhz=epoch.cn0_dbhz[ii],
        doppler_hz=epoch.doppler_hz[ii],
        eph=arr,
        t0=t0,
        p0=pz,
        p1=(pp - pm) / (2 * h),
        p2=(pp - 2 * pz + pm) / (2 * h * h),
        c0=cz,
        c1=(cp - cm) / (2 * h),
        c2=(cp - 2 * cz + cm) / (2 * h * h),
        drift_s_s=(cp - cm) / (2 * h),  # exact for the clock polynomial (ICD 5.2.4.10)
        layout=layout,
        clk=layout.clock_index(prn),
    )


def _up(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Geodetic height [m] and the local up unit vector of points ``x`` (..., 3)."""
    lat, lon, alt = ecef_to_geodetic(x)
    lat, lon = np.asarray(lat), np.asarray(lon)
    up = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], axis=-1)
    return np.asarray(alt), up


def _row_norms(d: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(d, axis=1)`` of ``d`` (n, 3): its arithmetic, sqrt of the
    ``add.reduce`` of the squares, without its per-call cost."""
    return np.sqrt(np.add.reduce(d * d, axis=1))


def _norm3(v: np.ndarray) -> float:
    """``np.linalg.norm`` of a vector (its own sqrt of the dot product, without its
    per-call cost)."""
    return math.sqrt(float(v @ v))


def doppler_position(
    sats: _Sats, ccfg: CoarseConfig, speed_sigma_m_s: float | None = None
) -> DopplerPrior | None:
    """Position, clock drift and the receiver's velocity from the Doppler rows alone (module
    docstring, step 1), from the Earth's centre: first at rest, then with the velocity as
    three more unknowns held by a prior of ``speed_sigma_m_s`` on each horizontal axis
    (``ccfg.speed_sigma_m_s`` when None; 0: at rest) and ``vertical_speed_sigma_m_s``, so
    that the covariance says how far a moving receiver's Doppler position may be off.
    None with fewer than 4 Doppler rows or no convergence."""
    ok = np.isfinite(sats.doppler_hz)
    if ok.sum() < 4:
        return None
    sv = ccfg.speed_sigma_m_s if speed_sigma_m_s is None else speed_sigma_m_s
    rr = range_rate_m_s(sats.prn, sats.doppler_hz)[ok]
    pos = sats.p0[ok]
    vel = sats.p1[ok]
    ddts = sats.drift_s_s[ok]
    omega = sats.eph.omega_e_rad_s[ok]
    n = len(rr)
    x = np.zeros(3)
    d = 0.0
    v_rx = np.zeros(3)
    cov: np.ndarray = np.eye(7)
    moving = False
    # the moving phase backtracks: a step that raises the weighted cost is halved (the
    # position-velocity trade-off of a few rows makes plain Gauss-Newton cycle there)
    last: tuple[float, np.ndarray, float, np.ndarray, np.ndarray] | None = None
    halvings = 0
    for _ in range(60):
        tau = _row_norms(pos - x) / C_M_S
        s = sagnac_rotate(pos, tau, omega)
        v = sagnac_rotate(vel, tau, omega)
        dv = s - x
        rho = _row_norms(dv)
        e = dv / rho[:, None]
        ev = np.einsum("ij,ij->i", e, v - v_rx)
        pred = ev + d - C_M_S * ddts
        h = np.zeros((n + 4, 7))
        r = np.zeros(n + 4)
        w = np.empty(n + 4)
        h[:n, :3] = -((v - v_rx) - ev[:, None] * e) / rho[:, None]
        h[:n, 3] = 1.0
        h[:n, 4:] = -e
        r[:n] = rr - pred
        w[:n] = 1.0 / ccfg.doppler_sigma_m_s**2
        if _norm3(x) > 1e6:
            lat, lon, alt = ecef_to_geodetic(x)
            rot = enu_rotation(float(lat), float(lon))
            r[n] = -float(alt)
            h[n, :3] = rot[2]  # the local up
        else:  # from the centre: the sphere's radius, the velocity held at 0
            nx = max(_norm3(x), 1.0)
            r[n] = 6_371e3 - nx
            h[n, :3] = x / nx if nx > 1.0 else 0.0
            rot = np.eye(3)
        w[n] = 1.0 / ccfg.height_sigma_m**2
        h[n + 1 :, 4:] = rot
        r[n + 1 :] = -(rot @ v_rx)
        sig = (sv, sv, ccfg.vertical_speed_sigma_m_s) if moving and sv > 0 else (1e-3,) * 3
        w[n + 1 :] = 1.0 / np.square(sig)
        cost = float(np.add.reduce(w * r * r))  # (np.sum's sum)
        if moving and last is not None and cost > last[0]:
            _, x0, d0, v0, half = last
            if halvings >= 8 or _norm3(half[:3]) < 10.0:
                # no descent left: the cost's minimum (along the ill-determined direction
                # its covariance, computed there, is wide); the Jacobian's approximations
                # put the Gauss-Newton fixed point a little off it
                x, d, v_rx, cost = x0, d0, v0, last[0]
                break
            halvings += 1
            last = (last[0], x0, d0, v0, 0.5 * half)
            x, d, v_rx = x0 + half[:3], d0 + float(half[3]), v0 + half[4:]
            continue
        hw = h.T * w
        try:
            cov = np.asarray(np.linalg.inv(hw @ h), dtype=float)
        except np.linalg.LinAlgError:
            return None
        step = cov @ (hw @ r)
        if moving:
            if last is not None and last[0] - cost < 1e-2:
                # the cost no more than 0.01 above its minimum here: within 0.1 sigma of it
                # (Mahalanobis) along the flat valley where plain steps zig-zag
                break
            last, halvings = (cost, x, d, v_rx, 0.5 * step), 0
        x = x + step[:3]
        d += float(step[3])
        v_rx = v_rx + step[4:]
        if _norm3(step[:3]) < 10.0:
            if moving or sv <= 0:
                break
            moving = True
    else:
        return None
    if not np.all(np.isfinite(x)):
        return None
    lat, lon, _ = ecef_to_geodetic(x)
    rot2 = enu_rotation(float(lat), float(lon))[:2]
    # the a posteriori variance factor: Doppler rows noisier than doppler_sigma_m_s (a
    # moving receiver's multipath, a slipped row) widen the covariance, and so the search,
    # instead of centring a narrow one hundreds of km off (n rows, the height and three
    # velocity pseudo-observations, seven unknowns: n - 3 degrees of freedom)
    factor = max(1.0, cost / (n - 3)) if n > 3 and math.isfinite(cost) else 1.0
    q = factor * (rot2 @ cov[:3, :3] @ rot2.T)
    return DopplerPrior(x, d, q, int(ok.sum()), cost)


def hypotheses(
    prior_ecef_m: np.ndarray,
    q_en_m2: np.ndarray | None,
    kappa: float,
    radius_m: float,
    step_m: float,
) -> np.ndarray:
    """Prior hypotheses (m, 3): a hexagonal grid of spacing ``step_m`` in the prior's local
    horizontal plane over the ellipse x^T Q^-1 x <= kappa^2 of the horizontal covariance
    ``q_en_m2`` (None: a circle of ``radius_m``), never beyond ``radius_m``, the prior
    itself always among them; each point put on the ellipsoid (height 0)."""
    lat, lon, _ = ecef_to_geodetic(prior_ecef_m)
    rot = enu_rotation(float(lat), float(lon))
    extent = radius_m
    if q_en_m2 is not None:
        extent = min(radius_m, kappa * math.sqrt(max(float(np.linalg.eigvalsh(q_en_m2)[-1]), 0)))
    k = math.ceil(extent / step_m) + 1
    i, j = np.meshgrid(np.arange(-k, k + 1), np.arange(-k, k + 1), indexing="ij")
    east = step_m * (i + 0.5 * j)
    north = step_m * (math.sqrt(3.0) / 2.0) * j
    keep = np.hypot(east, north) <= radius_m + 1e-6
    if q_en_m2 is not None:
        qi = np.linalg.inv(q_en_m2 + np.eye(2) * 1e-6)
        m2 = qi[0, 0] * east**2 + 2 * qi[0, 1] * east * north + qi[1, 1] * north**2
        # a cell's worth of margin: the truth within the ellipse has a point within step
        edge = (kappa + step_m / math.sqrt(max(float(np.linalg.eigvalsh(q_en_m2)[0]), 1.0))) ** 2
        keep &= m2 <= edge
    keep |= (i == 0) & (j == 0)
    enu = np.stack([east[keep], north[keep], np.zeros(int(keep.sum()))], axis=-1)
    pts = prior_ecef_m + enu @ rot
    glat, glon, _ = _geodetic(pts)
    return geodetic_to_ecef(glat, glon, np.zeros_like(glat))


def _unique_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The distinct rows of ``a`` in lexicographic order and the index of each one's first
    occurrence (``np.unique(a, axis=0, return_index=True)``, without its per-call cost)."""
    first: dict[tuple[float, ...], int] = {}
    for i, row in enumerate(map(tuple, a.tolist())):
        first.setdefault(row, i)
    keys = sorted(first)
    idx = np.array([first[k] for k in keys], dtype=int)
    return a[idx], idx


def _round(sats: _Sats, pts: np.ndarray) -> np.ndarray:
    """The integer vector (m, n) the nearest-satellite rule gives at each hypothesis, each
    system's clock on its own: where a system has full rows (N = 0) they fix its clock,
    else its nearest satellite does (its integers then relative: :func:`_relative`)."""
    n = len(sats.prn)
    m = len(pts)
    sat = np.broadcast_to(sats.p0, (m, n, 3))
    clk = np.broadcast_to(sats.c0, (m, n))
    omega = np.broadcast_to(sats.eph.omega_e_rad_s, (m, n))
    _, pred, _ = ranges(sat, clk, pts, omega)
    frac = sats.ct_m > 0
    ct = np.where(frac, sats.ct_m, 1.0)
    b = np.empty((m, sats.layout.n_clocks))
    pts_idx = np.arange(m)
    for s, rows, has_full, _, _ in sats.systems():
        if has_full:
            full_s = rows[~frac[rows]]
            b[:, s] = _median((sats.z_m - pred)[:, full_s])
        else:
            ref = rows[np.argmin(pred[:, rows], axis=1)]
            z_ref, ct_ref = sats.z_m[ref], ct[ref]
            p_ref = pred[pts_idx, ref]
            b[:, s] = z_ref + np.round((p_ref - z_ref) / ct_ref) * ct_ref - p_ref
    n_int = np.round((pred + b[:, sats.clk] - sats.z_m) / ct)
    return np.where(frac, n_int, 0.0)


@dataclass(slots=True, eq=False)
class _Solved:
    x: np.ndarray  # (k, 3)
    b: np.ndarray  # (k, S): a clock per system of the layout
    dt: np.ndarray  # (k,)
    t_stat: np.ndarray  # (k,)
    dof: np.ndarray  # (k,)
    alt: np.ndarray  # (k,)
    min_el_rad: np.ndarray  # (k,)
    normal: np.ndarray  # (k, P, P) the last normal matrix (with the time prior)
    design: np.ndarray  # (k, n, P) at the solution: x, y, z, S clocks, the time
    resid_m: np.ndarray  # (k, n)
    weight: np.ndarray  # (k, n): 1 / sigma^2, 0 below the mask


def _solve_candidates(
    sats: _Sats,
    n_int: np.ndarray,
    x0: np.ndarray,
    bdt_sow: float,
    iono: IonoSet,
    cfg: SolverConfig,
    ccfg: CoarseConfig,
    row_mask: np.ndarray | None = None,
    group: np.ndarray | None = None,
) -> _Solved:
    """The coarse-time solve (module docstring, step 3) of every candidate at once, by the
    kernel's iteration (:func:`service.engine.solver.iterate_fixed`).

    ``row_mask`` (k, n), True where a candidate uses a row, and ``group`` (k,), the start
    index of each candidate's group in the (contiguous) groups: several row subsets in one
    batch (fault exclusion), each group as if solved alone: its clock started from its own
    rows, its own convergence test, frozen once it has converged; a left-out row weighs 0
    and counts nowhere (redundancy, elevation, statistic)."""
    k, n = n_int.shape
    layout = sats.layout
    n_clk = layout.n_clocks
    i_t = layout.time_column
    onehot = np.zeros((n, n_clk))
    onehot[np.arange(n), sats.clk] = 1.0
    cix = None if n_clk == 1 else np.broadcast_to(sats.clk, (k, n))
    p = sats.z_m + n_int * sats.ct_m  # (k, n)
    omega = np.broadcast_to(sats.eph.omega_e_rad_s, (k, n))
    # each row's system's ionosphere, as the solver's (IonoSet.models: BeiDou's set for
    # BeiDou rows, GPS's for GPS and Galileo rows), each on its own carrier
    models = iono.models(cfg.iono)
    wcfg = cfg if cfg.weighted else replace(cfg, weighted=True)  # (always the error model)
    cn0_var = cn0_variance_m2(sats.cn0_dbhz, cfg)
    x = x0.copy()
    dt = np.zeros(k)
    rel = bdt_sow - sats.t0  # the tag's receive time, from t0
    # the clocks from the first geometry: each system's median over its (used) rows
    pos, _, clk = sats.at(np.full((k, n), rel - NOMINAL_FLIGHT_TIME_S))
    _, pred, _ = ranges(pos, clk, x, omega)
    if row_mask is None or group is None:
        starts = np.zeros(1, dtype=int)
        if n_clk == 1:
            b = _median(p - pred)[:, None]
        else:
            b = _clock_medians(p - pred, None, sats.clk, n_clk)
    else:
        starts = np.flatnonzero(np.r_[True, group[1:] != group[:-1]])
        b = _clock_medians(p - pred, row_mask, sats.clk, n_clk)
    batched = len(starts) > 1 or row_mask is not None
    active = np.ones(k, dtype=bool)
    mask_sin = math.sin(math.radians(cfg.elmask_deg))
    carrier = sats.eph.carrier_hz
    el = np.zeros((k, n))
    alt = np.zeros(k)
    hold = _hold_rows(k, layout) if n_clk > 1 else None
    h = v = w = g_all = v_all = w_all = np.zeros(0)
    out: list[np.ndarray] = []

    def linearize(ix: object, it: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        # (every candidate, every iteration: a frozen group keeps its state, step 0)
        nonlocal pos, el, alt, h, v, w, g_all, v_all, w_all
        # the orbits again at the receive time the iterate's dt moves (tag + dt - flight)
        d = pos - x[:, None, :]
        tau = np.sqrt(np.einsum("kni,kni->kn", d, d)) / C_M_S
        pos, vel, clk = sats.at(rel + dt[:, None] - tau)
        los, pred, _ = ranges(pos, clk, x, omega)
        vel = sagnac_rotate(vel, tau, omega)
        rdot = np.einsum("kni,kni->kn", los, vel)
        near = it >= 1
        if near or it == ccfg.iterations - 1:  # (the first, from afar: no mask, no delays)
            lat, lon, alt, rot = _frames(x)  # rot (k, 3, 3)
            enu = np.einsum("kij,knj->kni", rot, los)
            el = np.arcsin(np.clip(enu[..., 2], -1.0, 1.0))
            az = np.arctan2(enu[..., 0], enu[..., 1])
        if near:  # the kernel's rows (delays at the receive time tag + dt, weights)
            keepw = (enu[..., 2] >= mask_sin).astype(float)
            loc = (lat, lon, alt, el, az)
            h, v, w = weighted_rows(
                layout,
                los,
                cix,
                rdot,
                p - pred,
                b,
                loc,
                bdt_sow + dt,
                carrier,
                sats.eph.bds,
                models,
                keepw,
                cn0_var,
                None,
                wcfg,
            )
        else:
            h = layout.design(los, cix, rdot)
            v = p - pred - b[:, sats.clk]
            w = np.full((k, n), 1e-2)
        if row_mask is not None:
            w = np.where(row_mask, w, 0.0)
            v = np.where(row_mask, v, 0.0)
        # the time prior, a row of the least squares (and of the statistic below)
        g_all, v_all, w_all = time_prior_row(h, v, w, layout, dt, ccfg.time_prior_s)
        if hold is not None:  # a system with no row left (the mask): its clock held
            empty = (w > 0).astype(float) @ onehot == 0.0  # (k, S)
            g_all, v_all, w_all = pseudo_rows(g_all, v_all, w_all, hold, 0.0 * empty, empty)
        return g_all, v_all, w_all

    def advance(ix: object, act: np.ndarray, got: LsqStep, it: int) -> np.ndarray:
        nonlocal x, b, dt, out, active
        step = got[0]  # (a singular candidate's step is NaN: it cannot pass)
        if not batched:
            x = x + step[:, :3]
            b = b + step[:, 3:i_t]
            dt = dt + step[:, i_t]
            # converged with the corrections on: the steps shrink quadratically (HKSC:
            # 30 km, 175 m, 2.4 cm, 6e-5 m), so after one below 5 cm the next is < 0.1 mm
            moved = np.abs(step[:, :i_t]).max(initial=0.0)
            moved += 1e3 * np.abs(step[:, i_t]).max(initial=0.0)
            return act[:0] if it >= 2 and moved < 0.05 else act
        # several groups: the frozen ones keep their state and last figures
        step = np.where(active[:, None], step, 0.0)
        x = x + step[:, :3]
        b = b + step[:, 3:i_t]
        dt = dt + step[:, i_t]
        now = [v, w, h, g_all, v_all, w_all, el, np.asarray(alt)]
        if it == 0:
            out = now
        else:
            out = [np.where(_cast(active, o), a, o) for a, o in zip(now, out, strict=True)]
        if it >= 2:
            moved_g = np.maximum.reduceat(np.abs(step[:, :i_t]).max(axis=1), starts)
            moved_g = moved_g + 1e3 * np.maximum.reduceat(np.abs(step[:, i_t]), starts)
            done = np.repeat(moved_g < 0.05, np.diff(np.r_[starts, k]))
            active &= ~done
        return act if active.any() else act[:0]

    # the kernel's iteration (solver.iterate_fixed), every candidate at once
    iterate_fixed(k, ccfg.iterations, linearize, advance)
    if batched:
        v, w, h, g_all, v_all, w_all, el, alt = out
    # the statistic: the range rows' weighted squares at the last linearization and the
    # time prior row's at the solution (the held clocks' rows have misclosure 0); the
    # redundancy: the layout's, the prior a row, with the clocks that have rows
    t_stat = np.einsum("kn,kn->k", w * v, v) + w_all[:, n] * (0.0 - dt) ** 2
    n_sys = ((w > 0).astype(float) @ onehot > 0).sum(axis=1)
    dof = layout.redundancy((w > 0).sum(axis=1) + PRIOR_ROWS, n_sys)
    min_el = el.min(axis=1) if row_mask is None else np.where(row_mask, el, np.inf).min(axis=1)
    normal = normal_matrix(g_all, w_all)[1]
    return _Solved(x, b, dt, t_stat, np.asarray(dof), np.asarray(alt), min_el, normal, h, v, w)


def _hold_rows(k: int, layout: Layout) -> np.ndarray:
    """Pseudo-observation rows (k, clocks, p) that hold each clock where it is (partial 1
    on it, misclosure 0): weighted 1 for a system the mask left without rows, 0 else."""
    rows = np.zeros((k, layout.n_clocks, layout.n_params))
    idx = np.arange(layout.n_clocks)
    rows[:, idx, 3 + idx] = 1.0
    return rows


def _clock_medians(
    resid_m: np.ndarray, row_mask: np.ndarray | None, clk: np.ndarray, n_clk: int
) -> np.ndarray:
    """Each candidate's starting clocks (k, S): the median of each system's residuals
    ``resid_m`` (k, n) over its rows (``row_mask``: the rows each candidate uses; 0 for a
    system with none)."""
    out = np.zeros((len(resid_m), n_clk))
    for s in range(n_clk):
        cols = clk == s
        if not cols.any():
            continue
        r = resid_m[:, cols]
        if row_mask is None:
            out[:, s] = _median(r)
            continue
        m = row_mask[:, cols]
        has = m.any(axis=1)
        if not np.isfinite(r[m]).all():
            out[has, s] = np.nanmedian(np.where(m, r, np.nan)[has], axis=1)
            continue
        # np.nanmedian's values (its masked median: the middle element, or (lo + hi) / 2
        # of the middle two, of each row's used values), without its per-call cost
        srt = np.sort(np.where(m, r, np.inf), axis=1)
        count = m.sum(axis=1)
        h = count // 2
        lo = np.take_along_axis(srt, np.maximum(np.where(count % 2 == 1, h, h - 1), 0)[:, None], 1)
        hi = np.take_along_axis(srt, np.minimum(h, r.shape[1] - 1)[:, None], 1)
        out[has, s] = ((lo[:, 0] + hi[:, 0]) / 2.0)[has]
    return out


def _cast(active: np.ndarray, like: np.ndarray) -> np.ndarray:
    """``active`` (k,) shaped to broadcast against ``like`` (k, ...)."""
    return active.reshape((-1,) + (1,) * (like.ndim - 1))


def _geodetic(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`ecef_to_geodetic` of points ``x`` (k, 3) (:func:`_frames`)."""
    if len(x) > 8:
        return ecef_to_geodetic(x)
    lat, lon, alt, _ = geodetic_points(x)
    return lat, lon, alt


def _frames(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Geodetic latitude, longitude, height (k,) and :func:`enu_rotation` (k, 3, 3) of
    points ``x`` (k, 3): point by point (:func:`service.core.geometry.geodetic_points`)
    when they are few, where numpy's per-call cost is most of the time."""
    if len(x) > 8:
        lat, lon, alt = ecef_to_geodetic(x)
        return lat, lon, alt, enu_rotation(lat, lon)
    return geodetic_points(x)


def _inv_diag(m: np.ndarray) -> np.ndarray:
    """The diagonal of the inverse of ``m`` (inf where singular)."""
    try:
        return np.diag(np.linalg.inv(m))
    except np.linalg.LinAlgError:
        return np.full(len(m), np.inf)


def solve_coarse(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
    ccfg: CoarseConfig | None = None,
) -> CoarseResult:
    """The coarse-time first fix of one epoch (module docstring): a :class:`CoarseResult`
    whose ``fix`` is the published fix or a decline (``too_few_rows``, ``no_doppler``,
    ``chi2``, ``ambiguous``). Never raises for bad input or numbers."""
    cfg = cfg or SolverConfig()
    ccfg = ccfg or CoarseConfig()
    iono = iono or IonoSet()
    if not epoch.week_known:
        return CoarseResult(declined(epoch, Declined.of(Decline.NO_TIME)))
    try:
        with np.errstate(all="ignore"):
            return _solve_coarse(epoch, store, iono, cfg, ccfg)
    except (np.linalg.LinAlgError, ArithmeticError, ValueError) as exc:
        log.debug("coarse failure at GPST %.3f", epoch.gpst_tow_s, exc_info=True)
        why = Declined.of(Decline.NUMERICAL, error=type(exc).__name__, message=str(exc))
        return CoarseResult(declined(epoch, why))


def _solve_coarse(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    ccfg: CoarseConfig,
) -> CoarseResult:
    """Every system's rows first; when no candidate of theirs passes (``chi2``: more rows,
    more chances of two NLOS ranges, which one exclusion does not clear), BeiDou's alone,
    judged on their own (module docstring, step 4). Its decline stands if that fails too."""
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    sats = _sats(epoch, store, bdt_week, bdt_sow, ccfg.time_prior_s, ccfg.multi_system)
    result = _solve_sats(epoch, sats, store, iono, cfg, ccfg)
    if sats is None or sats.layout.n_clocks == 1 or result.fix.reason_code != Decline.CHI2:
        return result
    alone = _sats(epoch, store, bdt_week, bdt_sow, ccfg.time_prior_s, multi_system=False)
    if alone is None:
        return result
    again = _solve_sats(epoch, alone, store, iono, cfg, ccfg)
    return again if again.fix.ok else result


def _solve_sats(
    epoch: MeasurementEpoch,
    sats: _Sats | None,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    ccfg: CoarseConfig,
) -> CoarseResult:
    """The coarse-time fix of the rows ``sats`` of ``epoch`` (module docstring, 1-5)."""
    bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)[1]
    need = min_rows(ccfg, COARSE_LAYOUT if sats is None else sats.layout)
    if sats is None or len(sats.prn) < need:
        have = 0 if sats is None else len(sats.prn)
        why = Declined.of(Decline.TOO_FEW_ROWS, rows=have, need=need)
        return CoarseResult(declined(epoch, why))
    prior = doppler_position(sats, ccfg)
    if prior is None:
        why = Declined.of(Decline.NO_DOPPLER, rows=int(np.isfinite(sats.doppler_hz).sum()))
        return CoarseResult(declined(epoch, why))
    pts = hypotheses(
        prior.x_ecef_m, prior.q_en_m2, ccfg.search_sigmas, ccfg.search_radius_m, ccfg.grid_step_m
    )
    # each system without a full row: its whole period goes into its clock (module
    # docstring, step 2), its integers relative to its reference row
    n_all = _relative(sats, _round(sats, pts))
    frac = sats.ct_m > 0
    cand, first = _unique_rows(n_all)
    x0 = pts[first]
    ev = _evaluate(sats, cand, x0, bdt_sow, iono, cfg, ccfg)
    n_cand, n_pass = len(cand), int(ev.passing.sum())

    solved_rows = sats.prn

    def result(fix: Fix, **found: Any) -> CoarseResult:
        return CoarseResult(
            fix, prior=prior, candidates=n_cand, passing=n_pass, rows=solved_rows, **found
        )

    excluded: dict[str, str] = {}
    if not ev.passing.any() and ccfg.coarse_max_exclusions > 0 and len(sats.prn) - 1 >= need:
        # fault exclusion: each row left out in turn, every candidate again; published only
        # if every passing or rival solution of every subset agrees on the common rows
        outcome = _exclude_one(sats, cand, x0, bdt_sow, iono, cfg, ccfg)
        if isinstance(outcome, str):
            why = Declined.of(Decline.AMBIGUOUS, passing=0, rivals=outcome)
            return result(declined(epoch, why))
        if outcome is not None:
            j, sats, cand, ev = outcome
            excluded = {prn: excluded_why("coarse") for prn in j}
            frac = sats.ct_m > 0
    solved, passing, rivals, t_max = ev.solved, ev.passing, ev.rivals, ev.t_max
    if not passing.any():
        most = int(np.argmax(solved.dof))
        if int(solved.dof[most]) < ccfg.min_redundancy:
            # (the rows of that candidate above the mask: its redundancy counts the clocks
            # of the systems with rows only)
            rows = int((solved.weight[most] > 0).sum())
            why = Declined.of(Decline.TOO_FEW_ROWS, rows=rows, need=need)
            return result(declined(epoch, why))
        why = Declined.of(Decline.CHI2, "coarse", candidates=len(cand))
        return result(declined(epoch, why))
    ratio = np.where(passing, solved.t_stat / t_max, np.inf)
    best = int(np.argmin(ratio))
    if int(rivals.sum()) > 1:
        why = Declined.of(
            Decline.AMBIGUOUS, passing=int(passing.sum()), rivals=int(rivals.sum()) - 1
        )
        return result(declined(epoch, why))
    dt = float(solved.dt[best])
    n_best, b_all, absolute = _absolute(sats, cand[best], solved, best, ccfg)
    b = float(b_all[0])  # the first system's clock (BeiDou's when it has rows)
    p_full = sats.z_m + n_best * sats.ct_m
    fractional = tuple(p for p, f in zip(sats.prn, frac, strict=True) if f)
    integers = {p: int(k) for p, k, f in zip(sats.prn, n_best, frac, strict=True) if f}
    if absolute:
        full = _full_epoch(epoch, sats.prn, p_full)
        # phase 2 alone from the winner's position (every range full: conventional SPP, the
        # same solution as from the Earth's centre, SolverConfig.x0_ecef_m)
        x0 = tuple(float(v) for v in solved.x[best])
        spp_cfg = replace(cfg, x0_ecef_m=x0) if all(map(math.isfinite, x0)) else cfg
        fix, dt = spp_at_receive_time(full, dt, store, iono, spp_cfg, start_s=-b / C_M_S)
        recovered = {
            p: float(z + k * c)
            for p, z, k, c, f in zip(sats.prn, sats.z_m, n_best, sats.ct_m, frac, strict=True)
            if f
        }
    else:
        fix = _coarse_fix(epoch, sats, solved, best, cfg, ccfg)
        recovered = {}
    if fix.ok:
        # a row SPP's own FDE left out keeps its integer unpublished (never checked, never
        # a recovered range for the SOW check)
        used = set(fix.used)
        fix = replace(
            fix,
            solver="fast",
            mode="fast",
            full=tuple(p for p in fix.used if p not in integers),
            fractional=tuple(p for p in fractional if p in used),
            ambiguity={p: k for p, k in integers.items() if p in used} if absolute else {},
            relative_ambiguity=(
                {} if absolute else {p: k for p, k in integers.items() if p in used}
            ),
            recovered_pr_m={p: v for p, v in recovered.items() if p in used},
            method=COARSE_TIME,
            time_offset_s=dt,
            excluded={**excluded, **fix.excluded},
        )
    return result(fix, time_offset_s=dt, integers=integers, absolute=absolute)


@dataclass(slots=True, eq=False)
class _Evaluation:
    solved: _Solved
    t_max: np.ndarray
    passing: np.ndarray
    rivals: np.ndarray


def _evaluate(
    sats: _Sats,
    cand: np.ndarray,
    x0: np.ndarray,
    bdt_sow: float,
    iono: IonoSet,
    cfg: SolverConfig,
    ccfg: CoarseConfig,
) -> _Evaluation:
    """Solve and judge every candidate (module docstring, steps 3-4)."""
    return _judge(_solve_candidates(sats, cand, x0, bdt_sow, iono, cfg, ccfg), cfg, ccfg)


def _judge(solved: _Solved, cfg: SolverConfig, ccfg: CoarseConfig) -> _Evaluation:
    """Judge every solved candidate (module docstring, step 4). Where a candidate has no
    redundancy its threshold is infinite: it never passes, and if plausible it is a rival."""
    t_max = np.array([chi2_threshold(int(r), cfg.p_fa) if r >= 1 else np.inf for r in solved.dof])
    plausible = (
        (solved.alt >= ccfg.alt_min_m)
        & (solved.alt <= ccfg.alt_max_m)
        & (np.abs(solved.dt) <= 1.5 * ccfg.time_prior_s)
        & (solved.min_el_rad >= -math.radians(ccfg.horizon_deg))
        & np.isfinite(solved.t_stat)
    )
    passing = plausible & (solved.dof >= ccfg.min_redundancy) & (solved.t_stat <= t_max)
    rivals = plausible & (solved.t_stat <= ccfg.uniqueness_margin * t_max)
    return _Evaluation(solved, t_max, passing, rivals)


def _take(sats: _Sats, idx: np.ndarray) -> _Sats:
    """The rows ``idx`` of ``sats``."""
    return _Sats(
        prn=tuple(sats.prn[i] for i in idx),
        z_m=sats.z_m[idx],
        ct_m=sats.ct_m[idx],
        cn0_dbhz=sats.cn0_dbhz[idx],
        doppler_hz=sats.doppler_hz[idx],
        eph=sats.eph.take(idx),
        t0=sats.t0,
        p0=sats.p0[idx],
        p1=sats.p1[idx],
        p2=sats.p2[idx],
        c0=sats.c0[idx],
        c1=sats.c1[idx],
        c2=sats.c2[idx],
        drift_s_s=sats.drift_s_s[idx],
        layout=sats.layout,
        clk=sats.clk[idx],
    )


def _agree(sats: _Sats, rows: list[int], a: np.ndarray, b: np.ndarray) -> bool:
    """Whether integer vectors ``a`` and ``b`` over the rows ``rows`` of ``sats`` are the
    same set: system by system, absolutely where a full row among them anchors the
    system's clock, else relative to the system's fractional row of the longest period
    among them (each system's whole-period null space: :func:`_relative`)."""
    idx = np.asarray(rows, dtype=int)
    for s in np.unique(sats.clk[idx]).tolist():
        pos = np.flatnonzero(sats.clk[idx] == s)
        ct = sats.ct_m[idx[pos]]
        aa, bb = np.asarray(a, dtype=float)[pos], np.asarray(b, dtype=float)[pos]
        if (ct > 0).all():
            ref = int(np.argmax(ct))
            scale = np.round(ct[ref] / ct)
            aa, bb = aa - aa[ref] * scale, bb - bb[ref] * scale
        if np.any(aa != bb):
            return False
    return True


def _exclude_one(
    sats: _Sats,
    cand: np.ndarray,
    x0: np.ndarray,
    bdt_sow: float,
    iono: IonoSet,
    cfg: SolverConfig,
    ccfg: CoarseConfig,
) -> tuple[tuple[str], _Sats, np.ndarray, _Evaluation] | str | None:
    """One row left out (fault exclusion, as the solver's FDE, over every candidate): the
    row left out, the other rows, their candidates and evaluation of the best subset whose
    winner passes; None when no subset passes; a text (the rivals) when subsets disagree:
    a passing or rival solution of any subset whose integers differ from the winner's on
    the rows both use (:func:`_agree`: system by system, relative to a common fractional
    row where the system has no full row)."""
    n = len(sats.prn)
    n_clocks = sats.layout.n_clocks
    subsets = []
    for j in range(n):
        keep = np.array([i for i in range(n) if i != j])
        # (:func:`_relative` of the subset's rows, without building their _Sats)
        groups = _groups(sats.clk[keep], sats.ct_m[keep], n_clocks)
        cj, first = _unique_rows(_relative_in(groups, sats.ct_m[keep], cand[:, keep]))
        subsets.append((j, keep, cj, first))
    # every subset's candidates in one batch (each group solved as if alone), the left-out
    # row's integer 0 and its weight 0
    sizes = [len(cj) for _, _, cj, _ in subsets]
    ends = np.cumsum(sizes)
    n_all = np.zeros((int(ends[-1]), n))
    mask = np.ones((int(ends[-1]), n), dtype=bool)
    group = np.repeat(ends - np.asarray(sizes), sizes)
    for (j, keep, cj, _), e, m in zip(subsets, ends.tolist(), sizes, strict=True):
        n_all[e - m : e][:, keep] = cj
        mask[e - m : e, j] = False
    x_all = np.concatenate([x0[first] for _, _, _, first in subsets])
    batch = _solve_candidates(sats, n_all, x_all, bdt_sow, iono, cfg, ccfg, mask, group)
    # judged candidate by candidate: the batch at once is each subset judged alone
    ev_all = _judge(batch, cfg, ccfg)
    ratio_all = np.where(ev_all.passing, batch.t_stat / ev_all.t_max, np.inf)
    best = None
    for (j, _, _, _), e, m in zip(subsets, ends.tolist(), sizes, strict=True):
        ratio = ratio_all[e - m : e]
        if ev_all.passing[e - m : e].any():
            k = int(np.argmin(ratio))
            if best is None or ratio[k] < best[0]:
                best = (float(ratio[k]), j, k)
    if best is None:
        return None
    _, jb, kb = best
    keep_b, cand_b = subsets[jb][1], subsets[jb][2]
    win = dict(zip(keep_b.tolist(), cand_b[kb].tolist(), strict=True))
    rivals = 0
    for (j, keep, cj, _), e, m in zip(subsets, ends.tolist(), sizes, strict=True):
        common = [i for i in keep.tolist() if i in win]
        cols = [keep.tolist().index(i) for i in common]
        theirs = np.array([win[i] for i in common])
        either = ev_all.rivals[e - m : e] | ev_all.passing[e - m : e]
        for k in np.flatnonzero(either).tolist():
            if j == jb and k == kb:
                continue
            if not _agree(sats, common, cj[k, cols], theirs):
                rivals += 1
    if rivals:
        return f"{rivals} (one row left out)"
    rows = slice(int(ends[jb]) - sizes[jb], int(ends[jb]))
    solved = _Solved(
        batch.x[rows],
        batch.b[rows],
        batch.dt[rows],
        batch.t_stat[rows],
        batch.dof[rows],
        batch.alt[rows],
        batch.min_el_rad[rows],
        batch.normal[rows],
        batch.design[rows][:, keep_b],
        batch.resid_m[rows][:, keep_b],
        batch.weight[rows][:, keep_b],
    )
    ev_b = _Evaluation(solved, ev_all.t_max[rows], ev_all.passing[rows], ev_all.rivals[rows])
    return (sats.prn[jb],), _take(sats, keep_b), cand_b, ev_b


def _absolute(
    sats: _Sats, n_rel: np.ndarray, solved: _Solved, best: int, ccfg: CoarseConfig
) -> tuple[np.ndarray, np.ndarray, bool]:
    """The winner's integers made absolute where that is beyond doubt (module docstring,
    step 5): its integers, its clocks (for the full ranges they make) and whether every
    system's are absolute (else ``n_rel``, each system's relative to its reference row).

    A system with a full row is absolute already. Without any, the first system (the
    anchor, BeiDou when it has rows) takes its whole period K from the solved time: its
    full ranges are p - K c L with K c L = b + c dt (the receiver clock is the tag's
    error), resolved when the time leaves no doubt (4 sigma of dt inside half a period).
    Every other system takes K from its clock's difference to an absolute system's, the
    inter-system bias b_s - b_a - K c L, resolved when it is within ``isb_max_m`` with
    4 sigma to spare (an inter-system bias is nanoseconds in a receiver, far below the
    150 km of half a millisecond)."""
    n_best = np.array(n_rel, dtype=float)
    b = np.array(solved.b[best], dtype=float)
    cov = None
    groups = sats.systems()
    done = {s for s, _, has_full, _, _ in groups if has_full}
    i_t = 3 + sats.layout.n_clocks

    def shift(s: int, rows: np.ndarray, ct_l: float, k: int) -> None:
        nonlocal n_best
        n_best = n_best.copy()
        n_best[rows] -= k * np.round(ct_l / sats.ct_m[rows])
        b[s] -= k * ct_l

    if not done and groups:
        s, rows, _, _, ct_l = groups[0]
        k_float = (b[s] + C_M_S * float(solved.dt[best])) / ct_l
        k = round(k_float)
        sigma_dt = math.sqrt(max(float(_inv_diag(solved.normal[best])[i_t]), 0.0))
        if abs(k_float - k) + 4.0 * C_M_S * sigma_dt / ct_l < 0.5:
            shift(s, rows, ct_l, k)
            done.add(s)
    if not done:
        return np.asarray(n_rel, dtype=float), np.asarray(solved.b[best], dtype=float), False
    a = min(done)
    for s, rows, has_full, _, ct_l in groups:
        if s in done or has_full:
            continue
        if cov is None:
            try:
                cov = np.linalg.inv(solved.normal[best])
            except np.linalg.LinAlgError:
                break
        g = np.zeros(len(cov))
        g[3 + s], g[3 + a] = 1.0, -1.0
        sigma = math.sqrt(max(float(g @ cov @ g), 0.0))
        k = round((b[s] - b[a]) / ct_l)
        isb = b[s] - b[a] - k * ct_l
        if abs(isb) + 4.0 * sigma <= ccfg.isb_max_m:
            shift(s, rows, ct_l, k)
            done.add(s)
    everything = len(done) == len(groups)
    if not everything:
        return np.asarray(n_rel, dtype=float), np.asarray(solved.b[best], dtype=float), False
    return n_best, b, True


def _coarse_fix(
    epoch: MeasurementEpoch,
    sats: _Sats,
    solved: _Solved,
    best: int,
    cfg: SolverConfig,
    ccfg: CoarseConfig,
) -> Fix:
    """The coarse-time solution itself as a fix (the common millisecond unresolved): the
    winner's position, its integrity from the coarse-time design (position, a clock per
    system with rows above the mask, the time) and the rows that accepted it, the time
    prior's row among them (:func:`service.engine.solver.time_prior_row`: the chi-square,
    its redundancy and the protection levels of :func:`service.engine.raim.assess` with
    that coarse-time layout are those of the candidate's test, step 4), the PDOP gate (the
    satellites' rows with the coarse-time column, without the prior's row)."""
    used = solved.weight[best] > 0
    x = solved.x[best]
    lat, lon, alt = (float(v) for v in ecef_to_geodetic(x))
    rot = enu_rotation(lat, lon)
    with_rows = sorted({int(c) for c in sats.clk[used]})
    layout = Layout(tuple(sats.layout.systems[c] for c in with_rows), coarse_time=True)
    cols = [0, 1, 2, *(3 + c for c in with_rows), 3 + sats.layout.n_clocks]
    g = solved.design[best][used][:, cols]
    resid = solved.resid_m[best][used]
    dt = solved.dt[best : best + 1]
    w = solved.weight[best][used]
    g_p, v_p, w_p = time_prior_row(g[None], resid[None], w[None], layout, dt, ccfg.time_prior_s)
    integ = assess(g_p[0], v_p[0], 1.0 / np.sqrt(w_p[0]), rot, cfg.p_fa, cfg.p_md, layout)
    pdop = math.sqrt(max(float(np.sum(_inv_diag(g.T @ g)[:3])), 0.0))
    if not pdop <= cfg.pdop_max:  # the geometry's, with the coarse-time column
        why = Declined.of(Decline.PDOP_GATE, pdop=pdop, pdop_max=cfg.pdop_max)
        return declined(epoch, why)
    cov = integ.cov_enu_m2
    prns = tuple(p for p, u in zip(sats.prn, used, strict=True) if u)
    return Fix(
        solver="fast",
        mode="fast",
        gpst_week=epoch.gpst_week,
        gpst_tow_s=epoch.gpst_tow_s,
        x_ecef_m=(float(x[0]), float(x[1]), float(x[2])),
        lat_deg=math.degrees(lat),
        lon_deg=math.degrees(lon),
        alt_m=alt,
        clock_bias_m=-C_M_S * float(solved.dt[best]),
        std_enu_m=tuple(math.sqrt(max(float(cov[i, i]), 0.0)) for i in range(3)),  # type: ignore[arg-type]
        used=prns,
        resid_rms_m=float(np.sqrt(np.mean(resid**2))),
        redundancy=integ.redundancy,
        chi2=integ.chi2,
        chi2_max=integ.chi2_max,
        hpl_m=integ.hpl_m,
        vpl_m=integ.vpl_m,
        cov_enu_m2=tuple((float(r[0]), float(r[1]), float(r[2])) for r in cov),
    )


TIME_ITERATIONS = 3
"""SPP solves at most of :func:`spp_at_receive_time` (started at the coarse solution's
clock, the first leaves a clock below :data:`TIME_SETTLED_M` on every recording: HKSC
0.014 m at most, the TST drive 258 m; from a worse start the second leaves nanoseconds)."""
TIME_SETTLED_M = 1e3
"""A receiver clock [m] below which the tag plus the offset is the receive time as far as
the fix is concerned: the tag moved (ranges with it) moves only what depends on the
receive time itself, the Klobuchar model's local time, by at most 2 pi / 72,000 s x 150 m
(its shortest period and a large slant delay) = 0.013 m/s; measured 1.4e-4 m/s on HKSC,
7e-4 m/s on the TST drive. 1 km is 3.3 us: the fix moves < 5e-8 m (measured < 3e-9 m),
below the solver's own convergence noise (a second solve moves it by 3e-8 m on HKSC,
1.1e-7 m on the drive, bench/bench_coarse.py's figures unchanged)."""


def spp_at_receive_time(
    full: MeasurementEpoch,
    offset_s: float,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    start_s: float | None = None,
) -> tuple[Fix, float]:
    """The published fix of an accepted integer set: the solver's own SPP
    (:func:`service.engine.solver.solve`, all its corrections, FDE and protection levels)
    of the full ranges ``full`` (the fractional ranges plus their integers times c T),
    evaluated at the receive time, and the time offset (true receive time = tag + offset).

    The full ranges are on the receiver's clock, as the tag is: a transmit time is
    tag - pr / c whatever the clock's error, so SPP at the tag alone is already the fix of
    those ranges; but what depends on the receive time itself (the broadcast Klobuchar
    model's local time, ~0.3 mm over 2 s on HKSC) would be taken at the wrong time. So tag
    and ranges are moved together by S (tag + S, pr + c S: every transmit time unchanged),
    first by ``start_s`` (None: the coarse-time offset ``offset_s``; :func:`solve_coarse`
    gives -b / c, the coarse solution's clock, which puts the tag at the receive time to
    nanoseconds where the offset, solved from range rates, is off by up to 0.2 s on the
    drive), then by the clock each SPP is left with (S -= b / c) until it is below
    :data:`TIME_SETTLED_M`: the solve is then at the receive time, where SPP of the true
    full ranges at a correct tag is (one solve on every recording). The fix carries the
    epoch's tag, its clock relative to that tag (b - c S) and the offset S - b / c; a
    declined SPP, ``offset_s``."""
    shift = offset_s if start_s is None else start_s
    shift = shift if math.isfinite(shift) else 0.0
    fix = declined(full, Declined.of(Decline.NO_MEASUREMENTS))
    for it in range(TIME_ITERATIONS):
        fix = solve(moved(full, shift), store, iono, cfg, "spp")
        if not fix.ok or fix.clock_bias_m is None:
            return replace(fix, gpst_week=full.gpst_week, gpst_tow_s=full.gpst_tow_s), offset_s
        b = fix.clock_bias_m
        if abs(b) < TIME_SETTLED_M or it == TIME_ITERATIONS - 1:
            break  # (the clock and offset below are of this solve, at this shift)
        shift -= b / C_M_S
    b = fix.clock_bias_m or 0.0
    c_shift = C_M_S * shift
    fix = replace(
        fix,
        gpst_week=full.gpst_week,
        gpst_tow_s=full.gpst_tow_s,
        clock_bias_m=b - c_shift,
        clocks_m={k: v - c_shift for k, v in fix.clocks_m.items()},
    )
    return fix, shift - b / C_M_S


_EARTH_RADIUS_M = 6_371e3


def moved(epoch: MeasurementEpoch, shift_s: float) -> MeasurementEpoch:
    """``epoch`` with its tag and every range moved together by ``shift_s`` (tag + S,
    pr + c S, each fractional range + c S modulo its c T): every transmit time tag - pr / c
    unchanged, the receiver's clock less c S (the receive time it describes is the same)."""
    week, tow = normalize(epoch.gpst_week, epoch.gpst_tow_s + shift_s)
    cs = C_M_S * shift_s
    ct = C_M_S * epoch.period_s
    return replace(
        epoch,
        gpst_week=week,
        gpst_tow_s=tow,
        pr_m=epoch.pr_m + cs,
        frac_pr_m=np.mod(epoch.frac_pr_m + cs, ct),
    )


def sow_time_shift(epoch: MeasurementEpoch, store: EphemerisStore) -> float | None:
    """The shift [s] that puts the tag of an epoch whose receiver time is unknown (a phone
    before its first fix) at the receive time the first decoded SOW gives (issue 20's "first
    decoded SOW of any satellite, within about 20 ms"): a full range's transmit time
    tag - pr / c (on the satellite's clock, whatever the receiver clock's error) plus its
    flight time, the middle of [a - R, sqrt(a^2 - R^2)] / c for the orbit's semi-major axis
    a (MEO 72-91 ms, IGSO/GEO 119-139 ms: at most 10 ms off; the search then keeps the
    configured time prior, which holds that well inside; GPS 67-86 ms, Galileo 78-98 ms).
    None without a full BeiDou, GPS or Galileo range whose satellite has an ephemeris."""
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    for i in np.flatnonzero(np.isfinite(epoch.pr_m)).tolist():
        prn = epoch.prn[i]
        coded = prn[:1] in {s.value for s in CODED_SYSTEMS}
        eph = store.select(prn, bdt_week, bdt_sow) if coded else None
        if eph is None:
            continue
        a = eph.sqrt_a_sqrt_m**2
        r = _EARTH_RADIUS_M
        flight_s = 0.5 * ((a - r) + math.sqrt(max(a * a - r * r, 0.0))) / C_M_S
        return flight_s - float(epoch.pr_m[i]) / C_M_S
    return None


def solve_coarse_at_sow(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
    ccfg: CoarseConfig | None = None,
) -> CoarseResult:
    """:func:`solve_coarse` for an epoch whose time tag has no usable prior (its
    ``time_unc_s`` beyond ``time_prior_s``, or unknown) but which has a full range: solved
    with the epoch moved (:func:`moved`) to the time its first full range's SOW gives
    (:func:`sow_time_shift`, well inside the prior), the fix then put back at the epoch's
    tag: the same position, its clock relative to the tag, the offset from the tag, and the
    recovered ranges and integers of the epoch's own fractional ranges. Declined
    ``coarse_time`` (the reason to wait for the first SOW) without a full range."""
    shift = sow_time_shift(epoch, store)
    if shift is None:
        why = Declined.of(
            Decline.COARSE_TIME,
            time_unc_s=epoch.time_unc_s,
            n_frac=int((~np.isfinite(epoch.pr_m) & np.isfinite(epoch.frac_pr_m)).sum()),
            n_full=0,
            need=N_PARAMS - 1,
        )
        return CoarseResult(declined(epoch, why))
    result = solve_coarse(moved(epoch, shift), store, iono, cfg, ccfg)
    fix = replace(result.fix, gpst_week=epoch.gpst_week, gpst_tow_s=epoch.gpst_tow_s)
    offset = None if result.time_offset_s is None else result.time_offset_s + shift
    if fix.ok:
        cs = C_M_S * shift
        recovered = {p: pr - cs for p, pr in fix.recovered_pr_m.items()}
        where = {p: i for i, p in enumerate(epoch.prn)}
        ambiguity = {
            p: round(
                (pr - float(epoch.frac_pr_m[where[p]])) / (C_M_S * float(epoch.period_s[where[p]]))
            )
            for p, pr in recovered.items()
        }
        fix = replace(
            fix,
            clock_bias_m=None if fix.clock_bias_m is None else fix.clock_bias_m - cs,
            clocks_m={k: v - cs for k, v in fix.clocks_m.items()},
            recovered_pr_m=recovered,
            ambiguity=ambiguity if fix.ambiguity else {},
            time_offset_s=offset,
        )
        if result.absolute:
            result = replace(result, integers=ambiguity)
    return replace(result, fix=fix, time_offset_s=offset)


def _full_epoch(
    epoch: MeasurementEpoch, prns: tuple[str, ...], pr_m: np.ndarray
) -> MeasurementEpoch:
    """``epoch`` with the full ranges ``pr_m`` of ``prns`` (the other rows dropped)."""
    where = {p: i for i, p in enumerate(epoch.prn)}
    kept = epoch.rows([where[p] for p in prns])
    return replace(kept, pr_m=np.asarray(pr_m, dtype=float))


def plain_chain(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
    ccfg: CoarseConfig | None = None,
) -> tuple[np.ndarray, dict[str, int]] | None:
    """The untested chain this module replaces, for comparison only (bench/bench_coarse.py):
    the Doppler position (height pseudo-observation 0), every integer rounded once at it
    against the nearest satellite, the five-state least squares, no test (Pocket SDR
    ``pocket_snap.py``: ``pos_dop``, ``res_coff_amb``, ``pos_coff``). Its position and
    integers (each system's relative to its reference row: :func:`_relative`), or None
    without a Doppler position."""
    cfg = cfg or SolverConfig()
    ccfg = ccfg or CoarseConfig()
    with np.errstate(all="ignore"):
        bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
        sats = _sats(epoch, store, bdt_week, bdt_sow, ccfg.time_prior_s, ccfg.multi_system)
        if sats is None or len(sats.prn) < sats.layout.n_params:
            return None
        prior = doppler_position(sats, ccfg, speed_sigma_m_s=0.0)
        if prior is None:
            return None
        pts = hypotheses(prior.x_ecef_m, None, 0.0, 0.0, ccfg.grid_step_m)
        n_int = _round(sats, pts)
        solved = _solve_candidates(sats, n_int, pts, bdt_sow, iono or IonoSet(), cfg, ccfg)
    frac = sats.ct_m > 0
    if not frac.any() or not np.all(np.isfinite(solved.x[0])):
        return None
    rel = _relative(sats, n_int[0])
    ints = {p: int(n) for p, n, f in zip(sats.prn, rel, frac, strict=True) if f}
    return solved.x[0], ints
