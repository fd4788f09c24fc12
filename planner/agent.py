"""One drone's planning step from its view: the chain shared by the in-process simulator and
the planner node, so both compute the same thing (docs/distributed.md, "Distributed =
in-process": build the delayed view → estimate the source → compute the control step).

Given drone i's step inputs (:class:`planner.step.StepScene`: its view, the records it holds of
every drone, itself included, its estimate and its own measurement) and what it carries from
its last step (:class:`planner.step.DroneState`), :func:`plan` returns the control step of
:func:`planner.control.control_step` together with the cost of eq. 6 it descended and the state
it carries to its next step. Batched over leading dimensions: the simulator passes (trials,
drones), a planner node passes none. The whole step is one compiled kernel looping over the batch
(:func:`planner.kernels.plan_batch`: the predicted line of sight, the FIM and its gradient, the
carried state, keep-outs, loiter, peer rows, control step); with measurement components beyond
range and bearing the cost is computed first (:func:`_planning_cost`, their own terms added) and
given to it.

Policies fixed here (docs/control.md):

* Planning FIM: drone i's own term is weighted by the predicted line of sight of its link to
  the estimate, q = Π_b Φ(c_b/s), c_b the link's clearance from building b
  (:func:`planner.geometry.link_clearance_with_gradient`, negative across it) and s =
  :data:`LOS_SOFTNESS_M`: J = J_peers + q J_own,LOS + (1 − q) J_own,NLOS
  (:func:`own_los_weight`). The gradient then has a term tr(∂C/∂J (J_own,LOS − J_own,NLOS)) ∇q
  that leads a drone out of a building's shadow, where it would otherwise stay (with the
  recorded NLOS flag a bearing-only drone in a shadow has a zero gradient and drifts; with the
  own link taken as LOS, as fimnav did before, drones settled in shadows: 25 % of the
  heterogeneous swarm's final links). Far from every building q = 1 and nothing changes.
* Source keep-out: d_S* + min(max(3σ, min(4σ, 4 m), 1.5 m), d_S*) around the estimate, σ the estimate's largest standard
  deviation; no source constraint while the source is not observable. Second evidence, a
  ranging drone's own last ranges (:func:`own_ranges`): where their lower bound on its
  distance to the source is below d_S* + the activation margin and the estimate gives no
  direction to trust (not observable, 3σ ≥ d_S*, or contradicted by those ranges), the drone
  loiters in place (:func:`must_loiter`, :func:`loiter_gradient`). The simulator and the
  planner node pass the ranges; without them (None) the keep-out follows the estimate alone.
* Not observable yet: treated like a singular FIM (keep moving along the last direction with a
  random perturbation, the paper's fallback).
* Anti-collision against the peers heard directly (h_ij = 1) only: a peer not heard directly is
  farther than d_hop, which cannot close to d_U* within a step when d_hop is large enough
  (:func:`collision_relevant`); with a tiny d_hop every known peer counts, with its age.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner import estimator as est
from planner import kernels as K
from planner.config import PlannerConfig
from planner.control import StepResult, kernel_limits
from planner.fim import CostGradient, cost_gradient, fisher_information
from planner.geometry import as_boxes
from planner.params import Channel, Criterion, Limits
from planner.radio.power_planning import corrected_scene, unknown_power_cost
from planner.sensing import BEARING, COMPONENTS, RANGE, SensingComponent
from planner.step import OWN_RANGE_WINDOW as OWN_RANGE_WINDOW  # re-exported: the window lives with the carried state
from planner.step import DroneState, StepScene

FloatArray = NDArray[np.float64]

#: Standard deviations of the source estimate added to d_S*.
SOURCE_SIGMA_FACTOR: float = K.SOURCE_SIGMA_FACTOR
#: Standard deviations added to d_S* about a converged estimate (:func:`source_keepout_m`),
#: as long as they come to at most :data:`SOURCE_TAIL_MAX_M`.
SOURCE_TAIL_SIGMA_FACTOR: float = K.SOURCE_TAIL_SIGMA_FACTOR
#: Largest inflation (m) of the converged estimate's :data:`SOURCE_TAIL_SIGMA_FACTOR` σ.
SOURCE_TAIL_MAX_M: float = K.SOURCE_TAIL_MAX_M
#: Smallest inflation (m) of d_S* about the estimate, however small its σ.
SOURCE_INFLATION_MIN_M: float = K.SOURCE_INFLATION_MIN_M
#: Standard deviations of the own ranges' lower bound (:meth:`OwnRanges.lower_bound_m`).
OWN_RANGE_SIGMA_FACTOR: float = K.OWN_RANGE_SIGMA_FACTOR
#: Standard deviations by which a drone's own ranges must put the source nearer than its
#: estimate for the estimate to count as contradicted (:meth:`OwnRanges.contradicts`).
OWN_RANGE_CONTRADICTION_SIGMAS: float = K.OWN_RANGE_CONTRADICTION_SIGMAS
#: A drone loitering because its ranges contradicted its estimate holds the estimate
#: contradicted until they put the source nearer by fewer than this many standard deviations
#: (the contradiction's hysteresis, :func:`must_loiter`).
OWN_RANGE_RELEASE_SIGMAS: float = K.OWN_RANGE_RELEASE_SIGMAS
#: A loitering drone whose estimate is still not to be trusted resumes its cost only once its
#: own ranges' lower bound reaches this many times d_S* + a (:func:`must_loiter`).
OWN_RANGE_CLEAR_FACTOR: float = K.OWN_RANGE_CLEAR_FACTOR
#: Softness s (m) of the predicted line of sight Φ(c/s) of a drone's own link past one
#: building (c its clearance from it, Φ the standard normal CDF): 0.5 on a shadow's edge, 0.977
#: at 2 s outside, 0.023 at 2 s inside, 1 − 3·10⁻⁵ at 4 s. Read as the probability that the
#: link is LOS when the shadow's edge is known to s metres (the estimate's error, a few metres
#: at most once the swarm has converged).
LOS_SOFTNESS_M: float = K.LOS_SOFTNESS_M
#: Depth (in softnesses) into a shadow below which the slope of the predicted line of sight is
#: held at its value there (:func:`own_los_weight`): the way out of a deep shadow.
LOS_SLOPE_FLOOR_SOFTNESSES: float = K.LOS_SLOPE_FLOOR_SOFTNESSES
#: Links farther than this many softnesses from a building count as clear of it.
LOS_CUTOFF_SOFTNESSES: float = K.LOS_CUTOFF_SOFTNESSES
#: Bounds the drone's own measured LOS flag puts on q: at least Φ(1) in a measured LOS, at most
#: 1 − Φ(1) in a measured NLOS.
MEASURED_LOS_MIN: float = K.MEASURED_LOS_MIN
#: The longest gap (steps) between two records of a peer that still gives its last step.
DRIFT_MAX_GAP_STEPS: int = K.DRIFT_MAX_GAP_STEPS


def own_los_weight(
    position: ArrayLike,
    source: ArrayLike,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    measured_los: ArrayLike | None = None,
    softness_m: float = LOS_SOFTNESS_M,
) -> tuple[FloatArray, FloatArray]:
    """Predicted line of sight of a drone's link to the (estimated) source, and its gradient.

    q = Π_b Φ(c_b/s), the probability that no building blocks the link when each one's shadow
    edge is uncertain by s: c_b the link's clearance from building b
    (:func:`planner.geometry.link_clearance_with_gradient`; > 0 passing it, < 0 crossing it), Φ
    the standard normal CDF; ∇_p q = q̄ Σ_b (φ(v_b)/Φ(v_b)) ∇_p c_b / s with v_b = max(c_b/s, −1)
    (:data:`LOS_SLOPE_FLOOR_SOFTNESSES`) and q̄ = Π_b Φ(v_b): the derivative of q down to one
    softness inside a shadow, and that slope held deeper in, so that a drone deep in a shadow
    still has the way out (the derivative fades as φ(c/s): a drone that started behind two
    buildings of paper/dynamic_source never left their shadows and ended 244 m from the source;
    :func:`planner.geometry.link_clearance_with_gradient` gives the side to leave by). A smooth stand-in
    for the LOS indicator p_i of eq. 3 at a candidate position: the planning FIM weights the
    drone's own LOS and NLOS terms by q and 1 − q. The product (rather than the nearest
    building alone) keeps ∇q continuous where two shadows meet: with the nearest building only,
    a drone between two predicted shadows was sent to and fro between them.

    The drone's own measured LOS flag at ``position`` (its payload's, eq. 3) bounds q where the
    estimate misplaces a shadow: q ≥ Φ(1) = 0.84 in a measured LOS, q ≤ 1 − Φ(1) = 0.16 in a
    measured NLOS. ∇q is the prediction's, unbounded: the predicted way out of the shadow.
    Without the bound a drone whose estimate misplaces a shadow by a few metres settled on the
    predicted edge inside the real shadow, learned nothing more there and stayed (bearing-only
    swarm, A: 10 % of the trials ended with a mean PEB above 11 m; with it: 6.7 m at the 90th
    percentile).

    Args:
        position: the drone, (..., 3), m, ENU. source: the source estimate, (..., 3), m, ENU.
        boxes_min, boxes_max: buildings, (B, 3), m, ENU.
        measured_los: (...) bool, the drone's own LOS flag at ``position``; None: prediction only.
        softness_m: s, m (the compiled kernel's :data:`LOS_SOFTNESS_M`; another value is an error).

    Returns:
        ``(q, grad_q)`` of shapes (...) and (..., 3) (1/m); 1 and zeros without buildings.
    """
    if softness_m != LOS_SOFTNESS_M:
        raise ValueError(f"own_los_weight: the softness is {LOS_SOFTNESS_M} m, found {softness_m}")
    p, s = np.asarray(position, dtype=float), np.asarray(source, dtype=float)
    batch = np.broadcast_shapes(p.shape[:-1], s.shape[:-1], np.shape(measured_los) if measured_los is not None else ())
    measured = False if measured_los is None else measured_los
    args = (K.as_batch(p, batch + (3,), float, 1), K.as_batch(s, batch + (3,), float, 1), K.as_batch(measured, batch, bool, 0))
    q, grad = K.own_los_batch(*args, measured_los is not None, *as_boxes(boxes_min, boxes_max))
    return q.reshape(batch), grad.reshape(batch + (3,))


def _policy(
    limits: Limits, sigma: ArrayLike, observable: ArrayLike, distance_m: ArrayLike, own: OwnRanges, loitering: ArrayLike | None
) -> FloatArray:
    """The compiled keep-out and loiter policy per element (:func:`planner.kernels.policy_batch`):
    rows keep-out (m), loiter, contradicted (with the loiter's hysteresis), shapes broadcast."""
    was = False if loitering is None else loitering
    batch = np.broadcast_shapes(np.shape(sigma), np.shape(observable), np.shape(distance_m), np.shape(own.mean_m), np.shape(was))
    args = [
        K.as_batch(x, batch, t, 0)
        for x, t in ((sigma, float), (observable, bool), (distance_m, float), (own.mean_m, float), (own.weight, float), (was, bool))
    ]
    return K.policy_batch(*args, float(own.gamma), kernel_limits(limits)).reshape((3,) + batch)


def source_keepout_m(limits: Limits, sigma_m: ArrayLike) -> FloatArray:
    """Keep-out radius around the source estimate (m):
    d_S* + min(max(3σ, min(4σ, 4 m), 1.5 m), d_S*), σ the estimate's largest standard deviation (m).

    The inflation covers the estimate's error; its cap keeps an uncertain swarm from fleeing
    the estimate (fleeing lengthens the ranges, which grows σ: a runaway seen without the cap).
    Its floor, :data:`SOURCE_INFLATION_MIN_M`, covers a converged estimate whose σ is
    optimistic (a bearing-only estimate 1.3 m off with 3σ < 1.1 m came 0.3 m inside d_S*).
    Between them a converged estimate (σ ≤ 1 m) gets 4σ, up to :data:`SOURCE_TAIL_MAX_M`: its
    error's tail reaches 4σ (paper/joint, D: an estimate 2.50 m off with σ = 0.64 m, 3.9σ, took
    a drone 0.03 m inside d_S*; over 100 trials of paper/joint and paper/heterogeneous, A and D,
    flown with 3σ, the error beyond max(3σ, 1.5 m) reached 0.74 m where a drone was within 2 m
    of its keep-out, and beyond max(4σ, 1.5 m) 0.04 m; paper/joint, A, with loss and delay: an
    estimate 3.1-3.3 m off with σ = 1.0 m took a drone 0.10 m inside d_S* while the tail stopped at
    3 m). The tail term stops at 4 m, where 3σ takes over: a
    ranging estimate (σ of metres) keeps 3σ, as a wider keep-out moves its swarm out and grows
    its σ (4σ throughout: paper/ranging_los, A, final mean PEB 32.7 → 57.8 m over 100 trials).
    """
    none = OwnRanges(np.full(np.shape(sigma_m), np.nan), np.zeros(np.shape(sigma_m)), 2.0)
    return _policy(limits, sigma_m, True, 0.0, none, None)[0]


def followable_keepout_m(
    limits: Limits,
    own_position: ArrayLike,
    centre_m: ArrayLike,
    radius_m: ArrayLike,
    sigma_m: ArrayLike,
    last_centre_m: ArrayLike | None,
    last_radius_m: ArrayLike | None,
) -> FloatArray:
    """The keep-out radius (...), m, a drone at ``own_position`` (..., 3) plans with this step:
    ``radius_m`` about ``centre_m`` (..., 3) (the estimate), except that about an estimate too
    uncertain to cover the source (3σ ≥ d_S*: the inflation is capped, :func:`source_keepout_m`)
    its boundary advances on the drone by at most the turn buffer b per step.

    An uncertain estimate wanders: in paper/dynamic_source, D, its centre moved by a median
    1.7 m and a 90th percentile 6.6 m per step (20 % loss, 3 steps of delay; 1.9 m and 6.4 m
    without faults), and the keep-out's boundary advanced on a drone by more than v_max Δt at
    one drone-step in ten. No step can keep such a constraint, and the safety filter, which
    assumes a constraint that moves by less than b per step, falls through its tiers: two
    drones hugging it were squeezed 0.18 m inside d_U* (trial 33). Such a keep-out claims no
    coverage of the source (3σ is beyond its cap), so the radius is
    r̃ = min(r, max(r̃' + |x − ĉ| − |x − ĉ'| + b, d_S* + :data:`SOURCE_INFLATION_MIN_M`)),
    primes of the last step: the margin |x − ĉ| − r̃ shrinks by at most b while the drone holds
    still, and an estimate that jumped is followed at b per step. A trusted estimate (3σ <
    d_S*), a keep-out that was not there last step (−inf) or no last step: r unchanged.
    """
    r = np.asarray(radius_m, dtype=float)
    if last_centre_m is None or last_radius_m is None:
        return r
    x = np.asarray(own_position, dtype=float)
    batch = np.broadcast_shapes(
        x.shape[:-1], np.shape(centre_m)[:-1], r.shape, np.shape(sigma_m), np.shape(last_centre_m)[:-1], np.shape(last_radius_m)
    )
    vectors = [K.as_batch(v, batch + (3,), float, 1) for v in (x, centre_m, last_centre_m)]
    scalars = [K.as_batch(v, batch, float, 0) for v in (r, sigma_m, last_radius_m)]
    return K.followable_batch(vectors[0], vectors[1], scalars[0], scalars[1], vectors[2], scalars[2], kernel_limits(limits)).reshape(batch)


@dataclass(frozen=True, eq=False)
class OwnRanges:
    """A drone's own last ranges (eq. 3), combined: the evidence of its distance to the source
    that does not depend on the source estimate (:func:`own_ranges`).

    Model: the distance d is taken as constant over the window (the drone moves at most
    v_max Δt per step) and d̂_w = d (1 + s_w n_w), n_w ~ N(0, 1), with the relative standard
    deviation s_w = σ_r0,w d^(γ/2 − 1) of eq. 5. The weighted mean d̄ = Σ w d̂ / Σ w,
    w = 1/σ_r0,w², has relative standard deviation r(d) = 1/√(Σw d^(2 − γ)) about d (exact for
    γ = 2). One NLOS range at d_S* has σ_r = 37 m; ten NLOS ranges give r = 0.23.

    Attributes:
        mean_m: d̄ (...), m; NaN where the window holds no range.
        weight: Σ_w 1/σ_r0,w² (...); 0 where no range.
        gamma: the path-loss exponent γ of eq. 5.
    """

    mean_m: FloatArray
    weight: FloatArray
    gamma: float

    def _stats(self, distance_m: ArrayLike, k: ArrayLike) -> FloatArray:
        """(relative sd at d, lower bound with k σ, contradicted at d by k σ), compiled."""
        batch = np.broadcast_shapes(np.shape(self.mean_m), np.shape(distance_m), np.shape(k))
        args = (K.as_batch(self.mean_m, batch, float, 0), K.as_batch(self.weight, batch, float, 0))
        return K.own_range_batch(*args, float(self.gamma), K.as_batch(distance_m, batch, float, 0), K.as_batch(k, batch, float, 0)).reshape(
            (3,) + batch
        )

    def relative_sd(self, distance_m: ArrayLike) -> FloatArray:
        """r(d), the relative standard deviation of d̄ about a distance d (m); +inf without ranges."""
        return self._stats(distance_m, 0.0)[0]

    def lower_bound_m(self, sigma_factor: float = OWN_RANGE_SIGMA_FACTOR) -> FloatArray:
        """Lower confidence bound (m) on the distance: d̄ / (1 + k r(d̄)), which exceeds d with
        probability Φ(−k) (2.3 % at k = 2); +inf without ranges. Ten NLOS ranges give a bound
        32 % below their mean (twenty: 25 %)."""
        return self._stats(1.0, sigma_factor)[1]

    def contradicts(self, distance_m: ArrayLike, sigma_factor: ArrayLike = OWN_RANGE_CONTRADICTION_SIGMAS) -> NDArray[np.bool_]:
        """True where the ranges say the source is nearer than ``distance_m`` (the distance to
        the estimate, m): z = (d̄/d − 1)/r(d) < −k, k = ``sigma_factor`` (broadcast), the
        one-sided test of d̄ against a source at that distance (false alarm Φ(−k), 0.62 % at the
        default k = 2.5). False without ranges."""
        return self._stats(distance_m, sigma_factor)[2] > 0.5


def own_ranges(range_m: ArrayLike, los: ArrayLike, channel: Channel) -> OwnRanges:
    """Combine a drone's own last ranges into :class:`OwnRanges`.

    Args:
        range_m: (..., W) the drone's own measured ranges d̂ (eq. 3), m; NaN = no range.
        los: (..., W) bool, the LOS flag of each.
        channel: σ_r0 (LOS/NLOS) and γ of eq. 5.
    """
    r = np.asarray(range_m, dtype=float)
    batch, w = r.shape[:-1], r.shape[-1]
    mean, weight = K.own_ranges_batch(K.as_batch(r, r.shape, float, 1), K.as_batch(los, r.shape, bool, 1), channel.kernel_array)
    return (
        OwnRanges(mean_m=mean.reshape(batch), weight=weight.reshape(batch), gamma=float(channel.gamma))
        if w
        else OwnRanges(np.full(batch, np.nan), np.zeros(batch), float(channel.gamma))
    )


def must_loiter(
    limits: Limits,
    sigma_m: ArrayLike,
    observable: ArrayLike,
    distance_m: ArrayLike,
    own: OwnRanges,
    loitering: ArrayLike | None = None,
) -> NDArray[np.bool_]:
    """Where a drone loiters (:func:`loiter_gradient`) instead of descending its cost (...).

    The estimate gives no direction to trust where it is not ``observable``, uncertain beyond
    the keep-out's cap (3σ ≥ d_S*, ``sigma_m`` its largest standard deviation, m), or
    contradicted by the drone's own ranges ``own``, the source nearer than the estimate's
    ``distance_m`` (:meth:`OwnRanges.contradicts`). The keep-out about such an estimate does not
    cover the source (a confident estimate 80-140 m off after a partition, an uncertain one
    wrong along the drone's own line of sight), and no direction away from it is known to lead
    away from the source. With such an estimate a drone starts loitering where its ranges'
    lower bound (:meth:`OwnRanges.lower_bound_m`) is below d_S* + a (a =
    :func:`planner.control.source_activation_margin_m`), and a drone ``loitering`` at the last
    step goes on until the estimate is trusted again or the bound reaches
    :data:`OWN_RANGE_CLEAR_FACTOR` (d_S* + a). The hysteresis matters: resuming as soon as a
    noisy bound rose above d_S* + a, a drone crept in a step at a time and crossed d_S* by
    2.9 m (paper/ranging_nlos, A, 20 % loss and 3 steps of delay). Shapes broadcast; False
    without ranges.
    """
    return _policy(limits, sigma_m, observable, distance_m, own, loitering)[1] > 0.5


def contradicted(own: OwnRanges, distance_m: ArrayLike, loitering: ArrayLike | None = None) -> NDArray[np.bool_]:
    """(...) True where a drone's own ranges ``own`` contradict its estimate at ``distance_m``
    (m): by :data:`OWN_RANGE_CONTRADICTION_SIGMAS` (:meth:`OwnRanges.contradicts`), and for a
    drone ``loitering`` at its last step by :data:`OWN_RANGE_RELEASE_SIGMAS` only (the loiter's
    hysteresis; the keep-out is dropped only at the entry threshold). Without the
    hysteresis a drone whose ranges put the source 2-3 σ nearer than an estimate 65-75 m off
    left its loiter each time the statistic rose above −3, and the keep-out about that estimate
    pushed it toward the source between loiters (paper/ranging_nlos A, 20 % loss, trial 0:
    10.4 m inside d_S*)."""
    was = np.zeros((), dtype=bool) if loitering is None else np.asarray(loitering, dtype=bool)
    return own.contradicts(distance_m, np.where(was, OWN_RANGE_RELEASE_SIGMAS, OWN_RANGE_CONTRADICTION_SIGMAS))


def hop_rule(d_hop_m: float, limits: Limits) -> bool:
    """Whether only the peers heard directly (h_ij = 1) are collision-relevant
    (:func:`collision_relevant`): d_hop ≥ d_U* + 3 v_max Δt + 2 b."""
    return d_hop_m >= limits.d_uav_m + 3.0 * limits.step_max_m + 2.0 * limits.turn_buffer_m


def collision_relevant(hops: ArrayLike, d_hop_m: float, limits: Limits) -> NDArray[np.bool_]:
    """Which peers a drone must keep clear of this step, from its hop counts (..., N).

    A peer that is not a direct neighbour (h_ij ≠ 1) is farther than d_hop right now, so it
    cannot come within d_U* during the next step when d_hop ≥ d_U* + 3 v_max Δt + 2 turn
    buffers; its (stale) position is then ignored. With a smaller radius every known peer
    counts, with its age (see :func:`planner.control.control_step`).
    """
    h = np.asarray(hops)
    return h == 1 if hop_rule(d_hop_m, limits) else np.ones(h.shape, dtype=bool)


def estimate_sigma_m(information: ArrayLike) -> FloatArray:
    """Largest standard deviation (m) of an estimate with Fisher information (..., 3, 3):
    1/√λ_min (Jacobi eigenvalues, compiled), +inf where λ_min ≤ 0."""
    info = np.asarray(information, dtype=float)
    sigma, _ = K.small_batch(K.as_batch(info, info.shape, float, 2), np.zeros((0, 3)))
    return sigma.reshape(info.shape[:-2])


def loiter_gradient(previous_step: ArrayLike) -> FloatArray:
    """The gradient (..., 3) a loitering drone descends: minus the horizontal unit vector 90°
    to the left of its last step (east where it has none). The step of eq. 14 asks a quarter
    turn; the heading limit φ_max of eq. 2 grants φ_max a step, so the drone flies a level circle
    of circumference v_max Δt · 360°/φ_max (7.2 m at 1 m/step and 50°) about where it started
    loitering, under the same constraints and safety filter as any step: it makes no net
    progress in any direction, toward a source whose direction it does not know."""
    u = np.asarray(previous_step, dtype=float)
    _, g = K.small_batch(np.zeros((0, 3, 3)), K.as_batch(u, u.shape, float, 1))
    return g.reshape(u.shape)


class _Record(Protocol):
    """What :func:`records_as_arrays` reads of a record: where it was taken and its LOS flag."""

    @property
    def position_m(self) -> ArrayLike: ...

    @property
    def los(self) -> bool: ...


class _MeasuredRecord(_Record, Protocol):
    """What :func:`measurements_from_records` reads of a record: its position, LOS flag and
    measured values (NaN: not measured)."""

    @property
    def range_m(self) -> float: ...

    @property
    def azimuth_rad(self) -> float: ...

    @property
    def elevation_rad(self) -> float: ...

    @property
    def extra_values(self) -> Mapping[str, float]: ...


def measurements_from_records(records: Sequence[_MeasuredRecord | None], extra_value_names: Sequence[str] = ()) -> est.Measurements:
    """The estimator's rows (:class:`planner.estimator.Measurements`, one per record, None: an
    empty row) of records taken at ``position_m`` (m, ENU): range (m), azimuth and elevation
    (rad), LOS flag, and the values of ``extra_value_names`` (the components beyond range and
    bearing, :attr:`planner.sensing.SensingTable.extra_value_names`; NaN where a record has none)."""
    rows = len(records)
    pos = np.full((rows, 3), np.nan)
    rng = np.full(rows, np.nan)
    az = np.full(rows, np.nan)
    el = np.full(rows, np.nan)
    los = np.zeros(rows, dtype=bool)
    extra = {name: np.full(rows, np.nan) for name in extra_value_names}
    for row, rec in enumerate(records):
        if rec is None:
            continue
        pos[row] = rec.position_m
        rng[row], az[row], el[row], los[row] = rec.range_m, rec.azimuth_rad, rec.elevation_rad, rec.los
        for name, values in extra.items():
            values[row] = rec.extra_values.get(name, np.nan)
    return est.Measurements(positions_m=pos, range_m=rng, azimuth_rad=az, elevation_rad=el, los=los, extra_values=extra)


def records_as_arrays(records: Sequence[_Record | None]) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.bool_]]:
    """(positions (N, 3) m ENU, valid (N,), los (N,)) of N records, None where there is none
    (position zero, not valid, NLOS there)."""
    n = len(records)
    positions = np.zeros((n, 3))
    valid = np.zeros(n, dtype=bool)
    los = np.zeros(n, dtype=bool)
    for j, rec in enumerate(records):
        if rec is not None:
            positions[j], valid[j], los[j] = rec.position_m, True, rec.los
    return positions, valid, los


