"""Receiver velocity and clock drift from Doppler: a second weighted least-squares problem
beside the position fix (docs/method.md, "Velocity").

A Doppler shift D [Hz] of a carrier of wavelength lambda is a pseudorange rate
rdot = -lambda D (every driver gives D positive for an approaching satellite: UBX RXM-RAWX
``doMes``, RINEX 3.04 5.3 ``D``, RTCM 3 MSM phase-range rate converted by the driver). With
the satellite's position s and velocity v_s at transmit time rotated into the receive-time
Earth frame (the same rotation as the pseudorange's Sagnac term), e the unit vector
receiver -> satellite, v the receiver's velocity and d = c * (receiver clock rate), the
observation equation is (Kaplan & Hegarty, *Understanding GPS/GNSS*, 3rd ed., 9.3; RTKLIB
``resdop``)

    rdot_i + c * dts_i/dt - e_i . v_s,i = -e_i . v + d,

linear in the unknowns (v, d): no iteration. The satellite terms come from the broadcast
ephemeris (:func:`service.core.orbit.sat_pos_vel_clock`, BDS-SIS-ICD-B1I-3.0 5.2.4.10 and
5.2.4.12 differentiated); the ionospheric and tropospheric delay rates (mm/s) are neglected.
In the rotating frame the Earth's rotation adds nothing to e . v_s: the inertial velocities
differ from the rotated ECEF ones by omega x s and omega x x, whose difference
omega x (s - x) is perpendicular to e.

The rows are weighted by 1/sigma_i^2 with sigma_i from elevation and C/N0
(:class:`VelocityConfig`); the covariance (H^T W H)^-1 gives the sigmas. With redundancy
r = rows - unknowns >= 1 (velocity and one clock drift per system,
:mod:`service.engine.layout`), the residuals' weighted sum of squares is tested against the
chi-square quantile (as :mod:`service.engine.raim` tests the position); while it fails, the
row with the largest normalised residual (w-test, Baarda) is removed, up to ``max_exclusions``
times, each only from redundancy >= 2 (at redundancy 1 every w-test has the same size). A
solution that still fails, or one without enough rows, is not reported (None).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from functools import lru_cache

import numpy as np

from service.core.constants import C_M_S, NOMINAL_FLIGHT_TIME_S
from service.core.corrections import sagnac_rotate
from service.core.ephemeris import EphemerisStore
from service.core.geometry import enu_rotations_at
from service.core.orbit import sat_pos_clock, sat_pos_vel_clock
from service.core.systems import wavelength_m
from service.core.timebase import gpst_to_bdt
from service.core.types import Ephemeris, Fix, MeasurementEpoch, Velocity
from service.engine import linalg
from service.engine.layout import Layout, layout_of
from service.engine.raim import chi2_threshold

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class VelocityConfig:
    """Error model and test of the Doppler rows.

    sigma_i^2 = (sigma_a^2 + (sigma_b / sin E)^2) * 10^((cn0_ref - C/N0) / 10): a
    range-rate noise that grows at low elevation and with the inverse of the signal power
    (the carrier tracking loop's jitter, Kaplan & Hegarty 8.8). With the defaults the
    residuals' chi2 / redundancy has median 0.53 on the urban TST u-blox drive (after
    exclusions, in 475 of its 1448 tested epochs) and 0.12 on the HKSC geodetic receiver,
    whose Doppler is about three times less noisy than the model says.
    """

    sigma_a_m_s: float = 0.03
    sigma_b_m_s: float = 0.03
    cn0_ref_dbhz: float = 45.0
    elmask_deg: float = 5.0
    p_fa: float = 1e-3
    max_exclusions: int = 4


@dataclass(frozen=True, slots=True, eq=False)
class DopplerRows:
    """The inputs of :func:`solve_velocity`: one row per satellite, all at one epoch.

    ``range_rate_m_s`` is -lambda * Doppler; satellite states are at transmit time, already
    rotated into the receive-time Earth frame; ``sat_clock_drift_s_s`` is the satellite clock's
    rate (dts/dt)."""

    prn: tuple[str, ...]
    range_rate_m_s: np.ndarray
    cn0_dbhz: np.ndarray
    sat_ecef_m: np.ndarray
    sat_vel_ecef_m_s: np.ndarray
    sat_clock_drift_s_s: np.ndarray


def range_rate_m_s(prn: tuple[str, ...] | list[str], doppler_hz: np.ndarray) -> np.ndarray:
    """-lambda * D with each satellite system's carrier (:func:`wavelength_m`)."""
    lam = np.array([wavelength_m(p) for p in prn])
    return -lam * np.asarray(doppler_hz, dtype=float)


