"""The positioning engine: the Zhao-Cui-Lu fast fix and conventional SPP, one kernel.

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
   error model (and, given ``SolverConfig.height_aid``, one pseudo-observation row of the
   height: :func:`_height_row`), iterated to convergence. Then the integrity checks of
   docs/method.md: the chi-square test of the weighted residuals, fault exclusion, the
   plausible shell, the PDOP gate and the protection levels (:mod:`service.engine.raim`).

With every measurement full and an approximate position given (``x0_ecef_m``), phase 1 has
nothing to resolve and phase 2 starts there: conventional SPP, the same solution.

**One kernel** (:func:`_solve_chunk`) solves every epoch: each step of the iteration is one
set of numpy operations on (epoch, satellite) arrays of a chunk of epochs. The stream solves
a chunk of one (:func:`solve`), ``bdsfix solve`` chunks of :data:`CHUNK_EPOCHS`
(:func:`solve_many`), fault exclusion every candidate of every failed epoch of a stage in one
chunk, and the studies their trials in batches. The unknowns are the rows'
:class:`~service.engine.layout.Layout` (a receiver clock per satellite system); what a
solution becomes (the verdict, the fix or decline, fault exclusion) is written once in
:mod:`service.engine.judge`, in the words of :mod:`service.core.declines`. Each receiver's
geodetic position is computed alone, so an epoch solved alone and the same epoch inside a
chunk give the same bits.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np

from service.core.bds import is_geo
from service.core.constants import C_M_S, NOMINAL_FLIGHT_TIME_S
from service.core.corrections import klobuchar_bds_m, klobuchar_gps_m, saastamoinen_m, sagnac_rotate
from service.core.declines import Decline, Declined, excluded_why
from service.core.ephemeris import EphemerisStore, select_rows
from service.core.geometry import geodetic_points, look_angles
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.settings import setting
from service.core.systems import constants_of
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
from service.engine.layout import BDS_ONLY, Layout, dop, layout_of
from service.engine.raim import Integrity, assess_many

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
    height_aiding: bool = setting(
        False,
        "height aiding for a receiver whose height changes slowly (a car): a pseudo-"
        "observation of the height from the last fixes joins the least squares, its test "
        "and protection levels (service.engine.aiding; never for a first fix)",
        kind="bool",
    )
    height_aid_sigma_m: float = setting(
        3.0, "height aiding: 1-sigma of the held height [m]", kind="float", low=0.0, low_open=True
    )
    height_aid_window_s: float = setting(
        60.0,
        "height aiding: the fixes of this many seconds make the held height [s]",
        kind="float",
        low=0.0,
        low_open=True,
    )
    height_aid_min_fixes: int = setting(
        3, "height aiding: fewest fixes in the window", kind="int", low=1
    )
    height_aid_rate_m_s: float = setting(
        0.1,
        "height aiding: growth of the sigma per second since the newest fix held [m/s]",
        kind="float",
        low=0.0,
    )
    height_aid_grade: float = setting(
        0.05,
        "height aiding: road slope that grows the sigma with the distance moved (0.05: 1 in 20)",
        kind="float",
        low=0.0,
    )
    screen_predicted_m: float = setting(
        0.0,
        "prediction screen: a full range longer by more than this [m] than predicted at the "
        "last fix moved by its Doppler velocity (its system's median residual removed) is "
        "left out before the solve, as reflected (service.engine.aiding; 0: off)",
        kind="float",
        low=0.0,
    )
    # A known approximate position (a reference in studies, the last fix in a stream).
    # With every measurement full the solve is then conventional SPP from it (phase 2
    # alone) when it lies near the Earth (6,000-8,500 km from its centre); otherwise, and
    # with fractional rows, phase 1 starts there. None: the paper's start, the Earth's
    # centre (eq. 3). Either way the least-squares solution is the same.
    x0_ecef_m: tuple[float, float, float] | None = None
    # A pseudo-observation of the receiver's ellipsoidal height, (h [m], sigma [m]): one more
    # row of phase 2's least squares and of its test and protection levels
    # (:func:`_height_row`; service.engine.aiding builds it from past fixes). None: no row.
    # An :class:`EpochAids`: each epoch's own (a batch of epochs with different aids).
    height_aid: tuple[float, float] | EpochAids | None = None


@dataclass(frozen=True, eq=False, slots=True)
class EpochAids:
    """A height aid per epoch, (h [m], sigma [m]) by the epoch's GPST (week, tow), for
    :attr:`SolverConfig.height_aid` of a batch whose epochs hold different aids (every
    epoch of the batch must have one, and no two the same time): each epoch's row is the
    one a solve of that epoch alone with its aid has."""

    by_time: dict[tuple[int, float], tuple[float, float]]

    def of(self, epochs: Iterable[MeasurementEpoch]) -> tuple[np.ndarray, np.ndarray]:
        """The aids' heights and sigmas (e,) of ``epochs``."""
        got = [self.by_time[(ep.gpst_week, ep.gpst_tow_s)] for ep in epochs]
        return np.array([h for h, _ in got]), np.array([s for _, s in got])


def _aids_of(
    cfg: SolverConfig, epochs: Sequence[MeasurementEpoch], sel: np.ndarray
) -> tuple[float, float] | tuple[np.ndarray, np.ndarray] | None:
    """The height aid of the epochs ``sel`` of ``epochs``: ``cfg.height_aid`` itself (one
    for all, or None), or each epoch's (:class:`EpochAids`) as arrays."""
    aid = cfg.height_aid
    if isinstance(aid, EpochAids):
        return aid.of(epochs[int(i)] for i in sel)
    return aid


def _aid_at(
    aid: tuple[float, float] | tuple[np.ndarray, np.ndarray], ix: _Index
) -> tuple[float, float] | tuple[np.ndarray, np.ndarray]:
    """``aid`` of the epochs ``ix`` (a scalar aid is every epoch's)."""
    h, s = aid
    if isinstance(h, np.ndarray) and isinstance(s, np.ndarray):
        return h[ix], s[ix]
    return aid


def derive_beta(period_s: float, range_error_m: float) -> float:
    """Gate threshold beta = alpha / max|d rho| with alpha = c T / 2 (paper eq. 21).

    For T = 1 ms and a 50 m 3-sigma range error this is 2998, the paper's 3000.
    """
    return C_M_S * period_s / 2.0 / range_error_m


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
    sat = sagnac_rotate(sat0_ecef_m, np.sqrt(linalg.einsum(dot, d, d)) / C_M_S, omega_e_rad_s)
    d = sat - x
    rho = np.sqrt(linalg.einsum(dot, d, d))
    return d / rho[..., None], rho - C_M_S * clock_s, sat


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


GROSS_SPREAD_M = 25_000e3
"""Largest possible difference of two full B1I pseudoranges of one epoch [m]. They share
the receiver clock, so they differ by geometry and satellite clocks only: from a MEO at
zenith (~21,500 km) to a GEO/IGSO at the horizon (~41,700 km) is ~20,200 km for a user on
the ground or up to 1000 km above it, plus satellite clocks (< 1 ms, 300 km). A full
pseudorange further than this from the epoch's median is impossible, not merely faulty."""


def measurement_sigma_m(
    el_rad: np.ndarray,
    cn0_dbhz: np.ndarray | None,
    iono_m: np.ndarray | None,
    tropo_m: np.ndarray | None,
    cfg: SolverConfig,
    cn0_var_m2: np.ndarray | None = None,
) -> np.ndarray:
    """Standard deviation [m] of each pseudorange's error (model in :class:`SolverConfig`);
    ``cn0_dbhz`` None: no C/N0 (the reference C0); ``cn0_var_m2``: the rows' C/N0 term,
    :func:`cn0_variance_m2` (None: computed here; given, ``cn0_dbhz`` is not read).

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
    if cn0_var_m2 is None:
        cn0_var_m2 = cn0_variance_m2(np.asarray(cn0_dbhz, dtype=float), cfg)
    var = var + cn0_var_m2
    var = var + cfg.sigma_sis_m**2
    if iono_m is None:  # no broadcast model applied: the whole delay is error
        var = var + (cfg.iono_unmodelled_m * _obliquity(el_rad)) ** 2
    else:
        left = (cfg.iono_error_ratio * iono_m) ** 2
        # NaN: no model at that row's receiver (above 100 km); (a sum of squares is finite
        # only if every square is: one reduction, not two)
        if not math.isfinite(np.add.reduce(left, axis=None)):
            unmodelled = (cfg.iono_unmodelled_m * _obliquity(el_rad)) ** 2
            left = np.where(np.isfinite(iono_m), left, unmodelled)
        var = var + left
    if tropo_m is not None:
        var = var + (cfg.tropo_error_m / (s + 0.1)) ** 2
    return np.sqrt(var)


def cn0_variance_m2(cn0_dbhz: np.ndarray, cfg: SolverConfig) -> np.ndarray:
    """The C/N0 term of :func:`measurement_sigma_m`, c^2 10^((C0 - C/N0) / 10) [m^2] (C0
    where a row has no C/N0): it depends on the measurements alone, so the kernel computes
    it once per chunk, not once per iteration."""
    cn0 = np.where(np.isfinite(cn0_dbhz), cn0_dbhz, cfg.cn0_ref_dbhz)
    return cfg.sigma_cn0_m**2 * 10.0 ** ((cfg.cn0_ref_dbhz - cn0) / 10.0)


def _obliquity(el_rad: np.ndarray) -> np.ndarray:
    """Slant factor of a thin ionospheric shell at 350 km (IS-GPS-200 20.3.3.5.2.5 form)."""
    ratio = 6378.0 / (6378.0 + 350.0) * np.cos(el_rad)
    return 1.0 / np.sqrt(1.0 - ratio**2)


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
    on its own carrier. One epoch or a batch, as :func:`delays` (the kernel, and the
    coarse-time fix's candidates). Where every problem has the same system in each column
    (one epoch, a batch of one, the coarse-time fix's candidates of one epoch), each model
    is computed on its own system's columns only; otherwise both on every row and each
    row's taken (the same bits either way: each row's delay depends on its own figures
    alone)."""
    model = None if models is None else models.bds
    args = (lat_rad, lon_rad, alt_m, el_rad, az_rad, bdt_sow_s, carrier_hz)
    mixed = models is not None and models.other is not model and not bds_rows.all()
    if models is None or not mixed:
        return delays(*args, model, cfg)
    cols = _shared_columns(bds_rows)
    if cols is None:
        iono, tropo = delays(*args, model, cfg)
        if iono is not None:
            other, _ = delays(*args, models.other, replace(cfg, tropo="off"))
            if other is not None:
                iono = np.where(bds_rows, iono, other)
        return iono, tropo
    _, tropo = delays(*args, None, cfg)
    car = np.broadcast_to(carrier_hz, np.shape(el_rad))
    no_tropo = replace(cfg, tropo="off")
    iono = np.empty(np.shape(el_rad))
    for m, c in ((model, cols), (models.other, ~cols)):
        if c.any():
            part = (el_rad[..., c], az_rad[..., c], bdt_sow_s, car[..., c])
            io = delays(lat_rad, lon_rad, alt_m, *part, m, no_tropo)[0]
            if io is None:  # one receiver above 100 km: no ionosphere (delays)
                return None, tropo
            iono[..., c] = io
    return iono, tropo


