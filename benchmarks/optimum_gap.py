"""Where a swarm's final PEB stands against the optimal placement, and what the gap is made of.

    python benchmarks/optimum_gap.py [--trials 20] [--missions joint bearing ...] [--criterion A D]

For each paper mission and criterion, the in-process simulator (the same code as ``fimnav
montecarlo``, seeded) runs twice: planning with the true source (``--oracle-estimate``) and with
each drone's own estimate (the default). The reference is P*, the optimal placement's PEB around
the true source at the distances the safety filter requires (``fimnav optimum MISSION
--oracle-estimate``, margins ``filter``: d_S* + b, d_U* + v_max Δt + 2b, d_O* + ½ v_max Δt + b,
the altitude box; ``planner.placement``). The final mean PEB of a run over P* is split into three
factors whose product it is:

* **hold**: P*_hold / P*, the optimum at the distances where eq. 14's projection holds a drone
  that the gradient presses against a constraint (margins ``hold``: the activation margin
  beyond each distance and inside each face of the altitude box; about an estimate
  a = 2 v_max Δt + b, about a static true source one step of the drone's own motion,
  v_max Δt + b from the source and v_max Δt sin θ_max inside each face);
* **distance**: P*_d / P*_hold, the optimum with the source distance set to the run's median final
  distance of the drones from the true source (the altitude box and the other distances of
  ``hold``): what the source keep-out's inflation for the estimate's uncertainty costs (about 1
  with the true source);
* **arrangement**: PEB_run / P*_d, the rest: drones arranged around a wrong estimate (estimator
  error), links left in a building's shadow, a swarm not converged or in a local optimum.

Printed per run: P*, the run's final mean PEB and its ratio, the three factors, the median final
distance from the source, the share of final links that are NLOS, the median final estimate
error and the run's violating drone-steps over every family (inter-drone, source, obstacle,
altitude, speed, turn rate; ``SimulationResult.violations``, on the true positions). The PEB of
eq. 18 is taken at the true source (at the end of the run for a moving source). The optimum minimises the A cost (the smallest PEB) for either criterion.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path[:1]:
    sys.path.insert(0, str(REPO))

from missions.format.loader import load_mission, resolve_mission  # noqa: E402
from missions.format.schema import Mission  # noqa: E402
from missions.study.simulator import RunSpec, SimulationResult, simulate  # noqa: E402
from planner.geometry import line_of_sight  # noqa: E402
from planner.placement import PlacementBounds, optimal_placement, placement_bounds  # noqa: E402

PAPER = ("ranging_los", "ranging_nlos", "dynamic_source", "bearing", "joint", "heterogeneous")


def optimum_peb_m(mission: Mission, bounds: PlacementBounds, starts: int) -> float:
    """The optimal placement's PEB (m) around the true source at the end of the run."""
    bmin, bmax = mission.obstacle_bounds()
    placement = optimal_placement(
        mission.source.position_at(mission.duration_s),
        mission.drones.ranging_mask(),
        mission.drones.bearing_mask(),
        mission.channel.to_planner(),
        bounds,
        bmin,
        bmax,
        "A",
        starts=starts,
        seed=0,
    )
    return float(placement.peb_m)


def final_facts(mission: Mission, result: SimulationResult) -> tuple[float, float, float, float]:
    """Final mean PEB (m), median distance of the drones from the true source (m), share of
    NLOS drone → source links, median estimate error (m), all at the last step."""
    peb = result.peb_m[-1]
    pos = result.positions_m[-1].reshape(-1, 3)
    src = result.source_m[-1]
    bmin, bmax = mission.obstacle_bounds()
    nlos = 1.0 - float(np.mean(line_of_sight(pos, src, bmin, bmax)))
    dist = float(np.median(np.linalg.norm(pos - src, axis=-1)))
    return float(np.mean(peb[np.isfinite(peb)])), dist, nlos, float(np.median(result.estimate_error_m[-1]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--trials", type=int, default=20)
    ap.add_argument("--missions", nargs="+", default=list(PAPER))
    ap.add_argument("--criterion", nargs="+", default=["A", "D"], choices=["A", "D"])
    ap.add_argument("--starts", type=int, default=8, help="random starts of the optimum (as fimnav optimum)")
    args = ap.parse_args(argv)
    print(
        "| run | source | P* [m] | PEB [m] | PEB / P* | hold | distance | arrangement | median distance [m] | NLOS links | median error [m] | violating drone-steps |"
    )
    print("|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name in args.missions:
        mission = load_mission(resolve_mission(f"paper/{name}"))
        limits = mission.limits()
        p_filter = optimum_peb_m(mission, placement_bounds(limits, "filter", oracle_estimate=True), args.starts)
        # Where the rule holds drones about the true source (a static one: one step of their own
        # motion from the source and the altitude faces) and about an estimate (2 v_max dt + b),
        # both without the estimate's inflation, which the distance factor measures.
        holds = {
            oracle: placement_bounds(limits, "hold", oracle_estimate=True, source_slow=oracle and mission.source_is_slow())
            for oracle in (True, False)
        }
        p_holds = {oracle: optimum_peb_m(mission, hold, args.starts) for oracle, hold in holds.items()}
        for criterion in args.criterion:
            spec = RunSpec(mission, criterion, args.trials, mission.steps)
            for oracle in (True, False):
                hold, p_hold = holds[oracle], p_holds[oracle]
                result = simulate(spec, oracle_estimate=oracle)
                peb, dist, nlos, err = final_facts(mission, result)
                violations = sum(result.violations().values())
                at_distance = dataclasses.replace(hold, source_m=dist, rule="custom")
                p_dist = optimum_peb_m(mission, at_distance, args.starts)
                print(
                    f"| paper/{name} {criterion} | {'true' if oracle else 'estimated'} | {p_filter:.2f} | {peb:.2f} | {peb / p_filter:.3f} "
                    f"| {p_hold / p_filter:.3f} | {p_dist / p_hold:.3f} | {peb / p_dist:.3f} | {dist:.1f} | {100 * nlos:.0f} % | {err:.2f} | {violations} |",
                    flush=True,
                )
    return 0


if __name__ == "__main__":
    sys.exit(main())
