"""planner.fisher_information against the FIM derived numerically from the measurement model.

The reference never uses the closed forms of planner/fim.py: it differentiates the measurement
model itself (d, φ, θ as atan2 of r = p0 − p_j, and the RSS variance σ_r² = σ_r0² d^γ) by
central finite differences with respect to the source and assembles, per Gaussian
measurement with mean μ(p0) and variance σ²(p0),

    J = Σ ∇μ ∇μᵀ / σ² + ∇σ² ∇σ²ᵀ / (2 σ⁴)

(ranging: μ = d, σ² = σ_r²; bearing, LOS only: μ = φ and μ = θ, constant σ_b², no variance
term). A Monte Carlo check compares J with the covariance of the score of the log-likelihood of
measurements drawn by planner.observation.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner import Channel, fisher_information, observe_from_uniforms
from planner.geometry import line_of_sight

LN10_10 = math.log(10.0) / 10.0
ROLES = {"r": (True, False), "b": (False, True), "j": (True, True)}


# ---------------------------------------------------------------- independent reference


def _measurement_means(p0: np.ndarray, pj: np.ndarray) -> tuple[float, float, float]:
    """d, φ, θ of the source seen from p_j by direct trigonometry (scalar math, no numpy vectorization)."""
    rx, ry, rz = (float(p0[0] - pj[0]), float(p0[1] - pj[1]), float(p0[2] - pj[2]))
    return math.sqrt(rx * rx + ry * ry + rz * rz), math.atan2(ry, rx), math.atan2(rz, math.hypot(rx, ry))


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def _fd_grad(f, p0: np.ndarray, h: float, angle: bool = False) -> np.ndarray:
    g = np.empty(3)
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        diff = f(p0 + e) - f(p0 - e)
        g[k] = (_wrap(diff) if angle else diff) / (2.0 * h)
    return g


def numeric_fim_term(p0, pj, ranging, bearing, los, gamma, ratio_los, ratio_nlos, sigma_b) -> np.ndarray:
    """One drone's FIM term from finite-difference Jacobians of the measurement model."""
    d = _measurement_means(p0, pj)[0]
    h = 1e-4 * d
    ratio = ratio_los if los else ratio_nlos
    s0sq = (LN10_10 * ratio) ** 2

    def dist(p):
        return _measurement_means(p, pj)[0]

    def var(p):
        return s0sq * dist(p) ** gamma

    J = np.zeros((3, 3))
    if ranging:
        gd = _fd_grad(dist, p0, h)
        gv = _fd_grad(var, p0, h)
        s2 = var(p0)
        J += np.outer(gd, gd) / s2 + np.outer(gv, gv) / (2.0 * s2 * s2)
    if bearing and los:
        gphi = _fd_grad(lambda p: _measurement_means(p, pj)[1], p0, h, angle=True)
        gth = _fd_grad(lambda p: _measurement_means(p, pj)[2], p0, h)
        J += (np.outer(gphi, gphi) + np.outer(gth, gth)) / sigma_b**2
    return J


def random_geometry(rng: np.random.Generator, n: int, source: np.ndarray) -> np.ndarray:
    """n drones at 3-300 m from the source, not within ~6° of its vertical (φ well defined)."""
    out = []
    while len(out) < n:
        d = rng.uniform(3.0, 300.0)
        az = rng.uniform(-math.pi, math.pi)
        el = rng.uniform(-1.45, 1.45)
        out.append(source - d * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)]))
    return np.array(out)


def assert_matrix_close(actual: np.ndarray, expected: np.ndarray, rtol: float) -> None:
    scale = max(np.linalg.norm(expected), 1e-300)
    err = np.linalg.norm(actual - expected)
    assert err <= rtol * scale, f"|J - J_ref| = {err:.3e} > {rtol:g} * |J_ref| = {rtol * scale:.3e}\n{actual}\n{expected}"


# ---------------------------------------------------------------- property tests

channels = st.builds(
    Channel,
    gamma=st.floats(1.5, 4.0),
    sigma_ratio_los=st.floats(0.5, 3.0),
    sigma_ratio_nlos=st.floats(1.0, 6.0),
    sigma_bearing_rad=st.floats(math.radians(1.0), math.radians(30.0)),
)


