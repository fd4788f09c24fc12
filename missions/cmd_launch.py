"""``fimnav launch``: fly a mission as a swarm of processes (vehicles, planners, clock)."""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from planner.errors import UsageError


def register(subparsers: Any) -> None:
    """Add the ``launch`` subcommand."""
    p = subparsers.add_parser(
        "launch",
        help="fly a mission distributed: one vehicle and one planner process per drone, lockstep clock",
        description="Validate the mission, start N simulated vehicles and N planner processes talking "
        "over Zenoh (loopback) and MAVLink, step them in lockstep, show progress and write the results.",
    )
    p.add_argument("mission", type=Path, metavar="MISSION.yaml")
    p.add_argument("--out", type=Path, help="results directory (default: results/<mission id>-<time>)")
    p.add_argument("--steps", type=int, help="steps K (default: the mission's)")
    p.add_argument("--seed", type=int, help="root seed (default: the mission's)")
    p.add_argument("--criterion", choices=("A", "D"), help="design criterion (default: the mission's)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value (repeatable)")
    p.add_argument("--step-timeout", type=float, default=30.0, help="seconds a step may take before the run fails (default 30)")
    p.add_argument("--on-failure", choices=("continue", "abort", "restart"), default="continue",
                   help="when a vehicle or planner fails mid-mission: fly on without that drone (default), stop the run, "
                   "or also restart a failed planner, which rejoins at the current step; the summary lists every failure "
                   "and the exit status is then 3")
    p.add_argument("--vehicles-per-process", type=int, default=1, help="simulated vehicles hosted by one process (default 1; more for large swarms)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Validate, launch, report."""
    from tqdm import tqdm

    from missions.launcher import launch
    from missions.loader import load_mission, parse_overrides

    overrides = parse_overrides(args.overrides)
    for name in ("steps", "seed"):
        value = getattr(args, name)
        if value is not None:
            if value < (1 if name == "steps" else 0):
                raise UsageError(f"--{name}: expected {'a positive' if name == 'steps' else 'a non-negative'} integer, found {value}")
            overrides[name] = value
    if args.criterion:
        overrides["criterion"] = args.criterion
    if args.vehicles_per_process < 1:
        raise UsageError(f"--vehicles-per-process: expected a positive integer, found {args.vehicles_per_process}")
    mission = load_mission(args.mission, overrides)
    out = args.out or Path("results") / f"{mission.id}-{time.strftime('%Y%m%d-%H%M%S')}"
    bar = tqdm(total=mission.steps, unit="step", desc=f"launch {mission.id}", file=sys.stderr, disable=None)

    def progress(k: int, peb: float, err: float, alive: int) -> None:
        bar.set_postfix_str(f"PEB {peb:.3g} m, err {err:.3g} m, alive {alive}/{mission.drones.count}")
        bar.update(1)

    try:
        summary = launch(mission, out, progress=progress, step_timeout_s=args.step_timeout, vehicles_per_process=args.vehicles_per_process,
                         on_failure=args.on_failure)
    finally:
        bar.close()
    viol = sum(summary["violations"].values())
    print(
        f"{summary['run']}: PEB {summary['initial_peb_mean_m']} -> {summary['final_peb_mean_m']} m, "
        f"estimate error {summary['final_estimate_error_median_m']} m, violations {viol}, "
        f"{summary['runtime_s']:.1f} s\nresults: {out}"
    )
    for f in summary["failures"]:
        print(f"failure: {f['process']} (drones {f['drones']}) at step {f['step']}, status {f['status']}: {f['reason']} -> {f['action']}", file=sys.stderr)
    if summary["failures"]:
        print(f"the mission completed with {len(summary['failures'])} failure(s): see {out / 'summary.json'}", file=sys.stderr)
        return 3
    return 0
