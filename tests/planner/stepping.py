"""Helpers of the math-core tests that build a control step's or a planning step's inputs from
plain arguments (:class:`planner.control.ControlScene`, :class:`planner.step.StepScene`,
:class:`planner.step.DroneState`, :class:`planner.config.PlannerConfig`)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from planner.config import PlannerConfig
from planner.control import ControlScene, StepResult, control_step
from planner.estimator import EstimatorConfig
from planner.params import Channel, Limits
from planner.step import OWN_RANGE_WINDOW, DroneState, StepScene

NO_BOX = np.zeros((0, 3))


def control_step_of(
    own: ArrayLike,
    prev: ArrayLike,
    grad: ArrayLike,
    status: ArrayLike,
    peers: ArrayLike,
    mask: ArrayLike,
    age: ArrayLike,
    source: ArrayLike,
    keepout: ArrayLike,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    limits: Limits,
    uniforms: ArrayLike,
    *,
    xi: float | None = None,
    perturbation_rad: float = math.radians(20.0),
    peer_planes: ArrayLike | None = None,
    source_exact: bool = False,
    peer_drift_m: ArrayLike | None = None,
) -> StepResult:
    """:func:`planner.control.control_step` of the scene these arguments make (same units and
    shapes as :class:`planner.control.ControlScene`'s fields, in its order)."""
    scene = ControlScene(own, prev, grad, status, peers, mask, age, source, keepout, uniforms, peer_planes, peer_drift_m)
    return control_step(scene, limits, boxes_min, boxes_max, xi=xi, perturbation_rad=perturbation_rad, source_exact=source_exact)


def planner_config(
    ranging: ArrayLike,
    bearing: ArrayLike,
    limits: Limits | None = None,
    *,
    boxes: tuple[ArrayLike, ArrayLike] = (NO_BOX, NO_BOX),
    start_positions_m: ArrayLike | None = None,
    d_hop_m: float = 100.0,
    criterion: str = "A",
    channel: Channel | None = None,
) -> PlannerConfig:
    """A mission's planning parameters for drones with the given roles (κ, β per drone)."""
    return PlannerConfig(
        channel=Channel() if channel is None else channel,
        limits=Limits() if limits is None else limits,
        criterion=criterion,  # type: ignore[arg-type]
        component_masks={"range": np.asarray(ranging, dtype=bool), "bearing": np.asarray(bearing, dtype=bool)},
        boxes_min_m=np.asarray(boxes[0], dtype=float).reshape(-1, 3),
        boxes_max_m=np.asarray(boxes[1], dtype=float).reshape(-1, 3),
        d_hop_m=d_hop_m,
        start_positions_m=None if start_positions_m is None else np.asarray(start_positions_m, dtype=float),
        estimator=EstimatorConfig(),
    )


def step_scene(
    own_index: int,
    view_positions_m: ArrayLike,
    view_valid: ArrayLike,
    *,
    step_index: int = 0,
    view_los: ArrayLike | None = None,
    saved_steps: ArrayLike | None = None,
    hops: ArrayLike | None = None,
    estimate_m: ArrayLike = (0.0, 0.0, 0.0),
    information: ArrayLike | None = None,
    observable: bool = True,
    uniforms: ArrayLike = (0.5, 0.5),
    own_range_m: float = math.nan,
    own_los: bool = True,
    lost_contact: ArrayLike | None = None,
) -> StepScene:
    """One drone's step inputs: its view (positions (N, 3) and which rows hold a record), at
    ``view_positions_m[own_index]``; records of this step unless ``saved_steps`` says otherwise,
    LOS, every peer a direct neighbour by default."""
    pos = np.asarray(view_positions_m, dtype=float)
    valid = np.asarray(view_valid, dtype=bool)
    n = pos.shape[0]
    info = np.eye(3) if information is None else np.asarray(information, dtype=float)
    return StepScene(
        step_index=step_index,
        own_index=np.array(own_index),
        own_position_m=pos[own_index],
        own_range_m=np.array(own_range_m),
        own_los=np.array(own_los),
        view_positions_m=pos,
        view_valid=valid,
        view_los=np.ones(n, dtype=bool) if view_los is None else np.asarray(view_los, dtype=bool),
        saved_steps=np.where(valid, step_index, -1) if saved_steps is None else np.asarray(saved_steps),
        hops=np.where(np.arange(n) == own_index, 0, 1) if hops is None else np.asarray(hops),
        estimate_m=np.asarray(estimate_m, dtype=float),
        information=info,
        observable=np.array(observable),
        perturbation_uniforms=np.asarray(uniforms, dtype=float),
        lost_contact=None if lost_contact is None else np.asarray(lost_contact, dtype=bool),
    )


def drone_state(
    drones: int, *, previous_step_m: ArrayLike = (0.0, 0.0, 0.0), ranges_m: ArrayLike | None = None, los: Any = True, loitering: bool = False
) -> DroneState:
    """One drone's carried state: its last step and its own last ranges before this step (NaN:
    none; oldest first, at most :data:`planner.step.OWN_RANGE_WINDOW` − 1 of them, the step's own
    range follows in its scene)."""
    state = DroneState.initial((), drones)
    window = state.own_range_m.copy()
    flags = state.own_range_los.copy()
    if ranges_m is not None:
        r = np.asarray(ranges_m, dtype=float)[-(OWN_RANGE_WINDOW - 1) :]
        window[OWN_RANGE_WINDOW - r.size :] = r
        flags[OWN_RANGE_WINDOW - r.size :] = los
    return replace(
        state, previous_step_m=np.asarray(previous_step_m, dtype=float), own_range_m=window, own_range_los=flags, loitering=np.array(loitering)
    )