def _planning_cost(
    p_hat: FloatArray,
    own_position: ArrayLike,
    own: NDArray[np.bool_],
    view_positions: ArrayLike,
    rng_view: NDArray[np.bool_],
    brg_view: NDArray[np.bool_],
    view_los: ArrayLike,
    own_ranging: NDArray[np.bool_],
    own_bearing: NDArray[np.bool_],
    channel: Channel,
    criterion: Criterion,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    extra_view: Mapping[str, NDArray[np.bool_]] | None = None,
    own_extra: Mapping[str, NDArray[np.bool_]] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
) -> CostGradient:
    """Cost of eq. 6 and its gradient w.r.t. the drone's own position, with the own link's
    predicted line of sight q (:func:`own_los_weight`): J = J_peers + q J_L + (1 − q) J_N
    (J_L, J_N the own term in LOS and NLOS) and ∇C = q g_L + (1 − q) g_N + tr(M (J_L − J_N)) ∇q,
    M = ∂C/∂J (:func:`planner.fim.cost_gradient` with a LOS weight). The peers' terms use their
    records' LOS flags. ``extra_view`` / ``own_extra``: the masks of the components other than
    range and bearing in the view (..., N) and of the drone itself (...), by name
    (:func:`planner.sensing.component_masks`); ``components``: the component registry.
    """
    if np.size(boxes_min) == 0:  # no building: every link LOS, q = 1
        J = fisher_information(p_hat, view_positions, rng_view, brg_view, np.asarray(view_los, dtype=bool) | own, channel, extra_view, components)
        ones = np.ones(own_ranging.shape, dtype=bool)
        return cost_gradient(J, p_hat, own_position, own_ranging, own_bearing, ones, channel, criterion, own_extra=own_extra, components=components)
    measured = (np.asarray(view_los, dtype=bool) & own).any(-1)
    q, grad_q = own_los_weight(own_position, p_hat, boxes_min, boxes_max, measured_los=measured)
    plan_los = np.where(own, q[..., None], np.asarray(view_los, dtype=float))
    J = fisher_information(p_hat, view_positions, rng_view, brg_view, plan_los, channel, extra_view, components)
    return cost_gradient(
        J, p_hat, own_position, own_ranging, own_bearing, q, channel, criterion, own_los_gradient=grad_q, own_extra=own_extra, components=components
    )


