"""Fisher information of the source position (paper eqs. 8-12), A/D costs and gradients (eqs. 6, 13).

Notation (mission ENU frame, metres, radians): drone j at p_j, source p0, r = p0 - p_j,
d = |r|, ρ = sqrt(r_x² + r_y²). For drone j with ranging role κ_j and bearing role β_j:

.. math::
    J = \\sum_j \\kappa_j A_{r,j}\\,\\mathbf a_j\\mathbf a_j^T
        + \\beta_j p_j \\frac{1}{\\sigma_{b,0}^2}\\big(\\nabla\\phi_j\\nabla\\phi_j^T
        + \\nabla\\theta_j\\nabla\\theta_j^T\\big)

    A_{r,j} = \\frac{1}{\\sigma_{r,j}^2} + \\frac{\\gamma^2}{2 d_j^2},\\qquad
    \\sigma_{r,j}^2 = \\sigma_{r,0}^2 d_j^{\\gamma}

    \\nabla\\phi = \\frac{[-r_y, r_x, 0]}{\\rho^2},\\qquad
    \\nabla\\theta = \\frac{[-r_x r_z, -r_y r_z, \\rho^2]}{d^2\\rho}

which is eq. 10-12 written in Cartesian form (G_az = ∇φ∇φᵀ, G_el = ∇θ∇θᵀ). The second term
of A_r is the information carried by the distance-dependent variance,
∇σ²∇σ²ᵀ/(2σ⁴) = γ²/(2d²)·aaᵀ; see docs/paper-notes.md for the comparison with the printed
eq. 12.

Costs (eq. 6): A-optimality C = tr(J⁻¹), D-optimality C = −ln det J, with analytic gradients
with respect to the position of one drone (its own, for the control law of eq. 14).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.geometry import RHO_FLOOR_M
from planner.params import Channel, Criterion
from planner.sensing import BEARING, RANGE

FloatArray = NDArray[np.float64]

#: Reciprocal condition number (λ_min/λ_max) below which J is reported singular.
SINGULAR_RCOND: float = 1e-12
#: Reciprocal condition number below which J is reported ill-conditioned (still inverted).
ILL_CONDITIONED_RCOND: float = 1e-8


class FimStatus(IntEnum):
    """Health of a Fisher information matrix."""

    OK = 0
    ILL_CONDITIONED = 1  #: inverted, but the cost may be inaccurate
    SINGULAR = 2  #: not invertible: cost +inf (A) or +inf (D), gradient zero


# Plain-int codes for the hot paths: comparing arrays with IntEnum members costs microseconds.
_OK, _ILL, _SINGULAR = int(FimStatus.OK), int(FimStatus.ILL_CONDITIONED), int(FimStatus.SINGULAR)


def _los_weight(los: ArrayLike) -> FloatArray:
    """LOS flags (bool) or weights in [0, 1] as floats."""
    return np.asarray(los, dtype=float)


def _term_vectors(r: FloatArray, los: FloatArray, channel: Channel) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Vectors and scalars of the FIM terms for relative vectors r = p0 - p_j, shape (..., 3).

    Returns ``(V, rho2, d2, d, inv_s0sq, r)`` where V (..., 3, 3) stacks the rows
    r (ranging direction times d), b = [-r_y, r_x, 0] (∇φ·ρ²) and
    v = [-r_x r_z, -r_y r_z, ρ²] (∇θ·d²ρ), and inv_s0sq = q/σ_r0,LOS² + (1 − q)/σ_r0,NLOS² for
    the LOS weight q (1 LOS, 0 NLOS).
    """
    rx, ry, rz = r[..., 0], r[..., 1], r[..., 2]
    rho2 = np.maximum(rx * rx + ry * ry, RHO_FLOOR_M**2)
    d2 = rho2 + rz * rz
    d = np.sqrt(d2)
    inv_s0sq = los / channel.sigma_r0_los**2 + (1.0 - los) / channel.sigma_r0_nlos**2
    V = np.empty(r.shape[:-1] + (3, 3))
    V[..., 0, :] = r
    V[..., 1, 0] = -ry
    V[..., 1, 1] = rx
    V[..., 1, 2] = 0.0
    V[..., 2, 0] = -rx * rz
    V[..., 2, 1] = -ry * rz
    V[..., 2, 2] = rho2
    return V, rho2, d2, d, inv_s0sq, r


