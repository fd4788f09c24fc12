r"""The paper's ranging with an unknown transmit power: a 4 × 4 Fisher information, its Schur
complement, the PEB, the A/D costs with analytic gradients, and the joint estimator.

The paper assumes the source's power known (footnote to eq. 5). A ranging drone turns received
power into distance through the log-distance model: d̂ = 10^{(P_0 − P)/(10γ)}. If the
source's reference power is P_0 − ΔP instead of the assumed P_0 (ΔP dB weaker: a stronger source
has ΔP < 0), every range is scaled by the
same factor κ = 10^{ΔP/(10γ)} = e^b: the source looks like one at the distance s = e^b d of
known power. In the paper's model (eqs. 3, 5) the range then is

.. math::
    \hat d_j = s_j + n_{r,j},\qquad s_j = e^{b} d_j,\qquad n_{r,j}\sim\mathcal N(0, \sigma_{r,0}^2 s_j^{\gamma})

with the *power offset* b = ΔP ln 10/(10γ) (b = 0: the power as assumed). Mean and variance
depend on the parameters only through s, so each ranging drone adds

.. math::
    J_j = A_r(s_j)\,\nabla s_j\nabla s_j^T,\qquad
    \nabla_{(p_0, b)} s_j = e^{b}\,(\mathbf a_j, d_j) = \frac{e^b}{d_j}\,(\mathbf r_j, d_j^2)

(A_r of eq. 12 at s), i.e. rows u = (r, d²) with weight w = e^{2b} A_r(e^b d)/d², the range row
of eq. 10 with a fourth coordinate. Bearings do not depend on the power (a zero fourth
coordinate). The 4 × 4 information is

.. math::
    J_4 = \begin{pmatrix} J_3 & \mathbf c\\ \mathbf c^T & \beta\end{pmatrix},\quad
    \mathbf c = \sum_j \kappa_j w_j d_j^2\,\mathbf r_j,\quad \beta = \sum_j \kappa_j w_j d_j^4

and the information left for the position once b is estimated is the Schur complement
J_eq = J_3 − c cᵀ/β (= J_3 when no drone ranges: β = 0). The PEB (eq. 18) and the A/D costs
(eq. 6) act on J_eq. Their gradients with respect to a drone's own position (eq. 14) follow from
M₄ = ∂C/∂J₄: with S = J_eq⁻¹ and P = [S; −cᵀS/β] (the first three columns of J₄⁻¹),
M₄ = −P Pᵀ for A (C = tr S) and M₄ = −P J_eq Pᵀ for D (C = ln det S); the own range term
w u uᵀ then contributes ∂ tr(M₄ w u uᵀ)/∂r = (w'(d)/d)(uᵀM₄u) r + 2w (M₄u)₁:₃ + 4w (M₄u)₄ r.

The exponent may be unknown too (the estimator's option): a drone that assumes γ_a where the
channel has γ sees s = e^b d^ν with ν = γ/γ_a, a fifth parameter (∂s/∂ν = s ln d).

Frame: mission ENU, metres; b dimensionless (ΔP in dB = 10γ b/ln 10, the source that much weaker than
assumed; :mod:`planner.radio.power_offset` counts the other way, the power above the assumed one).
Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.fim import CostGradient, FimStatus, cost, fisher_information, invert_fim
from planner.params import Channel, Criterion
from planner.sensing import COMPONENTS, RANGE, SensingComponent, component_masks, link_geometry

FloatArray = NDArray[np.float64]

#: β (the power offset's own information) below this fraction of tr J₃ · d² counts as none: no
#: drone ranges, b is not estimable and the position keeps J₃.
_NO_OFFSET_INFORMATION: float = 1e-15


def offset_db(b: ArrayLike, gamma: float) -> FloatArray:
    """ΔP (dB) of a power offset b: ΔP = 10 γ b/ln 10, by how much the source is weaker than assumed."""
    return np.asarray(b, dtype=float) * (10.0 * gamma / math.log(10.0))


def _inv_s0sq(los: ArrayLike, channel: Channel) -> FloatArray:
    """1/σ_r0² of each link, a LOS weight q mixing the LOS and NLOS values as in :mod:`planner.fim`."""
    q = np.asarray(los, dtype=float)
    return q / channel.sigma_r0_los**2 + (1.0 - q) / channel.sigma_r0_nlos**2


def range_weight(d: ArrayLike, los: ArrayLike, channel: Channel, offset: ArrayLike = 0.0) -> tuple[FloatArray, FloatArray]:
    """w(d) = e^{2b} A_r(e^b d)/d² of the rows (r, d²), 1/m⁴, and dw/dd (1/m⁵).

    w = e^{(2−γ)b} d^{−γ−2}/σ_r0² + γ²/(2d⁴) (A_r = s^{−γ}/σ_r0² + γ²/(2s²), s = e^b d).
    """
    d = np.asarray(d, dtype=float)
    g = channel.gamma
    k = np.exp((2.0 - g) * np.asarray(offset, dtype=float)) * _inv_s0sq(los, channel)
    w = k * d ** (-g - 2.0) + g * g / (2.0 * d**4)
    dw = -(g + 2.0) * k * d ** (-g - 3.0) - 2.0 * g * g / d**5
    return w, dw


def fisher_information_unknown_power(
    source: ArrayLike,
    positions: ArrayLike,
    ranging: ArrayLike,
    bearing: ArrayLike,
    los: ArrayLike,
    channel: Channel,
    offset: ArrayLike = 0.0,
    extra_masks: Mapping[str, ArrayLike] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
) -> FloatArray:
    """J₄ of (p0, b) (..., 4, 4): 1/m² in the position block, 1/m on the border, 1 at (b, b).

    Arguments as :func:`planner.fim.fisher_information`, and ``offset`` the power offset b at
    which to evaluate it (dimensionless; 0: the power as assumed). The ranging rows are
    (r, d²) with weight w of :func:`range_weight`; every other component comes from
    :func:`planner.fim.fisher_information` (no power dependence: a zero fourth coordinate).
    """
    p = np.asarray(positions, dtype=float)
    r = np.asarray(source, dtype=float)[..., None, :] - p
    geom = link_geometry(r)
    kappa = np.broadcast_to(np.asarray(ranging, dtype=bool), geom.d.shape)
    w, _ = range_weight(geom.d, los, channel, np.asarray(offset, dtype=float)[..., None])
    w = np.where(kappa, w, 0.0)
    u = np.concatenate([r, geom.d2[..., None]], axis=-1)  # (..., N, 4)
    us = u * np.sqrt(w)[..., None]
    J = np.swapaxes(us, -1, -2) @ us
    others = fisher_information(source, p, np.zeros(kappa.shape, dtype=bool), bearing, los, channel, extra_masks, components)
    J[..., :3, :3] += others
    return J


@dataclass(frozen=True)
class SchurParts:
    """The pieces of J₄ and its Schur complement.

    Attributes:
        equivalent: J_eq = J₃ − c cᵀ/β (..., 3, 3), 1/m² (J₃ where β = 0).
        c: (..., 3), β: (...): the power offset's border and corner of J₄.
        has_offset: β > 0 (some drone ranges), bool (...).
    """

    equivalent: FloatArray
    c: FloatArray
    beta: FloatArray
    has_offset: NDArray[np.bool_]


def schur_parts(fim4: ArrayLike) -> SchurParts:
    """:class:`SchurParts` of J₄ (..., 4, 4)."""
    J = np.asarray(fim4, dtype=float)
    J3, c, beta = J[..., :3, :3], J[..., :3, 3], J[..., 3, 3]
    scale = np.trace(J3, axis1=-2, axis2=-1) * (1.0 + np.abs(beta))
    has = beta > _NO_OFFSET_INFORMATION * np.maximum(scale, 1e-300)
    safe = np.where(has, beta, 1.0)
    Jeq = J3 - np.where(has[..., None, None], c[..., :, None] * c[..., None, :] / safe[..., None, None], 0.0)
    return SchurParts(equivalent=0.5 * (Jeq + np.swapaxes(Jeq, -1, -2)), c=c, beta=beta, has_offset=has)


def equivalent_fim(fim4: ArrayLike) -> FloatArray:
    """J_eq = J₃ − c cᵀ/β (..., 3, 3): the position's information with b unknown."""
    return schur_parts(fim4).equivalent


