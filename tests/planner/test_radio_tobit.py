"""The censored normal model (planner.radio.tobit) against independent references: finite
differences, numerical integration of the score, a general-purpose optimiser, least squares."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, optimize, stats

from planner.radio.tobit import expected_information, fit_linear, inverse_mills, loglik_terms


def test_inverse_mills_against_scipy_and_its_tail() -> None:
    a = np.array([-40.0, -8.0, -1.0, 0.0, 2.0, 10.0])
    ref = stats.norm.pdf(a[1:]) / stats.norm.cdf(a[1:])
    assert np.allclose(inverse_mills(a[1:]), ref, rtol=1e-10)
    # Far in the lower tail φ/Φ ≈ −a (Mills' ratio), where the naive ratio is 0/0.
    assert inverse_mills(a[:1])[0] == pytest.approx(40.0249, rel=1e-4)


def test_loglik_terms_derivatives_match_finite_differences() -> None:
    rng = np.random.default_rng(1)
    y = rng.normal(0.0, 5.0, 40)
    cens = rng.random(40) < 0.4
    mu = rng.normal(0.0, 5.0, 40)
    sigma = rng.uniform(2.0, 8.0, 40)
    ll, d_mu, d_sigma = loglik_terms(y, cens, mu, sigma)
    h = 1e-6
    assert np.allclose(d_mu, (loglik_terms(y, cens, mu + h, sigma)[0] - loglik_terms(y, cens, mu - h, sigma)[0]) / (2 * h), atol=1e-6)
    assert np.allclose(d_sigma, (loglik_terms(y, cens, mu, sigma + h)[0] - loglik_terms(y, cens, mu, sigma - h)[0]) / (2 * h), atol=1e-6)
    # The values themselves: the normal density and the normal CDF.
    assert np.allclose(ll[~cens], stats.norm.logpdf(y[~cens], mu[~cens], sigma[~cens]))
    assert np.allclose(ll[cens], stats.norm.logcdf(y[cens], mu[cens], sigma[cens]))


@pytest.mark.parametrize(("mu", "sigma", "c"), [(0.0, 1.0, -1.0), (3.0, 6.0, 5.0), (-2.0, 2.5, 1.0), (10.0, 4.0, -3.0)])
def test_expected_information_equals_the_integrated_score_outer_product(mu: float, sigma: float, c: float) -> None:
    """E[s sᵀ] over y* ~ N(μ, σ²) censored below c, by quadrature of the detected part plus the
    censored mass, with the scores of loglik_terms."""

    def score(y: float, censored: bool) -> np.ndarray:
        _, d_mu, d_sigma = loglik_terms(np.array([y]), np.array([censored]), np.array([mu]), np.array([sigma]))
        return np.array([d_mu[0], d_sigma[0]])

    ref = np.zeros((2, 2))
    for i in range(2):
        for j in range(2):
            ref[i, j] = integrate.quad(lambda y, i=i, j=j: score(y, False)[i] * score(y, False)[j] * stats.norm.pdf(y, mu, sigma), c, np.inf)[0]
    s_c = score(c, True)
    ref += stats.norm.cdf(c, mu, sigma) * np.outer(s_c, s_c)
    i_mm, i_ms, i_ss = expected_information(mu, sigma, c)
    assert np.allclose([[i_mm, i_ms], [i_ms, i_ss]], ref, rtol=1e-7, atol=1e-12)


def test_expected_information_without_a_threshold_is_the_normal_one() -> None:
    i_mm, i_ms, i_ss = expected_information(np.array([1.0, 2.0]), np.array([2.0, 4.0]), np.array([np.nan, -np.inf]))
    assert np.allclose(i_mm, [1 / 4, 1 / 16])
    assert np.allclose(i_ms, 0.0)
    assert np.allclose(i_ss, [2 / 4, 2 / 16])


def _problem(seed: int, n: int = 120) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = np.column_stack([np.ones(n), rng.uniform(-2.0, 2.0, n)])
    offset = rng.normal(0.0, 1.0, n)
    scale = np.where(rng.random(n) < 0.3, 1.8, 1.0)
    y_star = offset + X @ np.array([1.0, -2.0]) + 1.5 * scale * rng.standard_normal(n)
    c = 0.5
    cens = y_star < c
    return np.where(cens, c, y_star), cens, X, offset, scale


def _nll(theta: np.ndarray, y: np.ndarray, cens: np.ndarray, X: np.ndarray, offset: np.ndarray, scale: np.ndarray) -> float:
    mu = offset + X @ theta[:2]
    return -float(loglik_terms(y, cens, mu, np.exp(theta[2]) * scale)[0].sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_fit_linear_reaches_the_maximum_a_general_optimiser_finds(seed: int) -> None:
    y, cens, X, offset, scale = _problem(seed)
    assert 0.2 < cens.mean() < 0.8
    fit = fit_linear(y, cens, X, offset=offset, scale=scale)
    ref = optimize.minimize(
        _nll,
        np.array([0.0, 0.0, 0.0]),
        args=(y, cens, X, offset, scale),
        method="Nelder-Mead",
        options={"xatol": 1e-10, "fatol": 1e-12, "maxiter": 20000},
    )
    assert bool(fit.converged)
    assert fit.loglik == pytest.approx(-ref.fun, abs=1e-7)
    assert np.allclose(fit.beta, ref.x[:2], atol=1e-4)
    assert float(fit.sigma) == pytest.approx(np.exp(ref.x[2]), rel=1e-4)


def test_fit_linear_batched_equals_one_by_one() -> None:
    problems = [_problem(s) for s in range(4)]
    cens = problems[0][1]
    # One censoring pattern for the batch (the design the localization has): reuse sample 0's.
    Y = np.stack([np.where(cens, 0.5, p[0]) for p in problems])
    XX = np.stack([p[2] for p in problems])
    offsets = np.stack([p[3] for p in problems])
    batch = fit_linear(Y, cens, XX, offset=offsets, scale=problems[0][4])
    for i in range(4):
        one = fit_linear(Y[i], cens, XX[i], offset=offsets[i], scale=problems[0][4])
        assert batch.loglik[i] == pytest.approx(float(one.loglik), abs=1e-9)
        assert np.allclose(batch.beta[i], one.beta, atol=1e-8)


def test_fit_linear_without_censoring_is_least_squares() -> None:
    rng = np.random.default_rng(3)
    X = np.column_stack([np.ones(50), rng.normal(size=50)])
    y = X @ np.array([2.0, 0.5]) + rng.normal(size=50)
    fit = fit_linear(y, np.zeros(50, dtype=bool), X)
    beta, rss = np.linalg.lstsq(X, y, rcond=None)[:2]
    assert np.allclose(fit.beta, beta, atol=1e-10)
    assert float(fit.sigma) == pytest.approx(np.sqrt(rss[0] / 50), rel=1e-10)
    assert float(fit.loglik) == pytest.approx(stats.norm.logpdf(y, X @ beta, np.sqrt(rss[0] / 50)).sum(), rel=1e-12)


def test_fit_linear_with_no_regressor_fits_sigma_alone() -> None:
    rng = np.random.default_rng(4)
    y = 3.0 * rng.standard_normal(200)
    fit = fit_linear(y, np.zeros(200, dtype=bool), np.zeros((200, 0)))
    assert fit.beta.shape == (0,)
    assert float(fit.sigma) == pytest.approx(np.sqrt(np.mean(y * y)), rel=1e-10)
