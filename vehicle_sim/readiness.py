"""Start-up readiness of a simulated vehicle (EKF alignment, GPS fix, home, origin) and its
arming checks."""

from __future__ import annotations

from collections.abc import Callable

from comms.autopilot import FlavourInfo
from vehicle_sim.flight_state import FlightState
from vehicle_sim.geofence import FenceGuard
from vehicle_sim.outbox import Outbox

#: Start-up stages: EKF initialising, attitude aligned (no GPS fix), ready (GPS, home, origin).
STAGES: tuple[str, ...] = ("init", "aligned", "ready")


class Readiness:
    """The start-up stage, advanced with sim time.

    Args:
        info: the autopilot profile. ready_after_s: sim seconds from boot until ready
            (0: ready at boot). outbox: for the flavour's start-up STATUSTEXTs.
    """

    def __init__(self, info: FlavourInfo, ready_after_s: float, outbox: Outbox) -> None:
        self.info = info
        self.ready_after_s = ready_after_s
        self.outbox = outbox
        self.stage = "ready" if ready_after_s <= 0.0 else "init"
        self.origin_set = self.stage == "ready"  # EKF origin known (ready, or set by a GCS)

    @property
    def ready(self) -> bool:
        """True once the vehicle can fly: GPS 3D fix, EKF position, home and EKF origin set."""
        return self.stage == "ready"

    def update(self, t_s: float) -> bool:
        """Advance the start-up stages to sim time ``t_s``: EKF attitude aligned at half of
        ``ready_after_s``, GPS fix, EKF position, home and origin at ``ready_after_s``.
        Returns True when the vehicle became ready now (the caller announces it)."""
        if self.stage == "ready":
            return False
        if t_s + 1e-9 >= self.ready_after_s:
            self.stage = "ready"
            self.origin_set = True
            return True
        if self.stage == "init" and t_s + 1e-9 >= 0.5 * self.ready_after_s:
            self.stage = "aligned"
            for text in self.info.aligned_texts:
                self.outbox.statustext(6, text)
        return False

    def not_ready_reason(self) -> str | None:
        """The pre-arm failure of a vehicle that is not ready yet (ArduPilot "PreArm: ...",
        PX4 "Preflight Fail: ..."), or None when ready."""
        if self.stage == "ready":
            return None
        return self.info.not_ready_init if self.stage == "init" else self.info.not_ready_aligned

    def available(self, name: str) -> bool:
        """Whether telemetry message ``name`` can be sent now: before the vehicle is ready
        there is no home, no local position and (unless a GCS set one) no EKF origin; PX4
        publishes no global position either (ArduPilot sends GLOBAL_POSITION_INT with zeros)."""
        if self.stage == "ready":
            return True
        if name in ("HOME_POSITION", "LOCAL_POSITION_NED"):
            return False
        if name == "GPS_GLOBAL_ORIGIN":
            return self.origin_set
        if name == "GLOBAL_POSITION_INT":
            return self.info.global_position_before_fix
        return True


class ArmingChecks:
    """The pre-arm checks (the arming command and SYS_STATUS's PREARM_CHECK health bit).

    Args:
        info: the autopilot profile. state: the flight state. readiness: the start-up stage.
        fence: the fence. offboard_stream_ok: PX4's "setpoints faster than 2 Hz" test.
    """

    def __init__(
        self, info: FlavourInfo, state: FlightState, readiness: Readiness, fence: FenceGuard, offboard_stream_ok: Callable[[], bool]
    ) -> None:
        self.info = info
        self.state = state
        self.readiness = readiness
        self.fence = fence
        self.offboard_stream_ok = offboard_stream_ok

    def prearm_failure(self) -> str | None:
        """The first failing pre-arm check as the flavour words it, or None."""
        s = self.state
        not_ready = self.readiness.not_ready_reason()
        if not_ready:
            return not_ready
        if not s.mode.armable:
            return self.info.mode_not_armable.format(mode=s.mode.name)
        if self.info.guided_needs_setpoint_stream and s.mode.behaviour == "guided" and not self.offboard_stream_ok():
            return "PreArm: no offboard setpoints"
        if not s.healthy:
            return "PreArm: vehicle unhealthy"
        if s.battery < 0.2:
            return "PreArm: battery low"
        if not self.fence.inside(s.position, check_floor=False):
            return "PreArm: vehicle outside fence"
        return None
