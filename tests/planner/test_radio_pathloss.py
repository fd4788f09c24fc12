"""The log-distance model (planner.radio.pathloss): antenna patterns and link terms against
finite differences, the channel fit's intervals against synthetic truth over seeded
repetitions, the residual's correlation distance against a process of known correlation."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner.radio.pathloss import PATTERN_FLOOR_DB, Pattern, decorrelation_distance, fit_channel, link_terms, path_length_m, thin_by_distance


def test_dipole_gain_values_and_derivative() -> None:
    dip = Pattern("dipole")
    g, _ = dip.gain_db(np.array([0.0, math.pi / 2, -math.pi / 2]))
    assert g[0] == pytest.approx(0.0, abs=1e-12)  # the horizon: the pattern's maximum
    assert g[1] == g[2] == PATTERN_FLOOR_DB  # the zenith (and nadir) null, floored
    psi = np.linspace(-1.3, 1.3, 27)
    g, dg = dip.gain_db(psi)
    h = 1e-6
    fd = (dip.gain_db(psi + h)[0] - dip.gain_db(psi - h)[0]) / (2 * h)
    assert np.allclose(dg, fd, atol=1e-5)
    # 20 log10 of the half-wave dipole's field pattern cos(π/2 sin ψ)/cos ψ, written out.
    ref = 20 * np.log10(np.cos(0.5 * np.pi * np.sin(psi)) / np.cos(psi))
    assert np.allclose(g, np.maximum(ref, PATTERN_FLOOR_DB), atol=1e-10)
    assert Pattern("isotropic").gain_db(psi)[0].tolist() == [0.0] * len(psi)
    pair_g, pair_dg = Pattern("dipole-pair").gain_db(psi)
    assert np.allclose(pair_g, 2 * g) and np.allclose(pair_dg, 2 * dg)  # the receiver's dipole sees the same elevation
    with pytest.raises(ValueError, match="pattern"):
        Pattern("yagi")


@pytest.mark.parametrize("name", ["isotropic", "dipole", "dipole-pair"])
def test_link_terms_derivatives_match_finite_differences(name: str) -> None:
    rng = np.random.default_rng(2)
    rx = np.column_stack([rng.uniform(-80, 80, 12), rng.uniform(-80, 80, 12), rng.uniform(20, 60, 12)])
    p = np.array([3.0, -4.0, 1.5])
    t = link_terms(p, rx, Pattern(name))
    assert np.allclose(t.log_d, 10 * np.log10(np.linalg.norm(rx - p, axis=1)))
    h = 1e-6
    for a in range(3):
        e = np.zeros(3)
        e[a] = h
        tp, tm = link_terms(p + e, rx, Pattern(name)), link_terms(p - e, rx, Pattern(name))
        assert np.allclose(t.dlogd_dp[:, a], (tp.log_d - tm.log_d) / (2 * h), atol=1e-6)
        assert np.allclose(t.dgain_dp[:, a], (tp.gain - tm.gain) / (2 * h), atol=1e-6)
    bare = link_terms(p, rx, Pattern(name), derivatives=False)
    assert np.array_equal(bare.log_d, t.log_d) and np.array_equal(bare.gain, t.gain)


def _calibration_log(rng: np.random.Generator, n: int, P0: float, gamma: float, s_los: float, s_nlos: float | None, threshold: float) -> tuple:
    d = rng.uniform(20.0, 400.0, n)
    los = np.ones(n, dtype=bool) if s_nlos is None else rng.random(n) < 0.6
    sigma = np.where(los, s_los, s_nlos if s_nlos is not None else s_los)
    y = P0 - 10 * gamma * np.log10(d) + sigma * rng.standard_normal(n)
    cens = y < threshold
    return d, np.where(cens, np.nan, y), cens, np.full(n, threshold), los


def test_fit_channel_intervals_cover_the_truth_at_their_nominal_rate() -> None:
    """300 samples, a third of them censored, 200 seeded repetitions: the 95 % intervals of P0,
    γ and σ cover the truth in 95 % ± 4.5 % of them (4.5 % ≈ 3 binomial standard errors of a
    rate estimated from 200 repetitions, √(0.95·0.05/200) = 1.5 %)."""
    P0, gamma, sigma = 30.0, 3.2, 6.0
    hits = np.zeros(3)
    censored = []
    for m in range(200):
        rng = np.random.default_rng([21, m])
        d, y, cens, thr, los = _calibration_log(rng, 300, P0, gamma, sigma, None, -45.0)
        censored.append(cens.mean())
        fit = fit_channel(d, y, cens, thr, los)
        hits += [
            fit.reference_power_db.low <= P0 <= fit.reference_power_db.high,
            fit.gamma.low <= gamma <= fit.gamma.high,
            fit.sigma_los_db.low <= sigma <= fit.sigma_los_db.high,
        ]
    assert 0.2 < np.mean(censored) < 0.45
    rates = hits / 200
    assert np.all((rates >= 0.905) & (rates <= 0.995)), rates


def test_fit_channel_separates_los_and_nlos_shadowing() -> None:
    rng = np.random.default_rng(5)
    d, y, cens, thr, los = _calibration_log(rng, 3000, 20.0, 2.8, 4.0, 9.0, -60.0)
    fit = fit_channel(d, y, cens, thr, los)
    assert fit.nlos == int((~los).sum())
    assert fit.sigma_nlos_db is not None
    assert fit.sigma_los_db.low <= 4.0 <= fit.sigma_los_db.high
    assert fit.sigma_nlos_db.low <= 9.0 <= fit.sigma_nlos_db.high
    assert fit.gamma.low <= 2.8 <= fit.gamma.high
    assert fit.sigma_ratio_los == pytest.approx(fit.sigma_los_db.value / fit.gamma.value)


def test_treating_censored_samples_as_measurements_biases_the_fit() -> None:
    """The reason censoring is modelled: the same log with the undetected samples set to the
    threshold gives an exponent far outside the censored fit's interval."""
    rng = np.random.default_rng(8)
    d, y, cens, thr, los = _calibration_log(rng, 2000, 30.0, 3.5, 6.0, None, -45.0)
    fit = fit_channel(d, y, cens, thr, los)
    naive = fit_channel(d, np.where(cens, thr, y), np.zeros_like(cens), np.full(len(d), np.nan), los)
    assert fit.gamma.low <= 3.5 <= fit.gamma.high
    assert naive.gamma.high < 3.5 - 0.3


