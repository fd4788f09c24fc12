r"""Robust, recursive, batched maximum-likelihood estimator of the source position.

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
    Frozen tuning: raw window, forgetting, robust loss, iterations, safeguards, ...
``EstimatorState``
    Frozen state: ``estimate_m`` (..., 3), ``information`` (..., 3, 3) (Fisher information of
    everything used, at the estimate, robust weights applied), ``observable`` (...,) bool,
    ``initialised`` (...,) bool, plus the internal accumulators.
``initial_state(batch_shape, config) -> EstimatorState``
``update(state, measurements, channel, config) -> EstimatorState``  (pure)
``empty_measurements(batch_shape, rows) -> Measurements``  (all NaN)

Measurement model (paper eqs. 3-5), drone at p, source at p0, r = p0 - p:

.. math::
    d = \lVert r\rVert,\quad \phi = \operatorname{atan2}(r_y, r_x),\quad
    \theta = \operatorname{atan2}(r_z, \sqrt{r_x^2+r_y^2})

    \hat d = d + n_r,\ n_r\sim\mathcal N(0, \sigma_{r,0}^2 d^{\gamma}),\qquad
    \hat\phi = \phi + n_b,\ \hat\theta = \theta + n_b,\ n_b\sim\mathcal N(0,\sigma_b^2)
    \text{ (LOS)}

with σ_r0 = (ln10/10)(σ_sh/γ) for the link's LOS or NLOS ratio; an NLOS bearing is the
outlier ω of eq. (3) and is given weight ``config.nlos_bearing_weight`` (0 by default).

Method, per call of :func:`update` and per batch element (vectorised over both):

1. Closed-form initialisation: pseudo-linear (PL) normal equations, linear in
   θ = (p0, R = ‖p0‖²), accumulated exactly until the element is initialised. Bearings
   project p0 − p onto the two directions orthogonal to the measured unit vector u
   (Lingren & Gong, IEEE T-AES 14(4), 1978; 3-D form of Doğançay, IEEE TSP 63(1), 2015); a
   range with a usable bearing gives uᵀ(p0 − p) = d̂; a range alone gives the squared-range
   equation 2pᵀp0 − R = ‖p‖² − d̂² + σ_r² (unconstrained LS of Cheung, So, Ma & Chan, IEEE
   TSP 52(4), 2004, bias E[d̂²] = d² + σ_r² removed), with the constraint R = ‖p0‖² applied
   along the weakest direction (coplanar drones: mirror ambiguity, ``config.mirror``).
2. Robust ML refinement, Levenberg-Marquardt with Fisher scoring, warm-started, of

   .. math::
       C(p_0) = \tfrac12 p_0^T\Lambda p_0 - \eta^T p_0 + \sum_i a_i\,\rho(e_i),
       \qquad e_i = (z_i - h_i(p_0))/\sigma_i

   over the latest ``window_rows`` raw records plus the new ones; (Λ, η) is the
   information-form summary of the records that left the window (each marginalised,
   linearised at the last iterate of the call it left). σ_r² = σ_r0² d^γ at the iterate
   ("gls") or with ½ ln σ_r² in the cost ("ml"); the reported Fisher information includes
   ∇σ²∇σ²ᵀ/(2σ⁴) = γ²/(2d²)∇d∇dᵀ (eq. 12's A_d). ρ: Huber from a fresh start, then Tukey's
   biweight (no influence beyond ``tukey_c``σ); steps capped at half the mean range.
3. Safeguards against a frozen wrong linearisation: *suspect* elements (too many records far
   from the estimate) get a deflated prior and Huber iterations; every ``recheck_every``
   calls the squared-range PL solution of all past ranges (each weighted at the estimate of
   the call it leaves a raw range window, ``recheck_window_rows``) replaces the estimate when it is
   much better on the PL cost and on the new records, claiming only ``recheck_trust`` of that
   solution's information (it can be biased by tens of metres). Optional innovation gate;
   optional score test of the recent records against the estimate (``consistency_threshold``).
4. Forgetting λ ∈ (0, 1]: every stored contribution (Λ, η, PL equations, window weights)
   is multiplied by λ per call, for a moving source.
5. Observability: initialised and det J/(tr J/3)³ ≥ ``min_rcond`` (J the information).

Every batch element runs its own number of LM iterations (``iterations``, or
``init_iterations`` in the call where it is initialised or moved), so an element of a batch
computes what the same records give with batch shape () (the simulator, batch (trials,
drones), and a planner node, batch (), agree).

Per-call cost is O(batch × (window_rows + M)), independent of the number of calls. No NaN is
returned: the estimate is finite everywhere (the origin, or the last value, until the element
is initialised), and ``observable`` says when it can be trusted.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, overload

import numpy as np
from numpy.typing import NDArray

from planner.params import Channel

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

__all__ = ["EstimatorConfig", "EstimatorState", "Measurements", "empty_measurements", "initial_state", "update"]

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
        loss: robust loss once an estimate exists: ``"tukey"`` (biweight, no influence beyond
            ``tukey_c``; default) or ``"huber"``. From a fresh start (the PL initialisation, a
            re-check move) the first half of the iterations always use Huber (convex).
        tukey_c: Tukey threshold on |e| (4.685: 95 % efficiency under Gaussian noise).
        gate_sigma: innovation gate in standard deviations (None disables it; with the Tukey
            loss it is redundant: a gated component, |e| > gate_sigma ≥ tukey_c, has no
            influence anyway; useful with ``loss="huber"``, e.g. 5).
        gate_max_fraction: if more than this fraction of an element's components would be
            gated, the gate is not applied to that element for this call.
        iterations: Levenberg-Marquardt iterations per call.
        init_iterations: iterations in a call where some element is initialised (from the
            pseudo-linear solution, which may be far from the ML one).
        suspect_sigma, suspect_fraction: an element more than ``suspect_fraction`` of whose
            ranges, or azimuths, or elevations (at least 3) in a call have |e| >
            ``suspect_sigma`` at its estimate is marked suspect
            (inconsistent with its own estimate). Gaussian inliers exceed 2.5σ 1.2 % of the
            time; with 20 % unflagged outliers about 18 % do, so 0.35 flags a consistent
            element rarely (≈ 5 % of calls with 10 bearings) and a wrong basin quickly.
        suspect_deflation: factor on the prior (Λ, η) of a suspect element at the next call.
        recheck_every: every this many calls, the estimate is checked against the global
            squared-range pseudo-linear solution of all ranges so far (0 disables); see
            :func:`update`, step 6.
        recheck_threshold: PL cost drop (≈ χ² units) that the PL solution must achieve over
            the current estimate before the estimate is moved there.
        recheck_trust: fraction of the re-check's PL information that is claimed (reported in
            ``information``) after the estimate moved there; the cost keeps all of it. The
            squared-range PL solution can be biased by tens of metres (NLOS ranges, 74 %
            relative noise), and claiming every range's information there made a wrong estimate
            a confident one (the source keep-out around it then missed the source).
        recheck_window_rows: ranges kept raw before they join the re-check's squared-range
            summary (0: at once). Each range's weight 1/(4D²σ_r²(D)) ∝ D⁻⁴ is fixed when it
            joins, D the distance from the estimate of that call: joining later, at a settled
            estimate, keeps the first ranges (weighted at a poor first estimate, D several
            times too short) from dominating the summary. The re-check uses the summary plus
            the ranges still in the window, weighted at the current estimate.
        consistency_threshold: χ² threshold (3 degrees of freedom) of the score test of the
            recent records against the estimate (None, the default, disables it; e.g. 25 ≈
            the 1.5·10⁻⁵ upper quantile of χ²₃); a failed test marks the element suspect and
            deflates its reported information by ``suspect_deflation`` (see
            :func:`_score_test`).
        consistency_forgetting: memory λ_c ∈ (0, 1) of the recent-records score, per call
            (0.9: about ten calls).
        lm_damping: initial LM damping, relative to the diagonal of the scoring matrix.
        nlos_bearing_weight: weight of bearings flagged NLOS (0: they carry no information).
        min_rcond: observability threshold on det J/(tr J/3)³ of the information matrix J
            (a lower bound of 27 λ_min/λ_max; 1 for isotropic information).
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

    window_rows: int = 0
    forgetting: float = 1.0
    huber_k: float = 1.345
    loss: Literal["huber", "tukey"] = "tukey"
    tukey_c: float = 4.685
    gate_sigma: float | None = None
    gate_max_fraction: float = 0.5
    iterations: int = 1
    init_iterations: int = 10
    suspect_sigma: float = 2.5
    suspect_fraction: float = 0.35
    suspect_deflation: float = 0.1
    recheck_every: int = 5
    recheck_threshold: float = 25.0
    recheck_trust: float = 0.1
    recheck_window_rows: int = 50
    consistency_threshold: float | None = None
    consistency_forgetting: float = 0.9
    lm_damping: float = 1e-3
    nlos_bearing_weight: float = 0.0
    min_rcond: float = 1e-9
    pl_rcond: float = 1e-10
    init_distance_m: float = 100.0
    mirror: Literal["below", "above"] = "below"
    range_cost: Literal["gls", "ml"] = "gls"
    #: Search region of the source (m, ENU): every estimate is projected into this box
    #: (projected Levenberg-Marquardt). Unbounded by default; a mission's ``source.search_box``
    #: sets it (e.g. z in [0, 30] m: an emitter between the ground and the rooftops).
    bounds_min_m: tuple[float, float, float] = (-math.inf, -math.inf, -math.inf)
    bounds_max_m: tuple[float, float, float] = (math.inf, math.inf, math.inf)

    def __post_init__(self) -> None:
        if not (isinstance(self.window_rows, int) and self.window_rows >= 0):
            raise ValueError(f"EstimatorConfig.window_rows: expected an integer >= 0, found {self.window_rows!r}")
        if not (isinstance(self.recheck_window_rows, int) and self.recheck_window_rows >= 0):
            raise ValueError(f"EstimatorConfig.recheck_window_rows: expected an integer >= 0, found {self.recheck_window_rows!r}")
        if not (isinstance(self.recheck_every, int) and self.recheck_every >= 0):
            raise ValueError(f"EstimatorConfig.recheck_every: expected an integer >= 0, found {self.recheck_every!r}")
        for name in ("iterations", "init_iterations"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"EstimatorConfig.{name}: expected an integer >= 1, found {value!r}")
        if not 0.0 < self.forgetting <= 1.0:
            raise ValueError(f"EstimatorConfig.forgetting: expected a value in (0, 1], found {self.forgetting!r}")
        if self.loss not in ("huber", "tukey"):
            raise ValueError(f"EstimatorConfig.loss: expected 'huber' or 'tukey', found {self.loss!r}")
        positive = ("huber_k", "tukey_c", "suspect_sigma", "lm_damping", "min_rcond", "pl_rcond", "init_distance_m", "recheck_threshold")
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"EstimatorConfig.{name}: expected a finite positive number, found {value!r}")
        if self.consistency_threshold is not None and not (math.isfinite(self.consistency_threshold) and self.consistency_threshold > 0.0):
            raise ValueError(f"EstimatorConfig.consistency_threshold: expected None or a positive number, found {self.consistency_threshold!r}")
        if not 0.0 < self.consistency_forgetting < 1.0:
            raise ValueError(f"EstimatorConfig.consistency_forgetting: expected a value in (0, 1), found {self.consistency_forgetting!r}")
        if self.gate_sigma is not None and not (math.isfinite(self.gate_sigma) and self.gate_sigma > 0.0):
            raise ValueError(f"EstimatorConfig.gate_sigma: expected None or a positive number, found {self.gate_sigma!r}")
        if not 0.0 <= self.gate_max_fraction <= 1.0:
            raise ValueError(f"EstimatorConfig.gate_max_fraction: expected a value in [0, 1], found {self.gate_max_fraction!r}")
        for name in ("suspect_fraction", "suspect_deflation", "recheck_trust"):
            value = getattr(self, name)
            if not 0.0 < value <= 1.0:
                raise ValueError(f"EstimatorConfig.{name}: expected a value in (0, 1], found {value!r}")
        if not 0.0 <= self.nlos_bearing_weight <= 1.0:
            raise ValueError(f"EstimatorConfig.nlos_bearing_weight: expected a value in [0, 1], found {self.nlos_bearing_weight!r}")
        if self.range_cost not in ("gls", "ml"):
            raise ValueError(f"EstimatorConfig.range_cost: expected 'gls' or 'ml', found {self.range_cost!r}")
        lo, hi = np.asarray(self.bounds_min_m, dtype=float), np.asarray(self.bounds_max_m, dtype=float)
        if lo.shape != (3,) or hi.shape != (3,) or np.isnan(lo).any() or np.isnan(hi).any() or (lo >= hi).any():
            raise ValueError(
                f"EstimatorConfig.bounds: expected three (min, max) pairs with min < max, found {self.bounds_min_m!r} and {self.bounds_max_m!r}"
            )
        if self.mirror not in ("below", "above"):
            raise ValueError(f"EstimatorConfig.mirror: expected 'below' or 'above', found {self.mirror!r}")

    def clip(self, x: FloatArray) -> FloatArray:
        """Project estimates (..., 3) into the search box."""
        return np.minimum(np.maximum(x, self.bounds_min_m), self.bounds_max_m)


@dataclass(frozen=True)
class EstimatorState:
    """Estimator state for a batch (leading shape ``...``). Treat as immutable.

    Attributes:
        estimate_m: source estimate p̂0, shape (..., 3), metres, ENU; finite everywhere
            (meaningful only where ``initialised``).
        information: Fisher information of all records used, evaluated at the estimate with
            the robust weights, shape (..., 3, 3), m⁻²; zero where not initialised.
        observable: (...,) bool, True where the source is locally identifiable (initialised
            and det J/(tr J/3)³ ≥ ``min_rcond``, J = ``information``).
        initialised: (...,) bool, True once the pseudo-linear system was solvable.
        prior_information: Λ, curvature of the marginalised records' cost, (..., 3, 3), m⁻²
            (their Fisher information in ML mode; in GLS mode without the variance term).
        prior_fisher: Fisher information of the marginalised records, (..., 3, 3), m⁻².
        prior_vector: η, so that their cost is ½xᵀΛx − ηᵀx, shape (..., 3), m⁻¹.
        pl_matrix, pl_vector: pseudo-linear normal equations of every record, (..., 4, 4), (..., 4).
        pl_dropped_matrix, pl_dropped_vector: the same for records that left the window before
            initialisation (they become the prior, R marginalised out, at initialisation).
        pl_range_matrix, pl_range_vector: squared-range PL equations of every range so far,
            weighted at the estimate of their call (the global re-check).
        window: the raw records kept, a :class:`Measurements` of shape (..., window_rows).
        window_weight: their forgetting weights λ^age, (..., window_rows).
        measurement_count: scalar components (range, azimuth, elevation) used so far, (...,).
        suspect: (...,) bool, True where more than ``suspect_fraction`` of the last call's
            components of one type lay beyond ``suspect_sigma`` (a wrong basin, perhaps), or
            where the score test failed: the next call deflates the prior and restarts with
            Huber iterations.
        score_matrix, score_vector: the recent records' scoring matrix S_H (..., 3, 3), m⁻²,
            and S_v (..., 3), m⁻¹, each record linearised at its call's estimate and weighted
            λ_c^age, so that their score at x is ≈ S_H x − S_v (the consistency test).
        consistency: (...,) the score statistic T of the last call (≈ χ²₃ when consistent).
        calls: number of :func:`update` calls so far.
    """

    estimate_m: FloatArray
    information: FloatArray
    observable: BoolArray
    initialised: BoolArray
    prior_information: FloatArray
    prior_fisher: FloatArray
    prior_vector: FloatArray
    pl_matrix: FloatArray
    pl_vector: FloatArray
    pl_dropped_matrix: FloatArray
    pl_dropped_vector: FloatArray
    pl_range_matrix: FloatArray
    pl_range_vector: FloatArray
    range_window: Measurements
    range_window_weight: FloatArray
    window: Measurements
    window_weight: FloatArray
    measurement_count: NDArray[np.int64]
    suspect: BoolArray
    score_matrix: FloatArray
    score_vector: FloatArray
    consistency: FloatArray
    calls: int = 0

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
        prior_fisher=np.zeros(b + (3, 3)),
        prior_vector=np.zeros(b + (3,)),
        pl_matrix=np.zeros(b + (4, 4)),
        pl_vector=np.zeros(b + (4,)),
        pl_dropped_matrix=np.zeros(b + (4, 4)),
        pl_dropped_vector=np.zeros(b + (4,)),
        pl_range_matrix=np.zeros(b + (4, 4)),
        pl_range_vector=np.zeros(b + (4,)),
        range_window=empty_measurements(b, config.recheck_window_rows),
        range_window_weight=np.zeros(b + (config.recheck_window_rows,)),
        window=empty_measurements(b, config.window_rows),
        window_weight=np.zeros(b + (config.window_rows,)),
        measurement_count=np.zeros(b, dtype=np.int64),
        suspect=np.zeros(b, dtype=bool),
        score_matrix=np.zeros(b + (3, 3)),
        score_vector=np.zeros(b + (3,)),
        consistency=np.zeros(b),
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


def _normalised_det(a: FloatArray) -> FloatArray:
    """det(A)/(tr(A)/3)³ of symmetric PSD 3x3 matrices (0 where tr A = 0).

    It lies in [0, 1], equals 1 for A ∝ I, and bounds the conditioning from below:
    det/(tr/3)³ ≤ 27 λ_min λ_mid λ_max/λ_max³ ≤ 27 λ_min/λ_max.
    """
    tr = np.einsum("...ii->...", a) / 3.0
    safe = np.where(tr > 0.0, tr, 1.0)
    return np.where(tr > 0.0, _det3(a) / safe**3, 0.0)


# --------------------------------------------------------------------------- measurement model


def _wrap(angle: FloatArray) -> FloatArray:
    """Wrap an angle difference to [-π, π] (radians)."""
    return angle - (2.0 * np.pi) * np.rint(angle * (0.5 / np.pi))


@dataclass(frozen=True)
class _Rows:
    """Records in component-major layout, NaN replaced by 0 and weight 0 (internal).

    Every array has shape (..., K): drone position (px, py, pz) in m; measured range, azimuth,
    elevation (zr, za, ze); component weights (ar, aa, ae) (0 = unused); σ_r0 of the link (m).
    """

    px: FloatArray
    py: FloatArray
    pz: FloatArray
    zr: FloatArray
    za: FloatArray
    ze: FloatArray
    ar: FloatArray
    aa: FloatArray
    ae: FloatArray
    s0: FloatArray

    def with_weights(self, ar: FloatArray, aa: FloatArray, ae: FloatArray) -> _Rows:
        return _Rows(self.px, self.py, self.pz, self.zr, self.za, self.ze, ar, aa, ae, self.s0)

    def sliced(self, sl: slice) -> _Rows:
        return _Rows(*(getattr(self, f)[..., sl] for f in self.__dataclass_fields__))

    def subset(self, mask: BoolArray) -> _Rows:
        return _Rows(*(getattr(self, f)[mask] for f in self.__dataclass_fields__))


def _rows(meas: Measurements, row_weight: FloatArray, channel: Channel, config: EstimatorConfig) -> _Rows:
    """Component-major rows with weights: ranges ``row_weight``; bearings ``row_weight`` in LOS
    and ``row_weight·nlos_bearing_weight`` when flagged NLOS; 0 where a value is absent."""
    p = meas.positions_m
    px, py, pz = p[..., 0], p[..., 1], p[..., 2]
    row_ok = np.isfinite(px + py + pz)  # NaN/inf in any coordinate
    los = meas.los
    wb = row_weight * np.where(los, 1.0, config.nlos_bearing_weight)

    def present(z: FloatArray, w: FloatArray) -> tuple[FloatArray, FloatArray]:
        ok = row_ok & np.isfinite(z)
        return np.where(ok, z, 0.0), np.where(ok, w, 0.0)

    zr, ar = present(meas.range_m, row_weight)
    za, aa = present(meas.azimuth_rad, wb)
    ze, ae = present(meas.elevation_rad, wb)
    s0 = channel.sigma_r0(los)
    return _Rows(np.where(row_ok, px, 0.0), np.where(row_ok, py, 0.0), np.where(row_ok, pz, 0.0), zr, za, ze, ar, aa, ae, s0)


@dataclass(frozen=True)
class _Eval:
    """Robust cost of the rows at one source position and the per-row factors from which its
    gradient and scoring matrix are summed (internal; arrays (..., K))."""

    cost: FloatArray  # (...,) summed over rows
    rx: FloatArray
    ry: FloatArray
    rz: FloatArray
    rho2: FloatArray
    # gradient factors: g = Σ [gA r + gB v + gC w], v = (−r_y, r_x, 0), w = (−r_x r_z, −r_y r_z, ρ²)
    gA: FloatArray
    gB: FloatArray
    gC: FloatArray
    # scoring factors: H = Σ [hA r rᵀ + hB v vᵀ + hC w wᵀ]; Fisher adds hF r rᵀ
    hA: FloatArray
    hB: FloatArray
    hC: FloatArray
    hF: FloatArray
    d: FloatArray
    # component weights actually used (after the innovation gate)
    ar: FloatArray
    aa: FloatArray
    ae: FloatArray
    # per element and component type (range, azimuth, elevation), (..., 3): weighted count of
    # the components used, and of those with |e| beyond ``suspect_sigma``
    n_used: FloatArray
    n_big: FloatArray


@dataclass(frozen=True)
class _Gate:
    """Innovation gate (internal): a bound on the variance of the previous estimate along any
    direction (tr Σ, m², shape (...,)), where to apply it (...,), the threshold in σ, and the
    largest gated fraction allowed per element."""

    var_bound_m2: FloatArray
    use: BoolArray
    sigma: float
    max_fraction: float


# The evaluation (cost_only False) or the cost alone (cost_only True): the return type follows.
@overload
def _evaluate(
    x: FloatArray,
    rows: _Rows,
    channel: Channel,
    k: float,
    ml: bool,
    d_var: FloatArray | None = None,
    gate: _Gate | None = None,
    cost_only: Literal[False] = False,
    redescend: bool | BoolArray = False,
    tukey_c: float = 4.685,
    suspect_sigma: float = 2.5,
) -> _Eval: ...
@overload
def _evaluate(
    x: FloatArray,
    rows: _Rows,
    channel: Channel,
    k: float,
    ml: bool,
    d_var: FloatArray | None = None,
    gate: _Gate | None = None,
    *,
    cost_only: Literal[True],
    redescend: bool | BoolArray = False,
    tukey_c: float = 4.685,
    suspect_sigma: float = 2.5,
) -> FloatArray: ...
def _evaluate(
    x: FloatArray,
    rows: _Rows,
    channel: Channel,
    k: float,
    ml: bool,
    d_var: FloatArray | None = None,
    gate: _Gate | None = None,
    cost_only: bool = False,
    redescend: bool | BoolArray = False,
    tukey_c: float = 4.685,
    suspect_sigma: float = 2.5,
) -> _Eval | FloatArray:
    r"""Robust negative log-likelihood of the rows at source ``x`` (..., 3) and its terms.

    Per component, with e = (z − h)/σ, robust loss ρ, ψ = ρ', w = ψ/e (:func:`_loss`: Huber
    with threshold k, or Tukey's biweight with threshold ``tukey_c`` where ``redescend``):

    .. math::
        C = \sum_i a_i\big[\rho(e_i) + [\text{ML, range}]\tfrac12\ln\sigma_{r,i}^2\big],\qquad
        \nabla C_i = -a\,\psi(e)\,\nabla h/\sigma
            + [\text{ML, range}]\,a\tfrac{\gamma}{2d}(1 - w e^2)\nabla d,

        I_i = a\,\nabla h\nabla h^T\big(w/\sigma^2 + [\text{range}]\,\gamma^2/(2d^2)\big)

    with ∇d = r/d, ∇φ = (−r_y, r_x, 0)/ρ², ∇θ = (−r_x r_z, −r_y r_z, ρ²)/(d²ρ), ρ the
    horizontal distance, σ_r = σ_r0 d^{γ/2} (eq. 5), σ_b constant. The γ²/(2d²) term is
    ∇σ²∇σ²ᵀ/(2σ⁴) (eq. 12's A_d): it enters the scoring matrix in ML mode and the reported
    Fisher information always. In GLS mode σ_r is evaluated at ``d_var`` if given.

    ``gate``: components whose innovation exceeds ``gate.sigma`` standard deviations of
    σ² + tr(Σ)‖∇h‖² (a bound on σ² + ∇hᵀΣ∇h) get weight 0, where ``gate.use`` and at most
    ``gate.max_fraction`` of the element's components are gated. ``cost_only``: return the
    summed cost (...,) only.
    """
    rx = x[..., 0, None] - rows.px
    ry = x[..., 1, None] - rows.py
    rz = x[..., 2, None] - rows.pz
    rho2 = rx * rx
    rho2 += ry * ry
    np.maximum(rho2, _RHO2_FLOOR_M2, out=rho2)
    rho = np.sqrt(rho2)
    d2 = rz * rz
    d2 += rho2
    d = np.sqrt(d2)
    gamma = channel.gamma
    dv = d if d_var is None else d_var
    sr = rows.s0 * (dv if gamma == 2.0 else dv ** (0.5 * gamma))
    inv_sr = 1.0 / sr
    inv_sb = 1.0 / channel.sigma_bearing_rad
    er = rows.zr - d
    er *= inv_sr
    ea = _wrap(rows.za - np.arctan2(ry, rx))
    ea *= inv_sb
    ee = rows.ze - np.arctan2(rz, rho)
    ee *= inv_sb
    ar, aa, ae = rows.ar, rows.aa, rows.ae
    if gate is not None:
        g2 = gate.sigma * gate.sigma
        tv = gate.var_bound_m2[..., None]
        tb = tv * (inv_sb * inv_sb)
        out_r = (er * er > g2 * (1.0 + tv * inv_sr * inv_sr)) & (ar > 0.0)
        out_a = (ea * ea > g2 * (1.0 + tb / rho2)) & (aa > 0.0)
        out_e = (ee * ee > g2 * (1.0 + tb / d2)) & (ae > 0.0)
        n_out = out_r.sum(axis=-1) + out_a.sum(axis=-1) + out_e.sum(axis=-1)
        n_all = (ar > 0.0).sum(axis=-1) + (aa > 0.0).sum(axis=-1) + (ae > 0.0).sum(axis=-1)
        apply = (gate.use & (n_out <= gate.max_fraction * n_all))[..., None]
        if np.any(apply):
            ar = np.where(out_r & apply, 0.0, ar)
            aa = np.where(out_a & apply, 0.0, aa)
            ae = np.where(out_e & apply, 0.0, ae)
    rr_, pr_, wr_ = _loss(er, k, tukey_c, redescend)
    ra_, pa_, wa_ = _loss(ea, k, tukey_c, redescend)
    re_, pe_, we_ = _loss(ee, k, tukey_c, redescend)
    cr = ar * rr_
    if ml:
        cr += ar * np.log(sr)
    cost = np.einsum("...k,...k->...", aa, ra_)
    cost += np.einsum("...k,...k->...", ae, re_)
    cost += cr.sum(axis=-1)
    if cost_only:
        return cost
    inv_d = 1.0 / d
    inv_rho = 1.0 / rho
    inv_d2 = inv_d * inv_d
    inv_rho2 = inv_rho * inv_rho
    sb2inv = inv_sb * inv_sb
    wr = ar * inv_sr
    ir = wr * inv_sr * wr_
    ia = aa * sb2inv * wa_
    ie = ae * sb2inv * we_
    gr = -wr * pr_
    ga = (aa * -inv_sb) * pa_
    ge = (ae * -inv_sb) * pe_
    gd = (0.5 * gamma) / dv
    extra = ar * (2.0 * gd * gd)
    if ml:
        gr += ar * gd * (1.0 - pr_ * er)
        ir += extra
        extra = np.zeros_like(extra)
    # Weighted counts (weights are 0 or λ^age ≤ 1): used components and those beyond the
    # suspect threshold, per type.
    c2 = suspect_sigma * suspect_sigma
    n_used = np.stack((ar.sum(axis=-1), aa.sum(axis=-1), ae.sum(axis=-1)), axis=-1)
    n_big = np.stack((_sum(ar, er * er > c2), _sum(aa, ea * ea > c2), _sum(ae, ee * ee > c2)), axis=-1)
    return _Eval(
        cost=cost,
        rx=rx,
        ry=ry,
        rz=rz,
        rho2=rho2,
        gA=gr * inv_d,
        gB=ga * inv_rho2,
        gC=ge * (inv_d2 * inv_rho),
        hA=ir * inv_d2,
        hB=ia * (inv_rho2 * inv_rho2),
        hC=ie * (inv_d2 * inv_d2 * inv_rho2),
        hF=extra * inv_d2,
        d=d,
        ar=ar,
        aa=aa,
        ae=ae,
        n_used=n_used,
        n_big=n_big,
    )


def _loss(e: FloatArray, k: float, c: float, redescend: bool | BoolArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Robust loss ρ(e), influence ψ(e) = ρ'(e) and IRLS weight w = ψ/e of normalised residuals.

    Huber (threshold k): ρ = e²/2 for |e| ≤ k, k|e| − k²/2 beyond; ψ = clip(e, −k, k).
    Tukey's biweight (threshold c), where ``redescend`` ((...,) or scalar): with
    u = min(e²/c², 1), ρ = c²/6 (1 − (1 − u)³), w = (1 − u)², ψ = w e (no influence beyond c).
    """

    def huber() -> tuple[FloatArray, FloatArray, FloatArray]:
        ae = np.abs(e)
        m = np.minimum(ae, k)
        return m * (ae - 0.5 * m), np.maximum(np.minimum(e, k), -k), k / np.maximum(ae, k)

    def tukey() -> tuple[FloatArray, FloatArray, FloatArray]:
        t = 1.0 - np.minimum(e * e * (1.0 / (c * c)), 1.0)
        w = t * t
        return (c * c / 6.0) * (1.0 - w * t), w * e, w

    if isinstance(redescend, bool) or np.ndim(redescend) == 0:
        return tukey() if bool(redescend) else huber()
    if np.all(redescend):
        return tukey()
    if not np.any(redescend):
        return huber()
    sel = np.asarray(redescend)[..., None]
    (t_rho, t_psi, t_w), (h_rho, h_psi, h_w) = tukey(), huber()
    return np.where(sel, t_rho, h_rho), np.where(sel, t_psi, h_psi), np.where(sel, t_w, h_w)


def _sum(a: FloatArray, b: FloatArray | BoolArray) -> FloatArray:
    return np.einsum("...k,...k->...", a, b)


def _accumulate(ev: _Eval, sl: slice | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Gradient (..., 3), scoring matrix and Fisher information (..., 3, 3), summed over the
    rows (``sl`` of them).

    With v = (−r_y, r_x, 0) and w = (−r_x r_z, −r_y r_z, ρ²): g = Σ gA r + gB v + gC w,
    H = Σ hA r rᵀ + hB v vᵀ + hC w wᵀ, F = H + Σ hF r rᵀ; written entry by entry to avoid
    (..., K, 3, 3) temporaries.
    """
    if sl is None:
        sl = slice(None)
    rx, ry, rz, rho2 = ev.rx[..., sl], ev.ry[..., sl], ev.rz[..., sl], ev.rho2[..., sl]
    gA, gB, gC = ev.gA[..., sl], ev.gB[..., sl], ev.gC[..., sl]
    hA, hB, hC, hF = ev.hA[..., sl], ev.hB[..., sl], ev.hC[..., sl], ev.hF[..., sl]
    t = gA - gC * rz
    g = np.stack((_sum(rx, t) - _sum(gB, ry), _sum(ry, t) + _sum(gB, rx), _sum(gA, rz) + _sum(gC, rho2)), axis=-1)
    rzz = rz * rz
    hCrzz = hC * rzz
    q1 = hA + hCrzz
    q2 = hA - hC * rho2
    rxx, ryy, rxy = rx * rx, ry * ry, rx * ry
    rxz, ryz = rx * rz, ry * rz
    hxx = _sum(rxx, q1) + _sum(ryy, hB)
    hyy = _sum(ryy, q1) + _sum(rxx, hB)
    hxy = _sum(rxy, q1 - hB)
    hzz = _sum(rzz, hA) + _sum(rho2 * rho2, hC)
    hxz = _sum(rxz, q2)
    hyz = _sum(ryz, q2)
    H = np.stack((hxx, hxy, hxz, hxy, hyy, hyz, hxz, hyz, hzz), axis=-1).reshape(hxx.shape + (3, 3))
    fxx, fyy, fzz = _sum(rxx, hF), _sum(ryy, hF), _sum(rzz, hF)
    fxy, fxz, fyz = _sum(rxy, hF), _sum(rxz, hF), _sum(ryz, hF)
    F = H + np.stack((fxx, fxy, fxz, fxy, fyy, fyz, fxz, fyz, fzz), axis=-1).reshape(hxx.shape + (3, 3))
    return g, H, F


def _prior_cost(x: FloatArray, lam: FloatArray, eta: FloatArray) -> FloatArray:
    """½ xᵀΛx − ηᵀx, (...,)."""
    return 0.5 * np.einsum("...i,...ij,...j->...", x, lam, x) - np.einsum("...i,...i->...", eta, x)


# --------------------------------------------------------------------------- pseudo-linear part


def _pl_rows(rows: _Rows, scale_d: FloatArray, channel: Channel) -> tuple[FloatArray, FloatArray]:
    """Pseudo-linear normal equations of the rows (..., K), summed: A (..., 4, 4), b (..., 4).

    Unknown θ = (x0, y0, z0, R = ‖p0‖²). Equations cᵀθ = β with weight ω, all linear in θ:

    * azimuth: (sin φ̂, −cos φ̂, 0)·(p0 − p) = 0, ω = a/(σ_b² (D cos θ̂)²);
    * elevation (with an azimuth): (−sin θ̂ cos φ̂, −sin θ̂ sin φ̂, cos θ̂)·(p0 − p) = 0,
      ω = a/(σ_b² D²);
    * range with a usable bearing u(φ̂, θ̂): uᵀ(p0 − p) = d̂, ω = a/σ_r²(D);
    * range alone: 2pᵀp0 − R = ‖p‖² − d̂² + σ_r²(D), ω = a/(4 D² σ_r²(D)) (the σ_r² term
      removes the bias E[d̂²] = d² + σ_r²; without it, 39 % ranging noise biases R).

    D = ``scale_d`` (..., K) is the distance used in the weights (see :func:`update`); it never
    depends on the row's own noisy range.
    """
    px, py, pz = rows.px, rows.py, rows.pz
    has_r = rows.ar > 0.0
    has_az = rows.aa > 0.0
    has_b = has_az & (rows.ae > 0.0)
    inv_sb2 = 1.0 / channel.sigma_bearing_rad**2
    D = scale_d
    var_r = rows.s0 * rows.s0 * (D * D if channel.gamma == 2.0 else D**channel.gamma)
    cphi, sphi = np.cos(rows.za), np.sin(rows.za)
    cth, sth = np.cos(rows.ze), np.sin(rows.ze)
    zero = np.zeros_like(px)
    rho_w2 = np.maximum(D * D * cth * cth, 1e-6 * D * D)
    w_az = np.where(has_az, rows.aa * inv_sb2 / rho_w2, 0.0)
    w_el = np.where(has_b, rows.ae * inv_sb2 / (D * D), 0.0)
    w_ru = np.where(has_r & has_b, rows.ar / var_r, 0.0)
    w_rr = np.where(has_r & ~has_b, rows.ar / (4.0 * D * D * var_r), 0.0)
    # Equations stacked along the last axis: (..., 4K).
    ux, uy = cth * cphi, cth * sphi
    c0 = np.concatenate((sphi, -sth * cphi, ux, 2.0 * px), axis=-1)
    c1 = np.concatenate((-cphi, -sth * sphi, uy, 2.0 * py), axis=-1)
    c2 = np.concatenate((zero, cth, sth, 2.0 * pz), axis=-1)
    c3 = np.concatenate((zero, zero, zero, zero - 1.0), axis=-1)
    b_az = sphi * px - cphi * py
    b_el = cth * pz - sth * (cphi * px + sphi * py)
    b_ru = ux * px + uy * py + sth * pz + rows.zr
    # E[d̂²] = d² + σ_r²(d): subtract σ_r²(D) so the squared-range equation is unbiased.
    b_rr = px * px + py * py + pz * pz - rows.zr * rows.zr + var_r
    beta = np.concatenate((b_az, b_el, b_ru, b_rr), axis=-1)
    om = np.concatenate((w_az, w_el, w_ru, w_rr), axis=-1)
    cs = (c0, c1, c2, c3)
    wc = [om * c for c in cs]
    A = np.empty(px.shape[:-1] + (4, 4))
    for i in range(4):
        for j in range(i, 4):
            A[..., i, j] = A[..., j, i] = _sum(wc[i], cs[j])
    b = np.stack([_sum(wc[i], beta) for i in range(4)], axis=-1)
    return A, b


def _pl_range_rows(rows: _Rows, scale_d: FloatArray, gamma: float) -> tuple[FloatArray, FloatArray]:
    """Squared-range pseudo-linear equations of every range in ``rows`` (with or without a
    bearing), summed: A (..., 4, 4), b (..., 4); 2pᵀp0 − R = ‖p‖² − d̂² + σ_r²(D),
    ω = a/(4D²σ_r²(D)).
    No trigonometry: cheap enough to accumulate at every call for the global re-check."""
    px, py, pz = rows.px, rows.py, rows.pz
    D2 = scale_d * scale_d
    var_r = rows.s0 * rows.s0 * (D2 if gamma == 2.0 else scale_d**gamma)
    om = rows.ar / (4.0 * D2 * var_r)
    cs = (2.0 * px, 2.0 * py, 2.0 * pz)
    beta = px * px + py * py + pz * pz - rows.zr * rows.zr + var_r  # E[d̂²] = d² + σ_r²
    wc = [om * c for c in cs]
    A = np.empty(px.shape[:-1] + (4, 4))
    for i in range(3):
        for j in range(i, 3):
            A[..., i, j] = A[..., j, i] = _sum(wc[i], cs[j])
        A[..., i, 3] = A[..., 3, i] = -wc[i].sum(axis=-1)
    A[..., 3, 3] = om.sum(axis=-1)
    b = np.stack((_sum(wc[0], beta), _sum(wc[1], beta), _sum(wc[2], beta), -_sum(om, beta)), axis=-1)
    return A, b


def _pl_cost(A: FloatArray, b: FloatArray, x: FloatArray) -> FloatArray:
    """Pseudo-linear cost θᵀAθ − 2bᵀθ at θ = (x, ‖x‖²) (up to a constant), (...,)."""
    theta = np.concatenate((x, np.einsum("...i,...i->...", x, x)[..., None]), axis=-1)
    return np.einsum("...i,...ij,...j->...", theta, A, theta) - 2.0 * np.einsum("...i,...i->...", b, theta)


def _distance_scale(rows: _Rows, config: EstimatorConfig) -> FloatArray:
    """Distance scale D (..., K) of the PL weights: the median measured range of the element's
    rows, or ``config.init_distance_m`` where it has none (m)."""
    z = np.where(rows.ar > 0.0, np.abs(rows.zr), np.nan)
    has = np.any(rows.ar > 0.0, axis=-1)
    med = np.nanmedian(np.where(has[..., None], z, 1.0), axis=-1)
    scale = np.where(has, np.maximum(med, 1.0), config.init_distance_m)
    return np.broadcast_to(scale[..., None], rows.zr.shape)


def _range_scale(x: FloatArray, initialised: BoolArray, rows: _Rows, config: EstimatorConfig) -> FloatArray:
    """Distance scale D (..., K) of the re-check's squared-range weights: |x − p| at the
    estimate x (..., 3) where the element is initialised, else the median measured range of
    the rows (:func:`_distance_scale`)."""
    rx = x[..., 0, None] - rows.px
    ry = x[..., 1, None] - rows.py
    rz = x[..., 2, None] - rows.pz
    scale = np.sqrt(np.maximum(rx * rx + ry * ry + rz * rz, 1.0))
    if not np.all(initialised):
        scale = scale.copy()
        scale[~initialised] = _distance_scale(rows.subset(~initialised), config)
    return scale


def _pl_solve(A: FloatArray, b: FloatArray, config: EstimatorConfig) -> tuple[FloatArray, BoolArray]:
    """Solve the pseudo-linear normal equations (n, 4, 4), (n, 4) -> p0 (n, 3), ok (n,).

    Without range-only equations R is decoupled and the 3x3 block is solved (ok if full rank).
    With them, the candidates are the weighted LS solution θ_LS (if full rank) and the two
    points of the line θ_LS + t v along the weakest direction v that satisfy R = ‖p0‖²
    (Cheung et al. 2004, constrained LS; for ranges from coplanar positions v is the null
    direction and the two points are mirror images). The candidate of lowest constrained PL
    cost θᵀAθ − 2bᵀθ, θ = (p0, ‖p0‖²), is returned; near-ties between the two roots are
    broken by ``config.mirror``.
    """
    n = A.shape[0]
    if n == 0:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    A0, b0 = A, b
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
    full = rank == 4
    cost_ls = np.where(full, _pl_cost(A0, b0, x), np.inf)
    # Constrained roots along the weakest direction (its R component must be significant).
    v = V[:, :, 0] * s
    along = has_R & (rank >= 3) & (np.abs(V[:, 3, 0]) > 1e-6)
    vp, vr = v[:, :3], v[:, 3]
    qa = np.einsum("ni,ni->n", vp, vp)
    qb = 2.0 * np.einsum("ni,ni->n", x, vp) - vr
    qc = np.einsum("ni,ni->n", x, x) - theta[:, 3]
    disc = qb * qb - 4.0 * qa * qc
    # No real root (noise, or the bias correction): use |disc|, two points symmetric about
    # the vertex, rather than the vertex itself (for coplanar drones, a saddle on their plane).
    sq = np.sqrt(np.abs(disc))
    safe_qa = np.where(qa > 1e-300, qa, 1.0)
    along &= qa > 1e-300
    x1 = x + ((-qb - sq) / (2.0 * safe_qa))[:, None] * vp
    x2 = x + ((-qb + sq) / (2.0 * safe_qa))[:, None] * vp
    c1 = np.where(along, _pl_cost(A0, b0, x1), np.inf)
    c2 = np.where(along, _pl_cost(A0, b0, x2), np.inf)
    finite = np.isfinite(c1) & np.isfinite(c2)
    c1f, c2f = np.where(finite, c1, 0.0), np.where(finite, c2, 0.0)
    tie = finite & (np.abs(c1f - c2f) <= 1e-9 * (np.abs(c1f) + 1.0))
    prefer1 = (x1[:, 2] <= x2[:, 2]) if config.mirror == "below" else (x1[:, 2] >= x2[:, 2])
    first = np.where(tie, prefer1, c1 < c2)
    x_root = np.where(first[:, None], x1, x2)
    c_root = np.where(first, c1, c2)
    use_root = along & (c_root < cost_ls)
    x = np.where(use_root[:, None], x_root, x)
    ok = (full & has_R) | use_root | (no_r & (rank == 4))
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
        raise ValueError(f"Measurements.positions_m: expected shape {batch_shape + ('M', 3)}, found {p.shape}")
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


def _scatter(a: NDArray, b: NDArray, sel: BoolArray) -> NDArray:
    """A copy of ``a`` with ``a[sel] = b``."""
    out = np.array(a, copy=True)
    out[sel] = b
    return out


def _lm_iterations(
    x: FloatArray,
    mu: FloatArray,
    rows: _Rows,
    ev: _Eval | None,
    prior_info: FloatArray,
    prior_vec: FloatArray,
    active: BoolArray,
    its: range,
    redescend: Callable[[int], bool | BoolArray],
    channel: Channel,
    config: EstimatorConfig,
) -> tuple[FloatArray, FloatArray, _Eval, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Levenberg-Marquardt (Fisher scoring) iterations ``its`` of the robust cost plus the prior
    ½xᵀΛx − ηᵀx, for a batch of source positions x (..., 3), m, ENU.

    ``ev``: the evaluation at x for the first iteration (None: evaluate here). ``redescend(it)``:
    where Tukey's loss applies at iteration it. Each step is capped at half the mean distance
    to the records and projected into the search box; it is kept only if the cost does not
    increase (then the damping μ shrinks by 3, else it grows by 4).

    Returns:
        x, μ, the evaluation at the last iterate x_lin, the gradient g (m⁻¹), scoring matrix H
        and Fisher information F (m⁻²) there (prior included in g and H, not in F), and x_lin.
    """
    k = config.huber_k
    ml = config.range_cost == "ml"
    c = config.tukey_c
    x_lin = x
    g = H = F = None
    for it in its:
        rd = redescend(it)
        if ev is None:
            ev = _evaluate(x, rows, channel, k, ml, redescend=rd, tukey_c=c, suspect_sigma=config.suspect_sigma)
        x_lin = x
        g, H, F = _accumulate(ev)
        g = g + np.einsum("...ij,...j->...i", prior_info, x) - prior_vec
        H = H + prior_info
        cost = ev.cost + _prior_cost(x, prior_info, prior_vec)
        dH = np.einsum("...ii->...i", H)
        tr = dH.sum(axis=-1)
        Hd = H + (mu[..., None] * dH + 1e-12 * tr[..., None] + 1e-300)[..., None] * np.eye(3)
        Hinv, ok = _inv3_spd(Hd)
        step = -np.einsum("...ij,...j->...i", Hinv, g)
        # Trust region: a step at most half the mean distance to the records (angles are
        # linear only for steps small against the range; far from the data the robust cost
        # is nearly flat and an unbounded step could run away).
        n_w = np.maximum(ev.n_used.sum(axis=-1), 1e-300)
        reach = 0.5 * np.einsum("...k,...k->...", ev.d, ev.ar + ev.aa + ev.ae) / n_w
        norm = np.sqrt(np.einsum("...i,...i->...", step, step))
        shrink = np.where(norm > reach, reach / np.maximum(norm, 1e-300), 1.0)
        cand = config.clip(x + np.where((ok & active)[..., None], step * shrink[..., None], 0.0))
        c_new = _evaluate(cand, rows, channel, k, ml, d_var=None if ml else ev.d, cost_only=True, redescend=rd, tukey_c=c)
        c_new = c_new + _prior_cost(cand, prior_info, prior_vec)
        accept = np.isfinite(c_new) & (c_new <= cost) & active
        x = np.where(accept[..., None], cand, x)
        mu = np.where(accept, mu / 3.0, mu * 4.0)
        last, ev = ev, None
    if g is None or H is None or F is None:
        raise ValueError(f"its: expected at least one iteration, found {its!r}")
    return x, mu, last, g, H, F, x_lin


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
    if state.range_window.count != config.recheck_window_rows:
        raise ValueError(
            f"EstimatorState: range window has {state.range_window.count} rows, config.recheck_window_rows is {config.recheck_window_rows}"
        )
    new = _check(measurements, bshape)
    lam = config.forgetting
    M = new.count

    # Forgetting, then all rows: window first (oldest), new last.
    # A suspect element (see EstimatorState.suspect) keeps a deflated prior.
    deflate = np.where(state.suspect, lam * config.suspect_deflation, lam)
    prior_info = state.prior_information * deflate[..., None, None]
    prior_fisher = state.prior_fisher * deflate[..., None, None]
    prior_vec = state.prior_vector * deflate[..., None]
    pl_A = state.pl_matrix * lam
    pl_b = state.pl_vector * lam
    dr_A = state.pl_dropped_matrix * lam
    dr_b = state.pl_dropped_vector * lam
    new_row_ok = np.isfinite(new.positions_m.sum(axis=-1))  # NaN/inf in any coordinate
    if W > 0:
        allm = _concat(state.window, new)
        weight = np.concatenate((state.window_weight * lam, np.where(new_row_ok, 1.0, 0.0)), axis=-1)
        if M > 0:
            # Keep the most recent valid rows at the end (stable: by validity, then by age).
            valid = np.concatenate((np.isfinite(state.window.positions_m[..., 0]), new_row_ok), axis=-1)
            order = np.argsort(valid, axis=-1, kind="stable")
            allm = _take(allm, order)
            weight = np.take_along_axis(weight, order, axis=-1)
    else:
        allm, weight = new, np.where(new_row_ok, 1.0, 0.0)
    rows = _rows(allm, weight, channel, config)
    K = W + M
    n_leave = K - W  # = M: the oldest M rows leave the window after this call
    new_rows = rows.sliced(slice(K - M, K)) if W == 0 else _rows(new, np.where(new_row_ok, 1.0, 0.0), channel, config)

    x_prev = state.estimate_m
    initialised = state.initialised
    x = x_prev
    todo = ~initialised
    long_run = np.zeros(bshape, dtype=bool)  # elements that get init_iterations this call
    fresh_start = state.suspect & state.initialised  # initialised, moved or suspect
    if M > 0 and np.any(todo):
        # Pseudo-linear equations of the new records (only needed until initialisation).
        sub = new_rows.subset(todo)
        A_new, b_new = _pl_rows(sub, _distance_scale(sub, config), channel)
        pl_A = pl_A.copy()
        pl_b = pl_b.copy()
        pl_A[todo] += A_new
        pl_b[todo] += b_new
        x_init, ok = _pl_solve(pl_A[todo], pl_b[todo], config)
        just = np.zeros(bshape, dtype=bool)
        just[todo] = ok
        x = x.copy()
        x[just] = config.clip(x_init[ok])
        # Records dropped before initialisation become the prior (R marginalised out).
        lam_d, eta_d = _schur_prior(dr_A, dr_b)
        prior_info = np.where(just[..., None, None], lam_d, prior_info)
        prior_fisher = np.where(just[..., None, None], lam_d, prior_fisher)
        prior_vec = np.where(just[..., None], eta_d, prior_vec)
        initialised = initialised | just
        fresh_start = fresh_start | just
        long_run = long_run | just
    # Global re-check (every recheck_every calls): the squared-range PL solution of all past
    # ranges against the current estimate; move there when the PL cost drops by more than the
    # threshold AND the new records prefer it.
    pr_A = state.pl_range_matrix * lam
    pr_b = state.pl_range_vector * lam
    range_weight = state.range_window_weight * lam
    if config.recheck_every > 0 and M > 0 and (state.calls + 1) % config.recheck_every == 0 and np.any(state.initialised):
        # The re-check's system: the summary plus the ranges still waiting in the range
        # window, weighted at the previous estimate.
        pend = _rows(state.range_window, range_weight, channel, config)
        A_p, b_p = _pl_range_rows(pend, _range_scale(x_prev, state.initialised, pend, config), channel.gamma)
        sys_A, sys_b = pr_A + A_p, pr_b + b_p
    else:
        sys_A, sys_b = pr_A, pr_b
    recheck = state.initialised & (np.einsum("...ii->...", sys_A) > 0.0)
    if config.recheck_every > 0 and M > 0 and (state.calls + 1) % config.recheck_every == 0 and np.any(recheck):
        x_pl, ok = _pl_solve(sys_A[recheck], sys_b[recheck], config)
        cand = x_prev.copy()
        cand[recheck] = config.clip(np.where(ok[:, None], x_pl, x_prev[recheck]))
        drop = _pl_cost(sys_A, sys_b, x_prev) - _pl_cost(sys_A, sys_b, cand)
        fresh = new_rows.with_weights(
            np.where(initialised[..., None], new_rows.ar, 0.0),
            np.where(initialised[..., None], new_rows.aa, 0.0),
            np.where(initialised[..., None], new_rows.ae, 0.0),
        )
        # The fresh records judge with the full likelihood (½ ln σ_r² included): comparing
        # distant candidates with σ_r evaluated at each would favour the farther one.
        c_prev = _evaluate(x_prev, fresh, channel, config.huber_k, True, cost_only=True)
        c_cand = _evaluate(cand, fresh, channel, config.huber_k, True, cost_only=True)
        move = recheck & (drop > config.recheck_threshold) & (c_cand < c_prev)
        if np.any(move):
            # The prior linearised in the other basin is replaced by the PL summary of the
            # ranges (R marginalised out); the past bearings' information is dropped.
            lam_r, eta_r = _schur_prior(sys_A, sys_b)
            x = np.where(move[..., None], cand, x)
            prior_info = np.where(move[..., None, None], lam_r, prior_info)
            # Claimed information after a move: only ``recheck_trust`` of the PL summary (the
            # squared-range PL solution can be biased, e.g. by NLOS ranges; the records that
            # follow rebuild the information at the new estimate).
            prior_fisher = np.where(move[..., None, None], lam_r * config.recheck_trust, prior_fisher)
            prior_vec = np.where(move[..., None], eta_r, prior_vec)
            fresh_start = fresh_start | move
            long_run = long_run | move
    active = initialised
    if not np.all(active):
        act = active[..., None]
        rows = rows.with_weights(np.where(act, rows.ar, 0.0), np.where(act, rows.aa, 0.0), np.where(act, rows.ae, 0.0))

    # Innovation gate against the previous state, applied in the first evaluation.
    gate = None
    if config.gate_sigma is not None and np.any(state.observable):
        J = state.information
        det = _det3(J)
        # tr(J⁻¹) = tr(adj J)/det J ≥ the variance of the estimate along any direction.
        tr_adj = (
            J[..., 1, 1] * J[..., 2, 2]
            - J[..., 1, 2] ** 2
            + J[..., 0, 0] * J[..., 2, 2]
            - J[..., 0, 2] ** 2
            + J[..., 0, 0] * J[..., 1, 1]
            - J[..., 0, 1] ** 2
        )
        use = state.observable & state.initialised & (det > 0.0)
        var_bound = np.where(use, tr_adj / np.where(use, det, 1.0), 0.0)
        gate = _Gate(var_bound, use, config.gate_sigma, config.gate_max_fraction)

    # Levenberg-Marquardt (Fisher scoring) iterations, all elements at once. Each element runs
    # its own number of iterations (``iterations``, or ``init_iterations`` in a call where it is
    # initialised or moved), whatever the rest of the batch does: a batch element computes
    # exactly what the same records give with batch shape () (simulator = planner node).
    k = config.huber_k
    ml = config.range_cost == "ml"
    run = bool(np.any(active)) and K > 0
    n_short = config.iterations
    n_long = max(config.iterations, config.init_iterations)
    # Loss schedule (config.loss == "tukey"): Tukey's biweight for settled elements; after a
    # PL initialisation, Huber for the first half of the iterations, then Tukey; for a
    # suspect or moved element, Huber for the whole call (Tukey's cost is flat far from the
    # data, Huber's still points back to it).
    tukey = config.loss == "tukey"
    c = config.tukey_c
    init_before = state.initialised

    def redescend(it: int, fresh: BoolArray, before: BoolArray, n_el: NDArray[np.int64]) -> bool | BoolArray:
        if not tukey:
            return False
        if not np.any(fresh):
            return True
        return ~fresh | ((2 * it >= n_el) & ~before)

    n_elem = np.where(long_run, n_long, n_short)
    ev = _evaluate(
        x,
        rows,
        channel,
        k,
        ml,
        gate=gate,
        redescend=redescend(0, fresh_start, init_before, n_elem),
        tukey_c=c,
        suspect_sigma=config.suspect_sigma,
    )
    rows = rows.with_weights(ev.ar, ev.aa, ev.ae)
    if run:
        mu = np.full(bshape, config.lm_damping)
        x, mu, ev, g, H, F, x_lin = _lm_iterations(
            x,
            mu,
            rows,
            ev,
            prior_info,
            prior_vec,
            active,
            range(n_short),
            lambda it: redescend(it, fresh_start, init_before, n_elem),
            channel,
            config,
        )
        sel = active & (n_elem > n_short)
        if n_long > n_short and np.any(sel):
            # The elements that need more iterations continue alone (batch subset).
            fs, ib, ne = fresh_start[sel], init_before[sel], n_elem[sel]
            xs, _, evs, gs, Hs, Fs, xls = _lm_iterations(
                x[sel],
                mu[sel],
                rows.subset(sel),
                None,
                prior_info[sel],
                prior_vec[sel],
                np.ones(ne.shape, dtype=bool),
                range(n_short, n_long),
                lambda it: redescend(it, fs, ib, ne),
                channel,
                config,
            )
            x, g, H, F, x_lin = (_scatter(a, b, sel) for a, b in ((x, xs), (g, gs), (H, Hs), (F, Fs), (x_lin, xls)))
            ev = _Eval(**{f: _scatter(getattr(ev, f), getattr(evs, f), sel) for f in _Eval.__dataclass_fields__})
    else:
        x_lin = x
        g, H, F = _accumulate(ev)
        g = g + np.einsum("...ij,...j->...i", prior_info, x) - prior_vec
        H = H + prior_info
    prior_info_used, prior_vec_used = prior_info, prior_vec
    # Information of everything used, linearised at x_lin (the last iterate evaluated).
    fisher = F + prior_fisher
    suspect = active & np.any((ev.n_used >= 2.5) & (ev.n_big > config.suspect_fraction * ev.n_used), axis=-1)
    # Marginalise the rows leaving the window (the oldest n_leave), linearised at x_lin:
    # their cost ≈ ½ xᵀH_l x − (H_l x_lin − g_l)ᵀx + const.
    if n_leave > 0:
        if n_leave == K:
            gl = g - (np.einsum("...ij,...j->...i", prior_info, x_lin) - prior_vec)
            Hl = H - prior_info
            Fl = F
        else:
            gl, Hl, Fl = _accumulate(ev, slice(0, n_leave))
        add_vec = np.einsum("...ij,...j->...i", Hl, x_lin) - gl
        prior_fisher = np.where(active[..., None, None], prior_fisher + Fl, prior_fisher)
        prior_info = np.where(active[..., None, None], prior_info + Hl, prior_info)
        prior_vec = np.where(active[..., None], prior_vec + add_vec, prior_vec)
        if W > 0 and np.any(~active):
            # Before initialisation the leaving rows are kept as PL equations only.
            leave = _rows(allm, weight, channel, config).sliced(slice(0, n_leave)).subset(~active)
            A_l, b_l = _pl_rows(leave, _distance_scale(leave, config), channel)
            dr_A = dr_A.copy()
            dr_b = dr_b.copy()
            dr_A[~active] += A_l
            dr_b[~active] += b_l

    # Consistency (score) test of the recent records against the estimate.
    score_H, score_v, consistency = state.score_matrix, state.score_vector, state.consistency
    if config.consistency_threshold is not None and M > 0 and run:
        if W == 0:
            g_new = g - (np.einsum("...ij,...j->...i", prior_info_used, x_lin) - prior_vec_used)
            H_new = H - prior_info_used
        else:
            g_new, H_new, _ = _accumulate(ev, slice(K - M, K))
        score_H, score_v, consistency, fail = _score_test(
            state.score_matrix, state.score_vector, g_new, H_new, x_lin, x, active, config.consistency_threshold, config
        )
        if np.any(fail):
            suspect = suspect | fail
            fisher = np.where(fail[..., None, None], fisher * config.suspect_deflation, fisher)
    fisher = 0.5 * (fisher + np.swapaxes(fisher, -1, -2))
    finite = np.all(np.isfinite(x), axis=-1) & np.all(np.isfinite(fisher), axis=(-1, -2))
    x = np.where(finite[..., None], x, x_prev)
    info = np.where((active & finite)[..., None, None], fisher, 0.0)
    observable = active & finite & (_normalised_det(info) >= config.min_rcond)

    # The new ranges join the range window; the oldest rows leave it and join the re-check's
    # squared-range summary, weighted at this call's estimate (a record's weight 1/(4D²σ_r²(D))
    # ∝ D⁻⁴ is frozen when it joins: a window of later estimates, not the first poor ones).
    if M > 0:
        P = config.recheck_window_rows
        new_ranges = Measurements(new.positions_m, new.range_m, np.full(new.range_m.shape, np.nan), np.full(new.range_m.shape, np.nan), new.los)
        new_weight = np.where(new_row_ok & np.isfinite(new.range_m), 1.0, 0.0)
        if P > 0:
            pool = _concat(state.range_window, new_ranges)
            pool_weight = np.concatenate((range_weight, new_weight), axis=-1)
            # Valid rows at the end, oldest first (stable sort): the first M rows leave.
            order = np.argsort(pool_weight > 0.0, axis=-1, kind="stable")
            pool = _take(pool, order)
            pool_weight = np.take_along_axis(pool_weight, order, axis=-1)
            leaving = Measurements(
                pool.positions_m[..., :M, :], pool.range_m[..., :M], pool.azimuth_rad[..., :M], pool.elevation_rad[..., :M], pool.los[..., :M]
            )
            leaving_weight = pool_weight[..., :M]
            range_window = Measurements(
                pool.positions_m[..., M:, :], pool.range_m[..., M:], pool.azimuth_rad[..., M:], pool.elevation_rad[..., M:], pool.los[..., M:]
            )
            range_weight = pool_weight[..., M:]
        else:
            leaving, leaving_weight = new_ranges, new_weight
            range_window = state.range_window
        lrows = _rows(leaving, leaving_weight, channel, config)
        if np.any(lrows.ar > 0.0):
            A_r, b_r = _pl_range_rows(lrows, _range_scale(x, initialised, lrows, config), channel.gamma)
            pr_A = pr_A + A_r
            pr_b = pr_b + b_r
    else:
        range_window = state.range_window
    range_window_weight = range_weight

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
    used = (new_rows.ar > 0.0).sum(axis=-1) + (new_rows.aa > 0.0).sum(axis=-1) + (new_rows.ae > 0.0).sum(axis=-1)
    count = state.measurement_count + used
    return EstimatorState(
        estimate_m=x,
        information=info,
        observable=observable,
        initialised=initialised,
        prior_information=prior_info,
        prior_fisher=prior_fisher,
        prior_vector=prior_vec,
        pl_matrix=pl_A,
        pl_vector=pl_b,
        pl_dropped_matrix=dr_A,
        pl_dropped_vector=dr_b,
        pl_range_matrix=pr_A,
        pl_range_vector=pr_b,
        range_window=range_window,
        range_window_weight=range_window_weight,
        window=window,
        window_weight=window_weight,
        measurement_count=count,
        suspect=suspect,
        score_matrix=score_H,
        score_vector=score_v,
        consistency=consistency,
        calls=state.calls + 1,
    )
