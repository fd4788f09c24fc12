"""A scripted ground station for the differential check of fimnav's simulated vehicle against
ArduPilot SITL (copter).

:func:`run_sequence` flies one fixed sequence against any ArduPilot-flavoured MAVLink vehicle
reachable at a ``tcp:127.0.0.1:PORT`` address and returns what a ground station observes as a
JSON-able transcript (summaries, not every message): heartbeat and flavour, stream requests
and the rates they give, the readiness wait, mode changes, arming, take-off, global and local
setpoints and where the vehicle went, refused commands (ACK results and STATUSTEXTs), LAND and
the disarm on landing. Every time in the transcript is **sim time** (the vehicle's
``time_boot_ms``), so transcripts taken at different speed-ups compare.

:func:`compare` lists the differences between two transcripts on the points where fimnav's
vehicle must answer as ArduPilot does (``tests/vehicle_sim/test_vehicle_vs_ardupilot.py`` and
``tests/sitl/test_sitl_transcript.py`` use it). Run as a script to record a transcript::

    python -m tests.sitl.gcs_script --connect tcp:127.0.0.1:5760 --speedup 10 --out t.json
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink import mavutil

mavlink = mavutil.mavlink

SCHEMA = 1
GCS_SYSID = 255
GCS_COMPID = 190
#: ArduPilot copter mode numbers used by the sequence.
STABILIZE, GUIDED, LAND = 0, 4, 9
UNKNOWN_MODE = 99
#: An id no autopilot implements (MAV_CMD_USER_1).
UNSUPPORTED_CMD = 31010
#: REQUEST_DATA_STREAM as MAVProxy sends it by default: every stream at 4 Hz.
DATA_STREAM_ALL_HZ = 4
#: SET_MESSAGE_INTERVAL requests (message id -> Hz), those fimnav's planner sends
#: (planner/node/realtime_preflight.py ``RealtimePreflight.request_streams``) plus LOCAL_POSITION_NED.
PLANNER_INTERVALS_HZ: dict[int, float] = {33: 10.0, 32: 10.0, 1: 1.0, 24: 1.0, 242: 0.5, 245: 1.0, 193: 1.0}
#: SET_POSITION_TARGET type masks: position only (ignore velocity, acceleration, yaw, yaw rate).
MASK_POSITION = 3576
TAKEOFF_ALT_M = 10.0
#: Setpoints: (name, frame, target) — LOCAL_NED targets as (N, E, D) m about the EKF origin;
#: global ones as (north m, east m, altitude m) from home, the altitude in the frame's meaning.
SETPOINTS: tuple[tuple[str, str, tuple[float, float, float]], ...] = (
    ("global_relative_alt", "GLOBAL_RELATIVE_ALT_INT", (20.0, 10.0, 15.0)),
    ("local_ned", "LOCAL_NED", (-10.0, 15.0, -12.0)),
    ("global_amsl", "GLOBAL_INT", (0.0, 0.0, 8.0)),
)
#: Arrival: within this distance (m) of the target, and slower than ARRIVED_SPEED_MPS.
ARRIVED_M = 0.5
ARRIVED_SPEED_MPS = 0.3
#: Readiness: the planner's own rule (comms.mavlink_client.EKF_READY_FLAGS).
EKF_READY_FLAGS = 1 | 2 | 4 | 16 | 32
EKF_CONST_POS_MODE = 128
SENSOR_GPS = 0x20
SENSOR_AHRS = 0x200000
SENSOR_PREARM = 0x10000000
#: Message types the planner reads; their rates are compared.
PLANNER_TYPES = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "SYS_STATUS", "GPS_RAW_INT", "HOME_POSITION",
                 "EXTENDED_SYS_STATE", "EKF_STATUS_REPORT")


class SequenceError(RuntimeError):
    """The vehicle did not do what the sequence waits for within its deadline."""


@dataclass
class Observer:
    """The GCS link: reads messages, tracks sim time and what the sequence needs.

    Attributes:
        conn: the pymavlink connection. speedup: the vehicle's sim/wall speed (deadlines).
        target: the vehicle's system id (from its first heartbeat).
    """

    conn: Any
    speedup: float
    target: int = 0
    t_boot_s: float | None = None
    t_boot_wall: float = 0.0
    wall0: float = field(default_factory=time.monotonic)
    last_hb_sent: float = -math.inf
    last: dict[str, Any] = field(default_factory=dict)
    counts: Counter[str] = field(default_factory=Counter)
    texts: list[tuple[float, int, str]] = field(default_factory=list)
    acks: list[tuple[float, int, int]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    first_seen: dict[str, float] = field(default_factory=dict)
    track: bool = False

    def sim_now(self) -> float:
        """The vehicle's sim time (s): the newest ``time_boot_ms`` extrapolated by the speed-up."""
        now = time.monotonic()
        if self.t_boot_s is None:
            return (now - self.wall0) * self.speedup
        return self.t_boot_s + (now - self.t_boot_wall) * self.speedup

    def _event(self, kind: str, **values: Any) -> None:
        self.events.append({"t_s": round(self.sim_now(), 2), "event": kind, **values})

    def pump(self, timeout_wall: float = 0.05) -> Any:
        """Send the GCS heartbeat when due (1 Hz wall), read one message, update the state."""
        now = time.monotonic()
        if now - self.last_hb_sent >= 1.0:
            self.conn.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            self.last_hb_sent = now
        msg = self.conn.recv_match(blocking=True, timeout=timeout_wall)
        if msg is None:
            return None
        mtype = msg.get_type()
        if mtype == "BAD_DATA":
            return None
        if self.target and msg.get_srcSystem() != self.target:
            return None
        if mtype == "HEARTBEAT" and msg.get_srcComponent() != 1:
            return None
        tb = getattr(msg, "time_boot_ms", None)
        if tb is not None and tb > 0:
            t = tb / 1000.0
            if self.t_boot_s is None or t >= self.t_boot_s:
                self.t_boot_s, self.t_boot_wall = t, time.monotonic()
        self.counts[mtype] += 1
        self.first_seen.setdefault(mtype, round(self.sim_now(), 2))
        self._observe(mtype, msg)
        self.last[mtype] = msg
        return msg

    def _observe(self, mtype: str, msg: Any) -> None:
        """Record state changes (timeline) of the messages that tell readiness and flight."""
        prev = self.last.get(mtype)
        if mtype == "STATUSTEXT":
            self.texts.append((round(self.sim_now(), 2), int(msg.severity), str(msg.text)))
        elif mtype == "COMMAND_ACK":
            self.acks.append((round(self.sim_now(), 2), int(msg.command), int(msg.result)))
        if not self.track:
            return
        if mtype == "EKF_STATUS_REPORT" and (prev is None or prev.flags != msg.flags):
            self._event("ekf_flags", flags=int(msg.flags))
        elif mtype == "GPS_RAW_INT" and (prev is None or prev.fix_type != msg.fix_type):
            self._event("gps_fix", fix_type=int(msg.fix_type), satellites=int(msg.satellites_visible))
        elif mtype == "SYS_STATUS":
            bits = int(msg.onboard_control_sensors_health) & (SENSOR_GPS | SENSOR_AHRS | SENSOR_PREARM)
            pbits = None if prev is None else int(prev.onboard_control_sensors_health) & (SENSOR_GPS | SENSOR_AHRS | SENSOR_PREARM)
            if bits != pbits:
                self._event("health", gps=bool(bits & SENSOR_GPS), ahrs=bool(bits & SENSOR_AHRS), prearm=bool(bits & SENSOR_PREARM))
        elif mtype in ("HOME_POSITION", "GPS_GLOBAL_ORIGIN", "LOCAL_POSITION_NED") and prev is None:
            self._event("first", message=mtype)
        elif mtype == "STATUSTEXT":
            self._event("text", text=str(msg.text))
        elif mtype == "EXTENDED_SYS_STATE" and (prev is None or prev.landed_state != msg.landed_state):
            self._event("landed_state", landed_state=int(msg.landed_state))
        elif mtype == "HEARTBEAT" and (
            prev is None or (prev.custom_mode, prev.base_mode & 128, prev.system_status) != (msg.custom_mode, msg.base_mode & 128, msg.system_status)
        ):
            self._event("heartbeat", custom_mode=int(msg.custom_mode), armed=bool(msg.base_mode & 128),
                        base_mode=int(msg.base_mode), system_status=int(msg.system_status))

    def wall_deadline(self, sim_s: float) -> float:
        """Wall deadline for ``sim_s`` seconds of sim time (twice the nominal, plus 5 s)."""
        return time.monotonic() + 2.0 * sim_s / self.speedup + 5.0

    def wait(self, pred: Callable[[], bool], sim_s: float, what: str) -> None:
        """Pump until ``pred()`` holds; SequenceError after ``sim_s`` of sim time (with margin)."""
        end = self.wall_deadline(sim_s)
        while not pred():
            if time.monotonic() > end:
                raise SequenceError(f"{what}: not seen within {sim_s:g} s of sim time")
            self.pump()

    def idle(self, sim_s: float) -> None:
        """Keep reading for ``sim_s`` seconds of sim time (a measurement window)."""
        t_end = self.sim_now() + sim_s
        wall_end = self.wall_deadline(sim_s)
        while self.sim_now() < t_end and time.monotonic() < wall_end:
            self.pump()

    def command(self, cmd: int, *params: float, sim_s: float = 5.0, text_window_s: float = 0.5) -> dict[str, Any]:
        """COMMAND_LONG; returns {"ack": result, "texts": [...]} with the STATUSTEXTs seen from
        the send until ``text_window_s`` sim seconds after the ACK."""
        p = list(params) + [0.0] * (7 - len(params))
        n_texts = len(self.texts)
        n_acks = len(self.acks)
        self.conn.mav.command_long_send(self.target, 1, cmd, 0, *p)
        self.wait(lambda: any(c == cmd for _, c, _ in self.acks[n_acks:]), sim_s, f"COMMAND_ACK of {cmd}")
        result = next(r for _, c, r in self.acks[n_acks:] if c == cmd)
        self.idle(text_window_s)
        return {"ack": result, "texts": [t for _, _, t in self.texts[n_texts:]]}

    def set_mode(self, custom_mode: int) -> dict[str, Any]:
        """MAV_CMD_DO_SET_MODE with a copter mode number."""
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom_mode)

    def heartbeat(self) -> Any:
        """The newest vehicle HEARTBEAT."""
        return self.last["HEARTBEAT"]

    def fresh_heartbeat(self, wall_s: float = 5.0) -> Any:
        """The next vehicle HEARTBEAT, asked for with MAV_CMD_REQUEST_MESSAGE (fimnav's vehicle
        sends heartbeats at 1 Hz of *wall* time, so at a speed-up the newest may be several sim
        seconds old; both autopilots answer the request at once)."""
        n = self.counts["HEARTBEAT"]
        self.conn.mav.command_long_send(self.target, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 0, 0, 0, 0, 0, 0, 0)
        end = time.monotonic() + wall_s
        while self.counts["HEARTBEAT"] == n:
            if time.monotonic() > end:
                raise SequenceError(f"no HEARTBEAT within {wall_s} s of wall time")
            self.pump()
        return self.heartbeat()

    def wait_mode(self, custom_mode: int, wall_s: float = 5.0) -> int:
        """The custom mode of the first heartbeat in ``custom_mode``, or of the last heartbeat
        seen within ``wall_s`` wall seconds (heartbeats are 1 Hz of wall time on fimnav's vehicle)."""
        end = time.monotonic() + wall_s
        while self.heartbeat().custom_mode != custom_mode and time.monotonic() < end:
            self.pump()
        return int(self.heartbeat().custom_mode)

    def rates(self, sim_s: float) -> dict[str, float]:
        """Messages per sim second of each type over a window of ``sim_s`` sim seconds."""
        before = Counter(self.counts)
        t0 = self.sim_now()
        self.idle(sim_s)
        dt = self.sim_now() - t0
        return {k: round((self.counts[k] - before[k]) / dt, 2) for k in sorted(self.counts) if self.counts[k] > before[k]}


