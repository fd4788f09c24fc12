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

from collections.abc import Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import TYPE_CHECKING, Literal

Behaviour = Literal["hold", "guided", "takeoff", "land", "rtl", "mission"]

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAV_AUTOPILOT_PX4 = 12

# COMMAND_ACK results (MAV_RESULT, common.xml) the profiles name.
MAV_RESULT_ACCEPTED = 0
MAV_RESULT_TEMPORARILY_REJECTED = 1
MAV_RESULT_DENIED = 2
MAV_RESULT_FAILED = 4

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
    """Identity, modes and rules of one autopilot flavour: every fact in which the flavours
    differ, read by the simulated vehicle (:mod:`vehicle_sim`) and the planner's client
    (:mod:`comms.mavlink_client`). Values are given as (ArduPilot, PX4).

    Attributes:
        name: the flavour's name in missions, configs and the CLI (``"ardupilot"``, ``"px4"``).
        display_name: the name in messages (``"ArduPilot"``, ``"PX4"``).
        autopilot: HEARTBEAT autopilot (MAV_AUTOPILOT_*; 3, 12).
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
        arm_tries: arming attempts of the planner's client (1, 3): PX4's pre-arm result
            flickers for a moment while its EKF settles ("Preflight Fail: vertical velocity
            unstable"), so the client waits for a passing SYS_STATUS and tries again.
        prearm_health_only: the pre-arm result is the SYS_STATUS PREARM_CHECK *health* bit
            alone, never marked present (False, True: PX4); disarmed in the guided mode it
            stays clear until a setpoint stream runs, so the client does not await it there.
            ArduPilot marks the bit present and enabled and reports the result in health.
        home_before_position: HOME_POSITION arrives before the EKF has a position and no
            position message comes until it has (False, True: PX4), so the client also waits
            for a GLOBAL_POSITION_INT / LOCAL_POSITION_NED.
        relative_alt_as_amsl: the client sends a GLOBAL_RELATIVE_ALT_INT target as a
            GLOBAL_INT one (home's AMSL altitude + relative altitude) (False, True): PX4
            (v1.15 and earlier) converts a relative altitude to local z with the sign of
            (home − EKF-origin altitude) reversed.
        arm_command_prefix: the ``"PreArm: "`` prefix of a pre-arm failure is replaced by this
            one in the answer to an arming command ("Arm: ": ArduPilot's AP_Arming runs the
            same checks with that prefix; None: PX4 answers with the text unchanged).
        takeoff_refused_result: the MAV_RESULT of a refused MAV_CMD_NAV_TAKEOFF (not armed,
            flying, no position, wrong mode) (FAILED, TEMPORARILY_REJECTED).
        takeoff_refused_text: that refusal carries a STATUSTEXT saying why (False: ArduPilot's
            do_user_takeoff() fails silently; True: PX4).
        unknown_mode_no_such_mode: a mode change (DO_SET_MODE or SET_MODE) to an unknown
            custom mode is answered FAILED with "No such mode <n>" (True: ArduPilot's
            notify_no_such_mode); False: DENIED with "Mode: unknown mode <n>" (PX4).
        home_unknown_result: MAV_CMD_GET_HOME_POSITION's result while there is no home yet
            (FAILED, DENIED).
        unknown_interval_result: MAV_CMD_SET_MESSAGE_INTERVAL's result for a message the
            autopilot cannot stream, e.g. EKF_STATUS_REPORT on PX4 (DENIED, FAILED).
        unavailable_request_result: MAV_CMD_REQUEST_MESSAGE's result for a message not
            available yet (no home, no origin) (ACCEPTED: ArduPilot's sender then sends
            nothing; DENIED: PX4's stream cannot send).
        reposition_changes_mode: MAV_CMD_DO_REPOSITION with MAV_DO_REPOSITION_FLAGS_CHANGE_MODE
            switches to the guided mode (True: ArduPilot); False: refused outside it (PX4).
        mode_checks_disarmed: a mode's requirements (a position) are checked while disarmed
            too (False: ArduPilot's Copter::set_mode allows any mode while disarmed; True: PX4).
        needs_position_text: the refusal of a mode that needs a position before there is one
            (``{mode}``: its name).
        mode_change_text: STATUSTEXT after an accepted mode change (None: ArduPilot sends
            none; PX4 "Mode {mode}").
        landed_disarm_text: STATUSTEXT when the vehicle disarms on touchdown ("Disarming
            motors", "Landed: disarmed").
        restore_mode_after_disarm: after disarming on touchdown the vehicle returns to the
            last armable mode chosen, e.g. OFFBOARD after AUTO.LAND (False, True: PX4's
            UserModeIntention::onDisarm).
        takeoff_complete_text: STATUSTEXT when a take-off reaches its height (None:
            ArduPilot's GUIDED take-off ends silently; PX4 "Takeoff complete").
        base_mode_manual_input: HEARTBEAT base_mode always has MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
            (True: ArduPilot's GCS_MAVLINK_Copter::base_mode; False: PX4).
        guided_flag_modes: names of the modes whose HEARTBEAT base_mode has
            MAV_MODE_FLAG_GUIDED_ENABLED (ArduPilot: the modes that navigate, AUTO, RTL, LOITER,
            GUIDED, POSHOLD, BRAKE, not LAND; PX4: the autonomous ones, AUTO.* and OFFBOARD).
        heartbeat_active_when_armed: HEARTBEAT system_status is ACTIVE while armed, else
            STANDBY (True: PX4); False: ACTIVE while flying, STANDBY on the ground, CRITICAL
            in the GCS failsafe (ArduPilot's vehicle_system_status). CRITICAL when unhealthy.
        repeats_prearm_failure: while disarmed and not ready the autopilot repeats its failing
            pre-arm check as a STATUSTEXT every 30 s (True: ArduPilot's AP_Arming::update).
        param_table: the name of the simulated vehicle's parameter table
            (:data:`vehicle_sim.params.PARAM_TABLES`: ``"ardupilot"`` WPNAV_*, GUID_TIMEOUT, FS_GCS_*
            in ArduPilot's units; ``"px4"`` MPC_*, COM_OF_LOSS_T, COM_OBL_RC_ACT in SI units).
    """

    name: str
    display_name: str
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
    arm_tries: int
    prearm_health_only: bool
    home_before_position: bool
    relative_alt_as_amsl: bool
    arm_command_prefix: str | None
    takeoff_refused_result: int
    takeoff_refused_text: bool
    unknown_mode_no_such_mode: bool
    home_unknown_result: int
    unknown_interval_result: int
    unavailable_request_result: int
    reposition_changes_mode: bool
    mode_checks_disarmed: bool
    needs_position_text: str
    mode_change_text: str | None
    landed_disarm_text: str
    restore_mode_after_disarm: bool
    takeoff_complete_text: str | None
    base_mode_manual_input: bool
    guided_flag_modes: frozenset[str]
    heartbeat_active_when_armed: bool
    repeats_prearm_failure: bool
    param_table: str

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
    name="ardupilot",
    display_name="ArduPilot",
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
    arm_tries=1,
    prearm_health_only=False,
    home_before_position=False,
    relative_alt_as_amsl=False,
    arm_command_prefix="Arm: ",
    takeoff_refused_result=MAV_RESULT_FAILED,
    takeoff_refused_text=False,
    unknown_mode_no_such_mode=True,
    home_unknown_result=MAV_RESULT_FAILED,
    unknown_interval_result=MAV_RESULT_DENIED,
    unavailable_request_result=MAV_RESULT_ACCEPTED,
    reposition_changes_mode=True,
    mode_checks_disarmed=False,
    needs_position_text="Mode change to {mode} failed: requires position",
    mode_change_text=None,
    landed_disarm_text="Disarming motors",
    restore_mode_after_disarm=False,
    takeoff_complete_text=None,
    base_mode_manual_input=True,
    guided_flag_modes=frozenset({"AUTO", "RTL", "LOITER", "GUIDED", "POSHOLD", "BRAKE"}),
    heartbeat_active_when_armed=False,
    repeats_prearm_failure=True,
    param_table="ardupilot",
)