@settings(max_examples=300, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    roles=st.lists(st.sampled_from("rbj"), min_size=1, max_size=7),
    los_bits=st.lists(st.booleans(), min_size=7, max_size=7),
    channel=channels,
)
def test_fim_matches_numeric_fim_of_measurement_model(seed, roles, los_bits, channel):
    rng = np.random.default_rng(seed)
    n = len(roles)
    source = rng.uniform(-200.0, 200.0, 3)
    positions = random_geometry(rng, n, source)
    ranging = np.array([ROLES[r][0] for r in roles])
    bearing = np.array([ROLES[r][1] for r in roles])
    los = np.array(los_bits[:n])
    args = (channel.gamma, channel.sigma_ratio_los, channel.sigma_ratio_nlos, channel.sigma_bearing_rad)
    total = np.zeros((3, 3))
    for j in range(n):
        ref = numeric_fim_term(source, positions[j], ranging[j], bearing[j], los[j], *args)
        total += ref
        got = fisher_information(source, positions[j : j + 1], ranging[j : j + 1], bearing[j : j + 1], los[j : j + 1], channel)
        if ref.any():
            assert_matrix_close(got, ref, 1e-6)
        else:  # NLOS bearing-only drone: no information at all
            assert np.array_equal(got, np.zeros((3, 3)))
    got = fisher_information(source, positions, ranging, bearing, los, channel)
    assert got.shape == (3, 3)
    assert np.allclose(got, got.T, rtol=0, atol=1e-15 * np.abs(got).max(initial=1.0))
    assert_matrix_close(got, total, 1e-6)


def test_fim_paper_values_single_joint_drone():
    """A hand-checkable case: joint drone 10 m due west of the source, same altitude, LOS.

    Then a = e_x (d = 10): ranging adds A_r on xx with A_r = 1/(σ_r0² d^γ) + γ²/(2d²);
    azimuth adds 1/(σ_b² d²) on yy; elevation adds 1/(σ_b² d²) on zz.
    """
    ch = Channel(gamma=2.0, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=math.radians(10.0))
    J = fisher_information([0.0, 0.0, 10.0], [[-10.0, 0.0, 10.0]], [True], [True], [True], ch)
    s0 = math.log(10.0) / 10.0 * 1.7
    a_r = 1.0 / (s0**2 * 100.0) + 4.0 / (2.0 * 100.0)
    a_b = 1.0 / (math.radians(10.0) ** 2 * 100.0)
    np.testing.assert_allclose(J, np.diag([a_r, a_b, a_b]), rtol=1e-12, atol=1e-15)


def test_fim_batching_over_leading_dims_equals_loop(rng):
    ch = Channel(gamma=2.7)
    T, S, N = 3, 4, 6
    src = rng.uniform(-50, 50, (T, S, 3))
    pos = src[..., None, :] + rng.uniform(-100, 100, (T, S, N, 3))
    rr = rng.random((T, S, N)) < 0.6
    bb = rng.random((T, S, N)) < 0.6
    los = rng.random((T, S, N)) < 0.7
    batched = fisher_information(src, pos, rr, bb, los, ch)
    assert batched.shape == (T, S, 3, 3)
    for t in range(T):
        for s in range(S):
            one = fisher_information(src[t, s], pos[t, s], rr[t, s], bb[t, s], los[t, s], ch)
            np.testing.assert_allclose(batched[t, s], one, rtol=1e-13, atol=0)
    # Roles given once per drone (N,) broadcast against the batch.
    shared = fisher_information(src, pos, rr[0, 0], bb[0, 0], los, ch)
    np.testing.assert_allclose(shared[1, 2], fisher_information(src[1, 2], pos[1, 2], rr[0, 0], bb[0, 0], los[1, 2], ch), rtol=1e-13)


def test_nlos_bearing_carries_no_information_and_nlos_range_less():
    ch = Channel()
    src = np.array([0.0, 0.0, 10.0])
    pos = np.array([[30.0, 40.0, 5.0]])
    assert not fisher_information(src, pos, [False], [True], [False], ch).any()
    los_r = fisher_information(src, pos, [True], [False], [True], ch)
    nlos_r = fisher_information(src, pos, [True], [False], [False], ch)
    # NLOS ranging: larger σ_sh/γ, so strictly less information (the γ²/2d² term is common).
    assert np.trace(nlos_r) < np.trace(los_r)