def _hb_summary(hb: Any) -> dict[str, Any]:
    return {
        "autopilot": int(hb.autopilot),
        "type": int(hb.type),
        "base_mode": int(hb.base_mode),
        "custom_mode": int(hb.custom_mode),
        "system_status": int(hb.system_status),
        "mavlink_version": int(hb.mavlink_version),
    }


def connect(address: str, deadline_s: float = 30.0) -> Any:
    """A pymavlink client of ``tcp:127.0.0.1:PORT`` (retried until ``deadline_s``: SITL may not
    listen yet)."""
    if not address.startswith("tcp:127.0.0.1:"):
        raise ValueError(f"loopback tcp:127.0.0.1:PORT only, got {address!r}")
    end = time.monotonic() + deadline_s
    while True:
        try:
            return mavutil.mavlink_connection(address, source_system=GCS_SYSID, source_component=GCS_COMPID,
                                              dialect="ardupilotmega", autoreconnect=False)
        except OSError:
            if time.monotonic() > end:
                raise
            time.sleep(0.1)  # retrying the connection, with the deadline above


def _ready(o: Observer) -> bool:
    """The planner's readiness rule: EKF position (flags, not constant-position mode), GPS 3D
    fix, home and EKF origin known, LOCAL_POSITION_NED flowing."""
    ekf = o.last.get("EKF_STATUS_REPORT")
    gps = o.last.get("GPS_RAW_INT")
    return (
        ekf is not None and (ekf.flags & EKF_READY_FLAGS) == EKF_READY_FLAGS and not ekf.flags & EKF_CONST_POS_MODE
        and gps is not None and gps.fix_type >= 3
        and "HOME_POSITION" in o.last and "GPS_GLOBAL_ORIGIN" in o.last and "LOCAL_POSITION_NED" in o.last
    )