def solve_velocity(
    rows: DopplerRows, x_ecef_m: np.ndarray, cfg: VelocityConfig | None = None
) -> Velocity | None:
    """Velocity and clock drift of a receiver at ``x_ecef_m`` (module docstring), or None
    when fewer than four rows remain above the mask or the residual test fails after
    ``cfg.max_exclusions`` exclusions: :func:`solve_velocities` of one epoch."""
    return solve_velocities([(rows, np.asarray(x_ecef_m, dtype=float))], cfg)[0]


def solve_velocities(
    problems: Sequence[tuple[DopplerRows, np.ndarray]], cfg: VelocityConfig | None = None
) -> list[Velocity | None]:
    """:func:`solve_velocity` of each (rows, receiver position), as one computation over
    epochs x rows per set of systems (the rows padded to the longest epoch, padding
    weighted 0): one epoch alone and the same epoch among others give the same solution.
    The exclusion rounds continue only for the epochs whose test failed.

    Epochs whose rows name different systems are solved in separate computations, each with
    the clock drifts of its own systems: in one layout over all of them an epoch without a
    system's rows would have a column of zeros (a singular system: no velocity, though it has
    one alone; 13 of 1603 TST fixes of ``bdsfix solve --systems C,G,E`` lost theirs so)."""
    groups: dict[Layout, list[int]] = {}
    for k, (rows, _) in enumerate(problems):
        groups.setdefault(layout_of(rows.prn), []).append(k)
    if len(groups) <= 1:
        return _solve_velocities(problems, cfg)
    out: list[Velocity | None] = [None] * len(problems)
    for idx in groups.values():
        for k, vel in zip(idx, _solve_velocities([problems[k] for k in idx], cfg), strict=True):
            out[k] = vel
    return out