# ---------------------------------------------------------------- Monte Carlo: J = E[score scoreᵀ]


def _log_likelihood(p0s: np.ndarray, positions, ranging, bearing, los, ch: Channel, d_hat, az_hat, el_hat) -> np.ndarray:
    """Gaussian log-likelihood of the measurements (M samples) at candidate sources p0s (K, 3) -> (K, M).

    Written from eqs. 3-5 directly: independent Gaussians; an NLOS bearing is an outlier whose
    (uniform) density does not depend on p0 and is left out.
    """
    out = []
    for p0 in p0s:
        total = np.zeros(d_hat.shape[0])
        for j in range(len(positions)):
            d, phi, th = _measurement_means(p0, positions[j])
            if ranging[j]:
                s2 = (LN10_10 * (ch.sigma_ratio_los if los[j] else ch.sigma_ratio_nlos)) ** 2 * d**ch.gamma
                total += -0.5 * np.log(2 * np.pi * s2) - (d_hat[:, j] - d) ** 2 / (2 * s2)
            if bearing[j] and los[j]:
                e_az = np.angle(np.exp(1j * (az_hat[:, j] - phi)))
                total += -(e_az**2 + (el_hat[:, j] - th) ** 2) / (2 * ch.sigma_bearing_rad**2)
        out.append(total)
    return np.array(out)


def test_score_covariance_equals_fim_monte_carlo():
    rng = np.random.default_rng(20261121)
    ch = Channel(gamma=2.5, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=math.radians(10.0))
    src = np.array([10.0, 200.0, 12.0])
    positions = np.array([[-20.0, 150.0, 8.0], [25.0, 160.0, 20.0], [60.0, 230.0, 5.0], [0.0, 260.0, 15.0], [-40.0, 210.0, 3.0]])
    ranging = np.array([True, False, True, True, False])
    bearing = np.array([False, True, True, True, True])
    los = np.array([True, True, False, True, False])
    M = 40000
    obs = observe_from_uniforms(src, positions, ranging, bearing, los, ch, rng.random((M, 5, 5)))
    h = 1e-4
    plus = src + h * np.eye(3)
    minus = src - h * np.eye(3)
    args = (positions, ranging, bearing, los, ch, obs.range_m, obs.azimuth_rad, obs.elevation_rad)
    score = (_log_likelihood(plus, *args) - _log_likelihood(minus, *args)) / (2 * h)  # (3, M)
    J = fisher_information(src, positions, ranging, bearing, los, ch)
    L = np.linalg.cholesky(J)
    white = np.linalg.solve(L, score)  # J^-1/2 score: identity covariance if J is right
    cov = white @ white.T / M
    mean = white.mean(axis=1)
    assert np.abs(mean).max() < 5.0 / math.sqrt(M) * 1.5
    assert np.abs(cov - np.eye(3)).max() < 0.04, cov
    # A wrong FIM is detected: leaving out the variance term γ²/(2d²) (a classic slip) fails.
    J_wrong = J.copy()
    for j in np.flatnonzero(ranging):
        r = src - positions[j]
        d2 = r @ r
        J_wrong -= ch.gamma**2 / (2 * d2) * np.outer(r, r) / d2
    white_w = np.linalg.solve(np.linalg.cholesky(J_wrong), score)
    assert np.abs(white_w @ white_w.T / M - np.eye(3)).max() > 0.1


# ---------------------------------------------------------------- eq. 11 as printed


def _a(phi: float, theta: float) -> np.ndarray:
    """The paper's direction vector a(φ, θ) (below eq. 11)."""
    return np.array([math.cos(phi) * math.cos(theta), math.sin(phi) * math.cos(theta), math.sin(theta)])


