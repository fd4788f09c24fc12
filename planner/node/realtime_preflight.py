"""The real-time pre-flight (external autopilots, docs/external-autopilots.md): detect the
autopilot (HEARTBEAT.autopilot), request its streams, check that the vehicle's clock runs at the
planner's speed-up (its time_boot_ms against the wall clock), wait until it is ready to fly
(GPS, EKF, home, EKF origin; the log says what is missing), take off by the autopilot's rules
(its profile: ArduPilot GUIDED, arm, NAV_TAKEOFF; PX4 setpoint stream first, OFFBOARD, arm)
and fly to the start."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from comms.mavlink_client import (
    MSG_EKF_STATUS_REPORT,
    MSG_EXTENDED_SYS_STATE,
    MSG_GLOBAL_POSITION_INT,
    MSG_GPS_GLOBAL_ORIGIN,
    MSG_GPS_RAW_INT,
    MSG_HOME_POSITION,
    MSG_LOCAL_POSITION_NED,
    MSG_SYS_STATUS,
)
from planner.node.config import NodeConfig, NodeError
from planner.node.io import NodeIO
from planner.node.takeover import TakeoverWatch

log = logging.getLogger("fimnav.plan")

#: Distance (m) within which a vehicle with real dynamics counts as at its start position.
START_TOLERANCE_REALTIME_M: float = 0.3
#: How often (wall s) the log repeats what the vehicle still lacks to fly.
READY_REPORT_PERIOD_S: float = 5.0
#: The vehicle's clock (``time_boot_ms`` against the wall clock) may run this far (relative)
#: from the planner's ``--speedup`` before the planner refuses to take off.
CLOCK_RATE_TOLERANCE: float = 0.25
#: How long (wall s) the clock check may wait for enough ``time_boot_ms`` samples.
CLOCK_CHECK_TIMEOUT_S: float = 15.0
#: PX4 (≥ 1.14) accepts OFFBOARD once the setpoint stream has run this long (mission s).
STREAM_BEFORE_GUIDED_S: float = 1.2


class _PilotTookOver(Exception):
    """A pilot took the vehicle over during the take-off or the flight to the start."""


class RealtimePreflight:
    """Brings one external vehicle from the ground (or wherever it is) to its start position,
    unless a pilot flies it (the one rule, :meth:`TakeoverWatch.found_at_start`): a vehicle
    found armed in another mode than the guided one is neither switched nor commanded.

    Args:
        config: the node's configuration. io: its link, swarm and clock.
        link_down: whether the vehicle link is lost now (the driver's link watch).
        takeover: the pilot take-over watch.
    """

    def __init__(self, config: NodeConfig, io: NodeIO, link_down: Callable[[], bool], takeover: TakeoverWatch) -> None:
        self.config = config
        self.io = io
        self.uav = config.uav
        self._link_down = link_down
        self.takeover = takeover
        #: The vehicle's clock rate (its time_boot_ms per wall second), once measured.
        self.vehicle_clock_rate: float | None = None

    def run(self) -> None:
        """Heartbeat, flavour, streams, readiness, mode, arm, take-off and flight to the
        start, by the rules of the detected autopilot."""
        link = self.io.require_link()
        t = self.config.preflight_timeout_s
        link.wait_heartbeat(t)
        link.check_signing()
        detected = link.telemetry.autopilot
        if link.forced_flavour is not None:
            log.info("uav %d: autopilot %s (forced; HEARTBEAT.autopilot = %s)", self.uav, link.flavour, detected)
        else:
            log.info("uav %d: autopilot %s (HEARTBEAT.autopilot = %s)", self.uav, link.flavour, detected)
        link.stream_period_s = 1.0 / (self.config.stream_hz * self.config.speedup)
        self.request_streams()
        if self.takeover.found_at_start("start"):
            return  # a pilot's: no readiness wait, no mode change, no take-off
        link.request_message(MSG_HOME_POSITION)
        link.request_message(MSG_GPS_GLOBAL_ORIGIN)
        self._ready_wait()
        self._check_clock()
        self._check_origin()
        self.io.wait(lambda: link.telemetry.position_enu_m is not None, t, "position telemetry")
        pos = link.telemetry.position_enu_m
        if pos is None:
            raise NodeError(f"uav {self.uav}: no position telemetry after waiting for it")
        climb_to = self.config.takeoff_alt_m
        # Take-off done at 95 % of the climb (an autopilot's altitude settles slowly at the end).
        climb_tol = max(START_TOLERANCE_REALTIME_M, 0.05 * (climb_to - float(pos[2])))
        try:
            if not self.io.profile.takeoff_by_setpoint:
                self._takeoff_by_command(climb_to, climb_tol)
            else:
                self._takeoff_on_setpoints(pos, climb_to, climb_tol)
            start = self.config.start_m
            link.set_stream(lambda _t: (start, None))
            log.info("uav %d: airborne in %s, flying to the start position", self.uav, link.mode_name())
            self._wait_linked(lambda: self._distance_to(start) < START_TOLERANCE_REALTIME_M, t, "start position")
        except _PilotTookOver:
            link.set_stream(None)

    def rejoin(self) -> None:
        """Take over a vehicle in flight from a planner that died (``--rejoin``): heartbeat,
        streams, the clock check and a position; no take-off, no flight to the start. A vehicle
        armed in another mode than the guided one (or whose take-over the launch says is in
        force) is a pilot's and is left alone; one armed in the guided mode holds where it is
        until the first step; a disarmed one is refused."""
        link = self.io.require_link()
        t = self.config.preflight_timeout_s
        link.wait_heartbeat(t)
        link.check_signing()
        link.stream_period_s = 1.0 / (self.config.stream_hz * self.config.speedup)
        self.request_streams()
        if not link.telemetry.armed and not self.takeover.in_force:
            raise NodeError(f"uav {self.uav}: cannot rejoin: the vehicle is disarmed (mode {link.mode_name()})")
        if self.takeover.found_at_start("rejoin"):
            return
        self._check_clock()
        self.io.wait(lambda: link.telemetry.position_enu_m is not None, t, "position telemetry")
        pos = link.telemetry.position_enu_m
        if pos is None:
            raise NodeError(f"uav {self.uav}: no position telemetry after waiting for it")
        hold = pos.astype(float)
        link.set_stream(lambda _t: (hold, None))
        log.info("uav %d: rejoining in %s, holding at %s until the next step", self.uav, link.mode_name(), tuple(round(float(v), 1) for v in hold))

    def request_streams(self) -> None:
        """The telemetry the real-time planner reads, at rates in the autopilot's time (Hz)."""
        link = self.io.require_link()
        pos_msg = MSG_GLOBAL_POSITION_INT if self.config.setpoint_frame == "global" else MSG_LOCAL_POSITION_NED
        rates = {pos_msg: 10.0, MSG_SYS_STATUS: 1.0, MSG_GPS_RAW_INT: 1.0, MSG_HOME_POSITION: 0.5, MSG_EXTENDED_SYS_STATE: 1.0}
        optional = [MSG_EXTENDED_SYS_STATE]
        if self.io.profile.ekf_status_report:
            rates[MSG_EKF_STATUS_REPORT] = 1.0
            optional.append(MSG_EKF_STATUS_REPORT)
        for note in link.request_streams(rates, optional):
            log.info("uav %d: %s", self.uav, note)

    def _takeoff_on_setpoints(self, pos: np.ndarray, climb_to: float, climb_tol: float) -> None:
        """PX4: the setpoint stream must run (> 2 Hz, PX4 ≥ 1.14 wants it for a second)
        before OFFBOARD is accepted; the stream is a hold above the current position."""
        link = self.io.require_link()
        t = self.config.preflight_timeout_s
        wall = self.io.clock.wall
        above = np.array([pos[0], pos[1], max(climb_to, float(pos[2]))])
        link.set_stream(lambda _t: (above, None))
        stream_since = wall()
        self._wait_linked(lambda: wall() - stream_since >= STREAM_BEFORE_GUIDED_S / self.config.speedup, t, "setpoint stream before OFFBOARD")
        self._guided_for_takeoff()
        if not link.telemetry.armed:
            link.arm()
        self._wait_linked(lambda: self._z() >= climb_to - climb_tol, t, f"take-off to {climb_to:g} m")

    def _takeoff_by_command(self, climb_to: float, climb_tol: float) -> None:
        """ArduPilot: GUIDED, arm, NAV_TAKEOFF (its altitude is above home); no setpoint until
        the take-off altitude is reached (a setpoint would end the take-off)."""
        link = self.io.require_link()
        self._guided_for_takeoff()
        if not link.telemetry.armed:
            link.arm()
            link.takeoff(climb_to - link.home_z_m())
            self._wait_linked(lambda: self._z() >= climb_to - climb_tol, self.config.preflight_timeout_s, f"take-off to {climb_to:g} m")

    def _guided_for_takeoff(self) -> None:
        """Switch a disarmed vehicle to the guided mode for its take-off. A vehicle armed in
        another mode by now was armed in the guided mode at the start (:meth:`run`) and a pilot
        has taken it over during the waits since (readiness, clock, the PX4 stream): the one
        rule, no mode change (:class:`_PilotTookOver`)."""
        link = self.io.require_link()
        guided = self.io.guided_mode
        if link.in_mode(guided):
            return
        if link.telemetry.armed and self.takeover.found_at_start("start"):
            raise _PilotTookOver
        link.set_mode(guided)

    def _check_origin(self) -> None:
        """The vehicle's EKF origin, logged; NodeError when there is none, or when local
        setpoints would need it at the mission origin and it is elsewhere."""
        link = self.io.require_link()
        origin = link.telemetry.origin_global
        if origin is None:
            raise NodeError(f"uav {self.uav}: the vehicle is ready but sent no EKF origin (GPS_GLOBAL_ORIGIN)")
        shared = self.config.mission_frame.matches(*origin)
        log.info(
            "uav %d: ready; EKF origin %.7f, %.7f, %.2f m (%s the mission origin); setpoints in %s",
            self.uav,
            *origin,
            "is" if shared else "is not",
            "SET_POSITION_TARGET_GLOBAL_INT" if self.config.setpoint_frame == "global" else "LOCAL_NED",
        )
        if self.config.setpoint_frame == "local_ned" and not shared:
            lat, lon, alt = self.config.origin_lat_lon_alt
            raise NodeError(
                f"uav {self.uav}: setpoint_frame local_ned needs the vehicle's EKF origin at the mission origin "
                f"({lat:.7f}, {lon:.7f}, {alt:g} m); it is at "
                f"({origin[0]:.7f}, {origin[1]:.7f}, {origin[2]:g} m): use setpoint_frame global"
            )

    def _wait_linked(self, predicate: Callable[[], bool], timeout_s: float, what: str, missing: Callable[[], Any] | None = None) -> None:
        """:meth:`NodeIO.wait` that also fails at once, naming ``what``, when the link is lost."""

        def ok() -> bool:
            if self._link_down():
                raise NodeError(f"uav {self.uav}: vehicle link lost while waiting for {what}")
            link = self.io.require_link()
            if link.left_guided or (link.telemetry.armed and not link.in_mode(self.io.guided_mode)):
                # (only waited on armed in the guided mode) a pilot took it over meanwhile
                if self.takeover.found_at_start("start"):
                    raise _PilotTookOver
                raise NodeError(f"uav {self.uav}: the vehicle left {self.io.guided_mode} while waiting for {what} (now {link.mode_name()}, disarmed)")
            return predicate()

        self.io.wait(ok, timeout_s, what, missing)

    def _ready_wait(self) -> None:
        """Wait until the vehicle can fly by setpoints, saying what it waits for."""
        link = self.io.require_link()
        wall = self.io.clock.wall
        timeout_s = self.config.preflight_timeout_s
        deadline = wall() + timeout_s
        last_report = -math.inf
        last_request = wall()
        while True:
            self._clock_verdict()  # a vehicle on another clock is refused at once, not after its readiness
            missing = link.not_ready(require_gps=self.config.setpoint_frame == "global")
            if not missing:
                return
            now = wall()
            if now >= deadline:
                raise NodeError(f"uav {self.uav}: vehicle not ready to fly after {timeout_s:g} s; still waiting for: {'; '.join(missing)}")
            if now - last_report >= READY_REPORT_PERIOD_S:
                log.info("uav %d: waiting for the vehicle: %s", self.uav, "; ".join(missing))
                last_report = now
            if now - last_request >= READY_REPORT_PERIOD_S:
                last_request = now
                if not link.telemetry.home_known:
                    link.request_message(MSG_HOME_POSITION)
                if link.telemetry.origin_global is None:
                    link.request_message(MSG_GPS_GLOBAL_ORIGIN)
            self.io.sleep_io(min(0.25, deadline - now))

    def _check_clock(self) -> None:
        """Refuse (NodeError) a vehicle whose clock runs at another rate than this planner's
        mission clock (``--speedup``): e.g. a SITL at ×1 under a planner at ×5, whose steps
        would be five times too short for the vehicle. The rate is the vehicle's
        ``time_boot_ms`` against the wall clock (:class:`comms.mavlink_client.ClockWatch`)
        over at least 1.5 wall seconds; a real autopilot's is 1. Checked as soon as it can be
        measured (during the readiness wait) and required before take-off."""
        if self.vehicle_clock_rate is None:
            self.io.wait(lambda: self._clock_verdict(), CLOCK_CHECK_TIMEOUT_S, "time_boot_ms stamps to measure the vehicle's clock rate")

    def _clock_verdict(self) -> bool:
        """Whether the vehicle's clock rate is known (and matches; NodeError if not)."""
        if self.vehicle_clock_rate is not None:
            return True
        link = self.io.require_link()
        rate = link.clock.rate()
        if rate is None:
            return False
        s = self.config.speedup
        span = link.clock.span_s()
        log.info("uav %d: vehicle clock x%.2f of wall time (time_boot_ms over %.1f s); this planner x%g", self.uav, rate, span, s)
        if abs(rate / s - 1.0) > CLOCK_RATE_TOLERANCE:
            raise NodeError(
                f"uav {self.uav}: the vehicle's clock runs at x{rate:.2f} of wall time (its time_boot_ms over {span:.1f} s) "
                f"but this planner's mission clock at x{s:g} (--speedup): start the vehicle (SITL --speedup, fimnav vehicle "
                f"--speedup) and the planner at the same speed-up; not taking off"
            )
        self.vehicle_clock_rate = rate
        return True

    def _z(self) -> float:
        pos = self.io.require_link().telemetry.position_enu_m
        return -math.inf if pos is None else float(pos[2])

    def _distance_to(self, target: np.ndarray) -> float:
        pos = self.io.require_link().telemetry.position_enu_m
        return math.inf if pos is None else float(np.linalg.norm(pos - target))