PX4 = FlavourInfo(
    name="px4",
    display_name="PX4",
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
    arm_tries=3,
    prearm_health_only=True,
    home_before_position=True,
    relative_alt_as_amsl=True,
    arm_command_prefix=None,
    takeoff_refused_result=MAV_RESULT_TEMPORARILY_REJECTED,
    takeoff_refused_text=True,
    unknown_mode_no_such_mode=False,
    home_unknown_result=MAV_RESULT_DENIED,
    unknown_interval_result=MAV_RESULT_FAILED,
    unavailable_request_result=MAV_RESULT_DENIED,
    reposition_changes_mode=False,
    mode_checks_disarmed=True,
    needs_position_text="Switching to {mode} is currently not possible",
    mode_change_text="Mode {mode}",
    landed_disarm_text="Landed: disarmed",
    restore_mode_after_disarm=True,
    takeoff_complete_text="Takeoff complete",
    base_mode_manual_input=False,
    guided_flag_modes=frozenset(m.name for m in PX4_MODES if m.behaviour in ("guided", "takeoff", "land", "rtl", "mission")),
    heartbeat_active_when_armed=True,
    repeats_prearm_failure=False,
    param_table="px4",
)


#: The flavours, by name: the one registry from which the mission schema's allowed values, the
#: CLI's choices, the node's and the vehicle's configs and :func:`flavour_of_autopilot` derive.
#: Read it through :func:`flavour_info`, :func:`flavour_names` and :func:`flavour_of_autopilot`
#: (they look it up at each call). A new flavour is one more :class:`FlavourInfo` here
#: (docs/autopilot-flavours.md).
FLAVOURS: Mapping[str, FlavourInfo] = MappingProxyType({f.name: f for f in (ARDUPILOT, PX4)})
if TYPE_CHECKING:
    FlavourName = str
    FlavourSetting = str
