"""The unknowns of a least-squares problem as data: which columns the design matrix has.

A position problem solves the receiver position (3 columns) and one receiver clock per
satellite system among the rows (each system's time scale and signal delays differ, so
each has its own clock: the inter-system bias is the difference of two of them); the
fast fix adds one integer-millisecond column per fractional row (paper eq. 11), which is
not part of the layout (they are resolved, then held). A velocity problem solves the
receiver velocity and one clock drift per system. The coarse-time fix
(:mod:`service.engine.coarse`) adds a coarse-time offset dt (the unknown receive time of a
tag that may be seconds off: true receive time = tag + dt), whose column is each row's
range rate (van Diggelen, *A-GPS*, ch. 4: d rho_j / d dt = e_j . V_j).

Every statistic that depends on the number of unknowns (redundancy, the chi-square test
and its degrees of freedom, w-tests, protection levels, DOPs, the least number of rows of
a solution) takes it from here: :meth:`Layout.redundancy` is the one place where
rows - parameters is written.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from typing import Literal

import numpy as np

from service.core.systems import GnssSystem, system_of
from service.engine import linalg

_ORDER = tuple(GnssSystem)
"""Canonical order of the clock columns (BeiDou first: its clock is ``Fix.clock_bias_m``)."""


@dataclass(frozen=True, slots=True)
class Layout:
    """The parameters of one problem, in column order: 3 position (or velocity)
    components, one clock (or clock drift) per system of ``systems``, then a coarse-time
    offset [s] when ``coarse_time`` (its column: the rows' range rates, :meth:`design`)."""

    systems: tuple[GnssSystem, ...] = (GnssSystem.BDS,)
    problem: Literal["position", "velocity"] = "position"
    coarse_time: bool = False

    @property
    def n_clocks(self) -> int:
        return len(self.systems)

    @property
    def n_params(self) -> int:
        """The number of unknowns."""
        return 3 + len(self.systems) + int(self.coarse_time)

    @property
    def names(self) -> tuple[str, ...]:
        """Column names: ``x y z`` then ``clock_C``... (``vx vy vz``, ``drift_C``... for
        velocity), then ``coarse_time``."""
        pos = ("x", "y", "z") if self.problem == "position" else ("vx", "vy", "vz")
        clk = "clock" if self.problem == "position" else "drift"
        tail = ("coarse_time",) if self.coarse_time else ()
        return (*pos, *(f"{clk}_{s.value}" for s in self.systems), *tail)

    def redundancy(
        self, n_rows: int | np.ndarray, clocks_used: int | np.ndarray | None = None
    ) -> int | np.ndarray:
        """Rows minus parameters: the degrees of freedom of the chi-square test. A
        pseudo-observation (a held height, the coarse-time fix's time prior) is a row.
        ``clocks_used``: how many of the clocks have rows (a system the elevation mask
        left without rows has no clock to solve; None: every one)."""
        if clocks_used is None:
            return n_rows - self.n_params
        return n_rows - (self.n_params - self.n_clocks + clocks_used)

    @property
    def time_column(self) -> int:
        """The index of the coarse-time column (the last)."""
        if not self.coarse_time:
            raise ValueError("this layout has no coarse-time column")
        return self.n_params - 1

    def clock_index(self, sats: Sequence[str]) -> np.ndarray:
        """For each row (satellite ID), the index of its system's clock among the clocks."""
        where = {s.value: k for k, s in enumerate(self.systems)}
        return np.fromiter((where[p[:1]] for p in sats), dtype=np.intp, count=len(sats))

    def design(
        self,
        los: np.ndarray,
        clock_idx: np.ndarray | None = None,
        rate_m_s: np.ndarray | None = None,
    ) -> np.ndarray:
        """The design matrix (..., n, n_params) of line-of-sight unit vectors ``los``
        (..., n, 3): rows [-e^T, one-hot of the row's clock] (paper eq. 9 with a clock
        per system), and with ``coarse_time`` the row's range rate ``rate_m_s`` (..., n)
        [m/s], e_j . V_j (the partial of the predicted range by the receive time,
        van Diggelen's coarse-time column). ``clock_idx``: :meth:`clock_index` of the rows
        (None: one system)."""
        shape = los.shape[:-1]
        if self.n_clocks == 1 and not self.coarse_time:
            return np.concatenate([-los, _ones(shape)], axis=-1)
        if clock_idx is None:
            clocks = np.zeros((*shape, self.n_clocks))
            clocks[..., 0] = 1.0
        else:  # each row's one-hot: its clock's row of the identity
            clocks = _eye(self.n_clocks)[np.broadcast_to(np.asarray(clock_idx), shape)]
        parts = [-los, clocks]
        if self.coarse_time:
            if rate_m_s is None:
                raise ValueError("a coarse-time design needs the rows' range rates")
            parts.append(np.broadcast_to(np.asarray(rate_m_s)[..., None], (*shape, 1)))
        return np.concatenate(parts, axis=-1)


@lru_cache(maxsize=64)
def _ones(shape: tuple[int, ...]) -> np.ndarray:
    """A read-only column of ones (*shape, 1): the clock column of a one-clock design, made
    once per shape (the solver's iterations ask for the same shapes again and again)."""
    out = np.ones((*shape, 1))
    out.flags.writeable = False
    return out


@lru_cache(maxsize=8)
def _eye(n: int) -> np.ndarray:
    """A read-only n x n identity: row k is the one-hot of clock k."""
    out = np.eye(n)
    out.flags.writeable = False
    return out


BDS_ONLY = Layout()
"""The layout of a BeiDou position fix: x, y, z and one clock."""


@lru_cache(maxsize=64)
def _of_systems(systems: frozenset[GnssSystem]) -> Layout:
    return Layout(tuple(s for s in _ORDER if s in systems))


def layout_of(sats: Sequence[str]) -> Layout:
    """The position layout of rows ``sats``: a clock for each system among them."""
    letters = {p[:1] for p in sats}
    if letters == {"C"} or not letters:
        return BDS_ONLY
    return _of_systems(frozenset(system_of(p) for p in letters))


def dop(g: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """sqrt(trace((G^T G)^-1)) of design matrices ``g`` (..., n, p) (paper eq. 20 with
    the layout's columns); ``weight`` (..., n) of 0/1 masks rows out; inf where singular."""
    if weight is not None:
        g = g * np.asarray(weight, dtype=float)[..., None]
    d = linalg.einsum("...ni,...nj->...ij", g, g)
    eig = linalg.eigvalsh(d)
    floor = 1e-12 * eig.max(axis=-1, keepdims=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = np.where(eig > floor, 1.0 / eig, np.inf)
    return np.sqrt(inv.sum(axis=-1))