def position_error_bound_unknown_power(fim4: ArrayLike) -> tuple[FloatArray, NDArray[np.int8]]:
    """PEB = √tr J_eq⁻¹ (eq. 18 with the power unknown), m; +inf where J_eq is singular."""
    value, status = cost(equivalent_fim(fim4), "A")
    return np.sqrt(value), status


def cost_unknown_power(fim4: ArrayLike, criterion: Criterion) -> tuple[FloatArray, NDArray[np.int8]]:
    """The A/D cost of eq. 6 on J_eq: tr J_eq⁻¹ (m²) or −ln det J_eq; +inf where singular."""
    return cost(equivalent_fim(fim4), criterion)


def _m4(parts: SchurParts, criterion: Criterion) -> tuple[FloatArray, FloatArray, NDArray[np.int8]]:
    """(C, M₄ = ∂C/∂J₄ (..., 4, 4), status) of C(J_eq(J₄))."""
    inv = invert_fim(parts.equivalent)
    S = inv.inverse
    safe = np.where(parts.has_offset, parts.beta, 1.0)
    bottom = -np.where(parts.has_offset[..., None], (parts.c[..., None, :] @ S)[..., 0, :] / safe[..., None], 0.0)  # −cᵀS/β
    P = np.concatenate([S, bottom[..., None, :]], axis=-2)  # (..., 4, 3)
    if criterion == "A":
        value = np.trace(S, axis1=-2, axis2=-1)
        M = -P @ np.swapaxes(P, -1, -2)
    elif criterion == "D":
        value = -inv.logdet
        M = -P @ parts.equivalent @ np.swapaxes(P, -1, -2)
    else:
        raise ValueError(f"criterion: expected 'A' or 'D', found {criterion!r}")
    return value, M, inv.status


