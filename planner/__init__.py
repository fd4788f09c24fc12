"""fimnav's math core: geometry, observation model, Fisher information, A/D costs, control law,
delayed view, PEB, source estimator. Pure numpy/scipy: no zenoh, no pymavlink, no files, no
network (tests/test_import_graph.py proves it). The planner node process lives at the edge,
in :mod:`planner.node`, and is not imported here.

The public names below are loaded lazily (PEP 562): ``import planner`` costs nothing, and a
process that needs only part of the core (a simulated vehicle's payload, say) imports only that
part — which keeps a vehicle process small and quick to start.
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name -> defining submodule.
_EXPORTS: dict[str, str] = {
    "FAMILIES": "planner.control",
    "StepResult": "planner.control",
    "control_step": "planner.control",
    "CostGradient": "planner.fim",
    "FimInverse": "planner.fim",
    "FimStatus": "planner.fim",
    "cost": "planner.fim",
    "cost_gradient": "planner.fim",
    "fisher_information": "planner.fim",
    "invert_fim": "planner.fim",
    "position_error_bound": "planner.fim",
    "distance_to_boxes": "planner.geometry",
    "distance_to_boxes_with_gradient": "planner.geometry",
    "line_of_sight": "planner.geometry",
    "ranges_angles": "planner.geometry",
    "hop_counts": "planner.network",
    "update_saved_steps": "planner.network",
    "Observation": "planner.observation",
    "observe": "planner.observation",
    "observe_from_uniforms": "planner.observation",
    "ranging_std": "planner.observation",
    "Channel": "planner.params",
    "Limits": "planner.params",
    "plan": "planner.agent",
    "PlanResult": "planner.agent",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'planner' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value  # cache: later look-ups bypass __getattr__
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_EXPORTS))