def fisher_information(
    source: ArrayLike,
    positions: ArrayLike,
    ranging: ArrayLike,
    bearing: ArrayLike,
    los: ArrayLike,
    channel: Channel,
) -> FloatArray:
    """Fisher information matrix J(p0; q) of the source position (paper eqs. 10-12).

    Args:
        source: source position p0 (true or estimated), shape (..., 3), m, ENU.
        positions: drone positions q = [p_j], shape (..., N, 3), m, ENU.
        ranging: κ_j, boolean (..., N): the drone measures range.
        bearing: β_j, boolean (..., N): the drone measures azimuth and elevation.
        los: p_j, boolean (..., N): the link is line of sight. An NLOS bearing carries no
            information; an NLOS range uses σ_sh/γ of NLOS. A weight q in [0, 1] instead of a
            flag gives the expected FIM q J_LOS + (1 − q) J_NLOS of a link that is LOS with
            probability q (the planner's predicted own link, :func:`planner.agent.own_los_weight`).
        channel: RSS channel (γ, σ_sh/γ LOS and NLOS, σ_b).

    Returns:
        J, shape (..., 3, 3), units 1/m².
    """
    r = np.asarray(source, dtype=float)[..., None, :] - np.asarray(positions, dtype=float)
    los_w = _los_weight(los)
    V, rho2, d2, d, inv_s0sq, _ = _term_vectors(r, los_w, channel)
    w = np.empty(V.shape[:-1])
    # Ranging: A_r a aᵀ = (A_r / d²) r rᵀ.
    w[..., 0] = np.asarray(ranging, dtype=bool) * RANGE.fim_weight(d, d2, inv_s0sq, channel.gamma) / d2
    # Bearing (LOS only): ∇φ∇φᵀ/σ_b² = b bᵀ/(σ_b² ρ⁴), ∇θ∇θᵀ/σ_b² = v vᵀ/(σ_b² d⁴ ρ²).
    w[..., 1], w[..., 2] = BEARING.fim_weights(rho2, d2, np.asarray(bearing, dtype=bool) * los_w, channel)
    Vs = (V * np.sqrt(w)[..., None]).reshape(V.shape[:-3] + (-1, 3))
    return np.swapaxes(Vs, -1, -2) @ Vs


@dataclass(frozen=True)
class FimInverse:
    """Inverse, determinant and health of a batch of FIMs.

    Attributes:
        inverse: J⁻¹, shape (..., 3, 3), m²; zeros where singular.
        logdet: ln det J, shape (...); -inf where singular.
        status: :class:`FimStatus` codes, int8 (...).
    """

    inverse: FloatArray
    logdet: FloatArray
    status: NDArray[np.int8]


def invert_fim(fim: ArrayLike) -> FimInverse:
    """Invert symmetric 3x3 FIMs with an explicit health check (no silent NaN or inf).

    The matrix is reported singular when λ_min ≤ 1e-12 λ_max (or λ_max ≤ 0 or non-finite),
    ill-conditioned below 1e-8.
    """
    J = np.asarray(fim, dtype=float)
    finite = np.isfinite(J).all(axis=(-2, -1))
    if not finite.all():
        J = np.where(finite[..., None, None], J, 0.0)
    eig = np.linalg.eigvalsh(J)
    lmin, lmax = eig[..., 0], eig[..., -1]
    ok_max = lmax > 0.0
    rcond = np.divide(lmin, lmax, out=np.zeros_like(lmax), where=ok_max)
    singular = (~finite) | (~ok_max) | (rcond <= SINGULAR_RCOND)
    status = np.where(singular, _SINGULAR, np.where(rcond <= ILL_CONDITIONED_RCOND, _ILL, _OK)).astype(np.int8)
    any_singular = bool(singular.any())
    if any_singular:
        J = np.where(singular[..., None, None], np.eye(3), J)
        eig = np.where(singular[..., None], 1.0, eig)
    inv = np.linalg.inv(J)
    logdet = np.log(eig).sum(axis=-1)
    if any_singular:
        inv = np.where(singular[..., None, None], 0.0, inv)
        logdet = np.where(singular, -np.inf, logdet)
    return FimInverse(inverse=inv, logdet=logdet, status=status)


def cost(fim: ArrayLike, criterion: Criterion) -> tuple[FloatArray, NDArray[np.int8]]:
    """A- or D-optimality cost of eq. 6 and the FIM health.

    Returns ``(C, status)``: C = tr(J⁻¹) (m²) for ``"A"``, −ln det J for ``"D"``; where J is
    singular C is ``+inf`` and ``status`` says :attr:`FimStatus.SINGULAR`.
    """
    inv = invert_fim(fim)
    singular = inv.status == _SINGULAR
    if criterion == "A":
        value = np.trace(inv.inverse, axis1=-2, axis2=-1)
    elif criterion == "D":
        value = -inv.logdet
    else:
        raise ValueError(f"criterion: expected 'A' or 'D', found {criterion!r}")
    if singular.any():
        value = np.where(singular, np.inf, value)
    return value, inv.status


