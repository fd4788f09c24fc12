"""Autopilot profiles: flight modes, identity and readiness flags of ArduPilot copter and PX4,
one table per flavour used by both sides of the link (the simulated vehicle,
:mod:`vehicle_sim` (its modes, readiness, commands and telemetry), and the planner's MAVLink client, :mod:`comms.mavlink_client`), so
the two cannot disagree.

A mode is identified by its HEARTBEAT ``custom_mode``: ArduPilot copter mode numbers
(GUIDED = 4, ...) or PX4's ``main_mode << 16 | sub_mode << 24``. Each mode maps to one
internal *behaviour*:

``hold``    hold position (no RC in a simulator: STABILIZE, ALT_HOLD, LOITER, POSHOLD, BRAKE,
            PX4 POSCTL, AUTO.LOITER, ...);
``guided``  follow external setpoints (ArduPilot GUIDED, PX4 OFFBOARD);
``takeoff`` climb to the take-off altitude (PX4 AUTO.TAKEOFF);
``land``    descend and disarm on touchdown; ``rtl`` climb, return home, land;
``mission`` fly the stored mission (refused: the mission is always empty).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

Behaviour = Literal["hold", "guided", "takeoff", "land", "rtl", "mission"]

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12

# EKF_STATUS_REPORT.flags (ArduPilot EKF_STATUS_FLAGS).
EKF_ATTITUDE = 1
EKF_VELOCITY_HORIZ = 2
EKF_VELOCITY_VERT = 4
EKF_POS_HORIZ_REL = 8
EKF_POS_HORIZ_ABS = 16
EKF_POS_VERT_ABS = 32
EKF_CONST_POS_MODE = 128
EKF_PRED_POS_HORIZ_REL = 256
EKF_PRED_POS_HORIZ_ABS = 512
#: The flags a copter needs for position control (ArduPilot's own pre-arm test: attitude,
#: velocities and absolute horizontal and vertical position); with them, EKF_CONST_POS_MODE
#: clear says it has a position.
EKF_READY_FLAGS = EKF_ATTITUDE | EKF_VELOCITY_HORIZ | EKF_VELOCITY_VERT | EKF_POS_HORIZ_ABS | EKF_POS_VERT_ABS


@dataclass(frozen=True)
class Mode:
    """One flight mode.

    Attributes:
        custom_mode: the HEARTBEAT custom_mode value.
        name: the name ground stations show (pymavlink's mode maps).
        behaviour: the internal behaviour, see the module doc.
        armable: arming is allowed in this mode.
        needs_position: the mode needs a position estimate (GPS fix, EKF position): refused
            while the vehicle is not ready (ArduPilot ``requires_GPS()``, PX4 mode requirements).
    """

    custom_mode: int
    name: str
    behaviour: Behaviour
    armable: bool
    needs_position: bool = False

    @property
    def qualified_name(self) -> str:
        """The name the planner's client uses for a mode change: PX4's sub-modes of AUTO as
        ``AUTO.<name>`` (AUTO.LOITER, AUTO.LAND, ...), every other mode by its name."""
        main, sub = (self.custom_mode >> 16) & 0xFF, (self.custom_mode >> 24) & 0xFF
        return f"AUTO.{self.name}" if main == PX4_MAIN_AUTO and sub else self.name


#: PX4's AUTO main mode (its sub-modes are TAKEOFF, LOITER, MISSION, RTL, LAND).
PX4_MAIN_AUTO = 4


def px4_custom_mode(main: int, sub: int = 0) -> int:
    """PX4 custom_mode from main and sub mode (``main << 16 | sub << 24``)."""
    return (main << 16) | (sub << 24)


ARDUPILOT_MODES: tuple[Mode, ...] = (
    Mode(0, "STABILIZE", "hold", True),
    Mode(2, "ALT_HOLD", "hold", True),
    Mode(3, "AUTO", "mission", False, True),
    Mode(4, "GUIDED", "guided", True, True),
    Mode(5, "LOITER", "hold", True, True),
    Mode(6, "RTL", "rtl", False, True),
    Mode(9, "LAND", "land", False),
    Mode(16, "POSHOLD", "hold", True, True),
    Mode(17, "BRAKE", "hold", False, True),
)

PX4_MODES: tuple[Mode, ...] = (
    Mode(px4_custom_mode(1), "MANUAL", "hold", True),
    Mode(px4_custom_mode(2), "ALTCTL", "hold", True),
    Mode(px4_custom_mode(3), "POSCTL", "hold", True, True),
    Mode(px4_custom_mode(7), "STABILIZED", "hold", True),
    Mode(px4_custom_mode(4, 2), "TAKEOFF", "takeoff", True, True),
    Mode(px4_custom_mode(4, 3), "LOITER", "hold", True, True),
    Mode(px4_custom_mode(4, 4), "MISSION", "mission", False, True),
    Mode(px4_custom_mode(4, 5), "RTL", "rtl", False, True),
    Mode(px4_custom_mode(4, 6), "LAND", "land", False),
    Mode(px4_custom_mode(6), "OFFBOARD", "guided", True, True),
)


@dataclass(frozen=True)
class FlavourInfo:
    """Identity and modes of one autopilot flavour.

    Attributes:
        autopilot: HEARTBEAT autopilot (MAV_AUTOPILOT_*).
        modes: the supported modes.
        boot_mode, air_boot_mode, hold_mode, guided_mode, takeoff_mode, land_mode, rtl_mode:
            custom_mode values used by the mode logic.
        flight_sw_version: AUTOPILOT_VERSION flight_sw_version (major.minor.patch, official).
        param_bytewise: PARAM_VALUE integer encoding (PX4 bytewise, ArduPilot C cast).
        mode_command_main_sub: MAV_CMD_DO_SET_MODE carries the mode as PX4's main mode
            (param2) and sub mode (param3), not as the custom_mode number (ArduPilot).
        guided_needs_setpoint_stream: the guided mode (PX4 OFFBOARD) is entered and kept only
            with a setpoint stream faster than 2 Hz; losing it triggers the offboard failsafe.
            ArduPilot's GUIDED holds the last target (a velocity times out after GUID_TIMEOUT).
        takeoff_by_setpoint: the vehicle leaves the ground on a guided position setpoint above
            it (PX4 OFFBOARD); ArduPilot needs MAV_CMD_NAV_TAKEOFF in GUIDED first.
        posvel_target_moves: a position+velocity setpoint is a target moving along its
            velocity (ArduPilot GUIDED); PX4 holds the point, the velocity a feed-forward.
        ekf_status_report: the autopilot streams EKF_STATUS_REPORT (ArduPilot's EXTRA3).
        global_position_before_fix: GLOBAL_POSITION_INT is sent before the position is known
            (ArduPilot, all zeros); PX4 sends none until its EKF has a position.
        gcs_failsafe: the GCS heartbeat failsafe (ArduPilot FS_GCS_ENABLE, SYSID_MYGCS).
        aligned_texts, ready_texts: STATUSTEXTs when the EKF aligns its attitude and when it
            has a position and origin (GPS in use).
        not_ready_init, not_ready_aligned: the pre-arm failure while the EKF initialises and
            after alignment (no 3D fix yet).
        mode_not_armable: the pre-arm failure in a mode that cannot arm (``{mode}``: its name).
        link_loss_failsafe: what the autopilot's own failsafe does while the planner's link
            is lost (for the planner's log).
    """

    autopilot: int
    modes: tuple[Mode, ...]
    boot_mode: int
    air_boot_mode: int
    hold_mode: int
    guided_mode: int
    takeoff_mode: int | None
    land_mode: int
    rtl_mode: int
    flight_sw_version: int
    param_bytewise: bool
    mode_command_main_sub: bool
    guided_needs_setpoint_stream: bool
    takeoff_by_setpoint: bool
    posvel_target_moves: bool
    ekf_status_report: bool
    global_position_before_fix: bool
    gcs_failsafe: bool
    aligned_texts: tuple[str, ...]
    ready_texts: tuple[str, ...]
    not_ready_init: str
    not_ready_aligned: str
    mode_not_armable: str
    link_loss_failsafe: str

    def mode(self, custom_mode: int) -> Mode | None:
        """The mode with this custom_mode, or None."""
        for m in self.modes:
            if m.custom_mode == custom_mode:
                return m
        return None

    def require_mode(self, custom_mode: int) -> Mode:
        """The mode with this custom_mode, one the flavour's mode logic uses (``boot_mode``,
        ``hold_mode``, ...); ValueError if the flavour has no such mode."""
        mode = self.mode(custom_mode)
        if mode is None:
            raise ValueError(f"custom_mode {custom_mode}: not a mode of this flavour (modes {', '.join(m.name for m in self.modes)})")
        return mode

    def mode_by_name(self, name: str) -> Mode | None:
        """The mode with this (case-insensitive) name, or None."""
        for m in self.modes:
            if m.name == name.upper():
                return m
        return None


def _version(major: int, minor: int, patch: int) -> int:
    return (major << 24) | (minor << 16) | (patch << 8) | 255  # FIRMWARE_VERSION_TYPE_OFFICIAL


ARDUPILOT = FlavourInfo(
    autopilot=MAV_AUTOPILOT_ARDUPILOTMEGA,
    modes=ARDUPILOT_MODES,
    boot_mode=0,
    air_boot_mode=4,
    hold_mode=5,
    guided_mode=4,
    takeoff_mode=None,
    land_mode=9,
    rtl_mode=6,
    flight_sw_version=_version(4, 5, 7),
    param_bytewise=False,
    mode_command_main_sub=False,
    guided_needs_setpoint_stream=False,
    takeoff_by_setpoint=False,
    posvel_target_moves=True,
    ekf_status_report=True,
    global_position_before_fix=True,
    gcs_failsafe=True,
    aligned_texts=("EKF3 IMU0 tilt alignment complete", "EKF3 IMU0 MAG0 initial yaw alignment complete"),
    ready_texts=("EKF3 IMU0 origin set", "EKF3 IMU0 is using GPS"),
    not_ready_init="PreArm: EKF attitude is bad",
    not_ready_aligned="PreArm: Need 3D Fix",
    mode_not_armable="PreArm: {mode} mode not armable",
    link_loss_failsafe="ArduPilot keeps GUIDED: the last position target holds; a velocity part stops after "
    "GUID_TIMEOUT; a GCS failsafe (FS_GCS_ENABLE) acts only if this link is the GCS (SYSID_MYGCS)",
)

PX4 = FlavourInfo(
    autopilot=MAV_AUTOPILOT_PX4,
    modes=PX4_MODES,
    boot_mode=px4_custom_mode(3),
    air_boot_mode=px4_custom_mode(4, 3),
    hold_mode=px4_custom_mode(4, 3),
    guided_mode=px4_custom_mode(6),
    takeoff_mode=px4_custom_mode(4, 2),
    land_mode=px4_custom_mode(4, 6),
    rtl_mode=px4_custom_mode(4, 5),
    flight_sw_version=_version(1, 15, 4),
    param_bytewise=True,
    mode_command_main_sub=True,
    guided_needs_setpoint_stream=True,
    takeoff_by_setpoint=True,
    posvel_target_moves=False,
    ekf_status_report=False,
    global_position_before_fix=False,
    gcs_failsafe=False,
    aligned_texts=(),
    ready_texts=(),
    not_ready_init="Preflight Fail: Attitude not valid",
    not_ready_aligned="Preflight Fail: GPS fix too low",
    mode_not_armable="PreArm: mode {mode} not armable",
    link_loss_failsafe="PX4 leaves OFFBOARD after COM_OF_LOSS_T and takes COM_OBL_RC_ACT (hold, land or RTL); a data-link loss (NAV_DLL_ACT) may follow",
)


def flavour_info(flavour: str) -> FlavourInfo:
    """The :class:`FlavourInfo` of ``"ardupilot"`` or ``"px4"``."""
    if flavour == "ardupilot":
        return ARDUPILOT
    if flavour == "px4":
        return PX4
    raise ValueError(f"unknown flavour {flavour!r}: expected 'ardupilot' or 'px4'")


def client_mode_table(flavour: str) -> dict[str, int]:
    """{qualified name: custom_mode} of a flavour's modes (:attr:`Mode.qualified_name`), the
    planner client's names for a mode change."""
    return {m.qualified_name: m.custom_mode for m in flavour_info(flavour).modes}
