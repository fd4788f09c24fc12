"""Robust, recursive, batched maximum-likelihood estimator of the source position.

The paper (Guerra, Dardari, Djurić) takes the source estimate p̂0 as given (sec. II-B,
footnote 2); fimnav computes it here from the ranging and bearing estimates of eq. (3), each
tagged with the position it was taken at and its LOS/NLOS flag. Design notes, the bias
discussion and the measured figures are in ``docs/estimator.md``.

Public API
----------
``Measurements``
    One batch of records. ``positions_m`` (..., M, 3) m ENU; ``range_m``, ``azimuth_rad``,
    ``elevation_rad`` (..., M); ``los`` (..., M) bool. NaN marks an absent value; a row whose
    position is NaN is no measurement, so batch elements may carry different counts.
``EstimatorConfig``
    Frozen tuning: raw window, forgetting, Huber threshold, innovation gate, iterations, ...
``EstimatorState``
    Frozen state: ``estimate_m`` (..., 3), ``information`` (..., 3, 3) (Fisher information of
    everything used, at the estimate, robust weights applied), ``observable`` (...,) bool,
    ``initialised`` (...,) bool, plus the internal accumulators.
``initial_state(batch_shape, config) -> EstimatorState``
``update(state, measurements, channel, config) -> EstimatorState``  (pure)

Measurement model (paper eqs. 3-5), drone at p, source at p0, r = p0 - p:

.. math::
    d = \\lVert r\\rVert,\\quad \\phi = \\operatorname{atan2}(r_y, r_x),\\quad
    \\theta = \\operatorname{atan2}(r_z, \\sqrt{r_x^2+r_y^2})

    \\hat d = d + n_r,\\ n_r\\sim\\mathcal N(0, \\sigma_{r,0}^2 d^{\\gamma}),\\qquad
    \\hat\\phi = \\phi + n_b,\\ \\hat\\theta = \\theta + n_b,\\ n_b\\sim\\mathcal N(0,\\sigma_b^2)
    \\text{ (LOS)}

with σ_r0 = (ln10/10)(σ_sh/γ) for the link's LOS or NLOS ratio; an NLOS bearing is the
outlier ω of eq. (3) and is given weight ``config.nlos_bearing_weight`` (0 by default).

Method, per call of :func:`update` and per batch element:

1. Closed-form pseudo-linear (PL) normal equations of every new record are accumulated
   exactly (they are linear in θ = (p0, R = ‖p0‖²)): bearing rows
   (Lingren & Gong 1978; 3-D form of Doğançay, IEEE TSP 63(1), 2015) project p0 − p onto
   the two directions orthogonal to the measured unit vector u; a range with a usable
   bearing gives uᵀ(p0 − p) = d̂; a range alone gives the squared-range equation
   2pᵀp0 − R = ‖p‖² − d̂² with the auxiliary unknown R (unconstrained LS of Cheung, So,
   Ma & Chan, IEEE TSP 52(4), 2004), with the constraint R = ‖p0‖² applied when R is the
   only degenerate direction (coplanar drones: mirror ambiguity, resolved by
   ``config.mirror``). An element is initialised by this PL solution.
2. Robust ML refinement (Levenberg-Marquardt, Fisher scoring) of

   .. math::
       C(p_0) = \\tfrac12 p_0^T\\Lambda p_0 - \\eta^T p_0
       + \\sum_i a_i\\big[\\rho_k(e_i) + \\tfrac12 \\ln\\sigma_i^2(p_0)\\,[i\\text{ range}]\\big],
       \\qquad e_i = (z_i - h_i(p_0))/\\sigma_i(p_0)

   over a bounded window of the latest ``window_rows`` raw records plus the new ones,
   warm-started at the previous estimate; ρ_k is Huber's loss, (Λ, η) the information-form
   summary of the records that left the window (each marginalised, linearised at the
   estimate of the step it left). The Fisher scoring matrix includes the range-dependent
   variance term, a_r ∇d∇dᵀ (w/σ_r² + γ²/(2d²)) (the paper's A_d of eq. 12 when w = 1).
3. Innovation gate: with an observable previous state, a component whose innovation exceeds
   ``gate_sigma`` standard deviations of σ² + ∇hᵀΛ⁻¹∇h is excluded (redescending beyond
   Huber), unless more than ``gate_max_fraction`` of the element's new components would be.
4. Forgetting λ ∈ (0, 1]: every stored contribution (Λ, η, PL equations, window weights)
   is multiplied by λ per call, for a moving source.
5. Observability: initialised and λ_min/λ_max of the information ≥ ``min_rcond``.

Per-call cost is O(batch × (window_rows + M)), independent of the number of calls. No NaN is
returned: the estimate is finite everywhere (the origin, or the last value, until the element
is initialised), and ``observable`` says when it can be trusted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from planner.params import Channel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["Measurements", "EstimatorConfig", "EstimatorState", "initial_state", "update", "empty_measurements"]

#: Floors (m) keeping the model finite when a drone sits on the source or right above it.
_RHO2_FLOOR_M2: float = 1e-12
_D_FLOOR_M: float = 1e-6
#: Distances below this (m) use this value in the ranging variance σ_r0² d^γ.
_VAR_D_FLOOR_M: float = 0.1


# --------------------------------------------------------------------------- public types


@dataclass(frozen=True)
class Measurements:
    """Range/bearing records, each with the drone position it was taken at (eq. 3).

    Attributes:
        positions_m: drone positions p_j, shape (..., M, 3), metres, mission ENU frame;
            a NaN position marks an empty row (no measurement).
        range_m: ranging estimates d̂_j, shape (..., M), metres; NaN where not measured.
        azimuth_rad: azimuth estimates φ̂_j, shape (..., M), radians from east towards north;
            NaN where not measured.
        elevation_rad: elevation estimates θ̂_j, shape (..., M), radians above horizontal;
            NaN where not measured.
        los: the drone's LOS classification of its link when measured, bool (..., M).
    """

    positions_m: FloatArray
    range_m: FloatArray
    azimuth_rad: FloatArray
    elevation_rad: FloatArray
    los: BoolArray

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading (batch) shape: ``positions_m.shape[:-2]``."""
        return tuple(np.shape(self.positions_m)[:-2])

    @property
    def count(self) -> int:
        """Rows per batch element, M."""
        return int(np.shape(self.positions_m)[-2])


