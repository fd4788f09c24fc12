"""``fimnav payload``: the simulated RSS payload of one drone flown on an external autopilot.

fimnav's simulated vehicle carries the drone's simulated payload (vehicle_sim/payload.py); a
drone flown on ArduPilot or PX4 (SITL, or a real drone without an RSS receiver) has none. This
command is that payload on its own: it follows the autopilot's reported position over its own
MAVLink connection (a second link to the autopilot, e.g. SITL's SERIAL1, a MAVProxy or
mavlink-router output; not the planner's) and publishes the mission's simulated measurement
every Δt of mission time on ``fimnav/<mission id>/measurement/<uav>``, exactly as the simulated
vehicle's payload does: same noise draws (:class:`vehicle_sim.payload.Payload`), same
schedule, record and key (:meth:`vehicle_sim.bridge.ZenohBridge.start_realtime`). The position
is the autopilot's own estimate (GLOBAL_POSITION_INT converted to the mission frame), not a
simulator's truth. While the autopilot's position is older than 1 s (not ready yet, link lost)
nothing is published.

``fimnav launch --realtime`` starts one for every drone with ``vehicles.overrides[i].connection``
unless ``vehicles.overrides[i].payload`` is ``external`` (a real payload publishes).
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import threading
from pathlib import Path
from typing import Any

from comms.errors import UsageError

#: Our MAVLink component on the autopilot's system: MAV_COMP_ID_PERIPHERAL (the planner is 191).
PAYLOAD_COMPONENT = 158
#: A position older than this (wall s) is not measured at.
POSITION_MAX_AGE_S = 1.0

log = logging.getLogger("fimnav.payload")


def register(subparsers: Any) -> None:
    """Add the ``payload`` subcommand."""
    p = subparsers.add_parser(
        "payload",
        help="the simulated RSS payload of a drone flown on an external autopilot (follows it over MAVLink)",
        description="Follow an autopilot's reported position over MAVLink and publish the mission's simulated "
        "measurements of one drone on its Zenoh measurement key, every dt of mission time.",
    )
    p.add_argument("--mission", required=True, type=Path, metavar="MISSION.yaml")
    p.add_argument("--uav", required=True, type=int, help="drone id, 1..N")
    p.add_argument(
        "--mavlink",
        metavar="CONN",
        help="a MAVLink connection to the autopilot for the payload (default: the "
        "mission's vehicles.overrides[i].payload_connection), e.g. tcp:127.0.0.1:5762 (SITL SERIAL1)",
    )
    p.add_argument("--sysid", type=int, help="the autopilot's system id (default: the drone id)")
    p.add_argument("--speedup", type=float, default=1.0, help="mission seconds per wall second (default 1; the planners' --speedup)")
    p.add_argument("--signing-key", type=Path, metavar="FILE", help="MAVLink 2 signing key file, mode 0600 (default: the mission's)")
    p.add_argument("--zenoh-config", help="session settings as JSON (set by fimnav launch)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT", help="extra zenoh endpoint to connect to")
    p.add_argument("--connect-timeout", type=float, default=180.0, help="seconds to wait for the autopilot's first heartbeat (default 180)")
    p.add_argument("--duration", type=float, help="stop after this many wall seconds")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value (repeatable)")
    p.add_argument("--log-level", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.set_defaults(func=run)


class FollowedDrone:
    """What :class:`vehicle_sim.bridge.ZenohBridge` reads of a hosted vehicle (``sysid``,
    ``payload``, ``position``), for a drone whose position comes from its autopilot: the
    payload is offered only while that position is fresh (the bridge then skips the
    measurement, and the payload's noise stream stays aligned by step)."""

    def __init__(self, sysid: int, payload: Any, link: Any, max_age_s: float = POSITION_MAX_AGE_S) -> None:
        self.sysid = sysid
        self._payload = payload
        self._link = link
        self._max_age_s = max_age_s

    @property
    def payload(self) -> Any:
        t = self._link.telemetry
        if t.position_enu_m is None or self._link.wall() - t.position_wall_s > self._max_age_s:
            return None
        return self._payload

    @property
    def position(self) -> tuple[float, float, float]:
        p = self._link.telemetry.position_enu_m
        return (float(p[0]), float(p[1]), float(p[2]))


def build_payload(mission: Any, uav: int, world: Any = None) -> Any:
    """The simulated payload of drone ``uav`` (1-based) of ``mission``: its world (built from the
    mission unless given), its role's components (range, bearing and any other registered in
    :data:`planner.sensing.SENSING`) and its noise stream; ``fimnav vehicle --mission`` and
    ``fimnav payload`` build it here."""
    from missions.cli.process_args import payload_world
    from vehicle_sim.payload import Payload, role_extra_components, roles_to_flags

    role = mission.drones.roles[uav - 1]
    ranging, bearing = roles_to_flags(role)
    return Payload(
        payload_world(mission) if world is None else world,
        uav - 1,
        sysid=uav,
        ranging=ranging,
        bearing=bearing,
        extra_components=role_extra_components(role),
    )


def _check_options(args: argparse.Namespace, mission: Any) -> None:
    """Refuse a drone id out of the mission, or a non-positive speed-up, timeout or duration.

    Raises:
        UsageError: naming the option, what was expected and what was found.
    """
    n = mission.drones.count
    if not 1 <= args.uav <= n:
        raise UsageError(f"--uav: expected a drone id in 1..{n}, found {args.uav}")
    for name in ("speedup", "connect_timeout"):
        v = getattr(args, name)
        if not (math.isfinite(v) and v > 0):
            raise UsageError(f"--{name.replace('_', '-')}: expected a positive number, found {v}")
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration: expected a positive number of seconds, found {args.duration}")


def _open_link(args: argparse.Namespace, mission: Any, conn: str, sysid: int, key: bytes | None) -> Any:
    """The payload's own MAVLink link to the autopilot ``sysid`` at ``conn``: global frame
    (the autopilot's position converted to the mission frame), our own component id.

    Raises:
        UsageError: the connection cannot be opened.
    """
    from comms.geodesy import MissionFrame
    from comms.mavlink_client import LinkError, VehicleLink

    resolved = mission.vehicles.for_drone(args.uav - 1)
    try:
        return VehicleLink(
            conn,
            sysid,
            signing_key=key,
            frame="global",
            mission_frame=MissionFrame.of_mission(mission),
            altitude_reference=mission.altitude_reference,
            flavour=None if resolved.autopilot == "auto" else resolved.autopilot,
            connect_timeout_s=args.connect_timeout,
            source_component=PAYLOAD_COMPONENT,
        )
    except LinkError as exc:
        raise UsageError(str(exc)) from None


def _request_position(link: Any, sysid: int, conn: str, mission: Any, uav: int) -> None:
    """Ask the autopilot for GLOBAL_POSITION_INT at 10 Hz (on its first heartbeat, and again
    after a loss: the autopilot may have rebooted)."""
    from comms.mavlink_client import MSG_GLOBAL_POSITION_INT, LinkError

    try:
        for note in link.request_streams({MSG_GLOBAL_POSITION_INT: 10.0}):
            log.info("%s", note)
    except LinkError as exc:
        log.warning("position stream: %s", exc)
    log.info(
        "following system %d (autopilot %s) on %s; measurements on fimnav/%s/measurement/%d every %g s of mission time",
        sysid,
        link.flavour,
        conn,
        mission.id,
        uav,
        mission.dt_s,
    )


def _follow(link: Any, args: argparse.Namespace, mission: Any, conn: str, sysid: int, stop: threading.Event) -> int:
    """Pump the link until ``stop``: the position stream requested while the autopilot is
    heard, whether the position is fresh enough to measure at logged. Exit status: 0, or 1
    when no heartbeat came within ``--connect-timeout``."""
    deadline = link.wall() + args.connect_timeout
    streaming = following = False
    while not stop.is_set():
        link.pump(0.1)
        if link.telemetry.heartbeats == 0:
            if link.wall() > deadline:
                log.error("no heartbeat from system %d on %s within %g s", sysid, conn, args.connect_timeout)
                return 1
            continue
        if link.lost and streaming:
            streaming = False
            log.warning("autopilot link lost (no heartbeat for %.1f s): no measurements until it returns", link.link_age_s())
        if not streaming and not link.lost:
            _request_position(link, sysid, conn, mission, args.uav)
            streaming = True
        fresh = link.telemetry.position_enu_m is not None and link.wall() - link.telemetry.position_wall_s <= POSITION_MAX_AGE_S
        if fresh != following:
            following = fresh
            log.info("%s", "position fresh: measuring" if fresh else "no fresh position: not measuring")
    log.info("stopped")
    return 0


def run(args: argparse.Namespace) -> int:
    """Follow the autopilot and publish the measurements until SIGINT/SIGTERM or --duration."""
    from comms.mavlink_client import read_signing_key
    from missions.cli.process_args import setup_logging, zenoh_settings
    from missions.format.loader import load_mission, parse_overrides
    from missions.launch.forkspawn import watch_launcher
    from missions.runtime.signals import StopRequest, stop_on_signals

    setup_logging(args.log_level, f"payload[{args.uav}]")
    watch_launcher()  # started by fimnav launch: stop when the launcher dies
    mission = load_mission(args.mission, parse_overrides(args.overrides))
    _check_options(args, mission)
    resolved = mission.vehicles.for_drone(args.uav - 1)
    conn = args.mavlink or resolved.payload_connection
    if conn is None:
        raise UsageError(f"--mavlink: no connection given and the mission has no vehicles.overrides[{args.uav - 1}].payload_connection")
    key_file = args.signing_key or resolved.signing_key_file
    key = read_signing_key(key_file) if key_file is not None else None
    settings = zenoh_settings(mission, args.zenoh_config, args.zenoh_connect)

    stop = threading.Event()
    request = StopRequest(stop.set)
    with stop_on_signals(request):
        status = _serve(args, mission, conn, key, settings, stop)
    request.raise_if_stopped()
    return status


def _serve(args: argparse.Namespace, mission: Any, conn: str, key: bytes | None, settings: Any, stop: threading.Event) -> int:
    """Open the link and the Zenoh bridge, follow the autopilot until ``stop`` is set (or
    ``--duration`` ends), then close both."""
    from vehicle_sim.bridge import ZenohBridge

    if args.duration is not None:
        timer = threading.Timer(args.duration, stop.set)
        timer.daemon = True
        timer.start()
    sysid = args.sysid or args.uav
    link = _open_link(args, mission, conn, sysid, key)
    drone = FollowedDrone(args.uav, build_payload(mission, args.uav), link)
    bridge = ZenohBridge(mission.id, mission.drones.count, mission.dt_s, None, [drone], settings)
    try:
        ready = {
            "event": "ready",
            "pid": os.getpid(),
            "uav": args.uav,
            "mavlink": conn,
            "sysid": sysid,
            "key": f"fimnav/{mission.id}/measurement/{args.uav}",
            "clock": f"realtime x{args.speedup:g}",
        }
        print(json.dumps(ready), flush=True)
        bridge.start_realtime([drone], args.speedup)
        return _follow(link, args, mission, conn, sysid, stop)
    finally:
        bridge.close()
        link.close()
