"""A scripted ground station for the differential check of fimnav's simulated vehicle (PX4
flavour) against real PX4 SITL (v1.15, SIH quadrotor), flown in OFFBOARD as fimnav's planner
flies it.

:func:`run_sequence` flies one fixed sequence against a PX4-flavoured MAVLink vehicle on a
loopback UDP link (``udpin:127.0.0.1:PORT`` for PX4's offboard link, ``udpout:127.0.0.1:PORT``
for ``fimnav vehicle --mavlink udpin:…``) and returns what a ground station observes as a
JSON-able transcript: heartbeat and flavour, what is sent unasked, SET_MESSAGE_INTERVAL (the
planner's messages, EKF_STATUS_REPORT included) and the rates they give, commands before the
vehicle is ready, the readiness wait (the planner's PX4 rule), frames (home, EKF origin, local
z on the ground), refused commands, the setpoint stream then OFFBOARD, arming, the climb on the
stream, setpoints in three frames, a take-off command in the air, AUTO.LAND and the disarm on
landing. Every time in it is **sim time** (the vehicle's ``time_boot_ms``).

:func:`compare` lists the differences on the points where fimnav's vehicle must answer as PX4
does (``tests/vehicle_sim/test_vehicle_vs_px4.py``). Record a transcript with
``python -m tests.sitl.record_transcript_px4``.
"""

from __future__ import annotations

import math
import statistics
import time
from collections.abc import Callable
from typing import Any

from tests.sitl.gcs_script import (
    ARRIVED_M, ARRIVED_SPEED_MPS, GCS_COMPID, GCS_SYSID, MASK_POSITION, SENSOR_AHRS, SENSOR_GPS, SENSOR_PREARM,
    UNSUPPORTED_CMD, Observer, SequenceError, _hb_summary, _local, _offset_latlon, _speed, mavlink, mavutil)

SCHEMA = 1
#: PX4 custom modes (main_mode << 16 | sub_mode << 24) and DO_SET_MODE parameters (main, sub).
POSCTL, OFFBOARD = (3, 0), (6, 0)
AUTO_LOITER, AUTO_LAND = (4, 3), (4, 6)
UNKNOWN_MODE = (99, 0)
#: SET_MESSAGE_INTERVAL requests (message id -> Hz) of fimnav's planner on PX4
#: (planner/node/realtime_preflight.py ``RealtimePreflight.request_streams``), EKF_STATUS_REPORT (193) too, which PX4 refuses.
INTERVALS_HZ: dict[int, float] = {33: 10.0, 32: 10.0, 1: 1.0, 24: 1.0, 242: 0.5, 245: 1.0, 193: 1.0}
#: Setpoint stream rate (wall Hz): PX4 wants > 2 Hz of its own time; 20 Hz covers a ×5 clock.
STREAM_HZ = 20.0
#: Height of the climb on the stream (m above the ground position read before take-off).
CLIMB_M = 10.0
#: Setpoints after the climb: (name, frame, target) — LOCAL_NED (N, E, D) m about the EKF
#: origin; global ones (north m, east m, altitude m) from home, the altitude in the frame's meaning.
SETPOINTS: tuple[tuple[str, str, tuple[float, float, float]], ...] = (
    ("local_ned", "LOCAL_NED", (10.0, 15.0, -12.0)),
    ("global_amsl", "GLOBAL_INT", (0.0, 0.0, 8.0)),
    ("global_relative_alt", "GLOBAL_RELATIVE_ALT_INT", (20.0, 10.0, 15.0)),
)
PLANNER_TYPES = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "SYS_STATUS", "GPS_RAW_INT", "HOME_POSITION", "EXTENDED_SYS_STATE")


def custom(mode: tuple[int, int]) -> int:
    """PX4's HEARTBEAT.custom_mode of (main, sub)."""
    return (mode[0] << 16) | (mode[1] << 24)


