"""One drone's planning step from its view: the chain shared by the in-process simulator and
the planner node, so both compute the same thing (DESIGN.md: "build the delayed view →
estimate the source → compute the control step under constraints").

Given drone i's view (the records it holds of every drone, itself included), its estimator
state and its last displacement, :func:`plan` returns the control step of
:func:`planner.control.control_step` together with the cost of eq. 6 it descended. Batched over
leading dimensions: the simulator passes (trials, drones), a planner node passes none.

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
from planner.config import PlannerConfig
from planner.params import Channel, Criterion, Limits
from planner.sensing import COMPONENTS, SensingComponent
from tests.reference_numpy.planner.control import (
    SOURCE_INFLATION_MIN_M,
    StepResult,
    control_step,
    lost_contact_planes,
    source_activation_margin_m,
)
from tests.reference_numpy.planner.fim import CostGradient, FimStatus, cost_gradient, fisher_information
from tests.reference_numpy.planner.geometry import link_clearance_with_gradient

FloatArray = NDArray[np.float64]

#: Standard deviations of the source estimate added to d_S*.
SOURCE_SIGMA_FACTOR: float = 3.0
#: Standard deviations added to d_S* about a converged estimate (:func:`source_keepout_m`),
#: as long as they come to at most :data:`SOURCE_TAIL_MAX_M`.
SOURCE_TAIL_SIGMA_FACTOR: float = 4.0
#: Largest inflation (m) of the converged estimate's :data:`SOURCE_TAIL_SIGMA_FACTOR` σ.
SOURCE_TAIL_MAX_M: float = 4.0
#: Own ranges (the last ones, the current step's included) a ranging drone combines into a
#: lower bound on its distance to the source (:meth:`OwnRanges.lower_bound_m`).
OWN_RANGE_WINDOW: int = 10
#: Standard deviations of that lower bound.
OWN_RANGE_SIGMA_FACTOR: float = 2.0
#: Standard deviations by which a drone's own ranges must put the source nearer than its
#: estimate for the estimate to count as contradicted (:meth:`OwnRanges.contradicts`).
OWN_RANGE_CONTRADICTION_SIGMAS: float = 2.5
#: A drone loitering because its ranges contradicted its estimate holds the estimate
#: contradicted until they put the source nearer by fewer than this many standard deviations
#: (the contradiction's hysteresis, :func:`must_loiter`).
OWN_RANGE_RELEASE_SIGMAS: float = 1.0
#: A loitering drone whose estimate is still not to be trusted resumes its cost only once its
#: own ranges' lower bound reaches this many times d_S* + a (:func:`must_loiter`).
OWN_RANGE_CLEAR_FACTOR: float = 1.5
#: Softness s (m) of the predicted line of sight Φ(c/s) of a drone's own link past one
#: building (c its clearance from it, Φ the standard normal CDF): 0.5 on a shadow's edge, 0.977
#: at 2 s outside, 0.023 at 2 s inside, 1 − 3·10⁻⁵ at 4 s. Read as the probability that the
#: link is LOS when the shadow's edge is known to s metres (the estimate's error, a few metres
#: at most once the swarm has converged).
LOS_SOFTNESS_M: float = 2.0
#: Depth (in softnesses) into a shadow below which the slope of the predicted line of sight is
#: held at its value there (:func:`own_los_weight`): the way out of a deep shadow.
LOS_SLOPE_FLOOR_SOFTNESSES: float = 1.0
#: Links farther than this many softnesses from a building count as clear of it.
LOS_CUTOFF_SOFTNESSES: float = 5.0
#: Bounds the drone's own measured LOS flag puts on q: at least Φ(1) in a measured LOS, at most
#: 1 − Φ(1) in a measured NLOS.
MEASURED_LOS_MIN: float = 0.8413447460685429


def _normal_cdf(u: FloatArray) -> FloatArray:
    """Φ(u), the standard normal CDF, elementwise: scipy.special.ndtr for batches; for the few
    values of one drone (a planner node) math.erfc, which spares the node scipy.special's 0.1 s
    import and numpy's per-call overhead."""
    if u.size <= 8:
        return np.array([0.5 * math.erfc(-x / math.sqrt(2.0)) for x in u.ravel().tolist()]).reshape(u.shape)
    from scipy.special import ndtr  # imported here: see above

    return ndtr(u)


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
        softness_m: s, m.

    Returns:
        ``(q, grad_q)`` of shapes (...) and (..., 3) (1/m); 1 and zeros without buildings.
    """
    # Links more than 5 s from a building have Φ(c/s) > 1 − 3·10⁻⁷ for it: not sampled (1, ∇ 0).
    c, gc = link_clearance_with_gradient(position, source, boxes_min, boxes_max, cutoff_m=LOS_CUTOFF_SOFTNESSES * softness_m)
    u = np.maximum(c / softness_m, -30.0)  # Φ(−30) > 0: no underflow
    q = _normal_cdf(u).prod(-1)
    # The slope is taken with every clearance floored at −LOS_SLOPE_FLOOR_SOFTNESSES s.
    v = np.maximum(u, -LOS_SLOPE_FLOOR_SOFTNESSES)
    phi_v = _normal_cdf(v)
    mills = np.exp(-0.5 * v * v) / (math.sqrt(2.0 * math.pi) * phi_v)  # φ/Φ per box
    grad_q = phi_v.prod(-1)[..., None] * (mills[..., None] * gc).sum(-2) / softness_m
    if measured_los is not None:
        m = np.asarray(measured_los, dtype=bool)
        q = np.where(m, np.maximum(q, MEASURED_LOS_MIN), np.minimum(q, 1.0 - MEASURED_LOS_MIN))
    return q, grad_q


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
    sigma = np.asarray(sigma_m, dtype=float)
    tail = np.minimum(SOURCE_TAIL_SIGMA_FACTOR * sigma, SOURCE_TAIL_MAX_M)
    inflation = np.maximum(np.maximum(SOURCE_SIGMA_FACTOR * sigma, tail), min(SOURCE_INFLATION_MIN_M, limits.d_source_m))
    return limits.d_source_m + np.minimum(inflation, limits.d_source_m)


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
    last_r = np.asarray(last_radius_m, dtype=float)
    moved = np.linalg.norm(x - np.asarray(centre_m, dtype=float), axis=-1) - np.linalg.norm(x - np.asarray(last_centre_m, dtype=float), axis=-1)
    floor = limits.d_source_m + min(SOURCE_INFLATION_MIN_M, limits.d_source_m)
    with np.errstate(invalid="ignore"):
        limited = np.minimum(r, np.maximum(last_r + moved + limits.turn_buffer_m, floor))
    uncertain = SOURCE_SIGMA_FACTOR * np.asarray(sigma_m, dtype=float) >= limits.d_source_m
    return np.where(uncertain & np.isfinite(r) & np.isfinite(last_r), limited, r)


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

    def relative_sd(self, distance_m: ArrayLike) -> FloatArray:
        """r(d), the relative standard deviation of d̄ about a distance d (m); +inf without ranges."""
        d = np.maximum(np.asarray(distance_m, dtype=float), 1e-9)
        info = self.weight * d ** (2.0 - self.gamma)
        return np.where(self.weight > 0.0, 1.0 / np.sqrt(np.where(info > 0.0, info, 1.0)), np.inf)

    def lower_bound_m(self, sigma_factor: float = OWN_RANGE_SIGMA_FACTOR) -> FloatArray:
        """Lower confidence bound (m) on the distance: d̄ / (1 + k r(d̄)), which exceeds d with
        probability Φ(−k) (2.3 % at k = 2); +inf without ranges. Ten NLOS ranges give a bound
        32 % below their mean (twenty: 25 %)."""
        have = self.weight > 0.0
        dbar = np.where(have, self.mean_m, 1.0)
        return np.where(have, dbar / (1.0 + sigma_factor * self.relative_sd(dbar)), np.inf)

    def contradicts(self, distance_m: ArrayLike, sigma_factor: ArrayLike = OWN_RANGE_CONTRADICTION_SIGMAS) -> NDArray[np.bool_]:
        """True where the ranges say the source is nearer than ``distance_m`` (the distance to
        the estimate, m): z = (d̄/d − 1)/r(d) < −k, k = ``sigma_factor`` (broadcast), the
        one-sided test of d̄ against a source at that distance (false alarm Φ(−k), 0.62 % at the
        default k = 2.5). False without ranges."""
        d = np.maximum(np.asarray(distance_m, dtype=float), 1e-9)
        have = self.weight > 0.0
        z = (np.where(have, self.mean_m, 0.0) / d - 1.0) / self.relative_sd(d)
        return np.asarray(have & (z < -np.asarray(sigma_factor, dtype=float)), dtype=bool)


def own_ranges(range_m: ArrayLike, los: ArrayLike, channel: Channel) -> OwnRanges:
    """Combine a drone's own last ranges into :class:`OwnRanges`.

    Args:
        range_m: (..., W) the drone's own measured ranges d̂ (eq. 3), m; NaN = no range.
        los: (..., W) bool, the LOS flag of each.
        channel: σ_r0 (LOS/NLOS) and γ of eq. 5.
    """
    r = np.asarray(range_m, dtype=float)
    have = np.isfinite(r)
    s0 = channel.sigma_r0(los)
    w0 = np.where(have, 1.0 / s0**2, 0.0)
    sw0 = w0.sum(-1)
    dbar = np.where(sw0 > 0.0, (w0 * np.where(have, r, 0.0)).sum(-1) / np.where(sw0 > 0.0, sw0, 1.0), np.nan)
    return OwnRanges(mean_m=np.asarray(dbar, dtype=float), weight=np.asarray(sw0, dtype=float), gamma=float(channel.gamma))


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
    sigma = np.asarray(sigma_m, dtype=float)
    untrusted = ~np.asarray(observable, dtype=bool) | (SOURCE_SIGMA_FACTOR * sigma >= limits.d_source_m) | contradicted(own, distance_m, loitering)
    near = limits.d_source_m + source_activation_margin_m(limits)
    lower = own.lower_bound_m()
    was = np.zeros((), dtype=bool) if loitering is None else np.asarray(loitering, dtype=bool)
    stay = was & (lower < OWN_RANGE_CLEAR_FACTOR * near)
    return np.asarray(untrusted & ((lower < near) | stay))


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


def collision_relevant(hops: ArrayLike, d_hop_m: float, limits: Limits) -> NDArray[np.bool_]:
    """Which peers a drone must keep clear of this step, from its hop counts (..., N).

    A peer that is not a direct neighbour (h_ij ≠ 1) is farther than d_hop right now, so it
    cannot come within d_U* during the next step when d_hop ≥ d_U* + 3 v_max Δt + 2 turn
    buffers; its (stale) position is then ignored. With a smaller radius every known peer
    counts, with its age (see :func:`planner.control.control_step`).
    """
    h = np.asarray(hops)
    reach = limits.d_uav_m + 3.0 * limits.step_max_m + 2.0 * limits.turn_buffer_m
    if d_hop_m >= reach:
        return h == 1
    return np.ones(h.shape, dtype=bool)


def estimate_sigma_m(information: ArrayLike) -> FloatArray:
    """Largest standard deviation (m) of an estimate with Fisher information (..., 3, 3)."""
    lmin = np.linalg.eigvalsh(np.asarray(information, dtype=float))[..., 0]
    return np.where(lmin > 0.0, 1.0 / np.sqrt(np.maximum(lmin, 1e-300)), np.inf)


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
    """A planning step: the control step and the cost it descended (at the estimate)."""

    step: StepResult
    cost: CostGradient
    keepout_m: FloatArray
    #: (..., 3) m, ENU, the centre of the keep-out of ``keepout_m`` (the estimate it planned with).
    keepout_centre_m: FloatArray
    #: (...) bool, the drone loitered: its own ranges put the source within reach of d_S*
    #: and its estimate gave no direction to trust (:func:`loiter_gradient`).
    loiter: NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class PlanView:
    """Drone i's delayed view as arrays (leading batch dims ``...``; N drones, itself included).

    Attributes:
        own_mask: (..., N) bool, True at drone i's own row.
        positions_m: (..., N, 3) positions of the records in the view, m, ENU.
        valid: (..., N) bool, the view holds a record of that drone.
        los: (..., N) bool, LOS flag of each record.
        age_steps: (..., N) k − ℓ, the age in steps of each record (0 where none).
        hops: (..., N) hop counts from drone i (−1 unreachable), for :func:`collision_relevant`.
        drift_m: (..., N, 3) each peer's last step as drone i's last two records of it give it,
            m per step, ENU (NaN: unknown; :class:`PeerDrift`); None: unknown for all.
    """

    own_mask: NDArray[np.bool_]
    positions_m: FloatArray
    valid: NDArray[np.bool_]
    los: NDArray[np.bool_]
    age_steps: NDArray[np.int64]
    hops: NDArray[np.int64]
    drift_m: FloatArray | None = None

    @classmethod
    def from_records(cls, own_index: int, records: Sequence[_Record | None], saved_steps: ArrayLike, step_index: int, hops: ArrayLike) -> PlanView:
        """One drone's view from its records (None where it holds none), the step ℓ of each
        (``saved_steps``), the current step k and its hop counts."""
        n = len(records)
        positions, valid, los = records_as_arrays(records)
        own = np.zeros(n, dtype=bool)
        own[own_index] = True
        ages = np.where(valid, step_index - np.asarray(saved_steps), 0)
        return cls(own, positions, valid, los, ages, np.asarray(hops))


#: The longest gap (steps) between two records of a peer that still gives its last step.
DRIFT_MAX_GAP_STEPS = 4


@dataclass(frozen=True, eq=False)
class PeerDrift:
    """Each peer's last step as drone i's records of it give it (leading batch dims ``...``).

    Attributes:
        positions_m: (..., N, 3) the newest record of each peer, m, ENU (NaN: none).
        saved_steps: (..., N) its step ℓ (−1: none).
        drift_m: (..., N, 3) the peer's mean step between its two newest records, m per step,
            ENU; NaN where drone i holds fewer than two, or they are more than
            :data:`DRIFT_MAX_GAP_STEPS` steps apart.
    """

    positions_m: FloatArray
    saved_steps: NDArray[np.int64]
    drift_m: FloatArray

    def update(self, positions_m: ArrayLike, saved_steps: ArrayLike, valid: ArrayLike) -> PeerDrift:
        """The drift after this step's view: ``positions_m`` (..., N, 3), m, of the records
        taken at ``saved_steps`` (..., N), where ``valid``."""
        pos = np.asarray(positions_m, dtype=float)
        ok = np.asarray(valid, dtype=bool)
        saved = np.where(ok, np.asarray(saved_steps), -1)
        new = ok & (saved > self.saved_steps)
        gap = saved - self.saved_steps
        usable = new & (self.saved_steps >= 0) & (gap <= DRIFT_MAX_GAP_STEPS)
        step = (pos - self.positions_m) / np.maximum(gap, 1)[..., None]
        drift = np.where(usable[..., None], step, np.where(new[..., None], np.nan, self.drift_m))
        return PeerDrift(np.where(new[..., None], pos, self.positions_m), np.where(new, saved, self.saved_steps), drift)

    @classmethod
    def empty(cls, shape: tuple[int, ...]) -> PeerDrift:
        """No record yet, for views of shape ``shape`` (..., N)."""
        return cls(np.full(shape + (3,), np.nan), np.full(shape, -1, dtype=np.int64), np.full(shape + (3,), np.nan))


class SourceEstimate(Protocol):
    """What :func:`plan` reads of a drone's source estimate (an
    :class:`planner.estimator.EstimatorState` is one)."""

    @property
    def estimate_m(self) -> FloatArray:
        """p̂0, (..., 3), m, ENU."""
        ...

    @property
    def information(self) -> FloatArray:
        """Its Fisher information, (..., 3, 3), m⁻²."""
        ...

    @property
    def observable(self) -> NDArray[np.bool_]:
        """(...) bool, the source is locally identifiable."""
        ...


class _Record(Protocol):
    """What :class:`PlanView` reads of a record: where it was taken and its LOS flag."""

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


def _status_and_keepout(
    cg: CostGradient,
    own_position: ArrayLike,
    p_hat: FloatArray,
    estimate: SourceEstimate,
    limits: Limits,
    *,
    oracle: bool,
    own: OwnRanges | None,
    loitering: ArrayLike | None,
    last_keepout: tuple[ArrayLike, ArrayLike] | None = None,
) -> tuple[NDArray[np.int8], FloatArray, NDArray[np.bool_]]:
    """The FIM status the control step sees, the source keep-out radius (...), m, and where the
    drone loiters (...) instead of descending its cost.

    With an oracle source: the cost's status, the plain d_S* and no loiter. Otherwise an
    estimate that is not observable counts as a singular FIM (the paper's fallback) and has no
    keep-out (−inf); an observable one has :func:`source_keepout_m` of its largest σ, limited
    by :func:`followable_keepout_m` against ``last_keepout`` (centre (..., 3), radius (...), m,
    of the last step). With the drone's own ranges (``own``) it loiters where
    :func:`must_loiter` says so (its status then OK: the loiter is not the singular fallback's
    wander), and keeps no keep-out where it is inside it and its ranges contradict it.
    """
    obs = np.asarray(estimate.observable, dtype=bool)
    batch = np.shape(own_position)[:-1]
    if oracle:
        return cg.status, np.full(batch, limits.d_source_m), np.zeros(batch, dtype=bool)
    status = np.where(obs, cg.status, np.int8(FimStatus.SINGULAR))
    sigma = estimate_sigma_m(estimate.information)
    keepout = np.where(obs, source_keepout_m(limits, sigma), -np.inf)
    if last_keepout is not None:
        keepout = followable_keepout_m(limits, own_position, p_hat, keepout, sigma, last_keepout[0], last_keepout[1])
    if own is None:
        return status, keepout, np.zeros(batch, dtype=bool)
    d_est = np.linalg.norm(np.asarray(own_position, dtype=float) - p_hat, axis=-1)
    loiter = np.broadcast_to(must_loiter(limits, sigma, obs, d_est, own, loitering), batch)
    # A loitering drone whose own ranges contradict its estimate keeps no keep-out about that
    # estimate where it is inside it. Kept, the keep-out about an estimate 140 m off on the far
    # side pushed a loitering drone straight at the source (paper/ranging_nlos A, 20 % loss and
    # 3 steps of delay, trial 82: 29.6 m inside d_S*), as the filter's fallback tier picks the
    # step that gains the most clearance from it. Outside it, it keeps it: its own noisy ranges can contradict a right
    # estimate, and without it drones of paper/joint D and paper/heterogeneous A (20 % loss)
    # loitering by a converged estimate (0.2-0.5 m off) came up to 0.30 m inside d_S*. An
    # uncertain estimate the ranges do not contradict is still the best guess of where the
    # source is: dropped about it too, a loitering drone of paper/dynamic_source D (3 steps of
    # delay, trial 25), its estimate 0.5-18 m off, was 3.5 m inside d_S* as the source drifted
    # in over 71 steps.
    keepout = np.where(loiter & contradicted(own, d_est) & (d_est < keepout), -np.inf, keepout)
    return np.where(loiter, np.int8(FimStatus.OK), status), keepout, loiter


def loiter_gradient(previous_step: ArrayLike) -> FloatArray:
    """The gradient (..., 3) a loitering drone descends: minus the horizontal unit vector 90°
    to the left of its last step (east where it has none). The step of eq. 14 asks a quarter
    turn; the heading limit φ_max of eq. 2 grants φ_max a step, so the drone flies a level circle
    of circumference v_max Δt · 360°/φ_max (7.2 m at 1 m/step and 50°) about where it started
    loitering, under the same constraints and safety filter as any step: it makes no net
    progress in any direction, toward a source whose direction it does not know."""
    u = np.asarray(previous_step, dtype=float)
    left = np.stack((-u[..., 1], u[..., 0], np.zeros(u.shape[:-1])), axis=-1)
    n = np.linalg.norm(left, axis=-1, keepdims=True)
    east = np.broadcast_to(np.array([1.0, 0.0, 0.0]), left.shape)
    return -np.where(n > 1e-12, left / np.where(n > 1e-12, n, 1.0), east)


def _peer_constraints(
    config: PlannerConfig,
    view: PlanView,
    step_index: int,
    lost_contact: ArrayLike | None,
    own_then_m: ArrayLike | None,
) -> tuple[FloatArray, NDArray[np.bool_], NDArray[np.int64], FloatArray | None]:
    """The peer rows of the anti-collision constraint: (rows (..., N, 3), m, ENU, mask (..., N),
    ages (..., N) in steps, plane normals (..., N, 3) or None).

    Peers heard directly (:func:`collision_relevant`); a lost-contact peer as its bisector
    plane (:func:`planner.control.lost_contact_planes`, age 0); a peer never heard of at its
    start position of ``config.start_positions_m``, aged ``step_index`` steps (see :func:`plan`).
    """
    valid = np.asarray(view.valid, dtype=bool)
    own = np.asarray(view.own_mask, dtype=bool)
    relevant = collision_relevant(view.hops, config.d_hop_m, config.limits)
    peer_rows = np.asarray(view.positions_m, dtype=float)
    ages = np.where(valid, view.age_steps, 0)
    planes = None
    if lost_contact is not None and np.asarray(lost_contact).any():
        if own_then_m is None:
            raise ValueError("plan: lost_contact needs own_then_m (the drone's positions at the peers' last records)")
        lost = np.asarray(lost_contact, dtype=bool) & valid & ~own
        peer_rows, planes = lost_contact_planes(own_then_m, peer_rows, lost)
        relevant = relevant | lost
        ages = np.where(lost, 0, ages)
    peers = valid & ~own & relevant
    if config.start_positions_m is not None:
        unheard = ~valid & ~own & relevant
        start = np.broadcast_to(np.asarray(config.start_positions_m, dtype=float), peer_rows.shape)
        peer_rows = np.where(unheard[..., None], start, peer_rows)
        ages = np.where(unheard, int(step_index), ages)
        peers = peers | unheard
    return peer_rows, peers, ages, planes


def plan(
    config: PlannerConfig,
    own_position: ArrayLike,
    previous_step: ArrayLike,
    view: PlanView,
    estimate: SourceEstimate,
    perturbation_uniforms: ArrayLike,
    *,
    step_index: int = 0,
    oracle_source: ArrayLike | None = None,
    oracle_slow: bool = True,
    own_ranges: OwnRanges | None = None,
    loitering: ArrayLike | None = None,
    last_keepout: tuple[ArrayLike, ArrayLike] | None = None,
    lost_contact: ArrayLike | None = None,
    own_then_m: ArrayLike | None = None,
) -> PlanResult:
    """Drone i's planning step from its view (eqs. 6, 10-17).

    Args:
        config: the mission's planning parameters (channel, limits, criterion, roles,
            buildings, d_hop, start positions, controller settings).
        own_position: p_i^(k) (..., 3), m, ENU. previous_step: u_i^(k) (..., 3), m.
        view: drone i's delayed view (:class:`PlanView`).
        estimate: drone i's estimator state (its estimate, information and observability).
        perturbation_uniforms: (..., 2) uniforms for the singular fallback.
        step_index: k, the current step (≥ 0), the age of a start position.
        oracle_source: plan with this source position instead of the estimate (research mode:
            the paper's "estimate given"), with the plain d_S* keep-out.
        oracle_slow: the oracle source moves less than b per step
            (:meth:`missions.schema.Mission.source_is_slow`): its constraint then acts within
            v_max Δt + b, one step of the drone's own motion
            (:func:`planner.control.source_activation_margin_m` with ``exact``); a faster one
            keeps the estimate's 2 v_max Δt + b.
        own_ranges: drone i's own last :data:`OWN_RANGE_WINDOW` ranges (:func:`own_ranges`;
            none for a drone that does not range): the evidence of its distance to the source
            that does not depend on the estimate: where they put the source within reach and
            the estimate gives no direction to trust, the drone loiters (:func:`must_loiter`,
            :func:`loiter_gradient`). None: the keep-out about the estimate alone.
        loitering: (...) bool, drone i loitered at its last step (:attr:`PlanResult.loiter`;
            the hysteresis of :func:`must_loiter`). None: it did not.
        last_keepout: drone i's keep-out of its last step, (:attr:`PlanResult.keepout_centre_m`,
            :attr:`PlanResult.keepout_m`): the keep-out about an uncertain estimate advances on
            the drone by at most b per step (:func:`followable_keepout_m`). None: not limited.
        lost_contact: (..., N) bool, peers this drone has lost contact with by a network fault
            (a partition, their planner gone from the liveliness view), not by distance: the
            hop argument of :func:`collision_relevant` ("not a neighbour, so farther than
            d_hop") does not hold for them. The drone keeps to its side of the bisector plane
            between its own position and the peer's at the step of the peer's last record, at
            least d_U*/2 from it (:func:`planner.control.lost_contact_planes`); the peer does
            the same on its side. None: no such peer.
        own_then_m: (..., N, 3), m, ENU: drone i's own position at the step of each peer's
            last record (needed with ``lost_contact``).

    A peer drone i holds no record of yet (its first records are late or lost) is kept clear
    of as if its start position (``config.start_positions_m``, the mission's start, known to
    all) were its record of step 0, aged ``step_index`` steps: it is within ``step_index + 1``
    v_max Δt of it at the end of this step. Its row is used for the anti-collision constraint
    only (no measurement). With no start positions such a peer is not a constraint.
    """
    channel, limits, criterion = config.channel, config.limits, config.criterion
    boxes_min, boxes_max = config.boxes_min_m, config.boxes_max_m
    own = np.asarray(view.own_mask, dtype=bool)
    valid = np.asarray(view.valid, dtype=bool)
    ranging, bearing = np.asarray(config.ranging, dtype=bool), np.asarray(config.bearing, dtype=bool)
    own_ranging, own_bearing = (ranging & own).any(-1), (bearing & own).any(-1)
    extra = {name: np.asarray(mask, dtype=bool) for name, mask in config.extra_masks.items()}
    extra_view = {name: mask & valid for name, mask in extra.items()}
    own_extra = {name: (mask & own).any(-1) for name, mask in extra.items()}
    estimate_m = estimate.estimate_m
    p_hat = (
        np.asarray(estimate_m, dtype=float)
        if oracle_source is None
        else np.broadcast_to(np.asarray(oracle_source, dtype=float), np.shape(estimate_m))
    )
    cg = _planning_cost(
        p_hat,
        own_position,
        own,
        view.positions_m,
        ranging & valid,
        bearing & valid,
        view.los,
        own_ranging,
        own_bearing,
        channel,
        criterion,
        boxes_min,
        boxes_max,
        extra_view,
        own_extra,
        config.sensing.components,
    )
    status, keepout, loiter = _status_and_keepout(
        cg,
        own_position,
        p_hat,
        estimate,
        limits,
        oracle=oracle_source is not None,
        own=own_ranges,
        loitering=loitering,
        last_keepout=last_keepout,
    )
    gradient = np.where(loiter[..., None], loiter_gradient(previous_step), cg.gradient) if loiter.any() else cg.gradient
    peer_rows, peers, ages, planes = _peer_constraints(config, view, step_index, lost_contact, own_then_m)
    step = control_step(
        own_position,
        previous_step,
        gradient,
        status,
        peer_rows,
        peers,
        ages,
        p_hat,
        keepout,
        boxes_min,
        boxes_max,
        limits,
        perturbation_uniforms,
        xi=config.xi,
        perturbation_rad=config.perturbation_rad,
        peer_planes=planes,
        source_exact=oracle_source is not None and oracle_slow,
        peer_drift_m=view.drift_m,
    )
    return PlanResult(step=step, cost=cg, keepout_m=np.asarray(keepout), keepout_centre_m=np.asarray(p_hat), loiter=loiter)
