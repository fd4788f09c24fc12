"""Optimal placement of a swarm: the smallest A/D cost (and its PEB) any placement allows.

A reference for the planner: where would the N drones best be, all at once, for a source at
``source`` (known, the paper's "estimate given"), under the distances the control rule keeps?
The planner descends the cost of eq. 6 one drone at a time from a delayed view; this solves
problem (7) of the paper for the whole swarm at once, without kinematics:

.. math::
    \\min_{\\mathbf q = [\\mathbf p_1 \\dots \\mathbf p_N]} C(\\mathbf J(\\mathbf p_0; \\mathbf q))
    \\quad\\text{s.t.}\\quad
    \\lVert\\mathbf p_j - \\mathbf p_0\\rVert \\ge R_S,\\
    \\lVert\\mathbf p_i - \\mathbf p_j\\rVert \\ge R_U,\\
    d_O(\\mathbf p_j) \\ge R_O,\\
    z_{lo} \\le z_j \\le z_{hi}

with C = tr J⁻¹ (A) or −ln det J (D) of eq. 6, J the FIM of eqs. 10-12 with every drone's
record (:func:`planner.fim.fisher_information`), d_O the distance to the nearest building
(eq. 17) and the distances R of :class:`PlacementBounds` (:func:`placement_bounds`: the paper's
d_S*, d_U*, d_O* and altitude box, plus by default the clearances fimnav's safe rule keeps at
the end of every step). The result reports the PEB = sqrt(tr J⁻¹) of eq. 18 at the source.

Line of sight. A link in a building's shadow has an NLOS range (σ_sh/γ of NLOS) and no bearing
(eq. 3's indicator p_j), so J jumps at a shadow's edge. The optimisation uses the smooth
predicted LOS of the planner (:func:`planner.agent.own_los_weight`): each link's FIM term is
q J_LOS + (1 − q) J_NLOS with q = Π_b Φ(c_b/s), c_b the link's clearance from building b
(:func:`planner.geometry.link_clearance_with_gradient`, negative across it), first with
s = 2 m, then s = 0.5 m (:data:`LOS_SOFTNESS_SCHEDULE_M`). The reported cost and PEB use the
exact LOS flags (:func:`planner.geometry.line_of_sight`) at the returned placement; a drone the
optimiser leaves outside every shadow has q < 1 but the flag 1, so the reported PEB is at most
the smoothed optimum's.

Solver: SLSQP (scipy.optimize) over the 3N coordinates with analytic gradients of the cost
(:func:`planner.fim.cost_gradient`, per drone, with the LOS weight's gradient) and of the
constraints, from ``starts`` random starts drawn from ``numpy.random.default_rng(seed)`` (no
global RNG): distance uniform in [R_S, 1.1 R_S], uniform on that sphere within the altitude
box, in LOS where a few draws find it (:func:`_random_start`).
The A cost is minimised as ln tr J⁻¹ (same minimiser, better scaled). The result is the best
start whose placement keeps every distance (to :data:`FEASIBILITY_TOL_M`). A local method from
a few starts: the value is an upper bound on the global optimum, tight in the tested cases
(``tests/planner/test_placement.py``: a closed form, an independent L-BFGS-B reference).

Frame and units: mission ENU, metres; angles in radians. Cost: m² (A) or dimensionless (D).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import minimize
from scipy.special import ndtr

from planner.agent import SOURCE_INFLATION_MIN_M
from planner.control import altitude_activation_margin_m, source_activation_margin_m
from planner.fim import cost as fim_cost
from planner.fim import cost_gradient, fisher_information, position_error_bound
from planner.geometry import distance_to_boxes, distance_to_boxes_with_gradient, line_of_sight, link_clearance_with_gradient
from planner.params import Channel, Criterion, Limits
from planner.sensing import COMPONENTS, SensingComponent

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Which distances :func:`placement_bounds` returns (see there): ``"filter"`` (default) the
#: clearances the safe rule's safety filter requires at the end of every step, ``"hold"`` the
#: distances at which the rule's projection holds a converged drone, ``"none"`` the bare
#: distances of problem (7) (d_S*, d_U*, d_O*, the altitude box).
MarginRule = Literal["filter", "hold", "none"]

#: Softness (m) of the predicted LOS, per optimisation stage (see the module docstring).
LOS_SOFTNESS_SCHEDULE_M: tuple[float, ...] = (2.0, 0.5)
#: Points sampled on each link for its clearance from the buildings (16 in the planner; more
#: here: the shadow's edge to ~1 m at 50 m).
LINK_SAMPLES: int = 64
#: A placement keeps its distances when no margin is below −this (m).
FEASIBILITY_TOL_M: float = 1e-6
#: Draws of a start position before an NLOS one is kept (:func:`_random_start`).
START_LOS_TRIES: int = 20
#: SLSQP's iteration cap and tolerance on the (log-scaled) cost, per stage.
SLSQP_MAXITER: int = 400
SLSQP_FTOL: float = 1e-10
#: Cost of a placement whose J is singular (the solver must leave it; never returned as optimal).
_SINGULAR_PENALTY: float = 1e6
#: No buildings: the default obstacle boxes of :func:`optimal_placement`, shape (0, 3).
_NO_BOXES = np.zeros((0, 3))


@dataclass(frozen=True)
class PlacementBounds:
    """Distances every drone of a placement keeps (m, ENU) and how they were derived.

    Attributes:
        source_m: R_S, smallest distance from the source.
        uav_m: R_U, smallest distance between two drones.
        obstacle_m: R_O, smallest distance from any building surface.
        z_min_m, z_max_m: altitude box (ENU up).
        rule: how the distances were derived (:data:`MarginRule`, or ``"custom"``).
        source_margin_m, uav_margin_m, obstacle_margin_m, altitude_margin_m: what was added to
            d_S*, d_U*, d_O* and taken off each face of the altitude box.
    """

    source_m: float
    uav_m: float
    obstacle_m: float
    z_min_m: float
    z_max_m: float
    rule: str = "custom"
    source_margin_m: float = 0.0
    uav_margin_m: float = 0.0
    obstacle_margin_m: float = 0.0
    altitude_margin_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("source_m", "uav_m", "obstacle_m"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"PlacementBounds.{name} must be finite and >= 0, found {value!r}")
        if not self.z_min_m <= self.z_max_m:
            raise ValueError(f"PlacementBounds: expected z_min_m <= z_max_m, found {self.z_min_m} and {self.z_max_m}")


def placement_bounds(limits: Limits, rule: MarginRule = "filter", oracle_estimate: bool = False, source_slow: bool = True) -> PlacementBounds:
    """The distances a placement keeps, from a mission's limits (docs/control.md, "Constraint
    activation"; b = :attr:`Limits.turn_buffer_m`, a = 2 v_max Δt + b the activation margin,
    :func:`planner.control.source_activation_margin_m`). ``source_slow``: the source moves less than
    b per step (:meth:`missions.schema.Mission.source_is_slow`; with ``oracle_estimate``, the hold
    margins are then the drone's own step).

    The source keep-out of the default rule is held about the estimate: d_S* + max(3σ, min(4σ,
    3 m), 1.5 m), which for a converged estimate (4σ below 1.5 m) is d_S* + 1.5 m, the inflation floor
    :data:`planner.agent.SOURCE_INFLATION_MIN_M`; planning with the true source
    (``oracle_estimate``, ``fimnav montecarlo --oracle-estimate``) it is d_S*. Below, K is that
    keep-out.

    ``rule="filter"`` (default): the clearances the safe rule's safety filter requires at the
    end of every step, so no placement the rule ends a step in does better: source K + b, peers
    d_U* + v_max Δt + 2b (fresh records), buildings d_O* + ½ v_max Δt + b, the whole altitude
    box (the tilt allowance is zero for a level drone). Paper values: R_S = 52.14 m (oracle
    50.64 m), R_U = 3.29 m, R_O = 6.14 m, z in [2, 25] m.

    ``rule="hold"``: where the projection of eq. 14 holds a drone the gradient presses against a
    constraint: each constraint acts within a of its clearance and the correction pushes the
    drone back to it: source K + a, peers d_U* + 2 v_max Δt + 2b, buildings d_O* + a, a inside
    each face of the altitude box. Paper values: R_S = 54.14 m, z in [4.64, 22.36] m. A 2-trial
    run of paper/joint ends with a median distance of 53.96 m and a median altitude of 22.36 m:
    the drones circle between K + b and K + a. With ``oracle_estimate`` and ``source_slow``
    (the true source, moving less than b per step) the source and the altitude faces act within one step of the
    drone's own motion (:func:`planner.control.source_activation_margin_m`,
    :func:`planner.control.altitude_activation_margin_m`): R_S = d_S* + v_max Δt + b = 51.64 m,
    z in [2.77, 24.23] m; a faster true source keeps the estimate's margins.

    ``rule="none"``: problem (7) as printed: d_S*, d_U*, d_O*, [z_min, z_max].

    With the paper's activation rule (``limits.activation == "paper"``) there is no filter and no
    activation margin: ``"filter"`` and ``"hold"`` are d_S* (+ 1.5 m about an estimate), d_U*,
    d_O* and the box.
    """
    if rule == "none":
        return PlacementBounds(limits.d_source_m, limits.d_uav_m, limits.d_obstacle_m, limits.z_min_m, limits.z_max_m, rule="none")
    if rule not in ("filter", "hold"):
        raise ValueError(f"rule: expected 'filter', 'hold' or 'none', found {rule!r}")
    safe = limits.activation == "safe"
    inflation = 0.0 if oracle_estimate else min(SOURCE_INFLATION_MIN_M, limits.d_source_m)
    smax, b = limits.step_max_m, limits.turn_buffer_m
    if not safe:
        src, uav, obs, alt = 0.0, 0.0, 0.0, 0.0
    elif rule == "filter":
        src, uav, obs, alt = b, smax + 2.0 * b, 0.5 * smax + b, 0.0
    else:
        a = source_activation_margin_m(limits)
        exact = oracle_estimate and source_slow
        a_src = source_activation_margin_m(limits, exact=exact)
        a_alt = altitude_activation_margin_m(limits, exact_source=exact)
        src, uav, obs, alt = a_src, 2.0 * smax + 2.0 * b, a, min(a_alt, 0.5 * (limits.z_max_m - limits.z_min_m))
    return PlacementBounds(
        source_m=limits.d_source_m + inflation + src,
        uav_m=limits.d_uav_m + uav,
        obstacle_m=limits.d_obstacle_m + obs,
        z_min_m=limits.z_min_m + alt,
        z_max_m=limits.z_max_m - alt,
        rule=rule,
        source_margin_m=inflation + src,
        uav_margin_m=uav,
        obstacle_margin_m=obs,
        altitude_margin_m=alt,
    )


@dataclass(frozen=True)
class Placement:
    """An optimal placement and its PEB.

    Attributes:
        positions_m: p_j, (N, 3), m, ENU.
        los: (N,) bool, exact LOS flag of each drone's link to the source.
        peb_m: PEB = sqrt(tr J⁻¹) (eq. 18) at the source, with every drone's record, m.
        cost: C of eq. 6 for ``criterion`` (tr J⁻¹ in m² for A, −ln det J for D), exact LOS.
        criterion: ``"A"`` or ``"D"``.
        source_m: p_0, (3,), m, ENU.
        bounds: the distances kept.
        margins_m: worst margin per family (``source``, ``uav``, ``obstacle``, ``altitude``):
            distance minus its bound (m; ``inf`` for a family with nothing to keep).
        start_costs: (starts,) the cost each start reached (+inf: no feasible placement).
        best_start: index of the start returned.
        seed, starts: as given.
    """

    positions_m: FloatArray
    los: BoolArray
    peb_m: float
    cost: float
    criterion: Criterion
    source_m: FloatArray
    bounds: PlacementBounds
    margins_m: dict[str, float]
    start_costs: FloatArray
    best_start: int
    seed: int
    starts: int
    evaluations: int = field(default=0)

    @property
    def distances_m(self) -> FloatArray:
        """Distance of each drone from the source (N,), m."""
        return np.linalg.norm(self.positions_m - self.source_m, axis=-1)

    @property
    def azimuths_rad(self) -> FloatArray:
        """Azimuth of each drone seen from the source (N,), rad, from east towards north."""
        r = self.positions_m - self.source_m
        return np.arctan2(r[:, 1], r[:, 0])


def placement_margins(
    positions: ArrayLike, source: ArrayLike, bounds: PlacementBounds, boxes_min: ArrayLike, boxes_max: ArrayLike
) -> dict[str, float]:
    """Worst margin (m) of a placement per family: distance minus its bound.

    ``source``: min_j |p_j − p_0| − R_S; ``uav``: min_{i<j} |p_i − p_j| − R_U (inf for one
    drone); ``obstacle``: min_j d_O(p_j) − R_O (inf without buildings); ``altitude``:
    min_j min(z_j − z_lo, z_hi − z_j). Non-negative everywhere = the placement keeps them all.
    """
    p = np.asarray(positions, dtype=float).reshape(-1, 3)
    s = np.asarray(source, dtype=float)
    n = p.shape[0]
    iu = np.triu_indices(n, 1)
    pair = np.linalg.norm(p[:, None] - p[None], axis=-1)[iu]
    return {
        "source": float(np.linalg.norm(p - s, axis=-1).min() - bounds.source_m),
        "uav": float(pair.min() - bounds.uav_m) if pair.size else math.inf,
        "obstacle": float(distance_to_boxes(p, boxes_min, boxes_max).min() - bounds.obstacle_m),
        "altitude": float(np.minimum(p[:, 2] - bounds.z_min_m, bounds.z_max_m - p[:, 2]).min()),
    }


def _soft_los(p: FloatArray, s: FloatArray, bmin: FloatArray, bmax: FloatArray, softness_m: float) -> tuple[FloatArray, FloatArray]:
    """Predicted LOS q = Π_b Φ(c_b/s) of each link (N,) and ∇_p q (N, 3), 1/m (as
    :func:`planner.agent.own_los_weight`, with :data:`LINK_SAMPLES` points per link)."""
    c, gc = link_clearance_with_gradient(p, s, bmin, bmax, samples=LINK_SAMPLES, cutoff_m=5.0 * softness_m)
    u = np.maximum(c / softness_m, -30.0)
    phi = ndtr(u)
    q = phi.prod(-1)
    mills = np.exp(-0.5 * u * u) / (math.sqrt(2.0 * math.pi) * phi)
    return q, q[:, None] * (mills[..., None] * gc).sum(-2) / softness_m


def _source_jacobian(p: FloatArray, source: FloatArray) -> FloatArray:
    """∂|p_j − p_0|/∂x (N, 3N): the unit vector from the source, in drone j's block."""
    n = p.shape[0]
    ds = p - source
    dist = np.linalg.norm(ds, axis=-1)
    js = np.zeros((n, n, 3))
    js[np.arange(n), np.arange(n)] = ds / np.where(dist > 0.0, dist, 1.0)[:, None]
    return js.reshape(n, 3 * n)


