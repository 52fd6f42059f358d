"""Height aiding: a pseudo-observation of the receiver's ellipsoidal height from its own
recent fixes, for a receiver whose height changes slowly (a car, a ship, a walker; not an
aircraft or a drone), as land-vehicle receivers do (their "automotive" dynamic model).

In a street canyon the rows that remain are few and mostly from high elevations, so the
vertical is the weakest direction, and reflected (NLOS) ranges, which are long, push the fix
upwards by tens to hundreds of metres while the chi-square test still passes
(docs/method.md, "Urban drive"). A height known to a few metres from the last half minute of
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
  its 68th percentile at 0.84 and its 95th at 1.27 (docs/method.md).
- The row is in the error model: weighted by its sigma, it enters the chi-square test and
  the protection levels like a range (a fault in the aid has its slope too); fault
  exclusion never removes it. The DOPs stay the satellites' geometry.
- No aid for a first fix (no history), after a gap longer than the window with no fix,
  or after a receiver restart (:meth:`HeightAid.reset`).

The kernel's mechanism is :attr:`service.engine.solver.SolverConfig.height_aid` (phase 2
only, so the fast fix and SPP of the same rows with the same aid are the same solution).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field, replace

import numpy as np

from service.core.geometry import ecef_to_geodetic
from service.core.timebase import diff_s
from service.core.types import Fix
from service.engine.solver import SolverConfig


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
        h = float(np.median([f.h_m for f in held]))
        newest, oldest = held[-1], held[0]
        dt = diff_s(week, tow_s, newest.week, newest.tow_s)
        span = _horizontal_m(newest.x_ecef_m, oldest.x_ecef_m)
        d = span / 2.0 + newest.speed_m_s * dt
        sigma = math.sqrt(
            cfg.height_aid_sigma_m**2
            + (cfg.height_aid_rate_m_s * dt) ** 2
            + (cfg.height_aid_grade * d) ** 2
        )
        return h, sigma

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


def _horizontal_m(a: np.ndarray, b: np.ndarray) -> float:
    """The horizontal distance [m] between two ECEF points (the chord less its vertical
    part at ``a``)."""
    d = a - b
    up = a / np.linalg.norm(a)
    return float(np.linalg.norm(d - up * float(d @ up)))