def empty_measurements(batch_shape: tuple[int, ...], rows: int) -> Measurements:
    """All-NaN :class:`Measurements` of shape ``batch_shape + (rows,)`` (LOS flags True)."""
    shape = tuple(batch_shape) + (int(rows),)
    nan = np.full(shape, np.nan)
    return Measurements(np.full(shape + (3,), np.nan), nan, nan.copy(), nan.copy(), np.ones(shape, dtype=bool))


@dataclass(frozen=True)
class EstimatorConfig:
    """Tuning of the estimator (all dimensionless unless a unit is in the name).

    Attributes:
        window_rows: raw records kept per batch element and re-linearised at every call
            (0 = pure information form). Records beyond it are marginalised into (Λ, η).
        forgetting: λ ∈ (0, 1]; stored information is multiplied by λ per call (1 = static).
        huber_k: Huber threshold on normalised residuals |e| = |z − h|/σ.
        gate_sigma: innovation gate in standard deviations (None disables it).
        gate_max_fraction: if more than this fraction of an element's components would be
            gated, the gate is not applied to that element for this call.
        iterations: Levenberg-Marquardt iterations per call.
        lm_damping: initial LM damping, relative to the diagonal of the scoring matrix.
        nlos_bearing_weight: weight of bearings flagged NLOS (0: they carry no information).
        min_rcond: observability threshold on λ_min/λ_max of the information matrix.
        pl_rcond: rank threshold of the (Jacobi-scaled) pseudo-linear normal equations.
        init_distance_m: distance used to weight a bearing's PL equations when no range is
            known for it and the element has no estimate yet (m).
        range_cost: ``"gls"`` (default): ranges weighted by 1/σ_r²(d) evaluated at the current
            iterate (iteratively re-weighted generalised LS; consistent, exact on noise-free data);
            ``"ml"``: the full likelihood with ½ ln σ_r²(d), efficient but biased towards short
            ranges when the residuals are smaller than their model (e.g. noise-free data).
        mirror: which root of the coplanar-range mirror ambiguity the PL initialisation
            takes: ``"below"`` (lower z, source under the swarm) or ``"above"``.
    """

    window_rows: int = 10
    forgetting: float = 1.0
    huber_k: float = 1.345
    gate_sigma: float | None = 5.0
    gate_max_fraction: float = 0.5
    iterations: int = 3
    lm_damping: float = 1e-3
    nlos_bearing_weight: float = 0.0
    min_rcond: float = 1e-9
    pl_rcond: float = 1e-10
    init_distance_m: float = 100.0
    mirror: Literal["below", "above"] = "below"
    range_cost: Literal["gls", "ml"] = "gls"

    def __post_init__(self) -> None:
        if not (isinstance(self.window_rows, int) and self.window_rows >= 0):
            raise ValueError(f"EstimatorConfig.window_rows: expected an integer >= 0, found {self.window_rows!r}")
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise ValueError(f"EstimatorConfig.iterations: expected an integer >= 1, found {self.iterations!r}")
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError(f"EstimatorConfig.forgetting: expected a value in (0, 1], found {self.forgetting!r}")
        positive = ("huber_k", "lm_damping", "min_rcond", "pl_rcond", "init_distance_m")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"EstimatorConfig.{name}: expected a finite positive number, found {value!r}")
        if self.gate_sigma is not None and not (math.isfinite(self.gate_sigma) and self.gate_sigma > 0.0):
            raise ValueError(f"EstimatorConfig.gate_sigma: expected None or a positive number, found {self.gate_sigma!r}")
        if not 0.0 <= self.gate_max_fraction <= 1.0:
            raise ValueError(
                f"EstimatorConfig.gate_max_fraction: expected a value in [0, 1], found {self.gate_max_fraction!r}"
            )
        if not 0.0 <= self.nlos_bearing_weight <= 1.0:
            raise ValueError(
                f"EstimatorConfig.nlos_bearing_weight: expected a value in [0, 1], found {self.nlos_bearing_weight!r}"
            )
        if self.range_cost not in ("gls", "ml"):
            raise ValueError(f"EstimatorConfig.range_cost: expected 'gls' or 'ml', found {self.range_cost!r}")
        if self.mirror not in ("below", "above"):
            raise ValueError(f"EstimatorConfig.mirror: expected 'below' or 'above', found {self.mirror!r}")