def cost_gradient_unknown_power(
    fim4: ArrayLike,
    source: ArrayLike,
    own_position: ArrayLike,
    own_ranging: ArrayLike,
    own_bearing: ArrayLike,
    own_los: ArrayLike,
    channel: Channel,
    criterion: Criterion,
    offset: ArrayLike = 0.0,
    own_los_gradient: ArrayLike | None = None,
    own_extra: Mapping[str, ArrayLike] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
) -> CostGradient:
    """C(J_eq) of eq. 6 with the power unknown and its analytic gradient w.r.t. drone i's own
    position (eq. 14), the counterpart of :func:`planner.fim.cost_gradient`.

    Args:
        fim4: J₄ of drone i's view, its own term included (..., 4, 4).
        source: the point J₄ was evaluated at (..., 3), m, ENU. own_position: p_i (..., 3).
        own_ranging, own_bearing, own_los: κ_i, β_i and the LOS flag or weight q (...).
        channel, criterion: as :func:`planner.fim.cost_gradient`. offset: b of J₄.
        own_los_gradient: ∇q (..., 3), 1/m, when q depends on p_i (adds tr(M₄ (J_LOS − J_NLOS)) ∇q).
        own_extra, components: the other components' masks and the registry.

    Returns:
        :class:`planner.fim.CostGradient` (value +inf and gradient 0 where J_eq is singular).
    """
    parts = schur_parts(fim4)
    value, M4, status = _m4(parts, criterion)
    singular = status == int(FimStatus.SINGULAR)
    r = np.asarray(source, dtype=float) - np.asarray(own_position, dtype=float)
    geom = link_geometry(r)
    los_w = np.asarray(own_los, dtype=float)
    # The own range term w u uᵀ, u = (r, d²).
    u = np.concatenate([r, geom.d2[..., None]], axis=-1)
    Mu = (M4 @ u[..., None])[..., 0]
    q4 = (u * Mu).sum(-1)
    w, dw = range_weight(geom.d, los_w, channel, offset)
    has_r = np.asarray(own_ranging, dtype=bool)
    g_range = (dw / geom.d * q4)[..., None] * r + 2.0 * w[..., None] * (Mu[..., :3] + 2.0 * Mu[..., 3:4] * r)
    total = np.where(has_r[..., None], g_range, 0.0)
    trace = None
    if own_los_gradient is not None:
        w_los, _ = range_weight(geom.d, 1.0, channel, offset)
        w_nlos, _ = range_weight(geom.d, 0.0, channel, offset)
        trace = np.where(has_r, (w_los - w_nlos) * q4, 0.0)
    # Every other component through its own gradient terms, with M = M₄'s position block.
    M3 = M4[..., :3, :3]
    masks = component_masks(False, own_bearing, own_extra, components)
    for component, mask in zip(components, masks, strict=True):
        if component.name == RANGE.name:
            continue
        V = component.fim_vectors(geom)
        MV = V @ M3
        q = (V * MV).sum(-1)
        g_c, tr_c = component.cost_gradient_terms(geom, q, MV, mask, los_w, channel, own_los_gradient is not None)
        total = total + g_c
        if trace is not None and tr_c is not None:
            trace = trace + tr_c
    gradient = -total
    if own_los_gradient is not None and trace is not None:
        gradient = gradient + trace[..., None] * np.asarray(own_los_gradient, dtype=float)
    if singular.any():
        gradient = np.where(singular[..., None], 0.0, gradient)
        value = np.where(singular, np.inf, value)
    return CostGradient(value=value, gradient=gradient, status=status)


