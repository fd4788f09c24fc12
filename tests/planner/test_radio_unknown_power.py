"""The paper's ranging with an unknown transmit power (planner.radio.unknown_power): the 4 × 4
Fisher information against the numerical FIM of the measurement model, its Schur complement
against closed forms, the costs' analytic gradients against finite differences, and the joint
estimator against synthetic truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner.fim import cost, cost_gradient, fisher_information
from planner.params import Channel
from planner.radio.unknown_power import (
    cost_gradient_unknown_power,
    cost_unknown_power,
    equivalent_fim,
    estimate_with_unknown_power,
    fisher_information_unknown_power,
    offset_db,
    position_error_bound_unknown_power,
    range_weight,
)

CH = Channel()


def _scene(seed: int, n: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    src = np.array([rng.uniform(-10, 10), rng.uniform(-10, 10), rng.uniform(0, 20)])
    pos = np.column_stack([rng.uniform(-90, 90, n), rng.uniform(-90, 90, n), rng.uniform(2, 25, n)])
    kappa = rng.random(n) < 0.7
    beta = ~kappa | (rng.random(n) < 0.4)
    los = rng.random(n) < 0.75
    return src, pos, kappa, beta, los


def _numerical_fim(src: np.ndarray, pos: np.ndarray, kappa: np.ndarray, los: np.ndarray, b: float) -> np.ndarray:
    """Σ ∇m∇mᵀ/v + ∇v∇vᵀ/(2v²) of d̂ ~ N(m, v), m = e^b d, v = σ_r0² m^γ, by central
    differences in (p0, b): the Gaussian FIM, independent of the A_r shortcut."""

    def mv(theta: np.ndarray, p: np.ndarray, in_los: bool) -> tuple[float, float]:
        m = math.exp(theta[3]) * float(np.linalg.norm(theta[:3] - p))
        s0 = CH.sigma_r0_los if in_los else CH.sigma_r0_nlos
        return m, s0 * s0 * m**CH.gamma

    theta = np.r_[src, b]
    J = np.zeros((4, 4))
    for j in np.nonzero(kappa)[0]:
        gm, gv = np.zeros(4), np.zeros(4)
        for a in range(4):
            e = np.zeros(4)
            e[a] = 1e-6
            (mp, vp), (mm, vm) = mv(theta + e, pos[j], los[j]), mv(theta - e, pos[j], los[j])
            gm[a], gv[a] = (mp - mm) / 2e-6, (vp - vm) / 2e-6
        v = mv(theta, pos[j], los[j])[1]
        J += np.outer(gm, gm) / v + np.outer(gv, gv) / (2 * v * v)
    return J


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("b", [0.0, 0.3])
def test_fim4_equals_the_numerical_fim_of_the_measurement_model(seed: int, b: float) -> None:
    src, pos, kappa, beta, los = _scene(seed)
    J4 = fisher_information_unknown_power(src, pos, kappa, beta, los, CH, offset=b)
    ref = _numerical_fim(src, pos, kappa, los, b)
    ref[:3, :3] += fisher_information(src, pos, np.zeros(len(pos), dtype=bool), beta, los, CH)  # bearings: no b
    assert np.allclose(J4, ref, rtol=1e-6, atol=1e-12 * np.abs(ref).max())


def test_fim4_position_block_is_the_known_power_fim_at_zero_offset() -> None:
    src, pos, kappa, beta, los = _scene(7)
    J4 = fisher_information_unknown_power(src, pos, kappa, beta, los, CH)
    assert np.allclose(J4[:3, :3], fisher_information(src, pos, kappa, beta, los, CH), rtol=1e-12)


def test_schur_complement_is_the_position_block_of_the_inverse() -> None:
    src, pos, kappa, beta, los = _scene(3)
    J4 = fisher_information_unknown_power(src, pos, kappa, beta, los, CH)
    assert np.allclose(np.linalg.inv(equivalent_fim(J4)), np.linalg.inv(J4)[:3, :3], rtol=1e-8)
    peb, status = position_error_bound_unknown_power(J4)
    assert int(status) == 0
    assert float(peb) == pytest.approx(math.sqrt(np.trace(np.linalg.inv(J4)[:3, :3])), rel=1e-10)
    # Not knowing the power never helps.
    assert float(peb) >= math.sqrt(np.trace(np.linalg.inv(J4[:3, :3]))) - 1e-12


def test_closed_form_circle_above_the_source_loses_all_vertical_information() -> None:
    """N ranging drones on a horizontal circle of radius R at height h above the source are all
    at the same distance d: c = −N w d² h e_z, β = N w d⁴, so J_eq,zz = N w h² − (N w d² h)²/(N w d⁴)
    = 0; the horizontal block is untouched, N w R²/2 on each axis."""
    n, R, h = 8, 60.0, 20.0
    ang = 2 * np.pi * np.arange(n) / n
    pos = np.column_stack([R * np.cos(ang), R * np.sin(ang), np.full(n, h)])
    src = np.zeros(3)
    J4 = fisher_information_unknown_power(src, pos, np.ones(n, bool), np.zeros(n, bool), np.ones(n, bool), CH)
    w, _ = range_weight(math.hypot(R, h), 1.0, CH)
    Jeq = equivalent_fim(J4)
    assert J4[2, 2] == pytest.approx(n * w * h * h, rel=1e-12)
    assert abs(Jeq[2, 2]) < 1e-12 * J4[2, 2]
    assert Jeq[0, 0] == pytest.approx(n * w * R * R / 2, rel=1e-12)
    assert Jeq[1, 1] == pytest.approx(n * w * R * R / 2, rel=1e-12)
    peb, status = position_error_bound_unknown_power(J4)
    assert math.isinf(float(peb)) and int(status) == 2


def test_closed_form_symmetric_swarm_loses_nothing() -> None:
    """Six drones on the axes at ±R around the source: Σ w d² r = 0, so J_eq = J₃ = (2wR²) I."""
    R = 50.0
    pos = np.array([[R, 0, 0], [-R, 0, 0], [0, R, 0], [0, -R, 0], [0, 0, R], [0, 0, -R]], dtype=float) + np.array([0.0, 0.0, 60.0])
    src = np.array([0.0, 0.0, 60.0])
    J4 = fisher_information_unknown_power(src, pos, np.ones(6, bool), np.zeros(6, bool), np.ones(6, bool), CH)
    w, _ = range_weight(R, 1.0, CH)
    assert np.allclose(J4[:3, 3], 0.0, atol=1e-15)
    assert np.allclose(equivalent_fim(J4), 2 * w * R * R * np.eye(3), rtol=1e-12)


def test_closed_form_two_drones_on_a_line() -> None:
    """Drones at −d1 and +d2 on the x axis: J_eq,xx = w1 w2 d1² d2² (d1 + d2)²/(w1 d1⁴ + w2 d2⁴)."""
    d1, d2 = 30.0, 80.0
    pos = np.array([[-d1, 0.0, 0.0], [d2, 0.0, 0.0]])
    J4 = fisher_information_unknown_power(np.zeros(3), pos, np.ones(2, bool), np.zeros(2, bool), np.ones(2, bool), CH)
    w1, _ = range_weight(d1, 1.0, CH)
    w2, _ = range_weight(d2, 1.0, CH)
    expected = w1 * w2 * d1**2 * d2**2 * (d1 + d2) ** 2 / (w1 * d1**4 + w2 * d2**4)
    assert equivalent_fim(J4)[0, 0] == pytest.approx(expected, rel=1e-12)


def test_bearing_only_swarm_is_unaffected() -> None:
    src, pos, _, _, los = _scene(5)
    n = len(pos)
    J4 = fisher_information_unknown_power(src, pos, np.zeros(n, bool), np.ones(n, bool), los, CH)
    J3 = fisher_information(src, pos, np.zeros(n, bool), np.ones(n, bool), los, CH)
    assert np.allclose(equivalent_fim(J4), J3, rtol=1e-12)
    for crit in ("A", "D"):
        g4 = cost_gradient_unknown_power(J4, src, pos[0], False, True, los[0], CH, crit)
        g3 = cost_gradient(J3, src, pos[0], False, True, los[0], CH, crit)
        assert float(g4.value) == pytest.approx(float(g3.value), rel=1e-12)
        assert np.allclose(g4.gradient, g3.gradient, rtol=1e-9, atol=1e-15)


@pytest.mark.parametrize("criterion", ["A", "D"])
@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("b", [0.0, -0.2])
def test_cost_gradient_matches_finite_differences(criterion: str, seed: int, b: float) -> None:
    src, pos, kappa, beta, los = _scene(seed, n=6)
    i = 0
    kappa[i] = True  # the drone whose step is planned ranges (and maybe bears)
    q = 0.6  # a LOS weight, as the planner's predicted own link

    def total(p_i: np.ndarray) -> float:
        P = pos.copy()
        P[i] = p_i
        L = los.astype(float)
        L[i] = q
        return float(cost_unknown_power(fisher_information_unknown_power(src, P, kappa, beta, L, CH, offset=b), criterion)[0])  # type: ignore[arg-type]

    L = los.astype(float)
    L[i] = q
    J4 = fisher_information_unknown_power(src, pos, kappa, beta, L, CH, offset=b)
    cg = cost_gradient_unknown_power(J4, src, pos[i], kappa[i], beta[i], q, CH, criterion, offset=b)  # type: ignore[arg-type]
    h = 1e-4
    fd = np.array([(total(pos[i] + e) - total(pos[i] - e)) / (2 * h) for e in np.eye(3) * h])
    assert float(cg.value) == pytest.approx(total(pos[i]), rel=1e-12)
    assert np.allclose(cg.gradient, fd, rtol=1e-5, atol=1e-9 * np.abs(fd).max())


def test_cost_gradient_los_weight_term_matches_finite_differences() -> None:
    """With ∇q given, the gradient adds tr(M₄ (J_LOS − J_NLOS)) ∇q: check d/dq by differences."""
    src, pos, kappa, beta, los = _scene(11, n=6)
    kappa[0] = beta[0] = True

    def c_of_q(q: float) -> float:
        L = los.astype(float)
        L[0] = q
        return float(cost_unknown_power(fisher_information_unknown_power(src, pos, kappa, beta, L, CH), "A")[0])

    L = los.astype(float)
    L[0] = 0.5
    J4 = fisher_information_unknown_power(src, pos, kappa, beta, L, CH)
    grad_q = np.array([1.0, 0.0, 0.0])  # a made-up ∇q: the x component picks up dC/dq
    with_q = cost_gradient_unknown_power(J4, src, pos[0], True, True, 0.5, CH, "A", own_los_gradient=grad_q)
    without = cost_gradient_unknown_power(J4, src, pos[0], True, True, 0.5, CH, "A")
    dc_dq = (c_of_q(0.5 + 1e-6) - c_of_q(0.5 - 1e-6)) / 2e-6
    assert with_q.gradient[0] - without.gradient[0] == pytest.approx(dc_dq, rel=1e-5)


def test_known_power_cost_is_a_lower_bound_of_the_unknown_one() -> None:
    for seed in range(6):
        src, pos, kappa, beta, los = _scene(seed)
        J4 = fisher_information_unknown_power(src, pos, kappa, beta, los, CH)
        a_known = float(cost(J4[:3, :3], "A")[0])
        a_unknown = float(cost_unknown_power(J4, "A")[0])
        assert a_unknown >= a_known * (1 - 1e-12)


def _ring(n: int = 10, radius: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(0)
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return np.column_stack([radius * np.cos(ang), radius * np.sin(ang), rng.uniform(2, 25, n)]), np.array([0.0, 0.0, 10.0])


def test_estimator_is_efficient_and_unbiased_against_synthetic_truth() -> None:
    """The paper's final-geometry shape (a ring of ten drones at the keep-out distance, heights
    2-25 m), 800 snapshots: over 200 seeded trials the joint ML of (p0, b) has RMSE within
    ±15 % of the unknown-power PEB (3.5 standard errors of an RMSE estimated from 200 trials:
    ≈ 1/√(2·200) = 3.5 % relative) and a bias below 0.2 PEB; b is unbiased and its spread is
    √(J₄⁻¹)_bb within 15 %."""
    pos, src = _ring()
    K = 800
    n = len(pos)
    J4 = K * fisher_information_unknown_power(src, pos, np.ones(n, bool), np.zeros(n, bool), np.ones(n, bool), CH)
    peb = float(position_error_bound_unknown_power(J4)[0])
    errs, offsets = [], []
    d = np.linalg.norm(src - pos, axis=1)
    P = np.tile(pos, (K, 1))
    D = np.tile(d, K)
    for m in range(200):
        rng = np.random.default_rng([40, m])
        z = D + CH.sigma_r0_los * D ** (CH.gamma / 2) * rng.standard_normal(D.shape)
        est = estimate_with_unknown_power(P, z, np.ones(len(z), bool), CH, src + rng.normal(0.0, 3.0, 3))
        assert est.converged
        errs.append(est.source_m - src)
        offsets.append(est.offset)
    errs = np.array(errs)
    rmse = math.sqrt((errs**2).sum(1).mean())
    assert 0.85 * peb <= rmse <= 1.15 * peb
    assert np.linalg.norm(errs.mean(0)) < 0.2 * peb
    sd_b = math.sqrt(np.linalg.inv(J4)[3, 3])
    assert abs(np.mean(offsets)) < 0.25 * sd_b
    assert np.std(offsets) == pytest.approx(sd_b, rel=0.15)


def test_estimator_recovers_an_offset_and_an_exponent() -> None:
    """Ranges from a source 3 dB weaker than assumed (ranges read long) and a channel of exponent 2.4 read by
    drones that assume 2.0: the estimate of b (ΔP = 10γ b/ln 10) and ν = γ/γ_assumed."""
    rng = np.random.default_rng(9)
    n = 40
    pos = np.column_stack([rng.uniform(-150, 150, n), rng.uniform(-150, 150, n), rng.uniform(2, 25, n)])
    src = np.array([5.0, -8.0, 3.0])
    nu, b = 1.2, 3.0 * math.log(10) / (10 * CH.gamma)
    d = np.linalg.norm(src - pos, axis=1)
    K = 400
    s = np.tile(math.exp(b) * d**nu, K)
    z = s + CH.sigma_r0_los * s ** (CH.gamma / 2) * 0.25 * rng.standard_normal(s.shape)  # quieter ranges
    est = estimate_with_unknown_power(np.tile(pos, (K, 1)), z, np.ones(len(z), bool), CH, src + 2.0, estimate_exponent=True)
    assert est.converged
    assert est.exponent_ratio == pytest.approx(nu, abs=0.02)
    assert float(offset_db(est.offset, CH.gamma)) == pytest.approx(3.0, abs=1.5)
    assert np.linalg.norm(est.source_m - src) < 5.0


def test_estimator_refuses_too_few_ranges() -> None:
    with pytest.raises(ValueError, match="at least 5 ranges"):
        estimate_with_unknown_power(np.zeros((3, 3)), np.ones(3), np.ones(3, bool), CH, np.zeros(3))
