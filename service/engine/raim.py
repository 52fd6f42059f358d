"""Statistical integrity of a weighted least-squares fix: the chi-square fault test and
slope-based protection levels (receiver autonomous integrity monitoring, RAIM).

Model (Brown & Chin 1998; Walter & Enge 1995, weighted RAIM): measurements y = G x + e with
independent errors e_i ~ N(0, sigma_i^2), W = diag(1/sigma_i^2), K = (G^T W G)^-1 G^T W and
the residual matrix S = I - G K, so that the residuals are v = S e.

- Detection: the statistic T = v^T W v follows a central chi-square with r = n - p degrees
  of freedom (the redundancy: n rows, p unknowns of the problem's
  :class:`service.engine.layout.Layout`) when no measurement is faulty. A fault is declared
  when T > T_max, the (1 - P_fa) quantile of that distribution. With r = 0 the residuals
  are all zero and no test is possible.
- A bias b on measurement i makes T non-central with lambda_i = b^2 S_ii / sigma_i^2 and moves
  the position by b K_i (column i of K). The smallest lambda that the test misses with
  probability P_md is lambda_md: P(chi2'(r, lambda_md) < T_max) = P_md. The slope of
  measurement i relates position error to the test's square root:
  slope_H,i = sigma_i sqrt(K_E,i^2 + K_N,i^2) / sqrt(S_ii) (vertical: |K_U,i|).
- Protection levels: HPL = max_i slope_H,i sqrt(lambda_md) + k_H sigma_major and
  VPL = max_i slope_V,i sqrt(lambda_md) + k_V sigma_U, i.e. the largest error a single
  fault can cause undetected (with probability 1 - P_md) plus the fault-free noise at the
  same probability (k_H = sqrt(-2 ln P_md), the Rayleigh quantile; k_V the two-sided normal
  quantile). A measurement with S_ii = 0 (no redundancy for it) has an unbounded slope: the
  fix is then not protected against it and the level is infinite.

The chi-square and non-central chi-square distributions are computed here from the
regularised incomplete gamma function (Numerical Recipes, 3rd ed., section 6.2: series and
Lentz continued fraction), so numpy is the only dependency; the tests cross-check them
against scipy.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from service.engine import linalg
from service.engine.layout import BDS_ONLY, Layout

_EPS = 1e-15
_TINY = 1e-300


def _gamma_p_series(a: float, x: float) -> float:
    """P(a, x) by its series, for x < a + 1."""
    term = total = 1.0 / a
    ap = a
    for _ in range(10_000):
        ap += 1.0
        term *= x / ap
        total += term
        if abs(term) < abs(total) * _EPS:
            break
    return total * math.exp(-x + a * math.log(x) - math.lgamma(a))


def _gamma_q_fraction(a: float, x: float) -> float:
    """Q(a, x) by its continued fraction (modified Lentz), for x >= a + 1."""
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, 10_000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = _TINY if abs(d) < _TINY else d
        c = b + an / c
        c = _TINY if abs(c) < _TINY else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    return math.exp(-x + a * math.log(x) - math.lgamma(a)) * h


def gamma_p(a: float, x: float) -> float:
    """Regularised lower incomplete gamma function P(a, x), a > 0."""
    if x <= 0.0:
        return 0.0
    if x < a + 1.0:
        return _gamma_p_series(a, x)
    return 1.0 - _gamma_q_fraction(a, x)


def gamma_q(a: float, x: float) -> float:
    """Regularised upper incomplete gamma function Q(a, x) = 1 - P(a, x), a > 0."""
    if x <= 0.0:
        return 1.0
    if x < a + 1.0:
        return 1.0 - _gamma_p_series(a, x)
    return _gamma_q_fraction(a, x)


def chi2_sf(x: float, dof: int) -> float:
    """P(chi2(dof) > x)."""
    return gamma_q(dof / 2.0, x / 2.0)


def _ncx2_cdf_pair(x: float, dof: int, lam: float) -> tuple[float, float]:
    """P(chi2'(dof, lam) <= x) and P(chi2'(dof + 2, lam) <= x).

    The Poisson(lam / 2) mixture sum_j Pois(j; lam / 2) P(dof / 2 + j, x / 2), over the
    weights that matter (mode +- 10 standard deviations). P(a + j, y) comes from one
    incomplete gamma at the top of the range and the downward recurrence
    P(a + j, y) = P(a + j + 1, y) + y^(a + j) e^-y / Gamma(a + j + 1) (positive terms
    only: stable)."""
    a, y = dof / 2.0, x / 2.0
    half = lam / 2.0
    spread = 10.0 * math.sqrt(half) + 20.0
    j_lo = max(0, int(half - spread))
    j_hi = int(half + spread) + 1
    log_y = math.log(y)
    p_next = gamma_p(a + j_hi + 1, y)  # P(a + j_hi + 1, y)
    log_half = math.log(half) if half > 0.0 else -math.inf
    f_k = f_k2 = 0.0
    for j in range(j_hi, j_lo - 1, -1):
        p_j = p_next + math.exp((a + j) * log_y - y - math.lgamma(a + j + 1.0))
        if half > 0.0:
            weight = math.exp(-half + j * log_half - math.lgamma(j + 1.0))
        else:
            weight = 1.0 if j == 0 else 0.0
        f_k += weight * p_j
        f_k2 += weight * p_next
        p_next = p_j
    return min(1.0, f_k), min(1.0, f_k2)


def ncx2_cdf(x: float, dof: int, lam: float) -> float:
    """P(chi2'(dof, lam) <= x)."""
    if x <= 0.0:
        return 0.0
    return _ncx2_cdf_pair(x, dof, max(lam, 0.0))[0]


def _newton_root(
    f: Callable[[float], tuple[float, float]], lo: float, hi: float, x0: float
) -> float:
    """Root of a decreasing f in [lo, hi] (f(lo) > 0 > f(hi)) by Newton steps kept inside
    the bracket (bisection when a step would leave it); ``f`` returns (value, slope)."""
    x = min(max(x0, lo), hi)
    for _ in range(100):
        value, slope = f(x)
        if value > 0.0:
            lo = x
        else:
            hi = x
        step = value / slope if slope < 0.0 else math.inf
        new = x - step
        if not lo < new < hi:
            new = 0.5 * (lo + hi)
        if abs(new - x) <= 1e-10 * max(abs(new), 1.0):
            return new
        x = new
    return x


@lru_cache(maxsize=512)
def chi2_threshold(dof: int, p_fa: float) -> float:
    """The (1 - p_fa) quantile of chi2(dof): the detection threshold T_max."""
    if dof < 1:
        raise ValueError(f"chi-square threshold needs dof >= 1, got {dof}")
    if p_fa <= 0.0:
        return math.inf
    a = dof / 2.0
    hi = max(10.0, 4.0 * dof)
    while chi2_sf(hi, dof) > p_fa:
        hi *= 2.0

    def f(x: float) -> tuple[float, float]:  # sf - p_fa and its derivative, -pdf
        y = x / 2.0
        pdf = 0.5 * math.exp((a - 1.0) * math.log(y) - y - math.lgamma(a)) if y > 0 else 0.0
        return chi2_sf(x, dof) - p_fa, -pdf

    return _newton_root(f, 0.0, hi, float(dof) + 4.0 * math.sqrt(2.0 * dof))


@lru_cache(maxsize=512)
def noncentrality_md(dof: int, p_fa: float, p_md: float) -> float:
    """lambda_md: the non-centrality whose chi2'(dof, lambda) falls below the threshold of
    :func:`chi2_threshold` with probability ``p_md`` (the missed detection)."""
    t_max = chi2_threshold(dof, p_fa)
    if not math.isfinite(t_max):
        return math.inf
    hi = max(10.0, t_max)
    while ncx2_cdf(t_max, dof, hi) > p_md:
        hi *= 2.0

    def f(lam: float) -> tuple[float, float]:  # dF/dlam = -(F(dof) - F(dof + 2)) / 2
        f_k, f_k2 = _ncx2_cdf_pair(t_max, dof, lam)
        return f_k - p_md, -0.5 * (f_k - f_k2)

    guess = (math.sqrt(t_max) + normal_two_sided_quantile(2.0 * p_md)) ** 2
    return _newton_root(f, 0.0, hi, guess)


@lru_cache(maxsize=64)
def normal_two_sided_quantile(p: float) -> float:
    """k with P(|N(0, 1)| > k) = p (bisection on erfc; memoised: every solution asks it for
    the same p_md)."""
    lo, hi = 0.0, 40.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if math.erfc(mid / math.sqrt(2.0)) > p:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@dataclass(frozen=True, slots=True, eq=False)
class Integrity:
    """The integrity figures of one weighted least-squares solution.

    ``cov_enu_m2`` is the 3x3 east-north-up covariance (G^T W G)^-1 of the position [m^2];
    ``w`` the normalised residuals v_i / (sigma_i sqrt(S_ii)) (Baarda's w-test), NaN where
    S_ii = 0. ``chi2`` and ``chi2_max`` are None at redundancy 0, as are the levels.
    """

    redundancy: int
    chi2: float | None
    chi2_max: float | None
    w: np.ndarray
    cov_enu_m2: np.ndarray
    hpl_m: float | None
    vpl_m: float | None

    @property
    def passed(self) -> bool:
        """The chi-square test passed (False when it failed or could not be made)."""
        return self.chi2 is not None and self.chi2_max is not None and self.chi2 <= self.chi2_max


def assess(
    g: np.ndarray,
    v_m: np.ndarray,
    sigma_m: np.ndarray,
    enu_rot: np.ndarray,
    p_fa: float,
    p_md: float,
    layout: Layout = BDS_ONLY,
) -> Integrity:
    """Test and protection levels of one solution with design ``g`` (n, p: [-e^T, clock
    columns] of ``layout``), post-fit residuals ``v_m`` and measurement sigmas ``sigma_m``;
    ``enu_rot`` is the ECEF to east-north-up rotation at the solution:
    :func:`assess_many` of a batch of one."""
    return assess_many(g[None], v_m[None], sigma_m[None], None, enu_rot[None], p_fa, p_md, layout)[
        0
    ]


def assess_many(
    g: np.ndarray,
    v_m: np.ndarray,
    sigma_m: np.ndarray,
    kept: np.ndarray | None,
    enu_rot: np.ndarray,
    p_fa: float,
    p_md: float,
    layout: Layout = BDS_ONLY,
) -> list[Integrity]:
    """The integrity of each solution of a batch: designs ``g`` (e, s, p), residuals and
    sigmas (e, s), ``kept`` (e, s) marking each solution's rows (the others are padding;
    None: every slot is a row),
    rotations ``enu_rot`` (e, 3, 3). The degrees of freedom are the layout's redundancy of
    each solution's rows; ``w`` of an :class:`Integrity` covers every slot (padding: 0)."""
    n_e = len(v_m)
    w = 1.0 / sigma_m**2 if kept is None else np.where(kept, 1.0 / sigma_m**2, 0.0)
    gtw = g.swapaxes(-1, -2) * w[:, None, :]
    cov = linalg.inv(gtw @ g)
    k = cov @ gtw  # (e, p, s)
    s_ii = 1.0 - linalg.einsum("esi,eis->es", g, k)
    cov_enu = enu_rot @ cov[:, :3, :3] @ enu_rot.swapaxes(-1, -2)
    n_rows = np.full(n_e, v_m.shape[1]) if kept is None else kept.sum(axis=1)
    r = np.asarray(layout.redundancy(n_rows)).tolist()
    chi2 = (v_m * v_m * w).sum(axis=1).tolist()  # each row summed as one epoch's alone
    ok = s_ii > 1e-10
    with np.errstate(invalid="ignore", divide="ignore"):
        root = np.sqrt(s_ii)
        wtest = np.where(ok, v_m / (sigma_m * root), np.nan)
        k_enu = enu_rot @ k[:, :3]
        slope_h = sigma_m * np.hypot(k_enu[:, 0], k_enu[:, 1]) / root
        slope_v = sigma_m * np.abs(k_enu[:, 2]) / root
        if kept is not None:
            slope_h = np.where(kept, slope_h, -np.inf)
            slope_v = np.where(kept, slope_v, -np.inf)
    all_ok = (ok if kept is None else ~kept | ok).all(axis=1).tolist()
    major = linalg.eigvalsh(cov_enu[:, :2, :2])[:, -1].tolist()
    up = cov_enu[:, 2, 2].tolist()
    h_max, v_max = slope_h.max(axis=1).tolist(), slope_v.max(axis=1).tolist()
    k_h = math.sqrt(-2.0 * math.log(p_md))
    k_v = normal_two_sided_quantile(p_md)
    out = []
    for i in range(n_e):
        ri = int(r[i])
        if ri < 1:
            out.append(Integrity(ri, None, None, wtest[i], cov_enu[i], None, None))
            continue
        t_max = chi2_threshold(ri, p_fa)
        if not all_ok[i]:
            out.append(Integrity(ri, chi2[i], t_max, wtest[i], cov_enu[i], math.inf, math.inf))
            continue
        pbias = math.sqrt(noncentrality_md(ri, p_fa, p_md))
        hpl = h_max[i] * pbias + k_h * math.sqrt(max(major[i], 0.0))
        vpl = v_max[i] * pbias + k_v * math.sqrt(max(up[i], 0.0))
        out.append(Integrity(ri, chi2[i], t_max, wtest[i], cov_enu[i], hpl, vpl))
    return out
