"""``fimnav plan``: one planner node, to a simulated or an external autopilot."""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
from pathlib import Path
from typing import Any

from comms.autopilot import flavour_names
from comms.errors import UsageError


def register(subparsers: Any) -> None:
    """Add the ``plan`` subcommand."""
    p = subparsers.add_parser(
        "plan",
        help="run one drone's planner node (Zenoh to the swarm, MAVLink to its autopilot)",
        description="Fly one drone of a mission: share records over Zenoh, estimate the source, "
        "compute the A/D-optimal projected-gradient step and stream setpoints to the vehicle.",
    )
    p.add_argument("--mission", required=True, type=Path, metavar="MISSION", help="a mission file, or the name of a shipped mission")
    p.add_argument("--uav", required=True, type=int, help="drone id, 1..N")
    p.add_argument(
        "--mavlink",
        metavar="CONN",
        help="pymavlink connection string to the vehicle (udpout:HOST:PORT, "
        "udpin:, tcp:, /dev/ttyUSB0,57600; default: the mission's vehicles.overrides[i].connection)",
    )
    p.add_argument("--sysid", type=int, help="vehicle system id (default: the drone id)")
    p.add_argument("--steps", type=int, help="steps to fly (default: the mission's)")
    p.add_argument("--lockstep", action="store_true", help="step on the lockstep clock (simulation)")
    p.add_argument("--zenoh-config", help="session settings as JSON (set by fimnav launch)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT", help="extra zenoh endpoint to connect to")
    p.add_argument("--log", type=Path, help="JSON-lines step log")
    p.add_argument(
        "--rejoin",
        action="store_true",
        help="take over a vehicle in flight from a planner that died (no take-off, no flight to the start; lockstep: fly from "
        "the clock's next step; real time, with --start-at: from the grid's current step; append to --log)",
    )
    p.add_argument(
        "--taken-over",
        action="store_true",
        help="start with the drone taken over, whatever its mode: command nothing until fimnav handback "
        "(fimnav launch restarts a planner so while a pilot flies its drone)",
    )
    p.add_argument("--step-timeout", type=float, default=30.0, help="seconds to wait for a tick, a measurement or peers (default 30)")
    p.add_argument(
        "--preflight-timeout", type=float, default=120.0, help="seconds the readiness wait, take-off and flight to the start may take (default 120)"
    )
    rt = p.add_argument_group("real time (external autopilots; without --lockstep)")
    rt.add_argument(
        "--speedup",
        type=float,
        default=1.0,
        help="mission seconds per wall second: 1 for a real vehicle, the --speedup of a simulated vehicle (default 1)",
    )
    rt.add_argument(
        "--flavour", choices=("auto", *flavour_names()), help="autopilot (default: the mission's override, else auto = from HEARTBEAT.autopilot)"
    )
    rt.add_argument(
        "--setpoint-frame",
        choices=("auto", "global", "local_ned"),
        help="setpoint frame (default: the mission's vehicles.setpoint_frame; auto = global in real time)",
    )
    rt.add_argument(
        "--signing-key",
        type=Path,
        metavar="FILE",
        help="MAVLink 2 signing key file, mode 0600 (default: the mission's vehicles.overrides[i].signing_key_file)",
    )
    rt.add_argument(
        "--start-at", type=float, metavar="UNIX_S", help="UNIX time of step 0 (default: the next multiple of dt/speedup once at the start position)"
    )
    rt.add_argument("--stream-hz", type=float, default=5.0, help="setpoint stream rate, mission-time Hz, >= 4 (default 5)")
    rt.add_argument(
        "--tlog",
        type=Path,
        metavar="PATH",
        help="write the vehicle link to this .tlog (every MAVLink frame in and out; fimnav launch gives one to every drone it does not simulate)",
    )
    rt.add_argument(
        "--measurement-max-age", type=float, metavar="S", help="newest payload measurement used if at most this old, mission seconds (default dt)"
    )
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value (repeatable)")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Load the mission and fly the node; print a JSON summary on stdout."""
    from comms.mavlink_client import read_signing_key
    from missions.cli.process_args import setup_logging, zenoh_settings
    from missions.format.loader import load_mission, parse_overrides
    from missions.launch.forkspawn import watch_launcher
    from missions.runtime.signals import signals_deferred
    from planner.node import NodeOptions, PlannerNode
    from planner.warm import available_cores, compile_aside, compile_notice, missing_groups

    setup_logging(args.log_level, f"plan[{args.uav}]")
    watch_launcher()  # started by fimnav launch: stop when the launcher dies
    logging.getLogger("fimnav.plan").info("pid %d, fimnav code from %s", os.getpid(), Path(__file__).resolve().parents[1])
    mission = load_mission(args.mission, parse_overrides(args.overrides))
    if args.steps is not None and args.steps < 1:
        raise UsageError(f"--steps: expected a positive integer, found {args.steps}")
    settings = zenoh_settings(mission, args.zenoh_config, args.zenoh_connect)
    n = mission.drones.count
    if not 1 <= args.uav <= n:
        raise UsageError(f"--uav: expected a drone id in 1..{n}, found {args.uav}")
    conn = args.mavlink or mission.vehicles.for_drone(args.uav - 1).connection
    if conn is None:
        raise UsageError(f"--mavlink: no connection given and the mission has no vehicles.overrides[{args.uav - 1}].connection")
    for name in ("speedup", "step_timeout", "preflight_timeout", "stream_hz"):
        v = getattr(args, name)
        if not (math.isfinite(v) and v > 0):
            raise UsageError(f"--{name.replace('_', '-')}: expected a positive number, found {v}")
    if args.stream_hz < 4:
        raise UsageError(f"--stream-hz: expected at least 4 Hz, found {args.stream_hz:g}")
    if args.rejoin and not args.lockstep and args.start_at is None:
        raise UsageError("--rejoin: in real time only with --start-at (it rejoins the mission's step grid at the current step)")
    if args.signing_key is not None:
        read_signing_key(args.signing_key)  # permissions and format, before anything starts
    options = NodeOptions(
        uav=args.uav,
        mavlink=conn,
        zenoh=settings,
        lockstep=args.lockstep,
        steps=args.steps,
        sysid=args.sysid,
        log_path=args.log,
        step_timeout_s=args.step_timeout,
        preflight_timeout_s=args.preflight_timeout,
        speedup=args.speedup,
        flavour=args.flavour,
        setpoint_frame=args.setpoint_frame,
        signing_key_file=args.signing_key,
        stream_hz=args.stream_hz,
        measurement_max_age_s=args.measurement_max_age,
        start_at_unix=args.start_at,
        rejoin=args.rejoin,
        tlog_path=args.tlog,
    )
    # The compiled kernels load (from numba's cache, or compiled once after an install) before
    # the node starts, with Ctrl-C, SIGTERM and SIGHUP held back: a signal in the middle of
    # numba's compiler would be raised inside its LLVM callback (a traceback, the load cut
    # short). A signal that came meanwhile stops the command as soon as they are in. (Started
    # by `fimnav launch`, the fork server has loaded them already.)
    # On a cold cache the two kernel groups are first compiled in child processes, at once, a
    # wait that a signal may end (the children are killed).
    missing = missing_groups()
    if missing:
        print(f"fimnav plan: {compile_notice(missing)}", file=sys.stderr, flush=True)
    compile_aside(available_cores())
    with signals_deferred():
        import planner.node.warm
        import planner.node.warm_estimator  # noqa: F401
    summary = PlannerNode(mission, options, taken_over=args.taken_over).run()
    print(json.dumps(summary), flush=True)
    return 0
