"""``fimnav handback MISSION --uav N``: give a taken-over drone back to its planner.

A planner whose vehicle leaves GUIDED (ArduPilot) or OFFBOARD (PX4) while it flies, because a
pilot, a ground station or a failsafe switched it, stops commanding it and never takes it back
on its own (docs/in-the-field.md). This command publishes ``{"command": "handback"}`` on the
drone's control key (``fimnav/<mission id>/control/<uav>``); the planner then switches the
vehicle back to GUIDED/OFFBOARD where it is and plans again from its next step.

The Zenoh network of a running ``fimnav launch`` is reached with ``--results DIR`` (the launch
writes its endpoint to ``DIR/logs/zenoh.json``); planners started by hand with
``--zenoh-connect`` or the mission's ``zenoh`` section.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from comms.errors import UsageError

#: How long the command waits for the planner's subscription to be matched (wall s): 5 s was
#: once too short with a real SITL at x5 and its planner loading the machine, right after the
#: planner had been restarted.
MATCH_TIMEOUT_S = 10.0


def register(subparsers: Any) -> None:
    """Add the ``handback`` subcommand."""
    p = subparsers.add_parser(
        "handback",
        help="give a drone taken over by a pilot back to its planner",
        description="Ask drone N's planner to take its vehicle back (GUIDED / OFFBOARD at its position) after a pilot or "
        "a ground station took it over. Reaches the planners of a fimnav launch with --results DIR.",
    )
    p.add_argument("mission", metavar="MISSION", help="mission file or shipped mission name (its id names the keys)")
    p.add_argument("--uav", type=int, required=True, help="drone id (1-based)")
    p.add_argument("--results", type=Path, help="results directory of a running fimnav launch (its Zenoh endpoint)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT", help="Zenoh endpoint to connect to (repeatable)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value")
    p.set_defaults(func=run)


def launch_endpoints(results: Path) -> list[str]:
    """The Zenoh endpoints of a running launch, from ``results/logs/zenoh.json``."""
    path = results / "logs" / "zenoh.json"
    try:
        data = json.loads(path.read_text())
    except OSError:
        raise UsageError(f"--results {results}: no {path.relative_to(results)} (is a fimnav launch running there?)") from None
    except ValueError as exc:
        raise UsageError(f"--results {results}: {path.name} is not JSON ({exc})") from None
    connect = data.get("connect") if isinstance(data, dict) else None
    if not (isinstance(connect, list) and connect and all(isinstance(e, str) for e in connect)):
        raise UsageError(f"--results {results}: {path.name} has no list of endpoints under 'connect'")
    return connect


def run(args: argparse.Namespace) -> int:
    """Publish the hand-back command; exit 0 once sent to a matched planner, 1 if none listens."""
    import dataclasses

    from comms import keys
    from comms.pubsub import declare_publisher
    from comms.session import SessionSettings, open_session
    from missions.format.loader import load_mission, parse_overrides

    mission = load_mission(args.mission, parse_overrides(args.overrides))
    if not 1 <= args.uav <= mission.drones.count:
        raise UsageError(f"--uav: expected a drone id in 1..{mission.drones.count}, found {args.uav}")
    settings = SessionSettings.from_mission(mission.zenoh)
    connect = list(args.zenoh_connect) + (launch_endpoints(args.results) if args.results else [])
    if connect:
        settings = dataclasses.replace(settings, mode="client", listen=(), connect=tuple(connect))
    session = open_session(settings)
    try:
        pub = declare_publisher(session, keys.control(mission.id, args.uav))
        deadline = time.monotonic() + MATCH_TIMEOUT_S
        matched = False
        while time.monotonic() < deadline:
            status = getattr(pub, "matching_status", None)
            if status is None or status.matching:
                matched = status is not None
                break
            time.sleep(0.05)  # polling the subscription match, with the deadline above
        pub.put(json.dumps({"command": "handback"}).encode())
        time.sleep(0.2)  # let the sample leave before the session closes
    finally:
        session.close()
    if not matched:
        print(
            f"fimnav handback: no planner of drone {args.uav} of mission {mission.id} answered on "
            f"{keys.control(mission.id, args.uav)} within {MATCH_TIMEOUT_S:g} s (sent anyway)"
        )
        return 1
    print(f"fimnav handback: asked drone {args.uav}'s planner to take its vehicle back")
    return 0
