"""Batch solving for files: many epochs at once, vectorised across epochs and satellites.

:func:`solve_many` gives, for a sequence of epochs, what :func:`service.engine.solver.solve`
gives for each (the same phases, GEO-GDOP gate, mask, corrections, weights, chi-square test
and checks; docs/method.md), but each step of the iteration is one set of numpy operations on
(epoch, satellite) arrays for a chunk of epochs instead of one set per epoch, so the Python
cost per epoch is paid once per chunk:

- phase 1 (paper eqs. 3-16) from the Earth's centre with the backtracking step, all epochs
  of the chunk in lockstep; an epoch that has converged keeps its state. The x/b step is
  the least-squares step over the full rows: each fractional row has its own ambiguity
  column in eq. (11), so its residual is absorbed by dN_j = h_j . [dx, db] - dz_j (in
  metres, rounded in units of c*T by eq. 13), which is the solution of the augmented
  system of eq. (10) without forming it (the per-epoch solver forms it: the same step in
  exact arithmetic, not in rounding, so no convergence is the per-epoch solver's to
  decide). The satellites' orbits (eqs. 4-5) depend on the integers only: an epoch's are
  computed again only when a step moves its integers;
- phase 2: the elevation mask, Klobuchar, Saastamoinen and the error model's weights,
  iterated to convergence (the ranges, delays and weights are the per-epoch solver's own
  functions, :func:`~service.engine.solver.ranges`, :func:`~service.engine.solver.delays`,
  :func:`~service.engine.solver.measurement_sigma_m`, over (epoch, satellite) arrays);
- the judgement: the chi-square test and protection levels
  (:func:`service.engine.raim.assess_many`, which the per-epoch solver calls with one
  epoch), the plausible shell and the PDOP gate, in the one judgement both paths call
  (:func:`service.engine.judge.verdict`); the declines of no rows, too few full ranges (also
  above the mask), the GEO-GDOP gate, a failed test, an implausible solution and the PDOP
  gate are built here by the builders both paths call (:mod:`service.engine.judge`), in the
  words of the one table (:mod:`service.core.declines`);
- the unknowns are the chunk's rows' :class:`~service.engine.layout.Layout`: a receiver
  clock per satellite system (a chunk whose epochs differ in their systems is solved one
  layout at a time);
- fault exclusion: the one loop both paths run (:func:`service.engine.judge.exclude`),
  with every candidate of every failed epoch of a stage in one batch, each starting where
  the per-epoch solver's would (:attr:`~service.engine.judge.Failed.warm_start`); a
  candidate the batch cannot decide is solved by the per-epoch solver's attempt at it
  (:func:`~service.engine.solver.attempt`), not its whole epoch.

An epoch without a GPS week is declined ``no_time`` here; with the test off (``p_fa=0``)
the batch judges as with it (no failed test to exclude from). A position far from the Earth
(a gross fault can put phase 1 there) is judged as the per-epoch solver judges it: no mask,
no corrections, one weight for every row. An epoch the batch cannot decide (an impossible
range, no convergence in phase 1, a singular system, a position not finite, the fast fix of
rows of several systems) and every epoch when a start position is given
(``SolverConfig.x0_ecef_m``: phase 2 alone) is solved by
:func:`~service.engine.solver.solve`. A fix from the batch equals the per-epoch solver's to
floating-point rounding (tests/engine/test_batch.py holds them to 1e-6 m on real files),
and an epoch solved alone equals the same epoch inside a chunk (the same bits where the
chunk has no padding slots).

The stream path (daemon, replay) keeps the per-epoch solver: an epoch is solved as it
arrives.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence
from dataclasses import replace
from typing import Literal

import numpy as np

from service.core.constants import C_M_S
from service.core.declines import Decline, Declined
from service.core.ephemeris import EphemerisStore
from service.core.geometry import ecef_to_geodetic, enu_rotation, look_angles
from service.core.orbit import EphemerisArrays, sat_pos_clock
from service.core.timebase import gpst_to_bdt
from service.core.types import Ephemeris, Fix, MeasurementEpoch
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
from service.engine.solver import (
    GROSS_SPREAD_M,
    IonoSet,
    SolverConfig,
    attempt,
    declined,
    measurement_sigma_m,
    ranges,
    sky_view,
    solve,
    system_delays,
    total_delay,
)

log = logging.getLogger(__name__)


CHUNK_EPOCHS = 256
"""Epochs solved together: large enough that numpy's per-call cost is spread thin, small
enough that the arrays stay in cache and output keeps flowing."""

_EPH_FIELDS = tuple(f for f in EphemerisArrays.__dataclass_fields__ if f != "prn")


class _Chunk:
    """The rows of a chunk of epochs as (epoch, slot) arrays; ``valid`` marks real rows."""

    def __init__(
        self,
        epochs: Sequence[MeasurementEpoch],
        store: EphemerisStore,
        solver: Literal["fast", "spp"],
    ) -> None:
        n_e = len(epochs)
        bdt = [gpst_to_bdt(ep.gpst_week, ep.gpst_tow_s) for ep in epochs]
        self.epochs = epochs
        self.bdt_week = np.array([w for w, _ in bdt], dtype=float)
        self.bdt_sow = np.array([s for _, s in bdt])
        # every measurement of the chunk in one flat column each
        sizes = [len(ep.prn) for ep in epochs]
        owner = np.repeat(np.arange(n_e), sizes)
        pr = np.concatenate([ep.pr_m for ep in epochs]) if n_e else np.zeros(0)
        frac_pr = np.concatenate([ep.frac_pr_m for ep in epochs]) if n_e else np.zeros(0)
        period = np.concatenate([ep.period_s for ep in epochs]) if n_e else np.zeros(0)
        cn0 = np.concatenate([ep.cn0_dbhz for ep in epochs]) if n_e else np.zeros(0)
        full = np.isfinite(pr)
        use = full
        if solver == "fast":
            use = full | (np.isfinite(frac_pr) & np.isfinite(period))
        prns = [p for ep in epochs for p in ep.prn]
        table: dict[int, int] = {}
        unique: list[Ephemeris] = []
        picked: list[int] = []  # flat index of each row
        eph_idx: list[int] = []
        # per epoch, its usable measurements without an ephemeris (select_rows' "missing")
        self.missing: list[list[str]] = [[] for _ in range(n_e)]
        for f in np.flatnonzero(use).tolist():
            k = int(owner[f])
            e = store.select(prns[f], *bdt[k])
            if e is None:
                self.missing[k].append(prns[f])
                continue
            u = table.get(id(e))
            if u is None:
                u = table[id(e)] = len(unique)
                unique.append(e)
            picked.append(f)
            eph_idx.append(u)
        rows = np.array(picked, dtype=int)
        row_owner = owner[rows]
        counts = np.bincount(row_owner, minlength=n_e)
        n_s = max(1, int(counts.max()) if n_e else 1)
        # slot of each row within its epoch: its rank among the epoch's rows
        first = np.concatenate([[0], np.cumsum(counts)[:-1]]) if n_e else np.zeros(0, int)
        slot = np.arange(len(rows)) - first[row_owner]
        self.valid = np.zeros((n_e, n_s), dtype=bool)
        self.z = np.zeros((n_e, n_s))
        self.ct = np.zeros((n_e, n_s))
        self.cn0 = np.full((n_e, n_s), np.nan)
        idx = np.zeros((n_e, n_s), dtype=int)
        at = (row_owner, slot)
        self.valid[at] = True
        self.z[at] = np.where(full[rows], pr[rows], frac_pr[rows])
        self.ct[at] = np.where(full[rows], 0.0, C_M_S * period[rows])
        self.cn0[at] = cn0[rows]
        idx[at] = eph_idx
        row_prns = [prns[f] for f in picked]
        ends = np.cumsum(counts).tolist()
        self.prn = [tuple(row_prns[a:b]) for a, b in zip([0, *ends[:-1]], ends, strict=True)]
        if not unique:  # nothing selectable: every epoch goes to the per-epoch solver
            unique.append(_placeholder())
        cols = EphemerisArrays.from_ephemerides(unique)
        self.eph = _gather(cols, idx)
        self.frac = self.valid & (self.ct > 0)
        self.full = self.valid & ~self.frac
        # the unknowns: one layout for the chunk (None: its epochs' rows differ in their
        # systems, and :func:`_outcomes` solves each layout's epochs as a chunk of their own)
        layouts = {layout_of(ps) for ps in self.prn if ps}
        self.layout: Layout | None = layouts.pop() if len(layouts) == 1 else None
        if not layouts and self.layout is None:
            self.layout = BDS_ONLY
        self.cix = np.zeros((n_e, n_s), dtype=np.intp)  # each row's clock (padding: 0)
        if self.layout is not None and self.layout.n_clocks > 1:
            for k, ps in enumerate(self.prn):
                self.cix[k, : len(ps)] = self.layout.clock_index(ps)


def _placeholder() -> Ephemeris:
    z = 0.0
    return Ephemeris("C01", 0, z, z, z, z, z, 6493.0, z, z, z, z, z, z, z, z, z, z, z, z, z, z)


def _gather(cols: EphemerisArrays, idx: np.ndarray) -> EphemerisArrays:
    """Ephemeris columns indexed by ``idx`` (any shape); ``prn`` is not carried."""
    kw = {name: getattr(cols, name)[idx] for name in _EPH_FIELDS}
    return EphemerisArrays(prn=(), **kw)


def _orbits(ch: _Chunk, sel: np.ndarray, n_int: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Satellite positions and clocks at the transmit times of eqs. (4)-(5) for epochs
    ``sel`` with integers ``n_int`` (as :func:`service.engine.solver._geometry`)."""
    # every epoch of the chunk (the start of phase 1): its columns as they are, not copied
    eph = ch.eph if len(sel) == len(ch.z) else _gather_rows(ch.eph, sel)
    sow = ch.bdt_sow[sel, None]
    t1 = sow - (ch.z[sel] + n_int * ch.ct[sel]) / C_M_S
    t_tx = t1 - (eph.af0_s + eph.af1_s_s * (t1 - eph.toc_sow_s))
    return sat_pos_clock(eph, ch.bdt_week[sel, None], t_tx)