@settings(max_examples=200, deadline=None)
@given(
    d=st.floats(5.0, 500.0),
    phi=st.floats(-math.pi, math.pi),
    theta=st.floats(-1.4, 1.4).filter(lambda t: abs(math.sin(2.0 * t)) > 0.05),
    sign=st.sampled_from((1.0, -1.0)),
)
def test_elevation_gradient_is_a_theta_plus_half_pi_not_the_printed_minus_theta_minus_half_pi(d, phi, theta, sign):
    """Eq. 11 prints G_el = G_r(φ, −θ − π/2)/d². The elevation's gradient (finite differences of
    atan2, with respect to the source or, with the opposite sign, the drone) is a(φ, θ + π/2)/d.
    a(φ, −θ − π/2) differs from it in the sign of its z component only: it is neither the same
    vector nor its opposite, so its outer product is not ∇θ∇θᵀ d² (they differ by √2 |sin 2θ| in
    Frobenius norm), and it is not even orthogonal to a(φ, θ) (a · a_printed = −sin 2θ)."""
    pj = np.array([3.0, -7.0, 11.0])
    p0 = pj + d * _a(phi, theta)  # source seen from the drone at distance d, azimuth φ, elevation θ
    dist, phi_m, th_m = _measurement_means(p0, pj)
    assert math.isclose(dist, d, rel_tol=1e-12) and math.isclose(th_m, theta, abs_tol=1e-12)

    def theta_of_source(p: np.ndarray) -> float:
        return _measurement_means(p, pj)[2]

    def theta_of_drone(p: np.ndarray) -> float:
        return _measurement_means(p0, p)[2]

    grad = _fd_grad(theta_of_source, p0, 1e-5 * d) if sign > 0 else -_fd_grad(theta_of_drone, pj, 1e-5 * d)
    model = _a(phi, theta + math.pi / 2.0)
    printed = _a(phi, -theta - math.pi / 2.0)
    np.testing.assert_allclose(grad * d, model, rtol=0, atol=1e-6)
    np.testing.assert_allclose(printed, model * np.array([1.0, 1.0, -1.0]), rtol=0, atol=1e-12)
    assert min(np.linalg.norm(grad * d - printed), np.linalg.norm(grad * d + printed)) > 0.04
    diff = np.linalg.norm(np.outer(printed, printed) - np.outer(grad, grad) * d * d)
    assert math.isclose(diff, math.sqrt(2.0) * abs(math.sin(2.0 * theta)), rel_tol=1e-4, abs_tol=1e-6)
    assert math.isclose(float(_a(phi, theta) @ printed), -math.sin(2.0 * theta), abs_tol=1e-12)


def test_printed_eq11_changes_the_fim_of_the_paper_geometry_by_up_to_71_percent():
    """docs/paper-notes.md's figure. A joint LOS drone of the paper's case study (σ_sh/γ = 1.7,
    σ_b = 10°, γ = 2; source at z = 2 m as in missions/paper) at the steepest elevation the
    constraints allow: on the d_S* = 50 m keep-out sphere at z_max = 25 m, θ = −asin(23/50) =
    −27.4°. fisher_information equals eq. 10 assembled from eq. 11 with G_el = G_r(φ, θ+π/2)/d²
    and differs from the FIM with the printed G_r(φ, −θ−π/2)/d² by 70.6 % (Frobenius, relative);
    the PEB of the printed FIM is 65 % larger. Ten such drones at one point give the same ratios
    (every term scales by N)."""
    ch = Channel(gamma=2.0, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=math.radians(10.0))
    src = np.array([0.0, 0.0, 2.0])
    theta = -math.asin(23.0 / 50.0)
    for phi in (0.3, 1.9, -2.4):
        pj = src - 50.0 * _a(phi, theta)
        assert math.isclose(pj[2], 25.0, rel_tol=1e-12)
        d, phi_m, th_m = _measurement_means(src, pj)
        s0sq = (LN10_10 * 1.7) ** 2
        a_r = 1.0 / (s0sq * d**2) * (1.0 + 2.0 * 4.0 * s0sq * d**2 / (4.0 * d**2))  # eq. 12 as printed
        a_b = 1.0 / ch.sigma_bearing_rad**2
        g_r = np.outer(_a(phi_m, th_m), _a(phi_m, th_m))
        g_az = np.outer(_a(phi_m + math.pi / 2, 0.0), _a(phi_m + math.pi / 2, 0.0)) / (d * math.cos(th_m)) ** 2
        e_model, e_printed = _a(phi_m, th_m + math.pi / 2), _a(phi_m, -th_m - math.pi / 2)
        j_model = a_r * g_r + a_b * (g_az + np.outer(e_model, e_model) / d**2)
        j_printed = a_r * g_r + a_b * (g_az + np.outer(e_printed, e_printed) / d**2)
        got = fisher_information(src, pj[None, :], [True], [True], [True], ch)
        assert_matrix_close(got, j_model, 1e-12)
        rel = np.linalg.norm(j_printed - got) / np.linalg.norm(got)
        assert 0.705 < rel < 0.707, rel
        peb_ratio = math.sqrt(np.trace(np.linalg.inv(j_printed)) / np.trace(np.linalg.inv(got)))
        assert 1.64 < peb_ratio < 1.66, peb_ratio