@dataclass(frozen=True)
class CostGradient:
    """Cost of eq. 6 at one drone's view and its gradient w.r.t. that drone's own position.

    Attributes:
        value: C (m² for A, dimensionless for D), shape (...); +inf where singular.
        gradient: ∇_{p_i} C, shape (..., 3) (m for A, 1/m for D), ENU; zeros where singular.
        status: :class:`FimStatus` codes, int8 (...).
    """

    value: FloatArray
    gradient: FloatArray
    status: NDArray[np.int8]


def cost_gradient(
    fim: ArrayLike,
    source: ArrayLike,
    own_position: ArrayLike,
    own_ranging: ArrayLike,
    own_bearing: ArrayLike,
    own_los: ArrayLike,
    channel: Channel,
    criterion: Criterion,
    own_los_gradient: ArrayLike | None = None,
) -> CostGradient:
    """Cost C(q_i) of eq. 6 and its analytic gradient w.r.t. drone i's own position (eq. 14).

    Only drone i's own term of J depends on p_i, so with M = ∂C/∂J (−J⁻² for A, −J⁻¹ for D)
    and r = p0 − p_i, ∇_{p_i} C = −∂C/∂r with

    .. math::
        \\partial_{r}\\,\\mathrm{tr}(M J_r) = \\frac{h'(d)}{d}(r^T M r)\\,r + 2h(d) M r,
        \\quad J_r = h(d)\\,r r^T,\\ h = \\frac{d^{-\\gamma}}{\\sigma_{r,0}^2 d^2} + \\frac{\\gamma^2}{2 d^4}

    and the analogous expressions for the azimuth (b bᵀ/ρ⁴) and elevation (v vᵀ/(d⁴ρ²)) terms.

    Args:
        fim: J of drone i's view (including its own term), shape (..., 3, 3).
        source: the source position J was evaluated at (drone i's estimate), (..., 3), m, ENU.
        own_position: p_i, (..., 3), m, ENU.
        own_ranging, own_bearing, own_los: drone i's κ_i, β_i and p_i, boolean (...). own_los
            may be a weight q in [0, 1] (J's own term then is q J_LOS + (1 − q) J_NLOS, see
            :func:`fisher_information`).
        channel: RSS channel. criterion: ``"A"`` or ``"D"``.
        own_los_gradient: ∇_{p_i} q (..., 3), 1/m, when q depends on p_i; adds
            tr(M (J_LOS − J_NLOS)) ∇q to the gradient (J_LOS − J_NLOS: drone i's own term).

    One drone (``fim`` (3, 3), ``own_position`` (3,)) takes a scalar fast path with the same
    value, status and (to round-off) gradient; see :func:`_cost_gradient_one`.
    """
    if np.shape(own_position) == (3,) and np.shape(source) == (3,) and np.shape(fim) == (3, 3) and criterion in ("A", "D"):
        fast = _cost_gradient_one(fim, source, own_position, own_ranging, own_bearing, own_los, channel, criterion, own_los_gradient)
        if fast is not None:
            return fast
    inv, value, M = _criterion_derivative(fim, criterion)
    singular = inv.status == _SINGULAR
    r = np.asarray(source, dtype=float) - np.asarray(own_position, dtype=float)
    los_w = _los_weight(own_los)
    V, rho2, d2, d, inv_s0sq, _ = _term_vectors(r, los_w, channel)
    MV = V @ M  # rows: M r, M b, M v (M symmetric)
    q = (V * MV).sum(-1)  # rᵀMr, bᵀMb, vᵀMv
    Mr, Mb, Mv = MV[..., 0, :], MV[..., 1, :], MV[..., 2, :]
    g_r = RANGE.cost_gradient(r, d, d2, q[..., 0], Mr, inv_s0sq, channel.gamma)
    g_b, tr_b = BEARING.cost_gradient(r, rho2, d2, q[..., 1], q[..., 2], Mb, Mv, channel)
    use_r = np.asarray(own_ranging, dtype=bool)[..., None]
    use_b = (np.asarray(own_bearing, dtype=bool) * los_w)[..., None]
    gradient = -(use_r * g_r + use_b * g_b)
    if own_los_gradient is not None:
        # tr(M (J_LOS − J_NLOS)): the ranging term's LOS/NLOS difference and the bearing terms.
        dr = RANGE.los_trace(d, d2, q[..., 0], channel)
        tr = use_r[..., 0] * dr + np.asarray(own_bearing, dtype=bool) * tr_b
        gradient = gradient + tr[..., None] * np.asarray(own_los_gradient, dtype=float)
    if singular.any():
        gradient = np.where(singular[..., None], 0.0, gradient)
        value = np.where(singular, np.inf, value)
    return CostGradient(value=value, gradient=gradient, status=inv.status)