def _pair_jacobian(p: FloatArray, pairs: tuple[NDArray[np.intp], NDArray[np.intp]]) -> FloatArray:
    """∂|p_i − p_j|/∂x (pairs, 3N): ± the unit vector between the pair, in their blocks."""
    n = p.shape[0]
    i, j = pairs
    dp = p[i] - p[j]
    dd = np.linalg.norm(dp, axis=-1)
    unit = dp / np.where(dd > 0.0, dd, 1.0)[:, None]
    jp = np.zeros((i.size, n, 3))
    k = np.arange(i.size)
    jp[k, i] = unit
    jp[k, j] = -unit
    return jp.reshape(i.size, 3 * n)


def _obstacle_jacobian(p: FloatArray, bmin: FloatArray, bmax: FloatArray) -> FloatArray:
    """∂(distance to the nearest building)/∂x (N, 3N), in drone j's block."""
    n = p.shape[0]
    _, g = distance_to_boxes_with_gradient(p, bmin, bmax)
    jo = np.zeros((n, n, 3))
    jo[np.arange(n), np.arange(n)] = g
    return jo.reshape(n, 3 * n)


class _Problem:
    """Cost and constraints of one optimisation, in the flat variables x = q.ravel() (3N,)."""

    def __init__(
        self,
        source: FloatArray,
        ranging: BoolArray,
        bearing: BoolArray,
        channel: Channel,
        criterion: Criterion,
        bounds: PlacementBounds,
        bmin: FloatArray,
        bmax: FloatArray,
        extra_masks: Mapping[str, BoolArray] | None = None,
        components: Sequence[SensingComponent] = COMPONENTS,
    ) -> None:
        self.source, self.ranging, self.bearing = source, ranging, bearing
        self.extra_masks, self.components = extra_masks, components
        self.channel, self.criterion, self.bounds = channel, criterion, bounds
        self.bmin, self.bmax = bmin, bmax
        self.n = ranging.shape[0]
        self.pairs = np.triu_indices(self.n, 1)
        self.softness_m = LOS_SOFTNESS_SCHEDULE_M[0]
        self.evaluations = 0

    def cost(self, x: FloatArray) -> tuple[float, FloatArray]:
        """Scaled cost (ln tr J⁻¹ for A, −ln det J for D) with the smooth LOS, and its gradient."""
        self.evaluations += 1
        p = x.reshape(self.n, 3)
        src = np.broadcast_to(self.source, p.shape)
        if self.bmin.shape[0]:
            q, gq = _soft_los(p, src, self.bmin, self.bmax, self.softness_m)
        else:
            q, gq = np.ones(self.n), None
        J = fisher_information(self.source, p, self.ranging, self.bearing, q, self.channel, self.extra_masks, self.components)
        cg = cost_gradient(
            np.broadcast_to(J, (self.n, 3, 3)),
            src,
            p,
            self.ranging,
            self.bearing,
            q,
            self.channel,
            self.criterion,
            own_los_gradient=gq,
            own_extra=self.extra_masks,
            components=self.components,
        )
        value = float(cg.value[0])
        if not math.isfinite(value) or (self.criterion == "A" and value <= 0.0):
            return _SINGULAR_PENALTY, np.zeros(x.shape)
        grad = cg.gradient.reshape(-1)
        if self.criterion == "A":
            return math.log(value), grad / value
        return value, grad

    def constraints(self, x: FloatArray) -> FloatArray:
        """Margins ≥ 0: source (N), pairs (N(N−1)/2), buildings (N, with buildings)."""
        p = x.reshape(self.n, 3)
        parts = [np.linalg.norm(p - self.source, axis=-1) - self.bounds.source_m]
        i, j = self.pairs
        parts.append(np.linalg.norm(p[i] - p[j], axis=-1) - self.bounds.uav_m)
        if self.bmin.shape[0]:
            parts.append(distance_to_boxes(p, self.bmin, self.bmax) - self.bounds.obstacle_m)
        return np.concatenate(parts)

    def constraints_jacobian(self, x: FloatArray) -> FloatArray:
        """∂(margins)/∂x, (rows of :meth:`constraints`, 3N)."""
        p = x.reshape(self.n, 3)
        rows = [_source_jacobian(p, self.source), _pair_jacobian(p, self.pairs)]
        if self.bmin.shape[0]:
            rows.append(_obstacle_jacobian(p, self.bmin, self.bmax))
        return np.concatenate(rows, axis=0)

    def exact(self, p: FloatArray) -> tuple[float, float, BoolArray]:
        """(cost of eq. 6, PEB, LOS flags) of a placement with the exact LOS flags."""
        los = line_of_sight(p, self.source, self.bmin, self.bmax)
        J = fisher_information(self.source, p, self.ranging, self.bearing, los, self.channel, self.extra_masks, self.components)
        peb, _ = position_error_bound(J)
        value, _ = fim_cost(J, self.criterion)
        return float(value), float(peb), los