def _gather_rows(eph: EphemerisArrays, sel: np.ndarray) -> EphemerisArrays:
    kw = {name: getattr(eph, name)[sel] for name in _EPH_FIELDS}
    return EphemerisArrays(prn=(), **kw)


def _row_clocks(b: np.ndarray, cix: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Each row's receiver clock [m] for epochs ``sel``: their clocks ``b`` (e, clocks) at
    the rows' clock indices ``cix[sel]`` (e, s); with one clock, ``b`` itself (it broadcasts
    over the rows, and no index is gathered)."""
    return b if b.shape[1] == 1 else np.take_along_axis(b, cix[sel], axis=1)


def _lsq(h: np.ndarray, dz: np.ndarray, w: np.ndarray) -> np.ndarray:
    """Per epoch, the weighted least-squares step over rows with w > 0 (rows with w = 0 are
    out); raises LinAlgError when any system is singular."""
    ht = np.swapaxes(h, -1, -2) * w[:, None, :]
    return linalg.solve(ht @ h, (ht @ dz[..., None]))[..., 0]


def _where(
    near: np.ndarray, value: np.ndarray | float, far: np.ndarray | float
) -> np.ndarray | float:
    """``value`` for the epochs ``near`` the Earth (e, 1), ``far`` for the others; ``value``
    itself (the same object, no copy) when every epoch is near."""
    if near.all():
        return value
    return np.where(near, value, far)


def _local(
    x: np.ndarray, sat: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    lat, lon, alt = ecef_to_geodetic(x)
    el, az = look_angles(x, sat, (lat, lon))
    return lat, lon, alt, el, az


_Outcome = Outcome
"""A fix or a decline, a failed chi-square test, or None: the per-epoch solver must decide
(a singular system, an impossible range, no convergence, a solution not finite)."""


def _fail(
    ok: np.ndarray, sel: np.ndarray, bad: np.ndarray, unsure: np.ndarray | None = None
) -> None:
    """Mark epochs ``sel[bad]`` as leaving the batch path (and, with ``unsure``, as ones
    whose outcome the per-epoch solver must find)."""
    ok[sel[bad]] = False
    if unsure is not None:
        unsure[sel[bad]] = True


def _solve_chunk(
    ch: _Chunk,
    layout: Layout,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
    start: np.ndarray | None = None,
) -> list[_Outcome]:
    """The outcome of each epoch of the chunk (:data:`_Outcome`), whose rows have the
    unknowns ``layout`` (a clock per system among them). ``start`` (e, 3): where each
    epoch's phase 1 starts (NaN, or None for every epoch: the Earth's centre)."""
    n_e, n_s = ch.z.shape
    ok = np.ones(n_e, dtype=bool)
    unsure = np.zeros(n_e, dtype=bool)
    n_full = ch.full.sum(axis=1)
    # impossible ranges (the per-epoch solver drops them and says so): not here
    zf = np.where(ch.full, ch.z, np.nan)
    zs = np.sort(zf, axis=1)
    k1 = np.clip((n_full - 1) // 2, 0, n_s - 1)[:, None]
    k2 = np.clip(n_full // 2, 0, n_s - 1)[:, None]
    median = 0.5 * (np.take_along_axis(zs, k1, 1) + np.take_along_axis(zs, k2, 1))
    with np.errstate(invalid="ignore"):
        gross = ch.full & ~(np.abs(ch.z - median) <= GROSS_SPREAD_M)
    n_rows = ch.valid.sum(axis=1)
    no_rows = n_rows == 0  # no ephemeris or no measurement
    unsure |= gross.any(axis=1)
    n_par, n_clk, cix = layout.n_params, layout.n_clocks, ch.cix

    def design(los_: np.ndarray, sel: np.ndarray | None = None) -> np.ndarray:
        if n_clk == 1:  # one clock column: no clock indices to gather
            return layout.design(los_)
        return layout.design(los_, cix if sel is None else cix[sel])

    too_few = ~unsure & ~no_rows & (n_full < n_par)
    ok &= ~unsure & ~too_few & ~no_rows
    # the declines decided here: (epoch, why, fields of the declined fix)
    declines: list[tuple[int, Declined, dict[str, object]]] = []
    for e in np.flatnonzero(no_rows & ~unsure).tolist():
        if ch.missing[e]:
            declines.append(
                (e, Declined.of(Decline.NO_EPHEMERIS, prns=", ".join(ch.missing[e])), {})
            )
        else:
            declines.append((e, Declined.of(Decline.NO_MEASUREMENTS), {}))
    for e in np.flatnonzero(too_few).tolist():
        n_f, n_q = int(n_full[e]), int(ch.frac[e].sum())
        why = Declined.of(Decline.TOO_FEW_FULL, n_full=n_f, n_frac=n_q, need=n_par)
        declines.append((e, why, {}))

    # ---- phase 1: the paper's iteration from the Earth's centre -----------------------------
    x = np.zeros((n_e, 3)) if start is None else np.where(np.isnan(start), 0.0, start)
    b = np.zeros((n_e, n_clk))
    n_int = np.zeros((n_e, n_s))
    iters = np.zeros(n_e, dtype=int)
    every = np.arange(n_e)
    sat0, clk = _orbits(ch, every, n_int)
    omega = ch.eph.omega_e_rad_s
    los, pred, sat = ranges(sat0, clk, x, omega)
    fullw = ch.full.astype(float)

    def cost_of(sel: np.ndarray, pred_: np.ndarray, b_: np.ndarray) -> np.ndarray:
        r = np.where(ch.full[sel], ch.z[sel] - pred_ - _row_clocks(b_, cix, sel), 0.0)
        return np.einsum("es,es->e", r, r)

    cost = cost_of(every, pred, b)
    active = ok.copy()
    converged = np.zeros(n_e, dtype=bool)
    for _it in range(cfg.max_iter):
        sel = np.flatnonzero(active)
        if not sel.size:
            break
        iters[sel] += 1
        dz = ch.z[sel] + n_int[sel] * ch.ct[sel] - pred[sel] - _row_clocks(b[sel], cix, sel)
        h = design(los[sel], sel)
        try:
            step = _lsq(h, dz, fullw[sel])  # eq. (10) over the full rows
        except np.linalg.LinAlgError:
            _fail(ok, sel, np.ones(sel.size, dtype=bool), unsure)
            active[sel] = False
            continue
        # each fractional row's ambiguity step [m]: its residual after the x/b step
        dn_m = np.einsum("esk,ek->es", h, step) - dz
        frac = ch.frac[sel]
        ct = np.where(frac, ch.ct[sel], 1.0)
        lam = np.ones(sel.size)
        pending = np.arange(sel.size)
        x_new = x[sel].copy()
        b_new = b[sel].copy()
        n_new = n_int[sel].copy()
        dn = np.zeros((sel.size, n_s))
        los_n, pred_n, sat_n = los[sel].copy(), pred[sel].copy(), sat[sel].copy()
        sat0_n, clk_n = sat0[sel].copy(), clk[sel].copy()
        cost_n = cost[sel].copy()
        while pending.size:
            p = sel[pending]
            lp = lam[pending]
            xp = x[p] + lp[:, None] * step[pending, :3]
            bp = b[p] + lp[:, None] * step[pending, 3:n_par]
            dnp = np.where(frac[pending], np.rint(lp[:, None] * dn_m[pending] / ct[pending]), 0.0)
            np_int = n_int[p] + dnp  # eq. (13)
            # the orbits depend on the integers only (eqs. 4-5): computed again only for
            # the epochs whose integers this step moves (never in SPP)
            s0, ck = sat0[p], clk[p]
            moved = np.flatnonzero(np.any(dnp != 0, axis=1))
            if moved.size:
                s0, ck = s0.copy(), ck.copy()
                s0[moved], ck[moved] = _orbits(ch, p[moved], np_int[moved])
            lo, pr, st = ranges(s0, ck, xp, omega[p])
            cp = cost_of(p, pr, bp)
            with np.errstate(invalid="ignore"):
                accept = (cp <= cost[p]) | (lp < 1e-3) | ~np.isfinite(cost[p])
            a = pending[accept]
            x_new[a], b_new[a], n_new[a] = xp[accept], bp[accept], np_int[accept]
            dn[a] = dnp[accept]
            los_n[a], pred_n[a], sat_n[a] = lo[accept], pr[accept], st[accept]
            sat0_n[a], clk_n[a], cost_n[a] = s0[accept], ck[accept], cp[accept]
            lam[pending[~accept]] /= 2.0
            pending = pending[~accept]
        x[sel], b[sel], n_int[sel] = x_new, b_new, n_new
        los[sel], pred[sel], sat[sel], sat0[sel], clk[sel] = los_n, pred_n, sat_n, sat0_n, clk_n
        cost[sel] = cost_n
        finite = np.isfinite(x_new).all(axis=1)
        settled = (np.linalg.norm(lam[:, None] * step[:, :n_par], axis=1) < cfg.theta_m) & ~np.any(
            dn != 0, axis=1
        )  # eq. (14)
        converged[sel] = finite & settled
        active[sel] = finite & ~settled

    # no convergence (or a position no longer finite): the per-epoch solver decides. With a
    # gross fault the iteration is sensitive to rounding, and its step here and the
    # per-epoch solver's (the augmented system formed) can settle differently (HKSC, 1 ms
    # on GEO C01, fast: at epochs 20 and 60 the per-epoch iteration converges in 11 steps,
    # this one not in 30; forming the augmented system here too settles epoch 20 but not
    # 60, and costs a fifth of the batch's time), so this decline is not the batch's to give
    _fail(ok, np.flatnonzero(ok), ~converged[ok], unsure)

    # eqs. (12), (20)-(21): the GEO-GDOP gate over the full rows at the converged position
    n_frac = ch.frac.sum(axis=1)
    if solver == "fast":
        with np.errstate(all="ignore"):
            gd = dop(design(los), fullw)
        beta = np.full(n_e, float(cfg.beta))
        if not cfg.beta:
            t_min = np.min(np.where(ch.frac, ch.ct, np.inf), axis=1) / C_M_S
            beta = np.where(n_frac > 0, C_M_S * t_min / 2.0 / cfg.range_error_m, 0.0)  # eq. 21
        gate = ok & (n_frac > 0) & ~(gd < beta)
        gd_l, beta_l, it_l = gd.tolist(), beta.tolist(), iters.tolist()
        for e in np.flatnonzero(gate).tolist():
            it = it_l[e]
            why = Declined.of(Decline.GDOP_GATE, gdop=gd_l[e], beta=beta_l[e], iterations=it)
            declines.append((e, why, {"gdop_full": gd_l[e], "iterations": it}))
        ok &= ~gate

    # eqs. (15)-(16): the integers held, [x, b] corrected over all rows (no corrections yet)
    sel = np.flatnonzero(ok)
    validw = ch.valid.astype(float)
    for _it in range(cfg.max_iter):
        if not sel.size:
            break
        iters[sel] += 1
        dz = ch.z[sel] + n_int[sel] * ch.ct[sel] - pred[sel] - _row_clocks(b[sel], cix, sel)
        try:
            step = _lsq(design(los[sel], sel), dz, validw[sel])
        except np.linalg.LinAlgError:
            _fail(ok, sel, np.ones(sel.size, dtype=bool), unsure)
            break
        x[sel] += step[:, :3]
        b[sel] += step[:, 3:n_par]
        finite = np.isfinite(np.concatenate([x[sel], b[sel]], axis=1)).all(axis=1)
        _fail(ok, sel, ~finite, unsure)
        los[sel], pred[sel], sat[sel] = ranges(sat0[sel], clk[sel], x[sel], omega[sel])
        sel = sel[finite & (np.linalg.norm(step, axis=1) >= cfg.conv_m)]

    # ---- phase 2: mask, corrections, weights -------------------------------------------------
    # a position far from the Earth (a gross fault can put phase 1 there): no mask, no
    # corrections and the same weight for every row, as the per-epoch solver does (its
    # ``_meaningful``); a position not finite: the per-epoch solver decides
    r = np.sqrt(np.einsum("ek,ek->e", x, x))
    lost = ok & ~np.isfinite(r)
    unsure |= lost
    ok &= ~lost
    meaningful = (r > 6.0e6) & (r < 8.5e6)
    out: list[_Outcome] = [None] * n_e
    sel = np.flatnonzero(ok)
    if sel.size:
        _, _, _, el, _ = _local(x[sel], sat[sel])
    keep = ch.valid.copy()
    if sel.size:
        keep[sel] &= (el >= np.radians(cfg.elmask_deg)) | ~meaningful[sel, None]
    n_full_k = (keep & ch.full).sum(axis=1)
    masked = ok & (n_full_k < n_par)
    if masked.any():
        with np.errstate(all="ignore"):
            gd = dop(design(los), fullw)  # at the position of the fixed iterations
        for e in np.flatnonzero(masked).tolist():
            why = Declined.of(
                Decline.TOO_FEW_FULL, "mask", mask_deg=cfg.elmask_deg, n_full=int(n_full_k[e])
            )
            gd_e = float(gd[e]) if n_frac[e] else None
            declines.append((e, why, {"gdop_full": gd_e, "iterations": int(iters[e])}))
    ok &= ~masked
    for e, why, fixed in declines:
        out[e] = _decline(ch, e, solver, why, fixed)
    keepw = keep.astype(float)
    models = iono.models(cfg.iono)
    bds = ch.eph.bds
    sel = np.flatnonzero(ok)
    for _it in range(cfg.max_iter):
        if not sel.size:
            break
        iters[sel] += 1
        dz = ch.z[sel] + n_int[sel] * ch.ct[sel] - pred[sel] - _row_clocks(b[sel], cix, sel)
        lat, lon, alt, el, az = _local(x[sel], sat[sel])
        io, tr = system_delays(
            lat, lon, alt, el, az, ch.bdt_sow[sel], ch.eph.carrier_hz[sel], bds[sel], models, cfg
        )
        near = meaningful[sel, None]
        dz = dz - _where(near, total_delay(io, tr), 0.0)
        w = keepw[sel]
        if cfg.weighted:
            w = np.asarray(
                _where(near, w / measurement_sigma_m(el, ch.cn0[sel], io, tr, cfg) ** 2, w)
            )
        try:
            step = _lsq(design(los[sel], sel), dz, w)
        except np.linalg.LinAlgError:
            _fail(ok, sel, np.ones(sel.size, dtype=bool), unsure)
            break
        x[sel] += step[:, :3]
        b[sel] += step[:, 3:n_par]
        finite = np.isfinite(np.concatenate([x[sel], b[sel]], axis=1)).all(axis=1)
        _fail(ok, sel, ~finite, unsure)
        los[sel], pred[sel], sat[sel] = ranges(sat0[sel], clk[sel], x[sel], omega[sel])
        sel = sel[finite & (np.linalg.norm(step, axis=1) >= cfg.conv_m)]

    # ---- judge the solution ------------------------------------------------------------------
    for e in np.flatnonzero(unsure).tolist():
        out[e] = None
    sel = np.flatnonzero(ok & ~unsure)
    if not sel.size:
        return out
    lat, lon, alt, el, az = _local(x[sel], sat[sel])
    io, tr = system_delays(
        lat, lon, alt, el, az, ch.bdt_sow[sel], ch.eph.carrier_hz[sel], bds[sel], models, cfg
    )
    kp = keep[sel]
    near = meaningful[sel, None]
    bc = _row_clocks(b[sel], cix, sel)
    corr = _where(near, total_delay(io, tr), 0.0)
    v = ch.z[sel] + n_int[sel] * ch.ct[sel] - pred[sel] - bc - corr
    v = np.where(kp, v, 0.0)
    if cfg.weighted:
        sigma = _where(near, measurement_sigma_m(el, ch.cn0[sel], io, tr, cfg), cfg.sigma_uniform_m)
        sigma = np.where(kp, sigma, 1.0)
    else:
        sigma = np.full(kp.shape, cfg.sigma_uniform_m)
    g = design(los[sel], sel)
    rot = enu_rotation(lat, lon)
    integ = assess_many(g, v, sigma, kp, rot, cfg.p_fa, cfg.p_md, layout)
    n_k = kp.sum(axis=1)
    resid_rms = np.sqrt(np.einsum("es,es->e", v, v) / n_k)
    kfull = kp & ch.full[sel]
    gd_final = dop(g, kfull.astype(float))
    gu = g * kp[..., None]
    q = linalg.inv(np.swapaxes(gu, -1, -2) @ gu)[:, :3, :3]
    q_enu = rot @ q @ np.swapaxes(rot, -1, -2)
    pdop = np.sqrt(np.trace(q_enu, axis1=1, axis2=2))
    numbers: dict[str, list] = {
        "x": x[sel].tolist(),
        "b": b[sel].tolist(),
        "lat_deg": np.degrees(lat).tolist(),
        "lon_deg": np.degrees(lon).tolist(),
        "alt": alt.tolist(),
        "gdop": gd_final.tolist(),
        "pdop": pdop.tolist(),
        "hdop": np.sqrt(q_enu[:, 0, 0] + q_enu[:, 1, 1]).tolist(),
        "vdop": np.sqrt(q_enu[:, 2, 2]).tolist(),
        "cov": [i.cov_enu_m2.tolist() for i in integ],
        "resid": resid_rms.tolist(),
        "iters": iters[sel].tolist(),
    }
    for k, e in enumerate(sel.tolist()):
        out[e] = _judged(ch, e, solver, layout, n_int, kp[k], integ[k], numbers, k, cfg)
    return out


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
) -> _Outcome:
    """Epoch ``e``'s solution judged (:func:`service.engine.judge.verdict`): its fix, its
    decline, or its failed test (``k``: its index among the judged epochs, in ``numbers``)."""
    ep = ch.epochs[e]
    prn = ch.prn[e]
    frac = ch.frac[e, : len(prn)].tolist()
    kk = np.flatnonzero(kept[: len(prn)]).tolist()
    used = tuple(prn[i] for i in kk)
    fr = [i for i in kk if frac[i]]  # the used fractional rows
    # (plain floats: the same sums, without numpy's per-item cost)
    n_row: list[float] = n_int[e].tolist() if fr else []
    ambiguity = {prn[i]: int(n_row[i]) for i in fr}
    gdop_full = numbers["gdop"][k] if solver == "fast" else None
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
        recovered_pr_m=_recovered(ch, e, prn, n_row, fr) if fr else {},
    )


def _recovered(
    ch: _Chunk, e: int, prn: tuple[str, ...], n_row: list[float], fr: list[int]
) -> dict[str, float]:
    """The full ranges z + N c T [m] of epoch ``e``'s used fractional rows ``fr``."""
    z, ct = ch.z[e].tolist(), ch.ct[e].tolist()
    return {prn[i]: z[i] + n_row[i] * ct[i] for i in fr}


