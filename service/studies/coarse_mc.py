"""Monte Carlo of the coarse-time first fix (service.engine.coarse) over the whole globe.

Each trial draws a receiver uniformly on the sphere (height 0-2 km; a share of aircraft at
250 m/s and 10 km), a horizontal velocity of 0-50 m/s in a random direction, a time in the
nav file's span and a host clock error uniform within the time prior (the receiver's tag
and ranges carry it together: :func:`service.sim.rangegen.true_ranges`, physically
generated with the broadcast Klobuchar model, Saastamoinen and 2 m of code noise). The
Doppler is the generator's carrier range rate (satellite motion, satellite clock rate,
delay rates) minus e . v (the receiver's motion), plus a receiver clock drift and
0.05 m/s of noise. Satellites above the solver's elevation mask are tracked; k of the GEOs
among them (0-3, drawn) are full, every other range is cut to 1 ms.

A trial succeeds with a published fix; it is wrong when any integer differs from the
generator's (absolute where the fix claims them, else relative within each system: to
its first fractional satellite); the figures also count fixes whose horizontal error
exceeds their HPL and fixes more than 100 m from the truth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from service.core.bds import is_geo
from service.core.constants import C_M_S
from service.core.ephemeris import EphemerisStore
from service.core.geometry import enu_rotation, geodetic_to_ecef
from service.core.systems import constants_of, wavelength_m
from service.core.timebase import gpst_to_bdt
from service.core.types import MeasurementEpoch
from service.engine.coarse import CoarseConfig, CoarseResult, solve_coarse
from service.engine.solver import IonoSet, SolverConfig
from service.sim.rangegen import true_ranges


@dataclass(frozen=True, slots=True)
class Trial:
    """One trial's draw and outcome."""

    lat_deg: float
    lon_deg: float
    speed_m_s: float
    clock_error_s: float
    n_sats: int
    k_geo: int
    fixed: bool
    wrong: bool  # a wrong integer
    reason_code: str | None
    error_m: float | None
    error_h_m: float | None = None
    hpl_m: float | None = None
    index: int = 0


@dataclass
class Summary:
    """The trials' figures."""

    trials: list[Trial] = field(default_factory=list)

    def figures(self) -> dict[str, float | int]:
        t = self.trials
        six = [x for x in t if x.n_sats >= 6]
        seven = [x for x in t if x.n_sats >= 7]
        fast = [x for x in t if x.speed_m_s > 100.0]
        out: dict[str, float | int] = {
            "trials": len(t),
            "fixed": sum(x.fixed for x in t),
            "wrong": sum(x.wrong for x in t),
            "beyond_hpl": sum(
                x.error_h_m is not None and x.hpl_m is not None and x.error_h_m > x.hpl_m for x in t
            ),
            "over_100_m": sum(x.error_m is not None and x.error_m > 100.0 for x in t),
            "with_6_sats": len(six),
            "success_pct_6": 100.0 * sum(x.fixed for x in six) / max(len(six), 1),
            "with_7_sats": len(seven),
            "success_pct_7": 100.0 * sum(x.fixed for x in seven) / max(len(seven), 1),
            "at_250_m_s": len(fast),
            "success_pct_250": 100.0 * sum(x.fixed for x in fast) / max(len(fast), 1),
        }
        errs = [x.error_m for x in t if x.fixed and x.error_m is not None]
        if errs:
            out["error_p50_m"] = float(np.median(errs))
            out["error_max_m"] = float(np.max(errs))
        return out

    def declines(self) -> dict[str, int]:
        out: dict[str, int] = {}
        for x in self.trials:
            if not x.fixed:
                key = x.reason_code or "?"
                out[key] = out.get(key, 0) + 1
        return out


def run_trial(
    store: EphemerisStore,
    iono: IonoSet,
    gpst_week: int,
    tow_range_s: tuple[float, float],
    rng: np.random.Generator,
    cfg: SolverConfig,
    ccfg: CoarseConfig,
    aircraft_share: float = 0.05,
) -> Trial:
    """One trial (module docstring)."""
    lat = math.asin(rng.uniform(-1.0, 1.0))
    lon = rng.uniform(-math.pi, math.pi)
    plane = rng.uniform() < aircraft_share
    h = 10_000.0 if plane else rng.uniform(0.0, 2_000.0)
    speed = 250.0 if plane else rng.uniform(0.0, 50.0)
    course = rng.uniform(0.0, 2 * math.pi)
    rot = enu_rotation(lat, lon)
    v = rot.T @ np.array([speed * math.sin(course), speed * math.cos(course), 0.0])
    tow = rng.uniform(*tow_range_s)
    clock_error = rng.uniform(-ccfg.time_prior_s, ccfg.time_prior_s)
    return simulate_and_solve(
        store, iono, gpst_week, tow, lat, lon, h, v, clock_error, None, rng, cfg, ccfg
    )