class Px4Observer(Observer):
    """:class:`gcs_script.Observer` that also streams a position setpoint (when set) at
    :data:`STREAM_HZ` of wall time from its pump, as an offboard client must."""

    stream: tuple[str, tuple[float, float, float]] | None = None
    last_sp_wall: float = -math.inf
    sp_sent: int = 0

    def pump(self, timeout_wall: float = 0.02) -> Any:
        now = time.monotonic()
        if self.stream is not None and now - self.last_sp_wall >= 1.0 / STREAM_HZ:
            self._send_setpoint(*self.stream)
            self.last_sp_wall = now
        return super().pump(min(timeout_wall, 1.0 / STREAM_HZ))

    def _send_setpoint(self, frame_name: str, target: tuple[float, float, float]) -> None:
        self.sp_sent += 1
        if frame_name == "LOCAL_NED":
            self.conn.mav.set_position_target_local_ned_send(0, self.target, 1, mavlink.MAV_FRAME_LOCAL_NED, MASK_POSITION,
                                                             *target, 0, 0, 0, 0, 0, 0, 0, 0)
        else:
            lat, lon, alt = target
            self.conn.mav.set_position_target_global_int_send(0, self.target, 1, getattr(mavlink, "MAV_FRAME_" + frame_name),
                                                              MASK_POSITION, int(lat), int(lon), alt, 0, 0, 0, 0, 0, 0, 0, 0)

    def set_px4_mode(self, mode: tuple[int, int]) -> dict[str, Any]:
        """MAV_CMD_DO_SET_MODE (custom mode enabled, main, sub)."""
        return self.command(mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, mode[0], mode[1])


def connect(address: str) -> Any:
    """A pymavlink client of a loopback UDP address (``udpin:`` or ``udpout:127.0.0.1:PORT``)."""
    if not address.startswith(("udpin:127.0.0.1:", "udpout:127.0.0.1:")):
        raise ValueError(f"loopback udpin:/udpout:127.0.0.1:PORT only, got {address!r}")
    return mavutil.mavlink_connection(address, source_system=GCS_SYSID, source_component=GCS_COMPID, dialect="common")


def _ready(o: Observer) -> bool:
    """The planner's PX4 readiness rule (comms.mavlink_client.VehicleLink.not_ready): GPS 3D
    fix, AHRS and pre-arm health bits of SYS_STATUS, a position (GLOBAL_POSITION_INT), home and
    EKF origin known; LOCAL_POSITION_NED flowing too (the sequence uses it)."""
    st, gps = o.last.get("SYS_STATUS"), o.last.get("GPS_RAW_INT")
    return (st is not None and (st.onboard_control_sensors_health & (SENSOR_AHRS | SENSOR_PREARM)) == (SENSOR_AHRS | SENSOR_PREARM)
            and gps is not None and gps.fix_type >= 3
            and all(k in o.last for k in ("GLOBAL_POSITION_INT", "HOME_POSITION", "GPS_GLOBAL_ORIGIN", "LOCAL_POSITION_NED")))


def _retry(o: Px4Observer, send: Callable[[], dict[str, Any]], sim_s: float, what: str) -> dict[str, Any]:
    """Repeat a command once per sim second until ACCEPTED; the refusals are counted."""
    end = o.wall_deadline(sim_s)
    refusals: list[dict[str, Any]] = []
    while True:
        r = send()
        if r["ack"] == mavlink.MAV_RESULT_ACCEPTED:
            return dict(r, refusals_before=len(refusals), first_refusal=refusals[0] if refusals else None)
        refusals.append(r)
        if time.monotonic() > end:
            raise SequenceError(f"{what}: still refused after {sim_s:g} s of sim time: {refusals[-1]}")
        o.idle(1.0)


