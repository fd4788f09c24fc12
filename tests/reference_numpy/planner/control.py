"""Projected-gradient control law (paper eqs. 14-17) with kinematic limits and a safety filter.

One drone's step, batched over leading dimensions (trials, drones):

1. Constraints g = d - d* (eqs. 15-17): distance to every known peer (d_U*), to the estimated
   source (d_S*, inflated by the estimate's uncertainty by the caller), to the nearest
   obstacle (d_O*). With ``activation="paper"`` a constraint is active only once violated
   (g < 0), as printed; with ``"safe"`` (default) it is active within a margin that covers one
   step of motion of both parties (g < a; planning with a source known exactly and static, of
   the drone alone for the source and the altitude box) and is then held at that margin.
2. The step of eq. 14: u = −ξ P ∇C − N (NᵀN)⁻¹ g̃, with P = I − N (NᵀN)⁻¹ Nᵀ over the (at most
   three most violated) active constraints. ξ is either given (m per unit gradient) or, by
   default, chosen so that ‖ξ P∇C‖ = v_max Δt (normalised steepest descent at top speed).
3. Kinematic limits of eq. 2: speed in [v_min, v_max]·Δt, heading change within ±φ_max, tilt
   change within ±θ_max per step; altitude box [z_min, z_max] (the paper clamps z).
4. ``"safe"`` only: a safety filter checks the limited step against every safety distance
   with worst-case motion of the peers (age of their data + one step) and a turn-away buffer;
   if it fails, the closest step of the kinematic envelope that passes is taken instead (or,
   if none passes, the one with the largest worst margin).

When J is singular (e.g. bearing-only drones all in NLOS) the drone keeps moving along its last
direction with a random heading/tilt perturbation, as the paper does (Sec. V).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.params import Limits
from tests.reference_numpy.planner.fim import FimStatus
from tests.reference_numpy.planner.geometry import distance_to_boxes, distance_to_boxes_with_gradient

#: Smallest inflation (m) of d_S* about the estimate, however small its σ (the keep-out's
#: floor; :mod:`tests.reference_numpy.planner.agent` takes it from here).
SOURCE_INFLATION_MIN_M: float = 1.5

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Indices of the constraint families in :attr:`StepResult.active`.
UAV, SOURCE, OBSTACLE, ALTITUDE = 0, 1, 2, 3
FAMILIES: tuple[str, ...] = ("uav", "source", "obstacle", "altitude")

#: Relative cut-off of the constraint normals' pseudo-inverse (eq. 14's (NᵀN)⁻¹).
PINV_RCOND: float = 1e-6
#: A projected gradient shorter than this fraction of the gradient is zero.
PG_REL_TOL: float = 1e-9


@dataclass(frozen=True)
class StepResult:
    """The next position of one drone and why it moved as it did.

    Attributes:
        next_position: p_i^(k+1), (..., 3), m, ENU.
        displacement: u_i^(k+1), (..., 3), m.
        active: (..., 4) bool, constraint families active in the projection or the filter:
            inter-drone, source, obstacle, altitude (see :data:`FAMILIES`).
        singular: (...) bool, J was singular and the random-perturbation fallback was used.
        filtered: (...) bool, the safety filter replaced the kinematically limited step.
        infeasible: (...) bool, no step of the kinematic envelope met every safety clearance
            (the least bad one was taken).
    """

    next_position: FloatArray
    displacement: FloatArray
    active: BoolArray
    singular: BoolArray
    filtered: BoolArray
    infeasible: BoolArray


def source_activation_margin_m(limits: Limits, exact: bool = False) -> float:
    """Clearance (m) beyond the source keep-out within which its constraint acts, with the safe
    rule (docs/control.md, "Constraint activation"): 2 v_max Δt + b about an estimate, which
    may move by up to a step's length between two steps as well as the drone; v_max Δt + b
    about a source known exactly (``exact``: planning with the true source), which only the
    drone's own step approaches (a source moving by less than b per step stays covered by the
    turn buffer b). 0 with the paper's rule (active once violated)."""
    if limits.activation != "safe":
        return 0.0
    return (1.0 if exact else 2.0) * limits.step_max_m + limits.turn_buffer_m


def altitude_activation_margin_m(limits: Limits, exact_source: bool = False) -> float:
    """Height (m) inside each face of the altitude box within which that face's constraint acts,
    with the safe rule (docs/control.md, "Constraint activation").

    The box itself is exact and static: one step of the drone's own climb, v_max Δt
    sin(min(θ_max, 90°)) (θ_max the tilt change per step of eq. 2), would keep it inside (a drone
    entering the band tilted is caught by the safety filter's tilt allowance,
    :func:`_tilt_buffer`). That is the margin with a source known exactly and static
    (``exact_source``). About an estimate it is 2 v_max Δt + b, as for the source: the band is
    the room a drone held at a face has to climb or sink away from an estimate that jumps
    towards it or a peer whose record is late (measured with the one-step band in
    docs/control.md, "How far from the optimum, and why"). 0 with the paper's rule (it clamps
    z)."""
    if limits.activation != "safe":
        return 0.0
    if exact_source:
        return limits.step_max_m * math.sin(min(limits.tilt_change_max_rad, 0.5 * math.pi))
    return source_activation_margin_m(limits)


def _tilt_buffer(tilt: FloatArray, limits: Limits) -> FloatArray:
    """Height (m) still climbed after a step of tilt Θ before the tilt can reach 0."""
    k = np.arange(1.0, 4.0) * limits.tilt_change_max_rad
    return limits.step_max_m * np.maximum(0.0, np.sin(np.asarray(tilt)[..., None] - k)).sum(-1)


def loiter_path(end: FloatArray, psi: FloatArray, theta: FloatArray, limits: Limits) -> FloatArray:
    """The two loiter paths a drone can always fly from an end position: vertices (..., 2, K, 3), m,
    ENU, of K steps of v_min Δt turning at the full rate φ_max to the left (index 0) and to the
    right (1) from heading ``psi`` (rad, from east), the tilt ``theta`` (rad) returning to level
    at θ_max per step (eq. 2's limits).

    Once level, the vertices lie on a circle of radius R = v_min Δt / (2 sin(φ_max/2)) (0.59 m
    with the case study's limits), which the drone can fly for ever; K covers the tilt's return
    and one full turn. A drone whose loiter path keeps every safety distance after its step can
    keep them all at every later step by flying it (docs/control.md, "Loiter certificate"). With
    v_min = 0 the path is the end position itself (a drone that can hover).
    """
    K = loiter_steps(limits)
    j = np.arange(1.0, K + 1.0)
    turn = np.array([1.0, -1.0])[:, None] * j * limits.heading_change_max_rad  # (2, K)
    psi_j = np.asarray(psi)[..., None, None] + turn
    tmax = limits.tilt_change_max_rad
    th = np.asarray(theta)[..., None, None]
    th_j = np.sign(th) * np.maximum(np.abs(th) - j * tmax, 0.0) if tmax > 0.0 else np.broadcast_to(th, th.shape[:-1] + (K,))
    steps = _cartesian(np.full(np.broadcast_shapes(psi_j.shape, th_j.shape), limits.step_min_m), psi_j, np.broadcast_to(th_j, psi_j.shape))
    return np.asarray(end)[..., None, None, :] + np.cumsum(steps, axis=-2)


def loiter_steps(limits: Limits) -> int:
    """K of :func:`loiter_path`: the steps the tilt takes to come back to level from ±90° at
    θ_max per step, plus one full turn at φ_max per step (0 when the drone cannot turn)."""
    if limits.heading_change_max_rad <= 0.0:
        return 0
    level = math.ceil(0.5 * math.pi / limits.tilt_change_max_rad - 1e-9) if limits.tilt_change_max_rad > 0.0 else 0
    return level + math.ceil(2.0 * math.pi / min(limits.heading_change_max_rad, 2.0 * math.pi) - 1e-9)


