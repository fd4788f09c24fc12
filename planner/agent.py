"""One drone's planning step from its view: the chain shared by the in-process simulator and
the planner node, so both compute the same thing (DESIGN.md: "build the delayed view →
estimate the source → compute the control step under constraints").

Given drone i's view (the records it holds of every drone, itself included), its estimator
state and its last displacement, :func:`plan` returns the control step of
:func:`planner.control.control_step` together with the cost of eq. 6 it descended. Batched over
leading dimensions: the simulator passes (trials, drones), a planner node passes none.

Policies fixed here (docs/control.md):

* Planning FIM: drone i's own term is taken as if its link were LOS — the information it can
  regain by moving. With the recorded NLOS flag a bearing-only drone in a shadow would have a
  zero gradient and drift away.
* Source keep-out: d_S* + min(3σ, d_S*) around the estimate, σ the estimate's largest standard
  deviation; no source constraint while the source is not observable.
* Not observable yet: treated like a singular FIM (keep moving along the last direction with a
  random perturbation, the paper's fallback).
* Anti-collision against the peers heard directly (h_ij = 1) only: a peer not heard directly is
  farther than d_hop, which cannot close to d_U* within a step when d_hop is large enough
  (:func:`collision_relevant`); with a tiny d_hop every known peer counts, with its age.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.control import StepResult, control_step
from planner.fim import CostGradient, FimStatus, cost_gradient, fisher_information
from planner.params import Channel, Criterion, Limits

FloatArray = NDArray[np.float64]

#: Standard deviations of the source estimate added to d_S*.
SOURCE_SIGMA_FACTOR: float = 3.0


def source_keepout_m(limits: Limits, sigma_m: ArrayLike) -> FloatArray:
    """Keep-out radius around the source estimate (m): d_S* + min(3σ, d_S*).

    The inflation covers the estimate's error; its cap keeps an uncertain swarm from fleeing
    the estimate (fleeing lengthens the ranges, which grows σ: a runaway seen without the cap).
    """
    return limits.d_source_m + np.minimum(SOURCE_SIGMA_FACTOR * np.asarray(sigma_m, dtype=float), limits.d_source_m)


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


@dataclass(frozen=True)
class PlanResult:
    """A planning step: the control step and the cost it descended (at the estimate)."""

    step: StepResult
    cost: CostGradient
    keepout_m: FloatArray


def plan(
    own_position: ArrayLike,
    previous_step: ArrayLike,
    own_mask: ArrayLike,
    view_positions: ArrayLike,
    view_valid: ArrayLike,
    view_los: ArrayLike,
    view_age_steps: ArrayLike,
    hops: ArrayLike,
    ranging: ArrayLike,
    bearing: ArrayLike,
    estimate_m: ArrayLike,
    estimate_information: ArrayLike,
    observable: ArrayLike,
    channel: Channel,
    limits: Limits,
    criterion: Criterion,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    d_hop_m: float,
    perturbation_uniforms: ArrayLike,
    xi: float | None = None,
    perturbation_rad: float = np.radians(20.0),
    oracle_source: ArrayLike | None = None,
) -> PlanResult:
    """Drone i's planning step from its view (eqs. 6, 10-17).

    Args:
        own_position: p_i^(k) (..., 3), m, ENU. previous_step: u_i^(k) (..., 3), m.
        own_mask: (..., N) bool, True at drone i's own row of the view.
        view_positions: (..., N, 3) positions of the records in the view, m, ENU.
        view_valid: (..., N) bool, the view holds a record of that drone.
        view_los: (..., N) bool, LOS flag of each record. view_age_steps: (..., N) k − ℓ.
        hops: (..., N) hop counts from drone i (−1 unreachable), for :func:`collision_relevant`.
        ranging, bearing: (N,) roles κ_j, β_j.
        estimate_m, estimate_information, observable: drone i's estimator output.
        channel, limits, criterion, boxes_min, boxes_max, d_hop_m: mission parameters.
        perturbation_uniforms: (..., 2) uniforms for the singular fallback.
        xi, perturbation_rad: controller parameters.
        oracle_source: plan with this source position instead of the estimate (research mode:
            the paper's "estimate given"), with the plain d_S* keep-out.
    """
    own = np.asarray(own_mask, dtype=bool)
    valid = np.asarray(view_valid, dtype=bool)
    rng_view = np.asarray(ranging, dtype=bool) & valid
    brg_view = np.asarray(bearing, dtype=bool) & valid
    own_ranging = (np.asarray(ranging, dtype=bool) & own).any(-1)
    own_bearing = (np.asarray(bearing, dtype=bool) & own).any(-1)
    plan_los = np.asarray(view_los, dtype=bool) | own
    p_hat = np.asarray(estimate_m, dtype=float) if oracle_source is None else np.broadcast_to(np.asarray(oracle_source, dtype=float), np.shape(estimate_m))
    J = fisher_information(p_hat, view_positions, rng_view, brg_view, plan_los, channel)
    cg = cost_gradient(J, p_hat, own_position, own_ranging, own_bearing, np.ones(own_ranging.shape, dtype=bool), channel, criterion)
    obs = np.asarray(observable, dtype=bool)
    batch = np.shape(own_position)[:-1]
    if oracle_source is not None:
        status = cg.status
        keepout = np.full(batch, limits.d_source_m)
    else:
        status = np.where(obs, cg.status, np.int8(FimStatus.SINGULAR))
        keepout = np.where(obs, source_keepout_m(limits, estimate_sigma_m(estimate_information)), -np.inf)
    peers = valid & ~own & collision_relevant(hops, d_hop_m, limits)
    step = control_step(
        own_position, previous_step, cg.gradient, status, view_positions, peers, np.where(valid, view_age_steps, 0),
        p_hat, keepout, boxes_min, boxes_max, limits, perturbation_uniforms, xi=xi, perturbation_rad=perturbation_rad,
    )
    return PlanResult(step=step, cost=cg, keepout_m=np.asarray(keepout))
