"""Height aiding and the prediction screen: what a receiver's past fixes tell its next one.

**Height aiding**: a pseudo-observation of the receiver's ellipsoidal height from its own
recent fixes, for a receiver whose height changes slowly (a car, a ship, a walker; not an
aircraft or a drone), as land-vehicle receivers do (their "automotive" dynamic model).

In a street canyon the rows that remain are few and mostly from high elevations, so the
vertical is the weakest direction, and reflected (NLOS) ranges, which are long, push the fix
upwards by tens to hundreds of metres while the chi-square test still passes
(docs/method.md, "Urban drive"). A height known to a few metres from the last minute of
fixes adds the missing vertical geometry and one degree of freedom to the test, so fault
exclusion sees the reflected rows instead of letting the vertical absorb them.

The aid is sequential (past epochs only):

- The held height at an epoch is the median of the ellipsoidal heights of the fixes the
  solver published in the last ``height_aid_window_s`` (at least ``height_aid_min_fixes``
  of them), aided or not: like the random-walk height state of a receiver's filter, the
  aid carries its own past forward, and the satellites move it at every fix by as much as
  their weight against its sigma allows.
- Its sigma is sqrt(s0^2 + (rate dt)^2 + (grade d)^2): ``height_aid_sigma_m`` (s0), growing
  with the time dt since the newest fix held and with the horizontal distance d the
  receiver may have moved from where the held fixes were taken (half their span plus the
  newest fix's Doppler speed times dt) along a road of slope ``height_aid_grade``.
  Measured on the TST drive against its ground truth: |held - true height| / sigma has
  its 68th percentile at 1.17 and its 95th at 1.73 with the prediction screen at 30 m
  (0.84 and 1.27 with the aid alone; docs/method.md).
- The row is in the error model: weighted by its sigma, it enters the chi-square test and
  the protection levels like a range (a fault in the aid has its slope too); fault
  exclusion never removes it. The DOPs stay the satellites' geometry.
- No aid for a first fix (no history), after a gap longer than the window with no fix,
  or after a receiver restart (:meth:`HeightAid.reset`).

The kernel's mechanism is :attr:`service.engine.solver.SolverConfig.height_aid` (phase 2
only, so the fast fix and SPP of the same rows with the same aid are the same solution).

**Prediction screen** (``screen_predicted_m``): the last published fix, at most
:data:`PREDICTION_MAX_AGE_S` old and with a Doppler velocity (service.engine.velocity),
moved by that velocity to the epoch's time predicts the position; each full range's
residual there (broadcast orbit and clock, Earth rotation; no atmosphere, whose
differences between satellites are metres) less its system's median (the receiver clock,
with at least :data:`PREDICTION_MIN_SYSTEM_ROWS` rows of that system) is what the range
has that the prediction does not explain. A range longer than predicted by more than the
setting is a reflected (NLOS) signal: it is left out before the solve (``Fix.excluded``
says so), when at least :data:`PREDICTION_MIN_ROWS` ranges remain. Only longer: a
reflected path is never shorter than the direct one (on the TST drive 91 % of the
residuals beyond 30 m at the true position are positive). The fix is still the snapshot
least squares of the ranges kept, tested and protected as any; the prediction only
chooses rows, so its error (the last fix's and the velocity's, metres) is not in the
fix's error model, and a wrong prediction costs rows, not a biased fix. Fractional ranges
are not screened (no integer yet): the fast fix and SPP of an epoch are given the same
ranges by the batch (:func:`service.commands.solve.solve_aided`).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from service.core.declines import excluded_why
from service.core.ephemeris import EphemerisStore, select_rows
from service.core.geometry import ecef_to_geodetic, enu_rotation
from service.core.stats import median
from service.core.timebase import diff_s, gpst_to_bdt
from service.core.types import Fix, MeasurementEpoch
from service.engine.solver import SolverConfig, ranges, sky_view, transmit_orbits

PREDICTION_MAX_AGE_S = 3.0
"""The prediction screen uses a fix at most this old [s]: at 1 Hz the last two epochs'."""
AID_QUANTUM_M = 0.1
"""The held height and its sigma are given to this step [m] (their error is metres; the sigma
is never below ``height_aid_sigma_m``): a change of a past fix in its last bits, or by
centimetres, seldom changes the next epoch's aid, so ``bdsfix solve``'s batch
(service.commands.solve.solve_aided) seldom solves an epoch twice (on the TST drive 1 mm:
3310 solves of 1760 epochs, 1 cm: 3130, 10 cm: 2836)."""
PREDICTION_MIN_ROWS = 6
"""The screen leaves ranges out only when at least this many remain (two clocks and the
position, with one degree of freedom for the test)."""
PREDICTION_MIN_SYSTEM_ROWS = 3
"""A system's ranges are screened only with at least this many (their median is the
clock)."""


@dataclass(frozen=True, slots=True)
class _Held:
    week: int
    tow_s: float
    h_m: float  # the fix's ellipsoidal height [m]
    x_ecef_m: np.ndarray
    speed_m_s: float  # horizontal speed from Doppler (0: not known)


