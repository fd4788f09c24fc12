"""The mission and file protocols of a simulated vehicle: an always empty mission (uploads
refused), ArduPilot's guided "fly to" MISSION_ITEM, and MAVLink FTP answered "no file"."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from vehicle_sim.flight_state import FlightState
from vehicle_sim.frames import VehicleFrames
from vehicle_sim.outbox import Outbox
from vehicle_sim.setpoints import GuidedSetpoints


class MissionProtocol:
    """Answers the mission protocol and MAVLink FTP.

    Args:
        state: the flight state. outbox: the sending side. frames: the vehicle's frames.
        setpoints: the guided setpoints (a guided MISSION_ITEM is a reposition).
    """

    def __init__(self, state: FlightState, outbox: Outbox, frames: VehicleFrames, setpoints: GuidedSetpoints) -> None:
        self.state = state
        self.outbox = outbox
        self.frames = frames
        self.setpoints = setpoints
        self.mavlink = outbox.mavlink

    def _mission_ack(self, msg: Any, result: int) -> None:
        self.outbox.send(self.mavlink.MAVLink_mission_ack_message(msg.get_srcSystem(), msg.get_srcComponent(), result, msg.mission_type))

    def on_mission_item_int(self, msg: Any) -> None:
        """MISSION_ITEM_INT (lat/lon 1e-7 deg), see :meth:`on_mission_item`."""
        self._mission_item(msg, msg.x * 1e-7, msg.y * 1e-7)

    def on_mission_item(self, msg: Any) -> None:
        """MISSION_ITEM: with ``current = 2`` and NAV_WAYPOINT, ArduPilot's guided "fly to";
        anything else is UNSUPPORTED (the mission stays empty)."""
        self._mission_item(msg, msg.x, msg.y)

    def _mission_item(self, msg: Any, lat: float, lon: float) -> None:
        m = self.mavlink
        result = m.MAV_MISSION_UNSUPPORTED
        if msg.current == 2 and msg.command == m.MAV_CMD_NAV_WAYPOINT:  # ArduPilot guided "fly to"
            if math.isfinite(lat) and math.isfinite(lon) and math.isfinite(msg.z) and abs(lat) < 90 and abs(lon) <= 180:
                x, y = self.frames.horizontal_enu(lat, lon)
                z = self.frames.alt_to_z(float(msg.z), msg.frame, amsl_default=False)
                ok = self.state.flying and self.setpoints.apply_guided(np.array([x, y, z]), None, source="reposition")
                result = m.MAV_MISSION_ACCEPTED if ok else m.MAV_MISSION_ERROR
            else:
                result = m.MAV_MISSION_INVALID
        self._mission_ack(msg, result)

    def on_mission_request_list(self, msg: Any) -> None:
        """MISSION_REQUEST_LIST: the mission has no items."""
        self.outbox.send(self.mavlink.MAVLink_mission_count_message(msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type))

    def on_mission_request(self, msg: Any) -> None:
        """MISSION_REQUEST(_INT): there is no item to send."""
        self._mission_ack(msg, self.mavlink.MAV_MISSION_INVALID_SEQUENCE)

    def on_mission_count(self, msg: Any) -> None:
        """MISSION_COUNT: an empty upload is accepted, any other refused."""
        m = self.mavlink
        self._mission_ack(msg, m.MAV_MISSION_ACCEPTED if msg.count == 0 else m.MAV_MISSION_UNSUPPORTED)

    def on_mission_clear_all(self, msg: Any) -> None:
        """MISSION_CLEAR_ALL: accepted (the mission is empty)."""
        self._mission_ack(msg, self.mavlink.MAV_MISSION_ACCEPTED)

    def on_file_transfer_protocol(self, msg: Any) -> None:
        """No file system: answer every FTP request at once so ground stations (MAVProxy's
        parameter download) fall back to the parameter protocol instead of timing out.
        Session resets are ACKed; opens/listings get NAK FileNotFound (10); the rest NAK
        UnknownCommand (7)."""
        req = bytes(msg.payload)
        if len(req) < 12:
            return
        seq, session, opcode = int.from_bytes(req[0:2], "little"), req[2], req[3]
        if opcode in (1, 2):  # TerminateSession, ResetSessions
            reply_op, size, data = 128, 0, b""
        else:
            reply_op, size = 129, 1
            data = bytes([10 if opcode in (3, 4, 6, 11, 14) else 7])
        body = ((seq + 1) & 0xFFFF).to_bytes(2, "little") + bytes([session, reply_op, size, opcode, 0, 0])
        body += bytes(4) + data
        payload = list(body + bytes(251 - len(body)))
        self.outbox.send(self.mavlink.MAVLink_file_transfer_protocol_message(0, msg.get_srcSystem(), msg.get_srcComponent(), payload))
