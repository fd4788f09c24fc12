"""The planning step's cost when the source's power is unknown (mission ``source.power:
unknown``): eq. 6 on the Schur complement of the 4 × 4 information (position and power
offset, :mod:`planner.radio.unknown_power`), with its analytic gradient w.r.t. the drone's own
position (eq. 14).

The same policy as the known-power cost of :func:`planner.agent.plan` (the own link's predicted
line of sight q, :func:`planner.agent.own_los_weight`, passed in: J₄ = J₄,peers + q J₄,own,LOS + (1 − q)
J₄,own,NLOS and its gradient's term in ∇q), evaluated at the estimate p̂0 and the estimated
offset b̂ (the ``power_offset`` of :func:`planner.agent.plan`). The cost is given to the compiled step
(:func:`planner.kernels.plan_batch` with a given cost), which does everything else as with a
known power. Pure numpy (a different model, not a second implementation of the compiled one).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.config import PlannerConfig
from planner.fim import CostGradient
from planner.radio.unknown_power import cost_gradient_unknown_power, fisher_information_unknown_power
from planner.step import StepScene

FloatArray = NDArray[np.float64]


#: The own link's predicted line of sight (q, ∇q) of :func:`planner.agent.own_los_weight`.
LosWeight = Callable[..., tuple[FloatArray, FloatArray]]


def offset_or_zero(offset: ArrayLike | None, batch: tuple[int, ...]) -> FloatArray:
    """b̂ (``batch``), 0 where it is NaN or not given."""
    if offset is None:
        return np.zeros(batch)
    b = np.asarray(offset, dtype=float)
    return np.broadcast_to(np.where(np.isfinite(b), b, 0.0), batch)


def corrected_scene(scene: StepScene, offset: ArrayLike | None) -> StepScene:
    """The scene with the drone's own range divided by e^b̂ (the range of a source of the
    assumed power, as the own-range policies of :func:`planner.agent.plan` read it)."""
    if offset is None:
        return scene
    rng = np.asarray(scene.own_range_m, dtype=float) * np.exp(-offset_or_zero(offset, scene.batch))
    return dataclasses.replace(scene, own_range_m=rng)


def unknown_power_cost(config: PlannerConfig, scene: StepScene, p_hat: FloatArray, offset: ArrayLike | None, los_weight: LosWeight) -> CostGradient:
    """C(J_eq) of eq. 6 at ``p_hat`` (..., 3) and the power offset ``offset`` (...) over the
    drone's view and its gradient w.r.t. its own position, with the power unknown (module doc);
    ``los_weight``: :func:`planner.agent.own_los_weight`."""
    own = scene.own_mask
    valid = np.asarray(scene.view_valid, dtype=bool)
    ranging, bearing = np.asarray(config.ranging, dtype=bool), np.asarray(config.bearing, dtype=bool)
    index = np.asarray(scene.own_index)
    extra = {name: np.asarray(mask, dtype=bool) for name, mask in config.extra_masks.items()}
    extra_view = {name: mask & valid for name, mask in extra.items()}
    own_extra = {name: mask[index] for name, mask in extra.items()}
    view_los = np.asarray(scene.view_los, dtype=bool)
    b = offset_or_zero(offset, scene.batch)
    components = config.sensing.components
    if np.size(config.boxes_min_m) == 0:
        q = np.ones(scene.batch)
        grad_q = None
        plan_los = (view_los | own).astype(float)
    else:
        measured = (view_los & own).any(-1)
        q, grad_q = los_weight(scene.own_position_m, p_hat, config.boxes_min_m, config.boxes_max_m, measured_los=measured)
        plan_los = np.where(own, q[..., None], view_los.astype(float))
    J4 = fisher_information_unknown_power(
        p_hat, scene.view_positions_m, ranging & valid, bearing & valid, plan_los, config.channel, b, extra_view, components
    )
    return cost_gradient_unknown_power(
        J4,
        p_hat,
        scene.own_position_m,
        ranging[index],
        bearing[index],
        q,
        config.channel,
        config.criterion,
        b,
        own_los_gradient=grad_q,
        own_extra=own_extra,
        components=components,
    )


__all__ = ["LosWeight", "corrected_scene", "offset_or_zero", "unknown_power_cost"]