@dataclass(frozen=True)
class EstimatorState:
    """Estimator state for a batch (leading shape ``...``). Treat as immutable.

    Attributes:
        estimate_m: source estimate p̂0, shape (..., 3), metres, ENU; finite everywhere
            (meaningful only where ``initialised``).
        information: Fisher information of all records used, evaluated at the estimate with
            the robust weights, shape (..., 3, 3), m⁻²; zero where not initialised.
        observable: (...,) bool, True where the source is locally identifiable (initialised
            and λ_min/λ_max(information) ≥ ``min_rcond``).
        initialised: (...,) bool, True once the pseudo-linear system was solvable.
        prior_information: Λ, information of the marginalised records, (..., 3, 3), m⁻².
        prior_vector: η, so that their cost is ½xᵀΛx − ηᵀx, shape (..., 3), m⁻¹.
        pl_matrix, pl_vector: pseudo-linear normal equations of every record, (..., 4, 4), (..., 4).
        pl_dropped_matrix, pl_dropped_vector: the same for records that left the window before
            initialisation (they become the prior, R marginalised out, at initialisation).
        window: the raw records kept, a :class:`Measurements` of shape (..., window_rows).
        window_weight: their forgetting weights λ^age, (..., window_rows).
        measurement_count: scalar components (range, azimuth, elevation) used so far, (...,).
    """

    estimate_m: FloatArray
    information: FloatArray
    observable: BoolArray
    initialised: BoolArray
    prior_information: FloatArray
    prior_vector: FloatArray
    pl_matrix: FloatArray
    pl_vector: FloatArray
    pl_dropped_matrix: FloatArray
    pl_dropped_vector: FloatArray
    window: Measurements
    window_weight: FloatArray
    measurement_count: NDArray[np.int64]

    @property
    def batch_shape(self) -> tuple[int, ...]:
        """Leading (batch) shape."""
        return tuple(self.estimate_m.shape[:-1])


def initial_state(batch_shape: tuple[int, ...] = (), config: EstimatorConfig | None = None) -> EstimatorState:
    """State with no information for a batch of shape ``batch_shape`` (``()`` for one drone).

    Args:
        batch_shape: leading shape, e.g. ``(trials, drones)``.
        config: the configuration (for the window size); defaults to ``EstimatorConfig()``.

    Returns:
        An :class:`EstimatorState` with ``estimate_m`` at the origin, not observable.
    """
    config = EstimatorConfig() if config is None else config
    b = tuple(int(n) for n in batch_shape)
    return EstimatorState(
        estimate_m=np.zeros(b + (3,)),
        information=np.zeros(b + (3, 3)),
        observable=np.zeros(b, dtype=bool),
        initialised=np.zeros(b, dtype=bool),
        prior_information=np.zeros(b + (3, 3)),
        prior_vector=np.zeros(b + (3,)),
        pl_matrix=np.zeros(b + (4, 4)),
        pl_vector=np.zeros(b + (4,)),
        pl_dropped_matrix=np.zeros(b + (4, 4)),
        pl_dropped_vector=np.zeros(b + (4,)),
        window=empty_measurements(b, config.window_rows),
        window_weight=np.zeros(b + (config.window_rows,)),
        measurement_count=np.zeros(b, dtype=np.int64),
    )


# --------------------------------------------------------------------------- small linear algebra


def _det3(a: FloatArray) -> FloatArray:
    return (
        a[..., 0, 0] * (a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1])
        - a[..., 0, 1] * (a[..., 1, 0] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 0])
        + a[..., 0, 2] * (a[..., 1, 0] * a[..., 2, 1] - a[..., 1, 1] * a[..., 2, 0])
    )


def _adj3(a: FloatArray) -> FloatArray:
    """Adjugate of symmetric 3x3 matrices (..., 3, 3)."""
    c = np.empty_like(a)
    c[..., 0, 0] = a[..., 1, 1] * a[..., 2, 2] - a[..., 1, 2] * a[..., 2, 1]
    c[..., 0, 1] = a[..., 0, 2] * a[..., 2, 1] - a[..., 0, 1] * a[..., 2, 2]
    c[..., 0, 2] = a[..., 0, 1] * a[..., 1, 2] - a[..., 0, 2] * a[..., 1, 1]
    c[..., 1, 1] = a[..., 0, 0] * a[..., 2, 2] - a[..., 0, 2] * a[..., 2, 0]
    c[..., 1, 2] = a[..., 0, 2] * a[..., 1, 0] - a[..., 0, 0] * a[..., 1, 2]
    c[..., 2, 2] = a[..., 0, 0] * a[..., 1, 1] - a[..., 0, 1] * a[..., 1, 0]
    c[..., 1, 0] = c[..., 0, 1]
    c[..., 2, 0] = c[..., 0, 2]
    c[..., 2, 1] = c[..., 1, 2]
    return c


def _inv3_spd(a: FloatArray) -> tuple[FloatArray, BoolArray]:
    """Inverse of symmetric 3x3 matrices and a flag where it is well defined."""
    det = _det3(a)
    scale = np.maximum(np.einsum("...ii->...", a), 1e-300) ** 3
    ok = np.isfinite(det) & (det > 1e-14 * scale)
    safe = np.where(ok, det, 1.0)
    return _adj3(a) / safe[..., None, None], ok


