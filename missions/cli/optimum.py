"""``fimnav optimum MISSION``: the optimal placement of a mission's swarm and its PEB.

The smallest A/D cost of eq. 6 (and its PEB, eq. 18) any placement of the mission's drones can
have at the source position, under the distances the control rule keeps
(:func:`planner.placement.optimal_placement`, :func:`planner.placement.placement_bounds`):
a reference for a run's final PEB (``fimnav montecarlo --optimum`` adds the ratio to each
run's summary). docs/control.md, "Optimal placement", describes it.
"""

from __future__ import annotations

import argparse
import math
import sys
from typing import Any

from comms.errors import UsageError
from missions.study.optimum import DEFAULT_STARTS, mission_optimum


def register(subparsers: Any) -> None:
    """Add the ``optimum`` subcommand."""
    p = subparsers.add_parser(
        "optimum",
        help="the optimal placement of a mission's swarm and its PEB (a reference for runs)",
        description=(
            "Minimise the mission's A or D cost (eq. 6) over the positions of all its drones at "
            "once, at the source position, keeping the distances of the control rule (source, "
            "peers, buildings, altitude box; each link's LOS from the buildings); print the PEB, "
            "the placement and what it depends on. SLSQP from seeded random starts."
        ),
    )
    p.add_argument(
        "mission", metavar="MISSION", help="mission file, or the name of a mission shipped with fimnav such as paper/joint (fimnav missions list)"
    )
    p.add_argument("--criterion", choices=("A", "D"), help="design criterion (default: the mission's)")
    p.add_argument("--starts", type=int, default=DEFAULT_STARTS, help=f"random starts (default {DEFAULT_STARTS})")
    p.add_argument("--seed", type=int, default=0, help="seed of the starts (default 0)")
    p.add_argument(
        "--margins",
        choices=("filter", "hold", "none"),
        default="filter",
        help="distances kept: the safe rule's end-of-step clearances (filter, default), where its "
        "projection holds a converged drone (hold), or the bare d_S*, d_U*, d_O*, altitude box (none)",
    )
    p.add_argument(
        "--oracle-estimate", action="store_true", help="the keep-out of a swarm planning with the true source (no 1.5 m inflation about an estimate)"
    )
    p.add_argument(
        "--time",
        type=float,
        default=None,
        metavar="SECONDS",
        help="source position at this time (default: the end of the mission, K dt; a static source does not move)",
    )
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Load the mission, compute its optimum, print it. Exit status 0."""
    from missions.format.loader import load_mission, parse_overrides

    if args.starts < 1:
        raise UsageError(f"--starts: expected a positive integer, found {args.starts}")
    if args.time is not None and not (math.isfinite(args.time) and args.time >= 0.0):
        raise UsageError(f"--time: expected a time >= 0 s, found {args.time}")
    mission = load_mission(args.mission, parse_overrides(args.overrides))
    crit = args.criterion or mission.criterion
    p = mission_optimum(mission, crit, args.starts, args.seed, args.margins, args.oracle_estimate, args.time)
    sys.stdout.write(report(mission, p, args.time))
    return 0


def report(mission: Any, p: Any, time_s: float | None = None) -> str:
    """The text ``fimnav optimum`` prints: parameters, the optimum, the placement per drone."""
    import numpy as np

    b = p.bounds
    lim = mission.limits()
    ch = mission.channel
    c = mission.constraints
    t = mission.duration_s if time_s is None else float(time_s)
    src = p.source_m
    where = "static" if mission.source.is_static else f"moving: its position at t = {t:g} s"
    unit = "m^2 (tr J^-1)" if p.criterion == "A" else "(-ln det J)"
    lines = [
        f"mission    {mission.id}: {mission.drones.count} drones "
        f"({int(mission.drones.ranging_mask().sum())} ranging, {int(mission.drones.bearing_mask().sum())} bearing), "
        f"criterion {p.criterion}",
        f"source     [{src[0]:g}, {src[1]:g}, {src[2]:g}] m ({where})",
        f"channel    gamma {ch.path_loss_exponent:g}, sigma_sh/gamma {ch.sigma_ratio_los:g} LOS / "
        f"{ch.sigma_ratio_nlos:g} NLOS, sigma_b {ch.sigma_bearing_deg:g} deg; {len(mission.obstacles)} building(s)",
        f"distances  margins '{b.rule}' (activation {c.activation}): source >= {b.source_m:.2f} m "
        f"(d_S* {c.d_source_m:g} + {b.source_margin_m:.2f}), drones >= {b.uav_m:.2f} m (d_U* {c.d_uav_m:g} + "
        f"{b.uav_margin_m:.2f}),",
        f"           buildings >= {b.obstacle_m:.2f} m (d_O* {c.d_obstacle_m:g} + {b.obstacle_margin_m:.2f}), "
        f"z {b.z_min_m:.2f}..{b.z_max_m:.2f} m (box {c.z_min_m:g}..{c.z_max_m:g}); turn buffer b {lim.turn_buffer_m:.2f} m",
        f"solver     SLSQP, {p.starts} random starts, seed {p.seed}; best start {p.best_start}, "
        f"{int(np.isfinite(p.start_costs).sum())} feasible; worst margin {min(p.margins_m.values()):.2g} m",
        "",
        f"optimal PEB  {p.peb_m:.4g} m   (cost {p.cost:.6g} {unit}; {int(p.los.sum())}/{p.los.size} links LOS)",
        "",
        f"{'drone':>5} {'role':<8} {'distance [m]':>12} {'azimuth [deg]':>13} {'altitude [m]':>12} {'LOS':>4}",
    ]
    roles = mission.drones.roles
    for i, (d, az, z, los) in enumerate(zip(p.distances_m, np.degrees(p.azimuths_rad), p.positions_m[:, 2], p.los, strict=True)):
        lines.append(f"{i + 1:>5} {roles[i]:<8} {d:>12.2f} {az:>13.1f} {z:>12.2f} {'yes' if los else 'no':>4}")
    lines.append("azimuth: of the drone seen from the source, degrees from east towards north (mission ENU)")
    return "\n".join(lines) + "\n"
