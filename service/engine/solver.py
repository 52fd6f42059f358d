"""The positioning engine: the Zhao-Cui-Lu fast fix and conventional SPP, as pure functions.

The fast fix follows the paper's eqs. (1)-(16): unknowns [x, y, z, b, N_1..N_m] start at zero;
fractional rows z_j = |X_j - x| + b - N_j c T_j get a -c T_j column (eq. 11); x and b take the
least-squares step (eq. 10) while each N_j takes round(dN_j) (eq. 13); transmit times use
z_j + N_j c T_j (eq. 5); iteration stops when the position/clock step is below theta and every
rounded dN is zero (eq. 14). The GEO-GDOP eigenvalue gate (eqs. 12, 20-21) is then evaluated
over the full rows at the converged position, and the state is corrected with the integers
fixed (eqs. 15-16). With every measurement full there are no N columns and the procedure is
conventional single-point positioning: :func:`solve` with ``solver="spp"``.

Two phases, so that fast and SPP share one fixed point:
1. From the Earth's centre with no corrections and no elevation mask (they mean nothing
   before the position does): the paper's iteration, gate and final correction.
2. From that position: elevation mask (a masked fractional satellite loses its row; its
   integer is already fixed), Klobuchar and Saastamoinen corrections, weights from the
   error model, iterated to convergence. Then the integrity checks of docs/method.md: the
   chi-square test of the weighted residuals, fault exclusion, the PDOP gate, the plausible
   shell and the protection levels (:mod:`service.engine.raim`).

With every measurement full and an approximate position given (``x0_ecef_m``), phase 1 has
nothing to resolve and phase 2 starts there: conventional SPP, the same solution.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from service.core.bds import is_geo
from service.core.constants import C_M_S, NOMINAL_FLIGHT_TIME_S
from service.core.corrections import klobuchar_bds_m, klobuchar_gps_m, saastamoinen_m, sagnac_rotate
from service.core.declines import Decline, Declined, excluded_why
from service.core.ephemeris import EphemerisStore
from service.core.geometry import ecef_to_geodetic, enu_rotation, look_angles
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.settings import setting
from service.core.systems import SYSTEM_CONSTANTS, GnssSystem, constants_of
from service.core.timebase import BDT_GPST_OFFSET_S, gpst_to_bdt
from service.core.types import Ephemeris, Fix, KlobucharParams, MeasurementEpoch, SatView
from service.engine import linalg
from service.engine.judge import (
    Failed,
    Outcome,
    decline_fix,
    exclude,
    no_exclusion,
    solution_fix,
    verdict,
)
from service.engine.layout import Layout, dop, layout_of
from service.engine.raim import Integrity, assess

log = logging.getLogger(__name__)

IonoChoice = Literal["auto", "bds", "gps", "off"]
TropoChoice = Literal["saastamoinen", "off"]


@dataclass(frozen=True, slots=True)
class SolverConfig:
    """Solver settings. ``beta=None`` derives the gate from T and ``range_error_m``.

    Error model (per measurement, :func:`measurement_sigma_m`):
    sigma^2 = a^2 + b^2 / sin^2 E + c^2 10^((C0 - C/N0) / 10) + sigma_sis^2
              + (k_iono I)^2 + (t_tropo / (sin E + 0.1))^2,
    with the C/N0 term only where the input carries C/N0 and the tropospheric term only
    where Saastamoinen is applied; I is the Klobuchar delay applied, or without a model an
    unmodelled zenith delay with its slant factor. ``weighted=False`` gives every row
    ``sigma_uniform_m``. Calibrated on the recordings (docs/method.md, "Error model").

    Integrity: a chi-square test of the weighted residuals at false-alarm probability
    ``p_fa``; up to ``max_exclusions`` satellites excluded one at a time when it fails;
    protection levels for missed-detection probability ``p_md``; fixes with PDOP above
    ``pdop_max``, an altitude outside [``alt_min_m``, ``alt_max_m``] or a receiver clock
    beyond ``clock_max_s`` are declined.
    """

    elmask_deg: float = setting(
        10.0, "elevation mask [deg]", kind="float", low=0.0, high=90.0, high_open=True
    )
    beta: float = setting(
        0.0,
        "GEO-GDOP gate of the fast fix, paper eq. 21 (0: derived from the code period T and "
        "--range-error-m: 2998 for 1 ms and 50 m)",
        kind="float",
        low=0.0,
    )
    range_error_m: float = setting(
        50.0,
        "3-sigma range error that derives the GDOP gate [m]",
        kind="float",
        low=0.0,
        low_open=True,
    )
    iono: IonoChoice = setting(
        "auto",
        "ionosphere: auto (BeiDou rows: BDS Klobuchar when broadcast, else GPS coefficients "
        "scaled to B1I; GPS and Galileo rows: GPS coefficients, else BDS), bds, gps (every "
        "row with those) or off",
        kind="str",
        choices=("auto", "bds", "gps", "off"),
    )
    tropo: TropoChoice = setting(
        "saastamoinen", "troposphere model", kind="str", choices=("saastamoinen", "off")
    )
    weighted: bool = True
    max_iter: int = 30
    theta_m: float = 1e-3
    conv_m: float = 1e-4
    sigma_a_m: float = setting(0.5, "error model: constant code term a [m]", kind="float", low=0.0)
    sigma_b_m: float = setting(
        0.5, "error model: elevation term b, b / sin E [m]", kind="float", low=0.0
    )
    sigma_cn0_m: float = setting(
        1.0,
        "error model: C/N0 term c, c 10^((C0 - C/N0) / 20) [m] (0: C/N0 not used)",
        kind="float",
        low=0.0,
    )
    cn0_ref_dbhz: float = setting(45.0, "error model: C/N0 reference C0 [dB-Hz]", kind="float")
    sigma_sis_m: float = setting(
        1.0, "error model: orbit and clock (signal in space) error [m]", kind="float", low=0.0
    )
    iono_error_ratio: float = setting(
        0.3, "error model: share of the Klobuchar delay left as error", kind="float", low=0.0
    )
    iono_unmodelled_m: float = setting(
        3.0, "error model: zenith ionosphere error without a model [m]", kind="float", low=0.0
    )
    tropo_error_m: float = setting(
        0.3, "error model: Saastamoinen zenith error [m]", kind="float", low=0.0
    )
    sigma_uniform_m: float = 3.0
    p_fa: float = setting(
        1e-5,
        "integrity: false-alarm probability of the chi-square test (0: no test)",
        kind="float",
        low=0.0,
        high=0.5,
    )
    p_md: float = setting(
        1e-3,
        "integrity: missed-detection probability of the protection levels",
        kind="float",
        low=0.0,
        high=0.5,
        low_open=True,
    )
    max_exclusions: int = setting(
        2, "integrity: satellites fault exclusion may remove", kind="int", low=0, high=10
    )
    pdop_max: float = setting(
        25.0, "largest PDOP of a published fix", kind="float", low=0.0, low_open=True
    )
    alt_min_m: float = setting(-1_000.0, "plausible shell: lowest altitude [m]", kind="float")
    alt_max_m: float = setting(1_100_000.0, "plausible shell: highest altitude [m]", kind="float")
    clock_max_s: float = setting(
        1_000.0,
        "plausible shell: largest receiver clock bias [s]",
        kind="float",
        low=0.0,
        low_open=True,
    )
    # A known approximate position (a reference in studies, the last fix in a stream).
    # With every measurement full the solve is then conventional SPP from it (phase 2
    # alone); with fractional rows phase 1 starts there. None: the paper's start, the
    # Earth's centre (eq. 3). Either way the least-squares solution is the same.
    x0_ecef_m: tuple[float, float, float] | None = None


def derive_beta(period_s: float, range_error_m: float) -> float:
    """Gate threshold beta = alpha / max|d rho| with alpha = c T / 2 (paper eq. 21).

    For T = 1 ms and a 50 m 3-sigma range error this is 2998, the paper's 3000.
    """
    return C_M_S * period_s / 2.0 / range_error_m


@dataclass(slots=True, eq=False)
class _Rows:
    """Measurement rows of one solve, aligned with their ephemerides."""

    prn: tuple[str, ...]
    z_m: np.ndarray  # full pseudorange, or fractional value in [0, cT)
    ct_m: np.ndarray  # c*T for fractional rows, 0 for full rows
    cn0_dbhz: np.ndarray
    eph: EphemerisArrays
    layout: Layout  # the unknowns: position and a clock per system among the rows
    clk: np.ndarray  # each row's clock (index into layout.systems)
    # satellite positions and clocks at the transmit times of eqs. (4)-(5): those depend on
    # the receive time and z + N cT only, not on the receiver state, so iterations that keep
    # N reuse them (key: :func:`_orbit_key`)
    orbit_cache: dict[bytes, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)

    @property
    def frac(self) -> np.ndarray:
        return self.ct_m > 0

    def take(self, idx: np.ndarray) -> _Rows:
        """Rows ``idx``; the cached satellite states come along."""
        cache = {}
        for key, (sat, clk) in self.orbit_cache.items():
            n_int, when = np.frombuffer(key[: -_TIME_KEY.size]), key[-_TIME_KEY.size :]
            cache[n_int[idx].tobytes() + when] = (sat[idx], clk[idx])
        prn = tuple(self.prn[i] for i in idx)
        layout = layout_of(prn)
        clk = self.clk[idx] if layout is self.layout else layout.clock_index(prn)
        return _Rows(
            prn,
            self.z_m[idx],
            self.ct_m[idx],
            self.cn0_dbhz[idx],
            self.eph.take(idx),
            layout,
            clk,
            cache,
        )

    def clocks(self, b: np.ndarray) -> np.ndarray | float:
        """Each row's receiver clock [m] from the clocks ``b`` of :attr:`layout`."""
        return b.item() if self.layout.n_clocks == 1 else b[self.clk]

    def design(self, los: np.ndarray) -> np.ndarray:
        """The design matrix of these rows at line-of-sight vectors ``los``."""
        return self.layout.design(los, self.clk)

    def dop(self, los: np.ndarray, idx: np.ndarray) -> float:
        """GDOP of rows ``idx`` (paper eq. 20, a clock per system; inf where singular)."""
        return float(dop(self.layout.design(los[idx], self.clk[idx])))