@dataclass(frozen=True)
class PlanResult:
    """A planning step: the control step, the cost it descended (at the estimate) and the state the
    drone carries to its next step."""

    step: StepResult
    cost: CostGradient
    keepout_m: FloatArray
    #: (..., 3) m, ENU, the centre of the keep-out of ``keepout_m`` (the estimate it planned with).
    keepout_centre_m: FloatArray
    #: (...) bool, the drone loitered: its own ranges put the source within reach of d_S*
    #: and its estimate gave no direction to trust (:func:`loiter_gradient`).
    loiter: NDArray[np.bool_]
    #: What the drone carries to its next step (:class:`planner.step.DroneState`).
    state: DroneState


def plan(
    config: PlannerConfig,
    scene: StepScene,
    state: DroneState,
    *,
    oracle_source: ArrayLike | None = None,
    oracle_slow: bool = True,
    power_offset: ArrayLike | None = None,
) -> PlanResult:
    """Drone i's planning step from its step inputs and carried state (eqs. 6, 10-17).

    Args:
        config: the mission's planning parameters (channel, limits, criterion, roles, buildings,
            d_hop, start positions, controller settings).
        scene: the step's inputs (:class:`planner.step.StepScene`): the drone's position, own
            measurement, delayed view, estimate, fallback uniforms and lost-contact peers.
        state: what it carries from its last step (:class:`planner.step.DroneState`; its
            :attr:`PlanResult.state` after the last step, :meth:`DroneState.initial` before the first).
        oracle_source: plan with this source position instead of the estimate (research mode:
            the paper's "estimate given"), with the plain d_S* keep-out.
        oracle_slow: the oracle source moves less than b per step
            (:meth:`missions.format.schema.Mission.source_is_slow`): its constraint then acts within
            v_max Δt + b (:func:`planner.control.source_activation_margin_m` with ``exact``).
        power_offset: with the source's power unknown (``config.unknown_power``), the drone's
            estimate b̂ (...) of its offset (:mod:`planner.radio.power_estimator`; NaN or None: 0):
            the cost is that of the Schur complement at (p̂0, b̂) and the own ranges are read as
            e^−b̂ d̂ (:mod:`planner.radio.power_planning`).

    The policies (docs/control.md): the own link's predicted line of sight in the planning FIM
    (:func:`own_los_weight`); the keep-out about the estimate (:func:`source_keepout_m`, rate
    limited about an uncertain estimate by :func:`followable_keepout_m`); the loiter where the
    drone's own last :data:`OWN_RANGE_WINDOW` ranges put the source within reach and the
    estimate gives no direction to trust (:func:`must_loiter`, :func:`loiter_gradient`); no
    keep-out and the singular fallback while the source is not observable. Peers: those heard
    directly (:func:`collision_relevant`), each at its record with its age; a lost-contact peer
    as the bisector plane of the step of its last record (:func:`planner.control.lost_contact_planes`);
    a peer drone i holds no record of yet at its start position (``config.start_positions_m``,
    known to all) aged k steps. The carried state gains the own range and position and the
    peers' drift (dead reckoning in the safety filter) before the step, its keep-out, loiter and
    step after it.
    """
    if config.unknown_power is not None:  # the own ranges as of the assumed power (planner.radio)
        scene = corrected_scene(scene, power_offset)
    batch = scene.batch
    p_hat = (
        np.asarray(scene.estimate_m, dtype=float) if oracle_source is None else np.broadcast_to(np.asarray(oracle_source, dtype=float), batch + (3,))
    )
    n = np.shape(scene.view_valid)[-1]
    kscene = _kernel_scene(scene, p_hat, batch, n)
    kconfig = _kernel_config(config, scene.step_index, oracle_source is not None, oracle_source is not None and oracle_slow, n)
    old = state.kernel_arrays()
    new = tuple(np.empty(a.shape, a.dtype) for a in old)
    u, flags, keepout = np.empty(batch + (3,)), np.empty(batch + (8,), dtype=bool), np.empty(batch + (1,))
    out = (u.reshape(-1, 3), flags.reshape(-1, 8), keepout.reshape(-1, 1))
    if config.criterion not in ("A", "D"):
        raise ValueError(f"criterion: expected 'A' or 'D', found {config.criterion!r}")
    roles = (K.contiguous(config.ranging, bool), K.contiguous(config.bearing, bool), config.criterion == "D")
    view_los = K.as_batch(scene.view_los, batch + (n,), bool, 1)
    value, grad, status = np.empty(batch), np.empty(batch + (3,)), np.empty(batch, dtype=np.int8)
    given = config.unknown_power is not None or any(name not in _RANGE_BEARING for name in config.component_masks)
    if given:
        # Components beyond range and bearing: the cost here, each adding its own terms; an
        # unknown power: the cost of the 4 × 4 information's Schur complement (planner.radio).
        cg = (
            _scene_cost(config, scene, scene.own_mask, p_hat)
            if config.unknown_power is None
            else unknown_power_cost(config, scene, p_hat, power_offset, own_los_weight)
        )
        value[...], grad[...], status[...] = cg.value, cg.gradient, cg.status
    K.plan_batch(kscene, view_los, roles, old, kconfig, new, out, (value.reshape(-1), grad.reshape(-1, 3), status.reshape(-1)), given)
    cg = CostGradient(value, grad, status)
    p = np.asarray(scene.own_position_m, dtype=float)
    step = StepResult(p + u, u, flags[..., :4], flags[..., 4], flags[..., 5], flags[..., 6])
    return PlanResult(step, cg, keepout[..., 0], np.asarray(p_hat), flags[..., 7], DroneState.from_kernel_arrays(new, batch))