@dataclass
class HeightAid:
    """The held height of one solver's fixes (module docstring); the settings are those of
    the :class:`~service.engine.solver.SolverConfig` each call is given."""

    _held: deque[_Held] = field(default_factory=deque)

    def reset(self) -> None:
        """Forget every fix (a receiver restart: its old fixes are no longer its own)."""
        self._held.clear()

    def prior(self, week: int, tow_s: float, cfg: SolverConfig) -> tuple[float, float] | None:
        """The aid (h [m], sigma [m]) for the epoch at GPS ``week`` + ``tow_s``, or None
        (fewer than ``height_aid_min_fixes`` fixes in the window)."""
        held = [
            f
            for f in self._held
            if 0.0 < diff_s(week, tow_s, f.week, f.tow_s) <= cfg.height_aid_window_s
        ]
        if len(held) < cfg.height_aid_min_fixes:
            return None
        h = median([f.h_m for f in held])
        newest, oldest = held[-1], held[0]
        dt = diff_s(week, tow_s, newest.week, newest.tow_s)
        span = _horizontal_m(newest.x_ecef_m, oldest.x_ecef_m)
        d = span / 2.0 + newest.speed_m_s * dt
        sigma = math.sqrt(
            cfg.height_aid_sigma_m**2
            + (cfg.height_aid_rate_m_s * dt) ** 2
            + (cfg.height_aid_grade * d) ** 2
        )
        # to AID_QUANTUM_M: a last-bit change of a past fix leaves the aid
        # as it was, so a batch that guesses the fixes before an epoch finds its aid exact
        # (service.commands.solve.solve_aided) once the guesses are close enough
        # the sigma never below the setting (nor 0: a sigma smaller than half the step
        # would round to nothing)
        return _quantized(h), max(_quantized(sigma), cfg.height_aid_sigma_m)

    def copy(self) -> HeightAid:
        """An independent copy of the held fixes (a batch's speculative pass)."""
        return HeightAid(deque(self._held))

    def cfg_for(self, week: int, tow_s: float, cfg: SolverConfig) -> SolverConfig:
        """``cfg`` with the aid for the epoch at ``week`` + ``tow_s`` (``cfg`` itself when
        there is none, or when ``cfg.height_aiding`` is off)."""
        aid = self.prior(week, tow_s, cfg) if cfg.height_aiding else None
        return cfg if aid is None else replace(cfg, height_aid=aid)

    def update(self, fix: Fix, cfg: SolverConfig) -> None:
        """Take a solver result: a published fix's height is held; fixes older than the
        window go."""
        week, tow = fix.gpst_week, fix.gpst_tow_s
        while self._held and diff_s(week, tow, self._held[0].week, self._held[0].tow_s) > (
            cfg.height_aid_window_s
        ):
            self._held.popleft()
        if not fix.ok or fix.x_ecef_m is None:
            return
        x = np.asarray(fix.x_ecef_m, dtype=float)
        h = float(ecef_to_geodetic(x)[2])  # ellipsoidal, as the kernel's height row
        speed = fix.velocity.speed_m_s if fix.velocity is not None else 0.0
        self._held.append(_Held(week, tow, h, x, speed if math.isfinite(speed) else 0.0))


def _quantized(v_m: float) -> float:
    """``v_m`` rounded to a multiple of :data:`AID_QUANTUM_M`."""
    return round(v_m / AID_QUANTUM_M) * AID_QUANTUM_M


def _horizontal_m(a: np.ndarray, b: np.ndarray) -> float:
    """The horizontal distance [m] between two ECEF points (the chord less its vertical
    part at ``a``)."""
    d = a - b
    up = a / np.linalg.norm(a)
    return float(np.linalg.norm(d - up * float(d @ up)))