def _loiter_reach_m(limits: Limits) -> float:
    """How far (m) a loiter path (:func:`loiter_path`) can take a drone from its start: the
    tilt's return to level, then the circle's diameter."""
    if loiter_steps(limits) == 0:
        return 0.0
    level = loiter_steps(limits) - math.ceil(2.0 * math.pi / min(limits.heading_change_max_rad, 2.0 * math.pi) - 1e-9)
    return level * limits.step_min_m + 2.0 * loiter_radius_m(limits)


def loiter_radius_m(limits: Limits) -> float:
    """R = v_min Δt / (2 sin(φ_max/2)), m: the radius of the level loiter circle of
    :func:`loiter_path` (the vertices of the polygon flown at v_min turning at φ_max)."""
    half = 0.5 * min(limits.heading_change_max_rad, math.pi)
    return limits.step_min_m / (2.0 * math.sin(half)) if half > 0.0 else math.inf


def _spherical(u: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    s = np.sqrt((u * u).sum(-1))
    return s, np.arctan2(u[..., 1], u[..., 0]), np.arctan2(u[..., 2], np.hypot(u[..., 0], u[..., 1]))


def _cartesian(s: FloatArray, psi: FloatArray, theta: FloatArray) -> FloatArray:
    sc = s * np.cos(theta)
    out = np.empty(np.shape(sc) + (3,))
    out[..., 0] = sc * np.cos(psi)
    out[..., 1] = sc * np.sin(psi)
    out[..., 2] = s * np.sin(theta)
    return out


def lost_contact_planes(own_then_m: ArrayLike, peer_then_m: ArrayLike, lost: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """The planes that keep two drones apart while they cannot hear each other (a partition).

    Drone i last heard peer j at step ℓ (j's record: position b = q_j(ℓ)); drone i was at
    a = p_i(ℓ) then. Both drones knew both positions of step ℓ: i keeps to its side of the
    perpendicular bisector of a and b, at least d_U*/2 from it (``control_step`` with
    ``peer_planes``), and j, applying the same rule to its record of i of the same step, to
    the other side. Their distance then stays at least d_U* whatever each does, for as long
    as the partition lasts (the planes do not grow with time as a reachable region would).
    The bound holds when both last heard each other at the same step ℓ (no record lost or
    delayed at the cut); each drone may start off its side (it moved since ℓ) and the safety
    filter then brings it back without ever letting its margin shrink.

    Args:
        own_then_m: a, (..., N, 3), m, ENU: drone i's own position at the step of each peer's
            last record.
        peer_then_m: b, (..., N, 3), m, ENU: each peer's last known position.
        lost: (..., N) bool, the peers drone i has lost contact with.

    Returns:
        (points, normals): the midpoint m = (a + b)/2 where ``lost`` (else b) and the unit
        normal n = (a − b)/|a − b| (zeros where not ``lost``), each (..., N, 3).
    """
    a = np.asarray(own_then_m, dtype=float)
    b = np.asarray(peer_then_m, dtype=float)
    lost_b = np.asarray(lost, dtype=bool)
    d = a - b
    norm = np.sqrt((d * d).sum(-1, keepdims=True))
    use = lost_b & (norm[..., 0] > 0.0)
    normals = np.where(use[..., None], d / np.where(norm > 0.0, norm, 1.0), 0.0)
    points = np.where(use[..., None], 0.5 * (a + b), b)
    return points, normals


def _wrap(a: FloatArray) -> FloatArray:
    return (a + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True)
class _Clearances:
    """Everything the safety filter needs to score candidate end positions."""

    peers: FloatArray  # (..., N, 3)
    peer_required: FloatArray  # (..., N), +inf-free; masked peers get -inf
    source: FloatArray  # (..., 3)
    source_required: FloatArray  # (...)
    obstacle_required: float
    planes: FloatArray | None = None  # (..., N, 3) unit normals of plane rows (zeros: a point peer)
    d_uav_m: float = 0.0
    # (..., N, 3) a peer's dead-reckoned position now and at the end of the step (NaN: none,
    # or not inside its reachable ball), :func:`_dead_reckoning_kept`.
    reckoned_now: FloatArray | None = None
    reckoned_next: FloatArray | None = None


def _subset(c: _Clearances, idx: tuple[NDArray[np.intp], ...]) -> _Clearances:
    keep = np.broadcast_to(c.source_required, c.source.shape[:-1])
    planes = None if c.planes is None else c.planes[idx]
    now = None if c.reckoned_now is None else c.reckoned_now[idx]
    nxt = None if c.reckoned_next is None else c.reckoned_next[idx]
    return _Clearances(c.peers[idx], c.peer_required[idx], c.source[idx], keep[idx], c.obstacle_required, planes, c.d_uav_m, now, nxt)


def peer_distance(x: FloatArray, peers: FloatArray, planes: FloatArray | None, d_uav_m: float) -> FloatArray:
    """Distance (m) of positions ``x`` (..., 3) to each peer row (..., N, 3) → (..., N).

    A plane row (non-zero unit normal n in ``planes``) is a peer drone i has lost contact with:
    the row holds the point m of the plane both keep to their own side of (see
    :func:`lost_contact_planes`) and the "distance" is ``(x − m)·n + d_U*/2``, the distance to
    the mirror image of x when the peer keeps to its side at the same distance; it is 1-Lipschitz
    like a point distance, so the safety filter's margins apply unchanged."""
    diff = x[..., None, :] - peers
    dist = np.sqrt((diff * diff).sum(-1))
    if planes is None:
        return dist
    is_plane = (planes != 0.0).any(-1)
    return np.where(is_plane, (diff * planes).sum(-1) + 0.5 * d_uav_m, dist)


def _peer_margin(cand: FloatArray, c: _Clearances) -> FloatArray:
    """Smallest peer margin (m) of candidate end positions (..., C, 3): min_j d_j − required_j."""
    planes = None if c.planes is None else c.planes[..., None, :, :]
    dist = peer_distance(cand, c.peers[..., None, :, :], planes, c.d_uav_m)
    return (dist - c.peer_required[..., None, :]).min(-1, initial=np.inf)


def _score(cand: FloatArray, tilt: FloatArray, c: _Clearances, boxes_min: FloatArray, boxes_max: FloatArray, limits: Limits) -> FloatArray:
    """Clearance margins (m) of candidate end positions (..., C, 3), per family (..., C, 4).

    Families in :data:`FAMILIES` order: nearest peer, source, nearest obstacle, altitude box
    (with the height still climbed while the tilt swings back, :func:`_tilt_buffer`).
    """
    out = np.empty(cand.shape[:-1] + (4,))
    out[..., UAV] = _peer_margin(cand, c)
    ds = cand - c.source[..., None, :]
    out[..., SOURCE] = np.sqrt((ds * ds).sum(-1)) - c.source_required[..., None]
    out[..., OBSTACLE] = distance_to_boxes(cand, boxes_min, boxes_max) - c.obstacle_required
    z = cand[..., 2]
    out[..., ALTITUDE] = np.minimum(limits.z_max_m - z - _tilt_buffer(tilt, limits), z - limits.z_min_m - _tilt_buffer(-tilt, limits))
    return out


def control_step(
    own_position: ArrayLike,
    previous_step: ArrayLike,
    gradient: ArrayLike,
    status: ArrayLike,
    peers: ArrayLike,
    peer_mask: ArrayLike,
    peer_age_steps: ArrayLike,
    source_estimate: ArrayLike,
    source_keepout_m: ArrayLike,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    limits: Limits,
    perturbation_uniforms: ArrayLike,
    xi: float | None = None,
    perturbation_rad: float = math.radians(20.0),
    peer_planes: ArrayLike | None = None,
    source_exact: bool = False,
    peer_drift_m: ArrayLike | None = None,
) -> StepResult:
    """One drone's control step: eq. 14 under constraints (15-17) and the limits of eq. 2/7.

    Args:
        own_position: p_i^(k), (..., 3), m, ENU.
        previous_step: u_i^(k), the last displacement (..., 3), m; zeros before the first step
            (no heading or tilt limit then).
        gradient: ∇_{p_i} C of eq. 6 (..., 3), from :func:`planner.fim.cost_gradient`.
        status: :class:`planner.fim.FimStatus` of drone i's J (...).
        peers: positions of the other drones as known to drone i, (..., N, 3), m, ENU.
        peer_mask: (..., N) bool, which rows of ``peers`` are real peers (False for drone i
            itself and for peers never heard of).
        peer_age_steps: (..., N) int ≥ 0, age in steps of each peer's known position.
        source_estimate: p̂_0 (..., 3), m, ENU.
        source_keepout_m: d_S* (possibly inflated by the estimate's uncertainty), (...), m.
        boxes_min, boxes_max: obstacles (B, 3), m, ENU.
        limits: safety distances and per-step kinematic limits.
        perturbation_uniforms: (..., 2) uniforms in [0, 1) for the singular fallback.
        xi: spatial step ξ (m per unit of gradient); None = normalised step at v_max Δt.
        perturbation_rad: half-width of the uniform heading and tilt perturbation of the
            singular fallback (rad).
        peer_planes: (..., N, 3) unit normals for the peers drone i has lost contact with
            (zeros elsewhere): their row of ``peers`` is then a point of the plane drone i keeps
            to its side of, with its age 0 (:func:`lost_contact_planes`); None: none.
        source_exact: ``source_estimate`` is the true source (planning with it, a research
            mode) and moves less than b per step: its constraint acts within v_max Δt + b instead of
            2 v_max Δt + b, the altitude box's within one level step's climb
            (:func:`source_activation_margin_m`, :func:`altitude_activation_margin_m`).
        peer_drift_m: (..., N, 3), m per step, ENU: each peer's last step as drone i's last two
            records of it give it (NaN: unknown): within a filter tier, a drone inside a peer's
            reachable ball prefers the steps that do not bring it nearer the peer's
            dead-reckoned position (:func:`_dead_reckoning_kept`). None: unknown for all.

    Returns:
        The :class:`StepResult`.
    """
    p = np.asarray(own_position, dtype=float)
    if p.ndim == 1:
        # One drone: run the batched code on a batch of one and unwrap.
        one = (previous_step, gradient, status, peers, peer_mask, peer_age_steps, source_estimate, source_keepout_m)
        drift = None if peer_drift_m is None else np.asarray(peer_drift_m, dtype=float)[None]
        return _one_drone(p, one, boxes_min, boxes_max, limits, perturbation_uniforms, xi, perturbation_rad, peer_planes, source_exact, drift)
    prev = np.asarray(previous_step, dtype=float)
    grad = np.asarray(gradient, dtype=float)
    scene = _scene(
        p, peers, peer_mask, peer_age_steps, peer_planes, source_estimate, source_keepout_m, boxes_min, boxes_max, source_exact, peer_drift_m
    )
    batch = p.shape[:-1]

    # 1. Constraint values g = d - d* and their gradients (unit normals) w.r.t. p_i.
    cons = _constraints(scene, limits)
    # 2. Projection onto the active constraints (at most the three most violated).
    project, correction = _projection(cons.gt, cons.normals, cons.active_all, p)
    singular = np.asarray(status) == int(FimStatus.SINGULAR)
    prev_s, prev_psi, prev_theta = _spherical(prev)
    has_prev = prev_s > 0.0
    descent = _descent(grad, project, xi, limits)
    if singular.any():
        wander = _wander(prev_psi, prev_theta, has_prev, np.asarray(perturbation_uniforms, dtype=float), perturbation_rad, limits)
        descent = np.where(singular[..., None], project(wander), descent)
    # 3. Kinematic limits (eq. 2): speed, heading and tilt rates.
    u, theta = _kinematic_limits(descent + correction, prev_psi, prev_theta, has_prev, limits)

    active = _active_families(cons.active_all, limits.activation == "safe")
    filtered = np.zeros(batch, dtype=bool)
    infeasible = np.zeros(batch, dtype=bool)
    if limits.activation != "safe":
        # The paper clamps the altitude to its box.
        z_next = p[..., 2] + u[..., 2]
        clamped = np.clip(z_next, limits.z_min_m, limits.z_max_m)
        active[..., ALTITUDE] = clamped != z_next
        u = np.concatenate((u[..., :2], (clamped - p[..., 2])[..., None]), axis=-1)
    else:
        # 4. Safety filter over the kinematic envelope.
        u, active, filtered, infeasible = _safety_filter(scene, cons, u, theta, prev, has_prev, limits, active)
    return StepResult(
        next_position=p + u,
        displacement=u,
        active=active,
        singular=singular,
        filtered=filtered,
        infeasible=infeasible,
    )


def _one_drone(
    p: FloatArray,
    per_drone: tuple[ArrayLike, ...],
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    limits: Limits,
    perturbation_uniforms: ArrayLike,
    xi: float | None,
    perturbation_rad: float,
    peer_planes: ArrayLike | None,
    source_exact: bool = False,
    peer_drift_m: FloatArray | None = None,
) -> StepResult:
    """:func:`control_step` of one drone (``p`` (3,)): the batched code on a batch of one,
    unwrapped. ``per_drone``: previous step, gradient, status, peers, peer mask, peer ages,
    source estimate and keep-out, in :func:`control_step`'s order and units."""
    previous_step, gradient, status, peers, peer_mask, peer_age_steps, source_estimate, source_keepout_m = per_drone
    r = control_step(
        p[None],
        np.asarray(previous_step, dtype=float)[None],
        np.asarray(gradient, dtype=float)[None],
        np.asarray(status)[None],
        np.asarray(peers, dtype=float)[None],
        np.asarray(peer_mask)[None],
        np.asarray(peer_age_steps)[None],
        np.asarray(source_estimate, dtype=float)[None],
        np.asarray(source_keepout_m, dtype=float).reshape(-1)[:1],
        boxes_min,
        boxes_max,
        limits,
        np.asarray(perturbation_uniforms, dtype=float)[None],
        xi,
        perturbation_rad,
        None if peer_planes is None else np.asarray(peer_planes, dtype=float)[None],
        source_exact,
        peer_drift_m,
    )
    return StepResult(*(np.asarray(getattr(r, f))[0] for f in ("next_position", "displacement", "active", "singular", "filtered", "infeasible")))


@dataclass(frozen=True)
class _Scene:
    """What one control step keeps clear of, batched (internal): own position p (..., 3), m,
    ENU; peer rows (..., N, 3), m, their mask (..., N) and age in steps (..., N); the unit
    normals of lost-contact plane rows (..., N, 3) or None; the source estimate (..., 3), m,
    its keep-out (...), m; obstacle boxes (B, 3), m, ENU; each peer's last step (..., N, 3), m
    (NaN: unknown) or None."""

    p: FloatArray
    peers: FloatArray
    mask: BoolArray
    age: FloatArray
    planes: FloatArray | None
    source: FloatArray
    keepout: FloatArray
    bmin: FloatArray
    bmax: FloatArray
    source_exact: bool = False
    drift: FloatArray | None = None


def _scene(
    p: FloatArray,
    peers: ArrayLike,
    peer_mask: ArrayLike,
    peer_age_steps: ArrayLike,
    peer_planes: ArrayLike | None,
    source_estimate: ArrayLike,
    source_keepout_m: ArrayLike,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    source_exact: bool = False,
    peer_drift_m: ArrayLike | None = None,
) -> _Scene:
    """:func:`control_step`'s inputs as a :class:`_Scene` of arrays (same units and shapes)."""
    # A source estimate shared by the whole batch is broadcast: the safety filter indexes it
    # per drone (without this, a (3,) estimate with batched drones raised in _subset).
    return _Scene(
        p,
        np.asarray(peers, dtype=float),
        np.asarray(peer_mask, dtype=bool),
        np.asarray(peer_age_steps, dtype=float),
        None if peer_planes is None else np.asarray(peer_planes, dtype=float),
        np.broadcast_to(np.asarray(source_estimate, dtype=float), p.shape),
        np.broadcast_to(np.asarray(source_keepout_m, dtype=float), p.shape[:-1]),
        np.asarray(boxes_min, dtype=float).reshape(-1, 3),
        np.asarray(boxes_max, dtype=float).reshape(-1, 3),
        source_exact,
        None if peer_drift_m is None else np.asarray(peer_drift_m, dtype=float),
    )


@dataclass(frozen=True)
class _Constraints:
    """Constraint values and normals of eqs. 15-17 at p (internal).

    ``G`` (..., C) = d − d* in the column order peers (N), source, obstacle, then with the safe
    rule the altitude box's top and bottom; ``normals`` (..., C, 3) their unit gradients
    w.r.t. p; ``gt`` the values less the activation margins (safe rule) and ``active_all``
    (..., C) = gt < 0; ``dist`` (..., N) the peer distances, m; ``g_s``, ``g_o`` (...) the source
    and obstacle values, m; ``n_alt`` the number of altitude columns (2 safe, 0 paper)."""

    G: FloatArray
    normals: FloatArray
    gt: FloatArray
    active_all: BoolArray
    dist: FloatArray
    g_s: FloatArray
    g_o: FloatArray
    n_alt: int


def _constraints(scene: _Scene, limits: Limits) -> _Constraints:
    """Constraint values g = d − d* of eqs. 15-17 and their unit normals w.r.t. p_i: every
    peer (d_U*), the source (its keep-out), the nearest obstacle (d_O*), and with the safe rule
    the altitude box. With the safe rule a constraint is active within a margin of one step of
    motion of both parties: v_max Δt (2 + age) + 2b for a peer (b the turn-away buffer),
    2 v_max Δt + b for the source estimate, the obstacle and the altitude box; planning with an
    exactly known static source, one step of the drone's own motion for the source and the
    altitude box (:func:`source_activation_margin_m`, :func:`altitude_activation_margin_m`).
    With the paper's rule once violated."""
    p, q, planes = scene.p, scene.peers, scene.planes
    safe = limits.activation == "safe"
    smax, tb = limits.step_max_m, limits.turn_buffer_m
    diff = p[..., None, :] - q
    dist = peer_distance(p, q, planes, limits.d_uav_m)
    n_u = diff / np.where(dist > 0.0, dist, 1.0)[..., None]
    if planes is not None:
        n_u = np.where((planes != 0.0).any(-1)[..., None], planes, n_u)
    g_u = np.where(scene.mask, dist - limits.d_uav_m, np.inf)
    ds = p - scene.source
    dist_s = np.sqrt((ds * ds).sum(-1))
    n_s = ds / np.where(dist_s > 0.0, dist_s, 1.0)[..., None]
    g_s = dist_s - scene.keepout
    sd, n_o = distance_to_boxes_with_gradient(p, scene.bmin, scene.bmax)
    g_o = sd - limits.d_obstacle_m
    # Altitude box as two more constraints (safe rule only; the paper clamps z afterwards).
    n_alt = 2 if safe else 0
    G = np.concatenate(
        [g_u, g_s[..., None], g_o[..., None]] + ([limits.z_max_m - p[..., 2:3], p[..., 2:3] - limits.z_min_m] if safe else []), axis=-1
    )
    parts = [n_u, n_s[..., None, :], n_o[..., None, :]]
    if safe:
        up = np.zeros(p.shape[:-1] + (2, 3))
        up[..., 0, 2] = -1.0
        up[..., 1, 2] = 1.0
        parts.append(up)
    normals = np.concatenate(parts, axis=-2)
    if safe:
        gt = G.copy()
        gt[..., : -2 - n_alt] -= smax * (2.0 + scene.age) + 2.0 * tb
        gt[..., -2 - n_alt] -= source_activation_margin_m(limits, scene.source_exact)
        gt[..., -1 - n_alt] -= source_activation_margin_m(limits)  # the obstacle: 2 v_max Δt + b
        gt[..., -n_alt:] -= altitude_activation_margin_m(limits, scene.source_exact)
    else:
        gt = G
    return _Constraints(G, normals, gt, gt < 0.0, dist, g_s, g_o, n_alt)


def _projection(gt: FloatArray, normals: FloatArray, active_all: BoolArray, p: FloatArray) -> tuple[Callable[[FloatArray], FloatArray], FloatArray]:
    """Eq. 14's projection onto the active constraints (at most the three most violated):
    P = I − N (NᵀN)⁻¹ Nᵀ as a function of a vector field (..., 3), and the correction
    −N (NᵀN)⁻¹ g̃ (..., 3), m, that brings violated constraints back."""
    k = min(3, gt.shape[-1])
    any_active = active_all.any(-1)
    correction = np.zeros_like(p)
    if not any_active.any():
        return lambda v: v, correction
    sub = np.nonzero(any_active)
    gt_s = gt[sub]
    sel = np.argsort(gt_s, axis=-1)[..., :k]
    g_sel = np.take_along_axis(gt_s, sel, -1)
    on = g_sel < 0.0
    Nm = np.swapaxes(np.take_along_axis(normals[sub], sel[..., None], -2), -1, -2) * on[..., None, :]  # (n, 3, k)
    # (n, k, 3) = (NᵀN)⁻¹Nᵀ for independent normals; nearly dependent normals (singular
    # values below 1e-6 of the largest) count as dependent, so P stays well conditioned.
    pinv = np.linalg.pinv(Nm, rcond=PINV_RCOND)
    P_sub = np.eye(3) - Nm @ pinv
    correction[sub] = -np.einsum("...ki,...k->...i", pinv, np.where(on, g_sel, 0.0))

    def project(v: FloatArray) -> FloatArray:
        out = v.copy()
        out[sub] = np.einsum("...ij,...j->...i", P_sub, v[sub])
        return out

    return project, correction


def _descent(grad: FloatArray, project: Callable[[FloatArray], FloatArray], xi: float | None, limits: Limits) -> FloatArray:
    """The gradient step of eq. 14, −ξ P∇C (..., 3), m: ξ given (m per unit gradient), or
    normalised to v_max Δt. A projected gradient at round-off level (the active constraints
    leave no descent direction) is zero: normalising it would turn numerical noise into a full
    step."""
    smax = limits.step_max_m
    pg = project(grad)
    pg_norm = np.sqrt((pg * pg).sum(-1))
    g_norm = np.sqrt((grad * grad).sum(-1))
    pg = np.where((pg_norm <= PG_REL_TOL * g_norm)[..., None], 0.0, pg)
    pg_norm = np.where(pg_norm <= PG_REL_TOL * g_norm, 0.0, pg_norm)
    return -smax * pg / np.where(pg_norm > 0.0, pg_norm, 1.0)[..., None] if xi is None else -float(xi) * pg


def _wander(
    prev_psi: FloatArray, prev_theta: FloatArray, has_prev: BoolArray, uni: FloatArray, perturbation_rad: float, limits: Limits
) -> FloatArray:
    """The singular fallback (paper Sec. V), before projection: a step of v_max Δt along the
    last heading and tilt perturbed uniformly by ±``perturbation_rad`` (``uni`` (..., 2) in
    [0, 1)); a random heading, level, before the first step."""
    jitter = (2.0 * uni - 1.0) * perturbation_rad
    psi_r = np.where(has_prev, prev_psi + jitter[..., 0], 2.0 * np.pi * uni[..., 0])
    th_r = np.where(has_prev, np.clip(prev_theta + jitter[..., 1], -0.5 * np.pi, 0.5 * np.pi), 0.0)
    return _cartesian(np.full(prev_psi.shape, limits.step_max_m), psi_r, th_r)


def _kinematic_limits(
    u_d: FloatArray, prev_psi: FloatArray, prev_theta: FloatArray, has_prev: BoolArray, limits: Limits
) -> tuple[FloatArray, FloatArray]:
    """Eq. 2's limits on the desired step u_d (..., 3), m: length in [v_min, v_max] Δt, heading
    change within ±φ_max and tilt change within ±θ_max of the previous step (rad). Returns the
    step (..., 3), m, and its tilt Θ (...), rad."""
    s, psi, theta = _spherical(u_d)
    tiny = s < 1e-12
    psi = np.where(tiny, prev_psi, psi)
    theta = np.where(tiny, prev_theta, theta)
    s = np.minimum(np.maximum(s, limits.step_min_m), limits.step_max_m)
    hmax, tmax = limits.heading_change_max_rad, limits.tilt_change_max_rad
    dpsi = np.minimum(np.maximum(_wrap(psi - prev_psi), -hmax), hmax)
    psi = np.where(has_prev, prev_psi + dpsi, psi)
    theta = np.where(has_prev, np.minimum(np.maximum(theta, prev_theta - tmax), prev_theta + tmax), theta)
    return _cartesian(s, psi, theta), theta


@dataclass(frozen=True)
class _Requirements:
    """The safety filter's requirements (internal): margins a step may not make negative, nor
    more negative than they are (``need`` (..., 4), m, per family), and the peers' clearances
    in three variants: ``strict`` (a margin in deficit may not shrink against the peer's
    ball of now), ``loose`` (nor against its end-of-step ball) and ``hard`` (without the
    turn-away buffers 2b); ``now`` (..., 4), m, the margins now against the end-of-step
    requirements."""

    now: FloatArray
    need: FloatArray
    strict: _Clearances
    loose: _Clearances
    hard: _Clearances


def _filter_requirements(scene: _Scene, cons: _Constraints, limits: Limits) -> _Requirements:
    """The safety filter's margins now and requirements (docs/control.md).

    Peers, one by one: peer j's record q_j of age a_j puts j within (a_j + 1) v_max Δt of q_j at
    the end of the step, within a_j v_max Δt now, so L_j = |p − q_j| − a_j v_max Δt bounds the
    true distance now from below. A step keeps every peer's end-of-step margin
    |p' − q_j| − (d_U* + (a_j + 1) v_max Δt + 2b) at least min(0, L_j − d_U* − 2b): L_j never
    shrinks below d_U* + 2b, whatever the records' delays. Measured against the end-of-step
    ball instead (``loose``), a margin in deficit could lose v_max Δt per step of a record's
    age. Per peer, not over the family's smallest margin: a deficit with one peer must not
    license an approach to another. A plane row (a lost peer, age 0) does not grow: its margin
    now is against the same requirement.
    """
    p, q, planes = scene.p, scene.peers, scene.planes
    smax, tb = limits.step_max_m, limits.turn_buffer_m
    clear = _Clearances(
        peers=q,
        peer_required=np.where(scene.mask, limits.d_uav_m + (scene.age + 1.0) * smax + 2.0 * tb, -np.inf),
        source=scene.source,
        source_required=scene.keepout + tb,
        obstacle_required=limits.d_obstacle_m + 0.5 * smax + tb,
        planes=planes,
        d_uav_m=limits.d_uav_m,
    )
    # Margins now, per family, from the constraint values already computed, each against its
    # end-of-step requirement.
    now = np.empty(p.shape[:-1] + (4,))
    now[..., SOURCE] = cons.g_s - tb
    now[..., OBSTACLE] = cons.g_o - (clear.obstacle_required - limits.d_obstacle_m)
    now[..., ALTITUDE] = np.minimum(limits.z_max_m - p[..., 2], p[..., 2] - limits.z_min_m)
    point = np.ones(q.shape[:-1], dtype=bool) if planes is None else ~(planes != 0.0).any(-1)
    peer_now = cons.G[..., : -2 - cons.n_alt] - (clear.peer_required - limits.d_uav_m)  # +inf for masked peers
    # The bisector planes of a partition, together: a drone off its side of several may let
    # each come back to the worst of them (it started off its sides as it moved since the
    # cut; held one by one, planes and keep-out boxed drones in and the keep-out gave way).
    plane_now = np.where(point, np.inf, peer_now).min(-1, keepdims=True, initial=np.inf)
    peer_now_eff = np.where(point, peer_now, np.minimum(peer_now, plane_now))
    peer_need_loose = np.minimum(peer_now_eff, 0.0)
    peer_need = np.minimum(peer_now_eff + np.where(point, smax, 0.0), 0.0)
    now[..., UAV] = (peer_now - peer_need).min(-1, initial=np.inf)
    need = np.minimum(now, 0.0)
    need[..., UAV] = 0.0
    reckoned_now = reckoned_next = None
    if scene.drift is not None:
        # Inside a peer's reachable ball (its record no longer bounds where it is), where the
        # peer is likely to be: its record moved on by its last step, per step of the record's age.
        inside = point & scene.mask & (peer_now_eff + 2.0 * tb < 0.0) & np.isfinite(scene.drift).all(-1)
        reckoned_now = np.where(inside[..., None], q + scene.age[..., None] * scene.drift, np.nan)
        reckoned_next = reckoned_now + scene.drift
    return _Requirements(
        now,
        need,
        dataclasses.replace(clear, peer_required=clear.peer_required + peer_need),
        dataclasses.replace(clear, peer_required=clear.peer_required + peer_need_loose),
        # Without the turn-away buffers 2b: the reachable ball itself, the end-of-step distance
        # that still keeps d_U* whatever the peer does (a margin already below it may not shrink).
        dataclasses.replace(
            clear,
            peer_required=clear.peer_required - 2.0 * tb + np.minimum(peer_now_eff + 2.0 * tb, 0.0),
            reckoned_now=reckoned_now,
            reckoned_next=reckoned_next,
        ),
    )


def _near_peers_only(req: _Requirements, scene: _Scene, dist: FloatArray, limits: Limits, reach_m: float = 0.0) -> _Requirements:
    """The requirements against the peers that can be nearest after one step only.

    Peers whose clearance now exceeds the smallest by more than 2 s_max can never be the
    nearest for a position reachable in one step (clearances are 1-Lipschitz, |u| <= s_max):
    candidates are scored against the others only. Exact (same minimum), and O(C k) instead of
    O(C N) for C candidates: at N = 1000 the filtered step went from ~5 ms to ~0.6 ms. (Per
    peer requirement variant, strict, loose and hard: the union of their columns.) ``reach_m``:
    how much further than the end of the step a scored position can be (a loiter path's reach).
    """
    q, planes, smax = scene.peers, scene.planes, limits.step_max_m
    cols = np.zeros(q.shape[-2], dtype=bool)
    for c in (req.strict, req.loose, req.hard):
        m_now = dist - c.peer_required
        cols |= (m_now <= m_now.min(-1, keepdims=True) + 2.0 * (smax + reach_m) + 1e-6).reshape(-1, q.shape[-2]).any(0)
    strict, loose, hard = (
        _Clearances(
            q[..., cols, :],
            c.peer_required[..., cols],
            scene.source,
            c.source_required,
            c.obstacle_required,
            None if planes is None else planes[..., cols, :],
            limits.d_uav_m,
            None if c.reckoned_now is None else c.reckoned_now[..., cols, :],
            None if c.reckoned_next is None else c.reckoned_next[..., cols, :],
        )
        for c in (req.strict, req.loose, req.hard)
    )
    return _Requirements(req.now, req.need, strict, loose, hard)


@dataclass(frozen=True)
class _Certificate:
    """What a loiter path (:func:`loiter_path`) after a step must keep (internal): the peers'
    reachable balls of ``clear`` (as in the filter's ``hard`` variant: d_U* + (a_j + 1) v_max Δt
    from the record, or a lost peer's plane), the source keep-out and d_O* + v_min Δt / 2 (the
    chords' interior) from the obstacles, without the turn-away buffers (the loiter is the
    turn away), the altitude box itself; a family already in deficit at p only may not get
    worse (``need`` (..., 4), m). ``now`` (..., 4): the margins at p."""

    clear: _Clearances
    need: FloatArray
    now: FloatArray


def _certificate(scene: _Scene, cons: _Constraints, hard: _Clearances, limits: Limits) -> _Certificate:
    """The loiter certificate's clearances for the drones of ``scene`` (:class:`_Certificate`)."""
    p = scene.p
    clear = dataclasses.replace(
        hard,
        source_required=np.broadcast_to(scene.keepout, p.shape[:-1]),
        obstacle_required=limits.d_obstacle_m + 0.5 * limits.step_min_m,
    )
    now = np.empty(p.shape[:-1] + (4,))
    now[..., UAV] = (cons.dist - clear.peer_required).min(-1, initial=np.inf)
    now[..., SOURCE] = cons.g_s
    now[..., OBSTACLE] = cons.g_o - 0.5 * limits.step_min_m
    now[..., ALTITUDE] = np.minimum(limits.z_max_m - p[..., 2], p[..., 2] - limits.z_min_m)
    return _Certificate(clear, np.minimum(now, 0.0), now)


def _certified(end: FloatArray, step: FloatArray, cert: _Certificate, bmin: FloatArray, bmax: FloatArray, limits: Limits) -> BoolArray:
    """(n, C) whether a loiter path from each end position (n, C, 3) after ``step`` (n, C, 3)
    keeps every clearance of ``cert`` (flat batch n): to the left or to the right.

    Every vertex of a loiter path is within :func:`_loiter_reach_m` of its end and every
    clearance is 1-Lipschitz, so a clearance (a peer, the source, the buildings, the altitude
    box) whose margin at every end exceeds the requirement by that reach is not scored along
    the paths (exact)."""
    n, C = end.shape[:2]
    if loiter_steps(limits) == 0 or n * C == 0:
        return np.ones((n, C), dtype=bool)
    reach = _loiter_reach_m(limits) + 1e-9
    c, need = cert.clear, cert.need[:, None, :]  # (n, 1, 4)
    planes = None if c.planes is None else c.planes[..., None, :, :]
    peer_end = peer_distance(end, c.peers[..., None, :, :], planes, c.d_uav_m) - c.peer_required[..., None, :]  # (n, C, N)
    cols = (peer_end - reach < need[..., UAV : UAV + 1]).any(axis=(0, 1))
    ds = end - c.source[..., None, :]
    src_on = bool((np.sqrt((ds * ds).sum(-1)) - c.source_required[..., None] - reach < need[..., SOURCE]).any())
    obs_on = bool((distance_to_boxes(end, bmin, bmax) - c.obstacle_required - reach < need[..., OBSTACLE]).any())
    z = end[..., 2]
    alt_on = bool((np.minimum(limits.z_max_m - z, z - limits.z_min_m) - reach < need[..., ALTITUDE]).any())
    if not (cols.any() or src_on or obs_on or alt_on):
        return np.ones((n, C), dtype=bool)
    _, psi, theta = _spherical(step)
    path = loiter_path(end, psi, theta, limits)  # (n, C, 2, K, 3)
    path = np.concatenate((np.broadcast_to(end[..., None, None, :], path.shape[:-2] + (1, 3)), path), -2)  # and the end itself
    K = path.shape[-2]
    flat = path.reshape(n, C * 2 * K, 3)
    flat_need = cert.need[:, None, :]
    ok = np.ones(flat.shape[:-1], dtype=bool)
    if cols.any():
        near = _Clearances(
            c.peers[..., cols, :],
            c.peer_required[..., cols],
            c.source,
            c.source_required,
            c.obstacle_required,
            None if c.planes is None else c.planes[..., cols, :],
            c.d_uav_m,
        )
        ok &= _peer_margin(flat, near) >= flat_need[..., UAV]
    if src_on:
        ds = flat - c.source[..., None, :]
        ok &= np.sqrt((ds * ds).sum(-1)) - c.source_required[..., None] >= flat_need[..., SOURCE]
    if obs_on:
        ok &= distance_to_boxes(flat, bmin, bmax) - c.obstacle_required >= flat_need[..., OBSTACLE]
    if alt_on:
        ok &= np.minimum(limits.z_max_m - flat[..., 2], flat[..., 2] - limits.z_min_m) >= flat_need[..., ALTITUDE]
    return np.asarray(ok.reshape(n, C, 2, K).all(-1).any(-1))


def _safety_filter(
    scene: _Scene,
    cons: _Constraints,
    u: FloatArray,
    theta: FloatArray,
    prev: FloatArray,
    has_prev: BoolArray,
    limits: Limits,
    active: BoolArray,
) -> tuple[FloatArray, BoolArray, BoolArray, BoolArray]:
    """Step 4 (safe rule): check the limited step u (..., 3), m, of tilt Θ (rad) against every
    safety distance (:func:`_filter_requirements`); where it fails, take the best step of the
    kinematic envelope instead (:func:`_envelope_search`). Returns the step, the active
    families (``active`` with the filter's), filtered and infeasible flags (...)."""
    p, bmin, bmax, smax = scene.p, scene.bmin, scene.bmax, limits.step_max_m
    req = _filter_requirements(scene, cons, limits)
    need = req.need
    cert = _certificate(scene, cons, req.hard, limits)
    reach = smax + _loiter_reach_m(limits)
    active = active.copy()
    filtered = np.zeros(p.shape[:-1], dtype=bool)
    infeasible = np.zeros(p.shape[:-1], dtype=bool)
    # Every clearance is 1-Lipschitz in the position and |u| <= s_max: only drones within
    # s_max of a clearance need their step scored; the altitude box is checked for all.
    z_next = p[..., 2] + u[..., 2]
    alt = np.minimum(limits.z_max_m - z_next - _tilt_buffer(theta, limits), z_next - limits.z_min_m - _tilt_buffer(-theta, limits))
    bad = alt < need[..., ALTITUDE]
    near = (req.now[..., :ALTITUDE] - smax < need[..., :ALTITUDE]).any(-1)
    # Drones whose loiter path after the step could reach a clearance: the step must leave one
    # that keeps them all (the loiter certificate).
    near_c = (cert.now - reach < cert.need).any(-1)
    if scene.peers.shape[-2] > 32 and (near.any() or bad.any() or near_c.any()):
        req = _near_peers_only(req, scene, cons.dist, limits, _loiter_reach_m(limits))
        cert = dataclasses.replace(
            cert, clear=dataclasses.replace(req.hard, source_required=cert.clear.source_required, obstacle_required=cert.clear.obstacle_required)
        )
    if near.any():
        idx = np.nonzero(near)
        score = _score((p + u)[idx][..., None, :], theta[idx][..., None], _subset(req.strict, idx), bmin, bmax, limits)
        bad[idx] |= (score[..., 0, :] < need[idx]).any(-1)
    if near_c.any():
        idx = np.nonzero(near_c & ~bad)
        bad[idx] |= ~_certified((p + u)[idx][:, None, :], u[idx][:, None, :], _cert_subset(cert, idx), bmin, bmax, limits)[:, 0]
    active[..., ALTITUDE] |= alt < 0.0
    if bad.any():
        idx = np.nonzero(bad)
        u_b, margins_b, inf_b = _envelope_search(
            p[idx],
            u[idx],
            prev[idx],
            has_prev[idx],
            need[idx],
            _subset(req.strict, idx),
            bmin,
            bmax,
            limits,
            _subset(req.loose, idx),
            _subset(req.hard, idx),
            _cert_subset(cert, idx),
        )
        u = u.copy()
        u[idx] = u_b
        filtered[idx] = True
        infeasible[idx] = inf_b
        active[idx] |= margins_b < 0.0
    return u, active, filtered, infeasible


def _certified_lazily(
    p: FloatArray,
    cand: FloatArray,
    tiers: Sequence[tuple[BoolArray, FloatArray]],
    cert: _Certificate,
    bmin: FloatArray,
    bmax: FloatArray,
    limits: Limits,
) -> BoolArray:
    """(n, C) :func:`_certified` of the candidate steps ``cand`` (n, C, 3) from ``p`` (n, 3), as far as
    the filter's pick needs it. ``tiers``: (eligible (n, C), score (n, C)) in order; per row, the
    eligible candidates of the first tier are checked best score first until one is certified,
    then, where none is, those of the next tier. Candidates left unchecked are False; the best
    certified candidate of the first tier that has one, and so the pick, is the one a full check
    gives (ties in order of index). A filtered step mostly checks one or a few candidates."""
    n, C = cand.shape[:2]
    certified = np.zeros((n, C), dtype=bool)
    done = np.zeros(n, dtype=bool)
    for eligible, score in tiers:
        order = np.argsort(np.where(eligible, -score, np.inf), axis=-1, kind="stable")
        open_rows: BoolArray = np.asarray(eligible.any(-1) & ~done)
        for lo, hi in ((0, 1), (1, 5), (5, C)):
            rows = np.nonzero(open_rows)[0]
            if rows.size == 0 or lo >= C:
                break
            cols = order[rows, lo:hi]
            r = rows[:, None]
            ok = eligible[r, cols] & _certified(p[rows, None, :] + cand[r, cols], cand[r, cols], _cert_subset(cert, (rows,)), bmin, bmax, limits)
            certified[r, cols] |= ok
            open_rows[rows] = ~ok.any(-1)
            done[rows] |= ok.any(-1)
    return certified


def _cert_subset(cert: _Certificate, idx: tuple[NDArray[np.intp], ...]) -> _Certificate:
    return _Certificate(_subset(cert.clear, idx), cert.need[idx], cert.now[idx])


def _active_families(active_all: BoolArray, safe: bool) -> BoolArray:
    """(..., 4) the constraint families (:data:`FAMILIES`) active in the projection, from the
    active columns (..., C) of :class:`_Constraints`."""
    n_alt = 2 if safe else 0
    active = np.zeros(active_all.shape[:-1] + (4,), dtype=bool)
    fam_active = active_all[..., : active_all.shape[-1] - n_alt]
    active[..., UAV] = fam_active[..., :-2].any(-1)
    active[..., SOURCE] = fam_active[..., -2]
    active[..., OBSTACLE] = fam_active[..., -1]
    if safe:
        active[..., ALTITUDE] = active_all[..., -2:].any(-1)
    return active


def _envelope_candidates(prev: FloatArray, has_prev: BoolArray, limits: Limits) -> tuple[FloatArray, FloatArray]:
    """The kinematic envelope's candidate steps (n, C, 3), m, and their tilts (n, C), rad:
    9 headings × 5 tilts across the allowed turn from the previous step ``prev`` (n, 3) (a full
    circle of headings, tilts within ±θ_max of level, before the first step) × {v_min, v_max}·Δt."""
    _, prev_psi, prev_theta = _spherical(prev)
    fr_h = np.linspace(-1.0, 1.0, 9)
    fr_t = np.linspace(-1.0, 1.0, 5)
    speeds = np.array([limits.step_min_m, limits.step_max_m])
    H, T, S = np.meshgrid(fr_h, fr_t, speeds, indexing="ij")
    H, T, S = H.ravel(), T.ravel(), S.ravel()
    psi = np.where(has_prev[:, None], prev_psi[:, None] + H * limits.heading_change_max_rad, np.pi * (H[None, :] + 1.0))
    th = np.where(
        has_prev[:, None],
        np.clip(prev_theta[:, None] + T * limits.tilt_change_max_rad, -0.5 * np.pi, 0.5 * np.pi),
        T * limits.tilt_change_max_rad,
    )
    # The loiter path's first step to either side (:func:`loiter_path`): a drone that keeps a
    # loiter certificate can always take it.
    turn = np.array([1.0, -1.0]) * limits.heading_change_max_rad
    level = np.sign(prev_theta) * np.maximum(np.abs(prev_theta) - limits.tilt_change_max_rad, 0.0)
    psi = np.concatenate((psi, prev_psi[:, None] + turn), -1)
    th = np.concatenate((th, np.repeat(level[:, None], 2, -1)), -1)
    S = np.concatenate((np.broadcast_to(S, prev_psi.shape + S.shape), np.full(prev_psi.shape + (2,), limits.step_min_m)), -1)
    return _cartesian(S, psi, th), th


def _relaxation_tiers(
    p: FloatArray,
    cand: FloatArray,
    u: FloatArray,
    margins: FloatArray,
    slack: FloatArray,
    strict: BoolArray,
    strict_uav: FloatArray,
    need: FloatArray,
    hard: _Clearances | None,
    limits: Limits,
    clear: _Clearances,
) -> tuple[list[tuple[BoolArray, FloatArray]], FloatArray]:
    """The tiers of :func:`_envelope_search`, most demanding first: per tier, which candidates
    (n, C) pass it and the score (n, C) the pick maximises among them; and the physical margin
    of the exactly known clearances (n, C), m, the last resort's score. ``margins`` (n, C, 4)
    per family, the peers' against ``loose``; ``slack`` = margins − need; ``strict`` the
    candidates passing every strict requirement and ``strict_uav`` their strict peer slack."""
    # The peers' reachable balls and the source keep-out without their turn-away buffers
    # (2b, b): still the safety distances (the source's while the estimate's error is within
    # the keep-out's inflation). A margin already below one of them may not shrink.
    tb = limits.turn_buffer_m
    uav_hard = (_peer_margin(p[:, None, :] + cand, hard) if hard is not None else slack[..., UAV] + 2.0 * tb) >= 0.0
    src_hard = margins[..., SOURCE] + tb >= np.minimum(need[:, None, SOURCE] + tb, 0.0)
    uav_record = _record_clearance_kept(p, cand, hard, limits.step_max_m) if hard is not None else uav_hard
    # The keep-out's floor: d_S* + its fixed inflation (never more than the keep-out); a drone
    # already inside it may not come nearer.
    keepout = np.broadcast_to(clear.source_required, p.shape[:-1]) - tb
    floor_r = np.minimum(limits.d_source_m + min(SOURCE_INFLATION_MIN_M, limits.d_source_m), keepout)
    d_now = np.sqrt(((p - clear.source) ** 2).sum(-1))
    d_cand = np.sqrt(((p[:, None, :] + cand - clear.source[:, None, :]) ** 2).sum(-1))
    src_floor = d_cand - floor_r[:, None] >= np.minimum(d_now - floor_r, 0.0)[:, None]
    # Physical margins of the exactly known clearances: without the recursive-feasibility
    # buffers (turn away, segment interior, tilt swing back).
    z = p[:, None, 2] + cand[..., 2]
    phys_obstacle = slack[..., OBSTACLE] + 0.5 * limits.step_max_m + limits.turn_buffer_m
    phys_altitude = np.minimum(limits.z_max_m - z, z - limits.z_min_m) - np.minimum(need[:, None, ALTITUDE], 0.0)
    exact = np.minimum(slack[..., OBSTACLE], slack[..., ALTITUDE])
    exact_phys = np.minimum(np.minimum(phys_obstacle, 0.5 * limits.step_max_m + limits.turn_buffer_m), phys_altitude)
    closeness = ((cand - u[:, None, :]) ** 2).sum(-1)
    # Tiers, most demanding first; within a tier the pick is the closest to the desired step
    # (tier 1) or the one that best restores what the tier gave up.
    tiers = [
        (strict, -closeness),  # 1. every clearance with its buffers, the peers' balls of now
        ((slack >= 0.0).all(-1), strict_uav),  # 2. the peers' requirements loose, the strict ones approached
        # 3. the peers' and the source's turn-away buffers relaxed, their safety distances kept
        ((exact >= 0.0) & uav_hard & src_hard, np.minimum(slack[..., UAV], slack[..., SOURCE])),
        # 4. the peers' balls beyond d_U* + v_max Δt of their records and the d_U*/2 in front
        #    of a lost peer's plane given up, the source keep-out kept: squeezed between stale
        #    peers' balls (or a plane) and the keep-out, drones went up to 0.91 m inside d_S*.
        ((exact >= 0.0) & src_hard & uav_record, slack[..., UAV]),
        # 5. the source keep-out relaxed to its floor, the peers' balls kept; 5'. the peers'
        #    balls given up, the floor kept (a drone at the altitude floor, squeezed by a lost
        #    peer's plane, went 0.48 m inside d_S* where the keep-out went first);
        #    5''. the source keep-out relaxed, the peers' balls kept.
        ((exact >= 0.0) & uav_hard & src_floor, slack[..., SOURCE]),
        ((exact >= 0.0) & src_floor, slack[..., UAV]),
        ((exact >= 0.0) & uav_hard, slack[..., SOURCE]),
        (exact >= 0.0, np.minimum(slack[..., UAV], slack[..., SOURCE])),  # 6. peers relaxed too
        # 7. the obstacle buffers relaxed (conservative: the turn-away and segment-interior
        #    allowances leave real room); the altitude keeps its tilt buffer, which is the
        #    climb that cannot be avoided next step.
        ((phys_obstacle >= 0.0) & (slack[..., ALTITUDE] >= 0.0), slack[..., OBSTACLE]),
        (exact_phys >= 0.0, exact),  # 8. every buffer relaxed
    ]
    return tiers, exact_phys


def _dead_reckoning_kept(p: FloatArray, cand: FloatArray, hard: _Clearances, limits: Limits) -> BoolArray | None:
    """(n, C) the candidate steps ``cand`` from ``p`` (n, 3) that do not bring drone i nearer
    the dead-reckoned position of a peer whose reachable ball it is inside (``hard.reckoned_now``
    and ``hard.reckoned_next``: the peer's record moved on by its last step per step of age, now
    and at the end of the step): |p + u − r_j'| ≥ min(|p − r_j|, d_U* + 2 v_max Δt + 2b), m.
    None where no such peer (every candidate keeps it).

    Inside a peer's reachable ball the record no longer bounds where the peer is, and "not
    nearer the record" lets two drones flying side by side with late records close on each other
    (the record of a co-moving peer lies behind it). Not a guarantee (the peer may have turned
    since its record): it orders the steps within a tier of the filter, it never licenses one.
    """
    if hard.reckoned_now is None or hard.reckoned_next is None:
        return None
    known: BoolArray = np.asarray(np.isfinite(hard.reckoned_now).all(-1))  # (n, N)
    if not known.any():
        return None
    d_now = np.linalg.norm(p[:, None, :] - hard.reckoned_now, axis=-1)  # (n, N)
    d_next = np.linalg.norm(p[:, None, None, :] + cand[:, :, None, :] - hard.reckoned_next[:, None, :, :], axis=-1)  # (n, C, N)
    floor = np.minimum(d_now, limits.d_uav_m + 2.0 * limits.step_max_m + 2.0 * limits.turn_buffer_m)
    return np.asarray((~known[:, None, :] | (d_next >= floor[:, None, :])).all(-1))


def _record_clearance_kept(p: FloatArray, cand: FloatArray, hard: _Clearances, step_max_m: float) -> BoolArray:
    """(n, C) the candidates that keep every peer's clearance as if its record were of now:
    d_U* + v_max Δt from a heard peer's record (not its whole reachable ball: the peer's own
    filter keeps this drone's ball, which alone keeps the pair d_U* apart) and the drone's own
    side of every lost peer's plane (up to the plane itself, not d_U*/2 short of it). A drone
    already nearer than that may not come nearer, nor may a drone already inside a heard peer's
    reachable ball (where ``hard`` requires the distance now): approaching a late record down to
    d_U* + v_max Δt, two drones pushed toward each other by their own source keep-outs closed
    on each other 0.4-0.7 m a step and met 0.24 m inside d_U* (paper/dynamic_source A, 20 %
    loss and 3 steps of delay)."""
    now = peer_distance(p, hard.peers, hard.planes, hard.d_uav_m)
    required = np.full(now.shape, hard.d_uav_m + step_max_m)
    inside = now - hard.peer_required <= 1e-9
    if hard.planes is not None:
        plane = (hard.planes != 0.0).any(-1)
        required = np.where(plane, 0.5 * hard.d_uav_m, required)
        inside &= ~plane
    required = np.where(inside, now, np.minimum(required, now))
    required = np.where(np.isfinite(hard.peer_required), required, -np.inf)
    return _peer_margin(p[:, None, :] + cand, dataclasses.replace(hard, peer_required=required)) >= 0.0


def _envelope_search(
    p: FloatArray,
    u: FloatArray,
    prev: FloatArray,
    has_prev: BoolArray,
    need: FloatArray,
    clear: _Clearances,
    bmin: FloatArray,
    bmax: FloatArray,
    limits: Limits,
    loose: _Clearances | None = None,
    hard: _Clearances | None = None,
    cert: _Certificate | None = None,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Best step of the kinematic envelope for the flat batch ``p`` (n, 3).

    Candidates: 9 headings × 5 tilts across the allowed turn (a full circle of headings before
    the first step) × {v_min, v_max}·Δt. Among those whose every family margin is at least
    ``need`` (n, 4), the one closest to the desired step ``u``. Without one, constraints are
    relaxed in order of how little is known of them:

    1. the peers' requirements to those of ``loose`` (in :func:`control_step`: a peer's margin
       in deficit then only may not shrink against its end-of-step ball), taking the step that
       comes closest to the strict ones of ``clear``;
    2. the turn-away buffers of the peers (to ``hard``: the reachable balls themselves) and of
       the source keep-out (b), their safety distances kept;
    3. the peers' reachable balls beyond d_U* + v_max Δt of their records and, in a
       partition, the d_U*/2 in front of a lost peer's plane (:func:`_record_clearance_kept`), the source
       keep-out kept;
    4. the source keep-out (it follows the estimate) down to its floor d_S* + 1.5 m, the peers
       kept as in 2; then the peers' balls and planes, that floor kept; then the rest of the
       keep-out, the peers kept as in 2;
    5. the peers' clearance (their data age);
    6. only then the recursive-feasibility buffers of the exactly known obstacles and
       altitude box.

    ``loose`` and ``hard`` default to ``clear`` and to ``clear`` without 2b. Returns the step
    (n, 3), its margins (n, 4, the peers' against ``loose``) and its infeasibility (n,): no
    step keeps every clearance with ``loose``.
    """
    cand, th = _envelope_candidates(prev, has_prev, limits)  # (n, C, 3), (n, C)
    margins = _score(p[:, None, :] + cand, th, clear, bmin, bmax, limits)  # (n, C, 4)
    strict = np.asarray((margins - need[:, None, :] >= 0.0).all(-1))
    strict_uav = margins[..., UAV] - need[:, None, UAV]
    if loose is not None:
        margins[..., UAV] = _peer_margin(p[:, None, :] + cand, loose)
    slack = margins - need[:, None, :]
    tiers, exact_phys = _relaxation_tiers(p, cand, u, margins, slack, strict, strict_uav, need, hard, limits, clear)
    infeasible = np.asarray(~tiers[1][0].any(-1))
    reckoned = _dead_reckoning_kept(p, cand, hard, limits) if hard is not None else None
    if reckoned is not None:
        # Only among the steps that keep the source, obstacle and altitude clearances with their
        # buffers: preferred at their expense, a drone beside a building gave up its buffers
        # for a peer and ended 0.69 m inside d_O* (paper/dynamic_source D, 20 % loss).
        reckoned &= (slack[..., SOURCE] >= 0.0) & (slack[..., OBSTACLE] >= 0.0) & (slack[..., ALTITUDE] >= 0.0)
    if cert is not None:
        # Tier 0's pick is the closest strict certified candidate, tier 0''s the certified one that
        # comes closest to the buffers: only as many candidates are checked as those picks need.
        buffers = np.minimum(slack[..., UAV], slack[..., SOURCE])
        everyone = np.ones_like(strict)
        lazy = [(strict, tiers[0][1]), (everyone, buffers)]
        if reckoned is not None:
            lazy = [(strict & reckoned, tiers[0][1]), lazy[0], (reckoned, buffers), lazy[1]]
        certified = _certified_lazily(p, cand, lazy, cert, bmin, bmax, limits)
        # 0. every clearance with its buffers and a loiter certificate after the step; 0'. a
        # loiter certificate, the buffers given up (the step that comes closest to them).
        tiers[0:0] = [(strict & certified, tiers[0][1]), (certified, buffers)]
    if reckoned is not None:
        # Within each tier, the steps that keep clear of the peers' dead-reckoned positions first.
        tiers = [t for ok, score in tiers for t in ((ok & reckoned, score), (ok, score))]
    pick = exact_phys.argmax(-1)  # 9. least bad for obstacles and altitude
    for ok, score in reversed(tiers):
        pick = np.where(ok.any(-1), np.where(ok, score, -np.inf).argmax(-1), pick)
    rows = np.arange(p.shape[0])
    return cand[rows, pick], margins[rows, pick], infeasible
