"""The planner's MAVLink link to its own autopilot (vehicle_sim, ArduPilot or PX4).

A thin, typed layer over pymavlink's ``mavutil`` connection: wait for the heartbeat, request
streams, switch modes, arm, take off, stream position + velocity setpoints, and read the
vehicle's position with its timestamp. Frames: the mission frame is ENU about the mission
origin; MAVLink LOCAL_NED is north-east-down about the vehicle's EKF origin, which for a
simulated vehicle of the mission is the mission origin. Conversion (x_E, y_N, z_U) ↔
(n, e, d) = (y, x, −z) happens here, at the MAVLink edge, and nowhere else.

Every wait has a deadline and says what it was waiting for when it expires
(:class:`LinkTimeout`); nothing sleeps a fixed time.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import numpy as np

from planner.errors import FimnavError

#: Our MAVLink identity: a companion computer of the vehicle's system.
COMPONENT_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
AUTOPILOT_COMPONENT = 1
ARDUPILOT_GUIDED = 4
ARDUPILOT_MODES = {"STABILIZE": 0, "ALT_HOLD": 2, "AUTO": 3, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9, "POSHOLD": 16, "BRAKE": 17}
#: PX4 custom modes (main_mode << 16 | sub_mode << 24).
PX4_MODES = {"POSCTL": 3 << 16, "OFFBOARD": 6 << 16, "AUTO.LOITER": (4 << 16) | (3 << 24), "AUTO.RTL": (4 << 16) | (5 << 24), "AUTO.LAND": (4 << 16) | (6 << 24), "AUTO.TAKEOFF": (4 << 16) | (2 << 24)}
MAV_AUTOPILOT_PX4 = 12
#: SET_POSITION_TARGET type masks (ignore acceleration and yaw / yaw rate).
MASK_POSITION_VELOCITY = 0b0000_1100_0000_0000 | 0b0000_0001_1100_0000  # use pos + vel
MASK_POSITION = MASK_POSITION_VELOCITY | 0b0000_0000_0011_1000
MASK_VELOCITY = MASK_POSITION_VELOCITY | 0b0000_0000_0000_0111


#: Deadline (s) for the heartbeat that confirms a mode change or arming (heartbeats are 1 Hz;
#: a loaded machine starting dozens of processes can delay them by seconds).
MODE_CONFIRM_TIMEOUT_S: float = 30.0


class LinkError(FimnavError):
    """The vehicle refused a command or the link failed."""


class LinkTimeout(LinkError):
    """A wait on the vehicle expired."""


def mavutil_module() -> Any:
    """pymavlink's mavutil with MAVLink 2 and the ardupilotmega dialect."""
    os.environ["MAVLINK20"] = "1"
    os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")
    from pymavlink import mavutil

    return mavutil


def enu_to_ned(v: Iterable[float]) -> tuple[float, float, float]:
    """(x east, y north, z up) → (north, east, down)."""
    x, y, z = v
    return float(y), float(x), float(-z)


def ned_to_enu(n: float, e: float, d: float) -> np.ndarray:
    """(north, east, down) → (x east, y north, z up)."""
    return np.array([e, n, -d], dtype=float)


@dataclass
class Telemetry:
    """What the link has heard of the vehicle (updated by :meth:`VehicleLink.pump`)."""

    heartbeat_wall_s: float = -math.inf
    autopilot: int | None = None
    custom_mode: int | None = None
    armed: bool = False
    position_enu_m: np.ndarray | None = None
    velocity_enu_mps: np.ndarray | None = None
    position_time_ms: int = -1
    home_known: bool = False