def _target(o: Px4Observer, frame_name: str, target: tuple[float, float, float]) -> tuple[tuple[str, tuple[float, float, float]], tuple[float, float, float]]:
    """The stream entry for a setpoint and the LOCAL_NED point it means (by MAVLink's
    definition of the frame: home's AMSL altitude + relative altitude)."""
    home, origin = o.last["HOME_POSITION"], o.last["GPS_GLOBAL_ORIGIN"]
    if frame_name == "LOCAL_NED":
        return (frame_name, target), target
    north, east, alt = target
    lat, lon = _offset_latlon(home.latitude, home.longitude, north, east)
    alt_sent = home.altitude / 1000.0 + alt if frame_name == "GLOBAL_INT" else alt
    home_d = (origin.altitude - home.altitude) / 1000.0  # NED down of home about the origin
    return (frame_name, (lat, lon, alt_sent)), (north + float(home.x), east + float(home.y), -alt + home_d)


def _leg(o: Px4Observer, target_ned: tuple[float, float, float], sim_s: float = 60.0) -> dict[str, Any]:
    """Wait until the vehicle settles at ``target_ned``; summary of the leg (as gcs_script)."""
    t0 = o.sim_now()
    start = _local(o)
    reached = True
    try:
        o.wait(lambda: math.dist(_local(o), target_ned) <= ARRIVED_M and _speed(o) <= ARRIVED_SPEED_MPS, sim_s, f"arrival at {target_ned}")
    except SequenceError:
        reached = False
    o.idle(1.0)
    g, home, end = o.last["GLOBAL_POSITION_INT"], o.last["HOME_POSITION"], _local(o)
    return {"start_local_ned": [round(v, 2) for v in start], "reached": reached, "duration_s": round(o.sim_now() - t0, 1),
            "final_local_ned": [round(v, 2) for v in end], "error_m": round(math.dist(end, target_ned), 2),
            "relative_alt_m": round(g.relative_alt / 1000.0, 2), "alt_minus_home_alt_m": round((g.alt - home.altitude) / 1000.0, 2),
            "mode": int(o.heartbeat().custom_mode)}