def _solve_velocities(
    problems: Sequence[tuple[DopplerRows, np.ndarray]], cfg: VelocityConfig | None
) -> list[Velocity | None]:
    """:func:`solve_velocities` of problems whose rows have one layout."""
    cfg = cfg or VelocityConfig()
    n_ep = len(problems)
    if n_ep == 0:
        return []
    counts = [len(rows.prn) for rows, _ in problems]
    width = max(counts)
    # the rows of all epochs, one after the other; (epoch, slot) places each in the padding
    # (one epoch: its rows are its slots, no padding)
    one = n_ep == 1
    if one:
        ep_of = np.zeros(width, dtype=np.intp)
    else:
        ep_of = np.repeat(np.arange(n_ep), counts)
        slot = np.arange(len(ep_of)) - np.repeat(np.cumsum(counts) - counts, counts)
    cat = np.concatenate if not one else _first
    sat = cat([rows.sat_ecef_m for rows, _ in problems])
    x_ep = np.array([np.asarray(x, dtype=float) for _, x in problems])
    d = sat - x_ep[ep_of]
    e = d / np.sqrt(linalg.einsum("ij,ij->i", d, d))[:, None]
    rots = enu_rotations_at(x_ep)
    sin_el = linalg.einsum("ij,ij->i", e, rots[ep_of, 2])
    y_row = (
        cat([rows.range_rate_m_s for rows, _ in problems])
        + C_M_S * cat([rows.sat_clock_drift_s_s for rows, _ in problems])
        - linalg.einsum("ij,ij->i", e, cat([rows.sat_vel_ecef_m_s for rows, _ in problems]))
    )
    cn0 = cat([rows.cn0_dbhz for rows, _ in problems])
    cn0 = np.where(np.isfinite(cn0), cn0, cfg.cn0_ref_dbhz)
    s = np.maximum(sin_el, 0.05)
    var_row = (cfg.sigma_a_m_s**2 + (cfg.sigma_b_m_s / s) ** 2) * 10.0 ** (
        (cfg.cn0_ref_dbhz - cn0) / 10.0
    )
    # the unknowns: velocity (ECEF) and one clock drift per system (service/engine/layout.py)
    prn_all = [p for rows, _ in problems for p in rows.prn] if not one else problems[0][0].prn
    layout = _velocity_layout(layout_of(prn_all))
    n_params = layout.n_params
    design = layout.design(e, None if layout.n_clocks == 1 else layout.clock_index(prn_all))
    keep_row = np.isfinite(y_row) & (sin_el >= math.sin(math.radians(cfg.elmask_deg)))
    if one:  # every slot a row: the rows' arrays as the one epoch's
        h, y, var, keep = design[None], y_row[None], var_row[None], keep_row[None]
    else:
        h = np.zeros((n_ep, width, n_params))
        h[ep_of, slot] = design
        y = np.zeros((n_ep, width))
        y[ep_of, slot] = y_row
        var = np.ones((n_ep, width))
        var[ep_of, slot] = var_row
        keep = np.zeros((n_ep, width), dtype=bool)
        keep[ep_of, slot] = keep_row
    y = np.where(keep, y, 0.0)
    w = 1.0 / var
    out: list[Velocity | None] = [None] * n_ep
    excluded: list[list[str]] = [[] for _ in range(n_ep)]
    todo = np.arange(n_ep)
    for _ in range(cfg.max_exclusions + 1):
        todo = todo[keep[todo].sum(axis=1) >= n_params]
        if len(todo) == 0:
            break
        hk, yk, kk = h[todo], y[todo], keep[todo]
        wk = np.where(kk, w[todo], 0.0)
        hw = hk * wk[:, :, None]  # (epochs, rows, unknowns): rows of H weighted
        normal = hw.transpose(0, 2, 1) @ hk
        try:
            cov = linalg.inv(normal)
        except np.linalg.LinAlgError:  # some epoch singular: find it, go on without
            ok = np.array([np.linalg.matrix_rank(m) == n_params for m in normal])
            todo, hk, yk, kk, wk, hw = todo[ok], hk[ok], yk[ok], kk[ok], wk[ok], hw[ok]
            cov = np.linalg.inv(normal[ok])
        sol = (cov @ (hw.transpose(0, 2, 1) @ yk[:, :, None]))[:, :, 0]
        resid = np.where(kk, yk - (hk @ sol[:, :, None])[:, :, 0], 0.0)
        chi2 = (resid * wk * resid).sum(axis=1)
        dof = np.asarray(layout.redundancy(kk.sum(axis=1)))
        chi2_max = np.array(
            [chi2_threshold(r, cfg.p_fa) if r > 0 else math.inf for r in dof.tolist()]
        )
        passed = (dof == 0) | (chi2 <= chi2_max)
        rot_p = rots[todo[passed]]
        v_enu = (rot_p @ sol[passed, :3, None])[:, :, 0]
        q_enu = rot_p @ cov[passed, :3, :3] @ rot_p.transpose(0, 2, 1)
        for m, j in enumerate(np.flatnonzero(passed).tolist()):
            k = int(todo[j])
            out[k] = _velocity(
                problems[k][0],
                sol[j],
                cov[j],
                v_enu[m],
                q_enu[m],
                keep[k],
                excluded[k],
                int(dof[j]),
                float(chi2[j]) if dof[j] > 0 else None,
                float(chi2_max[j]) if dof[j] > 0 else None,
            )
        # an exclusion must leave a testable solution (redundancy >= 1 after it), as fault
        # exclusion of the position requires: at redundancy 1 every row's w-test has the
        # same size, so which row is "worst" is rounding (a failed test there: no velocity)
        failed = np.flatnonzero(~passed & (dof >= 2))
        if len(failed) == 0:
            todo = failed
            break
        # w-test: each residual over its own standard deviation, sigma_i^2 - (H Q H^T)_ii
        hf, covf = hk[failed], cov[failed]
        q_v = 1.0 / w[todo[failed]] - linalg.einsum("esi,eij,esj->es", hf, covf, hf)
        wtest = np.abs(resid[failed]) / np.sqrt(np.maximum(q_v, 1e-12))
        worst = np.argmax(np.where(kk[failed], wtest, -1.0), axis=1)
        for k, i in zip(todo[failed].tolist(), worst.tolist(), strict=True):
            keep[k, i] = False
            excluded[k].append(problems[k][0].prn[i])
        todo = todo[failed]
    if len(todo):
        log.debug("velocity: Doppler residuals of %d epochs fail the test", len(todo))
    return out