def _shared_columns(bds_rows: np.ndarray) -> np.ndarray | None:
    """``bds_rows`` (s,) or (e, s) as one (s,) column mask when every problem has the same
    system in each column (e = 1, or the rows alike), else None."""
    b = np.asarray(bds_rows, dtype=bool)
    if b.ndim == 1:
        return b
    if b.ndim == 2 and (len(b) == 1 or bool((b == b[0]).all())):
        return b[0]
    return None


def iono_m(
    model: KlobucharParams,
    lat_rad: float | np.ndarray,
    lon_rad: float | np.ndarray,
    el_rad: np.ndarray,
    az_rad: np.ndarray,
    bdt_sow_s: float | np.ndarray,
    carrier_hz: np.ndarray,
) -> np.ndarray:
    """Klobuchar delay [m] of rows on ``carrier_hz`` by ``model``'s form: BDS (ICD B1I
    5.2.4.7) or GPS (IS-GPS-200 20.3.3.5.2.5, on GPS time), as :func:`delays` applies it."""
    if model.system == "BDS":
        return klobuchar_bds_m(model, lat_rad, lon_rad, el_rad, az_rad, bdt_sow_s, carrier_hz)
    gpst_tow = bdt_sow_s + BDT_GPST_OFFSET_S
    return klobuchar_gps_m(model, lat_rad, lon_rad, el_rad, az_rad, gpst_tow, carrier_hz)


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
    if (
        isinstance(alt_m, np.ndarray)
        and alt_m.shape == (1,)
        and isinstance(el_rad, np.ndarray)
        and el_rad.ndim == 2
        and len(el_rad) == 1
    ):
        # a batch of one: its receiver's figures as floats and its rows as one epoch's (the
        # same arithmetic, without broadcasting's per-call cost), in the batch's shapes
        alt = float(alt_m[0])
        car = carrier_hz  # (given per row or per epoch)
        if not (isinstance(car, np.ndarray) and car.shape == el_rad.shape):
            car = np.broadcast_to(car, el_rad.shape)
        one = delays(
            float(np.asarray(lat_rad)[0]),
            float(np.asarray(lon_rad)[0]),
            alt,
            el_rad[0],
            az_rad[0],
            float(np.asarray(bdt_sow_s)[0]),
            car[0],
            model,
            cfg,
        )
        io, tr = (None if v is None else v[None] for v in one)
        if model is not None and io is None:  # above 100 km: NaN, as a batch gives
            io = np.full(el_rad.shape, np.nan)
        return io, tr
    batch = not isinstance(alt_m, float) and np.ndim(alt_m) > 0
    if batch:  # receivers (e,) against rows (e, s)
        lat_rad, lon_rad = np.asarray(lat_rad)[:, None], np.asarray(lon_rad)[:, None]
        alt_m, bdt_sow_s = np.asarray(alt_m)[:, None], np.asarray(bdt_sow_s)[:, None]
    iono = None
    if model is not None and (batch or alt_m < 100e3):
        iono = iono_m(model, lat_rad, lon_rad, el_rad, az_rad, bdt_sow_s, carrier_hz)
        if batch and not np.all(alt_m < 100e3):
            iono = np.where(alt_m < 100e3, iono, np.nan)
    tropo = saastamoinen_m(lat_rad, alt_m, el_rad) if cfg.tropo != "off" else None
    return iono, tropo


def total_delay(iono_m: np.ndarray | None, tropo_m: np.ndarray | None) -> np.ndarray | float:
    """The delays to take from the measured ranges: ionosphere (NaN: not modelled, 0) plus
    troposphere (None: not applied)."""
    if iono_m is None:
        return 0.0 if tropo_m is None else 0.0 + tropo_m
    # NaN (a batch's epoch above 100 km): no model there, nothing to take
    io = iono_m if iono_m.ndim == 1 else np.where(np.isfinite(iono_m), iono_m, 0.0)
    # (0.0 + io is io: a delay is positive, or NaN, or 0 where there is no model)
    return io if tropo_m is None else io + tropo_m


def sky_view(epoch: MeasurementEpoch, store: EphemerisStore, fix: Fix) -> tuple[SatView, ...]:
    """Satellites of ``epoch`` with an ephemeris, seen from the fix (empty without one)."""
    if fix.x_ecef_m is None:
        return ()
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    ephs, idx = select_rows(store, epoch.prn, range(len(epoch.prn)), bdt_week, bdt_sow)
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


def declined(
    epoch: MeasurementEpoch,
    why: Declined,
    solver: Literal["fast", "spp"] = "fast",
) -> Fix:
    """A declined fix for ``epoch`` (``mode="none"``), declined for ``why`` before any row
    was solved (:func:`service.engine.judge.decline_fix` over no rows)."""
    return decline_fix(solver, epoch.gpst_week, epoch.gpst_tow_s, (), (), why)


# ---- the kernel: epochs x satellites ---------------------------------------------------------

CHUNK_EPOCHS = 256
"""Epochs ``bdsfix solve`` hands the kernel at once: large enough that numpy's per-call cost
is spread thin, small enough that the arrays stay in cache and output keeps flowing."""

_EPH_FIELDS = tuple(f for f in EphemerisArrays.__dataclass_fields__ if f != "prn")


def _with_full_systems(epoch: MeasurementEpoch, full: np.ndarray, fracok: np.ndarray) -> np.ndarray:
    """The fast fix's fractional rows of ``epoch``: when some system has a full row, only the
    fractional rows of the systems that have one (phase 1 resolves integers against clocks
    estimated from full rows; a system whose rows are all fractional has none, and its rows
    join afterwards, :func:`_with_other_systems`)."""
    prn = epoch.prn
    with_full = {prn[i][:1] for i in full.nonzero()[0].tolist()}
    if with_full and any(p[:1] not in with_full for p in prn):
        return fracok & np.array([p[:1] in with_full for p in prn], dtype=bool)
    return fracok