def _local(o: Observer) -> tuple[float, float, float]:
    m = o.last["LOCAL_POSITION_NED"]
    return (float(m.x), float(m.y), float(m.z))


def _speed(o: Observer) -> float:
    m = o.last["LOCAL_POSITION_NED"]
    return math.sqrt(m.vx**2 + m.vy**2 + m.vz**2)


def _retry_until_accepted(o: Observer, send: Callable[[], dict[str, Any]], sim_s: float, what: str) -> dict[str, Any]:
    """Repeat a command once per sim second until ACCEPTED; the refusals are counted."""
    end = o.wall_deadline(sim_s)
    refusals: list[dict[str, Any]] = []
    while True:
        r = send()
        if r["ack"] == mavlink.MAV_RESULT_ACCEPTED:
            r["refusals_before"] = len(refusals)
            r["first_refusal"] = refusals[0] if refusals else None
            return r
        refusals.append(r)
        if time.monotonic() > end:
            raise SequenceError(f"{what}: still refused after {sim_s:g} s of sim time: {refusals[-1]}")
        o.idle(1.0)


def _fly_to(o: Observer, target_ned: tuple[float, float, float], sim_s: float = 60.0) -> dict[str, Any]:
    """Wait until the vehicle settles at ``target_ned`` (LOCAL_NED); summary of the leg."""
    t0 = o.sim_now()
    start = _local(o)

    def arrived() -> bool:
        return math.dist(_local(o), target_ned) <= ARRIVED_M and _speed(o) <= ARRIVED_SPEED_MPS

    reached = True
    try:
        o.wait(arrived, sim_s, f"arrival at {target_ned}")
    except SequenceError:
        reached = False
    o.idle(1.0)
    g = o.last["GLOBAL_POSITION_INT"]
    home = o.last["HOME_POSITION"]
    end = _local(o)
    return {
        "start_local_ned": [round(v, 2) for v in start],
        "reached": reached,
        "duration_s": round(o.sim_now() - t0, 1),
        "final_local_ned": [round(v, 2) for v in end],
        "error_m": round(math.dist(end, target_ned), 2),
        "relative_alt_m": round(g.relative_alt / 1000.0, 2),
        "alt_minus_home_alt_m": round((g.alt - home.altitude) / 1000.0, 2),
        "mode": int(o.heartbeat().custom_mode),
    }


