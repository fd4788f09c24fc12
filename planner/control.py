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

The step is compiled (:mod:`planner.kernels`, ``control_batch``: one loop over the batch, one
drone at a time); its inputs are one :class:`ControlScene` of plain arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner import kernels as K
from planner.geometry import as_boxes
from planner.params import Limits

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Indices of the constraint families in :attr:`StepResult.active`.
UAV, SOURCE, OBSTACLE, ALTITUDE = K.UAV, K.SOURCE, K.OBSTACLE, K.ALTITUDE
FAMILIES: tuple[str, ...] = ("uav", "source", "obstacle", "altitude")

#: Relative cut-off of the constraint normals' pseudo-inverse (eq. 14's (NᵀN)⁻¹).
PINV_RCOND: float = K.PINV_RCOND
#: A projected gradient shorter than this fraction of the gradient is zero.
PG_REL_TOL: float = K.PG_REL_TOL


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
    e = np.asarray(end, dtype=float)
    shape = np.broadcast_shapes(e.shape[:-1], np.shape(psi), np.shape(theta))
    psi_b, theta_b = np.broadcast_to(np.asarray(psi, dtype=float), shape), np.broadcast_to(np.asarray(theta, dtype=float), shape)
    heading = np.stack((np.cos(theta_b) * np.cos(psi_b), np.cos(theta_b) * np.sin(psi_b), np.sin(theta_b)), -1)  # the step's direction
    args = (K.as_batch(e, shape + (3,), float, 1), K.as_batch(heading, shape + (3,), float, 1))
    return K.loiter_batch(*args, kernel_limits(limits)).reshape(shape + (2, loiter_steps(limits), 3))


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


def limits_array(limits: Limits) -> FloatArray:
    """The limits array of the compiled control step (:func:`planner.kernels.limits_array`): the
    values of ``limits``, its activation rule and the values derived from them here (turn buffer,
    loiter path, activation margins). :func:`kernel_limits` computes it once per limits value."""
    distances = (limits.d_uav_m, limits.d_source_m, limits.d_obstacle_m, limits.step_min_m, limits.step_max_m)
    values = distances + (limits.heading_change_max_rad, limits.tilt_change_max_rad, limits.z_min_m, limits.z_max_m)
    derived = (
        limits.turn_buffer_m,
        float(loiter_steps(limits)),
        _loiter_reach_m(limits),
        source_activation_margin_m(limits),
        source_activation_margin_m(limits, exact=True),
        altitude_activation_margin_m(limits),
        altitude_activation_margin_m(limits, exact_source=True),
    )
    steps = np.arange(1.0, loiter_steps(limits) + 1.0) * limits.heading_change_max_rad
    table = tuple(np.stack((np.cos(steps), np.sin(steps)), -1).ravel())  # the loiter path's turns
    return K.limits_array(values, limits.activation == "safe", derived + table)


def kernel_limits(limits: Limits) -> FloatArray:
    """:func:`limits_array` of ``limits``, computed once per :class:`~planner.params.Limits` value
    and kept on it (a frozen value: the array never goes stale; the planning step reads it at
    every step)."""
    cached = limits.__dict__.get("_kernel_array")
    if cached is None:
        cached = limits_array(limits)
        object.__setattr__(limits, "_kernel_array", cached)
    return cached


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
    a, b = np.asarray(own_then_m, dtype=float), np.asarray(peer_then_m, dtype=float)
    shape = np.broadcast_shapes(a.shape, b.shape, np.shape(lost) + (3,))
    args = (K.as_batch(a, shape, float, 1), K.as_batch(b, shape, float, 1), K.as_batch(lost, shape[:-1], bool, 0))
    points, normals = K.planes_batch(*args)
    return points.reshape(shape), normals.reshape(shape)