@dataclass
class Predictor:
    """The prediction screen's state: the last published fix with a velocity (module
    docstring)."""

    _last: Fix | None = None

    def reset(self) -> None:
        """Forget the last fix (a receiver restart)."""
        self._last = None

    def copy(self) -> Predictor:
        """A copy (a batch's speculative pass)."""
        return Predictor(self._last)

    def key(self) -> tuple[object, ...] | None:
        """What the prediction is made from (the last fix's time, position and velocity),
        as values: equal keys, equal screens."""
        last = self._last
        if last is None or last.x_ecef_m is None or last.velocity is None:
            return None
        return (
            last.gpst_week,
            last.gpst_tow_s,
            tuple(last.x_ecef_m),
            tuple(last.velocity.v_enu_m_s),
        )

    def guess(self, week: int, tow_s: float) -> Fix | None:
        """The last fix moved to GPS ``week`` + ``tow_s`` by its velocity (:meth:`predict`),
        as a stand-in for a fix not solved yet (a batch's first guess), or None."""
        x = self.predict(week, tow_s)
        if x is None or self._last is None:
            return None
        return replace(self._last, gpst_week=week, gpst_tow_s=tow_s, x_ecef_m=tuple(x.tolist()))

    def update(self, fix: Fix) -> None:
        """Take a solver result: a published fix with a Doppler velocity is the next
        prediction's start."""
        if fix.ok and fix.x_ecef_m is not None and fix.velocity is not None:
            self._last = fix

    def predict(self, week: int, tow_s: float) -> np.ndarray | None:
        """The position [m, ECEF] predicted for GPS ``week`` + ``tow_s`` (None: no fix of
        the last :data:`PREDICTION_MAX_AGE_S`)."""
        last = self._last
        if last is None or last.x_ecef_m is None or last.velocity is None:
            return None
        dt = diff_s(week, tow_s, last.gpst_week, last.gpst_tow_s)
        if not 0.0 < dt <= PREDICTION_MAX_AGE_S:
            return None
        x = np.asarray(last.x_ecef_m, dtype=float)
        lat, lon, _ = ecef_to_geodetic(x)
        v_ecef = enu_rotation(lat, lon).T @ np.asarray(last.velocity.v_enu_m_s, dtype=float)
        return x + v_ecef * dt

    def screen(
        self,
        epoch: MeasurementEpoch,
        store: EphemerisStore,
        cfg: SolverConfig,
        sats: SatSide | None = None,
    ) -> tuple[MeasurementEpoch, dict[str, str]]:
        """``epoch`` without the full ranges longer than predicted by more than
        ``cfg.screen_predicted_m``, and why each was left out (``epoch`` itself and no
        reasons when the screen is off, there is no prediction, none is that long, or
        fewer than :data:`PREDICTION_MIN_ROWS` would remain). ``sats``: the epoch's
        :func:`sat_side`, when already computed."""
        limit = cfg.screen_predicted_m
        if not limit > 0.0:
            return epoch, {}
        x = self.predict(epoch.gpst_week, epoch.gpst_tow_s)
        if x is None:
            return epoch, {}
        res = predicted_residuals(epoch, store, x, sats)
        long = {p: r for p, r in res.items() if r > limit}
        if not long or len(res) - len(long) < PREDICTION_MIN_ROWS:
            return epoch, {}
        keep = [i for i, p in enumerate(epoch.prn) if p not in long]
        why = {p: excluded_why("predicted", res_m=r, limit_m=limit) for p, r in long.items()}
        return epoch.rows(keep), why


@dataclass(frozen=True, slots=True)
class SatSide:
    """What :func:`predicted_residuals` needs of an epoch that does not depend on the
    position: its full ranges with an ephemeris, each satellite at its transmit time."""

    prns: list[str]
    z_m: np.ndarray
    sat0_ecef_m: np.ndarray
    clk_m: np.ndarray
    omega_e_rad_s: np.ndarray


def sat_side(epoch: MeasurementEpoch, store: EphemerisStore) -> SatSide | None:
    """The satellites of ``epoch``'s full ranges at their transmit times (eqs. 4-5 of the
    kernel; None: no full range with an ephemeris)."""
    week, sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
    full = np.flatnonzero(np.isfinite(epoch.pr_m)).tolist()
    ephs, idx = select_rows(store, epoch.prn, full, week, sow)
    if not ephs:
        return None
    prns = [epoch.prn[i] for i in idx]
    arr = store.arrays(ephs)
    z = np.asarray(epoch.pr_m, dtype=float)[idx]
    sat0, clk = transmit_orbits(arr, week, sow, z)
    return SatSide(prns, z, sat0, clk, arr.omega_e_rad_s)


def with_screened(
    fix: Fix, screened: dict[str, str], epoch: MeasurementEpoch, store: EphemerisStore
) -> Fix:
    """``fix`` (solved without the ranges the screen left out) naming them in ``excluded``
    with their reasons, and its sky (if it has one) of every satellite of ``epoch``, the
    screened ones unused: what the stream and ``bdsfix solve`` publish of a screened epoch."""
    if not screened:
        return fix
    return replace(
        fix,
        excluded={**screened, **fix.excluded},
        sky=sky_view(epoch, store, fix) if fix.sky else fix.sky,
    )


def predicted_residuals(
    epoch: MeasurementEpoch,
    store: EphemerisStore,
    x_ecef_m: np.ndarray,
    sats: SatSide | None = None,
) -> dict[str, float]:
    """Each full range of ``epoch`` less the range predicted at ``x_ecef_m`` (satellite at
    its transmit time, eqs. 4-5 of the kernel, clock and group delay, Earth rotation during
    the flight; no ionosphere or troposphere), less its system's median (the receiver
    clock), for the systems with at least :data:`PREDICTION_MIN_SYSTEM_ROWS` such ranges.
    ``sats``: the epoch's :func:`sat_side`, when already computed."""
    side = sats if sats is not None else sat_side(epoch, store)
    if side is None:
        return {}
    prns = side.prns
    _, pred, _ = ranges(
        side.sat0_ecef_m, side.clk_m, np.asarray(x_ecef_m, dtype=float), side.omega_e_rad_s
    )
    v = side.z_m - pred
    out: dict[str, float] = {}
    for system in sorted({p[:1] for p in prns}):
        idx = [k for k, p in enumerate(prns) if p[:1] == system]
        if len(idx) < PREDICTION_MIN_SYSTEM_ROWS:
            continue
        med = median(v[idx].tolist())
        for k in idx:
            out[prns[k]] = float(v[k]) - med
    return out
