"""``fimnav vehicle``: run one (or several) simulated MAVLink vehicles.

Examples::

    fimnav vehicle --sysid 1 --mavlink tcpin:127.0.0.1:5760
    fimnav vehicle --mission missions/paper/ranging_los.yaml --sysid 3 --mavlink udpout:127.0.0.1:14550
    fimnav vehicle --mission M.yaml --count 10 --mavlink udpin:127.0.0.1:14600 --lockstep

With ``--count N`` the process hosts N vehicles, system ids I..I+N-1 on ports
PORT, PORT+stride, ... (``--mavlink`` given once), or one ``--mavlink`` per vehicle.
Once every socket is open the command prints one JSON line
``{"event": "ready", "pid": PID, "code": DIR, "vehicles": [{"sysid": 1, "mavlink": "udpin:127.0.0.1:PORT"}], ...}``
to stdout (the actual ports when PORT 0 was asked; ``code``: the directory of the ``missions``
package it runs), then runs until SIGINT/SIGTERM (exit 0), ``--duration``, or, started by
``fimnav launch``, the launcher's death (:func:`missions.launch.forkspawn.watch_launcher`).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import threading
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from comms.autopilot import flavour_names
from comms.errors import UsageError


def register(subparsers: Any) -> None:
    """Add the ``vehicle`` subcommand to the ``fimnav`` parser."""
    p = subparsers.add_parser(
        "vehicle",
        help="run simulated MAVLink vehicles (ArduPilot copter or PX4 flavour)",
        description="Run one or several simulated MAVLink vehicles that ground stations accept.",
    )
    p.add_argument("--sysid", type=int, default=1, help="MAVLink system id of the (first) vehicle (default 1)")
    p.add_argument(
        "--mavlink",
        action="append",
        default=[],
        metavar="CONN",
        help="connection: udpin:|udpout:|tcpin:|tcp:HOST:PORT (repeat once per vehicle; default tcpin:127.0.0.1:5760+10*(sysid-1), as SITL)",
    )
    p.add_argument("--count", type=int, default=1, help="number of vehicles hosted by this process (default 1)")
    p.add_argument("--port-stride", type=int, default=1, help="port increment between vehicles (default 1)")
    p.add_argument("--mission", metavar="MISSION.yaml", help="take origin, start, fence, world and seed from a mission")
    p.add_argument("--flavour", choices=flavour_names(), help="autopilot flavour (default ardupilot)")
    p.add_argument("--profile", choices=("ideal", "pointmass"), help="dynamics (default: mission's, else pointmass)")
    p.add_argument("--start", metavar="X,Y,Z", help="start position, ENU m (default 0,0,0 or the mission's)")
    p.add_argument("--spacing", type=float, default=2.0, help="east spacing of extra vehicles without a mission (m)")
    p.add_argument("--airborne", action="store_true", help="boot armed and hovering at the start position")
    p.add_argument("--origin", metavar="LAT,LON,ALT", help="mission frame origin (deg, deg, m AMSL)")
    p.add_argument("--speed-max", type=float, help="maximum horizontal speed (m/s, default 10)")
    p.add_argument("--accel-max", type=float, help="maximum acceleration (m/s^2, default 5)")
    p.add_argument("--guided-timeout", type=float, default=3.0, help="GUIDED velocity timeout (s, default 3)")
    p.add_argument("--physics-hz", type=float, default=50.0, help="physics rate (Hz, default 50)")
    p.add_argument(
        "--ready-after",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="sim seconds from boot until GPS fix, EKF position, home and EKF origin (a real copter's "
        "start-up; arming is refused until then; default 0: ready at boot; real-time clock only)",
    )
    p.add_argument(
        "--ekf-status-hz",
        type=float,
        default=2.0,
        help="EKF_STATUS_REPORT rate, ArduPilot flavour (Hz of sim time, default 2 as ArduPilot's EXTRA3; 0: on request)",
    )
    p.add_argument("--lag", type=float, default=0.0, help="first-order velocity lag (s, pointmass)")
    p.add_argument("--wind", metavar="WX,WY,WZ", help="constant wind, ENU m/s (pointmass)")
    p.add_argument("--noise", type=float, default=0.0, help="reported position noise std (m)")
    p.add_argument("--seed", type=int, help="sensor-noise seed (default: the mission's, else 0)")
    p.add_argument("--fence-z", metavar="ZMIN,ZMAX", help="fence altitude box (ENU m)")
    p.add_argument("--fence-box", metavar="XMIN,XMAX,YMIN,YMAX", help="fence horizontal box (ENU m)")
    p.add_argument("--fence-radius", type=float, help="fence radius about home (m)")
    p.add_argument("--fence-action", choices=("clamp", "reject"), default="clamp", help="outside targets (default clamp)")
    p.add_argument("--no-fence", action="store_true", help="disable the geofence")
    p.add_argument(
        "--param",
        action="append",
        default=[],
        metavar="NAME=VALUE",
        help="set a parameter at boot, in the flavour's names and units (repeatable), e.g. FS_GCS_ENABLE=1 or COM_OBL_RC_ACT=4",
    )
    p.add_argument("--signing-key", metavar="FILE", help="MAVLink 2 signing key file (32 bytes or 64 hex digits)")
    p.add_argument("--tlog", metavar="PATH", help="write a .tlog; '{sysid}' in PATH is replaced per vehicle")
    clock = p.add_mutually_exclusive_group()
    clock.add_argument("--speedup", type=float, default=1.0, help="real-time speed-up factor (default 1)")
    clock.add_argument("--lockstep", action="store_true", help="advance only on zenoh clock ticks")
    p.add_argument("--mission-id", help="mission id of the zenoh tick key (default: the mission's)")
    p.add_argument("--zenoh-listen", action="append", default=[], metavar="ENDPOINT", help="zenoh listen endpoint")
    p.add_argument("--zenoh-mode", choices=("peer", "client", "router"), help="zenoh session mode (default: the mission's)")
    p.add_argument("--zenoh-connect", action="append", default=[], metavar="ENDPOINT", help="zenoh endpoint to connect")
    p.add_argument("--duration", type=float, help="stop after this many wall seconds")
    p.add_argument("--log-level", default="WARNING", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.set_defaults(func=run_vehicle)


def _floats(text: str | None, n: int, option: str) -> tuple[float, ...] | None:
    if text is None:
        return None
    parts = text.split(",")
    try:
        values = tuple(float(x) for x in parts)
    except ValueError:
        raise UsageError(f"{option}: expected {n} comma-separated numbers, found {text!r}") from None
    if len(values) != n or not all(math.isfinite(v) for v in values):
        raise UsageError(f"{option}: expected {n} comma-separated finite numbers, found {text!r}")
    return values


def _xyz(text: str | None, option: str) -> tuple[float, float, float] | None:
    """An x,y,z option (``--start``, ``--wind``): three comma-separated finite numbers, or None."""
    from planner.geometry import vec3

    values = _floats(text, 3, option)
    return None if values is None else vec3(values)


def _params(items: Sequence[str]) -> tuple[tuple[str, float], ...]:
    """``--param NAME=VALUE`` options -> (name, value) pairs (names checked by the vehicle)."""
    out: list[tuple[str, float]] = []
    for item in items:
        name, sep, text = item.partition("=")
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not sep or not name.strip() or not math.isfinite(value):
            raise UsageError(f"--param: expected NAME=VALUE with a finite number, found {item!r}")
        out.append((name.strip().upper(), value))
    return tuple(out)


def _connection_for(args: argparse.Namespace, i: int, sysid: int) -> str:
    from vehicle_sim.link import parse_connection

    if len(args.mavlink) == args.count:
        conn = args.mavlink[i]
        parse_connection(conn)
        return str(conn)
    if len(args.mavlink) > 1:
        raise UsageError(f"--mavlink: give it once or {args.count} times (--count), found {len(args.mavlink)}")
    if not args.mavlink:
        return f"tcpin:127.0.0.1:{5760 + 10 * (sysid - 1)}"
    kind, host, port = parse_connection(args.mavlink[0])
    if port == 0:
        return f"{kind}:{host}:0"
    port += i * args.port_stride
    if port > 65535:
        raise UsageError(f"--mavlink: port {port} of vehicle {i + 1} is above 65535")
    return f"{kind}:{host}:{port}"


def _check_options(args: argparse.Namespace) -> None:
    """Refuse vehicle options out of range (system ids, rates, the ready delay).

    Raises:
        UsageError: naming the option, what was expected and what was found.
    """
    if args.count < 1:
        raise UsageError(f"--count: expected >= 1, found {args.count}")
    if not 1 <= args.sysid <= 255 or args.sysid + args.count - 1 > 255:
        raise UsageError(f"--sysid/--count: system ids must lie in 1..255, found {args.sysid}..{args.sysid + args.count - 1}")
    for name in ("speedup", "physics_hz", "guided_timeout"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value > 0):
            raise UsageError(f"--{name.replace('_', '-')}: expected a positive number, found {value}")
    for name in ("ready_after", "ekf_status_hz"):
        value = getattr(args, name)
        if not (math.isfinite(value) and value >= 0):
            raise UsageError(f"--{name.replace('_', '-')}: expected a number >= 0, found {value}")
    if args.ready_after > 0 and args.lockstep:
        raise UsageError("--ready-after: needs the real-time clock (in lockstep, sim time only advances once the planners fly)")
    if args.ready_after > 0 and args.airborne:
        raise UsageError("--ready-after: a vehicle booting --airborne is ready at boot")


def _fleet_settings(args: argparse.Namespace, mission: Any | None) -> tuple[tuple[float, float, float] | None, dict[str, Any]]:
    """(``--start`` or None, the :class:`VehicleConfig` fields every hosted vehicle shares): the
    options, with the mission's origin and geofence (altitude limits, fence box) where the
    options do not set them.

    Raises:
        UsageError: a malformed option, or an origin, limit or geofence the vehicle refuses.
    """
    from vehicle_sim.config import Geofence, Origin, VehicleLimits

    boot_params = _params(args.param)
    start = _xyz(args.start, "--start")
    wind = _xyz(args.wind, "--wind") or (0.0, 0.0, 0.0)
    fence_z = _floats(args.fence_z, 2, "--fence-z")
    fence_box = _floats(args.fence_box, 4, "--fence-box")
    origin_v = _floats(args.origin, 3, "--origin")
    try:
        if origin_v is not None:
            origin = Origin(*origin_v)
        elif mission is not None:
            origin = mission.origin.to_origin()
        else:
            origin = Origin()
        limits = VehicleLimits()
        if args.speed_max is not None:
            limits = VehicleLimits(speed_max_h_mps=args.speed_max, accel_max_mps2=limits.accel_max_mps2)
        if args.accel_max is not None:
            limits = VehicleLimits(speed_max_h_mps=limits.speed_max_h_mps, accel_max_mps2=args.accel_max)
        fence_kw: dict[str, Any] = {}
        if mission is not None:
            c, f = mission.constraints, mission.fence
            fence_kw = {
                "z_min_m": c.z_min_m,
                "z_max_m": c.z_max_m,
                "x_min_m": f.x_min_m,
                "x_max_m": f.x_max_m,
                "y_min_m": f.y_min_m,
                "y_max_m": f.y_max_m,
            }
        if fence_z is not None:
            fence_kw.update(z_min_m=fence_z[0], z_max_m=fence_z[1])
        if fence_box is not None:
            fence_kw.update(x_min_m=fence_box[0], x_max_m=fence_box[1], y_min_m=fence_box[2], y_max_m=fence_box[3])
        if args.fence_radius is not None:
            fence_kw.update(radius_m=args.fence_radius)
        fence = Geofence(**fence_kw, enabled=not args.no_fence, action=args.fence_action)
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    shared = {
        "airborne": args.airborne,
        "ground_z_m": 0.0,
        "origin": origin,
        "limits": limits,
        "geofence": fence,
        "guided_timeout_s": args.guided_timeout,
        "physics_hz": args.physics_hz,
        "lag_s": args.lag,
        "wind_enu_mps": wind,
        "position_noise_m": args.noise,
        "ready_after_s": args.ready_after,
        "ekf_status_hz": args.ekf_status_hz,
        "params": boot_params,
    }
    return start, shared


def _tlog_of(args: argparse.Namespace, sysid: int) -> str | None:
    """The .tlog path of vehicle ``sysid`` (``--tlog`` with ``{sysid}`` replaced), or None.

    Raises:
        UsageError: several vehicles and a path without ``{sysid}``.
    """
    tlog = args.tlog.replace("{sysid}", str(sysid)) if args.tlog else None
    if tlog is not None and args.count > 1 and "{sysid}" not in args.tlog:
        raise UsageError("--tlog: with --count > 1 the path must contain '{sysid}'")
    return str(tlog) if tlog is not None else None


def build_configs(args: argparse.Namespace, mission: Any | None) -> list[tuple[Any, Any]]:
    """(VehicleConfig, Payload | None) of every hosted vehicle from the options (and mission).

    Drone ``i`` (0-based) of the mission has system id ``i + 1``; its vehicle is the mission's
    (:meth:`missions.format.schema.Mission.vehicle_config`) with the options' settings, its payload
    the mission's simulated payload.
    """
    from missions.cli.payload import build_payload
    from missions.cli.process_args import payload_world
    from vehicle_sim.config import VehicleConfig

    _check_options(args)
    start, shared = _fleet_settings(args, mission)
    world = None
    if mission is not None:
        n = mission.drones.count
        last = args.sysid + args.count - 1
        if last > n:
            raise UsageError(f"--sysid/--count: the mission has {n} drones (system ids 1..{n}), asked up to {last}")
        world = payload_world(mission)
    out: list[tuple[Any, Any]] = []
    for i in range(args.count):
        sysid = args.sysid + i
        drone = sysid - 1
        payload = None
        if mission is not None and world is not None:
            payload = build_payload(mission, sysid, world)
        tlog = _tlog_of(args, sysid)
        try:
            if mission is not None:
                given = {
                    "start_enu_m": start,
                    "flavour": args.flavour,
                    "profile": args.profile,
                    "signing_key_path": args.signing_key,
                    "seed": args.seed,
                }
                options = {name: value for name, value in given.items() if value is not None}
                cfg = mission.vehicle_config(drone, **shared, **options, tlog_path=tlog)
            else:
                base = start or (0.0, 0.0, 0.0)
                cfg = VehicleConfig(
                    sysid=sysid,
                    flavour=args.flavour or "ardupilot",
                    start_enu_m=(base[0] + i * args.spacing, base[1], base[2]),
                    profile=args.profile or "pointmass",
                    seed=0 if args.seed is None else args.seed,
                    signing_key_path=args.signing_key,
                    tlog_path=tlog,
                    **shared,
                )
        except ValueError as exc:
            raise UsageError(f"vehicle {sysid}: {exc}") from None
        out.append((cfg, payload))
    return out


def _build_vehicles(args: argparse.Namespace, configs: list[tuple[Any, Any]], vehicles: list[Any]) -> None:
    """Build every configured vehicle on its MAVLink connection, appended to ``vehicles`` as it
    is built (those already built are closed by the caller if a later one fails).

    Raises:
        UsageError: a connection option or a ``--param`` the vehicle refuses.
    """
    from vehicle_sim.host import build_vehicle

    for i, (cfg, payload) in enumerate(configs):
        conn = _connection_for(args, i, cfg.sysid)
        try:
            vehicles.append(build_vehicle(cfg, conn, payload=payload))
        except ValueError as exc:  # a --param the vehicle refuses
            raise UsageError(f"vehicle {cfg.sysid}: {exc}") from None


def _lockstep_source(args: argparse.Namespace, mission: Any | None, vehicles: list[Any]) -> tuple[Any, Any, Any, dict[str, Any]]:
    """Lockstep: (clock, tick source, its per-tick hook or None, what the ready line says of
    Zenoh). A mission run gets fimnav's clock protocol and the payload topics; without a
    mission, ticks only.

    Raises:
        UsageError: no mission id, or the Zenoh session cannot be opened.
    """
    from comms import keys
    from comms.session import SessionSettings
    from vehicle_sim.clock import TickQueue, ZenohTickSource

    mission_id = args.mission_id or (mission.id if mission is not None else None)
    if not mission_id:
        raise UsageError("--lockstep needs --mission or --mission-id (the tick key is fimnav/<id>/clock/tick)")
    clock = TickQueue()
    listen = args.zenoh_listen or ["tcp/127.0.0.1:0"]
    on_tick = None
    try:
        if mission is not None:
            # A mission run: fimnav's clock protocol and the payload topics.
            from vehicle_sim.bridge import ZenohBridge

            source: Any = ZenohBridge(mission.id, mission.drones.count, mission.dt_s, clock, vehicles, _bridge_settings(args, mission, listen))
            on_tick = source.on_tick
        else:
            source = ZenohTickSource(mission_id, clock, SessionSettings(listen=tuple(listen), connect=tuple(args.zenoh_connect or ())))
    except ValueError as exc:  # a mission id a key expression cannot hold
        raise UsageError(f"--mission-id: {exc}") from None
    except Exception as exc:  # zenoh raises its own error type for bad endpoints
        raise UsageError(f"zenoh: cannot open the session ({exc})") from None
    return clock, source, on_tick, {"tick_key": keys.tick(mission_id), "listen": listen, "connect": args.zenoh_connect}


def _realtime_bridge(args: argparse.Namespace, mission: Any, vehicles: list[Any]) -> tuple[Any, dict[str, Any]]:
    """Real time with Zenoh: the bridge through which the payloads publish their measurements
    (fimnav launch --realtime; presence tokens as in lockstep), not started yet, and what the
    ready line says of Zenoh.

    Raises:
        UsageError: the Zenoh session cannot be opened.
    """
    from vehicle_sim.bridge import ZenohBridge

    listen = args.zenoh_listen or ["tcp/127.0.0.1:0"]
    try:
        source = ZenohBridge(mission.id, mission.drones.count, mission.dt_s, None, vehicles, _bridge_settings(args, mission, listen))
    except Exception as exc:  # zenoh raises its own error type for bad endpoints
        raise UsageError(f"zenoh: cannot open the session ({exc})") from None
    return source, {"listen": listen, "connect": args.zenoh_connect, "payload": "realtime"}


def _serve(host: Any, duration_s: float | None) -> None:
    """Run the host until a stop signal or ``duration_s`` wall seconds; the vehicles stop
    cleanly either way (links closed, tlogs flushed).

    Raises:
        Interrupted: a signal stopped them (exit 128 + signal, :mod:`missions.runtime.signals`).
    """
    from missions.runtime.signals import StopRequest, stop_on_signals

    stop = StopRequest(host.stop)
    with stop_on_signals(stop):
        timer = threading.Timer(duration_s, host.stop) if duration_s is not None else None
        if timer is not None:
            timer.daemon = True
            timer.start()
        host.run()
        if timer is not None:
            timer.cancel()
    stop.raise_if_stopped()


def run_vehicle(args: argparse.Namespace) -> int:
    """Run the vehicles until a stop signal (exit 128 + signal) or ``--duration`` (exit 0)."""
    from missions.cli.process_args import setup_logging
    from missions.launch.forkspawn import watch_launcher

    setup_logging(args.log_level, "%(name)s")
    watch_launcher()  # started by fimnav launch: stop when the launcher dies
    mission = None
    if args.mission:
        from missions.format.loader import load_mission

        mission = load_mission(args.mission)
    configs = build_configs(args, mission)
    if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
        raise UsageError(f"--duration: expected a positive number of seconds, found {args.duration}")

    from vehicle_sim.clock import RealTimeClock
    from vehicle_sim.host import VehicleHost

    vehicles: list[Any] = []
    source: Any = None
    on_tick = None
    try:
        _build_vehicles(args, configs, vehicles)
        clock: Any
        zenoh_info: dict[str, Any] = {}
        if args.lockstep:
            clock, source, on_tick, zenoh_info = _lockstep_source(args, mission, vehicles)
        else:
            clock = RealTimeClock(args.speedup)
            if mission is not None and (args.zenoh_connect or args.zenoh_listen):
                source, zenoh_info = _realtime_bridge(args, mission, vehicles)
                source.start_realtime(vehicles, args.speedup)
        host = VehicleHost(vehicles, clock, on_tick=on_tick)
        ready = {
            "event": "ready",
            "pid": os.getpid(),
            "code": str(Path(__file__).resolve().parents[1]),
            "vehicles": [{"sysid": v.sysid, "mavlink": v.link.transport.address} for v in vehicles],
            "clock": "lockstep" if args.lockstep else f"realtime x{args.speedup:g}",
            **zenoh_info,
        }
        print(json.dumps(ready), flush=True)
        _serve(host, args.duration)
    finally:
        if source is not None:
            source.close()
        for v in vehicles:
            v.link.close()
    return 0


def _bridge_settings(args: argparse.Namespace, mission: Any, listen: Sequence[str]) -> Any:
    """The Zenoh session of a mission's vehicle bridge: the mission's settings with the CLI's
    endpoints; ``--zenoh-mode client`` makes it a client of the given router(s) only (fimnav
    launch: the launcher's)."""
    from comms.session import SessionSettings

    settings = SessionSettings.from_mission(mission.zenoh, connect=args.zenoh_connect, listen=listen)
    if args.zenoh_mode == "client":
        return dataclasses.replace(settings, mode="client", listen=(), connect=tuple(args.zenoh_connect))
    if args.zenoh_mode:
        return dataclasses.replace(settings, mode=args.zenoh_mode)
    return settings
