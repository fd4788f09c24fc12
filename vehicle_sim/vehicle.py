"""One simulated MAVLink vehicle: the composition of its protocol handlers, mode machine,
failsafes, telemetry and physics.

The vehicle owns no thread and no clock. Its driver (:class:`vehicle_sim.host.VehicleHost` or
a test) calls:

* :meth:`SimVehicle.advance_to` ``(t_s)``: drain pending MAVLink input, integrate the physics
  up to sim time ``t_s`` at the fixed physics rate, then send the telemetry that is due,
  stamped with sim time (``time_boot_ms`` = sim ms since boot);
* :meth:`SimVehicle.heartbeat` once per wall second (stops when :attr:`healthy` is False).

The collaborators, each in its own module: :class:`~vehicle_sim.flight_state.FlightState`
(the shared flight state), :class:`~vehicle_sim.outbox.Outbox` (STATUSTEXT, COMMAND_ACK),
:class:`~vehicle_sim.geofence.FenceGuard`, :class:`~vehicle_sim.frames.VehicleFrames`,
:class:`~vehicle_sim.readiness.Readiness` and :class:`~vehicle_sim.readiness.ArmingChecks`,
:class:`~vehicle_sim.setpoints.GuidedSetpoints`, :class:`~vehicle_sim.modes.ModeMachine`,
:class:`~vehicle_sim.failsafe.Failsafes`, :class:`~vehicle_sim.telemetry.TelemetryEncoder`,
:class:`~vehicle_sim.streams.TelemetryStreams`, :class:`~vehicle_sim.params.ParameterTable`,
:class:`~vehicle_sim.commands.CommandHandler` and
:class:`~vehicle_sim.mission_protocol.MissionProtocol`. The autopilot's own facts (modes,
numbers, identity, readiness signals) come from its profile, :mod:`comms.autopilot`.

Frames: physics, fence and home live in the mission ENU frame (see :mod:`vehicle_sim.frames`);
LOCAL_NED is NED about the EKF origin (the mission origin until SET_GPS_GLOBAL_ORIGIN moves it).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from comms.autopilot import FlavourInfo, Mode, flavour_info
from planner.geometry import vec3
from vehicle_sim.commands import CommandHandler
from vehicle_sim.config import Origin, VehicleConfig
from vehicle_sim.dynamics import FloatArray, PointMass
from vehicle_sim.failsafe import Failsafes
from vehicle_sim.flight_state import FlightState
from vehicle_sim.frames import VehicleFrames
from vehicle_sim.geofence import FenceGuard
from vehicle_sim.link import MavlinkLink
from vehicle_sim.mission_protocol import MissionProtocol
from vehicle_sim.modes import ModeMachine
from vehicle_sim.outbox import Outbox
from vehicle_sim.params import ParameterTable
from vehicle_sim.payload import Measurement, Payload
from vehicle_sim.readiness import STAGES, ArmingChecks, Readiness
from vehicle_sim.setpoints import GuidedSetpoints
from vehicle_sim.streams import TelemetryStreams
from vehicle_sim.telemetry import TelemetryEncoder

log = logging.getLogger(__name__)

__all__ = ["STAGES", "SimVehicle", "VehicleState"]


@dataclass(frozen=True)
class VehicleState:
    """Snapshot of what a test or a supervisor may check (true values, ENU frame).

    Attributes:
        t_s: sim time (s). armed, mode (custom_mode), mode_name, landed_state (MAV_LANDED_STATE_*).
        position_enu_m, velocity_enu_mps: true state (3,) each.
        params: every parameter value. intervals_s: telemetry intervals (None = off).
        origin: EKF origin. fence_enabled: fence on.
        stage: start-up stage (``"init"``, ``"aligned"``, ``"ready"``, see :data:`STAGES`).
        gcs_failsafe: the ArduPilot GCS failsafe is active.
    """

    t_s: float
    armed: bool
    mode: int
    mode_name: str
    landed_state: int
    position_enu_m: tuple[float, float, float]
    velocity_enu_mps: tuple[float, float, float]
    params: tuple[tuple[str, float], ...]
    intervals_s: tuple[tuple[str, float | None], ...]
    origin: Origin
    fence_enabled: bool
    stage: str = "ready"
    gcs_failsafe: bool = False


def _boot_flight_state(config: VehicleConfig, info: FlavourInfo, mavlink: Any) -> FlightState:
    """The flight state at boot: on the ground below ``start_enu_m`` (disarmed, boot mode),
    or airborne at it (armed, holding, in the flavour's airborne boot mode)."""
    start = np.array(config.start_enu_m, dtype=float)
    home = np.array([start[0], start[1], config.ground_z_m])
    if not config.airborne:
        start[2] = config.ground_z_m
    pm = PointMass(
        start,
        config.limits,
        config.profile,
        lag_s=config.lag_s,
        wind_enu_mps=np.array(config.wind_enu_mps),
        drag_per_s=config.drag_per_s,
        ground_z_m=config.ground_z_m,
    )
    state = FlightState(
        pm=pm,
        home=home,
        mode=info.require_mode(info.air_boot_mode if config.airborne else info.boot_mode),
        armed=bool(config.airborne),
        flying=bool(config.airborne),
        landed_state=mavlink.MAV_LANDED_STATE_IN_AIR if config.airborne else mavlink.MAV_LANDED_STATE_ON_GROUND,
    )
    if config.airborne:
        state.hold_here()
    return state


class SimVehicle:
    """A simulated ArduPilot-copter or PX4 vehicle behind one MAVLink link.

    Args:
        config: the vehicle configuration.
        link: the MAVLink endpoint (sockets, parser, encoder, .tlog).
        wall: wall clock (s) used only for STATUSTEXT rate limiting and SYSTEM_TIME.
        payload: the simulated RSS payload (:meth:`measure`), or None.

    Raises:
        ValueError: a boot parameter (``config.params``) the vehicle refuses.
    """

    def __init__(
        self,
        config: VehicleConfig,
        link: MavlinkLink,
        wall: Callable[[], float] = time.time,
        payload: Payload | None = None,
    ) -> None:
        self.config = config
        self.payload = payload
        self.link = link
        self.mavlink = m = link.mavlink
        self.sysid = config.sysid
        self.info: FlavourInfo = flavour_info(config.flavour)
        self.physics_dt_s = 1.0 / config.physics_hz
        self.physics_steps = 0  # physics grid index: the last grid point reached is n*dt
        self.flight = _boot_flight_state(config, self.info, m)
        self.outbox = Outbox(link, config.sysid, wall)
        self.geofence = FenceGuard(config.geofence, self.flight.home)
        self.frames = VehicleFrames(config.origin, self.flight.home, config.ground_z_m, m)
        self.readiness = Readiness(self.info, config.ready_after_s, self.outbox)
        self.setpoints = GuidedSetpoints(config, self.info, self.flight, self.outbox, self.geofence, self.frames)
        self.arming = ArmingChecks(self.info, self.flight, self.readiness, self.geofence, self.setpoints.offboard_stream_ok)
        self.modes = ModeMachine(config, self.info, self.flight, self.outbox, self.readiness, self.setpoints)
        self.failsafes = Failsafes(self.info, self.flight, self.outbox, self.modes, self.readiness)
        self.encoder = TelemetryEncoder(
            config, self.info, self.flight, self.readiness, self.arming, self.geofence, self.frames, lambda: self.failsafes.gcs_failsafe, wall, m
        )
        self.streams = TelemetryStreams(config, self.info, self.flight, self.outbox, self.readiness, self.encoder)
        self.parameters = ParameterTable(
            config.flavour, self.info, config.sysid, self.outbox, self.flight, self.geofence, self.modes, self.setpoints, self.failsafes
        )
        for name, value in config.params:
            self.parameters.boot_param(name, value)
        self.commands = CommandHandler(
            config,
            self.info,
            self.flight,
            self.outbox,
            self.readiness,
            self.arming,
            self.geofence,
            self.frames,
            self.modes,
            self.setpoints,
            self.streams,
            self.encoder,
        )
        self.missions = MissionProtocol(self.flight, self.outbox, self.frames, self.setpoints)
        self._handlers: dict[str, Callable[[Any], None]] = self._message_handlers()
        self._handler_failures = 0

    def _message_handlers(self) -> dict[str, Callable[[Any], None]]:
        """{MAVLink message type: handler} of every message the vehicle answers."""
        cmd, sp, mis, par, st = self.commands, self.setpoints, self.missions, self.parameters, self.streams
        return {
            "HEARTBEAT": self.failsafes.on_heartbeat,
            "COMMAND_LONG": cmd.on_command_long,
            "COMMAND_INT": cmd.on_command_int,
            "SET_MODE": cmd.on_set_mode,
            "SET_GPS_GLOBAL_ORIGIN": cmd.on_set_gps_global_origin,
            "SET_POSITION_TARGET_LOCAL_NED": sp.on_set_position_target_local_ned,
            "SET_POSITION_TARGET_GLOBAL_INT": sp.on_set_position_target_global_int,
            "MISSION_ITEM_INT": mis.on_mission_item_int,
            "MISSION_ITEM": mis.on_mission_item,
            "MISSION_REQUEST_LIST": mis.on_mission_request_list,
            "MISSION_REQUEST_INT": mis.on_mission_request,
            "MISSION_REQUEST": mis.on_mission_request,
            "MISSION_COUNT": mis.on_mission_count,
            "MISSION_CLEAR_ALL": mis.on_mission_clear_all,
            "FILE_TRANSFER_PROTOCOL": mis.on_file_transfer_protocol,
            "REQUEST_DATA_STREAM": st.on_request_data_stream,
            "TIMESYNC": st.on_timesync,
            "PARAM_REQUEST_LIST": par.on_param_request_list,
            "PARAM_REQUEST_READ": par.on_param_request_read,
            "PARAM_SET": par.on_param_set,
        }

    # ------------------------------------------------------------------ state seen from outside

    @property
    def position(self) -> FloatArray:
        """True position (3,), ENU m."""
        return self.flight.position

    @property
    def t(self) -> float:
        """Sim time (s)."""
        return self.flight.t_s

    @property
    def armed(self) -> bool:
        """The motors are armed."""
        return self.flight.armed

    @property
    def flying(self) -> bool:
        """In the air (taking off, flying or landing)."""
        return self.flight.flying

    @property
    def mode(self) -> Mode:
        """The current flight mode."""
        return self.flight.mode

    @property
    def healthy(self) -> bool:
        """False once the vehicle failed (its host stops it: no more heartbeats)."""
        return self.flight.healthy

    @healthy.setter
    def healthy(self, value: bool) -> None:
        self.flight.healthy = value

    @property
    def ready(self) -> bool:
        """True once the vehicle can fly: GPS 3D fix, EKF position, home and EKF origin set."""
        return self.readiness.ready

    @property
    def ignored_messages(self) -> int:
        """Messages and commands whose handler failed (logged; a bug in the vehicle)."""
        return self._handler_failures + self.commands.ignored_messages

    def time_boot_ms(self) -> int:
        """Sim time since boot in ms (uint32 wrap)."""
        return self.flight.time_boot_ms()

    def set_mode(self, mode: Mode) -> str | None:
        """Switch to ``mode``; return None or the reason for refusing."""
        return self.modes.set_mode(mode)

    # ------------------------------------------------------------------ time

    def _physics_to(self, t_next_s: float) -> None:
        """One physics step to sim time ``t_next_s``, then readiness, mode phases, guided
        timeouts, failsafes and the battery."""
        s = self.flight
        h = t_next_s - s.t_s
        if h <= 0.0:
            return
        s.pm.step(h, t_next_s)
        s.t_s = t_next_s
        if self.readiness.update(s.t_s):
            self.streams.announce_ready()
        if s.pm.fenced:
            self.outbox.statustext(4, "Fence: stopped at boundary", key="fence_motion")
        behaviour = self.modes.update_phase()
        if behaviour == "guided" and s.flying and s.phase == "" and self.setpoints.check_timeout():
            self.failsafes.offboard_lost()
        self.failsafes.check_gcs()
        self.failsafes.report_prearm()
        if s.flying:
            s.battery = max(0.0, s.battery - self.config.battery_drain_per_s * self.physics_dt_s)

    def advance_to(self, t_s: float, *, report_position: bool = False) -> None:
        """Drain MAVLink input, integrate to sim time ``t_s`` (s) on the fixed physics grid
        (plus one partial step when ``t_s`` is off the grid), then send the telemetry due.

        Args:
            t_s: target sim time (s); earlier than the current time is a no-op for physics.
            report_position: also send GLOBAL_POSITION_INT and LOCAL_POSITION_NED now, whatever
                their rate (lockstep: the planner learns the step is done from them).
        """
        self.poll()
        s = self.flight
        if t_s > s.t_s:
            eps = 1e-9 * max(1.0, t_s)
            while (self.physics_steps + 1) * self.physics_dt_s <= t_s + eps:
                self.physics_steps += 1
                self._physics_to(self.physics_steps * self.physics_dt_s)
            if t_s > s.t_s + eps:
                self._physics_to(t_s)
            else:
                s.t_s = max(s.t_s, t_s)
        self.emit_due(report_position=report_position)

    def next_due_s(self) -> float:
        """Earliest sim time (s) at which a telemetry message is due."""
        return self.streams.next_due_s()

    def heartbeat(self) -> None:
        """Send one HEARTBEAT (nothing while unhealthy)."""
        self.streams.heartbeat()

    def emit_due(self, *, report_position: bool = False) -> None:
        """Send every telemetry message whose interval has elapsed (sim time); see
        :meth:`vehicle_sim.streams.TelemetryStreams.emit_due`."""
        self.streams.emit_due(report_position=report_position)

    # ------------------------------------------------------------------ input

    def poll(self) -> int:
        """Drain and handle pending MAVLink input; return the number of messages handled."""
        msgs = self.link.receive()
        if self.link.transport.new_peers:
            self.link.transport.new_peers = 0
            self.heartbeat()  # greet a new ground station at once
        for msg in msgs:
            self.handle(msg)
        return len(msgs)

    def handle(self, msg: Any) -> None:
        """Handle one decoded MAVLink message (never raises)."""
        try:
            self._dispatch(msg)
        except Exception:  # a bad message must never take the vehicle down
            self._handler_failures += 1
            log.exception("sysid %d: error handling %s", self.sysid, msg.get_type())

    def _for_us(self, msg: Any) -> bool:
        ts = getattr(msg, "target_system", 0)
        tc = getattr(msg, "target_component", 0)
        return ts in (0, self.sysid) and tc in (0, 1)

    def _dispatch(self, msg: Any) -> None:
        if msg.get_srcSystem() == self.sysid and msg.get_srcComponent() == 1:
            return  # our own echo
        handler = self._handlers.get(msg.get_type())
        if handler is None:
            return
        if hasattr(msg, "target_system") and not self._for_us(msg):
            return
        handler(msg)

    # ------------------------------------------------------------------ payload

    def measure(self, step: int) -> Measurement:
        """The simulated RSS payload's measurement for step ``step``, taken at the *true*
        position and the current sim time.

        Raises:
            ValueError: no payload configured, or the step was already measured.
        """
        if self.payload is None:
            raise ValueError(f"sysid {self.sysid}: no payload configured")
        return self.payload.measure(self.position, step, self.flight.t_s)

    # ------------------------------------------------------------------ inspection

    def state(self) -> VehicleState:
        """A snapshot of the vehicle state (true values)."""
        s = self.flight
        return VehicleState(
            t_s=s.t_s,
            armed=s.armed,
            mode=s.mode.custom_mode,
            mode_name=s.mode.name,
            landed_state=s.landed_state,
            position_enu_m=vec3(s.position),
            velocity_enu_mps=vec3(s.pm.velocity),
            params=tuple((name, p.get()) for name, p in self.parameters.params.items()),
            intervals_s=tuple(self.streams.intervals.items()),
            origin=self.frames.ekf_origin,
            fence_enabled=self.geofence.fence.enabled,
            stage=self.readiness.stage,
            gcs_failsafe=self.failsafes.gcs_failsafe,
        )
