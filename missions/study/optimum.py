"""The optimal placement of a mission's swarm (:func:`planner.placement.optimal_placement`) as
a study computes it: for a mission (``fimnav optimum``) and for a run's summary
(``fimnav montecarlo --optimum``). docs/control.md, "Optimal placement", describes it."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from planner.params import Criterion
    from planner.placement import MarginRule

#: Random starts of the optimisation by default (each a few tenths of a second for ten drones).
DEFAULT_STARTS: int = 8


def mission_optimum(
    mission: Any,
    criterion: Criterion | None = None,
    starts: int = DEFAULT_STARTS,
    seed: int = 0,
    margins: MarginRule = "filter",
    oracle_estimate: bool = False,
    time_s: float | None = None,
) -> Any:
    """:func:`planner.placement.optimal_placement` for a :class:`missions.format.schema.Mission`: its
    roles, channel, buildings and limits, the source at ``time_s`` (default K·Δt, the end of the
    run: where a moving source is when the final PEB is taken). Returns the
    :class:`planner.placement.Placement`."""
    from planner.placement import optimal_placement, placement_bounds

    t = mission.duration_s if time_s is None else float(time_s)
    bmin, bmax = mission.obstacle_bounds()
    return optimal_placement(
        mission.source.position_at(t),
        mission.drones.ranging_mask(),
        mission.drones.bearing_mask(),
        mission.channel.to_planner(),
        placement_bounds(mission.limits(), margins, oracle_estimate, mission.source_is_slow()),
        bmin,
        bmax,
        criterion or mission.criterion,
        starts=starts,
        seed=seed,
        extra_masks=mission.planner_config(criterion or mission.criterion).extra_masks,
    )


def placement_summary(placement: Any) -> dict[str, Any]:
    """JSON-ready summary of a :class:`planner.placement.Placement` (m, degrees)."""
    b = placement.bounds
    return {
        "peb_m": placement.peb_m,
        "cost": placement.cost,
        "criterion": placement.criterion,
        "source_m": [float(v) for v in placement.source_m],
        "margins": b.rule,
        "source_distance_min_m": b.source_m,
        "uav_distance_min_m": b.uav_m,
        "obstacle_distance_min_m": b.obstacle_m,
        "z_range_m": [b.z_min_m, b.z_max_m],
        "starts": placement.starts,
        "seed": placement.seed,
        "los_links": int(placement.los.sum()),
        "positions_m": [[round(float(v), 3) for v in p] for p in placement.positions_m],
    }


def run_optimum_summary(result: Any, starts: int | None = None, seed: int = 0, known: dict[str, Any] | None = None) -> dict[str, Any]:
    """``{"optimum": ..., "final_peb_over_optimum": ...}`` for a
    :class:`missions.study.simulator.SimulationResult` (``fimnav montecarlo --optimum``): the optimum
    of its mission and criterion at the source's position after the run's last step, with the
    default rule's distances ("filter"; about the true source for an ``--oracle-estimate`` run),
    and the run's final mean PEB over it (None when that PEB is undefined). ``starts``: default
    :data:`DEFAULT_STARTS`. ``known``: placements already computed, by mission (whatever its
    navigation policy: the optimum does not depend on it), criterion, flags and steps; the one
    computed here is added."""
    spec = result.spec
    starts = DEFAULT_STARTS if starts is None else starts
    m = spec.mission
    oracle = bool(result.extra.get("oracle_estimate", 0.0))
    key = f"{m.model_copy(update={'policy': 'fim'}).model_dump_json()}|{spec.criterion}|{oracle}|{spec.steps}|{starts}|{seed}"
    p = (known or {}).get(key) or mission_optimum(m, spec.criterion, starts, seed, "filter", oracle, time_s=spec.steps * m.dt_s)
    if known is not None:
        known[key] = p
    final = float(result.peb_stats()["mean"][-1])
    ratio = final / p.peb_m if math.isfinite(final) and p.peb_m > 0.0 else None
    return {"optimum": placement_summary(p) | {"oracle_estimate": oracle}, "final_peb_over_optimum": ratio}
