"""Failsafes of a simulated vehicle: ArduPilot's GCS heartbeat failsafe, PX4's offboard-loss
failsafe, and ArduPilot's periodic pre-arm report."""

from __future__ import annotations

from typing import Any

from comms.autopilot import FlavourInfo
from vehicle_sim.flight_state import FlightState
from vehicle_sim.modes import ModeMachine
from vehicle_sim.outbox import Outbox
from vehicle_sim.readiness import Readiness

#: ArduPilot copter FS_GCS_ENABLE -> action on GCS heartbeat loss (no SmartRTL path and no
#: DO_LAND_START in the simulator: SmartRTL falls back as ArduPilot does, 6 is RTL).
FS_GCS_ACTIONS: dict[int, str | None] = {0: None, 1: "rtl", 2: "rtl", 3: "rtl", 4: "land", 5: "land", 6: "rtl"}
#: PX4 COM_OBL_RC_ACT -> action on offboard loss. Position/Altitude/Manual need an RC
#: transmitter, which a simulated vehicle has not: PX4 then falls back to Hold.
PX4_OBL_ACTIONS: dict[int, str] = {0: "hold", 1: "hold", 2: "hold", 3: "rtl", 4: "land", 5: "hold", 6: "terminate", 7: "terminate"}
FS_GCS_TIMEOUT_DEFAULT_S = 5.0
SYSID_MYGCS_DEFAULT = 255
#: ArduPilot reports a failing pre-arm check this often (sim s).
PREARM_DISPLAY_PERIOD_S = 30.0


class Failsafes:
    """The failsafes and their parameters.

    Args:
        info: the autopilot profile. state: the flight state. outbox: STATUSTEXT.
        modes: the mode machine (the failsafe actions). readiness: the start-up stage.

    Attributes:
        fs_gcs_enable: ArduPilot FS_GCS_ENABLE. fs_gcs_timeout_s: FS_GCS_TIMEOUT (sim s).
        sysid_mygcs: SYSID_MYGCS. gcs_last_seen_t_s: sim time of the last SYSID_MYGCS
            heartbeat (None: never). gcs_failsafe: the GCS failsafe is active.
        offboard_loss_action: PX4 COM_OBL_RC_ACT.
    """

    def __init__(self, info: FlavourInfo, state: FlightState, outbox: Outbox, modes: ModeMachine, readiness: Readiness) -> None:
        self.info = info
        self.state = state
        self.outbox = outbox
        self.modes = modes
        self.readiness = readiness
        self.fs_gcs_enable = 0.0
        self.fs_gcs_timeout_s = FS_GCS_TIMEOUT_DEFAULT_S
        self.sysid_mygcs = float(SYSID_MYGCS_DEFAULT)
        self.gcs_last_seen_t_s: float | None = None
        self.gcs_failsafe = False
        self.offboard_loss_action = 0.0
        self._prearm_next_t_s = PREARM_DISPLAY_PERIOD_S
        #: Only ArduPilot's AP_Arming repeats a failing pre-arm check on its own.
        self.reports_prearm = info.repeats_prearm_failure

    def on_heartbeat(self, msg: Any) -> None:
        """ArduPilot: a heartbeat from SYSID_MYGCS keeps the GCS failsafe away (or clears it)."""
        if not self.info.gcs_failsafe or msg.get_srcSystem() != int(self.sysid_mygcs):
            return
        self.gcs_last_seen_t_s = self.state.t_s
        if self.gcs_failsafe:
            self.gcs_failsafe = False
            self.outbox.statustext(4, "GCS Failsafe Cleared")

    def check_gcs(self) -> None:
        """ArduPilot copter GCS failsafe: FS_GCS_ENABLE set, a SYSID_MYGCS heartbeat seen once,
        none for FS_GCS_TIMEOUT (sim s): disarmed, nothing; landed, disarm; landing, go on
        landing; otherwise the FS_GCS_ENABLE action (RTL or LAND). Once per loss."""
        s = self.state
        if not self.info.gcs_failsafe or self.gcs_failsafe or self.gcs_last_seen_t_s is None:
            return
        action = FS_GCS_ACTIONS.get(int(self.fs_gcs_enable))
        if action is None or s.t_s - self.gcs_last_seen_t_s <= self.fs_gcs_timeout_s:
            return
        self.gcs_failsafe = True
        if not s.armed:
            self.outbox.statustext(4, "GCS Failsafe")
        elif not s.flying:
            self.outbox.statustext(4, "GCS Failsafe - Disarming")
            self.modes.motors_off()
            self.outbox.statustext(6, "Disarming motors")
        elif s.mode.behaviour == "land":
            self.outbox.statustext(4, "GCS Failsafe - Continuing Landing")
        else:
            self.outbox.statustext(4, "GCS Failsafe")
            self.modes.set_mode(self.info.require_mode(self.info.rtl_mode if action == "rtl" else self.info.land_mode))

    def offboard_lost(self) -> None:
        """PX4 offboard loss (no setpoint for COM_OF_LOSS_T): the COM_OBL_RC_ACT action."""
        action = PX4_OBL_ACTIONS.get(int(self.offboard_loss_action), "hold")
        if action == "hold":
            self.state.mode = self.info.require_mode(self.info.hold_mode)
            self.state.hold_here()
            self.outbox.statustext(2, "Failsafe: offboard lost, holding")
        elif action == "terminate":
            self.outbox.statustext(0, "Failsafe: offboard lost, motors off")
            self.modes.motors_off()
        else:
            self.outbox.statustext(2, f"Failsafe: offboard lost, {'returning' if action == 'rtl' else 'landing'}")
            self.modes.set_mode(self.info.require_mode(self.info.rtl_mode if action == "rtl" else self.info.land_mode))

    def report_prearm(self) -> None:
        """ArduPilot's periodic pre-arm report (AP_Arming::update): while disarmed and not ready,
        the failing check as ``PreArm: ...`` every PREARM_DISPLAY_PERIOD (30 s of sim time,
        the first at 30 s after boot)."""
        if not self.reports_prearm or self.state.armed or self.state.t_s < self._prearm_next_t_s:
            return
        self._prearm_next_t_s = self.state.t_s + PREARM_DISPLAY_PERIOD_S
        reason = self.readiness.not_ready_reason()
        if reason:
            self.outbox.statustext(2, reason)