else:
    #: A flavour's name, as a type (pydantic validates it; the JSON Schema's enum): the names of
    #: :data:`FLAVOURS` when this module is imported.
    FlavourName = Literal[tuple(FLAVOURS)]
    #: A flavour setting of the planner: ``"auto"`` (from HEARTBEAT.autopilot) or a flavour's name.
    FlavourSetting = Literal[("auto",) + tuple(FLAVOURS)]

#: The flavour the planner's client assumes when HEARTBEAT.autopilot names none of :data:`FLAVOURS`.
DEFAULT_FLAVOUR = "ardupilot"


def flavour_names() -> tuple[str, ...]:
    """The names of the registered flavours (:data:`FLAVOURS`), in registry order."""
    return tuple(FLAVOURS)


def flavour_info(flavour: str) -> FlavourInfo:
    """The :class:`FlavourInfo` of a registered flavour (``"ardupilot"``, ``"px4"``).

    Raises:
        ValueError: not a name in :data:`FLAVOURS`.
    """
    info = FLAVOURS.get(flavour)
    if info is None:
        raise ValueError(f"unknown flavour {flavour!r}: expected one of {', '.join(repr(n) for n in FLAVOURS)}")
    return info


def flavour_of_autopilot(autopilot: int | None) -> str | None:
    """The name of the flavour whose HEARTBEAT.autopilot (MAV_AUTOPILOT_*) is ``autopilot``, or
    None if no registered flavour has it."""
    return next((f.name for f in FLAVOURS.values() if f.autopilot == autopilot), None)


def client_mode_table(flavour: str) -> dict[str, int]:
    """{qualified name: custom_mode} of a flavour's modes (:attr:`Mode.qualified_name`), the
    planner client's names for a mode change."""
    return {m.qualified_name: m.custom_mode for m in flavour_info(flavour).modes}