def _decline(
    ch: _Chunk,
    e: int,
    solver: Literal["fast", "spp"],
    why: Declined,
    fields: dict[str, object],
) -> Fix:
    """Epoch ``e``'s decline decided before its solution is judged (the per-epoch solver's:
    over its rows, with ``fields``; an epoch without rows has none)."""
    ep, prn = ch.epochs[e], ch.prn[e]
    frac = ch.frac[e, : len(prn)].tolist()
    return decline_fix(solver, ep.gpst_week, ep.gpst_tow_s, prn, frac, why, **fields)


def _outcomes(
    epochs: Sequence[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
    start: np.ndarray | None = None,
) -> list[_Outcome]:
    """:func:`_solve_chunk` over ``epochs`` chunk by chunk (a chunk that raises: None);
    ``start`` (e, 3): where each epoch's phase 1 starts (NaN: the Earth's centre)."""
    out: list[_Outcome] = []
    for at in range(0, len(epochs), CHUNK_EPOCHS):
        part = epochs[at : at + CHUNK_EPOCHS]
        where = None if start is None else start[at : at + CHUNK_EPOCHS]
        try:
            with np.errstate(all="ignore"):
                ch = _Chunk(part, store, solver)
                out += _solve_layouts(ch, store, iono, cfg, solver, where)
        except (np.linalg.LinAlgError, ArithmeticError, ValueError):
            log.debug("batch solve failed on a chunk; its epochs go one by one", exc_info=True)
            out += [None] * len(part)
    return out


def _solve_layouts(
    ch: _Chunk,
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
    start: np.ndarray | None = None,
) -> list[_Outcome]:
    """:func:`_solve_chunk` of ``ch``; when its epochs' rows differ in their satellite
    systems (so in their clocks, :class:`~service.engine.layout.Layout`), each layout's
    epochs are solved as a chunk of their own."""
    if ch.layout is not None and (solver == "spp" or ch.layout.n_clocks == 1):
        return _solve_chunk(ch, ch.layout, iono, cfg, solver, start)
    groups: dict[Layout, list[int]] = {}
    for e, ps in enumerate(ch.prn):
        groups.setdefault(layout_of(ps) if ps else BDS_ONLY, []).append(e)
    out: list[_Outcome] = [None] * len(ch.prn)
    for idx in groups.values():
        sub = _Chunk([ch.epochs[e] for e in idx], store, solver)
        layout = sub.layout if sub.layout is not None else BDS_ONLY
        if solver == "fast" and layout.n_clocks > 1:
            # the fast fix of rows of several systems resolves the integers of a system
            # without full rows after the others' fix (solver._with_other_systems): the
            # per-epoch solver's (None: handed to it)
            continue
        where = None if start is None else start[idx]
        for e, res in zip(idx, _solve_chunk(sub, layout, iono, cfg, solver, where), strict=True):
            out[e] = res
    return out


def _without(epoch: MeasurementEpoch, prn: str) -> MeasurementEpoch:
    """``epoch`` without satellite ``prn``."""
    return epoch.rows([i for i, p in enumerate(epoch.prn) if p != prn])


def _exclude(
    failed: dict[int, Failed],
    epochs: Sequence[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet,
    cfg: SolverConfig,
    solver: Literal["fast", "spp"],
) -> tuple[dict[int, Fix], set[int]]:
    """Fault exclusion (:func:`service.engine.judge.exclude`, the loop the per-epoch solver
    runs too) for the epochs that failed the test, every candidate of every epoch of a stage
    solved in one batch (:func:`_outcomes`). Epochs with no passing candidate after the last
    stage are returned apart (``hopeless``: their fix is the failed solution's decline); an
    epoch with a candidate whose outcome is not certain is in neither (the per-epoch solver
    decides it)."""

    def without(cand: _Candidate, prn: str) -> _Candidate:
        return _without(cand[0], prn), cand[1]

    def solve(cands: list[_Candidate]) -> list[tuple[Outcome, _Candidate]]:
        start = np.array([(math.nan,) * 3 if s is None else s for _, s in cands])
        res = _outcomes([ep for ep, _ in cands], store, iono, cfg, solver, start)
        # a candidate the batch cannot decide (with a gross fault, no convergence of phase
        # 1): the per-epoch solver's attempt at it, as its own exclusion would make it, so
        # that its epoch's other candidates stay the batch's
        res = [
            attempt(ep, store, iono, cfg, solver, s) if r is None else r
            for r, (ep, s) in zip(res, cands, strict=True)
        ]
        return [
            (r, (ep, r.warm_start if isinstance(r, Failed) else None))
            for r, (ep, _) in zip(res, cands, strict=True)
        ]

    first = {e: (f, (epochs[e], f.warm_start)) for e, f in failed.items()}
    return exclude(first, without, solve, cfg.max_exclusions)


_Candidate = tuple[MeasurementEpoch, tuple[float, float, float] | None]
"""A candidate of fault exclusion: its epoch and where its phase 1 starts (None: the Earth's
centre; :attr:`service.engine.judge.Failed.warm_start`)."""


def solve_many(
    epochs: Sequence[MeasurementEpoch],
    store: EphemerisStore,
    iono: IonoSet | None = None,
    cfg: SolverConfig | None = None,
    solver: Literal["fast", "spp"] = "fast",
    with_sky: bool = False,
) -> list[Fix]:
    """``[solve(e, store, iono, cfg, solver, with_sky) for e in epochs]``, vectorised over
    chunks of :data:`CHUNK_EPOCHS` epochs (module docstring). Epochs in time order make
    the ephemeris selection cheapest; any order gives the same fixes."""
    cfg = cfg or SolverConfig()
    iono = iono or IonoSet()
    # no GPS week: declined before any row is read, as the per-epoch solver declines it
    out: list[Fix | None] = [
        None if ep.week_known else declined(ep, Declined.of(Decline.NO_TIME), solver)
        for ep in epochs
    ]
    if cfg.x0_ecef_m is None:  # (a known start: the per-epoch solver's phase 2 alone)
        todo = [i for i, ep in enumerate(epochs) if ep.week_known]
        results = _outcomes([epochs[i] for i in todo], store, iono, cfg, solver)
        failed: dict[int, Failed] = {}
        for i, res in zip(todo, results, strict=True):
            if isinstance(res, Fix):
                out[i] = res
            elif isinstance(res, Failed):
                failed[i] = res
        if failed and cfg.max_exclusions > 0:
            passed, hopeless = _exclude(failed, epochs, store, iono, cfg, solver)
            for i, fix in passed.items():
                out[i] = fix
            # no exclusion passes: the failed solution's decline
            for i in hopeless:
                out[i] = no_exclusion(failed[i].fix, cfg.max_exclusions)
        elif failed:  # no exclusion asked for: the failed solution's decline
            for i, f in failed.items():
                out[i] = f.fix
    return [
        (replace(f, sky=sky_view(ep, store, f)) if with_sky and f.ok else f)
        if f is not None
        else solve(ep, store, iono, cfg, solver, with_sky)
        for f, ep in zip(out, epochs, strict=True)
    ]
