"""``fimnav plan``: one planner node, to a simulated or an external autopilot."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path
from typing import Any

from planner.errors import UsageError


def register(subparsers: Any) -> None:
    """Add the ``plan`` subcommand."""
    p = subparsers.add_parser(
        "plan",
        help="run one drone's planner node (Zenoh to the swarm, MAVLink to its autopilot)",
        description="Fly one drone of a mission: share records over Zenoh, estimate the source, "
        "compute the A/D-optimal projected-gradient step and stream setpoints to the vehicle.",
    )
    p.add_argument("--mission", required=True, type=Path, metavar="MISSION.yaml")
    p.add_argument("--uav", required=True, type=int, help="drone id, 1..N")
    p.add_argument("--mavlink", required=True, metavar="CONN", help="pymavlink connection string to the vehicle")
    p.add_argument("--sysid", type=int, help="vehicle system id (default: the drone id)")
    p.add_argument("--steps", type=int, help="steps to fly (default: the mission's)")
    p.add_argument("--lockstep", action="store_true", help="step on the lockstep clock (simulation)")
    p.add_argument("--zenoh-config", help="session settings as JSON (set by fimnav launch)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT", help="extra zenoh endpoint to connect to")
    p.add_argument("--log", type=Path, help="JSON-lines step log")
    p.add_argument("--step-timeout", type=float, default=30.0, help="seconds to wait for a tick, a measurement or peers (default 30)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value (repeatable)")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Load the mission and fly the node; print a JSON summary on stdout."""
    from comms.session import SessionSettings
    from missions.loader import load_mission, parse_overrides
    from planner.node import NodeOptions, PlannerNode

    logging.basicConfig(level=args.log_level, stream=sys.stderr, format=f"plan[{args.uav}] %(levelname)s %(message)s")
    mission = load_mission(args.mission, parse_overrides(args.overrides))
    if args.steps is not None and args.steps < 1:
        raise UsageError(f"--steps: expected a positive integer, found {args.steps}")
    if args.zenoh_config:
        try:
            settings = SessionSettings.from_json(json.loads(args.zenoh_config))
        except (ValueError, TypeError, AttributeError) as exc:
            raise UsageError(f"--zenoh-config: expected the JSON written by fimnav launch ({exc})") from None
    else:
        settings = SessionSettings.from_mission(mission.zenoh)
    if args.zenoh_connect:
        settings = SessionSettings(**{**settings.__dict__, "connect": settings.connect + tuple(args.zenoh_connect)})
    options = NodeOptions(
        uav=args.uav, mavlink=args.mavlink, zenoh=settings, lockstep=args.lockstep, steps=args.steps,
        sysid=args.sysid, log_path=args.log, step_timeout_s=args.step_timeout,
    )
    summary = PlannerNode(mission, options).run()
    print(json.dumps(summary), flush=True)
    return 0