def _offset_latlon(lat_e7: int, lon_e7: int, north_m: float, east_m: float) -> tuple[int, int]:
    """Latitude/longitude (1e-7 deg) ``north_m``/``east_m`` from a point (pyproj geodesic)."""
    from pyproj import Geod

    geod = Geod(ellps="WGS84")
    lat, lon = lat_e7 * 1e-7, lon_e7 * 1e-7
    dist = math.hypot(north_m, east_m)
    if dist == 0.0:
        return lat_e7, lon_e7
    az = math.degrees(math.atan2(east_m, north_m))
    lon2, lat2, _ = geod.fwd(lon, lat, az, dist)
    return int(round(lat2 * 1e7)), int(round(lon2 * 1e7))


def _setpoint(o: Observer, frame_name: str, target: tuple[float, float, float]) -> tuple[float, float, float]:
    """Send one position setpoint; returns the LOCAL_NED point it means (home = origin here)."""
    home = o.last["HOME_POSITION"]
    origin = o.last["GPS_GLOBAL_ORIGIN"]
    if frame_name == "LOCAL_NED":
        o.conn.mav.set_position_target_local_ned_send(0, o.target, 1, mavlink.MAV_FRAME_LOCAL_NED, MASK_POSITION,
                                                      *target, 0, 0, 0, 0, 0, 0, 0, 0)
        return target
    north, east, alt = target
    lat, lon = _offset_latlon(home.latitude, home.longitude, north, east)
    frame = getattr(mavlink, "MAV_FRAME_" + frame_name)
    if frame_name == "GLOBAL_INT":  # AMSL: the altitude is metres above home plus home's AMSL altitude
        alt_sent = home.altitude / 1000.0 + alt
    else:
        alt_sent = alt
    o.conn.mav.set_position_target_global_int_send(0, o.target, 1, frame, MASK_POSITION, lat, lon, alt_sent,
                                                   0, 0, 0, 0, 0, 0, 0, 0)
    home_d_from_origin = (origin.altitude - home.altitude) / 1000.0  # NED down of home about the origin
    return (north + float(home.x), east + float(home.y), -alt + home_d_from_origin)