_TIME_KEY = struct.Struct("<id")


def _orbit_key(n_int: np.ndarray, bdt_week: int, bdt_sow_s: float) -> bytes:
    """Key of :attr:`_Rows.orbit_cache`: the integers' bytes, then the receive time's."""
    return n_int.tobytes() + _TIME_KEY.pack(bdt_week, bdt_sow_s)


@dataclass(slots=True)
class _Geometry:
    los: np.ndarray  # unit vectors receiver -> satellite (n, 3)
    pred_m: np.ndarray  # predicted pseudorange without the receiver clock and N terms
    sat_ecef_m: np.ndarray

    def take(self, idx: np.ndarray) -> _Geometry:
        return _Geometry(self.los[idx], self.pred_m[idx], self.sat_ecef_m[idx])


def _geometry(
    rows: _Rows, bdt_week: int, bdt_sow_s: float, x: np.ndarray, n_int: np.ndarray
) -> _Geometry:
    """Satellite positions at transmit time (paper eqs. 4-5) and geometric ranges."""
    key = _orbit_key(n_int, bdt_week, bdt_sow_s)
    cached = rows.orbit_cache.get(key)
    if cached is None:
        if len(rows.orbit_cache) > 64:
            rows.orbit_cache.clear()
        eph = rows.eph
        t1 = bdt_sow_s - (rows.z_m + n_int * rows.ct_m) / C_M_S
        t_tx = t1 - (eph.af0_s + eph.af1_s_s * (t1 - eph.toc_sow_s))
        cached = rows.orbit_cache[key] = sat_pos_clock(eph, bdt_week, t_tx)
    los, pred, sat = ranges(*cached, x, rows.eph.omega_e_rad_s)
    return _Geometry(los=los, pred_m=pred, sat_ecef_m=sat)


