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

The range and bearing terms, the inverse and the gradient are compiled (:mod:`planner.kernels`,
``fim_batch``, ``invert_batch``, ``cost_gradient_batch``: each loops over the batch); the terms of
further measurement components of a larger registry (:mod:`planner.sensing`) are added here with
their own numpy methods.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner import kernels as K
from planner.params import Channel, Criterion
from planner.sensing import BEARING, COMPONENTS, RANGE, SensingComponent, component_masks, link_geometry

FloatArray = NDArray[np.float64]

#: Reciprocal condition number (λ_min/λ_max) below which J is reported singular.
SINGULAR_RCOND: float = K.SINGULAR_RCOND
#: Reciprocal condition number below which J is reported ill-conditioned (still inverted).
ILL_CONDITIONED_RCOND: float = K.ILL_CONDITIONED_RCOND


class FimStatus(IntEnum):
    """Health of a Fisher information matrix."""

    OK = K.OK
    ILL_CONDITIONED = K.ILL  #: inverted, but the cost may be inaccurate
    SINGULAR = K.SINGULAR  #: not invertible: cost +inf (A) or +inf (D), gradient zero


def _extras(components: Sequence[SensingComponent]) -> Sequence[SensingComponent]:
    """The components after range and bearing, which the kernels cover (registry order)."""
    if len(components) < 2 or components[0] is not RANGE or components[1] is not BEARING:
        raise ValueError(f"components: expected range and bearing first, found {[c.name for c in components[:2]]}")
    return components[2:]


def _criterion_d(criterion: Criterion) -> bool:
    if criterion not in ("A", "D"):
        raise ValueError(f"criterion: expected 'A' or 'D', found {criterion!r}")
    return criterion == "D"


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

    Every component adds its rows u with weights w (w u uᵀ per drone): J = Σ w u uᵀ over the
    rows of all drones and components, in registry order.

    Returns:
        J, shape (..., 3, 3), units 1/m².
    """
    extras = _extras(components)
    src, pos = np.asarray(source, dtype=float), np.asarray(positions, dtype=float)
    rng, brg, los_w = np.asarray(ranging, dtype=bool), np.asarray(bearing, dtype=bool), np.asarray(los, dtype=float)
    n = pos.shape[-2]
    if src.ndim == 1 and pos.ndim == 2 and rng.shape == brg.shape == los_w.shape == (n,):  # one view
        J = np.zeros((1, 3, 3))
        one = (K.one_drone(src), K.one_drone(pos), K.one_drone(rng, bool), K.one_drone(brg, bool), K.one_drone(los_w))
        K.fim_batch(*one, channel.kernel_array, J)
        J = J[0]
    else:
        batch = np.broadcast_shapes(src.shape[:-1], pos.shape[:-2], rng.shape[:-1], brg.shape[:-1], los_w.shape[:-1])
        args = (K.as_batch(src, batch + (3,), float, 1), K.as_batch(pos, batch + (n, 3), float, 2))
        masks = (K.as_batch(rng, batch + (n,), bool, 1), K.as_batch(brg, batch + (n,), bool, 1), K.as_batch(los_w, batch + (n,), float, 1))
        J = np.zeros(batch + (3, 3))
        K.fim_batch(*args, *masks, channel.kernel_array, J.reshape(-1, 3, 3))
    if extra_masks:
        J = J + _extra_fim(src, pos, rng, brg, los_w, channel, extra_masks, components, extras)
    return J


def _extra_fim(
    src: FloatArray,
    pos: FloatArray,
    rng: ArrayLike,
    brg: ArrayLike,
    los_w: FloatArray,
    channel: Channel,
    extra_masks: Mapping[str, ArrayLike],
    components: Sequence[SensingComponent],
    extras: Sequence[SensingComponent],
) -> FloatArray:
    """The terms Σ w u uᵀ (..., 3, 3) of the components beyond range and bearing (their own rows
    and weights, :class:`planner.sensing.SensingComponent`)."""
    geom = link_geometry(src[..., None, :] - pos)
    masks = component_masks(rng, brg, extra_masks, components)[2:]
    J = np.zeros(geom.d.shape[:-1] + (3, 3))
    for component, mask in zip(extras, masks, strict=True):
        V = component.fim_vectors(geom)
        w = component.fim_row_weights(geom, mask, los_w, channel)
        Vs = (V * np.sqrt(w)[..., None]).reshape(V.shape[:-3] + (-1, 3))
        J = J + np.swapaxes(Vs, -1, -2) @ Vs
    return J


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
    ill-conditioned below 1e-8. Eigenvalues by cyclic Jacobi rotations, the inverse by
    cofactors, ln det J = Σ ln λ (compiled, :mod:`planner.kernels`).
    """
    J = np.asarray(fim, dtype=float)
    batch = J.shape[:-2]
    inv, out = np.empty(batch + (3, 3)), np.empty(batch + (2,))
    K.invert_batch(K.as_batch(J, J.shape, float, 2), inv.reshape(-1, 3, 3), out.reshape(-1, 2))
    return FimInverse(inverse=inv, logdet=out[..., 0], status=out[..., 1].astype(np.int8))