def test_fit_channel_refuses_bad_samples() -> None:
    with pytest.raises(ValueError, match="at least 3 detected"):
        fit_channel(np.array([10.0, 20.0]), np.array([1.0, 2.0]), np.zeros(2, bool), np.full(2, np.nan))
    with pytest.raises(ValueError, match="threshold"):
        fit_channel(np.ones(4) * 10, np.ones(4), np.array([True, False, False, False]), np.full(4, np.nan))


def test_decorrelation_distance_of_a_process_of_known_correlation() -> None:
    """An AR(1) residual sampled every 0.5 m of flight with correlation exp(−s/L), L = 20 m, falls
    below 1/e at about L; independent samples give 0."""
    rng = np.random.default_rng(3)
    n, step, L = 40000, 0.5, 20.0
    rho = math.exp(-step / L)
    e = np.empty(n)
    e[0] = rng.standard_normal()
    noise = rng.standard_normal(n) * math.sqrt(1 - rho * rho)
    for i in range(1, n):
        e[i] = rho * e[i - 1] + noise[i]
    path = np.arange(n) * step
    assert decorrelation_distance(path, e) == pytest.approx(L, rel=0.2)
    assert decorrelation_distance(path, rng.standard_normal(n)) == 0.0


def test_thin_by_distance_and_path_length() -> None:
    pos = np.column_stack([np.arange(11.0), np.zeros(11), np.zeros(11)])
    path = path_length_m(pos)
    assert path.tolist() == list(np.arange(11.0))
    assert thin_by_distance(path, 3.0).tolist() == [0, 3, 6, 9]
    assert thin_by_distance(path, 0.0).tolist() == list(range(11))