def peer_distance(x: FloatArray, peers: FloatArray, planes: FloatArray | None, d_uav_m: float) -> FloatArray:
    """Distance (m) of positions ``x`` (..., 3) to each peer row (..., N, 3) → (..., N).

    A plane row (non-zero unit normal n in ``planes``) is a peer drone i has lost contact with:
    the row holds the point m of the plane both keep to their own side of (see
    :func:`lost_contact_planes`) and the "distance" is ``(x − m)·n + d_U*/2``, the distance to
    the mirror image of x when the peer keeps to its side at the same distance; it is 1-Lipschitz
    like a point distance, so the safety filter's margins apply unchanged."""
    xa, q = np.asarray(x, dtype=float), np.asarray(peers, dtype=float)
    batch = np.broadcast_shapes(xa.shape[:-1], q.shape[:-2])
    n = q.shape[-2]
    pl = np.zeros(batch + (n, 3)) if planes is None else np.broadcast_to(np.asarray(planes, dtype=float), batch + (n, 3))
    args = (K.as_batch(xa, batch + (3,), float, 1), K.as_batch(q, batch + (n, 3), float, 2), K.as_batch(pl, batch + (n, 3), float, 2))
    return K.peer_distance_batch(*args, float(d_uav_m)).reshape(batch + (n,))


@dataclass(frozen=True, eq=False)
class ControlScene:
    """The inputs of one control step, as plain arrays (leading batch dimensions ``...``: the
    simulator's trials × drones, none for a planner node; N peer rows).

    Attributes:
        own_position_m: p_i^(k), (..., 3), m, ENU.
        previous_step_m: u_i^(k), the last displacement (..., 3), m; zeros before the first step
            (no heading or tilt limit then).
        gradient: ∇_{p_i} C of eq. 6 (..., 3), from :func:`planner.fim.cost_gradient`.
        status: :class:`planner.fim.FimStatus` of drone i's J (...).
        peers_m: the other drones as known to drone i, (..., N, 3), m, ENU.
        peer_mask: (..., N) bool, which rows are real peers (False for drone i itself and for
            peers never heard of).
        peer_age_steps: (..., N), ≥ 0, age in steps of each peer's known position.
        source_m: p̂_0, the source estimate (..., 3), m, ENU.
        source_keepout_m: d_S* (possibly inflated by the estimate's uncertainty), (...), m; −inf:
            no source constraint.
        perturbation_uniforms: (..., 2) uniforms in [0, 1) for the singular fallback.
        peer_planes: (..., N, 3) unit normals for the peers drone i has lost contact with (zeros
            elsewhere): their row of ``peers_m`` is then a point of the plane drone i keeps to its
            side of, with its age 0 (:func:`lost_contact_planes`); None: none.
        peer_drift_m: (..., N, 3), m per step, ENU: each peer's last step as drone i's last two
            records of it give it (NaN: unknown): within a filter tier, a drone inside a peer's
            reachable ball prefers the steps that do not bring it nearer the peer's dead-reckoned
            position (docs/control.md). None: unknown for all.
    """

    own_position_m: ArrayLike
    previous_step_m: ArrayLike
    gradient: ArrayLike
    status: ArrayLike
    peers_m: ArrayLike
    peer_mask: ArrayLike
    peer_age_steps: ArrayLike
    source_m: ArrayLike
    source_keepout_m: ArrayLike
    perturbation_uniforms: ArrayLike
    peer_planes: ArrayLike | None = None
    peer_drift_m: ArrayLike | None = None