def _random_start(gen: np.random.Generator, source: FloatArray, n: int, bounds: PlacementBounds, bmin: FloatArray, bmax: FloatArray) -> FloatArray:
    """N positions at a distance d uniform in [R_S, 1.1 R_S] from the source, uniform on the
    part of that sphere inside the altitude box (azimuth uniform, z uniform), each redrawn up to
    :data:`START_LOS_TRIES` times while its link is NLOS: deep in a shadow the information a
    link carries does not depend on where it is (a bearing carries none), so no gradient would
    lead the drone out."""
    out = np.empty((n, 3))
    for j in range(n):
        for _ in range(START_LOS_TRIES):
            d = bounds.source_m * gen.uniform(1.0, 1.1)
            lo, hi = max(bounds.z_min_m, source[2] - d), min(bounds.z_max_m, source[2] + d)
            z = gen.uniform(lo, hi) if lo <= hi else min(max(source[2], bounds.z_min_m), bounds.z_max_m)
            az = gen.uniform(0.0, 2.0 * math.pi)
            rho = math.sqrt(max(d * d - (z - source[2]) ** 2, 0.0))
            out[j] = (source[0] + rho * math.cos(az), source[1] + rho * math.sin(az), z)
            if bmin.shape[0] == 0 or bool(line_of_sight(out[j], source, bmin, bmax)):
                break
    return out


