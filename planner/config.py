"""What a drone's planning step takes from the mission, built once (``Mission.planner_config``)
and passed whole to :func:`planner.agent.plan`, the in-process simulator and the planner node:
one source for each fact."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from planner.estimator import EstimatorConfig
from planner.params import Channel, Criterion, Limits
from planner.radio.power_settings import UnknownPowerSettings
from planner.sensing import BEARING, RANGE, SENSING, SensingTable, extra_masks


@dataclass(frozen=True, eq=False)
class PlannerConfig:
    """The mission's planning parameters (paper section III-IV; mission frame ENU, metres).

    Attributes:
        channel: the RSS channel of eqs. 1-5 (γ, σ_sh/γ, σ_θ).
        limits: the kinematic limits and safety distances (v_max Δt, turn rates, d_U*, d_S*,
            d_O*, the altitude box) of problem 7, per step of ``limits.dt_s``.
        criterion: ``"A"`` or ``"D"``, the design criterion of eq. 6.
        component_masks: component name -> (N,) bool, which drones take each measurement
            component of ``sensing`` (from the drones' roles, :meth:`SensingTable.masks`);
            :attr:`ranging` (κ_j) and :attr:`bearing` (β_j) are views of it.
        boxes_min_m, boxes_max_m: (B, 3), the buildings' corners, m, ENU (B may be 0).
        d_hop_m: the radio range d_hop of the multi-hop network, m.
        start_positions_m: (N, 3), every drone's position at step 0, m, ENU (known to all); None:
            a peer not heard of yet is not a constraint.
        estimator: the source estimator's settings.
        xi: the projected-gradient step ξ of eq. 10; None: the controller's default.
        perturbation_rad: the random perturbation of the singular-FIM fallback, rad.
        sensing: the role table and component registry the masks refer to.
        unknown_power: the source's transmit power is unknown (mission ``source.power:
            unknown``): the estimator estimates it jointly with the position
            (:mod:`planner.radio.power_estimator`) and the planning cost is eq. 6 on the Schur
            complement of the 4 × 4 information (:mod:`planner.radio.power_planning`); None: the
            power is known (the paper's model).

    Raises:
        ValueError: ``component_masks`` does not name exactly the components of ``sensing``.
    """

    channel: Channel
    limits: Limits
    criterion: Criterion
    component_masks: Mapping[str, NDArray[np.bool_]]
    boxes_min_m: NDArray[np.float64]
    boxes_max_m: NDArray[np.float64]
    d_hop_m: float
    start_positions_m: NDArray[np.float64] | None
    estimator: EstimatorConfig
    xi: float | None = None
    perturbation_rad: float = math.radians(20.0)
    sensing: SensingTable = SENSING
    unknown_power: UnknownPowerSettings | None = None

    def __post_init__(self) -> None:
        expected = [c.name for c in self.sensing.components]
        if sorted(self.component_masks) != sorted(expected):
            raise ValueError(f"PlannerConfig.component_masks: expected masks of {expected}, found {list(self.component_masks)}")

    @property
    def ranging(self) -> NDArray[np.bool_]:
        """κ_j: (N,) bool, the drones that measure range."""
        return self.component_masks[RANGE.name]

    @property
    def bearing(self) -> NDArray[np.bool_]:
        """β_j: (N,) bool, the drones that measure azimuth and elevation."""
        return self.component_masks[BEARING.name]

    @property
    def extra_masks(self) -> Mapping[str, NDArray[np.bool_]]:
        """The masks of the components other than range and bearing, by name (empty for
        fimnav's own table)."""
        return extra_masks(self.component_masks)