def _velocity(
    rows: DopplerRows,
    sol: np.ndarray,
    cov: np.ndarray,
    v_enu: np.ndarray,
    q_enu: np.ndarray,
    keep: np.ndarray,
    excluded: list[str],
    redundancy: int,
    chi2: float | None,
    chi2_max: float | None,
) -> Velocity | None:
    """The :class:`Velocity` of one epoch's solution: ENU velocity and covariance, speed and
    course with their sigmas by first-order propagation."""
    if not all(map(math.isfinite, sol.tolist())):
        return None
    ve, vn = float(v_enu[0]), float(v_enu[1])
    speed = math.hypot(ve, vn)
    qee, qnn, qen = float(q_enu[0, 0]), float(q_enu[1, 1]), float(q_enu[0, 1])
    if speed > 0.0:
        var_speed = (ve * ve * qee + vn * vn * qnn + 2 * ve * vn * qen) / speed**2
        var_course = (vn * vn * qee + ve * ve * qnn - 2 * ve * vn * qen) / speed**4
        std_course = min(math.degrees(math.sqrt(max(var_course, 0.0))), 180.0)
    else:
        var_speed, std_course = (qee + qnn) / 2, 180.0
    std_enu = [math.sqrt(max(float(q_enu[k, k]), 0.0)) for k in range(3)]
    return Velocity(
        v_enu_m_s=(ve, vn, float(v_enu[2])),
        std_v_enu_m_s=(std_enu[0], std_enu[1], std_enu[2]),
        speed_m_s=speed,
        std_speed_m_s=math.sqrt(max(var_speed, 0.0)),
        course_deg=math.degrees(math.atan2(ve, vn)) % 360.0,
        std_course_deg=std_course,
        clock_drift_m_s=float(sol[3]),
        std_clock_drift_m_s=math.sqrt(max(float(cov[3, 3]), 0.0)),
        used=tuple(rows.prn[i] for i in np.flatnonzero(keep[: len(rows.prn)]).tolist()),
        excluded=tuple(excluded),
        redundancy=redundancy,
        chi2=chi2,
        chi2_max=chi2_max,
    )


def _first(arrays: Sequence[np.ndarray]) -> np.ndarray:
    """The one array of ``arrays`` (one epoch's rows: nothing to concatenate)."""
    return arrays[0]


@lru_cache(maxsize=64)
def _velocity_layout(position: Layout) -> Layout:
    """The velocity problem's unknowns for rows of ``position``'s systems: velocity and a
    clock drift per system."""
    return replace(position, problem="velocity")


@dataclass(frozen=True, slots=True)
class RowRequest:
    """What :func:`doppler_rows_many` needs of one epoch: the epoch, the receiver position
    and clock bias of its fix, the satellites to use (None: all) and the full pseudoranges
    of fractional satellites (the fast fix's recovered ones)."""

    epoch: MeasurementEpoch
    x_ecef_m: np.ndarray
    clock_bias_m: float = 0.0
    prns: tuple[str, ...] | None = None
    pr_m: dict[str, float] | None = None