def _check_placement_arguments(
    rng_m: BoolArray, brg_m: BoolArray, criterion: Criterion, starts: int, extra: Mapping[str, BoolArray] | None = None
) -> None:
    """Raise ValueError for masks of different shapes or no drone, a drone without a role (no
    component at all), an unknown criterion or no start (:func:`optimal_placement`)."""
    if rng_m.shape != brg_m.shape or rng_m.size == 0:
        raise ValueError(f"ranging and bearing: expected two (N,) masks with N >= 1, found {rng_m.shape} and {brg_m.shape}")
    sensing = rng_m | brg_m
    for mask in (extra or {}).values():
        sensing = sensing | mask
    if not sensing.all():
        raise ValueError("every drone must range, sense bearings, or both")
    if criterion not in ("A", "D"):
        raise ValueError(f"criterion: expected 'A' or 'D', found {criterion!r}")
    if starts < 1:
        raise ValueError(f"starts: expected a positive integer, found {starts}")


def _solve_from(prob: _Problem, x0: FloatArray) -> FloatArray:
    """SLSQP from the start ``x0`` (N, 3), m, ENU, through the LOS softness schedule
    (:data:`LOS_SOFTNESS_SCHEDULE_M`; its first stage only without buildings), each stage
    warm-started from the last; the altitude box as variable bounds. Returns (N, 3), m."""
    n, bounds = prob.n, prob.bounds
    cons = {"type": "ineq", "fun": prob.constraints, "jac": prob.constraints_jacobian}
    zb = [(None, None), (None, None), (bounds.z_min_m, bounds.z_max_m)] * n
    stages = LOS_SOFTNESS_SCHEDULE_M if prob.bmin.shape[0] else LOS_SOFTNESS_SCHEDULE_M[:1]
    x = x0.reshape(-1).copy()
    for s in stages:
        prob.softness_m = s
        res = minimize(prob.cost, x, jac=True, method="SLSQP", bounds=zb, constraints=[cons], options={"maxiter": SLSQP_MAXITER, "ftol": SLSQP_FTOL})
        x = np.asarray(res.x, dtype=float)
    return x.reshape(n, 3)