def ranges(
    sat0_ecef_m: np.ndarray, clock_s: np.ndarray, x_ecef_m: np.ndarray, omega_e_rad_s: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Line-of-sight unit vectors, predicted pseudoranges without the receiver clock and
    integer terms, and the satellite positions rotated by the Earth during the signal's
    travel (Sagnac), for satellites at transmit time ``sat0_ecef_m`` (..., n, 3) with clocks
    ``clock_s`` (..., n), each with its system's Earth rotation rate ``omega_e_rad_s``
    (..., n), and receivers ``x_ecef_m`` (..., 3): one epoch or a batch."""
    one = x_ecef_m.ndim == 1
    x = x_ecef_m if one else x_ecef_m[..., None, :]
    dot = "ij,ij->i" if one else "esk,esk->es"
    d = sat0_ecef_m - x
    sat = sagnac_rotate(sat0_ecef_m, np.sqrt(np.einsum(dot, d, d)) / C_M_S, omega_e_rad_s)
    d = sat - x
    rho = np.sqrt(np.einsum(dot, d, d))
    return d / rho[..., None], rho - C_M_S * clock_s, sat


_NO_INTEGERS = np.zeros(0)
_B1I_PERIOD_S = SYSTEM_CONSTANTS[GnssSystem.BDS].code_period_s
"""The GDOP gate's period when an epoch has no fractional row (beta of eq. 21)."""


def _full_cost(rows: _Rows, geo: _Geometry, b: np.ndarray, full_idx: np.ndarray) -> float:
    """Sum of squared residuals of the full rows (no corrections): the line-search merit."""
    bc = rows.clocks(b)
    if not isinstance(bc, float):
        bc = bc[full_idx]
    r = rows.z_m[full_idx] - geo.pred_m[full_idx] - bc
    return float(r @ r)


def _lsq(h: np.ndarray, dz: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """The (weighted) least-squares step (H^T W H)^-1 H^T W dz (paper eqs. 10 and 16).

    Solved through the normal equations: a handful of unknowns, where an SVD per iteration
    costs more than the rest of the iteration; a singular system falls back to numpy's
    minimum-norm least squares (raising LinAlgError only where that fails too)."""
    ht = h.T if w is None else h.T * w
    try:
        return linalg.solve(ht @ h, ht @ dz)
    except np.linalg.LinAlgError:
        if w is not None:
            sw = np.sqrt(w)
            h, dz = h * sw[:, None], dz * sw
        step, *_ = np.linalg.lstsq(h, dz, rcond=None)
        return np.asarray(step)


@dataclass(frozen=True, slots=True)
class IonoSet:
    """The broadcast ionosphere coefficients the solver may use: BDS (D1 page / BDSA-BDSB)
    and GPS (GPSA-GPSB), the fallback when no BDS set is known. The one holder every command
    and the stream use."""

    bds: KlobucharParams | None = None
    gps: KlobucharParams | None = None

    @classmethod
    def of(cls, params: Iterable[KlobucharParams | None]) -> IonoSet:
        """The holder of the first BDS and the first GPS set among ``params``."""
        out = cls()
        for p in params:
            if p is not None and getattr(out, p.system.lower()) is None:
                out = out.with_params(p)
        return out

    def with_params(self, params: KlobucharParams) -> IonoSet:
        """This holder with ``params`` (by its system) replacing the set it had."""
        if params.system == "BDS":
            return replace(self, bds=params)
        return replace(self, gps=params)

    @property
    def preferred(self) -> KlobucharParams | None:
        """BDS if known, else GPS (scaled to B1I by the model)."""
        return self.bds if self.bds is not None else self.gps

    def models(self, choice: IonoChoice) -> IonoModels | None:
        """The coefficients for BeiDou rows (:meth:`model`) and for GPS and Galileo rows:
        GPSA/GPSB (as RTKLIB corrects Galileo single-frequency rows; NeQuick-G is not
        implemented), else under ``auto`` the BDS set; None when ``off``. Both are None or
        neither is."""
        if choice in ("off", "bds", "gps"):
            model = self.model(choice)
            return None if model is None else IonoModels(model, model)
        bds, other = self.preferred, self.gps or self.bds
        return None if bds is None or other is None else IonoModels(bds, other)

    def model(self, choice: IonoChoice) -> KlobucharParams | None:
        """The coefficients for the ``iono`` setting: off, bds only, gps only, or auto
        (BDS, else the GPS fallback)."""
        if choice == "off":
            return None
        if choice == "bds":
            return self.bds
        if choice == "gps":
            return self.gps
        return self.preferred


@dataclass(frozen=True, slots=True)
class IonoModels:
    """The Klobuchar coefficients one epoch's rows are corrected with: ``bds`` for BeiDou
    rows, ``other`` for GPS and Galileo rows (:meth:`IonoSet.models`)."""

    bds: KlobucharParams
    other: KlobucharParams


def _norm(v: np.ndarray) -> float:
    """The Euclidean norm of a vector, as ``numpy.linalg.norm`` computes it (sqrt of the dot
    product), without its per-call cost."""
    return math.sqrt(float(v.dot(v)))


def _meaningful(x: np.ndarray) -> bool:
    """A position near enough the Earth for masks and delays to mean something."""
    r = _norm(x)
    return 6.0e6 < r < 8.5e6


GROSS_SPREAD_M = 25_000e3
"""Largest possible difference of two full B1I pseudoranges of one epoch [m]. They share
the receiver clock, so they differ by geometry and satellite clocks only: from a MEO at
zenith (~21,500 km) to a GEO/IGSO at the horizon (~41,700 km) is ~20,200 km for a user on
the ground or up to 1000 km above it, plus satellite clocks (< 1 ms, 300 km). A full
pseudorange further than this from the epoch's median is impossible, not merely faulty."""


@dataclass(frozen=True, slots=True)
class _Context:
    """What one epoch's solve needs besides its rows."""

    gpst_week: int
    gpst_tow_s: float
    bdt_week: int
    bdt_sow_s: float
    iono: IonoSet
    cfg: SolverConfig
    solver: Literal["fast", "spp"]


@dataclass(slots=True, eq=False)
class _State:
    """An iterate: position, clock bias [m], integers (0 for full rows) and its geometry."""

    x: np.ndarray
    b: np.ndarray  # a clock per system of the rows' layout [m]
    n_int: np.ndarray
    geo: _Geometry
    iterations: int = 0


@dataclass(frozen=True, slots=True)
class _Decline:
    """Why an attempt gave no solution (``why``), with the figures its declined fix keeps."""

    why: Declined
    gdop_full: float | None = None
    iterations: int = 0


def _phase1(rows: _Rows, ctx: _Context, start: np.ndarray | None = None) -> _State | _Decline:
    """Phase 1: the paper's iteration (eqs. 3-14) from the Earth's centre (or
    ``cfg.x0_ecef_m``, or ``start``) without corrections, the GEO-GDOP gate (eqs. 12, 20-21)
    and the fixed-integer correction (eqs. 15-16)."""
    cfg = ctx.cfg
    if start is not None:
        x = np.array(start, dtype=float)
    else:
        x = np.zeros(3) if cfg.x0_ecef_m is None else np.array(cfg.x0_ecef_m, dtype=float)
    b = np.zeros(rows.layout.n_clocks)
    p = 3 + rows.layout.n_clocks  # the position and clock columns; then the integers
    n_int = np.zeros(len(rows.prn))
    frac = rows.frac
    n_frac = int(frac.sum())
    frac_idx = np.flatnonzero(frac)
    full_idx = np.flatnonzero(~frac)
    converged = False
    it = 0
    geo = _geometry(rows, ctx.bdt_week, ctx.bdt_sow_s, x, n_int)
    cost = _full_cost(rows, geo, b, full_idx)
    for it in range(1, cfg.max_iter + 1):
        dz = rows.z_m + n_int * rows.ct_m - geo.pred_m - rows.clocks(b)  # eqs. (7)-(8)
        h = rows.design(geo.los)
        if n_frac:
            # eq. (11) with the ambiguity in metres (column -1 instead of -cT) for conditioning
            hn = np.zeros((len(rows.prn), n_frac))
            hn[frac_idx, np.arange(n_frac)] = -1.0
            h = np.concatenate([h, hn], axis=1)
        try:
            step = _lsq(h, dz)  # eq. (10)
        except np.linalg.LinAlgError:
            return _Decline(Declined.of(Decline.SINGULAR))
        # Backtracking: the float ambiguities absorb the fractional rows, so x and b move on
        # the full rows alone; from the Earth's centre, near-equatorial GEOs make the plain
        # step overshoot (beyond GEO altitude, then divergence). A step that increases the
        # full-row residual is halved; where the plain step helps it is taken unchanged.
        lam = 1.0
        while True:
            x_new = x + lam * step[:3]
            b_new = b + lam * step[3:p]
            if n_frac:
                dn = np.rint(lam * step[p:] / rows.ct_m[frac_idx])
                n_new = n_int.copy()
                n_new[frac_idx] += dn  # eq. (13)
            else:  # every row full: no integers to move
                dn, n_new = _NO_INTEGERS, n_int
            geo_new = _geometry(rows, ctx.bdt_week, ctx.bdt_sow_s, x_new, n_new)
            cost_new = _full_cost(rows, geo_new, b_new, full_idx)
            if cost_new <= cost or lam < 1e-3 or not math.isfinite(cost):
                break
            lam /= 2.0
        x, b, n_int, geo, cost = x_new, b_new, n_new, geo_new, cost_new
        if not np.isfinite(x).all():
            break
        if _norm(lam * step[:p]) < cfg.theta_m and not np.any(dn):  # eq. (14)
            converged = True
            break
    if not np.isfinite(x).all():
        return _Decline(Declined.of(Decline.NO_CONVERGENCE, iterations=it), iterations=it)

    # eqs. (12), (20)-(21): GEO-GDOP gate over the full rows, evaluated at the converged
    # phase-1 position (or at the last iterate when the iteration did not settle)
    gd = rows.dop(geo.los, full_idx)
    beta = cfg.beta
    if not beta:
        t_min = float(np.min(rows.ct_m[frac]) / C_M_S) if n_frac else _B1I_PERIOD_S
        beta = derive_beta(t_min, cfg.range_error_m)
    if n_frac and not gd < beta:
        variant = "" if converged else "unsettled"
        why = Declined.of(Decline.GDOP_GATE, variant, gdop=gd, beta=beta, iterations=it)
        return _Decline(why, gd, it)
    if not converged:
        return _Decline(Declined.of(Decline.NO_CONVERGENCE, iterations=it), gd, it)

    # eqs. (15)-(16): integers fixed, correct [x, b] over all rows (iterated to convergence)
    state = _fixed_iterations(rows, ctx, _State(x, b, n_int, geo, it), None, False)
    return state


@dataclass(frozen=True, slots=True, eq=False)
class _Attempt:
    """One solve of a set of rows: the fix (or why not) and the integrity figures of its
    final solution. ``kept`` indexes ``rows``: the rows the solution used (above the mask)."""

    fix: Fix
    rows: _Rows
    kept: np.ndarray
    integrity: Integrity | None = None
    x_ecef_m: np.ndarray | None = None  # the final solution, judged or not

    @property
    def failed_test(self) -> bool:
        i = self.integrity
        return i is not None and i.chi2 is not None and not i.passed


def _attempt(rows: _Rows, ctx: _Context, start: np.ndarray | None = None) -> _Attempt:
    """Solve ``rows`` (phase 1 when fractional rows need integers, then phase 2) and judge
    the solution: chi-square test, plausibility, PDOP gate (in that order). ``start``: where
    phase 1 starts instead of the Earth's centre (fault exclusion's candidates start at the
    failed solution: the same fixed point, reached in fewer iterations)."""
    cfg = ctx.cfg
    frac = rows.frac
    n_full, n_frac = int((~frac).sum()), int(frac.sum())

    def declined(d: _Decline) -> _Attempt:
        fix = decline_fix(
            ctx.solver,
            ctx.gpst_week,
            ctx.gpst_tow_s,
            rows.prn,
            frac.tolist(),
            d.why,
            gdop_full=d.gdop_full,
            iterations=d.iterations,
        )
        return _Attempt(fix, rows, np.zeros(0, dtype=int))

    need = rows.layout.n_params
    if n_full < need:
        return declined(
            _Decline(Declined.of(Decline.TOO_FEW_FULL, n_full=n_full, n_frac=n_frac, need=need))
        )
    if cfg.x0_ecef_m is not None and not n_frac:
        # every measurement full and a position known: conventional SPP, phase 2 alone (the
        # same solution as from the Earth's centre, see SolverConfig.x0_ecef_m)
        x = np.array(cfg.x0_ecef_m, dtype=float)
        n0 = np.zeros(len(rows.prn))
        b0 = np.zeros(rows.layout.n_clocks)
        state = _State(x, b0, n0, _geometry(rows, ctx.bdt_week, ctx.bdt_sow_s, x, n0))
    else:
        first = _phase1(rows, ctx, start)
        if isinstance(first, _Decline):
            return declined(first)
        state = first

    # ---- phase 2: mask, corrections, weights ---------------------------------------------
    meaningful = _meaningful(state.x)
    loc0 = None
    if meaningful:
        loc0 = _local(state.x, state.geo.sat_ecef_m)
        keep = np.flatnonzero(loc0.el_rad >= np.radians(cfg.elmask_deg))
    else:
        keep = np.arange(len(rows.prn))
    kept = rows if len(keep) == len(rows.prn) else rows.take(keep)
    kfrac = kept.frac
    n_full_k = int((~kfrac).sum())
    if n_full_k < kept.layout.n_params:
        return declined(
            _Decline(
                Declined.of(Decline.TOO_FEW_FULL, "mask", mask_deg=cfg.elmask_deg, n_full=n_full_k),
                rows.dop(state.geo.los, np.flatnonzero(~frac)) if n_frac else None,
                state.iterations,
            )
        )
    model = ctx.iono.models(cfg.iono) if meaningful else None
    geo = state.geo if kept is rows else state.geo.take(keep)
    state = _fixed_iterations(
        kept,
        ctx,
        _State(state.x, _clocks_for(state.b, rows, kept), state.n_int[keep], geo, state.iterations),
        model,
        meaningful,
        loc0 if kept is rows else None,  # a subset's angles are computed on their own
    )
    x, b, it = state.x, state.b, state.iterations
    if not (np.isfinite(x).all() and np.isfinite(b).all()):
        return declined(_Decline(Declined.of(Decline.DIVERGED), iterations=it))

    # ---- judge the solution -----------------------------------------------------------------
    geo = state.geo
    loc = _local(x, geo.sat_ecef_m)
    iono_m, tropo_m = (
        _delays(loc, ctx.bdt_sow_s, model, cfg, kept.eph) if meaningful else (None, None)
    )
    corr = total_delay(iono_m, tropo_m)
    v = kept.z_m + state.n_int * kept.ct_m - geo.pred_m - kept.clocks(b) - corr
    sigma = _sigma_m(kept, loc, iono_m, tropo_m, cfg, meaningful)
    a = kept.design(geo.los)
    rot = enu_rotation(loc.lat_rad, loc.lon_rad)
    integ = assess(a, v, sigma, rot, cfg.p_fa, cfg.p_md, kept.layout)
    resid_rms = float(np.sqrt(np.mean(v**2)))
    gd_final = kept.dop(geo.los, np.flatnonzero(~kfrac))
    frac_idx = np.flatnonzero(kfrac)
    ambiguity = {kept.prn[i]: int(state.n_int[i]) for i in frac_idx}
    gdop_full = gd_final if ctx.solver == "fast" else None

    lat_deg, lon_deg = float(np.degrees(loc.lat_rad)), float(np.degrees(loc.lon_rad))
    b_max = float(b[int(np.argmax(np.abs(b)))])  # the clock furthest from zero
    q_enu = rot @ linalg.inv(a.T @ a)[:3, :3] @ rot.T
    pdop = float(np.sqrt(np.trace(q_enu)))
    why = verdict(integ, kept.prn, loc.alt_m, b_max, pdop, cfg)
    if why is not None:
        fix = decline_fix(
            ctx.solver,
            ctx.gpst_week,
            ctx.gpst_tow_s,
            rows.prn,
            frac.tolist(),
            why,
            gdop_full=gdop_full,
            iterations=it,
            resid_rms_m=resid_rms,
            redundancy=integ.redundancy,
            chi2=integ.chi2,
            chi2_max=integ.chi2_max,
            **({"ambiguity": ambiguity} if why.code is Decline.CHI2 else {}),
        )
        return _Attempt(fix, rows, keep, integ, x)
    fix = solution_fix(
        solver=ctx.solver,
        gpst_week=ctx.gpst_week,
        gpst_tow_s=ctx.gpst_tow_s,
        x=x,
        clocks=b,
        systems=kept.layout.systems,
        lat_deg=lat_deg,
        lon_deg=lon_deg,
        alt_m=loc.alt_m,
        gdop_full=gdop_full,
        pdop=pdop,
        hdop=float(np.sqrt(q_enu[0, 0] + q_enu[1, 1])),
        vdop=float(np.sqrt(q_enu[2, 2])),
        cov=integ.cov_enu_m2.tolist(),  # the same floats as element by element
        integ=integ,
        resid_rms_m=resid_rms,
        iterations=it,
        used=kept.prn,
        frac=kfrac.tolist(),
        ambiguity=ambiguity,
        recovered_pr_m={
            kept.prn[i]: float(kept.z_m[i] + state.n_int[i] * kept.ct_m[i]) for i in frac_idx
        },
    )
    return _Attempt(fix, rows, keep, integ, x)


def _clocks_for(b: np.ndarray, rows: _Rows, kept: _Rows) -> np.ndarray:
    """The clocks ``b`` of ``rows``' layout for the subset ``kept`` (a system the subset
    no longer has loses its clock)."""
    if kept.layout is rows.layout:
        return b
    where = {s: k for k, s in enumerate(rows.layout.systems)}
    return np.array([b[where[s]] for s in kept.layout.systems])


def _solve_rows(rows: _Rows, ctx: _Context) -> Fix:
    """Solve with fault detection and exclusion: impossible ranges are dropped first; when
    the chi-square test fails, satellites are excluded one at a time (:func:`_exclude`)."""
    excluded: dict[str, str] = {}
    full = ~rows.frac
    if int(full.sum()) >= 2:
        # the median by sorting: numpy's median imports numpy.ma on its first call (~14 ms,
        # a stall on the first fast-fix epoch of a daemon)
        z = np.sort(rows.z_m[full])
        median = 0.5 * (z[(len(z) - 1) // 2] + z[len(z) // 2])
        dev = np.abs(rows.z_m - median)
        gross = full & ~(dev <= GROSS_SPREAD_M)
        if gross.any():
            for i in np.flatnonzero(gross):
                excluded[rows.prn[i]] = excluded_why("gross", dev_km=dev[i] / 1e3)
            rows = rows.take(np.flatnonzero(~gross))
    att = _attempt(rows, ctx)
    fix = att.fix
    if att.failed_test and ctx.cfg.max_exclusions > 0:
        fix = _exclude(att, ctx)
        excluded |= fix.excluded
    if excluded:
        return replace(fix, excluded=excluded)
    return fix


_Candidate = tuple[_Rows, np.ndarray | None]
"""A candidate of fault exclusion: its rows and where its phase 1 starts (:func:`_warm_start`)."""


def _exclude(failed: _Attempt, ctx: _Context) -> Fix:
    """Fault exclusion of a solution that failed the test (:func:`service.engine.judge.
    exclude`, the loop the batch runs too), each candidate solved by :func:`_attempt`: the
    fix it resolves to, or the failed solution's decline when no exclusion passes."""

    def without(cand: _Candidate, prn: str) -> _Candidate:
        rows, start = cand
        return rows.take(np.flatnonzero([p != prn for p in rows.prn])), start

    def solve(cands: list[_Candidate]) -> list[tuple[Outcome, _Candidate]]:
        out: list[tuple[Outcome, _Candidate]] = []
        for rows, start in cands:
            att = _attempt(rows, ctx, start)
            res = _outcome(att)
            warm = res.warm_start if isinstance(res, Failed) else None
            out.append((res, (att.rows, None if warm is None else np.array(warm))))
        return out

    first = _outcome(failed)
    if not isinstance(first, Failed):  # (the caller asks only for a failed test)
        return failed.fix
    start = None if first.warm_start is None else np.array(first.warm_start)
    passed, _ = exclude({0: (first, (failed.rows, start))}, without, solve, ctx.cfg.max_exclusions)
    return passed[0] if passed else no_exclusion(failed.fix, ctx.cfg.max_exclusions)


def _outcome(att: _Attempt) -> Outcome:
    """The fix of ``att``, or its failed test (:class:`service.engine.judge.Failed`)."""
    i = att.integrity
    if i is None or i.chi2 is None or i.chi2_max is None or i.passed:
        return att.fix
    kept = tuple(att.rows.prn[j] for j in att.kept.tolist())
    warm = _warm_start(att)
    start = None if warm is None else (float(warm[0]), float(warm[1]), float(warm[2]))
    return Failed(i.chi2, i.chi2_max, i.redundancy, kept, tuple(i.w.tolist()), att.fix, start)


def _warm_start(failed: _Attempt) -> np.ndarray | None:
    """Where the exclusion candidates of ``failed`` start phase 1: its solution, when every
    row is full (no integers to resolve, so phase 1 converges to the same fixed point from
    anywhere it converges from the Earth's centre, in 2-3 iterations instead of 6-8); None
    (the Earth's centre) with fractional rows, whose integers the fault may have corrupted."""
    x = failed.x_ecef_m
    if x is None or failed.rows.frac.any() or not _meaningful(x):
        return None
    return x


@dataclass(frozen=True, slots=True, eq=False)
class _Local:
    """Receiver geodetic position and satellite look angles at one iterate."""

    lat_rad: float
    lon_rad: float
    alt_m: float
    el_rad: np.ndarray
    az_rad: np.ndarray


def _local(x: np.ndarray, sat_ecef_m: np.ndarray) -> _Local:
    lat, lon, alt = (float(v) for v in ecef_to_geodetic(x))
    el, az = look_angles(x, sat_ecef_m, (lat, lon))
    return _Local(lat, lon, alt, el, az)


def measurement_sigma_m(
    el_rad: np.ndarray,
    cn0_dbhz: np.ndarray,
    iono_m: np.ndarray | None,
    tropo_m: np.ndarray | None,
    cfg: SolverConfig,
) -> np.ndarray:
    """Standard deviation [m] of each pseudorange's error (model in :class:`SolverConfig`).

    Code noise and multipath grow at low elevation and low C/N0 (the C/N0 term is what
    makes the model honest in urban canyons, where weak reflected signals carry tens of
    metres of error); the orbit and clock error (signal in space) is ``sigma_sis_m`` for
    every satellite: the broadcast URA (BDS-SIS-ICD-B1I-3.0 5.2.4.5) is a class bound,
    2.0-2.4 m for every healthy satellite in the recordings, not a standard deviation; the
    broadcast Klobuchar model leaves part of the ionospheric delay (``iono_error_ratio``),
    without one the whole delay (``iono_unmodelled_m`` at zenith, thin-shell slant factor);
    Saastamoinen leaves a decimetre-level zenith error mapped with 1 / (sin E + 0.1), as in
    RTKLIB's error model.
    """
    s = np.maximum(np.sin(el_rad), 0.05)
    var = cfg.sigma_a_m**2 + (cfg.sigma_b_m / s) ** 2
    cn0 = np.where(np.isfinite(cn0_dbhz), cn0_dbhz, cfg.cn0_ref_dbhz)
    var = var + cfg.sigma_cn0_m**2 * 10.0 ** ((cfg.cn0_ref_dbhz - cn0) / 10.0)
    var = var + cfg.sigma_sis_m**2
    if iono_m is None:  # no broadcast model applied: the whole delay is error
        var = var + (cfg.iono_unmodelled_m * _obliquity(el_rad)) ** 2
    else:
        left = (cfg.iono_error_ratio * iono_m) ** 2
        if not np.isfinite(left).all():  # NaN: no model at that row's receiver (the batch)
            unmodelled = (cfg.iono_unmodelled_m * _obliquity(el_rad)) ** 2
            left = np.where(np.isfinite(iono_m), left, unmodelled)
        var = var + left
    if tropo_m is not None:
        var = var + (cfg.tropo_error_m / (s + 0.1)) ** 2
    return np.sqrt(var)


def _obliquity(el_rad: np.ndarray) -> np.ndarray:
    """Slant factor of a thin ionospheric shell at 350 km (IS-GPS-200 20.3.3.5.2.5 form)."""
    ratio = 6378.0 / (6378.0 + 350.0) * np.cos(el_rad)
    return 1.0 / np.sqrt(1.0 - ratio**2)


def _sigma_m(
    rows: _Rows,
    loc: _Local,
    iono_m: np.ndarray | None,
    tropo_m: np.ndarray | None,
    cfg: SolverConfig,
    meaningful: bool,
) -> np.ndarray:
    if not (meaningful and cfg.weighted):
        return np.full(len(rows.prn), cfg.sigma_uniform_m)
    return measurement_sigma_m(loc.el_rad, rows.cn0_dbhz, iono_m, tropo_m, cfg)


def _delays(
    loc: _Local,
    bdt_sow: float,
    models: IonoModels | None,
    cfg: SolverConfig,
    eph: EphemerisArrays,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """:func:`system_delays` for the rows at this iterate."""
    return system_delays(
        loc.lat_rad,
        loc.lon_rad,
        loc.alt_m,
        loc.el_rad,
        loc.az_rad,
        bdt_sow,
        eph.carrier_hz,
        eph.bds,
        models,
        cfg,
    )


def system_delays(
    lat_rad: float | np.ndarray,
    lon_rad: float | np.ndarray,
    alt_m: float | np.ndarray,
    el_rad: np.ndarray,
    az_rad: np.ndarray,
    bdt_sow_s: float | np.ndarray,
    carrier_hz: np.ndarray,
    bds_rows: np.ndarray,
    models: IonoModels | None,
    cfg: SolverConfig,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """:func:`delays` with each row's system's ionosphere: BeiDou rows (``bds_rows``) with
    ``models.bds``, GPS and Galileo rows with ``models.other`` (:meth:`IonoSet.models`), each
    on its own carrier. One epoch or a batch, as :func:`delays`; the per-epoch solver and
    the batch both call it, so their corrections are the same numbers."""
    model = None if models is None else models.bds
    args = (lat_rad, lon_rad, alt_m, el_rad, az_rad, bdt_sow_s, carrier_hz)
    iono, tropo = delays(*args, model, cfg)
    mixed = models is not None and models.other is not model and not bool(np.all(bds_rows))
    if iono is not None and models is not None and mixed:
        other, _ = delays(*args, models.other, replace(cfg, tropo="off"))
        if other is not None:
            iono = np.where(bds_rows, iono, other)
    return iono, tropo


def delays(
    lat_rad: float | np.ndarray,
    lon_rad: float | np.ndarray,
    alt_m: float | np.ndarray,
    el_rad: np.ndarray,
    az_rad: np.ndarray,
    bdt_sow_s: float | np.ndarray,
    carrier_hz: np.ndarray,
    model: KlobucharParams | None,
    cfg: SolverConfig,
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """Ionospheric (Klobuchar: BDS ICD 5.2.4.7, or GPS IS-GPS-200 20.3.3.5.2.5, scaled to
    each row's ``carrier_hz``) and tropospheric (Saastamoinen) delays [m] per row; None:
    not applied. One epoch (receiver figures are floats, rows (n,)) or a batch (figures
    (e,), rows (e, s)). The ionosphere applies only below 100 km: above, None for one epoch,
    NaN for that epoch's rows in a batch (the error model then counts the whole delay as
    error)."""
    batch = np.ndim(alt_m) > 0
    if batch:  # receivers (e,) against rows (e, s)
        lat_rad, lon_rad = np.asarray(lat_rad)[:, None], np.asarray(lon_rad)[:, None]
        alt_m, bdt_sow_s = np.asarray(alt_m)[:, None], np.asarray(bdt_sow_s)[:, None]
    iono = None
    if model is not None and (batch or alt_m < 100e3):
        if model.system == "BDS":
            iono = klobuchar_bds_m(model, lat_rad, lon_rad, el_rad, az_rad, bdt_sow_s, carrier_hz)
        else:
            gpst_tow = bdt_sow_s + BDT_GPST_OFFSET_S
            iono = klobuchar_gps_m(model, lat_rad, lon_rad, el_rad, az_rad, gpst_tow, carrier_hz)
        if batch:
            iono = np.where(alt_m < 100e3, iono, np.nan)
    tropo = saastamoinen_m(lat_rad, alt_m, el_rad) if cfg.tropo != "off" else None
    return iono, tropo


def total_delay(iono_m: np.ndarray | None, tropo_m: np.ndarray | None) -> np.ndarray | float:
    """The delays to take from the measured ranges: ionosphere (NaN: not modelled, 0) plus
    troposphere (None: not applied)."""
    out: np.ndarray | float = 0.0
    if iono_m is not None:
        # NaN (a batch's epoch above 100 km): no model there, nothing to take
        out = out + (iono_m if iono_m.ndim == 1 else np.where(np.isfinite(iono_m), iono_m, 0.0))
    if tropo_m is not None:
        out = out + tropo_m
    return out


def _fixed_iterations(
    rows: _Rows,
    ctx: _Context,
    state: _State,
    model: IonoModels | None,
    meaningful: bool,
    loc0: _Local | None = None,
) -> _State:
    """Least squares on [x, y, z, b] with the integers held (paper eqs. 15-16), iterated
    from ``state``. When the position is ``meaningful`` the rows are weighted by the error
    model and corrected for the delays. ``loc0``: :func:`_local` at ``state`` when the
    caller has it already (the same values: it is not computed again)."""
    cfg = ctx.cfg
    x, b, geo, n_int = state.x, state.b, state.geo, state.n_int
    it = 0
    for it in range(1, cfg.max_iter + 1):
        dz = rows.z_m + n_int * rows.ct_m - geo.pred_m - rows.clocks(b)
        w = None
        if meaningful:
            loc = loc0 if loc0 is not None and it == 1 else _local(x, geo.sat_ecef_m)
            iono_m, tropo_m = _delays(loc, ctx.bdt_sow_s, model, cfg, rows.eph)
            dz = dz - total_delay(iono_m, tropo_m)
            if cfg.weighted:
                w = 1.0 / _sigma_m(rows, loc, iono_m, tropo_m, cfg, True) ** 2
        step = _lsq(rows.design(geo.los), dz, w)
        x = x + step[:3]
        b = b + step[3:]
        if not (np.isfinite(x).all() and np.isfinite(b).all()):
            break
        geo = _geometry(rows, ctx.bdt_week, ctx.bdt_sow_s, x, n_int)
        if _norm(step) < cfg.conv_m:
            break
    return _State(x, b, n_int, geo, state.iterations + it)


def sky_view(epoch: MeasurementEpoch, store: EphemerisStore, fix: Fix) -> tuple[SatView, ...]:
    """Satellites of ``epoch`` with an ephemeris, seen from the fix (empty without one)."""
    if fix.x_ecef_m is None:
        return ()
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    ephs, idx = [], []
    for i, prn in enumerate(epoch.prn):
        e = store.select(prn, bdt_week, bdt_sow)
        if e is not None:
            ephs.append(e)
            idx.append(i)
    if not ephs:
        return ()
    arr = store.arrays(ephs)
    pos, _ = sat_pos_clock(arr, bdt_week, np.full(len(ephs), bdt_sow - NOMINAL_FLIGHT_TIME_S))
    el, az = look_angles(np.asarray(fix.x_ecef_m), pos)
    used = set(fix.used)
    # whole-array conversions (the same floats as element by element, a fraction of the cost)
    el_deg, az_deg = np.degrees(el).tolist(), np.degrees(az).tolist()
    cn0 = epoch.cn0_dbhz[idx].tolist()
    full = np.isfinite(epoch.pr_m[idx]).tolist()
    prns, signals = epoch.prn, epoch.signal
    return tuple(
        SatView(prns[i], el_deg[k], az_deg[k], cn0[k], prns[i] in used, full[k], signals[i])
        for k, i in enumerate(idx)
    )


def select_rows(
    epoch: MeasurementEpoch, store: EphemerisStore, solver: Literal["fast", "spp"]
) -> tuple[_Rows | None, list[str]]:
    """Rows usable by ``solver`` (SPP: full only; fast: full and fractional) with ephemerides.

    When some system has a full row, the fast fix takes the fractional rows of a system only
    when that system has a full row too: phase 1 resolves integers against clocks estimated
    from full rows, and a system whose rows are all fractional has none; its rows join
    afterwards (:func:`_with_other_systems`). Returns the rows and the PRNs dropped for
    want of a usable ephemeris.
    """
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    full = np.isfinite(epoch.pr_m)
    fracok = ~full & np.isfinite(epoch.frac_pr_m) & np.isfinite(epoch.period_s)
    if solver == "fast" and fracok.any():
        with_full = {epoch.prn[i][:1] for i in np.flatnonzero(full)}
        if with_full and any(p[:1] not in with_full for p in epoch.prn):
            fracok &= np.array([p[:1] in with_full for p in epoch.prn], dtype=bool)
    use = full | fracok if solver == "fast" else full
    idx: list[int] = []
    ephs: list[Ephemeris] = []
    missing: list[str] = []
    for i in np.flatnonzero(use):
        e = store.select(epoch.prn[i], bdt_week, bdt_sow)
        if e is None:
            missing.append(epoch.prn[i])
            continue
        idx.append(int(i))
        ephs.append(e)
    if not idx:
        return None, missing
    ii = np.asarray(idx)
    z = np.where(full[ii], epoch.pr_m[ii], epoch.frac_pr_m[ii])
    ct = np.where(full[ii], 0.0, C_M_S * epoch.period_s[ii])
    prn = tuple(epoch.prn[i] for i in idx)
    layout = layout_of(prn)
    rows = _Rows(
        prn=prn,
        z_m=z,
        ct_m=ct,
        cn0_dbhz=epoch.cn0_dbhz[ii],
        eph=store.arrays(ephs),
        layout=layout,
        clk=layout.clock_index(prn),
    )
    return rows, missing


AMBIGUITY_MARGIN = 0.25
"""A fractional row of a system without full rows gets its integer from a fast fix only when
its predicted range puts it at most this many code periods from an integer: the prediction
(orbit at an approximate transmit time, no ionosphere or troposphere, the BeiDou clock for
the system's, whose inter-system bias is metres to kilometres) errs by far less than the
150 km of a quarter millisecond."""


def _with_other_systems(
    epoch: MeasurementEpoch, store: EphemerisStore, rows: _Rows, ctx: _Context, fix: Fix
) -> Fix:
    """The fast fix ``fix`` of ``rows`` joined by the fractional rows of the systems that have
    no full row (which :func:`select_rows` left out): each one's integer N (paper eq. 11)
    from the range predicted at the fix with the fix's BeiDou clock, N = round((rho - c
    dt_sat + b - z) / cT), then every row solved again with those integers held (the rows
    become full, and the fix reports them fractional with their N; its ``gdop_full`` stays
    ``fix``'s, the GDOP of eq. (20) over the full rows it reports, not over the joined rows
    held full). ``fix`` itself when there are none, when a prediction is ambiguous
    (:data:`AMBIGUITY_MARGIN`) or the joined solve fails."""
    have = set(rows.prn)
    todo = [
        i
        for i, p in enumerate(epoch.prn)
        if p not in have
        and not np.isfinite(epoch.pr_m[i])
        and np.isfinite(epoch.frac_pr_m[i])
        and np.isfinite(epoch.period_s[i])
    ]
    if not todo or fix.x_ecef_m is None:
        return fix
    x = np.asarray(fix.x_ecef_m, dtype=float)
    b = fix.clocks_m.get("C", fix.clock_bias_m or 0.0)
    ephs, idx = [], []
    for i in todo:
        e = store.select(epoch.prn[i], ctx.bdt_week, ctx.bdt_sow_s)
        if e is not None:
            ephs.append(e)
            idx.append(i)
    if not ephs:
        return fix
    arr = store.arrays(ephs)
    ii = np.asarray(idx)
    tau = np.full(len(ii), NOMINAL_FLIGHT_TIME_S)
    for _ in range(2):  # transmit time from the geometric range (metres of error, not km)
        sat, clk = sat_pos_clock(arr, ctx.bdt_week, ctx.bdt_sow_s - tau)
        tau = np.linalg.norm(sat - x, axis=1) / C_M_S
    _, pred, _ = ranges(sat, clk, x, arr.omega_e_rad_s)
    ct = C_M_S * epoch.period_s[ii]
    n_float = (pred + b - epoch.frac_pr_m[ii]) / ct
    n = np.rint(n_float)
    if np.any(np.abs(n_float - n) > AMBIGUITY_MARGIN):
        return fix
    pr = epoch.pr_m.copy()
    pr[ii] = epoch.frac_pr_m[ii] + n * ct
    joined, _ = select_rows(replace(epoch, pr_m=pr), store, "fast")
    if joined is None:
        return fix
    again = _solve_rows(joined, ctx)
    if not again.ok:
        return fix
    recovered = {epoch.prn[i]: int(k) for i, k in zip(ii, n, strict=True)}
    return replace(
        again,
        full=tuple(p for p in again.full if p not in recovered),
        fractional=again.fractional + tuple(p for p in recovered if p in again.used),
        ambiguity={**again.ambiguity, **{p: k for p, k in recovered.items() if p in again.used}},
        gdop_full=fix.gdop_full,
    )


def declined(
    epoch: MeasurementEpoch,
    why: Declined,
    solver: Literal["fast", "spp"] = "fast",
) -> Fix:
    """A declined fix for ``epoch`` (``mode="none"``), declined for ``why`` before any row
    was solved (:func:`service.engine.judge.decline_fix` over no rows)."""
    return decline_fix(solver, epoch.gpst_week, epoch.gpst_tow_s, (), (), why)


def solve(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
    solver: Literal["fast", "spp"] = "fast",
    with_sky: bool = False,
) -> Fix:
    """Solve one epoch. Never raises for bad input, geometry or numbers: a fix that cannot
    be trusted comes back as ``mode="none"`` with a reason (and ``reason_code``)."""
    cfg = cfg or SolverConfig()
    iono = iono or IonoSet()
    if not epoch.week_known:
        return declined(epoch, Declined.of(Decline.NO_TIME), solver)
    with np.errstate(all="ignore"):
        try:
            rows, missing = select_rows(epoch, store, solver)
            if rows is None:
                if missing:
                    why = Declined.of(Decline.NO_EPHEMERIS, prns=", ".join(missing))
                else:
                    why = Declined.of(Decline.NO_MEASUREMENTS)
                return declined(epoch, why, solver)
            bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
            ctx = _Context(epoch.gpst_week, epoch.gpst_tow_s, bdt_week, bdt_sow, iono, cfg, solver)
            fix = _solve_rows(rows, ctx)
            if solver == "fast" and fix.ok:
                fix = _with_other_systems(epoch, store, rows, ctx, fix)
            if with_sky and fix.ok:
                fix = replace(fix, sky=sky_view(epoch, store, fix))
        except (np.linalg.LinAlgError, ArithmeticError, ValueError) as exc:
            log.debug(
                "solver failure at GPST %d %.3f", epoch.gpst_week, epoch.gpst_tow_s, exc_info=True
            )
            why = Declined.of(Decline.NUMERICAL, error=type(exc).__name__, message=str(exc))
            return declined(epoch, why, solver)
    return fix


def attempt(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
    start: tuple[float, float, float] | None = None,
) -> Outcome:
    """One solve of ``epoch``'s rows as a candidate of fault exclusion solves it (phase 1
    from ``start`` or the Earth's centre, phase 2, the judgement; no impossible-range check
    and no exclusion of its own): its fix, its failed test, or None when it has no rows or
    the numbers fail. The batch asks this of the candidates it cannot decide itself."""
    with np.errstate(all="ignore"):
        try:
            rows, _ = select_rows(epoch, store, solver)
            if rows is None:
                return None
            bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
            ctx = _Context(epoch.gpst_week, epoch.gpst_tow_s, bdt_week, bdt_sow, iono, cfg, solver)
            return _outcome(_attempt(rows, ctx, None if start is None else np.array(start)))
        except (np.linalg.LinAlgError, ArithmeticError, ValueError):
            return None


def fractionalize(
    epoch: MeasurementEpoch, period_s: float | None = None, keep_full: Sequence[str] | None = None
) -> MeasurementEpoch:
    """Reduce pseudoranges modulo c*T except for ``keep_full`` PRNs (default: the GEOs); T is
    ``period_s``, or each satellite's system's code period when None
    (:attr:`service.core.systems.SystemConstants.code_period_s`, 1 ms for B1I).

    ``numpy.mod`` keeps z + N c T equal to the original to floating-point precision.
    """
    keep = set(keep_full) if keep_full is not None else {p for p in epoch.prn if is_geo(p)}
    mask = np.array([p not in keep for p in epoch.prn], dtype=bool)
    if period_s is None:
        period = np.array([constants_of(p).code_period_s for p in epoch.prn], dtype=float)
    else:
        period = np.full(len(epoch.prn), period_s)
    ct = C_M_S * period
    pr = np.where(mask, np.nan, epoch.pr_m)
    frac = np.where(mask, np.mod(epoch.pr_m, ct), epoch.frac_pr_m)
    per = np.where(mask, period, epoch.period_s)
    return replace(epoch, pr_m=pr, frac_pr_m=frac, period_s=per)
