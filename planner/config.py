"""What a drone's planning step takes from the mission, built once (``Mission.planner_config``)
and passed whole to :func:`planner.agent.plan`, the in-process simulator and the planner node:
one source for each fact."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planner.estimator import EstimatorConfig
from planner.params import Channel, Criterion, Limits


@dataclass(frozen=True, eq=False)
class PlannerConfig:
    """The mission's planning parameters (paper section III-IV; mission frame ENU, metres).

    Attributes:
        channel: the RSS channel of eqs. 1-5 (γ, σ_sh/γ, σ_θ).
        limits: the kinematic limits and safety distances (v_max Δt, turn rates, d_U*, d_S*,
            d_O*, the altitude box) of problem 7, per step of ``limits.dt_s``.
        criterion: ``"A"`` or ``"D"``, the design criterion of eq. 6.
        ranging, bearing: (N,) bool, the roles κ_j, β_j of every drone.
        boxes_min_m, boxes_max_m: (B, 3), the buildings' corners, m, ENU (B may be 0).
        d_hop_m: the radio range d_hop of the multi-hop network, m.
        start_positions_m: (N, 3), every drone's position at step 0, m, ENU (known to all); None:
            a peer not heard of yet is not a constraint.
        estimator: the source estimator's settings.
        xi: the projected-gradient step ξ of eq. 10; None: the controller's default.
        perturbation_rad: the random perturbation of the singular-FIM fallback, rad.
    """

    channel: Channel
    limits: Limits
    criterion: Criterion
    ranging: NDArray[np.bool_]
    bearing: NDArray[np.bool_]
    boxes_min_m: NDArray[np.float64]
    boxes_max_m: NDArray[np.float64]
    d_hop_m: float
    start_positions_m: NDArray[np.float64] | None
    estimator: EstimatorConfig
    xi: float | None = None
    perturbation_rad: float = math.radians(20.0)
