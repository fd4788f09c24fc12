"""The planner's MAVLink link to its own autopilot (vehicle_sim, ArduPilot or PX4).

A thin, typed layer over pymavlink's ``mavutil`` connection: wait for the heartbeat, tell the
autopilot's flavour from HEARTBEAT.autopilot, request streams (SET_MESSAGE_INTERVAL, or
REQUEST_DATA_STREAM where that is refused), report what the vehicle still lacks to fly (GPS
fix, EKF, home, EKF origin), switch modes, arm, take off, stream setpoints and read the
vehicle's position with its timestamp.

Frames (docs/architecture.md, "Frames, units, time"): the mission frame is ENU about the mission origin.

* ``frame="local_ned"``: SET_POSITION_TARGET_LOCAL_NED and LOCAL_POSITION_NED, NED about the
  vehicle's EKF origin; only right where that origin *is* the mission origin (fimnav's own
  simulated vehicles, or a vehicle whose GPS_GLOBAL_ORIGIN was checked). (x_E, y_N, z_U) ↔
  (n, e, d) = (y, x, −z).
* ``frame="global"``: SET_POSITION_TARGET_GLOBAL_INT and GLOBAL_POSITION_INT, converted with
  pyproj (:mod:`comms.geodesy`): every vehicle keeps its own EKF origin. The altitude reference
  is explicit: ``amsl`` (MAV_FRAME_GLOBAL_INT, altitude = origin altitude + z) or ``relative``
  (MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, altitude above home = z).

Setpoint streaming: :meth:`VehicleLink.set_stream` installs a function of wall time giving the
current setpoint; every :meth:`pump` re-sends it once its period has elapsed, so the stream
keeps flowing while the planner waits for anything (a command's ACK, a mode heartbeat, the
peers' records): ArduPilot's GUID_TIMEOUT and PX4's offboard-loss timer never see a gap
caused by the planner waiting.

Every wait has a deadline and says what it was waiting for when it expires
(:class:`LinkTimeout`); nothing sleeps a fixed time.

The link's parts, each in its own module: the transport (:mod:`comms.mavlink_transport`:
opening, UDP/TCP readers, signing, .tlog), what it hears (:mod:`comms.mavlink_telemetry`:
telemetry state, the autopilot's clock rate, readiness) and the setpoints it sends
(:mod:`comms.mavlink_setpoints`); :class:`VehicleLink` composes them with the command,
mode-change, arming and take-off sequences. The flavours' mode tables come from the autopilot
profiles (:mod:`comms.autopilot`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from comms.autopilot import DEFAULT_FLAVOUR, EKF_CONST_POS_MODE, EKF_READY_FLAGS, FlavourInfo, client_mode_table, flavour_info, flavour_of_autopilot
from comms.geodesy import MissionFrame
from comms.mavlink_setpoints import (
    MASK_POSITION,
    MASK_POSITION_VELOCITY,
    MASK_VELOCITY,
    SetpointEncoder,
    SetpointFunction,
    SetpointStream,
    enu_to_ned,
)
from comms.mavlink_signing import WRONG_KEY_AFTER_S, WRONG_KEY_MIN_FRAMES, read_signing_key, rejects_our_key, signing_hint, wrong_key_message
from comms.mavlink_streams import DATA_STREAM_OF, request_streams
from comms.mavlink_telemetry import (
    AUTOPILOT_COMPONENT,
    CLOCK_WINDOW_S,
    MAV_LANDED_STATE_NAMES,
    MAV_SYS_STATUS_AHRS,
    MAV_SYS_STATUS_PREARM_CHECK,
    MSG_EKF_STATUS_REPORT,
    MSG_EXTENDED_SYS_STATE,
    MSG_GLOBAL_POSITION_INT,
    MSG_GPS_GLOBAL_ORIGIN,
    MSG_GPS_RAW_INT,
    MSG_HOME_POSITION,
    MSG_LOCAL_POSITION_NED,
    MSG_SYS_STATUS,
    AltitudeReference,
    ClockWatch,
    Frame,
    Telemetry,
    TelemetryReceiver,
    missing_to_fly,
    ned_to_enu,
)
from comms.mavlink_transport import LinkError, LinkTimeout, MavlinkTransport, mavutil_module

__all__ = [
    "AUTOPILOT_COMPONENT",
    "CLOCK_WINDOW_S",
    "COMPONENT_ID",
    "DATA_STREAM_OF",
    "EKF_CONST_POS_MODE",
    "EKF_READY_FLAGS",
    "LINK_LOSS_S",
    "MASK_POSITION",
    "MASK_POSITION_VELOCITY",
    "MASK_VELOCITY",
    "MAV_LANDED_STATE_NAMES",
    "MAV_SYS_STATUS_AHRS",
    "MAV_SYS_STATUS_PREARM_CHECK",
    "MODE_CONFIRM_TIMEOUT_S",
    "MSG_EKF_STATUS_REPORT",
    "MSG_EXTENDED_SYS_STATE",
    "MSG_GLOBAL_POSITION_INT",
    "MSG_GPS_GLOBAL_ORIGIN",
    "MSG_GPS_RAW_INT",
    "MSG_HOME_POSITION",
    "MSG_LOCAL_POSITION_NED",
    "MSG_SYS_STATUS",
    "PX4_ARM_TRIES",
    "WRONG_KEY_AFTER_S",
    "WRONG_KEY_MIN_FRAMES",
    "AltitudeReference",
    "ClockWatch",
    "Flavour",
    "Frame",
    "LinkError",
    "LinkTimeout",
    "Telemetry",
    "VehicleLink",
    "enu_to_ned",
    "flavour_of_autopilot",
    "mavutil_module",
    "ned_to_enu",
    "read_signing_key",
]

#: Our MAVLink identity: a companion computer of the vehicle's system.
COMPONENT_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
#: A flavour's name, one of :data:`comms.autopilot.FLAVOURS` (``"ardupilot"``, ``"px4"``).
Flavour = str

#: Arming attempts on PX4, whose pre-arm result flickers while its EKF settles
#: (:attr:`comms.autopilot.FlavourInfo.arm_tries` of PX4).
PX4_ARM_TRIES = flavour_info("px4").arm_tries
#: Deadline (s) for the heartbeat that confirms a mode change or arming (heartbeats are 1 Hz;
#: a loaded machine starting dozens of processes can delay them by seconds).
MODE_CONFIRM_TIMEOUT_S: float = 30.0
#: No autopilot heartbeat for this long (wall s) = the link is lost (noticed within 3 s).
LINK_LOSS_S: float = 2.0
#: While the link counts as lost, a message from the vehicle asks for a heartbeat at most this
#: often (wall s): the vehicle's mode, which decides whether the stream may go on, is in it.
HEARTBEAT_POLL_AFTER_LOSS_S: float = 0.2


class VehicleLink:
    """MAVLink connection of one planner to one autopilot.

    Args:
        connection: pymavlink connection string (``udpout:127.0.0.1:14550``, ``tcp:...``,
            ``/dev/ttyUSB0,57600``).
        target_system: the vehicle's system id.
        source_system: our system id (default: the vehicle's, as a companion computer).
        signing_key: 32-byte MAVLink 2 signing key, or None. With a key, everything we send
            is signed and unsigned input is refused.
        wall: monotonic clock (seconds), injectable for tests.
        frame: ``"local_ned"`` or ``"global"`` (see the module doc).
        mission_frame: the mission's :class:`MissionFrame` (required for ``"global"``).
        altitude_reference: ``"amsl"`` or ``"relative"`` (global frame only).
        flavour: force a flavour of :data:`comms.autopilot.FLAVOURS` (``"ardupilot"``,
            ``"px4"``); None: from HEARTBEAT.autopilot.
        connect_timeout_s: how long a ``tcp:`` connection is retried while refused (s).
        source_component: our component id (default 191, onboard computer; fimnav's
            simulated payload uses another, so an autopilot tells the two links apart).
        tlog: write every frame received and sent to this .tlog (MAVProxy's format:
            big-endian µs UNIX time + frame).
    """

    def __init__(
        self,
        connection: str,
        target_system: int,
        source_system: int | None = None,
        signing_key: bytes | None = None,
        wall: Callable[[], float] = time.monotonic,
        frame: Frame = "local_ned",
        mission_frame: MissionFrame | None = None,
        altitude_reference: AltitudeReference = "relative",
        flavour: Flavour | None = None,
        connect_timeout_s: float = 30.0,
        source_component: int = COMPONENT_ID,
        tlog: str | Path | None = None,
    ) -> None:
        if frame == "global" and mission_frame is None:
            raise ValueError("frame='global' needs the mission frame")
        self.mavutil = mavutil_module()
        self.connection = connection
        self.target_system = target_system
        self.wall = wall
        self.frame: Frame = frame
        self.mission_frame = mission_frame
        self.altitude_reference: AltitudeReference = altitude_reference
        self.forced_flavour: Flavour | None = flavour
        self._source_system = source_system if source_system is not None else target_system
        if signing_key is not None and len(signing_key) != 32:
            raise LinkError(f"signing key: expected 32 bytes, found {len(signing_key)}")
        self._signing_key = signing_key
        self.connect_timeout_s = connect_timeout_s
        self.source_component = source_component
        self.tlog_path = Path(tlog) if tlog is not None else None
        self.transport = MavlinkTransport(
            self.mavutil, connection, self._source_system, source_component, signing_key, wall, connect_timeout_s, self.tlog_path
        )
        self.conn: Any = self.transport.conn
        self.mav: Any = self.transport.mav
        self.receiver = TelemetryReceiver(target_system, wall, frame, mission_frame, altitude_reference)
        self.telemetry: Telemetry = self.receiver.telemetry
        self.clock: ClockWatch = self.receiver.clock
        self._last_gcs_heartbeat = -math.inf
        self._last_poll_after_loss = -math.inf
        self.acks: dict[int, int] = self.receiver.acks
        self.statustexts = self.telemetry.statustexts
        self._setpoints = SetpointEncoder(self.mavutil.mavlink, target_system, frame, mission_frame, altitude_reference)
        self._stream = SetpointStream(period_s=0.25)
        #: A heartbeat showed the vehicle leave the guided mode since the flag was last cleared
        #: (the setpoint stream was stopped then); the planner's take-over watch reads it.
        self.left_guided = False

    @property
    def foreign_datagrams(self) -> int:
        """UDP datagrams from another address than the vehicle's (dropped)."""
        return self.transport.foreign_datagrams

    @property
    def reconnects(self) -> int:
        """TCP connections opened again after a drop."""
        return self.transport.reconnects

    @property
    def setpoints_sent(self) -> int:
        """Setpoints sent so far."""
        return self._setpoints.sent

    @property
    def stream_period_s(self) -> float:
        """The setpoint stream's period (wall s)."""
        return self._stream.period_s

    @stream_period_s.setter
    def stream_period_s(self, period_s: float) -> None:
        self._stream.period_s = period_s

    # -- identity ---------------------------------------------------------------------------
    @property
    def flavour(self) -> Flavour:
        """The autopilot flavour: the forced one, else HEARTBEAT.autopilot (ArduPilot when the
        heartbeat names no registered flavour)."""
        if self.forced_flavour is not None:
            return self.forced_flavour
        return flavour_of_autopilot(self.telemetry.autopilot) or DEFAULT_FLAVOUR

    @property
    def profile(self) -> FlavourInfo:
        """The autopilot profile of :attr:`flavour` (:func:`comms.autopilot.flavour_info`)."""
        return flavour_info(self.flavour)

    # -- receiving --------------------------------------------------------------------------
    def pump(self, timeout_s: float = 0.0) -> int:
        """Read every pending message (waiting up to ``timeout_s`` for the first); return how
        many were for us. Sends our own 1 Hz heartbeat and the due setpoint as side effects.

        What has arrived is read before the due setpoint goes out: a heartbeat saying the
        vehicle left the guided mode (a pilot's mode change) stops the stream
        (:attr:`left_guided`) before another setpoint is sent."""
        self._heartbeat_out()
        n = self._read(0.0)
        self._stream_out()
        if n == 0 and timeout_s > 0:
            n = self._read(timeout_s)
        return n

    def _read(self, timeout_s: float) -> int:
        """Read every pending message, waiting up to ``timeout_s`` (wall s) for the first."""
        n = 0
        deadline = self.wall() + timeout_s
        while True:
            remaining = deadline - self.wall()
            blocking = remaining > 0 and n == 0
            try:
                # Not blocking: no timeout, or pymavlink may return before reading (it gives up
                # once its clock moved past start + timeout, which for 0 a slow computer always does).
                msg = self.conn.recv_match(blocking=blocking, timeout=remaining if blocking else None)
            except (OSError, ValueError):
                return n  # a transport error is a silent link: the heartbeat timeout reports it
            if msg is None:
                return n
            self.transport.log_received(msg)
            if self._handle(msg):
                n += 1

    def _handle(self, msg: Any) -> bool:
        """Take one parsed message into the telemetry (False: not for us). A heartbeat that
        shows the vehicle leaving the guided mode (GUIDED/OFFBOARD) ends the setpoint stream at
        once and sets :attr:`left_guided` (docs/in-the-field.md: a pilot's mode change wins).
        A message from the vehicle while the link counts as lost (no heartbeat yet) asks for a
        heartbeat at once: until one says the vehicle's mode, nothing is streamed."""
        before = self.telemetry.custom_mode
        mine = self.receiver.handle(msg, self.mav.signing.sig_count)
        after = self.telemetry.custom_mode
        if mine and before != after and after is not None:
            guided = self.profile.guided_mode
            if before == guided and after != guided:
                self._stream.fn = None
                self.left_guided = True
        if mine and self.lost and self.wall() - self._last_poll_after_loss >= HEARTBEAT_POLL_AFTER_LOSS_S:
            self._last_poll_after_loss = self.wall()
            try:
                self._poll_heartbeat()
            except OSError:
                pass  # the link is down again: the heartbeat timeout keeps reporting it
        return mine

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Pump messages until ``predicate()`` holds; :class:`LinkTimeout` naming ``what``."""
        deadline = self.wall() + timeout_s
        while not predicate():
            remaining = deadline - self.wall()
            if remaining <= 0:
                raise LinkTimeout(f"vehicle {self.target_system}: no {what} within {timeout_s:g} s{self._signing_hint()}")
            self.pump(min(remaining, 0.02 if self._stream.fn is not None else 0.05))

    def _signing_hint(self) -> str:
        return signing_hint(self._signing_key is not None, self.mav.signing, self.telemetry.signed_seen)

    def wait_heartbeat(self, timeout_s: float = 10.0) -> None:
        """Wait for the autopilot's heartbeat.

        With a signing key, a vehicle whose every frame for :data:`WRONG_KEY_AFTER_S` carried a
        signature that does not match ours (and none that does) is refused then, not after
        ``timeout_s``: its key differs from ours, and waiting longer cannot help.
        :class:`LinkError` naming the count."""
        start = self.telemetry.heartbeats
        t0 = self.wall()

        def done() -> bool:
            if self.telemetry.heartbeats > start:
                return True
            sig = self.mav.signing
            if self._signing_key is not None and rejects_our_key(sig) and self.wall() - t0 >= WRONG_KEY_AFTER_S:
                raise LinkError(wrong_key_message(self.target_system, self.wall() - t0, sig))
            return False

        self.wait_for(done, timeout_s, "heartbeat")

    def check_signing(self) -> None:
        """Refuse to go on unsigned with a vehicle that signs its frames (it refuses unsigned
        commands: every command would time out). :class:`LinkError` with what to do."""
        if self._signing_key is None and self.telemetry.signed_seen:
            raise LinkError(
                f"vehicle {self.target_system} uses MAVLink 2 signing and would refuse this planner's unsigned "
                "frames: give the key with --signing-key FILE or vehicles.overrides[i].signing_key_file"
            )

    def fileno(self) -> int | None:
        """The file descriptor to select() on for incoming MAVLink, if the transport has one."""
        return self.transport.fileno()

    def link_age_s(self) -> float:
        """Seconds since the last autopilot heartbeat."""
        return self.wall() - self.telemetry.heartbeat_wall_s

    @property
    def lost(self) -> bool:
        """No autopilot heartbeat for :data:`LINK_LOSS_S` (after having heard one)."""
        return self.telemetry.heartbeats > 0 and self.link_age_s() > LINK_LOSS_S

    # -- readiness --------------------------------------------------------------------------
    def not_ready(self, require_gps: bool = True) -> list[str]:
        """What the vehicle still lacks to fly by setpoints, in words (empty: ready):
        :func:`comms.mavlink_telemetry.missing_to_fly` of its telemetry."""
        profile = self.profile
        in_guided = profile.prearm_health_only and self.telemetry.custom_mode == profile.guided_mode
        return missing_to_fly(self.telemetry, profile, in_guided, self.frame, require_gps)

    def _poll_heartbeat(self) -> None:
        """Ask for a HEARTBEAT now (MAV_CMD_REQUEST_MESSAGE, not awaited): an accepted mode change
        or arming shows in the next heartbeat, which comes once a second otherwise. ArduPilot and
        PX4 answer the request at once; an autopilot that ignores it costs nothing (the caller
        still waits for the periodic heartbeat). Its acknowledgement is dropped with the next
        REQUEST_MESSAGE's (:meth:`command` clears stale acknowledgements)."""
        m = self.mavutil.mavlink
        self.mav.command_long_send(
            self.target_system, AUTOPILOT_COMPONENT, m.MAV_CMD_REQUEST_MESSAGE, 0, m.MAVLINK_MSG_ID_HEARTBEAT, 0, 0, 0, 0, 0, 0
        )

    def request_message(self, message_id: int) -> bool:
        """MAV_CMD_REQUEST_MESSAGE (one message now); False if refused or unanswered."""
        m = self.mavutil.mavlink
        try:
            self.command(m.MAV_CMD_REQUEST_MESSAGE, [message_id], timeout_s=3.0, what=f"REQUEST_MESSAGE({message_id})")
        except LinkTimeout:
            return False
        except LinkError:
            if message_id == MSG_HOME_POSITION:
                self.mav.command_long_send(self.target_system, AUTOPILOT_COMPONENT, m.MAV_CMD_GET_HOME_POSITION, 0, 0, 0, 0, 0, 0, 0, 0)
            return False
        return True

    # -- sending ----------------------------------------------------------------------------
    def _heartbeat_out(self) -> None:
        now = self.wall()
        if now - self._last_gcs_heartbeat >= 1.0:
            self._last_gcs_heartbeat = now
            m = self.mavutil.mavlink
            try:
                self.mav.heartbeat_send(m.MAV_TYPE_ONBOARD_CONTROLLER, m.MAV_AUTOPILOT_INVALID, 0, 0, m.MAV_STATE_ACTIVE)
            except OSError:
                pass  # the link is down: the heartbeat timeout reports it

    def set_stream(self, fn: SetpointFunction | None, period_s: float | None = None) -> None:
        """Stream ``fn(wall_s) -> (position ENU m | None, velocity ENU m/s | None)`` every
        ``period_s`` wall seconds from now on (sent at once, unless the link is :attr:`lost`);
        None stops the stream."""
        self._stream.set(fn, period_s)
        self._stream_out()

    @property
    def streaming(self) -> bool:
        """Whether a setpoint stream is installed (:meth:`set_stream`; a heartbeat showing the
        vehicle leave the guided mode ends it). An installed stream sends nothing while the link
        is :attr:`lost`."""
        return self._stream.fn is not None

    def _stream_out(self) -> None:
        # Nothing while the link is lost: who flies the vehicle is unknown until a heartbeat
        # says its mode (a pilot or a failsafe may have changed it meanwhile); a heartbeat in
        # another mode than the guided one then ends the stream before it sends again.
        if self._stream.fn is None or self.lost:
            return
        setpoint = self._stream.due(self.wall())
        if setpoint is None:
            return
        try:
            self.send_setpoint(*setpoint)
        except OSError:
            pass

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
            if len(self.statustexts) == texts_before:  # an autopilot sends its reason after the ACK
                self._wait_for_statustext_after(texts_before)
            reason = "; ".join(self.statustexts[texts_before:]) or "no reason given"
            name = m.enums["MAV_RESULT"][result].name if result in m.enums["MAV_RESULT"] else str(result)
            raise LinkError(f"vehicle {self.target_system} refused {label}: {name} ({reason})")
        raise LinkTimeout(
            f"vehicle {self.target_system}: no acknowledgement of {label} after {retries} tries in {timeout_s:g} s{self._signing_hint()}"
        )

    def _wait_for_statustext_after(self, count: int) -> None:
        """Wait briefly (0.3 s) for a STATUSTEXT beyond the first ``count``: a refusal's reason."""
        try:
            self.wait_for(lambda: len(self.statustexts) > count, 0.3, "reason")
        except LinkTimeout:
            pass

    def request_interval(self, message_id: int, rate_hz: float) -> None:
        """SET_MESSAGE_INTERVAL for one message (rate in the autopilot's time, Hz)."""
        m = self.mavutil.mavlink
        self.command(m.MAV_CMD_SET_MESSAGE_INTERVAL, [message_id, 1e6 / rate_hz], what=f"SET_MESSAGE_INTERVAL({message_id})")

    def request_streams(self, rates_hz: dict[int, float], optional: Iterable[int] = ()) -> list[str]:
        """Request each message at its rate, falling back to REQUEST_DATA_STREAM where refused
        or unanswered (:func:`comms.mavlink_streams.request_streams`); notes for the log."""
        return request_streams(self, rates_hz, optional)

    def _modes(self) -> dict[str, int]:
        """{mode name: custom_mode} of the vehicle's flavour (:func:`comms.autopilot.client_mode_table`;
        PX4's custom modes are main_mode << 16 | sub_mode << 24, its AUTO sub-modes named AUTO.<name>)."""
        return client_mode_table(self.flavour)

    def set_mode(self, name: str, timeout_s: float = MODE_CONFIRM_TIMEOUT_S, ack_timeout_s: float = 15.0) -> None:
        """Switch flight mode by name (ArduPilot copter or PX4 names) and wait to see it: the
        acknowledgement within ``ack_timeout_s``, the heartbeat in the mode within
        ``timeout_s`` (wall s)."""
        m = self.mavutil.mavlink
        profile = self.profile
        table = self._modes()
        if name not in table:
            raise LinkError(f"unknown {profile.display_name} mode {name!r}; known: {sorted(table)}")
        custom = table[name]
        if profile.mode_command_main_sub:
            params = [m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, (custom >> 16) & 0xFF, (custom >> 24) & 0xFF]
        else:
            params = [m.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, custom]
        self.command(
            m.MAV_CMD_DO_SET_MODE, params, timeout_s=ack_timeout_s, what=f"mode {name}", done_already=lambda: self.telemetry.custom_mode == custom
        )
        if self.telemetry.custom_mode != custom:
            self._poll_heartbeat()
        self.wait_for(lambda: self.telemetry.custom_mode == custom, timeout_s, f"heartbeat in mode {name}")

    def mode_name(self) -> str:
        """The current mode's name (from the last heartbeat), or its number."""
        table = self._modes()
        cm = self.telemetry.custom_mode
        return next((n for n, v in table.items() if v == cm), str(cm))

    def in_mode(self, name: str) -> bool:
        """True when the last heartbeat reports mode ``name``."""
        table = self._modes()
        return self.telemetry.custom_mode == table.get(name)

    def arm(self) -> None:
        """Arm and wait until the heartbeat says armed."""
        m = self.mavutil.mavlink
        tries = self.profile.arm_tries
        for attempt in range(tries):
            try:
                self.command(m.MAV_CMD_COMPONENT_ARM_DISARM, [1], what="arm", done_already=lambda: self.telemetry.armed)
                break
            except LinkTimeout:
                raise
            except LinkError:
                # PX4's pre-arm result flickers ("Preflight Fail: vertical velocity unstable"
                # for a moment while its EKF settles): wait for a new pass, then try again.
                if attempt == tries - 1:
                    raise
                self._wait_for_prearm_pass()
        if not self.telemetry.armed:
            self._poll_heartbeat()
        self.wait_for(lambda: self.telemetry.armed, MODE_CONFIRM_TIMEOUT_S, "armed heartbeat")

    def _wait_for_prearm_pass(self) -> None:
        """Wait (10 s) for a SYS_STATUS, after the next one, whose pre-arm check passes."""
        seen = self.telemetry.sys_status_count
        self.wait_for(
            lambda: self.telemetry.sys_status_count > seen + 1 and bool((self.telemetry.sensors_health or 0) & MAV_SYS_STATUS_PREARM_CHECK),
            10.0,
            "pre-arm checks passing again",
        )

    def takeoff(self, altitude_m: float) -> None:
        """MAV_CMD_NAV_TAKEOFF to ``altitude_m`` above home (acknowledged, not awaited)."""
        m = self.mavutil.mavlink
        start = self.telemetry.position_enu_m
        z0 = float(start[2]) if start is not None else 0.0

        def climbing() -> bool:
            pos = self.telemetry.position_enu_m
            return pos is not None and float(pos[2]) > z0 + 0.01

        self.command(m.MAV_CMD_NAV_TAKEOFF, [0, 0, 0, 0, 0, 0, altitude_m], what=f"takeoff to {altitude_m:g} m", done_already=climbing)

    def home_z_m(self) -> float:
        """Mission-frame height of the vehicle's home (m): from HOME_POSITION with the AMSL
        reference; 0 with the relative one (home on the ground at the origin's height)."""
        h = self.telemetry.home_global
        if self.altitude_reference == "amsl" and h is not None and self.mission_frame is not None:
            return self.mission_frame.to_enu(*h)[2]
        return 0.0

    def send_setpoint(self, position_enu_m: Iterable[float] | None, velocity_enu_mps: Iterable[float] | None) -> None:
        """One setpoint with position and/or velocity (mission ENU, m and m/s), as
        SET_POSITION_TARGET_LOCAL_NED (MAV_FRAME_LOCAL_NED) or SET_POSITION_TARGET_GLOBAL_INT
        (MAV_FRAME_GLOBAL_INT or MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) by the link's frame
        (:class:`comms.mavlink_setpoints.SetpointEncoder`)."""
        if position_enu_m is None and velocity_enu_mps is None:
            raise ValueError("a setpoint needs a position or a velocity")
        self._setpoints.send(self.mav, position_enu_m, velocity_enu_mps, self.profile.relative_alt_as_amsl, self.telemetry.home_global)

    def close(self) -> None:
        """Stop the setpoint stream, close the connection and the .tlog."""
        self._stream.fn = None
        self.transport.close()