def _best_start(
    prob: _Problem, x0s: Sequence[FloatArray], src: FloatArray, bounds: PlacementBounds, bmin: FloatArray, bmax: FloatArray
) -> tuple[FloatArray, tuple[float, FloatArray, float, BoolArray] | None, int]:
    """Solve problem 7 from every start ``x0s`` ((N, 3) each, m, ENU); return each start's exact
    cost (eq. 6; +inf where the solution breaks a distance of ``bounds`` by more than
    :data:`FEASIBILITY_TOL_M` or J is singular), the best (cost, positions, PEB (eq. 18), LOS
    links) or None, and the index of the best start (-1 for none)."""
    costs = np.full(len(x0s), np.inf)
    best: tuple[float, FloatArray, float, BoolArray] | None = None
    best_k = -1
    for k, x0 in enumerate(x0s):
        p = _solve_from(prob, x0)
        margins = placement_margins(p, src, bounds, bmin, bmax)
        if min(margins.values()) < -FEASIBILITY_TOL_M:
            continue
        value, peb, los = prob.exact(p)
        if not math.isfinite(value):
            continue
        costs[k] = value
        if best is None or value < best[0]:
            best, best_k = (value, p, peb, los), k
    return costs, best, best_k


def optimal_placement(
    source: ArrayLike,
    ranging: ArrayLike,
    bearing: ArrayLike,
    channel: Channel,
    bounds: PlacementBounds,
    boxes_min: ArrayLike = _NO_BOXES,
    boxes_max: ArrayLike = _NO_BOXES,
    criterion: Criterion = "A",
    starts: int = 8,
    seed: int = 0,
    initial_positions: ArrayLike | None = None,
    extra_masks: Mapping[str, ArrayLike] | None = None,
    components: Sequence[SensingComponent] = COMPONENTS,
) -> Placement:
    """The placement of N drones with the smallest cost of eq. 6 under ``bounds`` (problem 7).

    Args:
        source: p_0, (3,), m, ENU: the (true) source position the FIM is evaluated at.
        ranging, bearing: (N,) bool, the drones' roles κ_j and β_j.
        channel: RSS channel (γ, σ_sh/γ LOS and NLOS, σ_b).
        bounds: distances to keep (:func:`placement_bounds`).
        boxes_min, boxes_max: buildings (B, 3), m, ENU; they block links (NLOS) and keep
            drones R_O away.
        criterion: ``"A"`` (tr J⁻¹, the PEB²) or ``"D"`` (−ln det J); the PEB is reported for
            either.
        starts: random starts (≥ 1), drawn from ``numpy.random.default_rng(seed)``.
        seed: seed of the starts.
        initial_positions: (N, 3) an extra first start (e.g. a run's final placement), m, ENU.
        extra_masks: (N,) bool per measurement component beyond range and bearing
            (:data:`planner.sensing.COMPONENTS`), by name: the drones that have it
            (:attr:`planner.config.PlannerConfig.extra_masks`); absent: none.
        components: the measurement components (:data:`planner.sensing.COMPONENTS`).

    Returns:
        The :class:`Placement` of the best start that keeps every distance.

    Raises:
        ValueError: bad shapes or arguments; RuntimeError when no start gave a placement that
            keeps every distance with a regular J.
    """
    src = np.asarray(source, dtype=float).reshape(3)
    rng_m = np.asarray(ranging, dtype=bool).reshape(-1)
    brg_m = np.asarray(bearing, dtype=bool).reshape(-1)
    n = rng_m.size
    extra = None if not extra_masks else {name: np.asarray(mask, dtype=bool).reshape(n) for name, mask in extra_masks.items()}
    _check_placement_arguments(rng_m, brg_m, criterion, starts, extra)
    bmin = np.asarray(boxes_min, dtype=float).reshape(-1, 3)
    bmax = np.asarray(boxes_max, dtype=float).reshape(-1, 3)
    prob = _Problem(src, rng_m, brg_m, channel, criterion, bounds, bmin, bmax, extra, components)
    gen = np.random.default_rng(seed)
    x0s = [_random_start(gen, src, n, bounds, bmin, bmax) for _ in range(starts)]
    if initial_positions is not None:
        x0s.insert(0, np.asarray(initial_positions, dtype=float).reshape(n, 3))
    costs, best, best_k = _best_start(prob, x0s, src, bounds, bmin, bmax)
    if best is None:
        raise RuntimeError(f"no placement keeping every distance was found from {len(x0s)} starts (seed {seed})")
    value, p, peb, los = best
    return Placement(
        positions_m=p,
        los=los,
        peb_m=peb,
        cost=value,
        criterion=criterion,
        source_m=src,
        bounds=bounds,
        margins_m=placement_margins(p, src, bounds, bmin, bmax),
        start_costs=costs,
        best_start=best_k,
        seed=seed,
        starts=starts,
        evaluations=prob.evaluations,
    )