def simulate_and_solve(
    store: EphemerisStore,
    iono: IonoSet,
    gpst_week: int,
    tow: float,
    lat: float,
    lon: float,
    h: float,
    v: np.ndarray,
    clock_error: float,
    k_full: int | None,
    rng: np.random.Generator,
    cfg: SolverConfig,
    ccfg: CoarseConfig,
) -> Trial:
    """One simulated epoch at geodetic (``lat``, ``lon`` [rad], ``h`` [m]) moving at ECEF
    ``v`` [m/s], true GPST (``gpst_week``, ``tow``), host clock ``clock_error`` [s], with
    ``k_full`` GEOs full (None: drawn 0-3), solved by :func:`solve_coarse` (module docstring)."""
    rot = enu_rotation(lat, lon)
    x = geodetic_to_ecef(lat, lon, h)
    speed = float(np.linalg.norm(v))
    bdt_week, bdt_sow = gpst_to_bdt(gpst_week, tow)
    ephs = [e for p in sorted(store.prns) if (e := store.select(p, bdt_week, bdt_sow)) is not None]
    arr = store.arrays(ephs)
    tr = true_ranges(
        arr,
        x,
        gpst_week,
        tow,
        clock_error,
        iono=iono.preferred,
        tropo=True,
        noise_m=2.0,
        rng=rng,
    )
    seen = np.flatnonzero(tr.el_rad >= math.radians(cfg.elmask_deg))
    prn = [tr.prn[i] for i in seen]
    e = tr.sat_ecef_m[seen] - x
    e /= np.linalg.norm(e, axis=1)[:, None]
    drift = rng.uniform(-300.0, 300.0)
    rate = tr.carrier_rate_m_s[seen] - e @ v + drift + rng.normal(0.0, 0.05, len(seen))
    doppler = -rate / np.array([wavelength_m(p) for p in prn])
    geos = [p for p in prn if is_geo(p)]
    k = int(rng.integers(0, min(3, len(geos)) + 1)) if k_full is None else k_full
    full = set(geos[:k])
    pr = tr.pr_m[seen]
    other = np.array([p[:1] != "C" for p in prn], dtype=bool)
    if other.any():  # a receiver's inter-system bias, one per extra system, +-100 ns
        for letter in sorted({p[:1] for p in prn} - {"C"}):
            mine = np.array([p[:1] == letter for p in prn], dtype=bool)
            pr = pr + np.where(mine, rng.uniform(-30.0, 30.0), 0.0)
    # each row cut to its own system's code period (1 ms B1I and GPS C/A, 4 ms Galileo E1)
    period = np.array([constants_of(p).code_period_s for p in prn])
    ct = C_M_S * period
    epoch = MeasurementEpoch.from_columns(
        tr.tag_gpst_week,
        tr.tag_gpst_tow_s,
        prn,
        ["B1I" if p[:1] == "C" else constants_of(p).signal for p in prn],
        np.where([p in full for p in prn], pr, np.nan),
        frac_pr_m=np.mod(pr, ct),
        period_s=period,
        cn0_dbhz=np.full(len(prn), 42.0),
        doppler_hz=doppler,
    )
    res = solve_coarse(epoch, store, iono, cfg, ccfg)
    truth = {
        p: round((r - np.mod(r, c)) / c)
        for p, r, c in zip(prn, pr.tolist(), ct.tolist(), strict=True)
    }
    wrong, err = _judge(res, truth, x)
    err_h = None
    if res.fix.ok and res.fix.x_ecef_m is not None:
        d_enu = rot @ np.subtract(res.fix.x_ecef_m, x)
        err_h = math.hypot(float(d_enu[0]), float(d_enu[1]))
    return Trial(
        math.degrees(lat),
        math.degrees(lon),
        speed,
        clock_error,
        len(prn),
        k,
        res.fix.ok,
        wrong,
        res.fix.reason_code,
        err,
        err_h,
        res.fix.hpl_m,
    )


def _judge(res: CoarseResult, truth: dict[str, int], x: np.ndarray) -> tuple[bool, float | None]:
    if not res.fix.ok or res.fix.x_ecef_m is None:
        return False, None
    err = float(np.linalg.norm(np.subtract(res.fix.x_ecef_m, x)))
    ints = res.integers or {}
    if res.absolute:
        bad = any(ints[p] != truth[p] for p in ints)
    else:  # system by system (a system without a full row has its whole period in its clock)
        first: dict[str, str] = {}
        for p in ints:
            first.setdefault(p[:1], p)
        bad = any(ints[p] - ints[first[p[:1]]] != truth[p] - truth[first[p[:1]]] for p in ints)
    return bad, err


def run(
    store: EphemerisStore,
    iono: IonoSet,
    gpst_week: int,
    tow_range_s: tuple[float, float],
    n: int,
    seed: int = 1,
    cfg: SolverConfig | None = None,
    ccfg: CoarseConfig | None = None,
) -> Summary:
    """``n`` trials with a fixed seed."""
    rng = np.random.default_rng(seed)
    cfg = cfg or SolverConfig()
    ccfg = ccfg or CoarseConfig()
    out = Summary()
    for i in range(n):
        trial = run_trial(store, iono, gpst_week, tow_range_s, rng, cfg, ccfg)
        out.trials.append(replace(trial, index=i))
    return out