def control_step(
    scene: ControlScene,
    limits: Limits,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    *,
    xi: float | None = None,
    perturbation_rad: float = math.radians(20.0),
    source_exact: bool = False,
) -> StepResult:
    """One drone's control step: eq. 14 under constraints (15-17) and the limits of eq. 2/7.

    Args:
        scene: the step's inputs (:class:`ControlScene`; shapes broadcast to its batch).
        limits: safety distances and per-step kinematic limits.
        boxes_min, boxes_max: obstacles (B, 3), m, ENU.
        xi: spatial step ξ (m per unit of gradient); None = normalised step at v_max Δt.
        perturbation_rad: half-width of the uniform heading and tilt perturbation of the
            singular fallback (rad).
        source_exact: ``scene.source_m`` is the true source (planning with it, a research mode)
            and moves less than b per step: its constraint acts within v_max Δt + b instead of
            2 v_max Δt + b, the altitude box's within one level step's climb
            (:func:`source_activation_margin_m`, :func:`altitude_activation_margin_m`).

    Returns:
        The :class:`StepResult`. Compiled (:func:`planner.kernels.control_batch`).
    """
    p = np.asarray(scene.own_position_m, dtype=float)
    peers = np.asarray(scene.peers_m, dtype=float)
    batch, n = p.shape[:-1], peers.shape[-2]
    args = _one_drone(scene, p, peers) if p.ndim == 1 and peers.ndim == 2 else _batch_args(scene, p, peers, batch, n)
    u, flags = np.empty(batch + (3,)), np.empty(batch + (7,), dtype=bool)
    xi_value = np.nan if xi is None else float(xi)
    K.control_batch(
        *args,
        *as_boxes(boxes_min, boxes_max),
        kernel_limits(limits),
        xi_value,
        float(perturbation_rad),
        bool(source_exact),
        u.reshape(-1, 3),
        flags.reshape(-1, 7),
    )
    return StepResult(p + u, u, flags[..., :4], flags[..., 4], flags[..., 5], flags[..., 6])


def _batch_args(scene: ControlScene, p: FloatArray, peers: FloatArray, batch: tuple[int, ...], n: int) -> tuple[NDArray[Any], ...]:
    """The scene's arrays, broadcast to the batch and flattened, in the order of
    :func:`planner.kernels.control_batch`."""
    planes = np.zeros(batch + (n, 3)) if scene.peer_planes is None else scene.peer_planes
    drift = np.full(batch + (n, 3), np.nan) if scene.peer_drift_m is None else scene.peer_drift_m
    return (
        *(K.as_batch(x, batch + (3,), float, 1) for x in (p, scene.previous_step_m, scene.gradient)),
        K.as_batch(scene.status, batch, np.int8, 0),
        K.as_batch(peers, batch + (n, 3), float, 2),
        K.as_batch(scene.peer_mask, batch + (n,), bool, 1),
        K.as_batch(scene.peer_age_steps, batch + (n,), float, 1),
        K.as_batch(planes, batch + (n, 3), float, 2),
        K.as_batch(drift, batch + (n, 3), float, 2),
        K.as_batch(scene.source_m, batch + (3,), float, 1),
        K.as_batch(scene.source_keepout_m, batch, float, 0),
        K.as_batch(scene.perturbation_uniforms, batch + (2,), float, 1),
    )


def _one_drone(scene: ControlScene, p: FloatArray, peers: FloatArray) -> tuple[NDArray[Any], ...]:
    """:func:`_batch_args` of one drone's scene (no leading dimension; a batch of one, as views)."""
    n = peers.shape[0]
    planes = np.zeros((1, n, 3)) if scene.peer_planes is None else K.one_drone(scene.peer_planes)
    drift = np.full((1, n, 3), np.nan) if scene.peer_drift_m is None else K.one_drone(scene.peer_drift_m)
    one = (K.one_drone(p), K.one_drone(scene.previous_step_m), K.one_drone(scene.gradient), np.full(1, scene.status, dtype=np.int8))
    rows = (K.one_drone(peers), K.one_drone(scene.peer_mask, bool), K.one_drone(scene.peer_age_steps), planes, drift)
    return one + rows + (K.one_drone(scene.source_m), np.full(1, scene.source_keepout_m, dtype=float), K.one_drone(scene.perturbation_uniforms))


def _envelope_candidates(prev: FloatArray, has_prev: BoolArray, limits: Limits) -> tuple[FloatArray, FloatArray]:
    """The kinematic envelope's candidate steps (n, C, 3), m, and their tilts (n, C), rad, from the
    previous steps ``prev`` (n, 3) (:func:`planner.kernels.envelope_candidates`)."""
    prev_f = np.ascontiguousarray(np.asarray(prev, dtype=float).reshape(-1, 3))
    return K.candidates_batch(prev_f, K.contiguous(np.asarray(has_prev, dtype=bool).reshape(-1), bool), kernel_limits(limits))