def run_sequence(address: str, *, speedup: float, vehicle: dict[str, Any], log: Callable[[str], None] | None = None) -> dict[str, Any]:
    """Fly the PX4 differential-check sequence against the vehicle at ``address`` (its first
    boot: disarmed on the ground, not yet ready) and return its transcript.

    Args:
        address: ``udpin:127.0.0.1:PORT`` (PX4's offboard link) or ``udpout:127.0.0.1:PORT``.
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
        o = Px4Observer(conn, speedup)
        tr: dict[str, Any] = {"schema": SCHEMA, "vehicle": dict(vehicle, speedup=speedup)}
        # udpout: the vehicle learns our address from our first datagram (a heartbeat).
        o.wait(lambda: "HEARTBEAT" in o.last, 60.0 * speedup, "first HEARTBEAT")
        hb = o.heartbeat()
        o.target = hb.get_srcSystem()
        tr["heartbeat"] = dict(_hb_summary(hb), sysid=o.target, compid=hb.get_srcComponent(),
                               flavour={mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA: "ardupilot", mavlink.MAV_AUTOPILOT_PX4: "px4"}.get(hb.autopilot, "other"))
        say(f"heartbeat {tr['heartbeat']}")
        o.counts.clear()
        tr["unrequested"] = {"rates_hz": o.rates(5.0)}
        acks: dict[str, int] = {}
        for mid, hz in INTERVALS_HZ.items():
            acks[str(mid)] = o.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mid, 1e6 / hz, text_window_s=0.0)["ack"]
        o.idle(1.0)
        tr["set_message_interval"] = {"hz": {str(k): v for k, v in INTERVALS_HZ.items()}, "acks": acks, "rates_hz": o.rates(5.0)}
        say(f"streams: {tr['set_message_interval']}")
        # -- before ready (no setpoint stream yet)
        before: dict[str, Any] = {"t_s": round(o.sim_now(), 1), "home_seen": "HOME_POSITION" in o.last,
                                  "global_position_seen": "GLOBAL_POSITION_INT" in o.last}
        before["arm"] = o.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        before["request_origin"] = o.command(mavlink.MAV_CMD_REQUEST_MESSAGE, 49, text_window_s=1.0)
        tr["before_ready"] = before
        say(f"before ready: {before}")
        # -- the readiness wait
        o.track = True
        t_wait = o.sim_now()
        try:
            o.wait(lambda: _ready(o), 180.0, "readiness (pre-arm, AHRS, 3D fix, position, home, origin)")
        except SequenceError as exc:
            st, gps = o.last.get("SYS_STATUS"), o.last.get("GPS_RAW_INT")
            raise SequenceError(f"{exc}: SYS_STATUS health {None if st is None else hex(st.onboard_control_sensors_health)}, "
                                f"GPS fix {None if gps is None else gps.fix_type}, seen {sorted(o.last)}, texts {o.texts[-5:]}") from None
        t_ready = o.sim_now()
        tr["readiness"] = {"wait_started_s": round(t_wait, 1), "ready_s": round(t_ready, 1),
                           "timeline": [e for e in o.events if e["event"] in ("gps_fix", "health", "first")],
                           "wall_s_since_connect": round(time.monotonic() - wall_start, 1)}
        o.events.clear()
        say(f"ready at sim {t_ready:.1f} s")
        o.idle(2.0)
        home, origin, g = o.last["HOME_POSITION"], o.last["GPS_GLOBAL_ORIGIN"], o.last["GLOBAL_POSITION_INT"]
        ground = _local(o)
        tr["frames"] = {
            "home": {"alt_minus_origin_alt_m": round((home.altitude - origin.altitude) / 1000.0, 2),
                     "local_ned": [round(float(home.x), 2), round(float(home.y), 2), round(float(home.z), 2)]},
            "origin_is_home_latlon": (origin.latitude, origin.longitude) == (home.latitude, home.longitude),
            "on_ground_local_ned": [round(v, 2) for v in ground],
            "on_ground_relative_alt_m": round(g.relative_alt / 1000.0, 2),
        }
        # -- refused commands (ready, disarmed, on the ground)
        ref: dict[str, Any] = {}
        ref["unsupported_command"] = o.command(UNSUPPORTED_CMD)
        ref["unknown_mode"] = o.set_px4_mode(UNKNOWN_MODE)
        ref["offboard_without_stream"] = o.set_px4_mode(OFFBOARD)
        ref["land_mode_disarmed"] = o.set_px4_mode(AUTO_LAND)
        o.wait_mode(custom(AUTO_LAND), 1.5)
        ref["land_mode_disarmed"]["custom_mode_after"] = int(o.fresh_heartbeat().custom_mode)
        ref["arm_in_land"] = o.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        ref["posctl_again"] = o.set_px4_mode(POSCTL)
        o.wait_mode(custom(POSCTL), 1.5)
        tr["refusals"] = ref
        say(f"refusals: {ref}")
        # -- setpoint stream, OFFBOARD, arm, climb on the stream
        o.events.clear()
        climb_to = (ground[0], ground[1], ground[2] - CLIMB_M)
        o.stream = ("LOCAL_NED", climb_to)
        o.idle(1.0)
        offboard = _retry(o, lambda: o.set_px4_mode(OFFBOARD), 10.0, "OFFBOARD with the stream")
        mode_after = o.wait_mode(custom(OFFBOARD), 2.0)
        t0 = o.sim_now()
        arm = _retry(o, lambda: o.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1), 20.0, "arming")
        o.wait(lambda: bool(o.heartbeat().base_mode & 128), 10.0, "armed heartbeat")
        alts: list[tuple[float, float]] = []

        def climbed() -> bool:
            gp = o.last["GLOBAL_POSITION_INT"]
            if not alts or alts[-1][0] != gp.time_boot_ms / 1000.0:
                alts.append((gp.time_boot_ms / 1000.0, gp.relative_alt / 1000.0))
            return math.dist(_local(o), climb_to) <= ARRIVED_M and _speed(o) <= ARRIVED_SPEED_MPS

        o.wait(climbed, 60.0, "climb on the stream")
        t_reached = o.sim_now()
        in_air = _hb_summary(o.fresh_heartbeat())
        to_again = o.command(mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, float("nan"))
        o.idle(2.0)
        tr["offboard"] = {
            "mode_ack": offboard["ack"], "mode_refusals_with_stream": offboard["refusals_before"], "mode_after": mode_after,
            "arm_ack": arm["ack"], "arm_refusals": arm["refusals_before"],
            "climb_reached_after_s": round(t_reached - t0, 1), "max_relative_alt_m": round(max(a for _, a in alts), 2),
            "final_relative_alt_m": round(o.last["GLOBAL_POSITION_INT"].relative_alt / 1000.0, 2),
            "landed_states": [e["landed_state"] for e in o.events if e["event"] == "landed_state"],
            "heartbeat_in_air": in_air, "takeoff_in_air": to_again,
            "mode_after_takeoff_cmd": int(o.heartbeat().custom_mode),
            "texts": [e["text"] for e in o.events if e["event"] == "text"],
        }
        say(f"offboard: {tr['offboard']}")
        if int(o.heartbeat().custom_mode) != custom(OFFBOARD):
            o.set_px4_mode(OFFBOARD)
            o.wait_mode(custom(OFFBOARD), 2.0)
        # -- setpoints (streamed)
        legs = []
        for name, frame_name, target in SETPOINTS:
            n_texts = len(o.texts)
            o.stream, ned = _target(o, frame_name, target)
            leg = {"name": name, "frame": frame_name, "sent": list(target), "expected_local_ned": [round(v, 2) for v in ned]}
            leg.update(_leg(o, ned))
            leg["texts"] = [t for _, _, t in o.texts[n_texts:]]
            legs.append(leg)
            say(f"setpoint {leg}")
        tr["setpoints"] = legs
        # -- AUTO.LAND; the stream stops
        o.events.clear()
        t0 = o.sim_now()
        land = o.set_px4_mode(AUTO_LAND)
        o.stream = None
        land_hb = _hb_summary(o.fresh_heartbeat())
        vz: list[float] = []

        def disarmed() -> bool:
            m = o.last["LOCAL_POSITION_NED"]
            if m.z - ground[2] < -1.0:
                vz.append(float(m.vz))
            return not o.heartbeat().base_mode & 128

        o.wait(disarmed, 120.0, "disarm on landing")
        t_disarm = o.sim_now()
        o.idle(3.0)
        after = _hb_summary(o.fresh_heartbeat())
        tr["land"] = {
            "ack": land["ack"], "heartbeat": land_hb,
            "descent_rate_median_mps": round(statistics.median(vz), 2) if vz else None,
            "disarmed_after_s": round(t_disarm - t0, 1),
            "landed_states": [e["landed_state"] for e in o.events if e["event"] == "landed_state"],
            "texts": [e["text"] for e in o.events if e["event"] == "text"],
            "heartbeat_after": after,
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
#: Distance (m) within which two vehicles' final positions of a setpoint leg agree (PX4's EKF
#: is 0.5-1.3 m off in height; fimnav's vehicle reports its exact state).
POSITION_TOL_M = 1.5


def _get(tr: dict[str, Any], path: str) -> Any:
    v: Any = tr
    for part in path.split("."):
        v = v.get(part) if isinstance(v, dict) else None
    return v


#: Values a ground station or the planner reads, compared exactly (dotted paths).
EXACT = (
    "heartbeat.autopilot", "heartbeat.type", "heartbeat.compid", "heartbeat.flavour", "heartbeat.mavlink_version",
    "before_ready.arm.ack", "before_ready.request_origin.ack",
    "frames.origin_is_home_latlon",
    "refusals.unsupported_command.ack", "refusals.unknown_mode.ack", "refusals.offboard_without_stream.ack",
    "refusals.land_mode_disarmed.ack", "refusals.land_mode_disarmed.custom_mode_after", "refusals.arm_in_land.ack",
    "refusals.posctl_again.ack",
    "offboard.mode_ack", "offboard.mode_after", "offboard.arm_ack", "offboard.landed_states",
    "offboard.heartbeat_in_air.base_mode", "offboard.heartbeat_in_air.custom_mode", "offboard.heartbeat_in_air.system_status",
    "offboard.takeoff_in_air.ack", "offboard.mode_after_takeoff_cmd",
    "land.ack", "land.heartbeat.base_mode", "land.heartbeat.custom_mode", "land.heartbeat.system_status", "land.landed_states",
    "land.heartbeat_after.base_mode", "land.heartbeat_after.custom_mode", "land.heartbeat_after.system_status",
)


def compare(ref: dict[str, Any], got: dict[str, Any]) -> list[str]:
    """Differences of ``got`` from the PX4 transcript ``ref`` on every point a planner or a
    ground station could trip on (empty: they answer alike). Times, STATUSTEXT wording, the
    EKF's noise and the messages fimnav does not simulate are not compared (docs/vehicle_sim.md,
    "Known differences from PX4 SITL")."""
    diffs: list[str] = []
    for path in EXACT:
        a, b = _get(ref, path), _get(got, path)
        if a != b:
            diffs.append(f"{path}: PX4 {a!r}, vehicle {b!r}")
    for mid, result in ref["set_message_interval"]["acks"].items():
        if got["set_message_interval"]["acks"].get(mid) != result:
            diffs.append(f"set_message_interval.acks[{mid}]: PX4 {result}, vehicle {got['set_message_interval']['acks'].get(mid)}")
    r, g = ref["set_message_interval"]["rates_hz"], got["set_message_interval"]["rates_hz"]
    for name in PLANNER_TYPES:
        if name in ("HOME_POSITION", "GLOBAL_POSITION_INT") or name not in r:
            continue  # sent once home / the EKF position exist
        a, b = r.get(name, 0.0), g.get(name, 0.0)
        if abs(b - a) > RATE_REL * a + RATE_ABS:
            diffs.append(f"set_message_interval.rates_hz[{name}]: PX4 {a}, vehicle {b}")
    for key in ("before_ready.arm.texts", "refusals.arm_in_land.texts"):
        if bool(_get(ref, key)) != bool(_get(got, key)):
            diffs.append(f"{key}: PX4 {_get(ref, key)!r}, vehicle {_get(got, key)!r}")
    if abs(ref["offboard"]["final_relative_alt_m"] - got["offboard"]["final_relative_alt_m"]) > POSITION_TOL_M:
        diffs.append(f"offboard.final_relative_alt_m: PX4 {ref['offboard']['final_relative_alt_m']}, vehicle {got['offboard']['final_relative_alt_m']}")
    for rl, gl in zip(ref["setpoints"], got["setpoints"], strict=True):
        for k in ("reached", "mode"):
            if rl[k] != gl[k]:
                diffs.append(f"setpoints[{rl['name']}].{k}: PX4 {rl[k]!r}, vehicle {gl[k]!r}")
        if math.dist(rl["final_local_ned"], gl["final_local_ned"]) > POSITION_TOL_M:
            diffs.append(f"setpoints[{rl['name']}].final_local_ned: PX4 {rl['final_local_ned']}, vehicle {gl['final_local_ned']}")
        for k in ("relative_alt_m", "alt_minus_home_alt_m"):
            if abs(rl[k] - gl[k]) > POSITION_TOL_M:
                diffs.append(f"setpoints[{rl['name']}].{k}: PX4 {rl[k]}, vehicle {gl[k]}")
    return diffs
