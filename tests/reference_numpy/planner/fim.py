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
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.params import Channel, Criterion
from planner.sensing import COMPONENTS, LinkGeometry, SensingComponent, component_masks, link_geometry
from tests.reference_numpy.planner.geometry import RHO_FLOOR_M

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


def _stacked_rows(geom: LinkGeometry, components: Sequence[SensingComponent]) -> FloatArray:
    """The rows u of every component's terms w u uᵀ, stacked in registry order, (..., k, 3):
    for the registry, r (ranging direction times d), b = [-r_y, r_x, 0] (∇φ·ρ²) and
    v = [-r_x r_z, -r_y r_z, ρ²] (∇θ·d²ρ)."""
    return np.concatenate([c.fim_vectors(geom) for c in components], axis=-2)


def fisher_information(
    source: ArrayLike,
    positions: ArrayLike,
    ranging: ArrayLike,
    bearing: ArrayLike,
    los: ArrayLike,
    channel: Channel,
    extra_masks: Mapping[str, ArrayLike] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
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
        extra_masks: masks (..., N) of the components in ``components`` other than range and
            bearing, by component name (absent: no drone has it).
        components: the measurement components (:data:`planner.sensing.COMPONENTS`).

    Every component adds its rows u with weights w (w u uᵀ per drone): J = Σ w u uᵀ is one
    product of the rows of all drones and components, stacked in registry order.

    Returns:
        J, shape (..., 3, 3), units 1/m².
    """
    r = np.asarray(source, dtype=float)[..., None, :] - np.asarray(positions, dtype=float)
    los_w = _los_weight(los)
    geom = link_geometry(r)
    masks = component_masks(ranging, bearing, extra_masks, components)
    V = _stacked_rows(geom, components)
    w = np.concatenate([c.fim_row_weights(geom, mask, los_w, channel) for c, mask in zip(components, masks, strict=True)], axis=-1)
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
    own_extra: Mapping[str, ArrayLike] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
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
        own_extra: drone i's masks of the other components, by name (see
            :func:`fisher_information`). components: the measurement components.

    Each component supplies its own term's gradient
    (:meth:`planner.sensing.SensingComponent.cost_gradient_terms`), summed in registry order.
    One drone (``fim`` (3, 3), ``own_position`` (3,)) takes a scalar fast path with the same
    value, status and (to round-off) gradient; see :func:`_cost_gradient_one`.
    """
    if np.shape(own_position) == (3,) and np.shape(source) == (3,) and np.shape(fim) == (3, 3) and criterion in ("A", "D"):
        fast = _cost_gradient_one(
            fim, source, own_position, own_ranging, own_bearing, own_los, channel, criterion, own_los_gradient, own_extra, components
        )
        if fast is not None:
            return fast
    inv, value, M = _criterion_derivative(fim, criterion)
    singular = inv.status == _SINGULAR
    r = np.asarray(source, dtype=float) - np.asarray(own_position, dtype=float)
    los_w = _los_weight(own_los)
    geom = link_geometry(r)
    masks = component_masks(own_ranging, own_bearing, own_extra, components)
    V = _stacked_rows(geom, components)
    MV = V @ M  # rows M u (M symmetric): M r, M b, M v for the registry
    q = (V * MV).sum(-1)  # uᵀMu
    with_trace = own_los_gradient is not None
    total: FloatArray | None = None
    tr: FloatArray | None = None
    row = 0
    for component, mask in zip(components, masks, strict=True):
        rows = slice(row, row + component.fim_row_count)
        row += component.fim_row_count
        g_c, tr_c = component.cost_gradient_terms(geom, q[..., rows], MV[..., rows, :], mask, los_w, channel, with_trace)
        total = g_c if total is None else total + g_c
        if tr_c is not None:
            # tr(M (J_LOS − J_NLOS)) of the own term.
            tr = tr_c if tr is None else tr + tr_c
    gradient = -total if total is not None else np.zeros(np.shape(r))
    if own_los_gradient is not None and tr is not None:
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
    own_extra: Mapping[str, ArrayLike] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
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
    masks = component_masks(own_ranging, own_bearing, own_extra, components)
    for component, mask in zip(components, masks, strict=True):
        terms = component.cost_gradient_one_terms(r, rho2, d, d2, m, bool(np.asarray(mask)), los, channel, own_los_gradient is not None)
        if terms is not None:
            gx, gy, gz = gx + terms[0], gy + terms[1], gz + terms[2]
            tr += terms[3]
    gradient = np.array([-gx, -gy, -gz])
    if own_los_gradient is not None:
        gradient = gradient + tr * np.asarray(own_los_gradient, dtype=float)
    return CostGradient(value=value, gradient=gradient, status=status)


def position_error_bound(fim: ArrayLike) -> tuple[FloatArray, NDArray[np.int8]]:
    """PEB = sqrt(tr J⁻¹) (eq. 18, one drone's view), metres; ``+inf`` where J is singular."""
    value, status = cost(fim, "A")
    return np.sqrt(value), status