# ----------------------------------------------------------------------------- estimator
@dataclass(frozen=True)
class OffsetEstimate:
    """The joint estimate of :func:`estimate_with_unknown_power`.

    Attributes:
        source_m: p̂0 (3,), m, ENU.
        offset: b̂ (dimensionless; ΔP̂ = :func:`offset_db`).
        exponent_ratio: ν̂ = γ/γ_assumed (1.0 when not estimated).
        information: the Fisher information of the estimated parameters at the estimate,
            (4, 4) or (5, 5) with ν.
        iterations: scoring iterations used. converged: the last step was negligible.
    """

    source_m: FloatArray
    offset: float
    exponent_ratio: float
    information: FloatArray
    iterations: int
    converged: bool

    @property
    def peb_m(self) -> float:
        """√ of the trace of the position block of the inverse information, m."""
        try:
            return float(math.sqrt(np.trace(np.linalg.inv(self.information)[:3, :3])))
        except np.linalg.LinAlgError:
            return math.inf


def _range_model(x: FloatArray, positions: FloatArray, estimate_exponent: bool) -> tuple[FloatArray, FloatArray]:
    """s_j (M,) and ∇s_j (M, 4 or 5) at x = (p0, b[, ν])."""
    r = x[:3] - positions
    d = np.sqrt((r * r).sum(-1))
    nu = x[4] if estimate_exponent else 1.0
    s = np.exp(x[3] + nu * np.log(d))
    cols = [(s * nu / (d * d))[:, None] * r, s[:, None]]
    if estimate_exponent:
        cols.append((s * np.log(d))[:, None])
    return s, np.concatenate(cols, axis=1)


