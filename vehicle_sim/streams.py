"""Telemetry scheduling of a simulated vehicle: message intervals (SET_MESSAGE_INTERVAL,
REQUEST_DATA_STREAM), one-off requests (REQUEST_MESSAGE), and what is due at each sim time."""

from __future__ import annotations

import math
from typing import Any

from comms.autopilot import FlavourInfo
from vehicle_sim.config import VehicleConfig
from vehicle_sim.flight_state import FlightState
from vehicle_sim.link import PROTOCOL_VERSION_ID
from vehicle_sim.outbox import Outbox
from vehicle_sim.readiness import Readiness
from vehicle_sim.telemetry import TelemetryEncoder

# REQUEST_DATA_STREAM groups (ArduPilot's assignment of our messages).
#: As ArduCopter 4.5's STREAM_*_msgs (GCS_Mavlink.cpp); EXTENDED_SYS_STATE and HOME_POSITION
#: are in no stream there (SET_MESSAGE_INTERVAL / REQUEST_MESSAGE only): here they keep their rate.
DATA_STREAMS: dict[int, tuple[str, ...]] = {
    2: ("SYS_STATUS", "GPS_RAW_INT"),  # EXTENDED_STATUS
    6: ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED"),  # POSITION
    10: ("ATTITUDE",),  # EXTRA1
    11: ("VFR_HUD",),  # EXTRA2
    12: ("SYSTEM_TIME", "BATTERY_STATUS", "EKF_STATUS_REPORT"),  # EXTRA3
}