def run_sequence(address: str, *, speedup: float, vehicle: dict[str, Any], log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Fly the differential-check sequence against the vehicle at ``address`` (loopback TCP,
    the vehicle's first boot: disarmed on the ground, not yet ready) and return its transcript.

    Args:
        address: ``tcp:127.0.0.1:PORT``.
        speedup: the vehicle's sim/wall speed (for deadlines only; times are sim time).
        vehicle: what was flown (kind, version, command line), copied into the transcript.
        log: progress lines (optional).

    Raises:
        SequenceError: a step did not complete within its deadline.
    """
    say = log or (lambda s: None)
    wall_start = time.monotonic()
    conn = connect(address)
    try:
        o = Observer(conn, speedup)
        tr: dict[str, Any] = {"schema": SCHEMA, "vehicle": dict(vehicle, speedup=speedup)}
        # -- heartbeat and flavour
        o.wait(lambda: "HEARTBEAT" in o.last, 60.0 * speedup, "first HEARTBEAT")
        hb = o.heartbeat()
        o.target = hb.get_srcSystem()
        tr["heartbeat"] = dict(_hb_summary(hb), sysid=o.target, compid=hb.get_srcComponent(),
                               flavour={mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", mavlink.MAV_AUTOPILOT_PX4: "px4"}.get(hb.autopilot, "other"),
                               mode_name=mavutil.mode_string_v10(hb))
        say(f"heartbeat {tr['heartbeat']}")
        # -- before any stream request: what the vehicle sends unasked
        o.counts.clear()
        tr["unrequested"] = {"rates_hz": o.rates(5.0)}
        # -- REQUEST_DATA_STREAM ALL at 4 Hz (MAVProxy's default)
        conn.mav.request_data_stream_send(o.target, 1, mavlink.MAV_DATA_STREAM_ALL, DATA_STREAM_ALL_HZ, 1)
        o.idle(1.0)
        tr["request_data_stream"] = {"stream": "ALL", "hz": DATA_STREAM_ALL_HZ, "rates_hz": o.rates(5.0)}
        # -- SET_MESSAGE_INTERVAL as the planner asks
        acks: dict[str, int] = {}
        for mid, hz in PLANNER_INTERVALS_HZ.items():
            acks[str(mid)] = o.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mid, 1e6 / hz, text_window_s=0.0)["ack"]
        o.idle(1.0)
        tr["set_message_interval"] = {"hz": {str(k): v for k, v in PLANNER_INTERVALS_HZ.items()}, "acks": acks, "rates_hz": o.rates(5.0)}
        say(f"streams done at sim {o.sim_now():.1f} s")
        # -- before ready: GUIDED, arming, home requests
        before: dict[str, Any] = {"t_s": round(o.sim_now(), 1), "home_seen": "HOME_POSITION" in o.last,
                                  "local_position_seen": "LOCAL_POSITION_NED" in o.last}
        before["guided"] = o.set_mode(GUIDED)
        before["mode_after"] = o.wait_mode(GUIDED, 1.5)
        before["arm_stabilize"] = o.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        n_home = o.counts["HOME_POSITION"]
        req = o.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 242, text_window_s=1.0)
        req["home_sent"] = o.counts["HOME_POSITION"] > n_home
        before["request_home"] = req
        tr["before_ready"] = before
        say(f"before ready: {before}")
        # -- the readiness wait
        o.track = True
        t_wait = o.sim_now()
        ekf, gps, st = o.last.get("EKF_STATUS_REPORT"), o.last.get("GPS_RAW_INT"), o.last.get("SYS_STATUS")
        at_start = {
            "ekf_flags": None if ekf is None else int(ekf.flags),
            "gps_fix": None if gps is None else int(gps.fix_type),
            "health": None if st is None else {
                "gps": bool(st.onboard_control_sensors_health & SENSOR_GPS),
                "ahrs": bool(st.onboard_control_sensors_health & SENSOR_AHRS),
                "prearm": bool(st.onboard_control_sensors_health & SENSOR_PREARM)},
            "seen": sorted(k for k in ("HOME_POSITION", "GPS_GLOBAL_ORIGIN", "LOCAL_POSITION_NED") if k in o.last),
            "texts_so_far": [t for _, _, t in o.texts],
        }
        o.wait(lambda: _ready(o), 180.0, "readiness (EKF position, 3D fix, home, origin, LOCAL_POSITION_NED)")
        t_ready = o.sim_now()
        guided = _retry_until_accepted(o, lambda: o.set_mode(GUIDED), 60.0, "GUIDED")
        tr["readiness"] = {
            "wait_started_s": round(t_wait, 1),
            "at_start": at_start,
            "ready_s": round(t_ready, 1),
            "guided_accepted_s": round(o.sim_now(), 1),
            "guided_refusals_after_ready": guided["refusals_before"],
            "timeline": [e for e in o.events if e["event"] != "heartbeat"],
            "wall_s_since_connect": round(time.monotonic() - wall_start, 1),
        }
        o.events.clear()
        say(f"ready at sim {t_ready:.1f} s, GUIDED at {o.sim_now():.1f} s")
        o.wait_mode(GUIDED)
        home, origin = o.last["HOME_POSITION"], o.last["GPS_GLOBAL_ORIGIN"]
        g = o.last["GLOBAL_POSITION_INT"]
        tr["frames"] = {
            "home": {"lat_e7": int(home.latitude), "lon_e7": int(home.longitude), "alt_mm": int(home.altitude),
                     "local_ned": [round(float(home.x), 2), round(float(home.y), 2), round(float(home.z), 2)]},
            "origin": {"lat_e7": int(origin.latitude), "lon_e7": int(origin.longitude), "alt_mm": int(origin.altitude)},
            "origin_is_home": (origin.latitude, origin.longitude) == (home.latitude, home.longitude)
            and abs(origin.altitude - home.altitude) < 100,
            "on_ground_local_ned": [round(v, 2) for v in _local(o)],
            "on_ground_relative_alt_m": round(g.relative_alt / 1000.0, 2),
            "on_ground_alt_minus_home_alt_m": round((g.alt - home.altitude) / 1000.0, 2),
        }
        # -- refused commands (ready, disarmed, on the ground)
        ref: dict[str, Any] = {}
        ref["takeoff_disarmed"] = o.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, TAKEOFF_ALT_M)
        ref["unsupported_command"] = o.command(UNSUPPORTED_CMD)
        ref["unknown_mode"] = o.set_mode(UNKNOWN_MODE)
        ref["land_mode_disarmed"] = o.set_mode(LAND)
        o.wait_mode(LAND)
        ref["land_mode_disarmed"]["heartbeat"] = _hb_summary(o.heartbeat())
        ref["arm_in_land"] = o.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        back = o.set_mode(GUIDED)
        ref["guided_again"] = back
        o.wait_mode(GUIDED)
        ref["guided_disarmed_heartbeat"] = _hb_summary(o.heartbeat())
        tr["refusals"] = ref
        say(f"refusals: {ref}")
        # -- arm and take off
        o.events.clear()
        arm = _retry_until_accepted(o, lambda: o.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), 30.0, "arming")
        o.wait(lambda: bool(o.heartbeat().base_mode & 128), 50.0, "armed heartbeat")
        arm["heartbeat"] = _hb_summary(o.heartbeat())
        tr["arm"] = arm
        t0 = o.sim_now()
        to = o.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, TAKEOFF_ALT_M, text_window_s=0.0)
        alts: list[tuple[float, float]] = []

        def climbed() -> bool:
            g = o.last["GLOBAL_POSITION_INT"]
            if not alts or alts[-1][0] != g.time_boot_ms:
                alts.append((g.time_boot_ms / 1000.0, g.relative_alt / 1000.0))
            return abs(g.relative_alt / 1000.0 - TAKEOFF_ALT_M) <= 0.3 and _speed(o) <= ARRIVED_SPEED_MPS

        o.wait(climbed, 60.0, "take-off altitude")
        t_reached = o.sim_now()
        in_air_hb = _hb_summary(o.fresh_heartbeat())
        to_again = o.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, TAKEOFF_ALT_M + 5)
        o.idle(2.0)
        rising = [(t, a) for t, a in alts if 0.2 * TAKEOFF_ALT_M <= a <= 0.8 * TAKEOFF_ALT_M]
        climb = (rising[-1][1] - rising[0][1]) / (rising[-1][0] - rising[0][0]) if len(rising) > 1 and rising[-1][0] > rising[0][0] else None
        tr["takeoff"] = {
            "ack": to["ack"],
            "texts": [e["text"] for e in o.events if e["event"] == "text"],
            "alt_m": TAKEOFF_ALT_M,
            "reached_after_s": round(t_reached - t0, 1),
            "climb_rate_mps": None if climb is None else round(climb, 2),
            "max_relative_alt_m": round(max(a for _, a in alts), 2),
            "final_relative_alt_m": round(o.last["GLOBAL_POSITION_INT"].relative_alt / 1000.0, 2),
            "landed_states": [e["landed_state"] for e in o.events if e["event"] == "landed_state"],
            "heartbeat_in_air": in_air_hb,
            "heartbeats": [e for e in o.events if e["event"] == "heartbeat"],
            "takeoff_in_air": to_again,
        }
        o.events.clear()
        say(f"take-off: {tr['takeoff']}")
        # -- setpoints
        legs = []
        for name, frame_name, target in SETPOINTS:
            n_texts = len(o.texts)
            ned = _setpoint(o, frame_name, target)
            leg = {"name": name, "frame": frame_name, "sent": list(target), "expected_local_ned": [round(v, 2) for v in ned]}
            leg.update(_fly_to(o, ned))
            leg["texts"] = [t for _, _, t in o.texts[n_texts:]]
            legs.append(leg)
            say(f"setpoint {leg}")
        tr["setpoints"] = legs
        o.events.clear()
        # -- LAND
        t0 = o.sim_now()
        land = o.set_mode(LAND)
        land_hb = _hb_summary(o.fresh_heartbeat())
        vz: list[float] = []

        def disarmed() -> bool:
            m = o.last["LOCAL_POSITION_NED"]
            if -m.z > 1.0:
                vz.append(float(m.vz))
            return not o.heartbeat().base_mode & 128

        o.wait(disarmed, 120.0, "disarm on landing")
        t_disarm = o.sim_now()
        o.idle(3.0)
        tr["land"] = {
            "ack": land["ack"],
            "heartbeat": land_hb,
            "descent_rate_median_mps": round(statistics.median(vz), 2) if vz else None,
            "descent_rate_max_mps": round(max(vz), 2) if vz else None,
            "disarmed_after_s": round(t_disarm - t0, 1),
            "landed_states": [e["landed_state"] for e in o.events if e["event"] == "landed_state"],
            "texts": [e["text"] for e in o.events if e["event"] == "text"],
            "heartbeat_after": _hb_summary(o.heartbeat()),
            "final_relative_alt_m": round(o.last["GLOBAL_POSITION_INT"].relative_alt / 1000.0, 2),
        }
        say(f"land: {tr['land']}")
        tr["wall_s"] = round(time.monotonic() - wall_start, 1)
        return tr
    finally:
        conn.close()


# ---------------------------------------------------------------------------- comparison

#: Rate tolerance: |got - ref| <= REL * ref + ABS (Hz).
RATE_REL, RATE_ABS = 0.25, 0.3


#: STATUSTEXTs of the simulator, the EKF and the sensors that fimnav's vehicle does not model;
#: left out when texts are compared.
IGNORED_TEXT_PREFIXES = ("EKF3 ", "SIM ", "Field Elevation", "GPS 1:", "AHRS:", "Barometer", "Calibrating")


def _texts(texts: list[str]) -> list[str]:
    return [t for t in texts if not t.startswith(IGNORED_TEXT_PREFIXES)]


def _rate_ok(ref: float, got: float) -> bool:
    return abs(got - ref) <= RATE_REL * ref + RATE_ABS


def compare(ref: dict[str, Any], got: dict[str, Any]) -> list[str]:
    """Differences of ``got`` from the reference transcript ``ref`` on every point a planner
    or a ground station could trip on (empty: they answer alike). Times, speeds and the
    messages fimnav does not simulate are not compared (docs/vehicle_sim.md, "Known
    differences from ArduPilot SITL")."""
    diffs: list[str] = []

    def same(path: str, a: Any, b: Any) -> None:
        if a != b:
            diffs.append(f"{path}: ArduPilot {a!r}, vehicle {b!r}")

    # (system_status of the very first heartbeat is not compared: ArduPilot reports ACTIVE for
    # its first seconds after boot, before land_complete is set, then STANDBY.)
    for k in ("autopilot", "type", "base_mode", "custom_mode", "mavlink_version", "compid", "flavour", "mode_name"):
        same(f"heartbeat.{k}", ref["heartbeat"][k], got["heartbeat"][k])
    # Stream rates of the planner's messages (after the planner's SET_MESSAGE_INTERVAL).
    for mid, result in ref["set_message_interval"]["acks"].items():
        same(f"set_message_interval.acks[{mid}]", result, got["set_message_interval"]["acks"].get(mid))
    for section in ("request_data_stream", "set_message_interval"):
        r, g = ref[section]["rates_hz"], got[section]["rates_hz"]
        for name in PLANNER_TYPES:
            if name in ("HOME_POSITION", "LOCAL_POSITION_NED") or name not in r:
                continue  # sent only once home / the EKF position exist; unrequested extras allowed
            a, b = r.get(name, 0.0), g.get(name, 0.0)
            if not _rate_ok(a, b):
                diffs.append(f"{section}.rates_hz[{name}]: ArduPilot {a}, vehicle {b}")
    # Before ready.
    rb, gb = ref["before_ready"], got["before_ready"]
    for k in ("guided", "arm_stabilize"):
        same(f"before_ready.{k}.ack", rb[k]["ack"], gb[k]["ack"])
    same("before_ready.guided.texts", _texts(rb["guided"]["texts"]), _texts(gb["guided"]["texts"]))
    # The reason depends on the start-up stage (its timing differs): only the prefix must match.
    for who, tr in (("ArduPilot", rb), ("vehicle", gb)):
        texts = _texts(tr["arm_stabilize"]["texts"])
        if not texts or not all(t.startswith("Arm: ") for t in texts):
            diffs.append(f"before_ready.arm_stabilize.texts ({who}): {texts} (expected 'Arm: ...')")
    same("before_ready.mode_after", rb["mode_after"], gb["mode_after"])
    same("before_ready.request_home.ack", rb["request_home"]["ack"], gb["request_home"]["ack"])
    # Frames.
    rf, gf = ref["frames"], got["frames"]
    same("frames.origin_is_home", rf["origin_is_home"], gf["origin_is_home"])
    for k in ("on_ground_local_ned", "on_ground_relative_alt_m", "on_ground_alt_minus_home_alt_m"):
        a, b = rf[k], gf[k]
        if not all(abs(x - y) <= 0.5 for x, y in zip(a if isinstance(a, list) else [a], b if isinstance(b, list) else [b], strict=True)):
            diffs.append(f"frames.{k}: ArduPilot {a}, vehicle {b}")
    if not all(abs(v) <= 0.5 for v in gf["home"]["local_ned"]):
        diffs.append(f"frames.home.local_ned: vehicle {gf['home']['local_ned']} (ArduPilot {rf['home']['local_ned']})")
    # Refusals.
    for k in ("takeoff_disarmed", "unsupported_command", "unknown_mode", "land_mode_disarmed", "arm_in_land", "guided_again"):
        same(f"refusals.{k}.ack", ref["refusals"][k]["ack"], got["refusals"][k]["ack"])
        same(f"refusals.{k}.texts", _texts(ref["refusals"][k]["texts"]), _texts(got["refusals"][k]["texts"]))
    for k in ("base_mode", "custom_mode", "system_status"):
        same(f"refusals.land_mode_disarmed.heartbeat.{k}", ref["refusals"]["land_mode_disarmed"]["heartbeat"][k],
             got["refusals"]["land_mode_disarmed"]["heartbeat"][k])
        same(f"refusals.guided_disarmed_heartbeat.{k}", ref["refusals"]["guided_disarmed_heartbeat"][k],
             got["refusals"]["guided_disarmed_heartbeat"][k])
    # Arm, take-off.
    same("arm.ack", ref["arm"]["ack"], got["arm"]["ack"])
    for k in ("base_mode", "custom_mode", "system_status"):
        same(f"arm.heartbeat.{k}", ref["arm"]["heartbeat"][k], got["arm"]["heartbeat"][k])
        same(f"takeoff.heartbeat_in_air.{k}", ref["takeoff"]["heartbeat_in_air"][k], got["takeoff"]["heartbeat_in_air"][k])
        same(f"land.heartbeat.{k}", ref["land"]["heartbeat"][k], got["land"]["heartbeat"][k])
        same(f"land.heartbeat_after.{k}", ref["land"]["heartbeat_after"][k], got["land"]["heartbeat_after"][k])
    rt, gt = ref["takeoff"], got["takeoff"]
    same("takeoff.ack", rt["ack"], gt["ack"])
    same("takeoff.texts", _texts(rt["texts"]), _texts(gt["texts"]))
    same("takeoff.landed_states", rt["landed_states"], gt["landed_states"])
    same("takeoff.takeoff_in_air.ack", rt["takeoff_in_air"]["ack"], gt["takeoff_in_air"]["ack"])
    if abs(rt["final_relative_alt_m"] - gt["final_relative_alt_m"]) > 0.5:
        diffs.append(f"takeoff.final_relative_alt_m: ArduPilot {rt['final_relative_alt_m']}, vehicle {gt['final_relative_alt_m']}")
    # Setpoints: same place in every frame.
    for rl, gl in zip(ref["setpoints"], got["setpoints"], strict=True):
        same(f"setpoints[{rl['name']}].reached", rl["reached"], gl["reached"])
        same(f"setpoints[{rl['name']}].mode", rl["mode"], gl["mode"])
        if math.dist(rl["final_local_ned"], gl["final_local_ned"]) > 1.0:
            diffs.append(f"setpoints[{rl['name']}].final_local_ned: ArduPilot {rl['final_local_ned']}, vehicle {gl['final_local_ned']}")
        for k in ("relative_alt_m", "alt_minus_home_alt_m"):
            if abs(rl[k] - gl[k]) > 0.5:
                diffs.append(f"setpoints[{rl['name']}].{k}: ArduPilot {rl[k]}, vehicle {gl[k]}")
        same(f"setpoints[{rl['name']}].texts", _texts(rl["texts"]), _texts(gl["texts"]))
    # Land.
    rl, gl = ref["land"], got["land"]
    same("land.ack", rl["ack"], gl["ack"])
    same("land.landed_states", rl["landed_states"], gl["landed_states"])
    same("land.texts", _texts(rl["texts"]), _texts(gl["texts"]))
    if abs(rl["final_relative_alt_m"] - gl["final_relative_alt_m"]) > 0.3:
        diffs.append(f"land.final_relative_alt_m: ArduPilot {rl['final_relative_alt_m']}, vehicle {gl['final_relative_alt_m']}")
    return diffs


def main(argv: list[str] | None = None) -> int:
    """Record a transcript: ``--connect tcp:127.0.0.1:PORT --speedup S --kind K --out FILE``."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--connect", required=True)
    ap.add_argument("--speedup", type=float, default=1.0)
    ap.add_argument("--kind", default="unknown")
    ap.add_argument("--out", default="-")
    a = ap.parse_args(argv)
    tr = run_sequence(a.connect, speedup=a.speedup, vehicle={"kind": a.kind}, log=lambda s: print(s, file=sys.stderr, flush=True))
    text = json.dumps(tr, indent=1, sort_keys=True)
    if a.out == "-":
        print(text)
    else:
        with open(a.out, "w", encoding="utf-8") as f:
            f.write(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
