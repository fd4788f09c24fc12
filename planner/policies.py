"""Baseline navigation policies: what a swarm does without the information-driven planner, for
a study to compare the planner against (``fimnav montecarlo --policy``, the mission key
``policy``).

* ``fim``: the paper's planner (:func:`planner.agent.plan`), the default.
* ``static``: every drone holds its start position (it does not move; holding is below v_min,
  which the speed accounting counts).
* ``orbit``: each drone circles its current source estimate in the horizontal plane at its
  start altitude, at the source keep-out distance plus three steps (:data:`ORBIT_MARGIN_STEPS`),
  following a slot of its own: the slots evenly spaced in angle by index, moving
  counter-clockwise seen from above a little faster than v_min (a drone off its slot catches
  up at v_max, along the circle).
* ``random``: a random walk at v_max: each step aims in a direction drawn uniformly on the
  sphere from the drone's own stream (:data:`RANDOM_WALK_STREAM`).
* ``centralized``: the planner with every record at once (no latency, no hop limit, no comms
  fault): each drone's view is every drone's current record, so each drone's gradient is its
  block of the joint gradient of the cost over all drones at its estimate, and every
  estimator sees the same records (one planner's). The simulator gives it that view
  (:mod:`missions.study.simulator`); the planning step is :func:`planner.agent.plan`.

``orbit`` and ``random`` replace the planner's cost gradient only: the step goes through the
same control law and safety filter (:func:`planner.control.control_step`: eq. 14 at v_max,
kinematic limits, the keep-out about the estimate, the own-range loiter, the singular-FIM
fallback while the estimate is not observable), so every policy keeps the same safety rules
and is counted by the same violation accounting.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.params import Limits

FloatArray = NDArray[np.float64]

#: The policies, the planner first.
POLICIES: tuple[str, ...] = ("fim", "static", "orbit", "random", "centralized")
PolicyName = Literal["fim", "static", "orbit", "random", "centralized"]
#: Policies whose step is the planner's (:func:`planner.agent.plan`).
PLANNER_POLICIES: tuple[str, ...] = ("fim", "centralized")
#: Purpose tag of the random walk's stream (:func:`planner.randomness.stream`; 0-2 are taken).
RANDOM_WALK_STREAM: int = 7
#: Uniforms per drone and step of the random walk (a direction on the sphere).
RANDOM_WALK_DRAWS: int = 2
#: The orbit's radius beyond the keep-out about the estimate, in steps of v_max Δt: outside the
#: band (2 v_max Δt + b) in which the keep-out's constraint acts, which would project the
#: drone's turn towards the centre away.
ORBIT_MARGIN_STEPS: float = 3.0
#: How far along its circle (in steps of v_max Δt) an orbiting drone away from its slot aims.
ORBIT_LOOKAHEAD_STEPS: float = 5.0


def random_walk_direction(uniforms: ArrayLike) -> FloatArray:
    """Unit vectors (..., 3) uniform on the sphere from uniforms (..., 2) in [0, 1): z = 2u₀ − 1,
    azimuth 2π u₁ (Archimedes' hat-box theorem)."""
    u = np.asarray(uniforms, dtype=float)
    z = 2.0 * u[..., 0] - 1.0
    phi = 2.0 * np.pi * u[..., 1]
    rho = np.sqrt(np.maximum(1.0 - z * z, 0.0))
    return np.stack([rho * np.cos(phi), rho * np.sin(phi), z], axis=-1)


def orbit_radius_m(limits: Limits, keepout_m: ArrayLike) -> FloatArray:
    """The orbit's radius (m): the keep-out about the estimate (at least d_S*) plus
    :data:`ORBIT_MARGIN_STEPS` steps of v_max Δt."""
    return np.maximum(np.asarray(keepout_m, dtype=float), limits.d_source_m) + ORBIT_MARGIN_STEPS * limits.step_max_m


def orbit_slot_speed_m(limits: Limits) -> float:
    """How far (m) an orbit slot moves per step: v_min Δt plus a tenth of (v_max − v_min) Δt, so
    a drone on its slot can follow it and one off it catches up at v_max."""
    return limits.step_min_m + 0.1 * (limits.step_max_m - limits.step_min_m)


def orbit_aim(
    position_m: ArrayLike,
    centre_m: ArrayLike,
    radius_m: ArrayLike,
    altitude_m: ArrayLike,
    index: ArrayLike,
    drones: int,
    step_index: int,
    phase0_rad: ArrayLike,
    limits: Limits,
) -> FloatArray:
    """The point (..., 3), m, ENU, an orbiting drone flies to at step k: on the horizontal
    circle of ``radius_m`` about ``centre_m`` (its x, y) at ``altitude_m``. Its slot is at
    θ_i = φ₀ + 2π i/N + ω (k + 1), ω = s / r with s the slot speed (:func:`orbit_slot_speed_m`):
    the slots evenly spaced by index, counter-clockwise seen from above. A drone within
    :data:`ORBIT_LOOKAHEAD_STEPS` steps of arc of its slot aims at the slot; one farther aims
    that far along the circle from its own bearing, the shorter way round to its slot (a
    straight line to the slot could cross the keep-out about the centre).

    Args:
        position_m: p_i (..., 3). centre_m: the estimate (..., 3). radius_m: r (...).
        altitude_m: the drone's height on its circle (...). index: i (0-based, ...).
        drones: N. step_index: k. phase0_rad: φ₀ (...), the first slot's angle from east.
    """
    r = np.asarray(radius_m, dtype=float)
    c = np.asarray(centre_m, dtype=float)
    p = np.asarray(position_m, dtype=float)
    slot = np.asarray(phase0_rad, dtype=float) + 2.0 * np.pi * np.asarray(index) / drones + orbit_slot_speed_m(limits) / r * (step_index + 1)
    own = np.arctan2(p[..., 1] - c[..., 1], p[..., 0] - c[..., 0])
    reach = ORBIT_LOOKAHEAD_STEPS * limits.step_max_m / r
    theta = own + np.clip((slot - own + np.pi) % (2.0 * np.pi) - np.pi, -reach, reach)
    return np.stack([c[..., 0] + r * np.cos(theta), c[..., 1] + r * np.sin(theta), np.broadcast_to(altitude_m, np.shape(theta))], axis=-1)


def check_policy(name: str) -> PolicyName:
    """``name`` if it is a policy of :data:`POLICIES` (ValueError naming them otherwise)."""
    if name not in POLICIES:
        raise ValueError(f"unknown policy {name!r}: expected one of {', '.join(POLICIES)}")
    return name  # type: ignore[return-value]


#: A planning step with the signature of :func:`planner.agent.plan`.
Planner = Callable[..., Any]


def policy_planner(name: str, walk_uniforms: FloatArray | None = None) -> Planner:
    """The planning step of policy ``name``, with the signature of :func:`planner.agent.plan`:
    :func:`planner.agent.plan` itself for ``fim`` and ``centralized`` (the latter differs by its
    view), else a step that replaces the planner's cost gradient (``orbit``, ``random``) or
    stays put (``static``).

    Args:
        name: one of :data:`POLICIES`.
        walk_uniforms: ``random``: the walk's uniforms (K, ..., 2) by step, from the drones'
            :data:`RANDOM_WALK_STREAM` streams (:func:`planner.randomness.presampled_uniforms`).
    """
    import functools

    from planner.agent import plan

    check_policy(name)
    if name in PLANNER_POLICIES:
        return plan
    if name == "static":
        return _held
    if name == "random":
        if walk_uniforms is None:
            raise ValueError("policy_planner: the random walk needs its uniforms")
        return functools.partial(_steered, aim=functools.partial(_random_gradient, np.asarray(walk_uniforms, dtype=float)))
    return functools.partial(_steered, aim=_orbit_gradient)


def _held(config: Any, scene: Any, state: Any, **_: Any) -> Any:
    """``static``: the step of a drone that holds its position (no displacement, no constraint,
    no fallback), as :func:`planner.agent.plan` returns it; the carried state unchanged."""
    from planner.agent import PlanResult
    from planner.control import StepResult
    from planner.fim import CostGradient

    p = np.array(scene.own_position_m, dtype=float)
    batch = p.shape[:-1]
    none = np.zeros(batch, dtype=bool)
    step = StepResult(p, np.zeros_like(p), np.zeros(batch + (4,), dtype=bool), none, none, none)
    cost = CostGradient(np.zeros(batch), np.zeros_like(p), np.zeros(batch, dtype=np.int8))
    return PlanResult(step, cost, np.full(batch, np.nan), np.asarray(scene.estimate_m), none, state)


def _random_gradient(
    table: FloatArray, config: Any, position: FloatArray, estimate_m: FloatArray, keepout_m: FloatArray, index: Any, k: int
) -> tuple[FloatArray, float | None]:
    """``random``: minus the step's random direction, normalised (the control law steps along
    −gradient at v_max)."""
    return -random_walk_direction(table[k]), None


def _orbit_gradient(
    config: Any, position: FloatArray, estimate_m: FloatArray, keepout_m: FloatArray, index: Any, k: int
) -> tuple[FloatArray, float | None]:
    """``orbit``: the displacement to the drone's slot (:func:`orbit_aim`) as minus a gradient with
    a spatial step ξ = 1 (the control law clips its length to [v_min, v_max] Δt); the first slot
    at the azimuth of the swarm's start centroid seen from the estimate."""
    starts = np.asarray(config.start_positions_m, dtype=float)
    n = starts.shape[0]
    centroid = starts.mean(0)
    phase0 = np.arctan2(centroid[1] - estimate_m[..., 1], centroid[0] - estimate_m[..., 0])
    radius = orbit_radius_m(config.limits, np.where(np.isfinite(keepout_m), keepout_m, config.limits.d_source_m))
    aim = orbit_aim(position, estimate_m, radius, starts[index, 2], index, n, k, phase0, config.limits)
    return position - aim, 1.0


def _steered(
    config: Any,
    scene: Any,
    state: Any,
    *,
    aim: Callable[..., tuple[FloatArray, float | None]],
    oracle_source: ArrayLike | None = None,
    oracle_slow: bool = True,
    power_offset: ArrayLike | None = None,
) -> Any:
    """:func:`planner.agent.plan` with the cost gradient of ``aim`` (``orbit``, ``random``):
    the same planning kernel after the cost (:func:`planner.kernels.plan_batch`: the FIM status
    of the estimate, the singular fallback while it is not observable, keep-out, own-range
    loiter, peer constraints, control step and safety filter)."""
    import math

    from planner import kernels as K
    from planner.agent import PlanResult, _kernel_config, _kernel_scene, estimate_sigma_m, source_keepout_m
    from planner.control import StepResult
    from planner.fim import CostGradient
    from planner.radio.power_planning import corrected_scene
    from planner.step import DroneState

    scene = corrected_scene(scene, power_offset)  # the own range of a source of the assumed power
    batch = scene.batch
    n = np.shape(scene.view_valid)[-1]
    p = np.asarray(scene.own_position_m, dtype=float)
    oracle = oracle_source is not None
    p_hat = np.broadcast_to(np.asarray(oracle_source, dtype=float), p.shape) if oracle else np.asarray(scene.estimate_m, dtype=float)
    keepout = np.full(batch, config.limits.d_source_m) if oracle else source_keepout_m(config.limits, estimate_sigma_m(scene.information))
    index = np.broadcast_to(np.asarray(scene.own_index), batch)
    gradient, xi = aim(config, p, p_hat, np.asarray(keepout, dtype=float), index, scene.step_index)
    status = np.zeros(batch, dtype=np.int8)
    kconfig = list(_kernel_config(config, scene.step_index, oracle, oracle and oracle_slow, n))
    kconfig[10] = math.nan if xi is None else float(xi)  # the spatial step ξ (NaN: normalised, v_max)
    old = state.kernel_arrays()
    new = tuple(np.empty_like(a) for a in old)
    u, flags, kept = np.empty(batch + (3,)), np.empty(batch + (8,), dtype=bool), np.empty(batch + (1,))
    out = (u.reshape(-1, 3), flags.reshape(-1, 8), kept.reshape(-1, 1))
    roles = (K.contiguous(config.ranging, bool), K.contiguous(config.bearing, bool), config.criterion == "D")
    view_los = K.as_batch(scene.view_los, batch + (n,), bool, 1)
    value, grad = np.zeros(batch), np.array(np.broadcast_to(gradient, batch + (3,)), dtype=float)  # writable: the kernel's signature
    # The cost given (True): the kernel takes the policy's gradient instead of the planner's.
    K.plan_batch(
        _kernel_scene(scene, p_hat, batch, n),
        view_los,
        roles,
        old,
        tuple(kconfig),
        new,
        out,
        (value.reshape(-1), grad.reshape(-1, 3), status.reshape(-1)),
        True,
    )
    step = StepResult(p + u, u, flags[..., :4], flags[..., 4], flags[..., 5], flags[..., 6])
    cg = CostGradient(np.zeros(batch), gradient, status)
    return PlanResult(step, cg, kept[..., 0], np.asarray(p_hat), flags[..., 7], DroneState.from_kernel_arrays(new, batch))