def _range_nll(
    x: FloatArray, positions: FloatArray, range_m: FloatArray, inv_s0sq: FloatArray, gamma: float, nu: bool
) -> tuple[float, FloatArray, FloatArray]:
    """−ℓ, its gradient and the expected information of ranges d̂ ~ N(s, s^γ/inv_s0sq)."""
    s, grad_s = _range_model(x, positions, nu)
    v = s**gamma / inv_s0sq
    e = range_m - s
    nll = 0.5 * float((e * e / v + np.log(v)).sum())
    # ∂(−ℓ)/∂s = −e/v + (γ/(2s))(1 − e²/v)
    ds = -e / v + 0.5 * gamma / s * (1.0 - e * e / v)
    a = inv_s0sq * s ** (-gamma) + 0.5 * gamma * gamma / (s * s)  # A_r(s)
    info = (grad_s * a[:, None]).T @ grad_s
    return nll, ds @ grad_s, info


def estimate_with_unknown_power(
    positions: ArrayLike,
    range_m: ArrayLike,
    los: ArrayLike,
    channel: Channel,
    start_m: ArrayLike,
    start_offset: float = 0.0,
    estimate_exponent: bool = False,
    iterations: int = 100,
) -> OffsetEstimate:
    """Maximum-likelihood p0 and power offset b (and optionally ν) from ranges (eqs. 3, 5).

    Fisher scoring with step halving on the likelihood of d̂_j ~ N(s_j, σ_r0,j² s_j^γ),
    s_j = e^b d_j^ν, from (``start_m``, ``start_offset``, ν = 1).

    Args:
        positions: the drones' positions at the records (M, 3), m, ENU.
        range_m: the measured ranges d̂ (M,), m (NaN rows are dropped).
        los: the records' LOS flags (M,) (σ_r0 of LOS or NLOS).
        channel: γ and σ_r0 (the exponent the drones assumed is ``channel.gamma``).
        start_m: the starting position (3,), e.g. the known-power estimate.
        estimate_exponent: estimate ν = γ/γ_assumed too.

    Raises:
        ValueError: fewer than 5 (6 with ν) finite ranges.
    """
    pos = np.asarray(positions, dtype=float).reshape(-1, 3)
    z = np.asarray(range_m, dtype=float).reshape(-1)
    keep = np.isfinite(z) & np.isfinite(pos).all(-1)
    pos, z = pos[keep], z[keep]
    inv = _inv_s0sq(np.asarray(los, dtype=float).reshape(-1)[keep], channel)
    npar = 5 if estimate_exponent else 4
    if len(z) < npar + 1:
        raise ValueError(f"estimate_with_unknown_power: expected at least {npar + 1} ranges, found {len(z)}")
    x = np.concatenate([np.asarray(start_m, dtype=float).reshape(3), [start_offset], [1.0] if estimate_exponent else []])
    f, g, info = _range_nll(x, pos, z, inv, channel.gamma, estimate_exponent)
    converged = False
    used = 0
    for _ in range(iterations):
        used += 1
        try:
            step = np.linalg.solve(info + 1e-12 * np.trace(info) * np.eye(npar), -g)
        except np.linalg.LinAlgError:
            break
        t = 1.0
        for _halving in range(40):
            cand = x + t * step
            fc, gc, ic = _range_nll(cand, pos, z, inv, channel.gamma, estimate_exponent)
            if np.isfinite(fc) and fc <= f:
                break
            t *= 0.5
        else:
            converged = True  # no ascent direction left at machine precision
            break
        decrement = float(-g @ step)
        x, f, g, info = cand, fc, gc, ic
        if decrement < 1e-12:
            converged = True
            break
    return OffsetEstimate(
        source_m=x[:3].copy(),
        offset=float(x[3]),
        exponent_ratio=float(x[4]) if estimate_exponent else 1.0,
        information=info,
        iterations=used,
        converged=converged,
    )


__all__ = [
    "OffsetEstimate",
    "SchurParts",
    "cost_gradient_unknown_power",
    "cost_unknown_power",
    "equivalent_fim",
    "estimate_with_unknown_power",
    "fisher_information_unknown_power",
    "offset_db",
    "position_error_bound_unknown_power",
    "range_weight",
    "schur_parts",
]