def _eig_extremes3(a: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Smallest and largest eigenvalues of symmetric 3x3 matrices (closed form, Smith 1961)."""
    p1 = a[..., 0, 1] ** 2 + a[..., 0, 2] ** 2 + a[..., 1, 2] ** 2
    q = (a[..., 0, 0] + a[..., 1, 1] + a[..., 2, 2]) / 3.0
    p2 = (a[..., 0, 0] - q) ** 2 + (a[..., 1, 1] - q) ** 2 + (a[..., 2, 2] - q) ** 2 + 2.0 * p1
    p = np.sqrt(p2 / 6.0)
    safe_p = np.where(p > 0.0, p, 1.0)
    b = (a - q[..., None, None] * np.eye(3)) / safe_p[..., None, None]
    r = np.clip(_det3(b) / 2.0, -1.0, 1.0)
    phi = np.arccos(r) / 3.0
    big = np.where(p > 0.0, q + 2.0 * p * np.cos(phi), q)
    small = np.where(p > 0.0, q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0), q)
    return small, big


# --------------------------------------------------------------------------- measurement model


def _model(x: FloatArray, p: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Predicted (d, φ, θ) and their gradients w.r.t. the source.

    Args:
        x: source (..., 3), m. p: drone positions (..., K, 3), m (finite).

    Returns:
        ``h`` (..., K, 3) [m, rad, rad], ``grad`` (..., K, 3, 3) with grad[..., c, :] = ∇_x h_c,
        and ``d`` (..., K) in m (floored).
    """
    r = x[..., None, :] - p
    rx, ry, rz = r[..., 0], r[..., 1], r[..., 2]
    rho2 = np.maximum(rx * rx + ry * ry, _RHO2_FLOOR_M2)
    rho = np.sqrt(rho2)
    d2 = rho2 + rz * rz
    d = np.maximum(np.sqrt(d2), _D_FLOOR_M)
    h = np.stack((d, np.arctan2(ry, rx), np.arctan2(rz, rho)), axis=-1)
    grad = np.empty(r.shape[:-1] + (3, 3))
    grad[..., 0, :] = r / d[..., None]
    grad[..., 1, 0] = -ry / rho2
    grad[..., 1, 1] = rx / rho2
    grad[..., 1, 2] = 0.0
    f = rz / (d * d * rho)
    grad[..., 2, 0] = -rx * f
    grad[..., 2, 1] = -ry * f
    grad[..., 2, 2] = rho / (d * d)
    return h, grad, d


def _wrap(angle: FloatArray) -> FloatArray:
    """Wrap to [-π, π)."""
    return (angle + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True)
class _Rows:
    """Finite-filled rows with per-component weights (internal)."""

    p: FloatArray  # (..., K, 3)
    z: FloatArray  # (..., K, 3): range, azimuth, elevation
    a: FloatArray  # (..., K, 3): weights (0 = unused)
    s0sq: FloatArray  # (..., K): σ_r0² of the row's link


def _rows(meas: Measurements, row_weight: FloatArray, channel: Channel, config: EstimatorConfig) -> _Rows:
    p = meas.positions_m
    row_ok = np.all(np.isfinite(p), axis=-1)
    z = np.stack((meas.range_m, meas.azimuth_rad, meas.elevation_rad), axis=-1)
    ok = np.isfinite(z) & row_ok[..., None]
    los = meas.los
    bearing_w = np.where(los, 1.0, config.nlos_bearing_weight)
    a = np.stack((np.ones_like(bearing_w), bearing_w, bearing_w), axis=-1) * row_weight[..., None]
    a = np.where(ok, a, 0.0)
    s0 = np.where(los, channel.sigma_r0_los, channel.sigma_r0_nlos)
    return _Rows(np.where(row_ok[..., None], p, 0.0), np.where(ok, z, 0.0), a, s0 * s0)


def _residuals(
    x: FloatArray, rows: _Rows, channel: Channel, d_var: FloatArray | None = None
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Normalised residuals e = (z − h)/σ (..., K, 3), 1/σ (..., K, 3), σ_r² (..., K), the
    floored distance (..., K) and ∇h (..., K, 3, 3). ``d_var`` (..., K), if given, is the
    distance at which σ_r² is evaluated (GLS: frozen within an iteration)."""
    h, grad, d = _model(x, rows.p)
    dv = np.maximum(d if d_var is None else d_var, _VAR_D_FLOOR_M)
    var_r = rows.s0sq * dv**channel.gamma
    res = rows.z - h
    res[..., 1] = _wrap(res[..., 1])
    inv_sd = np.empty_like(res)
    inv_sd[..., 0] = 1.0 / np.sqrt(var_r)
    inv_sd[..., 1:] = 1.0 / channel.sigma_bearing_rad
    return res * inv_sd, inv_sd, var_r, dv, grad


def _huber(e: FloatArray, k: float) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Huber loss ρ_k(e), the mask |e| ≤ k, and |e|."""
    ae = np.abs(e)
    inside = ae <= k
    rho = np.where(inside, 0.5 * e * e, k * ae - 0.5 * k * k)
    return rho, inside, ae


def _robust_cost(x: FloatArray, rows: _Rows, channel: Channel, k: float, d_var: FloatArray | None) -> FloatArray:
    """Robust cost per component (..., K, 3): a·ρ_k(e), plus a·½ ln σ_r² for ranges in ML mode
    (``d_var`` None); in GLS mode σ_r² is evaluated at ``d_var`` and the log term is constant."""
    e, _, var_r, _, _ = _residuals(x, rows, channel, d_var)
    rho, _, _ = _huber(e, k)
    cost = rows.a * rho
    if d_var is None:
        cost[..., 0] += rows.a[..., 0] * 0.5 * np.log(var_r)
    return cost


def _terms(
    x: FloatArray, rows: _Rows, channel: Channel, k: float, ml: bool
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Robust cost per component and its Fisher-scoring terms at ``x``.

    Returns ``cost`` (..., K, 3); ``gcoef``, ``icoef`` (..., K, 3) such that the gradient of
    the cost is Σ gcoef ∇h and its scoring matrix Σ icoef ∇h∇hᵀ; ``fcoef`` (..., K, 3), the
    same for the robust-weighted Fisher information; ``grad`` = ∇h (..., K, 3, 3); and the
    distances (..., K). With IRLS weight w = ψ(e)/e and e = (z − h)/σ:

    .. math::
        \nabla C_i = -a w e \nabla h/\sigma + [\text{ML, range}]\,a\tfrac{\gamma}{2d}(1 - w e^2)\nabla d,
        \qquad
        I_i = a\,\nabla h\nabla h^T\big(w/\sigma^2 + [\text{range}]\,\gamma^2/(2d^2)\big)

    the last term being ∇σ²∇σ²ᵀ/(2σ⁴) of the range-dependent variance (eq. 12's A_d); in GLS
    mode (``ml`` False) the scoring matrix omits it and the gradient has no variance term.
    """
    e, inv_sd, var_r, dv, grad = _residuals(x, rows, channel)
    rho, inside, ae = _huber(e, k)
    cost = rows.a * rho
    w = np.where(inside, 1.0, k / np.maximum(ae, 1e-300))
    gcoef = -rows.a * w * e * inv_sd
    icoef = rows.a * w * inv_sd * inv_sd
    gd = channel.gamma / (2.0 * dv)
    fcoef = icoef.copy()
    fcoef[..., 0] += rows.a[..., 0] * 2.0 * gd * gd
    if ml:
        cost[..., 0] += rows.a[..., 0] * 0.5 * np.log(var_r)
        gcoef[..., 0] += rows.a[..., 0] * gd * (1.0 - w[..., 0] * e[..., 0] ** 2)
        icoef = fcoef
    return cost, gcoef, icoef, fcoef, grad, dv


def _prior_cost(x: FloatArray, lam: FloatArray, eta: FloatArray) -> FloatArray:
    """½ xᵀΛx − ηᵀx, (...,)."""
    return 0.5 * np.einsum("...i,...ij,...j->...", x, lam, x) - np.einsum("...i,...i->...", eta, x)


def _assemble(gcoef: FloatArray, icoef: FloatArray, grad: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Gradient (..., 3) and scoring matrix (..., 3, 3) summed over rows and components."""
    shape = grad.shape[:-3]
    g2 = grad.reshape(shape + (-1, 3))
    g = np.einsum("...n,...ni->...i", gcoef.reshape(shape + (-1,)), g2)
    weighted = g2 * icoef.reshape(shape + (-1, 1))
    info = np.matmul(np.swapaxes(weighted, -1, -2), g2)
    return g, info


# --------------------------------------------------------------------------- pseudo-linear part


def _pl_rows(rows: _Rows, scale_d: FloatArray, channel: Channel) -> tuple[FloatArray, FloatArray]:
    """Pseudo-linear normal-equation contributions of each row: A (..., K, 4, 4), b (..., K, 4).

    Unknown θ = (x0, y0, z0, R = ‖p0‖²). Equations (weight ω, all linear in θ):

    * azimuth: (sin φ̂, −cos φ̂, 0)·(p0 − p) = 0, ω = a/(σ_b² (d_w cos θ̂)²);
    * elevation (with an azimuth): (−sin θ̂ cos φ̂, −sin θ̂ sin φ̂, cos θ̂)·(p0 − p) = 0,
      ω = a/(σ_b² d_w²);
    * range with a usable bearing: uᵀ(p0 − p) = d̂, ω = a/σ_r²(d̂);
    * range alone: 2pᵀp0 − R = ‖p‖² − d̂², ω = a/(4 d̂² σ_r²(d̂)).

    d_w is the measured range if any, else ``scale_d`` (..., K).
    """
    p, z, a = rows.p, rows.z, rows.a
    has_r = a[..., 0] > 0.0
    has_az = a[..., 1] > 0.0
    has_el = (a[..., 2] > 0.0) & has_az
    has_b = has_az & has_el
    dhat = np.maximum(np.abs(z[..., 0]), 1.0)
    d_w = np.where(has_r, dhat, scale_d)
    sb2 = channel.sigma_bearing_rad**2
    var_r = rows.s0sq * dhat**channel.gamma
    cphi, sphi = np.cos(z[..., 1]), np.sin(z[..., 1])
    cth, sth = np.cos(z[..., 2]), np.sin(z[..., 2])
    zero = np.zeros_like(cphi)
    one = np.ones_like(cphi)
    pp = np.einsum("...i,...i->...", p, p)
    # Equation coefficient rows c (..., K, 4 eqs, 4), rhs beta (..., K, 4 eqs), weight (..., K, 4 eqs).
    c_az = np.stack((sphi, -cphi, zero, zero), axis=-1)
    c_el = np.stack((-sth * cphi, -sth * sphi, cth, zero), axis=-1)
    c_ru = np.stack((cth * cphi, cth * sphi, sth, zero), axis=-1)
    c_rr = np.concatenate((2.0 * p, -one[..., None]), axis=-1)
    c = np.stack((c_az, c_el, c_ru, c_rr), axis=-2)
    p4 = np.concatenate((p, zero[..., None]), axis=-1)
    beta = np.einsum("...ej,...j->...e", c, p4)
    beta[..., 2] += z[..., 0]
    beta[..., 3] = pp - z[..., 0] ** 2
    rho_w = np.maximum(d_w * np.abs(cth), 1e-3 * d_w)
    w_az = np.where(has_az, a[..., 1] / (sb2 * rho_w**2), 0.0)
    w_el = np.where(has_el, a[..., 2] / (sb2 * d_w**2), 0.0)
    w_ru = np.where(has_r & has_b, a[..., 0] / var_r, 0.0)
    w_rr = np.where(has_r & ~has_b, a[..., 0] / (4.0 * dhat**2 * var_r), 0.0)
    omega = np.stack((w_az, w_el, w_ru, w_rr), axis=-1)
    wc = c * omega[..., None]
    A = np.matmul(np.swapaxes(wc, -1, -2), c)
    b = np.einsum("...ej,...e->...j", wc, beta)
    return A, b


def _pl_solve(A: FloatArray, b: FloatArray, config: EstimatorConfig) -> tuple[FloatArray, BoolArray]:
    """Solve the pseudo-linear normal equations (n, 4, 4), (n, 4) -> p0 (n, 3), ok (n,).

    Full rank: the weighted LS solution. Rank 3 with the null direction involving R (ranges
    from coplanar positions): the two points of the null line that satisfy R = ‖p0‖², the one
    chosen by ``config.mirror`` (Cheung et al. 2004, constrained LS, degenerate case).
    Without range-only equations R is decoupled (R = 0) and the 3x3 block is solved.
    """
    n = A.shape[0]
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    A = A.copy()
    b = b.copy()
    diag = np.einsum("...ii->...i", A)
    has_R = diag[:, 3] > 1e-300
    no_r = ~has_R
    A[no_r, 3, :] = 0.0
    A[no_r, :, 3] = 0.0
    A[no_r, 3, 3] = 1.0
    b[no_r, 3] = 0.0
    diag = np.einsum("...ii->...i", A)
    s = np.where(diag > 1e-300, 1.0 / np.sqrt(np.maximum(diag, 1e-300)), 1.0)
    As = A * s[:, :, None] * s[:, None, :]
    bs = b * s
    ev, V = np.linalg.eigh(As)
    tol = config.pl_rcond * np.maximum(ev[:, -1], 1e-300)
    good = ev > tol[:, None]
    rank = good.sum(axis=1)
    inv_ev = np.where(good, 1.0 / np.where(good, ev, 1.0), 0.0)
    ys = np.einsum("nij,nj,nkj,nk->ni", V, inv_ev, V, bs)
    theta = ys * s
    x = theta[:, :3].copy()
    ok = rank == 4
    # Degenerate by one direction with an R component: apply R = ‖p0‖².
    v = V[:, :, 0] * s
    mirror = (rank == 3) & has_R & (np.abs(V[:, 3, 0]) > 1e-6)
    if np.any(mirror):
        vp, vr = v[:, :3], v[:, 3]
        qa = np.einsum("ni,ni->n", vp, vp)
        qb = 2.0 * np.einsum("ni,ni->n", x, vp) - vr
        qc = np.einsum("ni,ni->n", x, x) - theta[:, 3]
        disc = qb * qb - 4.0 * qa * qc
        sq = np.sqrt(np.maximum(disc, 0.0))
        safe_qa = np.where(qa > 1e-300, qa, 1.0)
        t1 = (-qb - sq) / (2.0 * safe_qa)
        t2 = (-qb + sq) / (2.0 * safe_qa)
        z1 = x[:, 2] + t1 * vp[:, 2]
        z2 = x[:, 2] + t2 * vp[:, 2]
        pick_first = (z1 <= z2) if config.mirror == "below" else (z1 >= z2)
        t = np.where(pick_first, t1, t2)
        x = np.where(mirror[:, None], x + t[:, None] * vp, x)
        ok = ok | (mirror & (qa > 1e-300))
    ok &= np.all(np.isfinite(x), axis=1)
    return np.where(ok[:, None], x, 0.0), ok


def _schur_prior(A: FloatArray, b: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Marginalise R out of PL normal equations: Λ = A_pp − A_pR A_RR⁻¹ A_Rp, η likewise."""
    arr = A[..., 3, 3]
    safe = np.where(arr > 1e-300, arr, 1.0)
    coupling = np.where((arr > 1e-300)[..., None], A[..., :3, 3] / safe[..., None], 0.0)
    lam = A[..., :3, :3] - coupling[..., :, None] * A[..., None, 3, :3]
    eta = b[..., :3] - coupling * b[..., 3:4]
    lam = 0.5 * (lam + np.swapaxes(lam, -1, -2))
    return lam, eta


# --------------------------------------------------------------------------- update


def _check(measurements: Measurements, batch_shape: tuple[int, ...]) -> Measurements:
    p = np.asarray(measurements.positions_m, dtype=float)
    if p.ndim < 2 or p.shape[-1] != 3 or p.shape[:-2] != batch_shape:
        raise ValueError(
            f"Measurements.positions_m: expected shape {batch_shape + ('M', 3)}, found {p.shape}"
        )
    rows = p.shape[:-1]
    fields = {}
    for name in ("range_m", "azimuth_rad", "elevation_rad"):
        arr = np.asarray(getattr(measurements, name), dtype=float)
        if arr.shape != rows:
            raise ValueError(f"Measurements.{name}: expected shape {rows}, found {arr.shape}")
        fields[name] = arr
    los = np.asarray(measurements.los)
    if los.dtype != np.bool_ or los.shape != rows:
        raise ValueError(f"Measurements.los: expected a bool array of shape {rows}, found {los.dtype} {los.shape}")
    return Measurements(p, fields["range_m"], fields["azimuth_rad"], fields["elevation_rad"], los)


def _concat(a: Measurements, b: Measurements) -> Measurements:
    return Measurements(
        np.concatenate((a.positions_m, b.positions_m), axis=-2),
        np.concatenate((a.range_m, b.range_m), axis=-1),
        np.concatenate((a.azimuth_rad, b.azimuth_rad), axis=-1),
        np.concatenate((a.elevation_rad, b.elevation_rad), axis=-1),
        np.concatenate((a.los, b.los), axis=-1),
    )


def _take(m: Measurements, idx: NDArray[np.intp]) -> Measurements:
    return Measurements(
        np.take_along_axis(m.positions_m, idx[..., None], axis=-2),
        np.take_along_axis(m.range_m, idx, axis=-1),
        np.take_along_axis(m.azimuth_rad, idx, axis=-1),
        np.take_along_axis(m.elevation_rad, idx, axis=-1),
        np.take_along_axis(m.los, idx, axis=-1),
    )


def _slice_rows(rows: _Rows, sl: slice) -> _Rows:
    return _Rows(rows.p[..., sl, :], rows.z[..., sl, :], rows.a[..., sl, :], rows.s0sq[..., sl])


def update(
    state: EstimatorState,
    measurements: Measurements,
    channel: Channel,
    config: EstimatorConfig | None = None,
) -> EstimatorState:
    """Incorporate new records and return the new state (pure function, inputs untouched).

    Args:
        state: previous state, batch shape ``B`` (``()`` for one planner).
        measurements: new records, ``positions_m`` of shape ``B + (M, 3)`` (m, ENU), angles in
            radians, NaN for absent values, ``los`` bool ``B + (M,)``. M may be 0.
        channel: the RSS channel (γ, σ_sh/γ LOS/NLOS, σ_b), eqs. (3)-(5).
        config: estimator configuration; must be the one ``state`` was created with.

    Returns:
        The updated :class:`EstimatorState`; see the module docstring for the method.

    Raises:
        ValueError: shapes or dtypes that do not match the state.
    """
    config = EstimatorConfig() if config is None else config
    bshape = state.batch_shape
    W = config.window_rows
    if state.window.count != W:
        raise ValueError(f"EstimatorState: window has {state.window.count} rows, config.window_rows is {W}")
    new = _check(measurements, bshape)
    lam = config.forgetting
    M = new.count

    # Forgetting, then all rows: window first (oldest), new last.
    prior_info = state.prior_information * lam
    prior_vec = state.prior_vector * lam
    pl_A = state.pl_matrix * lam
    pl_b = state.pl_vector * lam
    dr_A = state.pl_dropped_matrix * lam
    dr_b = state.pl_dropped_vector * lam
    new_row_ok = np.all(np.isfinite(new.positions_m), axis=-1)
    allm = _concat(state.window, new)
    weight = np.concatenate((state.window_weight * lam, np.where(new_row_ok, 1.0, 0.0)), axis=-1)
    if W > 0 and M > 0:
        # Keep the most recent valid rows at the end (stable: order by validity, then age).
        valid = np.concatenate((np.isfinite(state.window.positions_m[..., 0]), new_row_ok), axis=-1)
        order = np.argsort(valid, axis=-1, kind="stable")
        allm = _take(allm, order)
        weight = np.take_along_axis(weight, order, axis=-1)
    rows = _rows(allm, weight, channel, config)
    K = W + M
    n_leave = K - W  # = M: the oldest rows leave the window after this call

    x_prev = state.estimate_m
    initialised = state.initialised.copy()
    # Pseudo-linear equations of the new records, weighted with the previous estimate's distances.
    new_rows = _rows(new, np.where(new_row_ok, 1.0, 0.0), channel, config)
    scale_new = np.where(
        initialised[..., None],
        np.linalg.norm(x_prev[..., None, :] - new_rows.p, axis=-1),
        config.init_distance_m,
    )
    A_new, b_new = _pl_rows(new_rows, np.maximum(scale_new, 1.0), channel)
    pl_A = pl_A + A_new.sum(axis=-3)
    pl_b = pl_b + b_new.sum(axis=-2)

    # Initialise the elements whose PL system became solvable.
    x = x_prev.copy()
    todo = ~initialised
    if np.any(todo):
        x_init, ok = _pl_solve(pl_A[todo], pl_b[todo], config)
        idx = np.flatnonzero(todo)
        xf = x.reshape(-1, 3)
        xf[idx[ok]] = x_init[ok]
        x = xf.reshape(x.shape)
        just = np.zeros(int(np.prod(bshape, dtype=np.int64)), dtype=bool)
        just[idx[ok]] = True
        just = just.reshape(bshape)
        # Records dropped before initialisation become the prior (R marginalised out).
        lam_d, eta_d = _schur_prior(dr_A, dr_b)
        prior_info = np.where(just[..., None, None], lam_d, prior_info)
        prior_vec = np.where(just[..., None], eta_d, prior_vec)
        initialised = initialised | just

    active = initialised
    a_active = np.where(active[..., None, None], rows.a, 0.0)

    # Innovation gate against the previous state.
    if config.gate_sigma is not None and K > 0 and np.any(state.observable):
        cov, inv_ok = _inv3_spd(state.information)
        use = state.observable & inv_ok
        h0, grad0, d0 = _model(x_prev, rows.p)
        var = np.empty_like(h0)
        var[..., 0] = rows.s0sq * np.maximum(d0, _VAR_D_FLOOR_M) ** channel.gamma
        var[..., 1:] = channel.sigma_bearing_rad**2
        pred = np.einsum("...kci,...ij,...kcj->...kc", grad0, cov, grad0)
        innov = rows.z - h0
        innov[..., 1] = _wrap(innov[..., 1])
        gated = (innov * innov > config.gate_sigma**2 * (var + np.maximum(pred, 0.0))) & (a_active > 0.0)
        n_valid = np.maximum((a_active > 0.0).sum(axis=(-1, -2)), 1)
        frac = gated.sum(axis=(-1, -2)) / n_valid
        apply = use & (frac <= config.gate_max_fraction)
        a_active = np.where(gated & apply[..., None, None], 0.0, a_active)
    rows = _Rows(rows.p, rows.z, a_active, rows.s0sq)

    # Levenberg-Marquardt (Fisher scoring) iterations, all elements at once.
    k = config.huber_k
    mu = np.full(bshape, config.lm_damping)

    n_iter = config.iterations if np.any(active) else 0
    ml = config.range_cost == "ml"
    it = 0
    while True:
        cost_rows, gcoef, icoef, fcoef, grad, dist = _terms(x, rows, channel, k, ml)
        g, H = _assemble(gcoef, icoef, grad)
        g = g + np.einsum("...ij,...j->...i", prior_info, x) - prior_vec
        H = H + prior_info
        if it == n_iter:
            break
        it += 1
        cost = cost_rows.sum(axis=(-1, -2)) + _prior_cost(x, prior_info, prior_vec)
        dH = np.einsum("...ii->...i", H)
        tr = dH.sum(axis=-1)
        Hd = H + (mu[..., None] * dH + 1e-12 * tr[..., None] + 1e-300)[..., None] * np.eye(3)
        Hinv, ok = _inv3_spd(Hd)
        step = -np.einsum("...ij,...j->...i", Hinv, g)
        cand = x + np.where((ok & active)[..., None], step, 0.0)
        c_rows = _robust_cost(cand, rows, channel, k, None if ml else dist)
        c_new = c_rows.sum(axis=(-1, -2)) + _prior_cost(cand, prior_info, prior_vec)
        accept = np.isfinite(c_new) & (c_new <= cost) & active
        x = np.where(accept[..., None], cand, x)
        mu = np.where(accept, mu / 3.0, mu * 4.0)
    fisher = _assemble(gcoef, fcoef, grad)[1] + prior_info if not ml else H

    # Marginalise the rows leaving the window (the oldest n_leave), linearised at x.
    if n_leave > 0:
        gl, Hl = _assemble(gcoef[..., :n_leave, :], icoef[..., :n_leave, :], grad[..., :n_leave, :, :])
        add_info = Hl
        add_vec = np.einsum("...ij,...j->...i", Hl, x) - gl
        prior_info = np.where(active[..., None, None], prior_info + add_info, prior_info)
        prior_vec = np.where(active[..., None], prior_vec + add_vec, prior_vec)
        # Before initialisation the leaving rows are kept only as PL equations.
        leave_rows = _slice_rows(_rows(allm, weight, channel, config), slice(0, n_leave))
        if np.any(~active):
            scale_l = np.full(leave_rows.a.shape[:-1], config.init_distance_m)
            A_l, b_l = _pl_rows(leave_rows, scale_l, channel)
            dr_A = dr_A + np.where(~active[..., None, None], A_l.sum(axis=-3), 0.0)
            dr_b = dr_b + np.where(~active[..., None], b_l.sum(axis=-2), 0.0)

    fisher = 0.5 * (fisher + np.swapaxes(fisher, -1, -2))
    finite = np.all(np.isfinite(x), axis=-1) & np.all(np.isfinite(fisher), axis=(-1, -2))
    x = np.where(finite[..., None], x, x_prev)
    info = np.where((active & finite)[..., None, None], fisher, 0.0)
    lo, hi = _eig_extremes3(info)
    observable = active & finite & (hi > 0.0) & (lo >= config.min_rcond * hi)

    if W > 0:
        window = Measurements(
            allm.positions_m[..., K - W :, :],
            allm.range_m[..., K - W :],
            allm.azimuth_rad[..., K - W :],
            allm.elevation_rad[..., K - W :],
            allm.los[..., K - W :],
        )
        window_weight = weight[..., K - W :]
    else:
        window, window_weight = state.window, state.window_weight
    count = state.measurement_count + (new_rows.a > 0.0).sum(axis=(-1, -2))
    return EstimatorState(
        estimate_m=x,
        information=info,
        observable=observable,
        initialised=initialised,
        prior_information=prior_info,
        prior_vector=prior_vec,
        pl_matrix=pl_A,
        pl_vector=pl_b,
        pl_dropped_matrix=dr_A,
        pl_dropped_vector=dr_b,
        window=window,
        window_weight=window_weight,
        measurement_count=count,
    )