def doppler_rows_many(
    requests: Sequence[RowRequest], store: EphemerisStore
) -> list[DopplerRows | None]:
    """For each request, the rows of its epoch (those of ``prns`` when given) that have a
    Doppler and an ephemeris, with the satellites' states at transmit time for a receiver
    at ``x_ecef_m`` whose clock is ``clock_bias_m`` ahead (None: no such row). The orbits
    of all requests are computed in one call.

    The flight time is the pseudorange (the epoch's, else ``pr_m``) less the receiver
    clock, over c; a satellite without one is first placed :data:`NOMINAL_FLIGHT_TIME_S`
    back and its flight time taken from that position. A flight time wrong by 1 ms moves a
    range rate by < 1 mm/s."""
    row_sets: list[Ephemeris] = []  # each row's set; their arrays are built once at the end
    metas: list[tuple[int, tuple[str, ...]]] = []
    # per row, in plain floats (the same IEEE arithmetic as numpy's, without its per-call
    # cost on a dozen values): week, transmit time, flight time, Doppler, C/N0, wavelength
    weeks: list[int] = []
    times: list[float] = []
    taus: list[float] = []
    dops: list[float] = []
    cn0s: list[float] = []
    lams: list[float] = []
    out: list[DopplerRows | None] = [None] * len(requests)
    # an epoch's columns as floats and its sets by satellite, once for the requests of
    # several solvers (bdsfix solve --mode both)
    seen: dict[int, tuple[list[float], list[float], list[float], dict[str, Ephemeris | None]]]
    seen = {}
    finite = math.isfinite
    for k, req in enumerate(requests):
        epoch = req.epoch
        bdt_week, bdt_sow = gpst_to_bdt(epoch.gpst_week, epoch.gpst_tow_s)
        bias_m = req.clock_bias_m if finite(req.clock_bias_m) else 0.0
        t_rx = bdt_sow - bias_m / C_M_S
        wanted = None if req.prns is None else set(req.prns)
        cols = seen.get(id(epoch))
        if cols is None:
            cols = seen[id(epoch)] = (
                epoch.pr_m.tolist(),
                epoch.doppler_hz.tolist(),
                epoch.cn0_dbhz.tolist(),
                {},
            )
        pr_all, dop_all, cn0_all, known = cols
        idx: list[int] = []
        ephs: list[Ephemeris] = []
        for i, dop in enumerate(dop_all):
            if not finite(dop):
                continue
            sat = epoch.prn[i]
            if wanted is not None and sat not in wanted:
                continue
            if sat in known:
                eph = known[sat]
            else:
                eph = known[sat] = store.select(sat, bdt_week, bdt_sow)
            if eph is not None:
                idx.append(i)
                ephs.append(eph)
        if not idx:
            continue
        prn = tuple(epoch.prn[i] for i in idx)
        pr = [pr_all[i] for i in idx]
        if not all(map(finite, pr)):
            recovered = req.pr_m or {}
            pr = [float(recovered.get(p, v)) for p, v in zip(prn, pr, strict=True)]
        tau = [(v - bias_m) / C_M_S for v in pr]
        if not all(map(finite, tau)):
            first, _ = sat_pos_clock(
                store.arrays(ephs), bdt_week, np.full(len(idx), t_rx - NOMINAL_FLIGHT_TIME_S)
            )
            dist_s = (np.linalg.norm(first - req.x_ecef_m, axis=1) / C_M_S).tolist()
            tau = [t if finite(t) else d for t, d in zip(tau, dist_s, strict=True)]
        row_sets += ephs
        weeks += [bdt_week] * len(idx)
        times += [t_rx - t for t in tau]
        taus += tau
        dops += [dop_all[i] for i in idx]
        cn0s += [cn0_all[i] for i in idx]
        lams += [wavelength_m(p) for p in prn]
        metas.append((k, prn))
    if not row_sets:
        return out
    # the distinct sets as arrays once (a chunk's rows share a few tens), then one row each
    position: dict[int, int] = {}
    distinct: list[Ephemeris] = []
    for e in row_sets:
        if id(e) not in position:
            position[id(e)] = len(distinct)
            distinct.append(e)
    arr = store.arrays(distinct)
    if len(distinct) != len(row_sets):
        arr = arr.take([position[id(e)] for e in row_sets])
    # else each row its own set, in order (one epoch): the store's arrays themselves, not a
    # copy, so the orbit's per-set terms are the ones memoised for them (orbit._constants)
    tau_all = np.array(taus)
    pos, vel, _, drift = sat_pos_vel_clock(arr, np.array(weeks), np.array(times))
    omega = arr.omega_e_rad_s
    pos, vel = sagnac_rotate(pos, tau_all, omega), sagnac_rotate(vel, tau_all, omega)
    rate = -np.array(lams) * np.array(dops)  # range_rate_m_s of every row
    cn0 = np.array(cn0s)
    start = 0
    for k, prn in metas:
        end = start + len(prn)
        out[k] = DopplerRows(
            prn=prn,
            range_rate_m_s=rate[start:end],
            cn0_dbhz=cn0[start:end],
            sat_ecef_m=pos[start:end],
            sat_vel_ecef_m_s=vel[start:end],
            sat_clock_drift_s_s=drift[start:end],
        )
        start = end
    return out


def with_velocity(
    fix: Fix, epoch: MeasurementEpoch, store: EphemerisStore, cfg: VelocityConfig | None = None
) -> Fix:
    """``fix`` with its :class:`Velocity` from ``epoch``'s Doppler (the satellites the fix
    used), or ``fix`` itself when it has no position or the velocity is not trusted."""
    return with_velocities([(fix, epoch)], store, cfg)[0]


def with_velocities(
    pairs: Sequence[tuple[Fix, MeasurementEpoch]],
    store: EphemerisStore,
    cfg: VelocityConfig | None = None,
) -> list[Fix]:
    """:func:`with_velocity` of each (fix, epoch), computed together (the batch path of
    ``bdsfix solve``; the same values as one by one)."""
    requests: list[RowRequest] = []
    owners: list[int] = []
    for k, (fix, epoch) in enumerate(pairs):
        if fix.ok and fix.x_ecef_m is not None and fix.used:
            bias = fix.clock_bias_m if fix.clock_bias_m is not None else 0.0
            x = np.asarray(fix.x_ecef_m, dtype=float)
            requests.append(RowRequest(epoch, x, bias, fix.used, fix.recovered_pr_m))
            owners.append(k)
    out = [fix for fix, _ in pairs]
    if not requests:
        return out
    try:
        with np.errstate(all="ignore"):
            rows = doppler_rows_many(requests, store)
            problems = [(r, req.x_ecef_m) for r, req in zip(rows, requests, strict=True) if r]
            solved = iter(solve_velocities(problems, cfg))
    except (np.linalg.LinAlgError, ArithmeticError, ValueError):
        log.debug("velocity failure", exc_info=True)
        return out
    for k, r in zip(owners, rows, strict=True):
        vel = next(solved) if r is not None else None
        if vel is not None:
            out[k] = replace(out[k], velocity=vel)
    return out
