"""The integrity statistics of service.engine.raim against scipy, and the protection-level algebra
against a direct computation with numpy's least squares."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

import service.engine.raim as raim


@given(a=st.floats(0.5, 60.0), x=st.floats(1e-3, 300.0))
@settings(max_examples=300, deadline=None, derandomize=True)
def test_incomplete_gamma_matches_scipy(a, x):
    p = stats.gamma.cdf(x, a)
    assert raim.gamma_p(a, x) == pytest.approx(p, abs=1e-12)
    assert raim.gamma_q(a, x) == pytest.approx(1.0 - p, abs=1e-12)
    q = stats.gamma.sf(x, a)
    if q > 1e-280:
        assert raim.gamma_q(a, x) == pytest.approx(q, rel=1e-9)


@pytest.mark.parametrize("p_fa", [1e-3, 1e-5, 1e-7])
@pytest.mark.parametrize("dof", [1, 2, 3, 5, 8, 12, 20, 35, 60])
def test_chi2_threshold_matches_scipy(dof, p_fa):
    assert raim.chi2_threshold(dof, p_fa) == pytest.approx(stats.chi2.isf(p_fa, dof), rel=1e-9)


@given(dof=st.integers(1, 60), x=st.floats(0.1, 300.0), lam=st.floats(0.0, 400.0))
@settings(max_examples=300, deadline=None, derandomize=True)
def test_noncentral_cdf_matches_scipy(dof, x, lam):
    assert raim.ncx2_cdf(x, dof, lam) == pytest.approx(stats.ncx2.cdf(x, dof, lam), abs=1e-10)


@pytest.mark.parametrize("p_md", [1e-2, 1e-3, 1e-7])
@pytest.mark.parametrize("dof", [1, 4, 12, 30])
def test_noncentrality_gives_the_missed_detection(dof, p_md):
    lam = raim.noncentrality_md(dof, 1e-5, p_md)
    t_max = stats.chi2.isf(1e-5, dof)
    assert stats.ncx2.cdf(t_max, dof, lam) == pytest.approx(p_md, rel=1e-6)


def test_test_off_means_infinite_threshold():
    assert raim.chi2_threshold(5, 0.0) == math.inf
    assert raim.noncentrality_md(5, 0.0, 1e-3) == math.inf
    with pytest.raises(ValueError):
        raim.chi2_threshold(0, 1e-5)


def _geometry(seed: int, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    el = rng.uniform(np.radians(10), np.radians(85), n)
    az = rng.uniform(0, 2 * np.pi, n)
    e_enu = np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=1)
    g = np.concatenate([-e_enu, np.ones((n, 1))], axis=1)  # ENU frame: rotation = I
    sigma = rng.uniform(0.8, 4.0, n)
    return g, sigma, rng.normal(0.0, sigma)


@pytest.mark.parametrize("seed", range(5))
def test_assess_statistic_covariance_and_slopes_are_the_least_squares_ones(seed):
    n = 9
    g, sigma, noise = _geometry(seed, n)
    # the fit itself by numpy's lstsq on whitened rows, independently of service.engine.raim
    gw, yw = g / sigma[:, None], noise / sigma
    x, *_ = np.linalg.lstsq(gw, yw, rcond=None)
    v = noise - g @ x
    out = raim.assess(g, v, sigma, np.eye(3), 1e-5, 1e-3)
    assert out.redundancy == n - 4
    assert out.chi2 == pytest.approx(float(np.sum((v / sigma) ** 2)), rel=1e-9)
    cov = np.linalg.inv(gw.T @ gw)
    assert out.cov_enu_m2 == pytest.approx(cov[:3, :3], rel=1e-9)
    # a bias b on satellite i: its position shift and test statistic, by re-fitting
    pbias = math.sqrt(raim.noncentrality_md(n - 4, 1e-5, 1e-3))
    worst_h = worst_v = 0.0
    for i in range(n):
        b = np.zeros(n)
        b[i] = 1.0
        dx, *_ = np.linalg.lstsq(gw, b / sigma, rcond=None)
        resid = (b - g @ dx) / sigma
        lam_per_b2 = float(resid @ resid)  # T of a unit bias
        worst_h = max(worst_h, math.hypot(dx[0], dx[1]) / math.sqrt(lam_per_b2))
        worst_v = max(worst_v, abs(dx[2]) / math.sqrt(lam_per_b2))
    sig_major = math.sqrt(np.linalg.eigvalsh(cov[:2, :2])[-1])
    k_h = math.sqrt(-2 * math.log(1e-3))
    k_v = stats.norm.isf(0.5e-3)
    assert out.hpl_m == pytest.approx(worst_h * pbias + k_h * sig_major, rel=1e-9)
    assert out.vpl_m == pytest.approx(worst_v * pbias + k_v * math.sqrt(cov[2, 2]), rel=1e-9)


def test_assess_without_redundancy_has_no_test():
    g, sigma, _ = _geometry(7, 4)
    out = raim.assess(g, np.zeros(4), sigma, np.eye(3), 1e-5, 1e-3)
    assert out.redundancy == 0 and out.chi2 is None and not out.passed
    assert out.hpl_m is None and out.vpl_m is None