def _criterion_derivative(fim: ArrayLike, criterion: Criterion) -> tuple[FimInverse, FloatArray, FloatArray]:
    """J's inverse and health (:func:`invert_fim`), the cost C of eq. 6 and M = ∂C/∂J:
    C = tr J⁻¹, M = −J⁻² for A; C = −ln det J, M = −J⁻¹ for D."""
    inv = invert_fim(fim)
    Jinv = inv.inverse
    if criterion == "A":
        return inv, np.trace(Jinv, axis1=-2, axis2=-1), -Jinv @ Jinv
    if criterion == "D":
        return inv, -inv.logdet, -Jinv
    raise ValueError(f"criterion: expected 'A' or 'D', found {criterion!r}")


def _cost_gradient_one(
    fim: ArrayLike,
    source: ArrayLike,
    own_position: ArrayLike,
    own_ranging: ArrayLike,
    own_bearing: ArrayLike,
    own_los: ArrayLike,
    channel: Channel,
    criterion: Criterion,
    own_los_gradient: ArrayLike | None = None,
) -> CostGradient | None:
    """:func:`cost_gradient` for one drone and one 3x3 J, in Python floats (the planner node's
    hot path: ~3x faster than the batched code on 0-d arrays).

    Same health test, inverse, value and status as :func:`invert_fim`; the gradient is the same
    expression as the batched code, term by term (agrees to round-off; tested in
    ``tests/planner/test_costs.py``). Returns None when J is singular or not finite (the
    batched code handles those).
    """
    J = np.asarray(fim, dtype=float)
    if not np.isfinite(J).all():
        return None
    eig = np.linalg.eigvalsh(J)
    lmin, lmax = float(eig[0]), float(eig[-1])
    if not lmax > 0.0:
        return None
    rcond = lmin / lmax
    if rcond <= SINGULAR_RCOND:
        return None
    status = np.array(_ILL if rcond <= ILL_CONDITIONED_RCOND else _OK, dtype=np.int8)
    Jinv = np.linalg.inv(J)
    if criterion == "A":
        value = np.trace(Jinv, axis1=-2, axis2=-1)
        M = -Jinv @ Jinv
    else:
        value = -np.log(eig).sum(axis=-1)
        M = -Jinv
    m = M.tolist()
    s = np.asarray(source, dtype=float)
    o = np.asarray(own_position, dtype=float)
    r = (float(s[0] - o[0]), float(s[1] - o[1]), float(s[2] - o[2]))
    rho2 = max(r[0] * r[0] + r[1] * r[1], RHO_FLOOR_M**2)
    d2 = rho2 + r[2] * r[2]
    d = math.sqrt(d2)
    los = float(np.asarray(own_los, dtype=float))
    tr = 0.0  # tr(M (J_LOS − J_NLOS)) of the own term
    gx = gy = gz = 0.0
    if bool(own_ranging):
        gx, gy, gz, tr_r = RANGE.cost_gradient_one(r, d, d2, m, los, channel)
        tr += tr_r
    if bool(own_bearing) and (los > 0.0 or own_los_gradient is not None):
        bgx, bgy, bgz, tr_b = BEARING.cost_gradient_one(r, rho2, d2, m, channel)
        # The bearing terms carry the LOS weight q (an NLOS bearing carries no information).
        gx, gy, gz = gx + los * bgx, gy + los * bgy, gz + los * bgz
        tr += tr_b
    gradient = np.array([-gx, -gy, -gz])
    if own_los_gradient is not None:
        gradient = gradient + tr * np.asarray(own_los_gradient, dtype=float)
    return CostGradient(value=value, gradient=gradient, status=status)


def position_error_bound(fim: ArrayLike) -> tuple[FloatArray, NDArray[np.int8]]:
    """PEB = sqrt(tr J⁻¹) (eq. 18, one drone's view), metres; ``+inf`` where J is singular."""
    value, status = cost(fim, "A")
    return np.sqrt(value), status