def cost(fim: ArrayLike, criterion: Criterion) -> tuple[FloatArray, NDArray[np.int8]]:
    """A- or D-optimality cost of eq. 6 and the FIM health.

    Returns ``(C, status)``: C = tr(J⁻¹) (m²) for ``"A"``, −ln det J for ``"D"``; where J is
    singular C is ``+inf`` and ``status`` says :attr:`FimStatus.SINGULAR`.
    """
    d = _criterion_d(criterion)
    inv = invert_fim(fim)
    value = -inv.logdet if d else np.trace(inv.inverse, axis1=-2, axis2=-1)
    return np.where(inv.status == K.SINGULAR, np.inf, value), inv.status


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

    The range and bearing terms are compiled (:mod:`planner.kernels`); a further component adds
    its own term's gradient (:meth:`planner.sensing.SensingComponent.cost_gradient_terms`).
    """
    d = _criterion_d(criterion)
    extras = _extras(components)
    J = np.asarray(fim, dtype=float)
    src, p = np.asarray(source, dtype=float), np.asarray(own_position, dtype=float)
    rng, brg, q = np.asarray(own_ranging, dtype=bool), np.asarray(own_bearing, dtype=bool), np.asarray(own_los, dtype=float)
    use_gq = own_los_gradient is not None
    gq_in = np.zeros(3) if own_los_gradient is None else own_los_gradient
    if J.shape == (3, 3) and src.shape == p.shape == (3,) and rng.ndim == brg.ndim == q.ndim == 0:  # one drone
        batch: tuple[int, ...] = ()
        args = (K.one_drone(J), K.one_drone(src), K.one_drone(p), rng.reshape(1), brg.reshape(1), q.reshape(1), K.one_drone(gq_in))
    else:
        batch = np.broadcast_shapes(J.shape[:-2], src.shape[:-1], p.shape[:-1], rng.shape, brg.shape, q.shape)
        vectors = (K.as_batch(src, batch + (3,), float, 1), K.as_batch(p, batch + (3,), float, 1))
        flags = (K.as_batch(rng, batch, bool, 0), K.as_batch(brg, batch, bool, 0), K.as_batch(q, batch, float, 0))
        args = (K.as_batch(J, batch + (3, 3), float, 2), *vectors, *flags, K.as_batch(gq_in, batch + (3,), float, 1))
    out = np.empty(batch + (14,))
    K.cost_gradient_batch(*args, use_gq, channel.kernel_array, d, out.reshape(-1, 14))
    value, grad, status = out[..., 0], out[..., 1:4], out[..., 4].astype(np.int8)
    if own_extra:
        M = out[..., 5:].reshape(batch + (3, 3))
        grad = grad + _extra_gradient(src - p, M, rng, brg, q, own_los_gradient, channel, own_extra, components, extras)
        grad = np.where((status == K.SINGULAR)[..., None], 0.0, grad)
    return CostGradient(value=value, gradient=grad, status=status)


def _extra_gradient(
    r: FloatArray,
    M: FloatArray,
    rng: ArrayLike,
    brg: ArrayLike,
    q: FloatArray,
    own_los_gradient: ArrayLike | None,
    channel: Channel,
    own_extra: Mapping[str, ArrayLike],
    components: Sequence[SensingComponent],
    extras: Sequence[SensingComponent],
) -> FloatArray:
    """−∂ tr(M J_c)/∂r of the own terms of the components beyond range and bearing, plus
    tr(M ∂J_c/∂q) ∇q where the LOS weight q depends on the position (their own methods)."""
    geom = link_geometry(r)
    masks = component_masks(rng, brg, own_extra, components)[2:]
    grad = np.zeros(np.shape(r))
    for component, mask in zip(extras, masks, strict=True):
        V = component.fim_vectors(geom)
        MV = V @ M
        g_c, tr_c = component.cost_gradient_terms(geom, (V * MV).sum(-1), MV, mask, q, channel, own_los_gradient is not None)
        grad = grad - g_c
        if tr_c is not None and own_los_gradient is not None:
            grad = grad + tr_c[..., None] * np.asarray(own_los_gradient, dtype=float)
    return grad


def position_error_bound(fim: ArrayLike) -> tuple[FloatArray, NDArray[np.int8]]:
    """PEB = sqrt(tr J⁻¹) (eq. 18, one drone's view), metres; ``+inf`` where J is singular."""
    value, status = cost(fim, "A")
    return np.sqrt(value), status
