"""The estimator's data: the records it is fed (:class:`Measurements`), its settings
(:class:`EstimatorConfig`) and its state (:class:`EstimatorState`), and the row operations on
records."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from tests.reference_numpy.estimator.memory import RangeMemory, empty_memory

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


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
        extra_values: the values of measurement components other than range and bearing
            (:attr:`planner.sensing.SensingComponent.value_names`), by value name, each of
            shape (..., M); NaN where not measured. Read by :func:`planner.estimator.update`
            for the components it is given.
    """

    positions_m: FloatArray
    range_m: FloatArray
    azimuth_rad: FloatArray
    elevation_rad: FloatArray
    los: BoolArray
    extra_values: Mapping[str, FloatArray] = field(default_factory=lambda: MappingProxyType({}))

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
        range_memory_cells: cells of the range memory (:mod:`planner.estimator.memory`; 0, the
            default here, turns it off; a mission file sets 256 for a static source): every range so far, compressed by where it was taken. For
            an element that has used ranges only, the re-check then polishes the current
            estimate and the best start of the other basin (the PL solution, or a point along
            the least-informed direction) on the exact likelihood of all ranges, and moves to
            the better optimum when the current estimate is less likely than it by more than
            ``recheck_likelihood_drop``; the prior becomes the memory's cost re-linearised
            there, claimed in full (it is the likelihood, not the biased PL cost). Elements that
            used bearings keep the PL re-check (``recheck_threshold``).
        range_memory_radius: a range joins a memory cell within this fraction of the cell's
            mean range (0.05: 3 m at 60 m). The offsets within a cell enter the residuals to
            first order, but each range's variance σ_r0² d^γ is taken at the cell's centre, a
            relative error of up to γ × this fraction; for NLOS ranges the variance carries
            more than half of a range's information (γ²/(2d²) against 1/(σ_r0² d²)), so wide
            cells pull the exact-likelihood optimum off the source.
        recheck_likelihood_drop: with the range memory, the negative log-likelihood by which
            the current estimate must exceed the best optimum before it moves there (a
            log-likelihood ratio; 1: the estimate is off its own likelihood's optimum by more
            than a linearised prior should allow).
        consistency_threshold: χ² threshold (3 degrees of freedom) of the score test of the
            recent records against the estimate (None disables it; the default 25 is about
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
        init_max_relative_sigma: an element whose records all carry a bearing initialises once its PL
            system's weakest direction has a standard deviation at most this fraction of
            ``init_distance_m`` (0.5; None: as soon as the system solves). Two nearly parallel
            bearings solve but fix the point along their lines to tens of metres.
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
    range_memory_cells: int = 0
    range_memory_radius: float = 0.05
    recheck_likelihood_drop: float = 1.0
    consistency_threshold: float | None = 25.0
    consistency_forgetting: float = 0.9
    lm_damping: float = 1e-3
    nlos_bearing_weight: float = 0.0
    min_rcond: float = 1e-9
    pl_rcond: float = 1e-10
    init_distance_m: float = 100.0
    init_max_relative_sigma: float | None = 0.5
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
        if not (isinstance(self.range_memory_cells, int) and self.range_memory_cells >= 0):
            raise ValueError(f"EstimatorConfig.range_memory_cells: expected an integer >= 0, found {self.range_memory_cells!r}")
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
        positive = (
            "huber_k",
            "tukey_c",
            "suspect_sigma",
            "lm_damping",
            "min_rcond",
            "pl_rcond",
            "init_distance_m",
            "recheck_threshold",
            "range_memory_radius",
            "recheck_likelihood_drop",
        )
        for name in positive:
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0.0):
                raise ValueError(f"EstimatorConfig.{name}: expected a finite positive number, found {value!r}")
        if self.consistency_threshold is not None and not (math.isfinite(self.consistency_threshold) and self.consistency_threshold > 0.0):
            raise ValueError(f"EstimatorConfig.consistency_threshold: expected None or a positive number, found {self.consistency_threshold!r}")
        if self.init_max_relative_sigma is not None and not (math.isfinite(self.init_max_relative_sigma) and self.init_max_relative_sigma > 0.0):
            raise ValueError(f"EstimatorConfig.init_max_relative_sigma: expected None or a positive number, found {self.init_max_relative_sigma!r}")
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
        range_memory: every range so far, compressed by position
            (:class:`planner.estimator.memory.RangeMemory`, ``range_memory_cells`` cells).
        angles_used: (...,) bool, True once the element used any record component other than
            a range (a bearing, an elevation, a registered extension): its prior then holds more
            than the range memory, and the re-check compares on the PL cost instead.
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
    range_memory: RangeMemory
    angles_used: BoolArray
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
        range_memory=empty_memory(b, config.range_memory_cells),
        angles_used=np.zeros(b, dtype=bool),
        window=empty_measurements(b, config.window_rows),
        window_weight=np.zeros(b + (config.window_rows,)),
        measurement_count=np.zeros(b, dtype=np.int64),
        suspect=np.zeros(b, dtype=bool),
        score_matrix=np.zeros(b + (3, 3)),
        score_vector=np.zeros(b + (3,)),
        consistency=np.zeros(b),
    )


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
    extra = {}
    for name, value in measurements.extra_values.items():
        arr = np.asarray(value, dtype=float)
        if arr.shape != rows:
            raise ValueError(f"Measurements.extra_values[{name!r}]: expected shape {rows}, found {arr.shape}")
        extra[name] = arr
    return Measurements(p, fields["range_m"], fields["azimuth_rad"], fields["elevation_rad"], los, MappingProxyType(extra))


def _concat(a: Measurements, b: Measurements) -> Measurements:
    names = list(dict.fromkeys([*a.extra_values, *b.extra_values]))

    def value(m: Measurements, name: str) -> FloatArray:
        return m.extra_values[name] if name in m.extra_values else np.full(np.shape(m.range_m), np.nan)

    return Measurements(
        np.concatenate((a.positions_m, b.positions_m), axis=-2),
        np.concatenate((a.range_m, b.range_m), axis=-1),
        np.concatenate((a.azimuth_rad, b.azimuth_rad), axis=-1),
        np.concatenate((a.elevation_rad, b.elevation_rad), axis=-1),
        np.concatenate((a.los, b.los), axis=-1),
        MappingProxyType({name: np.concatenate((value(a, name), value(b, name)), axis=-1) for name in names}),
    )


def _take(m: Measurements, idx: NDArray[np.intp]) -> Measurements:
    return Measurements(
        np.take_along_axis(m.positions_m, idx[..., None], axis=-2),
        np.take_along_axis(m.range_m, idx, axis=-1),
        np.take_along_axis(m.azimuth_rad, idx, axis=-1),
        np.take_along_axis(m.elevation_rad, idx, axis=-1),
        np.take_along_axis(m.los, idx, axis=-1),
        MappingProxyType({name: np.take_along_axis(v, idx, axis=-1) for name, v in m.extra_values.items()}),
    )


def _rows_of(m: Measurements, sl: slice) -> Measurements:
    """The rows ``sl`` of ``m``."""
    return Measurements(
        m.positions_m[..., sl, :],
        m.range_m[..., sl],
        m.azimuth_rad[..., sl],
        m.elevation_rad[..., sl],
        m.los[..., sl],
        MappingProxyType({name: v[..., sl] for name, v in m.extra_values.items()}),
    )


def _scatter(a: NDArray, b: NDArray, sel: BoolArray) -> NDArray:
    """A copy of ``a`` with ``a[sel] = b``."""
    out = np.array(a, copy=True)
    out[sel] = b
    return out
