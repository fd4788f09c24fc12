"""Safeguards: the score test that tells a wrong basin from a right one (the package doc,
step 3)."""

from __future__ import annotations

import numpy as np

from tests.reference_numpy.estimator.linalg import _inv3_spd
from tests.reference_numpy.estimator.state import BoolArray, EstimatorConfig, FloatArray


def _score_test(
    score_H: FloatArray,
    score_v: FloatArray,
    g_new: FloatArray,
    H_new: FloatArray,
    x_lin: FloatArray,
    x: FloatArray,
    active: BoolArray,
    threshold: float,
    config: EstimatorConfig,
) -> tuple[FloatArray, FloatArray, FloatArray, BoolArray]:
    r"""Score test of the recent records against the estimate (Rao's test, 3 dof).

    The new records' robust cost, linearised at x_lin (its gradient g_new (..., 3), m⁻¹, and
    scoring matrix H_new (..., 3, 3), m⁻²), joins the recent-records model with memory λ_c:

    .. math::
        S_H \leftarrow \lambda_c S_H + H_{new},\qquad
        S_v \leftarrow \lambda_c S_v + H_{new} x_{lin} - g_{new},\qquad
        s(x) = S_H x - S_v \approx \sum_{recent} \lambda_c^{age} \nabla C_i(x).

    When the estimate x is consistent with those records, s(x) is their score, zero-mean with
    covariance ≈ S_H (each record's score has covariance H_i: a robust GLS estimating equation),
    so T = s(x)ᵀ S_H⁻¹ s(x) ≈ χ²₃ (a little less: x has used them). A wrong estimate that the
    accumulated prior defends (records linearised once, at poor earlier estimates) makes the
    recent records pull consistently one way: T grows with every call. Coordinates of x on a
    bound of the search box are left out (at a constrained optimum the score along them is not
    zero-mean). Where T > ``threshold`` the test fails; the recent model is then
    reset so that a failure needs fresh evidence.

    Returns:
        (S_H, S_v, T, fail), shapes (..., 3, 3), (..., 3), (...,), (...,).
    """
    lc = config.consistency_forgetting
    act = active[..., None]
    S_H = score_H * lc + np.where(act[..., None], H_new, 0.0)
    S_v = score_v * lc + np.where(act, np.einsum("...ij,...j->...i", H_new, x_lin) - g_new, 0.0)
    s = np.einsum("...ij,...j->...i", S_H, x) - S_v
    lo = np.asarray(config.bounds_min_m, dtype=float)
    hi = np.asarray(config.bounds_max_m, dtype=float)
    free = (x > lo) & (x < hi)
    s = np.where(free, s, 0.0)
    keep = free[..., :, None] & free[..., None, :]
    eye = np.eye(3, dtype=bool)
    tr = np.maximum(np.einsum("...ii->...", S_H), 1e-300)
    S_t = np.where(keep, S_H, np.where(eye, tr[..., None, None], 0.0))
    S_inv, ok = _inv3_spd(S_t)
    T = np.where(ok & active, np.einsum("...i,...ij,...j->...", s, S_inv, s), 0.0)
    fail = active & (T > threshold)  # noqa: SIM300 - T is the test statistic (an array), not a constant
    S_H = np.where(fail[..., None, None], 0.0, S_H)
    S_v = np.where(fail[..., None], 0.0, S_v)
    return S_H, S_v, T, fail