#: The components whose terms the kernels add themselves (any other: :func:`_scene_cost`).
_RANGE_BEARING: tuple[str, ...] = (RANGE.name, BEARING.name)


def _scene_cost(config: PlannerConfig, scene: StepScene, own: NDArray[np.bool_], p_hat: FloatArray) -> CostGradient:
    """The cost of eq. 6 the drones of ``scene`` descend, with its gradient (:func:`_planning_cost`)."""
    valid = np.asarray(scene.view_valid, dtype=bool)
    ranging, bearing = np.asarray(config.ranging, dtype=bool), np.asarray(config.bearing, dtype=bool)
    index = np.asarray(scene.own_index)
    extra = {name: np.asarray(mask, dtype=bool) for name, mask in config.extra_masks.items()}
    return _planning_cost(
        p_hat,
        scene.own_position_m,
        own,
        scene.view_positions_m,
        ranging & valid,
        bearing & valid,
        scene.view_los,
        ranging[index],
        bearing[index],
        config.channel,
        config.criterion,
        config.boxes_min_m,
        config.boxes_max_m,
        {name: mask & valid for name, mask in extra.items()},
        {name: mask[index] for name, mask in extra.items()},
        config.sensing.components,
    )


def _kernel_scene(scene: StepScene, p_hat: FloatArray, batch: tuple[int, ...], n: int) -> tuple[np.ndarray, ...]:
    """The scene's arrays as :func:`planner.kernels.plan_batch` takes them (flat batch)."""
    lost = np.zeros(batch + (n,), dtype=bool) if scene.lost_contact is None else scene.lost_contact
    return (
        K.as_batch(scene.own_index, batch, np.int64, 0),
        K.as_batch(scene.own_position_m, batch + (3,), float, 1),
        K.as_batch(scene.own_range_m, batch, float, 0),
        K.as_batch(scene.own_los, batch, bool, 0),
        K.as_batch(scene.view_positions_m, batch + (n, 3), float, 2),
        K.as_batch(scene.view_valid, batch + (n,), bool, 1),
        K.as_batch(scene.saved_steps, batch + (n,), np.int64, 1),
        K.as_batch(scene.hops, batch + (n,), np.int64, 1),
        K.as_batch(lost, batch + (n,), bool, 1),
        K.as_batch(p_hat, batch + (3,), float, 1),
        K.as_batch(scene.information, batch + (3, 3), float, 2),
        K.as_batch(scene.observable, batch, bool, 0),
        K.as_batch(scene.perturbation_uniforms, batch + (2,), float, 1),
    )


def _kernel_config(config: PlannerConfig, step_index: int, oracle: bool, source_exact: bool, n: int) -> tuple[object, ...]:
    """The mission's planning parameters as :func:`planner.kernels.plan_batch` takes them."""
    start = config.start_positions_m
    bmin, bmax = as_boxes(config.boxes_min_m, config.boxes_max_m)
    return (
        int(step_index),
        np.zeros((n, 3)) if start is None else np.ascontiguousarray(np.asarray(start, dtype=float).reshape(n, 3)),
        start is not None,
        hop_rule(config.d_hop_m, config.limits),
        bool(oracle),
        bool(source_exact),
        bmin,
        bmax,
        kernel_limits(config.limits),
        config.channel.kernel_array,
        math.nan if config.xi is None else float(config.xi),
        float(config.perturbation_rad),
    )
