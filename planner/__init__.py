"""fimnav's math core: geometry, observation model, Fisher information, A/D costs, control law,
delayed view, PEB, source estimator. Pure numpy/scipy: no zenoh, no pymavlink, no files, no
network (tests/test_import_graph.py proves it). The planner node process lives at the edge,
in :mod:`planner.node`, and is not imported here.
"""

from planner.control import FAMILIES, StepResult, control_step
from planner.fim import (
    CostGradient,
    FimInverse,
    FimStatus,
    cost,
    cost_gradient,
    fisher_information,
    invert_fim,
    position_error_bound,
)
from planner.geometry import distance_to_boxes, distance_to_boxes_with_gradient, line_of_sight, ranges_angles
from planner.network import hop_counts, update_saved_steps
from planner.observation import Observation, observe, observe_from_uniforms, ranging_std
from planner.params import Channel, Limits

__all__ = [
    "FAMILIES",
    "Channel",
    "CostGradient",
    "FimInverse",
    "FimStatus",
    "Limits",
    "Observation",
    "StepResult",
    "control_step",
    "cost",
    "cost_gradient",
    "distance_to_boxes",
    "distance_to_boxes_with_gradient",
    "fisher_information",
    "hop_counts",
    "invert_fim",
    "line_of_sight",
    "observe",
    "observe_from_uniforms",
    "position_error_bound",
    "ranges_angles",
    "ranging_std",
    "update_saved_steps",
]