def _printed_minus_model_elevation_terms(src, positions, los, ch: Channel) -> np.ndarray:
    """J_printed − J_model for joint drones: for every LOS drone, A_b (e eᵀ − e' e'ᵀ)/d² with the
    printed e = a(φ, −θ−π/2) and the model's e' = a(φ, θ+π/2) (eq. 11's elevation term)."""
    diff = np.zeros((3, 3))
    for pj, l in zip(positions, los):
        if not l:
            continue
        d, phi, th = _measurement_means(src, pj)
        e_printed, e_model = _a(phi, -th - math.pi / 2), _a(phi, th + math.pi / 2)
        diff += (np.outer(e_printed, e_printed) - np.outer(e_model, e_model)) / (ch.sigma_bearing_rad**2 * d * d)
    return diff


def test_printed_eq11_at_the_paper_start_and_for_one_drone_by_elevation():
    """docs/paper-notes.md's eq. 11 figures other than the maximum. (1) The joint paper mission at
    k = 0 (missions/paper/joint.yaml: ten joint drones on the start ellipse, centre [0, 150, 8] m,
    r_x = 20 m, r_z = 5 m; source [0, 0, 2] m; buildings B1-B3 for the LOS flags): the printed
    G_el changes the FIM by 7.7 % (Frobenius, relative) and the PEB by +0.25 %. (2) One joint LOS
    drone 50 m from the source at an elevation of 5°, 10°, 20°: 17 %, 33 %, 59 % (with γ = 2 the
    ratio does not depend on the distance: checked at 50 m and 150 m)."""
    ch = Channel(gamma=2.0, sigma_ratio_los=1.7, sigma_ratio_nlos=3.2, sigma_bearing_rad=math.radians(10.0))
    src = np.array([0.0, 0.0, 2.0])
    alpha = 2.0 * math.pi * np.arange(10) / 10.0
    starts = np.stack([20.0 * np.cos(alpha), np.full(10, 150.0), 8.0 + 5.0 * np.sin(alpha)], axis=-1)
    boxes_min = np.array([[-40.0, 95.0, 0.0], [10.0, 70.0, 0.0], [-18.0, 12.0, 0.0]])
    boxes_max = np.array([[-10.0, 115.0, 30.0], [35.0, 90.0, 30.0], [-8.0, 24.0, 30.0]])
    los = line_of_sight(starts, src, boxes_min, boxes_max)
    assert los.tolist() == [False, True, True, True, False, False, False, True, True, True]
    ones = np.ones(10, dtype=bool)
    j_model = fisher_information(src, starts, ones, ones, los, ch)
    j_printed = j_model + _printed_minus_model_elevation_terms(src, starts, los, ch)
    rel = np.linalg.norm(j_printed - j_model) / np.linalg.norm(j_model)
    assert 0.0765 < rel < 0.0775, rel
    peb_change = math.sqrt(np.trace(np.linalg.inv(j_printed)) / np.trace(np.linalg.inv(j_model))) - 1.0
    assert 0.00245 < peb_change < 0.00255, peb_change

    for elevation_deg, expected in ((5.0, 0.17), (10.0, 0.33), (20.0, 0.59)):
        for dist in (50.0, 150.0):
            pj = src - dist * _a(0.3, -math.radians(elevation_deg))
            j1 = fisher_information(src, pj[None, :], [True], [True], [True], ch)
            j1p = j1 + _printed_minus_model_elevation_terms(src, pj[None, :], [True], ch)
            rel1 = np.linalg.norm(j1p - j1) / np.linalg.norm(j1)
            assert abs(rel1 - expected) < 0.005, (elevation_deg, dist, rel1)
