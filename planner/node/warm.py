"""Importing this module loads the compiled planning kernels into the process (numba: from its
cache, or compiled once after an install): the fork server of ``fimnav launch`` imports it
before it forks the planners (``missions.launch.forkspawn.PRELOAD``), so ten planners do not
each load, or compile, the same kernels at their first step.

:func:`warm_up` runs one planning step (:func:`planner.agent.plan`) of a small synthetic
mission: the same kernels, with the same argument types, as a planner's steps.
"""

from __future__ import annotations

import numpy as np

from planner.agent import plan
from planner.config import PlannerConfig
from planner.estimator import EstimatorConfig
from planner.params import Channel, Limits
from planner.step import DroneState, StepScene


def warm_up() -> None:
    """One planning step of drone 0 of two (joint and ranging, one building, start positions
    known), its peer heard directly: every kernel a planner's step calls is loaded."""
    start = np.array([[0.0, 100.0, 10.0], [5.0, 100.0, 10.0]])
    config = PlannerConfig(
        channel=Channel(),
        limits=Limits(),
        criterion="A",
        component_masks={"range": np.array([True, True]), "bearing": np.array([True, False])},
        boxes_min_m=np.array([[20.0, 40.0, 0.0]]),
        boxes_max_m=np.array([[30.0, 50.0, 15.0]]),
        d_hop_m=100.0,
        start_positions_m=start,
        estimator=EstimatorConfig(),
    )
    scene = StepScene(
        step_index=0,
        own_index=np.array(0),
        own_position_m=start[0],
        own_range_m=np.array(100.0),
        own_los=np.array(True),
        view_positions_m=start,
        view_valid=np.ones(2, dtype=bool),
        view_los=np.ones(2, dtype=bool),
        saved_steps=np.zeros(2, dtype=np.int64),
        hops=np.array([0, 1]),
        estimate_m=np.array([0.0, 0.0, 2.0]),
        information=np.eye(3),
        observable=np.array(True),
        perturbation_uniforms=np.array([0.5, 0.5]),
        lost_contact=np.zeros(2, dtype=bool),
    )
    plan(config, scene, DroneState.initial((), 2))


warm_up()
