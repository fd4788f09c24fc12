"""A/D-optimality costs (eq. 6, eq. 13) and their gradients w.r.t. one drone's own position.

References: numpy's generic inverse and slogdet, the paper's cofactor expressions of eq. 13
written out literally, and central finite differences of cost(fisher_information(...)).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from planner import Channel, FimStatus, cost, cost_gradient, fisher_information, invert_fim, position_error_bound

ROLES = {"r": (True, False), "b": (False, True), "j": (True, True)}


def random_positions(rng: np.random.Generator, n: int, source: np.ndarray) -> np.ndarray:
    d = rng.uniform(5.0, 250.0, n)
    az = rng.uniform(-math.pi, math.pi, n)
    el = rng.uniform(-1.3, 1.3, n)
    return source - d[:, None] * np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)


def random_spd(rng: np.random.Generator, cond: float) -> np.ndarray:
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    lam = np.exp(rng.uniform(0.0, math.log(cond), 3))
    lam[0], lam[-1] = 1.0, cond
    return (q * (rng.uniform(1e-4, 1e2) * lam)) @ q.T


def paper_eq13(J: np.ndarray) -> tuple[float, float]:
    """Eq. 13 exactly as printed: cofactors C and the first-row expansion of det J."""
    Jxx, Jxy, Jxz = J[0, 0], J[0, 1], J[0, 2]
    Jyy, Jyz, Jzz = J[1, 1], J[1, 2], J[2, 2]
    Cxx = Jyy * Jzz - Jyz**2
    Cyy = Jxx * Jzz - Jxz**2
    Cyx = Jyz * Jxz - Jxy * Jzz
    Czx = Jxy * Jyz - Jyy * Jxz
    Czz = Jxx * Jyy - Jxy**2
    det = Jxx * Cxx + Jxy * Cyx + Jxz * Czx
    return (Cxx + Cyy + Czz) / det, -math.log(det)


def test_cost_matches_numpy_and_paper_cofactors(rng):
    for _ in range(200):
        cond = 10 ** rng.uniform(0, 6)
        J = random_spd(rng, cond=cond)
        a, sa = cost(J, "A")
        d, sd = cost(J, "D")
        assert sa == sd and sa in (FimStatus.OK, FimStatus.ILL_CONDITIONED)
        np.testing.assert_allclose(a, np.trace(np.linalg.inv(J)), rtol=1e-9)
        sign, logdet = np.linalg.slogdet(J)
        assert sign == 1.0
        np.testing.assert_allclose(d, -logdet, rtol=1e-9, atol=1e-9)
        # The first-row cofactor expansion cancels: its relative error grows like eps·cond².
        a13, d13 = paper_eq13(J)
        tol13 = 1e-10 + 1e-13 * cond**2
        np.testing.assert_allclose(a, a13, rtol=tol13)
        np.testing.assert_allclose(d, d13, rtol=0, atol=tol13)
        inv = invert_fim(J)
        np.testing.assert_allclose(inv.inverse @ J, np.eye(3), atol=1e-6)


def test_cost_batched_and_peb(rng):
    Js = np.stack([random_spd(rng, 100.0) for _ in range(12)]).reshape(3, 4, 3, 3)
    a, status = cost(Js, "A")
    assert a.shape == (3, 4) and status.shape == (3, 4)
    np.testing.assert_allclose(a, np.trace(np.linalg.inv(Js), axis1=-2, axis2=-1), rtol=1e-10)
    peb, _ = position_error_bound(Js)
    np.testing.assert_allclose(peb, np.sqrt(np.trace(np.linalg.inv(Js), axis1=-2, axis2=-1)), rtol=1e-10)


def test_unknown_criterion_is_an_error():
    with pytest.raises(ValueError, match="criterion"):
        cost(np.eye(3), "E")  # type: ignore[arg-type]


# ---------------------------------------------------------------- gradients vs finite differences


@settings(max_examples=300, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    roles=st.lists(st.sampled_from("rbj"), min_size=3, max_size=7),
    los_bits=st.lists(st.booleans(), min_size=7, max_size=7),
    criterion=st.sampled_from("AD"),
    gamma=st.floats(1.5, 4.0),
    me=st.integers(0, 6),
)
def test_cost_gradient_matches_finite_differences(seed, roles, los_bits, criterion, gamma, me):
    rng = np.random.default_rng(seed)
    n = len(roles)
    i = me % n
    ch = Channel(gamma=gamma, sigma_bearing_rad=math.radians(rng.uniform(2.0, 20.0)))
    src = rng.uniform(-100, 100, 3)
    pos = random_positions(rng, n, src)
    rr = np.array([ROLES[r][0] for r in roles])
    bb = np.array([ROLES[r][1] for r in roles])
    los = np.array(los_bits[:n])
    J = fisher_information(src, pos, rr, bb, los, ch)
    cg = cost_gradient(J, src, pos[i], rr[i], bb[i], los[i], ch, criterion)
    assume(cg.status == FimStatus.OK)
    value, _ = cost(J, criterion)
    assert cg.value == pytest.approx(float(value), rel=1e-12)

    def c(p: np.ndarray) -> float:
        q = pos.copy()
        q[i] = p
        return float(cost(fisher_information(src, q, rr, bb, los, ch), criterion)[0])

    d = np.linalg.norm(src - pos[i])

    def central(step: float) -> np.ndarray:
        return np.array([(c(pos[i] + step * e) - c(pos[i] - step * e)) / (2 * step) for e in np.eye(3)])

    # Richardson extrapolation of two central differences: O(h^4). Nearly singular J (A costs up
    # to 1e11 m^2 occur) curve so hard that the best step is smaller: accept the analytic gradient
    # when the finite differences agree with it at one of a few steps (a wrong formula is off by
    # far more than 1e-6 at every step).
    errors = []
    for h in (2e-4 * d, 5e-5 * d, 1e-5 * d):
        fd = (4.0 * central(h / 2) - central(h)) / 3.0
        scale = max(np.linalg.norm(fd), np.linalg.norm(cg.gradient))
        # Cost round-off is ~1e-16 |C|, amplified by 1/h; truncation is O(h^4).
        tol = 1e-6 * scale + 1e-13 * abs(float(value)) / h
        errors.append((np.linalg.norm(cg.gradient - fd), tol, fd))
        if errors[-1][0] <= tol:
            break
    else:
        raise AssertionError(f"analytic {cg.gradient} vs finite differences (error, tol, fd): {errors}")
    assert np.isfinite(cg.gradient).all()


def test_cost_gradient_batched_equals_loop(rng):
    ch = Channel(gamma=3.0)
    T, N = 5, 6
    src = rng.uniform(-50, 50, (T, 3))
    pos = np.stack([random_positions(rng, N, s) for s in src])
    rr = np.array([1, 0, 1, 1, 0, 1], bool)
    bb = np.array([0, 1, 1, 1, 1, 0], bool)
    los = rng.random((T, N)) < 0.7
    J = fisher_information(src, pos, rr, bb, los, ch)
    i = 2
    for crit in "AD":
        cg = cost_gradient(J, src, pos[:, i], rr[i], bb[i], los[:, i], ch, crit)
        assert cg.gradient.shape == (T, 3)
        for t in range(T):
            one = cost_gradient(J[t], src[t], pos[t, i], rr[i], bb[i], los[t, i], ch, crit)
            np.testing.assert_allclose(cg.gradient[t], one.gradient, rtol=1e-12, atol=1e-300)


def test_single_drone_path_equals_batched_path(rng):
    """cost_gradient on one (3, 3) J takes a scalar fast path; it must agree with the batched code
    (value and status exactly, gradient to round-off), ill-conditioned J included."""
    ch = Channel(gamma=2.6)
    seen = set()
    for k in range(300):
        n = int(rng.integers(1, 7))
        src = rng.uniform(-100, 100, 3)
        pos = random_positions(rng, n, src)
        rr, bb, los = rng.random(n) < 0.6, rng.random(n) < 0.6, rng.random(n) < 0.7
        if k % 10 == 0:  # ranging drones almost on a line through the source: ill-conditioned
            n = 4
            u = np.array([1.0, 0.0, 0.0])
            eps = 10 ** rng.uniform(-5.5, -4.5)
            pos = src + np.array([-50 * u, 80 * u, -120 * u + [0.0, 120 * eps, 0.0], 60 * u + [0.0, 0.0, 60 * eps]])
            rr, bb, los = np.ones(4, bool), np.zeros(4, bool), np.ones(4, bool)
        J = fisher_information(src, pos, rr, bb, los, ch)
        i = int(rng.integers(0, n))
        for crit in "AD":
            one = cost_gradient(J, src, pos[i], rr[i], bb[i], los[i], ch, crit)
            many = cost_gradient(J[None], src[None], pos[i][None], rr[i : i + 1], bb[i : i + 1], los[i : i + 1], ch, crit)
            assert one.status == many.status[0]
            seen.add(int(one.status))
            assert one.value == many.value[0] or (np.isinf(one.value) and np.isinf(many.value[0]))
            scale = np.abs(many.gradient[0]).max()
            assert np.abs(one.gradient - many.gradient[0]).max() <= 1e-12 * scale, (one.gradient, many.gradient[0])
    assert seen == {FimStatus.OK, FimStatus.ILL_CONDITIONED, FimStatus.SINGULAR}


# ---------------------------------------------------------------- singular and ill-conditioned J


def _singular_cases() -> dict[str, tuple]:
    src = np.array([0.0, 100.0, 10.0])
    ring = random_positions(np.random.default_rng(7), 5, src)
    line = src + np.outer(np.array([-30.0, -60.0, 90.0, 120.0]), np.array([0.6, 0.8, 0.0]))
    return {
        "bearing-only, all NLOS": (src, ring, np.zeros(5, bool), np.ones(5, bool), np.zeros(5, bool)),
        "one ranging drone": (src, ring[:1], np.ones(1, bool), np.zeros(1, bool), np.ones(1, bool)),
        "two ranging drones": (src, ring[:2], np.ones(2, bool), np.zeros(2, bool), np.ones(2, bool)),
        "collinear ranging drones": (src, line, np.ones(4, bool), np.zeros(4, bool), np.ones(4, bool)),
        "no drone": (src, np.zeros((0, 3)), np.zeros(0, bool), np.zeros(0, bool), np.zeros(0, bool)),
    }


@pytest.mark.parametrize("case", list(_singular_cases()))
@pytest.mark.parametrize("criterion", ["A", "D"])
def test_singular_fim_is_reported_never_silent_nan(case, criterion):
    src, pos, rr, bb, los = _singular_cases()[case]
    J = fisher_information(src, pos, rr, bb, los, Channel())
    value, status = cost(J, criterion)
    assert status == FimStatus.SINGULAR
    assert value == np.inf
    own = pos[0] if len(pos) else src + [10.0, 0.0, 0.0]
    own_r = bool(rr[0]) if len(rr) else True
    own_b = bool(bb[0]) if len(bb) else False
    with np.errstate(all="raise"):  # no hidden division by zero or invalid operation either
        cg = cost_gradient(J, src, own, own_r, own_b, True, Channel(), criterion)
    assert cg.status == FimStatus.SINGULAR and cg.value == np.inf
    assert np.isfinite(cg.gradient).all()
    peb, st_ = position_error_bound(J)
    assert peb == np.inf and st_ == FimStatus.SINGULAR


def test_ill_conditioned_fim_is_flagged_but_finite():
    # Three ranging drones on a line through the source, plus one slightly off it.
    src = np.array([0.0, 0.0, 10.0])
    u = np.array([1.0, 0.0, 0.0])
    eps = 1e-5
    pos = np.array([src - 50 * u, src + 80 * u, src - 120 * u + [0.0, 120 * eps, 0.0], src + 60 * u + [0.0, 0.0, 60 * eps]])
    J = fisher_information(src, pos, np.ones(4, bool), np.zeros(4, bool), np.ones(4, bool), Channel())
    lam = np.linalg.eigvalsh(J)
    assert 1e-12 < lam[0] / lam[-1] <= 1e-8  # the reference says: ill-conditioned, not singular
    value, status = cost(J, "A")
    assert status == FimStatus.ILL_CONDITIONED and np.isfinite(value)
    np.testing.assert_allclose(value, np.trace(np.linalg.inv(J)), rtol=1e-5)


@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf])
def test_non_finite_fim_is_singular(bad):
    J = np.eye(3)
    J[1, 1] = bad
    value, status = cost(J, "A")
    assert status == FimStatus.SINGULAR and value == np.inf
    cg = cost_gradient(J, np.zeros(3), np.array([10.0, 1.0, 2.0]), True, True, True, Channel(), "D")
    assert cg.status == FimStatus.SINGULAR and np.isfinite(cg.gradient).all()


def test_zero_and_negative_definite_fims_are_singular():
    for J in (np.zeros((3, 3)), -np.eye(3), np.diag([1.0, 1.0, -1e-3])):
        for crit in "AD":
            value, status = cost(J, crit)
            assert status == FimStatus.SINGULAR and value == np.inf


def _indefinite_with_positive_trace_and_det(rng: np.random.Generator) -> np.ndarray:
    """Two negative eigenvalues and a large positive one: tr J > 0 and det J > 0 all the same."""
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    lam = np.array([-rng.uniform(0.1, 1.0), -rng.uniform(0.1, 1.0), rng.uniform(5.0, 50.0)])
    return (q * lam) @ q.T


def test_the_d_cost_skips_the_eigenvalues_of_a_well_conditioned_fim_with_the_same_status_and_gradient():
    """The D cost's gradient also skips the eigenvalues where J is provably well conditioned:
    its status is bit for bit ``invert_fim``'s and its value −ln det J that of the eigenvalues
    to a few ε (ln det from the LU factors). (Its gradient, −J⁻¹ through eq. 14, is checked
    against finite differences by :func:`test_cost_gradient_matches_finite_differences`.)"""
    rng = np.random.default_rng(20261130)
    mats = [random_spd(rng, cond) for cond in np.logspace(0.0, 14.0, 57) for _ in range(8)]
    mats += [_indefinite_with_positive_trace_and_det(rng) for _ in range(50)]
    J = np.array(mats)
    src, own = np.zeros(3), np.array([30.0, -40.0, 12.0])
    cg = cost_gradient(J, np.broadcast_to(src, (len(J), 3)), np.broadcast_to(own, (len(J), 3)), True, True, True, Channel(), "D")
    ref = invert_fim(J)
    np.testing.assert_array_equal(cg.status, ref.status)
    finite = ref.status != FimStatus.SINGULAR
    assert finite.sum() > 300 and (~finite).sum() > 10
    np.testing.assert_allclose(cg.value[finite], -ref.logdet[finite], rtol=1e-12, atol=1e-12)
    assert np.all(np.isinf(cg.value[~finite]))


def test_a_cost_status_and_inverse_are_those_of_the_eigenvalues_at_every_condition():
    """The A cost's gradient (``cost_gradient``) skips the eigenvalues where trace, leading
    minors and determinant already prove J well conditioned: its status and cost must be
    bit for bit those of ``invert_fim`` (eigenvalues by Jacobi rotations) on FIMs from
    perfectly conditioned to singular, indefinite ones with a positive trace and determinant,
    and not exactly symmetric ones; numpy's eigenvalues say which status is right."""
    rng = np.random.default_rng(20261129)
    mats = [random_spd(rng, cond) for cond in np.logspace(0.0, 14.0, 57) for _ in range(8)]
    mats += [_indefinite_with_positive_trace_and_det(rng) for _ in range(50)]
    mats += [m + np.triu(rng.normal(scale=1e-9 * np.abs(m).max(), size=(3, 3)), 1) for m in mats[:100]]
    J = np.array(mats)
    src, own = np.zeros(3), np.array([30.0, -40.0, 12.0])
    cg = cost_gradient(J, np.broadcast_to(src, (len(J), 3)), np.broadcast_to(own, (len(J), 3)), True, True, True, Channel(), "A")
    ref = invert_fim(J)
    np.testing.assert_array_equal(cg.status, ref.status)
    expected = np.where(ref.status == FimStatus.SINGULAR, np.inf, np.trace(ref.inverse, axis1=-2, axis2=-1))
    np.testing.assert_array_equal(cg.value, expected)
    lam = np.linalg.eigvalsh(0.5 * (J + np.swapaxes(J, -1, -2)))
    rcond = lam[:, 0] / lam[:, -1]
    clear = (rcond > 1e-7) | (rcond < 1e-13)  # away from the thresholds, the status is certain
    want = np.where(rcond > 1e-8, FimStatus.OK, np.where(rcond > 1e-12, FimStatus.ILL_CONDITIONED, FimStatus.SINGULAR))
    np.testing.assert_array_equal(cg.status[clear], want[clear])
    assert {FimStatus.OK, FimStatus.ILL_CONDITIONED, FimStatus.SINGULAR} <= set(cg.status.tolist())