class VehicleLink:
    """MAVLink connection of one planner to one autopilot.

    Args:
        connection: pymavlink connection string (``udpout:127.0.0.1:14550``, ``tcp:...``,
            ``/dev/ttyUSB0,57600``).
        target_system: the vehicle's system id.
        source_system: our system id (default: the vehicle's, as a companion computer).
        signing_key: 32-byte MAVLink 2 signing key, or None.
        wall: monotonic clock (seconds), injectable for tests.
    """

    def __init__(
        self,
        connection: str,
        target_system: int,
        source_system: int | None = None,
        signing_key: bytes | None = None,
        wall: Callable[[], float] = time.monotonic,
    ) -> None:
        self.mavutil = mavutil_module()
        self.target_system = target_system
        self.wall = wall
        try:
            self.conn = self.mavutil.mavlink_connection(
                connection,
                source_system=source_system if source_system is not None else target_system,
                source_component=COMPONENT_ID,
                dialect="ardupilotmega",
            )
        except Exception as exc:  # pymavlink raises bare OSError/ValueError/SerialException
            raise LinkError(f"cannot open MAVLink connection {connection!r}: {exc}") from None
        self.mav = self.conn.mav
        if signing_key is not None:
            if len(signing_key) != 32:
                raise LinkError(f"signing key: expected 32 bytes, found {len(signing_key)}")
            self.conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=lambda *_: False)
        self.telemetry = Telemetry()
        self._last_gcs_heartbeat = -math.inf
        self.acks: dict[int, int] = {}
        self.statustexts: list[str] = []

    # -- receiving --------------------------------------------------------------------------
    def pump(self, timeout_s: float = 0.0) -> int:
        """Read every pending message (waiting up to ``timeout_s`` for the first); return how
        many were for us. Sends our own 1 Hz heartbeat as a side effect."""
        self._heartbeat_out()
        n = 0
        deadline = self.wall() + timeout_s
        while True:
            remaining = deadline - self.wall()
            msg = self.conn.recv_match(blocking=remaining > 0 and n == 0, timeout=max(remaining, 0.0))
            if msg is None:
                return n
            if self._handle(msg):
                n += 1

    def _handle(self, msg: Any) -> bool:
        if msg.get_srcSystem() != self.target_system:
            return False
        kind = msg.get_type()
        tel = self.telemetry
        if kind == "HEARTBEAT" and msg.get_srcComponent() == AUTOPILOT_COMPONENT:
            tel.heartbeat_wall_s = self.wall()
            tel.autopilot = msg.autopilot
            tel.custom_mode = msg.custom_mode
            tel.armed = bool(msg.base_mode & 128)
        elif kind == "LOCAL_POSITION_NED":
            if msg.time_boot_ms >= tel.position_time_ms:
                tel.position_time_ms = msg.time_boot_ms
                tel.position_enu_m = ned_to_enu(msg.x, msg.y, msg.z)
                tel.velocity_enu_mps = ned_to_enu(msg.vx, msg.vy, msg.vz)
        elif kind == "HOME_POSITION":
            tel.home_known = True
        elif kind == "COMMAND_ACK":
            self.acks[msg.command] = msg.result
        elif kind == "STATUSTEXT":
            self.statustexts.append(msg.text)
        return True

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Pump messages until ``predicate()`` holds; :class:`LinkTimeout` naming ``what``."""
        deadline = self.wall() + timeout_s
        while not predicate():
            remaining = deadline - self.wall()
            if remaining <= 0:
                raise LinkTimeout(f"vehicle {self.target_system}: no {what} within {timeout_s:g} s")
            self.pump(min(remaining, 0.05))

    def wait_heartbeat(self, timeout_s: float = 10.0) -> None:
        """Wait for the autopilot's heartbeat."""
        start = self.telemetry.heartbeat_wall_s
        self.wait_for(lambda: self.telemetry.heartbeat_wall_s > start, timeout_s, "heartbeat")

    def fileno(self) -> int | None:
        """The file descriptor to select() on for incoming MAVLink, if the transport has one."""
        fd = getattr(self.conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def link_age_s(self) -> float:
        """Seconds since the last autopilot heartbeat."""
        return self.wall() - self.telemetry.heartbeat_wall_s

    @property
    def is_px4(self) -> bool:
        return self.telemetry.autopilot == MAV_AUTOPILOT_PX4

    # -- sending ----------------------------------------------------------------------------
    def _heartbeat_out(self) -> None:
        now = self.wall()
        if now - self._last_gcs_heartbeat >= 1.0:
            self._last_gcs_heartbeat = now
            m = self.mavutil.mavlink
            self.mav.heartbeat_send(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE)

    def command(
        self,
        command: int,
        params: Iterable[float] = (),
        timeout_s: float = 15.0,
        what: str = "",
        retries: int = 3,
        done_already: Callable[[], bool] | None = None,
    ) -> int:
        """Send COMMAND_LONG and wait for its COMMAND_ACK; return the result code.

        A command whose acknowledgement is late is sent again (confirmation field counting
        up). For a command that is not idempotent, ``done_already`` tells whether an earlier
        attempt took effect: a refusal on a retry is then a success (e.g. a second take-off
        refused because the first one is climbing).

        Raises :class:`LinkError` if the vehicle refuses it (result other than ACCEPTED or
        IN_PROGRESS), naming the command and the vehicle's STATUSTEXT reason if any.
        """
        p = list(params) + [0.0] * (7 - len(list(params)))
        label = what or f"command {command}"
        per_try = timeout_s / max(retries, 1)
        for attempt in range(max(retries, 1)):
            self.acks.pop(command, None)
            texts_before = len(self.statustexts)
            self.mav.command_long_send(self.target_system, AUTOPILOT_COMPONENT, command, attempt, *p[:7])
            try:
                self.wait_for(lambda: command in self.acks, per_try, f"acknowledgement of {label}")
            except LinkTimeout:
                continue
            result = self.acks[command]
            m = self.mavutil.mavlink
            if result in (m.MAV_RESULT_ACCEPTED, m.MAV_RESULT_IN_PROGRESS):
                return result
            if attempt > 0 and done_already is not None and done_already():
                return m.MAV_RESULT_ACCEPTED
            reason = "; ".join(self.statustexts[texts_before:]) or "no reason given"
            name = m.enums["MAV_RESULT"][result].name if result in m.enums["MAV_RESULT"] else str(result)
            raise LinkError(f"vehicle {self.target_system} refused {label}: {name} ({reason})")
        raise LinkTimeout(f"vehicle {self.target_system}: no acknowledgement of {label} after {retries} tries in {timeout_s:g} s")

    def request_interval(self, message_id: int, rate_hz: float) -> None:
        """SET_MESSAGE_INTERVAL for one message."""
        m = self.mavutil.mavlink
        self.command(m.MAV_CMD_SET_MESSAGE_INTERVAL, [message_id, 1e6 / rate_hz], what=f"SET_MESSAGE_INTERVAL({message_id})")

    def set_mode(self, name: str) -> None:
        """Switch flight mode by name (ArduPilot copter or PX4 names) and wait to see it."""
        m = self.mavutil.mavlink
        table = PX4_MODES if self.is_px4 else ARDUPILOT_MODES
        if name not in table:
            raise LinkError(f"unknown {'PX4' if self.is_px4 else 'ArduPilot'} mode {name!r}; known: {sorted(table)}")
        custom = table[name]
        if self.is_px4:
            params = [m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, (custom >> 16) & 0xFF, (custom >> 24) & 0xFF]
        else:
            params = [m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom]
        self.command(m.MAV_CMD_DO_SET_MODE, params, what=f"mode {name}", done_already=lambda: self.telemetry.custom_mode == custom)
        self.wait_for(lambda: self.telemetry.custom_mode == custom, MODE_CONFIRM_TIMEOUT_S, f"heartbeat in mode {name}")

    def arm(self) -> None:
        """Arm and wait until the heartbeat says armed."""
        m = self.mavutil.mavlink
        self.command(m.MAV_CMD_COMPONENT_ARM_DISARM, [1], what="arm", done_already=lambda: self.telemetry.armed)
        self.wait_for(lambda: self.telemetry.armed, MODE_CONFIRM_TIMEOUT_S, "armed heartbeat")

    def takeoff(self, altitude_m: float) -> None:
        """MAV_CMD_NAV_TAKEOFF to ``altitude_m`` above home (acknowledged, not awaited)."""
        m = self.mavutil.mavlink
        start = self.telemetry.position_enu_m
        z0 = float(start[2]) if start is not None else 0.0

        def climbing() -> bool:
            pos = self.telemetry.position_enu_m
            return pos is not None and float(pos[2]) > z0 + 0.01

        self.command(m.MAV_CMD_NAV_TAKEOFF, [0, 0, 0, 0, 0, 0, altitude_m], what=f"takeoff to {altitude_m:g} m", done_already=climbing)

    def send_setpoint(self, position_enu_m: Iterable[float] | None, velocity_enu_mps: Iterable[float] | None) -> None:
        """SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED) with position and/or velocity."""
        m = self.mavutil.mavlink
        if position_enu_m is None and velocity_enu_mps is None:
            raise ValueError("a setpoint needs a position or a velocity")
        mask = MASK_POSITION_VELOCITY if position_enu_m is not None and velocity_enu_mps is not None else (MASK_POSITION if velocity_enu_mps is None else MASK_VELOCITY)
        n, e, d = enu_to_ned(position_enu_m) if position_enu_m is not None else (0.0, 0.0, 0.0)
        vn, ve, vd = enu_to_ned(velocity_enu_mps) if velocity_enu_mps is not None else (0.0, 0.0, 0.0)
        self.mav.set_position_target_local_ned_send(
            0, self.target_system, AUTOPILOT_COMPONENT, m.MAV_FRAME_LOCAL_NED, mask, n, e, d, vn, ve, vd, 0, 0, 0, 0, 0
        )

    def close(self) -> None:
        try:
            self.conn.close()
        except OSError:
            pass