class TelemetryStreams:
    """Which telemetry is sent when.

    Args:
        config: the vehicle configuration (default rates, physics step). info: the profile.
        state: the flight state. outbox: the sending side. readiness: the start-up stage
            (what can be sent yet). encoder: the message encoders.

    Attributes:
        defaults: default interval of each stream (sim s; None = off).
        intervals: current interval of each stream (sim s; None = off).
    """

    def __init__(
        self, config: VehicleConfig, info: FlavourInfo, state: FlightState, outbox: Outbox, readiness: Readiness, encoder: TelemetryEncoder
    ) -> None:
        self.config = config
        self.info = info
        self.state = state
        self.outbox = outbox
        self.readiness = readiness
        self.encoder = encoder
        self.mavlink = outbox.mavlink
        self.physics_dt_s = 1.0 / config.physics_hz
        self.defaults: dict[str, float | None] = {}
        for name, hz in config.rates_hz:
            self.defaults[name] = 1.0 / hz if hz > 0 else None
        if info.ekf_status_report:
            self.defaults["EKF_STATUS_REPORT"] = 1.0 / config.ekf_status_hz if config.ekf_status_hz > 0 else None
        self.intervals: dict[str, float | None] = dict(self.defaults)
        self._due_s: dict[str, float] = dict.fromkeys(self.intervals, 0.0)

    def heartbeat(self) -> None:
        """Send one HEARTBEAT (nothing while unhealthy)."""
        if self.state.healthy:
            self.outbox.send(self.encoder.msg_heartbeat())

    def emit_due(self, *, report_position: bool = False) -> None:
        """Send every telemetry message whose interval has elapsed (sim time).

        A lockstep tick report (``report_position``) starts with a HEARTBEAT when the mode or
        the armed state changed since the last one: the 1 Hz wall-clock heartbeat spans many
        lockstep steps, and a planner must see a pilot's take-over (a ground station switching
        the mode between two ticks) with the position of the next tick, before it commands."""
        s = self.state
        t = s.t_s
        if report_position and s.healthy and self.encoder.heartbeat_state not in (None, (s.mode.custom_mode, s.armed)):
            self.heartbeat()
        forced = ("GLOBAL_POSITION_INT", "LOCAL_POSITION_NED") if report_position else ()
        for name, iv in self.intervals.items():
            if iv is None:
                continue
            due = self._due_s[name]
            if t + 1e-9 >= due or name in forced:
                if self.readiness.available(name):
                    self.outbox.send(self.encoder.builder(name)())
                nxt = due + iv
                self._due_s[name] = nxt if nxt > t else t + iv

    def next_due_s(self) -> float:
        """Earliest sim time (s) at which a telemetry message is due."""
        due = [self._due_s[n] for n, iv in self.intervals.items() if iv is not None]
        return min(due) if due else self.state.t_s + 1.0

    def announce_ready(self) -> None:
        """GPS fix, EKF position, home and origin set: report them at once, position first
        (a planner that sees home and origin then already has a valid position), then
        HOME_POSITION and GPS_GLOBAL_ORIGIN (ArduPilot's AP_AHRS::set_home sends both)."""
        names = ["GPS_RAW_INT", "GLOBAL_POSITION_INT", "LOCAL_POSITION_NED", "SYS_STATUS"]
        if "EKF_STATUS_REPORT" in self.defaults:
            names.append("EKF_STATUS_REPORT")
        for name in names:
            self.outbox.send(self.encoder.builder(name)())
        for text in self.info.ready_texts:
            self.outbox.statustext(6, text)
        self.outbox.send(self.encoder.msg_home_position())
        self.outbox.send(self.encoder.msg_gps_global_origin())

    def stream_name(self, msg_id: float) -> str | None:
        """The streamed message with MAVLink id ``msg_id``, or None."""
        if not math.isfinite(msg_id):
            return None
        cls = self.mavlink.mavlink_map.get(int(msg_id))
        if cls is None:
            return None
        name = cls.msgname
        return name if name in self.defaults else None

    def cmd_set_interval(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        """MAV_CMD_SET_MESSAGE_INTERVAL: param1 message id, param2 interval (µs; 0 default,
        -1 off), never faster than the physics rate."""
        m = self.mavlink
        cmd = m.MAV_CMD_SET_MESSAGE_INTERVAL
        name = self.stream_name(p[0])
        if name is None:
            # PX4 (1.15) answers FAILED for a message it has no stream for (EKF_STATUS_REPORT).
            return self.outbox.ack(msg, cmd, self.info.unknown_interval_result, f"Interval: cannot stream msg {p[0]:g}")
        us = p[1]
        if not math.isfinite(us) or (us < 0 and us != -1):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, "Interval: bad interval")
        if us == -1:
            self.intervals[name] = None
        elif us == 0:
            self.intervals[name] = self.defaults[name]
        else:
            self.intervals[name] = max(us * 1e-6, self.physics_dt_s)
        self._due_s[name] = self.state.t_s
        return self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)

    def cmd_get_interval(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        """MAV_CMD_GET_MESSAGE_INTERVAL: ACCEPTED, then MESSAGE_INTERVAL (µs, -1 off)."""
        m = self.mavlink
        name = self.stream_name(p[0])
        if name is None:
            return self.outbox.ack(msg, m.MAV_CMD_GET_MESSAGE_INTERVAL, m.MAV_RESULT_DENIED)
        iv = self.intervals[name]
        self.outbox.ack(msg, m.MAV_CMD_GET_MESSAGE_INTERVAL, m.MAV_RESULT_ACCEPTED)
        self.outbox.send(m.MAVLink_message_interval_message(int(p[0]), -1 if iv is None else int(round(iv * 1e6))))
        return int(m.MAV_RESULT_ACCEPTED)

    def cmd_request_message(self, msg: Any, p: tuple[float, ...], _f: int | None) -> int:
        """MAV_CMD_REQUEST_MESSAGE: param1 message id; ACCEPTED, then the message once."""
        m = self.mavlink
        cmd = m.MAV_CMD_REQUEST_MESSAGE
        if not math.isfinite(p[0]):
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED)
        mid = int(p[0])
        enc = self.encoder
        builders = {
            m.MAVLINK_MSG_ID_AUTOPILOT_VERSION: enc.msg_autopilot_version,
            PROTOCOL_VERSION_ID: enc.msg_protocol_version,
            m.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: enc.msg_gps_global_origin,
            m.MAVLINK_MSG_ID_HEARTBEAT: enc.msg_heartbeat,
        }
        name = self.stream_name(mid)
        builder = builders.get(mid) or (enc.builder(name) if name else None)
        if builder is None:
            return self.outbox.ack(msg, cmd, m.MAV_RESULT_DENIED, f"Request: message {mid} not available")
        cls = m.mavlink_map.get(mid)
        if cls is not None and not self.readiness.available(cls.msgname):
            # Not available yet (no home, no origin): ArduPilot accepts the request and its
            # sender sends nothing; PX4's stream cannot send and the request is DENIED.
            return self.outbox.ack(msg, cmd, self.info.unavailable_request_result)
        self.outbox.ack(msg, cmd, m.MAV_RESULT_ACCEPTED)
        self.outbox.send(builder())
        return int(m.MAV_RESULT_ACCEPTED)

    def on_request_data_stream(self, msg: Any) -> None:
        """REQUEST_DATA_STREAM: start (at a rate) or stop a group of streams (0: all)."""
        sid = msg.req_stream_id
        names: tuple[str, ...] = tuple(n for group in DATA_STREAMS.values() for n in group) if sid == 0 else DATA_STREAMS.get(sid, ())
        for name in names:
            if name not in self.intervals:
                continue
            if msg.start_stop == 0 or msg.req_message_rate == 0:
                self.intervals[name] = None
            else:
                self.intervals[name] = max(1.0 / msg.req_message_rate, self.physics_dt_s)
                self._due_s[name] = self.state.t_s

    def on_timesync(self, msg: Any) -> None:
        """TIMESYNC request (tc1 = 0): answered with the sim time (ns)."""
        if msg.tc1 == 0:
            now_ns = int(round(self.state.t_s * 1e9))
            self.outbox.send(self.mavlink.MAVLink_timesync_message(now_ns, msg.ts1))