class _Chunk:
    """The rows of a chunk of epochs as (epoch, slot) arrays; ``valid`` marks real rows.

    A row is a measurement the solver uses (SPP: full; fast: full and fractional,
    :func:`_with_full_systems`) whose satellite has an ephemeris; ``missing`` lists, per
    epoch, the usable measurements without one. A full pseudorange further than
    :data:`GROSS_SPREAD_M` from its epoch's median is impossible, not merely faulty: it is
    not a row, and ``gross`` says why (``Fix.excluded``); ``screen=False`` (fault
    exclusion's candidates, made from rows already screened) keeps every row."""

    def __init__(
        self,
        epochs: Sequence[MeasurementEpoch],
        store: EphemerisStore,
        solver: Literal["fast", "spp"],
        screen: bool = True,
    ) -> None:
        n_e = len(epochs)
        self.epochs = epochs
        bdt = [gpst_to_bdt(ep.gpst_week, ep.gpst_tow_s) for ep in epochs]
        self.bdt_week = np.array([w for w, _ in bdt], dtype=float)
        self.bdt_sow = np.array([s for _, s in bdt])
        self.missing: list[list[str]] = [[] for _ in range(n_e)]
        self.gross: list[dict[str, str]] = [{} for _ in range(n_e)]
        # per epoch: the measurements of systems without a full row (fast: they join later)
        self.others = [False] * n_e
        table: dict[int, int] = {}
        unique: list[Ephemeris] = []
        eph_idx: list[int] = []
        owner: list[int] = []
        cols: list[tuple[float, float, float]] = []  # z, c*T (0: full), C/N0
        prns: list[str] = []
        for k, ep in enumerate(epochs):
            full = np.isfinite(ep.pr_m)
            use = full
            if solver == "fast":
                fracok = ~full & np.isfinite(ep.frac_pr_m) & np.isfinite(ep.period_s)
                if fracok.any():
                    kept = _with_full_systems(ep, full, fracok)
                    self.others[k] = bool((fracok & ~kept).any())
                    use = full | kept
            week, sow = bdt[k]
            zf, zq = ep.pr_m.tolist(), ep.frac_pr_m.tolist()
            per, cn0 = ep.period_s.tolist(), ep.cn0_dbhz.tolist()
            for i in use.nonzero()[0].tolist():
                prn = ep.prn[i]
                e = store.select(prn, week, sow)
                if e is None:
                    self.missing[k].append(prn)
                    continue
                u = table.get(id(e))
                if u is None:
                    u = table[id(e)] = len(unique)
                    unique.append(e)
                eph_idx.append(u)
                owner.append(k)
                prns.append(prn)
                z = zf[i]
                cols.append((z, 0.0, cn0[i]) if z == z else (zq[i], C_M_S * per[i], cn0[i]))
        flat = np.array(cols, dtype=float).reshape(-1, 3)
        own = np.array(owner, dtype=np.intp)
        gross = self._gross(n_e, own, flat, prns, cols) if screen else None
        if gross is not None:
            keep = ~gross
            flat, own = flat[keep], own[keep]
            prns = [p for p, g in zip(prns, gross.tolist(), strict=True) if not g]
            eph_idx = [u for u, g in zip(eph_idx, gross.tolist(), strict=True) if not g]
        if not unique:
            unique.append(_placeholder())
        arr = store.arrays(unique)
        if n_e == 1 and flat.shape[0]:  # one epoch: its rows are its slots
            n_s = flat.shape[0]
            self.valid = ~np.zeros((1, n_s), dtype=bool)  # (np.ones costs more)
            cols_t = flat.T
            self.z, self.ct, self.cn0 = cols_t[0:1].copy(), cols_t[1:2].copy(), cols_t[2:3].copy()
            self.prn = [tuple(prns)]
            if eph_idx == list(range(len(unique))):  # each row its own set, in order
                self.eph = _gather(arr, None)
            else:
                self.eph = _gather(arr, np.array([eph_idx], dtype=np.intp))
        else:
            counts = np.bincount(own, minlength=n_e)
            n_s = max(1, int(counts.max()) if n_e else 1)
            first = np.concatenate([[0], np.cumsum(counts)[:-1]]) if n_e else np.zeros(0, int)
            slot = np.arange(len(own)) - first[own]
            at = (own, slot)
            self.valid = np.zeros((n_e, n_s), dtype=bool)
            self.valid[at] = True
            self.z = np.zeros((n_e, n_s))
            self.z[at] = flat[:, 0]
            self.ct = np.zeros((n_e, n_s))
            self.ct[at] = flat[:, 1]
            self.cn0 = np.full((n_e, n_s), np.nan)
            self.cn0[at] = flat[:, 2]
            ends = np.cumsum(counts).tolist()
            self.prn = [tuple(prns[a:b]) for a, b in zip([0, *ends[:-1]], ends, strict=True)]
            idx = np.zeros((n_e, n_s), dtype=np.intp)
            idx[at] = eph_idx
            self.eph = _gather(arr, idx)
        self.frac = self.valid & (self.ct > 0)
        self.full = self.valid & ~self.frac
        self.has_frac = bool(self.frac.any())  # (no fractional row: no integers to add)
        layouts = {layout_of(self.prn[0])} if n_e == 1 else {layout_of(p) for p in self.prn if p}
        # the unknowns: one layout for the chunk (None: its epochs' rows differ in their
        # systems, and :func:`_outcomes` solves each layout's epochs as a chunk of their own)
        self.layout: Layout | None = layouts.pop() if len(layouts) == 1 else None
        if not layouts and self.layout is None:
            self.layout = BDS_ONLY
        self.cix = np.zeros((n_e, n_s), dtype=np.intp)  # each row's clock (padding: 0)
        if self.layout is not None and self.layout.n_clocks > 1:
            for k, ps in enumerate(self.prn):
                self.cix[k, : len(ps)] = self.layout.clock_index(ps)

    def _gross(
        self,
        n_e: int,
        own: np.ndarray,
        flat: np.ndarray,
        prns: list[str],
        cols: list[tuple[float, float, float]],
    ) -> np.ndarray | None:
        """The flat rows (``flat``, or the same as tuples, ``cols``) that are impossible
        ranges (None: none), recorded in ``gross``."""
        if n_e == 1:  # one epoch: the same median and deviations, in floats
            zl = sorted(c[0] for c in cols if c[1] == 0.0)
            n = len(zl)
            if n < 2 or zl[-1] - zl[0] <= GROSS_SPREAD_M:  # (no row further from the median)
                return None
            med = 0.5 * (zl[(n - 1) // 2] + zl[n // 2])
            devs = [abs(c[0] - med) for c in cols]
            flags = [
                c[1] == 0.0 and not (d <= GROSS_SPREAD_M) for c, d in zip(cols, devs, strict=True)
            ]
            if not any(flags):
                return None
            for i, flag in enumerate(flags):
                if flag:
                    self.gross[0][prns[i]] = excluded_why("gross", dev_km=devs[i] / 1e3)
            return np.array(flags, dtype=bool)
        full = flat[:, 1] == 0.0
        z = flat[:, 0]
        n_full = np.bincount(own[full], minlength=n_e)
        if not (n_full >= 2).any():
            return None
        # each epoch's median of its full rows: sort by (epoch, z), full rows first
        order = np.lexsort((z, ~full, own))
        start = np.searchsorted(own[order], np.arange(n_e))
        lo = start + np.maximum(n_full - 1, 0) // 2
        hi = start + n_full // 2
        zs = z[order]
        median = 0.5 * (zs[np.minimum(lo, len(z) - 1)] + zs[np.minimum(hi, len(z) - 1)])
        dev = np.abs(z - median[own])
        bad = full & (n_full[own] >= 2) & ~(dev <= GROSS_SPREAD_M)
        if not bad.any():
            return None
        for i in bad.nonzero()[0].tolist():
            self.gross[int(own[i])][prns[i]] = excluded_why("gross", dev_km=dev[i] / 1e3)
        return bad


def _placeholder() -> Ephemeris:
    z = 0.0
    return Ephemeris("C01", 0, z, z, z, z, z, 6493.0, z, z, z, z, z, z, z, z, z, z, z, z, z, z)


def _gather(cols: EphemerisArrays, idx: np.ndarray | None) -> EphemerisArrays:
    """Ephemeris columns indexed by ``idx`` (any shape; None: the columns as one epoch's
    rows, views, kept for the next epoch with the same sets); ``prn`` is not carried."""
    if idx is None:
        hit = _AS_ONE_EPOCH.get(id(cols))
        if hit is not None and hit[0] is cols:
            return hit[1]
        kw = {name: getattr(cols, name)[None] for name in _EPH_FIELDS}
        one = EphemerisArrays(prn=(), **kw)
        if len(_AS_ONE_EPOCH) >= 64:
            _AS_ONE_EPOCH.clear()
        _AS_ONE_EPOCH[id(cols)] = (cols, one)
        return one
    kw = {name: getattr(cols, name)[idx] for name in _EPH_FIELDS}
    return EphemerisArrays(prn=(), **kw)


_AS_ONE_EPOCH: dict[int, tuple[EphemerisArrays, EphemerisArrays]] = {}
""":func:`_gather` of a set's columns as one epoch's rows, by the set (the stream solves
the same satellites' sets epoch after epoch; the store memoises the sets' columns)."""


def _orbits(ch: _Chunk, sel: _Index, n_int: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Satellite positions and clocks at the transmit times of eqs. (4)-(5) for epochs
    ``sel`` with integers ``n_int`` (None: every one 0): they depend on the receive time and
    z + N cT only, not on the receiver state."""
    # every epoch (sel is sorted and unique): the chunk's columns as they are, not copied
    eph = ch.eph
    if not isinstance(sel, slice) and len(sel) != len(ch.z):
        eph = _gather(ch.eph, sel)
    zn = ch.z[sel] if n_int is None else ch.z[sel] + n_int * ch.ct[sel]
    return transmit_orbits(eph, ch.bdt_week[sel, None], ch.bdt_sow[sel, None], zn)


def transmit_orbits(
    eph: EphemerisArrays, bdt_week: int | np.ndarray, bdt_sow: float | np.ndarray, z_m: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Satellite positions and clocks at the transmit times of full pseudoranges ``z_m``
    received at BDT ``bdt_week`` + ``bdt_sow`` (paper eqs. 4-5: the receive time less the
    flight time z/c, less the satellite clock's af0 + af1 (t - toc) there)."""
    t1 = bdt_sow - z_m / C_M_S
    t_tx = t1 - (eph.af0_s + eph.af1_s_s * (t1 - eph.toc_sow_s))
    return sat_pos_clock(eph, bdt_week, t_tx)


def _row_clocks(b: np.ndarray, cix: np.ndarray) -> np.ndarray:
    """Each row's receiver clock [m]: the clocks ``b`` (e, clocks) at the rows' clock
    indices ``cix`` (e, s); with one clock, ``b`` itself (it broadcasts over the rows)."""
    if b.shape[1] == 1:
        return b
    return b[np.arange(len(b))[:, None], cix]  # (np.take_along_axis: the same, at more cost)


LsqStep = tuple[np.ndarray, np.ndarray | None, np.ndarray | None]
"""The least-squares steps of some epochs (e, params), the epochs whose system is singular
(None: none) and the epochs whose step is finite (None: every one's)."""


def normal_matrix(h: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """H^T W and the normal matrix H^T W H (e, p, p) of designs ``h`` (e, n, p) with row
    weights ``w`` (e, n) (paper eq. 10): the matrix :func:`lsq_step` solves with."""
    ht = h.swapaxes(-1, -2) * w[:, None, :]
    return ht, ht @ h


def lsq_step(h: np.ndarray, dz: np.ndarray, w: np.ndarray) -> LsqStep:
    """Per epoch, the weighted least-squares step (H^T W H)^-1 H^T W dz (paper eqs. 10 and
    16) over rows with w > 0 (rows with w = 0 are out), through the normal equations (a
    handful of unknowns, where an SVD per iteration costs more than the rest of the
    iteration). An epoch whose normal matrix is singular takes numpy's minimum-norm least
    squares; the second value marks the epochs that fails for too (None: none), whose step
    is NaN; the third, the epochs whose step is finite (None: all of them)."""
    ht, a = normal_matrix(h, w)
    rhs = ht @ dz[..., None]
    try:
        x, finite = linalg.solve_finite(a, rhs)
        step = x[..., 0]
        return step, None, None if finite else np.isfinite(step).all(axis=1)
    except np.linalg.LinAlgError:
        pass
    out = np.full(dz.shape[:1] + h.shape[-1:], np.nan)
    bad = np.zeros(len(dz), dtype=bool)
    for k in range(len(dz)):
        try:
            out[k] = linalg.solve(a[k], rhs[k])[:, 0]
        except np.linalg.LinAlgError:
            sw = np.sqrt(w[k])
            try:
                out[k] = np.linalg.lstsq(h[k] * sw[:, None], dz[k] * sw, rcond=None)[0]
            except np.linalg.LinAlgError:
                bad[k] = True
    return out, bad, np.isfinite(out).all(axis=1)


def _add(a: np.ndarray, ix: _Index, v: np.ndarray | int) -> None:
    """``a[ix] += v`` in place; for every epoch (a slice) without indexing (a[:] += v would
    copy the sum onto itself)."""
    if isinstance(ix, slice):
        a += v
    else:
        a[ix] += v


def _where(
    near: np.ndarray | None, value: np.ndarray | float, far: np.ndarray | float
) -> np.ndarray | float:
    """``value`` for the epochs ``near`` the Earth (e, 1), ``far`` for the others; ``value``
    itself (the same object, no copy) when every epoch is near (``near`` None)."""
    return value if near is None else np.where(near, value, far)


_Local = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]
"""Latitude, longitude, height (e,), elevation, azimuth (e, s) and ENU rotation (e, 3, 3)."""


def _local(x: np.ndarray, sat: np.ndarray) -> _Local:
    """Geodetic latitude, longitude, height of receivers ``x`` (e, 3), elevation and azimuth
    of their satellites ``sat`` (e, s, 3), and the receivers' east-north-up rotations: each
    receiver alone (:func:`service.core.geometry.geodetic_points`)."""
    lat, lon, alt, rot = geodetic_points(x)
    enu = (sat - x[:, None, :]) @ rot.swapaxes(-1, -2)
    el = np.arctan2(enu[..., 2], np.hypot(enu[..., 0], enu[..., 1]))
    az = np.mod(np.arctan2(enu[..., 0], enu[..., 1]), 2 * np.pi)
    return lat, lon, alt, el, az, rot


class _Decided:
    """The epochs of a chunk whose outcome is known, and the declines decided before a
    solution is judged: (epoch, why, fields of the declined fix)."""

    def __init__(self, n_e: int) -> None:
        self.out: list[Outcome] = [None] * n_e
        self.declines: list[tuple[int, Declined, dict[str, object]]] = []

    def decline(self, e: int, why: Declined, **fields: object) -> None:
        self.declines.append((e, why, fields))


_Index = slice | np.ndarray
"""Epochs of a chunk: all of them (a slice, whose arrays are views) or some (indices)."""

_MERIT_SLACK = 1.0 + 1e-6
"""Phase 1's line search takes a step unless it raises the full rows' sum of squared
residuals by more than this factor. A full row with a gross fault leaves a residual of
hundreds of kilometres, and near the fixed point of the iteration (eq. 14) the step, made
with the line-of-sight design (eq. 9, the Earth's rotation during the flight left out),
is metres that change that sum by parts in 1e8: it is a step of the paper's iteration,
not a divergence, and halving it never ends (a 1 ms error on GEO C01, HKSC). A step from
the Earth's centre that overshoots raises the sum many times over."""


def _cost(
    ch: _Chunk, rows: _Index, pred: np.ndarray, b: np.ndarray, fullw: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The residuals z - pred - b of epochs ``rows`` (no corrections, no integers) and the
    sum of squares of their full rows: phase 1's line-search merit. Without fractional
    rows the residuals are the next iteration's dz (eqs. 7-8)."""
    resid = ch.z[rows] - pred - _row_clocks(b, ch.cix[rows])
    r = resid * fullw[rows]
    return resid, linalg.einsum("es,es->e", r, r)


@dataclass(slots=True, eq=False)
class _Trial:
    """Phase 1's iterate of some epochs after a step (:func:`_trial`)."""

    x: np.ndarray
    b: np.ndarray
    n_int: np.ndarray
    moves: np.ndarray | None  # per epoch, whether its integers moved (None: no fractional rows)
    moved: bool  # any integer moved
    sat0: np.ndarray
    clk: np.ndarray
    los: np.ndarray
    pred: np.ndarray
    sat: np.ndarray
    resid: np.ndarray
    cost: np.ndarray

    def take(self, at: np.ndarray, part: _Trial, pick: np.ndarray) -> None:
        """Rows ``at`` of this trial from rows ``pick`` of ``part`` (copied first: this
        trial's arrays may be views of the iterate)."""
        for name in _TRIAL_ARRAYS:
            mine, theirs = getattr(self, name), getattr(part, name)
            if mine is None or theirs is None:
                continue
            mine = mine.copy()
            mine[at] = theirs[pick]
            setattr(self, name, mine)
        self.moved = self.moved or part.moved


_TRIAL_ARRAYS = ("x", "b", "n_int", "moves", "sat0", "clk", "los", "pred", "sat", "resid", "cost")


def _trial(
    ch: _Chunk,
    st: _Iterate,
    rows: _Index,
    sel: np.ndarray,
    step: np.ndarray,
    dn_m: np.ndarray | None,
    lp: np.ndarray | None,
    ct1: np.ndarray,
    omega: np.ndarray,
    fullw: np.ndarray,
    layout: Layout,
) -> _Trial:
    """Phase 1's iterate of epochs ``rows`` (indices ``sel``) after their step ``step``
    (x, clocks) times ``lp`` (None: the whole step): the integers move by the rounded
    ambiguity steps ``dn_m`` [m] (eq. 13; None: no fractional rows), the orbits are computed
    again for the epochs whose integers moved (eqs. 4-5), the ranges and the merit."""
    n_par = layout.n_params
    sx, sb = step[:, :3], step[:, 3:n_par]
    if lp is not None:
        sx, sb = lp[:, None] * sx, lp[:, None] * sb
    xp, bp = st.x[rows] + sx, st.b[rows] + sb
    s0, ck, ni = st.sat0[rows], st.clk[rows], st.n_int[rows]
    mv = None
    moved = False
    if dn_m is not None:
        dm = dn_m if lp is None else lp[:, None] * dn_m
        dn = np.where(ch.frac[rows], np.rint(dm / ct1[rows]), 0.0)
        mv = np.asarray(dn.any(axis=1))
        m = mv.nonzero()[0]
        if m.size:
            moved = True
            ni = ni + dn
            if m.size == len(mv):  # every epoch's integers moved: their orbits, no copies
                s0, ck = _orbits(ch, rows, ni)
            else:
                s0, ck = s0.copy(), ck.copy()
                s0[m], ck[m] = _orbits(ch, sel[m], ni[m])
    lo, pr, sa = ranges(s0, ck, xp, omega[rows])
    return _Trial(xp, bp, ni, mv, moved, s0, ck, lo, pr, sa, *_cost(ch, rows, pr, bp, fullw))


def _solve_chunk(
    ch: _Chunk,
    layout: Layout,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
    start: np.ndarray | None = None,
) -> list[Outcome]:
    """The outcome of each epoch of the chunk, whose rows have the unknowns ``layout`` (a
    clock per system among them): its fix or decline, or its failed chi-square test
    (:class:`~service.engine.judge.Failed`). ``start`` (e, 3): where each epoch's phase 1
    starts (NaN rows, or None for every epoch: ``cfg.x0_ecef_m``, else the Earth's centre).

    Phase 1 (paper eqs. 3-16), every epoch in lockstep, an epoch that has converged keeping
    its state: the x/b step is the least-squares step over the full rows; each fractional
    row has its own ambiguity column in eq. (11), so its residual is absorbed by
    dN_j = h_j . [dx, db] - dz_j (in metres, rounded in units of c*T by eq. 13), which is
    the solution of the augmented system of eq. (10) without forming it. A step that
    increases the full rows' residual (by more than :data:`_MERIT_SLACK`) is halved (from
    the Earth's centre, near-equatorial GEOs make the plain step overshoot). The
    satellites' orbits (eqs. 4-5) depend on the integers only: an epoch's are computed
    again only when a step moves its integers. Then
    the GEO-GDOP gate (eqs. 12, 20-21) and the fixed-integer correction (eqs. 15-16).
    Phase 2 (:func:`_phase2`) adds the mask, corrections and weights, and judges."""
    n_e, n_s = ch.z.shape
    d = _Decided(n_e)
    n_full = ch.full.sum(axis=1)
    n_frac = ch.frac.sum(axis=1)
    n_rows = n_full + n_frac
    n_par, n_clk, cix = layout.n_params, layout.n_clocks, ch.cix
    # no rows: no ephemeris, no measurement, or every one an impossible range
    for e in [] if n_rows.all() else (n_rows == 0).nonzero()[0].tolist():
        if ch.gross[e]:  # every row an impossible range: none left to solve
            why = Declined.of(Decline.TOO_FEW_FULL, n_full=0, n_frac=0, need=n_par)
            d.decline(e, why)
        elif ch.missing[e]:
            d.decline(e, Declined.of(Decline.NO_EPHEMERIS, prns=", ".join(ch.missing[e])))
        else:
            d.decline(e, Declined.of(Decline.NO_MEASUREMENTS))
    too_few = (n_rows > 0) & (n_full < n_par)
    for e in too_few.nonzero()[0].tolist() if too_few.any() else []:
        n_f, n_q = int(n_full[e]), int(n_frac[e])
        d.decline(e, Declined.of(Decline.TOO_FEW_FULL, n_full=n_f, n_frac=n_q, need=n_par))
    ok = (n_rows > 0) & ~too_few

    def design(los_: np.ndarray, rows: _Index) -> np.ndarray:
        if n_clk == 1:  # one clock column: no clock indices to gather
            return layout.design(los_)
        return layout.design(los_, cix[rows])

    # every row full and a position known: conventional SPP, phase 2 alone from there (the
    # same solution as from the Earth's centre, see SolverConfig.x0_ecef_m); with
    # fractional rows phase 1 starts there
    x = np.zeros((n_e, 3))
    direct = np.zeros(n_e, dtype=bool)
    if cfg.x0_ecef_m is not None:
        x[:] = cfg.x0_ecef_m
        if 6.0e6 < math.sqrt(sum(v * v for v in cfg.x0_ecef_m)) < 8.5e6:
            direct = ok & (n_frac == 0)  # (a start far from the Earth: phase 1 from it)
    if start is not None:
        x = np.where(np.isnan(start) | direct[:, None], x, start)
    b = np.zeros((n_e, n_clk))
    n_int = np.zeros((n_e, n_s))
    iters = np.zeros(n_e, dtype=int)
    sat0, clk = _orbits(ch, slice(None), None)
    omega = ch.eph.omega_e_rad_s
    los, pred, sat = ranges(sat0, clk, x, omega)
    fullw = ch.full.astype(float)

    # ---- phase 1: the paper's iteration -----------------------------------------------------
    has_frac = ch.has_frac
    st = _Iterate(x, b, n_int, iters, sat0, clk, los, pred, sat)
    resid, cost = _cost(ch, slice(None), pred, b, fullw)
    one = ok & ~direct
    active = one.copy()
    singular = np.zeros(n_e, dtype=bool)
    ct1 = np.where(ch.frac, ch.ct, 1.0) if has_frac else ch.ct
    zn = ch.z  # z + N c T of each row (eq. 5), as the integers move
    for _it in range(cfg.max_iter):
        sel = active.nonzero()[0]
        if not sel.size:
            break
        whole = sel.size == n_e
        ix: _Index = slice(None) if whole else sel
        st.iters += active
        # (without fractional rows zn is z: dz is the merit's residuals)
        dz = zn[ix] - st.pred[ix] - _row_clocks(st.b[ix], cix[ix]) if has_frac else resid[ix]
        h = design(st.los[ix], ix)
        step, bad, _ = lsq_step(h, dz, fullw[ix])  # eq. (10) over the full rows
        if bad is not None:
            singular[sel[bad]] = True
            active[sel[bad]] = False
            sel, dz, h, step = sel[~bad], dz[~bad], h[~bad], step[~bad]
            whole, ix = False, sel
            if not sel.size:
                continue
        # each fractional row's ambiguity step [m]: its residual after the x/b step
        dn_m = linalg.einsum("esk,ek->es", h, step) - dz if has_frac else None
        got = _trial(ch, st, ix, sel, step, dn_m, None, ct1, omega, fullw, layout)
        accept = got.cost <= cost[ix] * _MERIT_SLACK
        if not accept.all():  # (an epoch without a finite merit takes any step)
            accept |= ~np.isfinite(cost[ix])
        lam: np.ndarray | float = 1.0
        if not accept.all():
            # a step that raises the full rows' residual is halved (from the Earth's
            # centre, near-equatorial GEOs make the plain step overshoot)
            lam = np.ones(sel.size)
            pending = (~accept).nonzero()[0]
            while pending.size:
                lam[pending] /= 2.0
                lp = lam[pending]
                rows = sel[pending]
                part = _trial(
                    ch,
                    st,
                    rows,
                    rows,
                    step[pending],
                    None if dn_m is None else dn_m[pending],
                    lp,
                    ct1,
                    omega,
                    fullw,
                    layout,
                )
                c0 = cost[rows]
                ok_p = (part.cost <= c0 * _MERIT_SLACK) | (lp < 1e-3) | ~np.isfinite(c0)
                got.take(pending[ok_p], part, ok_p)
                pending = pending[~ok_p]
        if whole:  # every epoch stepped: the new arrays are the iterate
            st.x, st.b, st.n_int, st.sat0, st.clk = got.x, got.b, got.n_int, got.sat0, got.clk
            st.los, st.pred, st.sat, resid, cost = got.los, got.pred, got.sat, got.resid, got.cost
        else:
            st.x[ix], st.b[ix], st.n_int[ix] = got.x, got.b, got.n_int
            st.sat0[ix], st.clk[ix], st.los[ix], st.pred[ix] = got.sat0, got.clk, got.los, got.pred
            st.sat[ix], resid[ix], cost[ix] = got.sat, got.resid, got.cost
        if got.moved:
            zn = ch.z + st.n_int * ch.ct
        size = np.sqrt(linalg.einsum("ek,ek->e", step, step))
        # eq. (14): settled when the step is below theta and no integer moved
        going = ~((size if isinstance(lam, float) else size * lam) < cfg.theta_m)
        if got.moves is not None:
            going |= got.moves
        finite = np.isfinite(got.x).all(axis=1)
        active[ix] = finite & going
    x, b, n_int, iters = st.x, st.b, st.n_int, st.iters
    sat0, clk, los, pred, sat = st.sat0, st.clk, st.los, st.pred, st.sat
    for e in singular.nonzero()[0].tolist():
        d.decline(e, Declined.of(Decline.SINGULAR))
    ok &= ~singular

    # no convergence, or a position no longer finite
    lost = one & ok & ~np.isfinite(x).all(axis=1)
    for e in lost.nonzero()[0].tolist():
        it = int(iters[e])
        d.decline(e, Declined.of(Decline.NO_CONVERGENCE, iterations=it), iterations=it)
    ok &= ~lost
    # an epoch left (one & ok: finite, not singular) has converged unless it is still active
    converged = ~active
    # eqs. (12), (20)-(21): the GEO-GDOP gate over the full rows at the phase-1 position
    with_frac = n_frac > 0
    gated = one & ok & (with_frac | ~converged)
    if gated.any():
        if gated.all():  # (every epoch: no other epoch's figure to leave NaN)
            gd = dop(design(los, slice(None)), fullw)
        else:
            gs = gated.nonzero()[0]
            gd = np.full(n_e, np.nan)
            gd[gs] = dop(design(los[gs], gs), fullw[gs])
        if cfg.beta:
            beta = np.full(n_e, float(cfg.beta))
        else:  # eq. 21 with the shortest code period among the fractional rows
            t_min = np.where(ch.frac, ch.ct, np.inf).min(axis=1) / C_M_S
            beta = np.where(with_frac, C_M_S * t_min / 2.0 / cfg.range_error_m, 0.0)
        fails = with_frac & ~(gd < beta)
        declined_here = gated & (fails | ~converged)
        if declined_here.any():
            gate = gated & fails
            unsettled = declined_here & ~gate  # (passed the gate or had nothing to gate)
            gd_l, beta_l, it_l = gd.tolist(), beta.tolist(), iters.tolist()
            for e in gate.nonzero()[0].tolist():
                variant = "" if converged[e] else "unsettled"
                it = it_l[e]
                why = Declined.of(
                    Decline.GDOP_GATE, variant, gdop=gd_l[e], beta=beta_l[e], iterations=it
                )
                d.decline(e, why, gdop_full=gd_l[e], iterations=it)
            for e in unsettled.nonzero()[0].tolist():
                it = it_l[e]
                why = Declined.of(Decline.NO_CONVERGENCE, iterations=it)
                d.decline(e, why, gdop_full=gd_l[e], iterations=it)
            ok &= ~declined_here

    # eqs. (15)-(16): the integers held, [x, b] corrected over all rows (no corrections yet)
    validw = ch.valid.astype(float)
    sel = (ok & one).nonzero()[0]
    numerical: dict[int, str] = {}
    zn = ch.z + n_int * ch.ct if has_frac else ch.z  # the integers are held from here
    for _it in range(cfg.max_iter):
        if not sel.size:
            break
        ix = slice(None) if sel.size == n_e else sel
        _add(iters, ix, 1)
        dz = zn[ix] - pred[ix] - _row_clocks(b[ix], cix[ix])
        step, bad, finite = lsq_step(design(los[ix], ix), dz, validw[ix])
        if bad is not None:
            for e in sel[bad].tolist():
                numerical[e] = _SINGULAR_MESSAGE
            sel, step = sel[~bad], step[~bad]
            finite = None if finite is None else finite[~bad]
            ix = sel
        _add(x, ix, step[:, :3])
        _add(b, ix, step[:, 3:n_par])
        # (phase 1 ended finite: a step that is not makes the iterate so)
        if finite is None and isinstance(ix, slice):
            los, pred, sat = ranges(sat0, clk, x, omega)
        else:
            fin = sel if finite is None else sel[finite]
            los[fin], pred[fin], sat[fin] = ranges(sat0[fin], clk[fin], x[fin], omega[fin])
        size = np.sqrt(linalg.einsum("ek,ek->e", step, step))
        more = size >= cfg.conv_m
        sel = sel[more if finite is None else finite & more]
    it_state = _Iterate(x, b, n_int, iters, sat0, clk, los, pred, sat)
    return _phase2(ch, d, ok, numerical, layout, it_state, iono, cfg, solver)


_SINGULAR_MESSAGE = "singular least-squares system"


@dataclass(slots=True, eq=False)
class _Iterate:
    """The chunk's iterate: positions (e, 3), clocks (e, clocks) [m], integers (e, s),
    iterations so far, satellite states at transmit time (orbit positions and clocks, then
    rotated by the Earth during the flight, with lines of sight and predicted ranges)."""

    x: np.ndarray
    b: np.ndarray
    n_int: np.ndarray
    iters: np.ndarray
    sat0: np.ndarray
    clk: np.ndarray
    los: np.ndarray
    pred: np.ndarray
    sat: np.ndarray


def _phase2(
    ch: _Chunk,
    d: _Decided,
    ok: np.ndarray,
    numerical: dict[int, str],
    layout: Layout,
    st: _Iterate,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
) -> list[Outcome]:
    """Phase 2 of the epochs ``ok`` from the iterate ``st``: the elevation mask (a masked
    fractional satellite loses its row; its integer is already fixed), Klobuchar and
    Saastamoinen, the error model's weights, iterated to convergence; then the judgement
    (:func:`_judged`). A position far from the Earth (a gross fault can put phase 1 there)
    gets no mask, no corrections and one weight for every row: they mean nothing there.
    An epoch whose mask leaves a system without rows loses that system's clock."""
    n_e = len(ch.z)
    x = st.x
    finite = np.isfinite(x).all(axis=1) & np.isfinite(st.b).all(axis=1)
    for e in [] if finite.all() else (ok & ~finite).nonzero()[0].tolist():
        it = int(st.iters[e]) + 1
        d.decline(e, Declined.of(Decline.DIVERGED), iterations=it)
    for e in numerical:
        ok[e] = False
    ok &= finite
    r = np.sqrt(linalg.einsum("ek,ek->e", x, x))
    meaningful = (r > 6.0e6) & (r < 8.5e6)
    keep = ch.valid.copy()
    sel0 = ok.nonzero()[0]
    loc0 = None
    if sel0.size:
        s0: _Index = slice(None) if sel0.size == n_e else sel0
        loc0 = _local(x[s0], st.sat[s0])
        above = loc0[3] >= math.radians(cfg.elmask_deg)
        keep[s0] &= above if meaningful.all() else above | ~meaningful[s0, None]
    # each epoch's unknowns after the mask: the layout of its kept rows
    klayout: list[Layout] = [layout] * n_e
    if layout.n_clocks > 1 and sel0.size:
        for e in sel0.tolist():
            ps = ch.prn[e]
            kept_ps = [ps[i] for i in np.flatnonzero(keep[e, : len(ps)]).tolist()]
            klayout[e] = layout_of(kept_ps) if kept_ps else layout
    n_full_k = (keep & ch.full).sum(axis=1)
    need = layout.n_params if layout.n_clocks == 1 else np.array([k.n_params for k in klayout])
    masked = ok & (n_full_k < need)
    if masked.any():
        ms = masked.nonzero()[0]
        gd = dop(layout.design(st.los[ms], ch.cix[ms]), ch.full[ms].astype(float))
        n_frac = ch.frac.sum(axis=1)
        for k, e in enumerate(ms.tolist()):
            why = Declined.of(
                Decline.TOO_FEW_FULL, "mask", mask_deg=cfg.elmask_deg, n_full=int(n_full_k[e])
            )
            gd_e = float(gd[k]) if n_frac[e] else None
            d.decline(e, why, gdop_full=gd_e, iterations=int(st.iters[e]))
    ok &= ~masked
    out = d.out
    for e, why, fields in d.declines:
        out[e] = _decline(ch, e, solver, why, fields)
    for e, message in numerical.items():
        out[e] = _numerical(ch.epochs[e], solver, "LinAlgError", message)
    sel_all = ok.nonzero()[0]
    if not sel_all.size:
        return out
    groups: dict[Layout, list[int]] = {}
    for k, e in enumerate(sel_all.tolist()):
        groups.setdefault(klayout[e], []).append(k)
    for lay, ks in groups.items():
        sel = sel_all[ks] if len(ks) != len(sel_all) else sel_all
        if lay is layout:
            b, cix = st.b[sel], ch.cix[sel]
        else:  # the clocks of the systems left, each row pointing at its system's
            cols = [layout.systems.index(s) for s in lay.systems]
            b = st.b[sel][:, cols]
            remap = np.zeros(layout.n_clocks, dtype=np.intp)
            remap[cols] = np.arange(len(cols))
            cix = remap[ch.cix[sel]]
        # the look angles at this position, computed for the mask (over the epochs ``ok``
        # had then, ``sel0``)
        loc: _Local | None = loc0
        if loc0 is not None and len(sel) != len(sel0):
            at = np.searchsorted(sel0, sel)
            lat, lon, alt, el, az, rot = loc0
            loc = (lat[at], lon[at], alt[at], el[at], az[at], rot[at])
        for e, res in zip(
            sel.tolist(),
            _weighted(ch, sel, lay, b, cix, keep[sel], meaningful[sel], st, loc, iono, cfg, solver),
            strict=True,
        ):
            out[e] = res
    return out


def _weighted(
    ch: _Chunk,
    sel: np.ndarray,
    layout: Layout,
    b: np.ndarray,
    cix: np.ndarray,
    keep: np.ndarray,
    meaningful: np.ndarray,
    st: _Iterate,
    loc: _Local | None,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
) -> list[Outcome]:
    """Phase 2's iterations for epochs ``sel`` (rows ``keep``, clocks ``b`` of ``layout``
    at the rows' indices ``cix``; :func:`iterate_fixed`, the loop the coarse-time fix's
    candidates share), then the judgement of each solution."""
    n_par = layout.n_params
    n1 = len(sel)
    rows: _Index = slice(None) if n1 == len(ch.z) else sel  # (all: views, no copies)
    x = st.x[rows]
    n_int, iters = st.n_int[rows], st.iters[rows]
    sat0, clk, los, pred, sat = (
        st.sat0[rows],
        st.clk[rows],
        st.los[rows],
        st.pred[rows],
        st.sat[rows],
    )
    eph = ch.eph
    omega, carrier, bds = eph.omega_e_rad_s[rows], eph.carrier_hz[rows], eph.bds[rows]
    z = ch.z[rows] + n_int * ch.ct[rows] if ch.has_frac else ch.z[rows]
    sow = ch.bdt_sow[rows]
    # the epochs near the Earth (None: all of them, the usual case)
    near = None if meaningful.all() else meaningful[:, None]
    keepw = keep.astype(float)
    models = iono.models(cfg.iono)
    cn0_var = cn0_variance_m2(ch.cn0[rows], cfg)  # (the same every iteration)
    aid = _aids_of(cfg, ch.epochs, sel)
    diverged = np.zeros(n1, dtype=bool)
    bad_lsq = np.zeros(n1, dtype=bool)

    def linearize(ix: _Index, it: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        nonlocal loc
        _add(iters, ix, 1)
        if loc is None or it:
            loc = _local(x[ix], sat[ix])
        lat, lon, alt, el, az, _rot = loc
        nr = None if near is None else near[ix]
        g, dz, w = weighted_rows(
            layout,
            los[ix],
            cix[ix],
            None,
            z[ix] - pred[ix],
            b[ix],
            (lat, lon, alt, el, az),
            sow[ix],
            carrier[ix],
            bds[ix],
            models,
            keepw[ix],
            cn0_var[ix],
            nr,
            cfg,
        )
        if aid is not None:  # (unweighted, a range's weight 1 stands for sigma_uniform_m)
            unit_m = 1.0 if cfg.weighted else cfg.sigma_uniform_m
            at = _aid_at(aid, ix)
            g, dz, w = _height_row(g, dz, w, _rot, alt, nr, at, squared=True, unit_m=unit_m)
        return g, dz, w

    def advance(ix: _Index, act: np.ndarray, got: LsqStep, it: int) -> np.ndarray:
        nonlocal los, pred, sat
        step, bad, finite = got
        if bad is not None:
            bad_lsq[act[bad]] = True
            act, step = act[~bad], step[~bad]
            finite = None if finite is None else finite[~bad]
            ix = act
        _add(x, ix, step[:, :3])
        _add(b, ix, step[:, 3:n_par])
        # (the iterate was finite: a step that is not makes it so)
        if finite is None and isinstance(ix, slice):
            los, pred, sat = ranges(sat0, clk, x, omega)
        else:
            fin = act
            if finite is not None:
                diverged[act[~finite]] = True
                fin = act[finite]
            los[fin], pred[fin], sat[fin] = ranges(sat0[fin], clk[fin], x[fin], omega[fin])
        size = np.sqrt(linalg.einsum("ek,ek->e", step, step))
        more = size >= cfg.conv_m
        return act[more if finite is None else finite & more]

    iterate_fixed(n1, cfg.max_iter, linearize, advance)
    out: list[Outcome] = [None] * n1
    for k in bad_lsq.nonzero()[0].tolist():
        out[k] = _numerical(ch.epochs[int(sel[k])], solver, "LinAlgError", _SINGULAR_MESSAGE)
    for k in (diverged & ~bad_lsq).nonzero()[0].tolist():
        e = int(sel[k])
        why = Declined.of(Decline.DIVERGED)
        out[k] = _decline(ch, e, solver, why, {"iterations": int(iters[k])})
    good = (~diverged & ~bad_lsq).nonzero()[0]
    if not good.size:
        return out
    if good.size != n1:
        x, b, cix, keep = x[good], b[good], cix[good], keep[good]
        aid = None if aid is None else _aid_at(aid, good)
        near = None if near is None else near[good]
        n_int, iters, los, pred, sat = n_int[good], iters[good], los[good], pred[good], sat[good]
        z, sow, cn0_var = z[good], sow[good], cn0_var[good]
        carrier, bds = carrier[good], bds[good]
    # ---- judge the solution ------------------------------------------------------------------
    lat, lon, alt, el, az, rot = _local(x, sat)
    io, tr = system_delays(lat, lon, alt, el, az, sow, carrier, bds, models, cfg)
    corr = total_delay(io, tr)
    v = z - pred - _row_clocks(b, cix) - _where(near, corr, 0.0)
    v = np.where(keep, v, 0.0)
    if cfg.weighted:
        sig = measurement_sigma_m(el, None, io, tr, cfg, cn0_var)
        sigma = _where(near, sig, cfg.sigma_uniform_m)
        sigma = np.where(keep, sigma, 1.0)
    else:
        sigma = np.full(keep.shape, cfg.sigma_uniform_m)
    g = layout.design(los, cix)
    n_k = keep.sum(axis=1)
    resid_rms = np.sqrt(linalg.einsum("es,es->e", v, v) / n_k)
    g_sat, keep_sat = g, keep  # the DOPs are the satellites' geometry alone
    if aid is not None:
        g, v, sigma = _height_row(g, v, sigma, rot, alt, near, aid, squared=False)
        keep = np.concatenate([keep, sigma[:, -1:] < np.inf], axis=1)
        sigma = np.where(keep, sigma, 1.0)
    integ = assess_many(g, v, sigma, keep, rot, cfg.p_fa, cfg.p_md, layout)
    gsel = sel[good]
    if solver == "fast":
        gd_final = dop(g_sat, (keep_sat & ch.full[gsel]).astype(float)).tolist()
    else:
        gd_final = [None] * len(good)
    gu = g_sat * keep_sat[..., None]
    q = linalg.inv(gu.swapaxes(-1, -2) @ gu)[:, :3, :3]
    q_enu = rot @ q @ rot.swapaxes(-1, -2)
    pdop = np.sqrt(q_enu.trace(axis1=1, axis2=2))
    numbers: dict[str, list] = {
        "x": x.tolist(),
        "b": b.tolist(),
        "lat_deg": np.degrees(lat).tolist(),
        "lon_deg": np.degrees(lon).tolist(),
        "alt": alt.tolist(),
        "gdop": gd_final,
        "pdop": pdop.tolist(),
        "hdop": np.sqrt(q_enu[:, 0, 0] + q_enu[:, 1, 1]).tolist(),
        "vdop": np.sqrt(q_enu[:, 2, 2]).tolist(),
        "cov": [i.cov_enu_m2.tolist() for i in integ],
        "resid": resid_rms.tolist(),
        "iters": iters.tolist(),
    }
    for k, (g_k, e) in enumerate(zip(good.tolist(), gsel.tolist(), strict=True)):
        out[g_k] = _judged(ch, e, solver, layout, n_int[k], keep[k], integ[k], numbers, k, cfg)
    return out


def iterate_fixed(
    n: int,
    max_iter: int,
    linearize: Callable[[_Index, int], tuple[np.ndarray, np.ndarray, np.ndarray]],
    advance: Callable[[_Index, np.ndarray, LsqStep, int], np.ndarray],
) -> None:
    """The weighted least-squares iteration with the integers fixed, of ``n`` problems at
    once: the kernel's phase 2 (:func:`_weighted`) and the coarse-time fix's candidates
    (:mod:`service.engine.coarse`). Each iteration asks ``linearize(ix, it)`` for the
    design, misclosures and weights of the problems ``ix`` (:func:`weighted_rows` and any
    pseudo-observation rows: a held height, the time prior), solves their step
    (:func:`lsq_step`, paper eq. 10) and hands it to ``advance(ix, act, step, it)``, which
    applies it, computes the geometry at the new iterate (the kernel: the ranges from its
    fixed orbits; coarse time: the orbits again at the moved receive time), tests
    convergence and returns the problems still active (``act``: their indices; ``ix``
    the same, or a slice when every problem is active). The kernel linearizes and moves
    the active problems only; the coarse-time candidates, all of them each time (a
    converged group's step is zeroed, its figures kept), until every group has
    converged."""
    act = np.arange(n)
    for it in range(max_iter):
        if not act.size:
            break
        ix: _Index = slice(None) if act.size == n else act
        g, dz, w = linearize(ix, it)
        act = advance(ix, act, lsq_step(g, dz, w), it)


def weighted_rows(
    layout: Layout,
    los: np.ndarray,
    cix: np.ndarray | None,
    rate_m_s: np.ndarray | None,
    resid_m: np.ndarray,
    b: np.ndarray,
    loc: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray],
    bdt_sow_s: np.ndarray,
    carrier_hz: np.ndarray,
    bds_rows: np.ndarray,
    models: IonoModels | None,
    keepw: np.ndarray,
    cn0_var_m2: np.ndarray,
    near: np.ndarray | None,
    cfg: SolverConfig,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One weighted iteration's rows of some problems (e) with fixed integers, s rows
    each, at the iterate's geometry: the design (e, s, p) (:meth:`Layout.design`: lines of
    sight ``los``, clock indices ``cix``, with a coarse-time layout the range rates
    ``rate_m_s``), the misclosures z - pred - b - delays (``resid_m``: z - pred, ``b``
    the clocks (e, clocks)) and the weights ``keepw`` / sigma^2 (``keepw``: 1 for a row
    in, 0 out; :func:`measurement_sigma_m`, C/N0 term ``cn0_var_m2``; unweighted
    (``cfg.weighted`` False): ``keepw`` itself). ``loc``: latitude, longitude, height (e,),
    elevation, azimuth (e, s) of the receivers; delays per row's system
    (:func:`system_delays`) at receive times ``bdt_sow_s`` (e,). Problems not ``near``
    the Earth (e, 1; None: all near) get no delays and ``keepw``. The kernel's phase 2
    (:func:`_weighted`) and the coarse-time fix's candidates both iterate with these."""
    lat, lon, alt, el, az = loc
    io, tr = system_delays(lat, lon, alt, el, az, bdt_sow_s, carrier_hz, bds_rows, models, cfg)
    dz = resid_m - _row_clocks(b, cix) if cix is not None else resid_m - b
    corr = total_delay(io, tr)
    dz = dz - _where(near, corr, 0.0)
    w = keepw
    if cfg.weighted:
        sig = measurement_sigma_m(el, None, io, tr, cfg, cn0_var_m2)
        w = np.asarray(_where(near, w / sig**2, w))
    return layout.design(los, cix, rate_m_s), dz, w


def _height_row(
    g: np.ndarray,
    dz: np.ndarray,
    w: np.ndarray,
    rot: np.ndarray,
    alt_m: np.ndarray,
    near: np.ndarray | None,
    aid: tuple[float, float] | tuple[np.ndarray, np.ndarray],
    squared: bool,
    unit_m: float = 1.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The design ``g`` (e, s, p), misclosures ``dz`` (e, s) and weights or sigmas ``w``
    (e, s) joined by one row: the pseudo-observation ``aid`` = (h, sigma) of the ellipsoidal
    height, whose partials are the local up vector (the third row of the ENU rotation
    ``rot``) and no clock, misclosure h - height of the iterate (``alt_m``). ``squared``:
    ``w`` holds weights 1 / sigma^2 (else sigmas), or (unit_m / sigma)^2 where a weight
    of 1 stands for a sigma of ``unit_m``. Epochs not ``near`` the Earth get no
    row (weight 0, sigma inf): the height means nothing there. ``aid``: one for every
    epoch, or each epoch's as arrays (e,)."""
    h_m, sigma_m = aid
    n_e = len(dz)
    row = np.zeros((n_e, 1, g.shape[-1]))
    row[:, 0, :3] = rot[:, 2, :]
    mis = (h_m - np.asarray(alt_m, dtype=float)).reshape(n_e, 1)
    val = unit_m**2 / sigma_m**2 if squared else sigma_m
    far = 0.0 if squared else np.inf
    if isinstance(val, np.ndarray):
        val = val.reshape(n_e, 1)
        ww = val if near is None else np.where(near, val, far)
    else:
        ww = np.full((n_e, 1), val) if near is None else np.where(near, val, far)
    ww = ww.reshape(n_e, 1)
    mis = np.where(ww == far, 0.0, mis)
    return pseudo_rows(g, dz, w, row, mis, ww)


def pseudo_rows(
    g: np.ndarray,
    dz: np.ndarray,
    w: np.ndarray,
    rows: np.ndarray,
    misclosure: np.ndarray,
    weight: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The design ``g`` (e, s, p), misclosures ``dz`` (e, s) and weights (or sigmas) ``w``
    (e, s) of some problems joined by pseudo-observation rows: their partials ``rows``
    (e, r, p), misclosures (e, r) and weights (or sigmas) (e, r). A pseudo-observation is
    a row like any other: it enters the least squares (:func:`lsq_step`), the chi-square
    statistic and the redundancy (:meth:`Layout.redundancy`)."""
    return (
        np.concatenate([g, rows], axis=1),
        np.concatenate([dz, misclosure], axis=1),
        np.concatenate([w, weight], axis=1),
    )


def time_prior_row(
    g: np.ndarray, dz: np.ndarray, w: np.ndarray, layout: Layout, dt_s: np.ndarray, sigma_s: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The design ``g`` (e, s, p) of a coarse-time ``layout``, misclosures ``dz`` and
    weights ``w`` (e, s) joined by the time prior (:func:`pseudo_rows`): the tag is an
    observation of the receive time with its own sigma, dt = 0 +- ``sigma_s`` (van
    Diggelen, *A-GPS*, ch. 4): partial 1 on the coarse-time column, misclosure 0 - dt of
    the iterate ``dt_s`` (e,), weight 1 / sigma^2."""
    n_e = len(dz)
    row = np.zeros((n_e, 1, layout.n_params))
    row[:, 0, layout.time_column] = 1.0
    weight = np.full((n_e, 1), 1.0 / sigma_s**2)
    return pseudo_rows(g, dz, w, row, (0.0 - dt_s)[:, None], weight)


def _judged(
    ch: _Chunk,
    e: int,
    solver: Literal["fast", "spp"],
    layout: Layout,
    n_int: np.ndarray,
    kept: np.ndarray,
    integ: Integrity,
    numbers: dict[str, list],
    k: int,
    cfg: SolverConfig,
) -> Outcome:
    """Epoch ``e``'s solution judged (:func:`service.engine.judge.verdict`): its fix, its
    decline, or its failed test (``k``: its index among the judged epochs, in ``numbers``;
    ``n_int`` and ``kept``: its integers and kept rows, by slot)."""
    ep = ch.epochs[e]
    prn = ch.prn[e]
    frac = ch.frac[e, : len(prn)].tolist()
    kk = [i for i, k in enumerate(kept[: len(prn)].tolist()) if k]
    used = tuple(prn[i] for i in kk)
    fr = [i for i in kk if frac[i]]  # the used fractional rows
    # (plain floats: the same sums, without numpy's per-item cost)
    n_row: list[float] = n_int.tolist() if fr else []
    ambiguity = {prn[i]: int(n_row[i]) for i in fr}
    gdop_full = numbers["gdop"][k]
    alt, clocks, pdop = numbers["alt"][k], numbers["b"][k], numbers["pdop"][k]
    clock = clocks[0] if len(clocks) == 1 else max(clocks, key=abs)  # furthest from zero
    why = verdict(integ, used, alt, clock, pdop, cfg, kk)
    if why is not None:
        fix = decline_fix(
            solver,
            ep.gpst_week,
            ep.gpst_tow_s,
            prn,
            frac,
            why,
            gdop_full=gdop_full,
            iterations=numbers["iters"][k],
            resid_rms_m=numbers["resid"][k],
            redundancy=integ.redundancy,
            chi2=integ.chi2,
            chi2_max=integ.chi2_max,
            **({"ambiguity": ambiguity} if why.code is Decline.CHI2 else {}),
        )
        if why.code is not Decline.CHI2 or integ.chi2 is None or integ.chi2_max is None:
            return fix
        w = integ.w.tolist()
        wtest = tuple(w[i] for i in kk)
        x = numbers["x"][k]
        # every row full and near the Earth: the candidates start here (Failed.warm_start)
        near = 6.0e6 < math.sqrt(x[0] * x[0] + x[1] * x[1] + x[2] * x[2]) < 8.5e6
        warm = (x[0], x[1], x[2]) if near and not any(frac) else None
        return Failed(integ.chi2, integ.chi2_max, integ.redundancy, used, wtest, fix, warm)
    z, ct = (ch.z[e].tolist(), ch.ct[e].tolist()) if fr else ([], [])
    return solution_fix(
        solver=solver,
        gpst_week=ep.gpst_week,
        gpst_tow_s=ep.gpst_tow_s,
        x=numbers["x"][k],
        clocks=clocks,
        systems=layout.systems,
        lat_deg=numbers["lat_deg"][k],
        lon_deg=numbers["lon_deg"][k],
        alt_m=alt,
        gdop_full=gdop_full,
        pdop=pdop,
        hdop=numbers["hdop"][k],
        vdop=numbers["vdop"][k],
        cov=numbers["cov"][k],
        integ=integ,
        resid_rms_m=numbers["resid"][k],
        iterations=numbers["iters"][k],
        used=used,
        frac=[frac[i] for i in kk],
        ambiguity=ambiguity,
        recovered_pr_m={prn[i]: z[i] + n_row[i] * ct[i] for i in fr},
    )


def _decline(
    ch: _Chunk,
    e: int,
    solver: Literal["fast", "spp"],
    why: Declined,
    fields: dict[str, object],
) -> Fix:
    """Epoch ``e``'s decline decided before its solution is judged: over its rows, with
    ``fields`` (an epoch without rows has none)."""
    ep, prn = ch.epochs[e], ch.prn[e]
    frac = ch.frac[e, : len(prn)].tolist()
    return decline_fix(solver, ep.gpst_week, ep.gpst_tow_s, prn, frac, why, **fields)


def _numerical(
    epoch: MeasurementEpoch, solver: Literal["fast", "spp"], error: str, message: str
) -> Fix:
    """The decline of an epoch whose numbers failed (no rows are named)."""
    why = Declined.of(Decline.NUMERICAL, error=error, message=message)
    return declined(epoch, why, solver)


_NUMBER_ERRORS = (np.linalg.LinAlgError, ArithmeticError, ValueError)


def _outcomes(
    epochs: Sequence[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
    start: np.ndarray | None = None,
    screen: bool = True,
) -> tuple[list[Outcome], list[dict[str, str]], list[bool]]:
    """:func:`_solve_chunk` over ``epochs`` chunk by chunk; ``start`` (e, 3): where each
    epoch's phase 1 starts (NaN: ``cfg.x0_ecef_m`` or the Earth's centre). Also, per epoch,
    the impossible ranges left out (``_Chunk.gross``) and whether it has fractional rows of
    systems without a full row (``_Chunk.others``; ``screen``: whether impossible ranges
    are looked for). A chunk whose numbers fail is solved again epoch by epoch; an epoch
    alone whose numbers fail is declined ``numerical``."""
    out: list[Outcome] = []
    gross: list[dict[str, str]] = []
    others: list[bool] = []
    for at in range(0, len(epochs), CHUNK_EPOCHS):
        part = epochs[at : at + CHUNK_EPOCHS]
        where = None if start is None else start[at : at + CHUNK_EPOCHS]
        try:
            with np.errstate(all="ignore"):
                ch = _Chunk(part, store, solver, screen)
                out += _solve_layouts(ch, store, iono, cfg, solver, where, screen)
            gross += ch.gross
            others += ch.others
        except _NUMBER_ERRORS as exc:
            if len(part) == 1:
                log.debug(
                    "solver failure at GPST %d %.3f",
                    part[0].gpst_week,
                    part[0].gpst_tow_s,
                    exc_info=True,
                )
                out.append(_numerical(part[0], solver, type(exc).__name__, str(exc)))
                gross.append({})
                others.append(False)
                continue
            log.debug("a chunk's numbers failed; its epochs are solved one by one", exc_info=True)
            for k, ep in enumerate(part):
                one = None if where is None else where[k : k + 1]
                o, g, t = _outcomes([ep], store, iono, cfg, solver, one, screen)
                out += o
                gross += g
                others += t
    return out, gross, others


def _solve_layouts(
    ch: _Chunk,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
    start: np.ndarray | None = None,
    screen: bool = True,
) -> list[Outcome]:
    """:func:`_solve_chunk` of ``ch``; when its epochs' rows differ in their satellite
    systems (so in their clocks, :class:`~service.engine.layout.Layout`), each layout's
    epochs are solved as a chunk of their own."""
    if ch.layout is not None:
        return _solve_chunk(ch, ch.layout, iono, cfg, solver, start)
    groups: dict[Layout, list[int]] = {}
    for e, ps in enumerate(ch.prn):
        groups.setdefault(layout_of(ps) if ps else BDS_ONLY, []).append(e)
    out: list[Outcome] = [None] * len(ch.prn)
    for idx in groups.values():
        sub = _Chunk([ch.epochs[e] for e in idx], store, solver, screen)
        layout = sub.layout if sub.layout is not None else BDS_ONLY
        where = None if start is None else start[idx]
        for e, res in zip(idx, _solve_chunk(sub, layout, iono, cfg, solver, where), strict=True):
            out[e] = res
    return out


def _without(epoch: MeasurementEpoch, prns: Iterable[str]) -> MeasurementEpoch:
    """``epoch`` without satellites ``prns``."""
    drop = set(prns)
    return epoch.rows([i for i, p in enumerate(epoch.prn) if p not in drop])


_Candidate = tuple[MeasurementEpoch, tuple[float, float, float] | None]
"""A candidate of fault exclusion: its epoch and where its phase 1 starts (None: the Earth's
centre; :attr:`service.engine.judge.Failed.warm_start`)."""


def _exclude(
    failed: dict[int, tuple[Failed, MeasurementEpoch]],
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
) -> tuple[dict[int, Fix], set[int]]:
    """Fault exclusion (:func:`service.engine.judge.exclude`) for the epochs that failed the
    test, every candidate of every epoch of a stage solved in one call of the kernel."""

    def without(cand: _Candidate, prn: str) -> _Candidate:
        return _without(cand[0], (prn,)), cand[1]

    def solve(cands: list[_Candidate]) -> list[tuple[Outcome, _Candidate]]:
        start = np.array([(math.nan,) * 3 if s is None else s for _, s in cands]).reshape(-1, 3)
        res, _, _ = _outcomes([ep for ep, _ in cands], store, iono, cfg, solver, start, False)
        return [
            (r, (ep, r.warm_start if isinstance(r, Failed) else None))
            for r, (ep, _) in zip(res, cands, strict=True)
        ]

    first = {e: (f, (ep, f.warm_start)) for e, (f, ep) in failed.items()}
    return exclude(first, without, solve, cfg.max_exclusions)


def solve_many(
    epochs: Sequence[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
    solver: Literal["fast", "spp"] = "fast",
    with_sky: bool = False,
) -> list[Fix]:
    """The fix of each epoch (:func:`solve` of each): the kernel over chunks of
    :data:`CHUNK_EPOCHS` epochs, fault exclusion with every candidate of every failed epoch
    of a stage in one call. Never raises for bad input, geometry or numbers: a fix that
    cannot be trusted comes back as ``mode="none"`` with a reason (``reason_code``). Epochs
    in time order make the ephemeris selection cheapest; any order gives the same fixes."""
    cfg = cfg or SolverConfig()
    iono = iono or IonoSet()
    # no GPS week: declined before any row is read
    out: list[Fix | None] = [
        None if ep.week_known else declined(ep, Declined.of(Decline.NO_TIME), solver)
        for ep in epochs
    ]
    todo = [i for i, ep in enumerate(epochs) if ep.week_known]
    results, gross, others = _outcomes([epochs[i] for i in todo], store, iono, cfg, solver)
    failed: dict[int, tuple[Failed, MeasurementEpoch]] = {}
    for k, (i, res) in enumerate(zip(todo, results, strict=True)):
        if isinstance(res, Fix):
            out[i] = res
        elif isinstance(res, Failed):
            # its candidates are made from its rows, the impossible ranges left out
            ep = _without(epochs[i], gross[k]) if gross[k] else epochs[i]
            failed[i] = (res, ep)
    if failed and cfg.max_exclusions > 0:
        passed, hopeless = _exclude(failed, store, iono, cfg, solver)
        for i, fix in passed.items():
            out[i] = fix
        for i in hopeless:  # no exclusion passes: the failed solution's decline
            out[i] = no_exclusion(failed[i][0].fix, cfg.max_exclusions)
    else:  # no exclusion asked for: the failed solution's decline
        for i, (bad, _) in failed.items():
            out[i] = bad.fix
    fixes: list[Fix] = []
    pos = {i: k for k, i in enumerate(todo)}
    for i, (got, ep) in enumerate(zip(out, epochs, strict=True)):
        if got is None:  # (every epoch has its outcome by now)
            raise RuntimeError(f"epoch {i} has no outcome")
        at = pos.get(i)
        if at is not None and gross[at]:
            got = replace(got, excluded=gross[at] | got.excluded)
        join = at is not None and others[at] and got.ok and solver == "fast"
        try:
            if join or (with_sky and got.ok):
                with np.errstate(all="ignore"):
                    if join:
                        got = _with_other_systems(ep, store, iono, cfg, got)
                    if with_sky and got.ok:
                        got = replace(got, sky=sky_view(ep, store, got))
        except _NUMBER_ERRORS as exc:
            log.debug("solver failure at GPST %d %.3f", ep.gpst_week, ep.gpst_tow_s, exc_info=True)
            got = _numerical(ep, solver, type(exc).__name__, str(exc))
        fixes.append(got)
    return fixes


def solve(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
    solver: Literal["fast", "spp"] = "fast",
    with_sky: bool = False,
) -> Fix:
    """Solve one epoch: the kernel with a chunk of one (:func:`solve_many`). Never raises
    for bad input, geometry or numbers: a fix that cannot be trusted comes back as
    ``mode="none"`` with a reason (and ``reason_code``)."""
    return solve_many((epoch,), store, iono, cfg, solver, with_sky)[0]


AMBIGUITY_MARGIN = 0.25
"""A fractional row of a system without full rows gets its integer from a fast fix only when
its predicted range puts it at most this many code periods from an integer: the prediction
(orbit at an approximate transmit time, no ionosphere or troposphere, the BeiDou clock for
the system's, whose inter-system bias is metres to kilometres) errs by far less than the
150 km of a quarter millisecond."""


def _with_other_systems(
    epoch: MeasurementEpoch, store: EphemerisStore, iono: IonoSet, cfg: SolverConfig, fix: Fix
) -> Fix:
    """The fast fix ``fix`` of ``epoch`` joined by the fractional rows of the systems that
    have no full row (which the fast fix leaves out, :func:`_with_full_systems`): each one's
    integer N (paper eq. 11) from the range predicted at the fix with the fix's BeiDou
    clock, N = round((rho - c dt_sat + b - z) / cT), then every row solved again with those
    integers held (the rows become full, and the fix reports them fractional with their N;
    its ``gdop_full`` stays ``fix``'s, the GDOP of eq. (20) over the full rows it reports,
    not over the joined rows held full). ``fix`` itself when there are none, when a
    prediction is ambiguous (:data:`AMBIGUITY_MARGIN`) or the joined solve fails."""
    full = np.isfinite(epoch.pr_m)
    fracok = ~full & np.isfinite(epoch.frac_pr_m) & np.isfinite(epoch.period_s)
    todo = np.flatnonzero(fracok & ~_with_full_systems(epoch, full, fracok)).tolist()
    if not todo or fix.x_ecef_m is None:
        return fix
    bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    x = np.asarray(fix.x_ecef_m, dtype=float)
    b = fix.clocks_m.get("C", fix.clock_bias_m or 0.0)
    ephs, idx = select_rows(store, epoch.prn, todo, bdt_week, bdt_sow)
    if not ephs:
        return fix
    arr = store.arrays(ephs)
    ii = np.asarray(idx)
    tau = np.full(len(ii), NOMINAL_FLIGHT_TIME_S)
    for _ in range(2):  # transmit time from the geometric range (metres of error, not km)
        sat, clk = sat_pos_clock(arr, bdt_week, bdt_sow - tau)
        tau = np.linalg.norm(sat - x, axis=1) / C_M_S
    _, pred, _ = ranges(sat, clk, x, arr.omega_e_rad_s)
    ct = C_M_S * epoch.period_s[ii]
    n_float = (pred + b - epoch.frac_pr_m[ii]) / ct
    n = np.rint(n_float)
    if not np.all(np.abs(n_float - n) <= AMBIGUITY_MARGIN):  # (NaN: not resolved either)
        return fix
    pr = epoch.pr_m.copy()
    pr[ii] = epoch.frac_pr_m[ii] + n * ct
    if not np.isfinite(pr[ii]).all():
        return fix
    # (those rows are full now: the joined epoch has no system left to join)
    again = solve(replace(epoch, pr_m=pr), store, iono, cfg, "fast")
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
