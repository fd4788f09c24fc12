"""The planner's MAVLink link to its own autopilot (vehicle_sim, ArduPilot or PX4).

A thin, typed layer over pymavlink's ``mavutil`` connection: wait for the heartbeat, tell the
autopilot's flavour from HEARTBEAT.autopilot, request streams (SET_MESSAGE_INTERVAL, or
REQUEST_DATA_STREAM where that is refused), report what the vehicle still lacks to fly (GPS
fix, EKF, home, EKF origin), switch modes, arm, take off, stream setpoints and read the
vehicle's position with its timestamp.

Frames (DESIGN.md): the mission frame is ENU about the mission origin.

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
"""

from __future__ import annotations

import errno
import math
import os
import socket
import struct
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from comms.autopilot import EKF_CONST_POS_MODE, EKF_READY_FLAGS, MAV_AUTOPILOT_ARDUPILOTMEGA, MAV_AUTOPILOT_PX4, client_mode_table
from comms.errors import FimnavError, UsageError
from comms.geodesy import MissionFrame
from comms.session import check_secret_file

#: Our MAVLink identity: a companion computer of the vehicle's system.
COMPONENT_ID = 191  # MAV_COMP_ID_ONBOARD_COMPUTER
AUTOPILOT_COMPONENT = 1
#: {mode name: custom_mode} per flavour, from the autopilot profiles (comms.autopilot); PX4's
#: custom modes are main_mode << 16 | sub_mode << 24, its AUTO sub-modes named AUTO.<name>.
ARDUPILOT_MODES = client_mode_table("ardupilot")
PX4_MODES = client_mode_table("px4")
Flavour = Literal["ardupilot", "px4"]
Frame = Literal["local_ned", "global"]
AltitudeReference = Literal["amsl", "relative"]

#: SET_POSITION_TARGET type masks (POSITION_TARGET_TYPEMASK: bits set = ignored). Always
#: ignore acceleration (bits 6-8), yaw (10) and yaw rate (11); ArduPilot and PX4 accept
#: position, velocity and position + velocity with these (ArduPilot: "all 3 axes must be
#: provided"). Position + velocity = 0b1101_1100_0000 = 3520.
MASK_POSITION_VELOCITY = 0b0000_1100_0000_0000 | 0b0000_0001_1100_0000  # use pos + vel
MASK_POSITION = MASK_POSITION_VELOCITY | 0b0000_0000_0011_1000
MASK_VELOCITY = MASK_POSITION_VELOCITY | 0b0000_0000_0000_0111

#: Arming attempts on PX4, whose pre-arm result flickers while its EKF settles.
PX4_ARM_TRIES = 3
#: Deadline (s) for the heartbeat that confirms a mode change or arming (heartbeats are 1 Hz;
#: a loaded machine starting dozens of processes can delay them by seconds).
MODE_CONFIRM_TIMEOUT_S: float = 30.0
#: No autopilot heartbeat for this long (wall s) = the link is lost (noticed within 3 s).
LINK_LOSS_S: float = 2.0
#: The autopilot's clock rate is measured over at least this many wall seconds of its
#: ``time_boot_ms`` stamps (:class:`ClockWatch`).
CLOCK_WINDOW_S: float = 1.5

MAV_SYS_STATUS_AHRS = 0x200000
MAV_SYS_STATUS_PREARM_CHECK = 0x10000000
MAV_LANDED_STATE_NAMES = {0: "UNDEFINED", 1: "ON_GROUND", 2: "IN_AIR", 3: "TAKEOFF", 4: "LANDING"}

#: Message ids.
MSG_SYS_STATUS = 1
MSG_GPS_RAW_INT = 24
MSG_LOCAL_POSITION_NED = 32
MSG_GLOBAL_POSITION_INT = 33
MSG_GPS_GLOBAL_ORIGIN = 49
MSG_EKF_STATUS_REPORT = 193
MSG_HOME_POSITION = 242
MSG_EXTENDED_SYS_STATE = 245
#: REQUEST_DATA_STREAM groups (ArduPilot) that carry each message, for the fallback.
DATA_STREAM_OF = {
    MSG_SYS_STATUS: 2,
    MSG_GPS_RAW_INT: 2,
    MSG_LOCAL_POSITION_NED: 6,
    MSG_GLOBAL_POSITION_INT: 6,
    MSG_EKF_STATUS_REPORT: 12,
    MSG_HOME_POSITION: 12,
    MSG_EXTENDED_SYS_STATE: 12,
}


#: A vehicle whose frames all fail our signature check for this long (wall s) and at least
#: :data:`WRONG_KEY_MIN_FRAMES` of them was set up with another key: refused at once.
WRONG_KEY_AFTER_S = 3.0
WRONG_KEY_MIN_FRAMES = 5


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


def read_signing_key(path: str | Path) -> bytes:
    """Read a MAVLink 2 signing key file: 32 raw bytes, or 64 hex digits (text).

    The key is a secret: a file that its group or others may read or write is refused
    (``chmod 600 FILE``), and the key itself never appears in a message.

    Raises:
        UsageError: missing or unreadable file, permissions too open, wrong length/content.
    """
    p = Path(path)
    check_secret_file(p, "signing key")
    try:
        data = p.read_bytes()
    except OSError as exc:
        raise UsageError(f"signing key {str(p)!r}: {exc.strerror or exc}") from None
    if len(data) == 32:
        return data
    text = data.strip()
    if len(text) == 64:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise UsageError(f"signing key {str(p)!r}: expected 32 raw bytes or 64 hex digits, found {len(data)} bytes")


def _frame_or_garbage_buffered(mav: Any) -> bool:
    """True when pymavlink's parser buffer holds a whole frame, or a byte that is not a
    frame start (the parser skips it): parsing can go on without reading more. False when it
    is empty or holds only the beginning of a frame. (``bytes_needed()`` cannot tell: it
    stays at 1 while several frames are buffered.)"""
    buf = mav.buf
    i = mav.buf_index
    avail = len(buf) - i
    if avail <= 0:
        return False
    magic = buf[i]
    if magic == 0xFD:  # MAVLink 2: 10-byte header, payload, CRC, optional 13-byte signature
        if avail < 3:
            return False
        need = 10 + buf[i + 1] + 2 + (13 if buf[i + 2] & 0x01 else 0)
    elif magic == 0xFE:  # MAVLink 1: 6-byte header, payload, CRC
        if avail < 2:
            return False
        need = 6 + buf[i + 1] + 2
    else:
        return True
    return avail >= need


def enu_to_ned(v: Iterable[float]) -> tuple[float, float, float]:
    """(x east, y north, z up) → (north, east, down)."""
    x, y, z = v
    return float(y), float(x), float(-z)


def ned_to_enu(n: float, e: float, d: float) -> np.ndarray:
    """(north, east, down) → (x east, y north, z up)."""
    return np.array([e, n, -d], dtype=float)


def flavour_of_autopilot(autopilot: int | None) -> Flavour | None:
    """The flavour of a HEARTBEAT.autopilot value (MAV_AUTOPILOT_*), or None if unknown."""
    if autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    if autopilot == MAV_AUTOPILOT_PX4:
        return "px4"
    return None


class ClockWatch:
    """The rate of the autopilot's clock against the wall clock: ``time_boot_ms`` of its
    messages against our wall clock on receipt, over a sliding window.

    The rate is the median of the slopes between pairs of samples at least half the window
    apart (Theil-Sen): a message delayed by a stalled process or a burst read at once moves
    a few slopes, not the median. A ``time_boot_ms`` that goes back (a reboot) starts over.
    ArduPilot SITL's and fimnav's simulated vehicle's ``time_boot_ms`` run on simulated time,
    so the rate is their speed-up; a real autopilot's is 1."""

    def __init__(self, keep_s: float = 10.0) -> None:
        self.keep_s = keep_s
        self.samples: list[tuple[float, float]] = []  # (wall s, boot s)

    def add(self, wall_s: float, time_boot_ms: int) -> None:
        boot = time_boot_ms * 1e-3
        if self.samples:
            last_wall, last_boot = self.samples[-1]
            if boot < last_boot - 1.0:
                self.samples.clear()  # the autopilot rebooted
            elif wall_s - last_wall < 0.02:
                return  # a burst read at once: one sample of it is enough
        self.samples.append((wall_s, boot))
        while self.samples and wall_s - self.samples[0][0] > self.keep_s:
            self.samples.pop(0)

    def span_s(self) -> float:
        """Wall seconds covered by the samples."""
        return self.samples[-1][0] - self.samples[0][0] if len(self.samples) > 1 else 0.0

    def rate(self, min_span_s: float = CLOCK_WINDOW_S) -> float | None:
        """Autopilot seconds per wall second, or None until ``min_span_s`` wall seconds of
        samples are in."""
        if self.span_s() < min_span_s or len(self.samples) < 4:
            return None
        pts = self.samples
        if len(pts) > 40:
            step = len(pts) / 40.0
            pts = [pts[int(i * step)] for i in range(40)] + [pts[-1]]
        half = 0.5 * min_span_s
        slopes = [(b2 - b1) / (w2 - w1) for i, (w1, b1) in enumerate(pts) for (w2, b2) in pts[i + 1 :] if w2 - w1 >= half]
        return float(np.median(slopes)) if slopes else None


@dataclass
class Telemetry:
    """What the link has heard of the vehicle (updated by :meth:`VehicleLink.pump`).

    Positions are in the mission ENU frame (m), converted from LOCAL_POSITION_NED or from
    GLOBAL_POSITION_INT according to the link's frame; ``position_time_ms`` is the vehicle's
    ``time_boot_ms`` of that message and ``position_wall_s`` our wall clock on receipt.
    """

    heartbeat_wall_s: float = -math.inf
    heartbeats: int = 0
    autopilot: int | None = None
    custom_mode: int | None = None
    armed: bool = False
    position_enu_m: np.ndarray | None = None
    velocity_enu_mps: np.ndarray | None = None
    position_time_ms: int = -1
    position_wall_s: float = -math.inf
    home_known: bool = False
    home_global: tuple[float, float, float] | None = None  # lat deg, lon deg, alt m AMSL
    origin_global: tuple[float, float, float] | None = None  # EKF origin, same units
    gps_fix_type: int | None = None
    satellites: int | None = None
    sensors_present: int | None = None
    sensors_health: int | None = None
    sys_status_count: int = 0
    ekf_flags: int | None = None
    landed_state: int | None = None
    signed_seen: bool = False
    statustexts: list[str] = field(default_factory=list)


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
        flavour: force ``"ardupilot"`` or ``"px4"``; None: from HEARTBEAT.autopilot.
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
        self.conn: Any = None
        self.foreign_datagrams = 0
        self.reconnects = 0
        self.tlog_path = Path(tlog) if tlog is not None else None
        self._tlog: Any = None
        self._open()
        self.telemetry = Telemetry()
        self.clock = ClockWatch()
        self._last_gcs_heartbeat = -math.inf
        self.acks: dict[int, int] = {}
        self.statustexts = self.telemetry.statustexts
        self._stream: Callable[[float], tuple[np.ndarray | None, np.ndarray | None]] | None = None
        self.stream_period_s = 0.25
        self._stream_last = -math.inf
        self.setpoints_sent = 0

    def _open(self) -> None:
        tcp = self.connection.startswith("tcp:")
        deadline = self.wall() + (self.connect_timeout_s if tcp else 0.0)
        while True:
            try:
                self.conn = self.mavutil.mavlink_connection(
                    self.connection,
                    source_system=self._source_system,
                    source_component=self.source_component,
                    dialect="ardupilotmega",
                    **({"retries": 0} if tcp else {}),
                )
                break
            except ConnectionRefusedError as exc:
                # A TCP autopilot or SITL that is not listening yet: try again until the deadline.
                if self.wall() >= deadline:
                    raise LinkError(f"cannot open MAVLink connection {self.connection!r} within {self.connect_timeout_s:g} s: {exc}") from None
                time.sleep(0.25)
            except Exception as exc:  # pymavlink raises bare OSError/ValueError/SerialException
                raise LinkError(f"cannot open MAVLink connection {self.connection!r}: {exc}") from None
        self.mav = self.conn.mav
        if isinstance(self.conn, self.mavutil.mavudp):
            self._datagram_receiver(self.conn)
        elif isinstance(self.conn, self.mavutil.mavtcp):
            self._tcp_transport(self.conn)
        if self._signing_key is not None:
            self.conn.setup_signing(self._signing_key, sign_outgoing=True, allow_unsigned_callback=lambda *_: False)
        if self.tlog_path is not None:
            self._start_tlog(self.tlog_path)

    def _start_tlog(self, path: Path) -> None:
        """Log every frame in (each parsed message, stamped on receipt, in :meth:`pump`) and
        out (our own frames, stamped when written) to ``path``."""
        path.parent.mkdir(parents=True, exist_ok=True)
        self._tlog = open(path, "wb")  # noqa: SIM115 - closed by close()
        write = self.conn.write
        tlog = self._tlog

        def logged_write(buf: bytes) -> Any:
            try:
                tlog.write(struct.pack(">Q", int(time.time() * 1e6)) + bytes(buf))
            except (ValueError, OSError):
                pass  # closed
            return write(buf)

        self.conn.write = logged_write

    def _datagram_receiver(self, conn: Any) -> None:
        """Read the UDP socket ourselves: with ``udpout`` only datagrams from the vehicle's
        address are accepted (others are counted in :attr:`foreign_datagrams`), and a frame
        left unfinished at the end of a datagram is dropped before the next datagram is
        parsed, so a stray byte from any host cannot swallow the vehicle's next frames
        (MAVLink senders put whole frames in each datagram)."""
        peer = None if conn.udp_server else conn.destination_addr
        mav = conn.mav
        self.foreign_datagrams = 0

        def recv(n: int | None = None) -> bytes | str:
            if _frame_or_garbage_buffered(mav):
                return b""  # the current datagram still holds something to parse
            while True:
                try:
                    data, addr = conn.port.recvfrom(65535)
                except (BlockingIOError, InterruptedError):
                    return b""
                except OSError as exc:
                    if exc.errno in (errno.EAGAIN, errno.EWOULDBLOCK, errno.ECONNREFUSED):
                        return b""
                    raise
                if peer is not None and addr != peer:
                    self.foreign_datagrams += 1
                    continue
                if conn.udp_server:
                    conn.clients.add(addr)
                    conn.clients_last_alive[addr] = time.time()
                if mav.buf_len() > 0:  # an unfinished frame of the previous datagram
                    mav.buf = bytearray()
                    mav.buf_index = 0
                    mav.expected_length = 8  # HEADER_LEN_V1 + 2, the parser's initial state
                    mav.have_prefix_error = False
                return data

        conn.recv = recv

    def _tcp_transport(self, conn: Any) -> None:
        """A TCP connection that never blocks the planner: a closed or reset connection is
        dropped at once (nothing printed, nothing raised) and opened again at most once per
        second from :meth:`pump` (0.2 s connect timeout), e.g. to an autopilot or SITL that
        restarts on the same port. Frames that cannot be written while it is down are lost,
        as on a radio link."""
        dest = conn.destination_addr
        mav = conn.mav
        next_try = [0.0]

        def down() -> None:
            if conn.port is not None:
                try:
                    conn.port.close()
                except OSError:
                    pass
                conn.port = None

        def recv(n: int | None = None) -> bytes:
            if conn.port is None:
                now = self.wall()
                if now < next_try[0]:
                    return b""
                next_try[0] = now + 1.0
                try:
                    sock = socket.create_connection(dest, timeout=0.2)
                except OSError:
                    return b""
                sock.setblocking(False)
                sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                conn.port = sock
                conn.fd = sock.fileno()
                mav.buf = bytearray()  # a frame cut by the old connection is gone
                mav.buf_index = 0
                mav.expected_length = 8
                self.reconnects += 1
            try:
                data = conn.port.recv(n if n and n > 0 else 4096)
            except (BlockingIOError, InterruptedError):
                return b""
            except OSError:
                down()
                return b""
            if not data:
                down()
            return data

        def write(buf: bytes) -> None:
            if conn.port is None:
                return
            try:
                conn.port.send(buf)
            except (BlockingIOError, InterruptedError):
                pass  # send buffer full: this frame is lost
            except OSError:
                down()

        conn.recv = recv
        conn.write = write

    # -- identity ---------------------------------------------------------------------------
    @property
    def flavour(self) -> Flavour:
        """The autopilot flavour: the forced one, else HEARTBEAT.autopilot (ArduPilot when the
        heartbeat names neither)."""
        if self.forced_flavour is not None:
            return self.forced_flavour
        return flavour_of_autopilot(self.telemetry.autopilot) or "ardupilot"

    @property
    def is_px4(self) -> bool:
        return self.flavour == "px4"

    # -- receiving --------------------------------------------------------------------------
    def pump(self, timeout_s: float = 0.0) -> int:
        """Read every pending message (waiting up to ``timeout_s`` for the first); return how
        many were for us. Sends our own 1 Hz heartbeat and the due setpoint as side effects."""
        self._heartbeat_out()
        self._stream_out()
        n = 0
        deadline = self.wall() + timeout_s
        while True:
            remaining = deadline - self.wall()
            try:
                msg = self.conn.recv_match(blocking=remaining > 0 and n == 0, timeout=max(remaining, 0.0))
            except (OSError, ValueError):
                return n  # a transport error is a silent link: the heartbeat timeout reports it
            if msg is None:
                return n
            if self._tlog is not None and msg.get_type() != "BAD_DATA":
                try:
                    self._tlog.write(struct.pack(">Q", int(getattr(msg, "_timestamp", time.time()) * 1e6)) + msg.get_msgbuf())
                except (ValueError, OSError):
                    pass
            if self._handle(msg):
                n += 1

    def _handle(self, msg: Any) -> bool:
        if msg.get_srcSystem() != self.target_system:
            return False
        kind = msg.get_type()
        if kind == "BAD_DATA":
            return False
        tel = self.telemetry
        boot_ms = getattr(msg, "time_boot_ms", None)
        if boot_ms is not None and msg.get_srcComponent() == AUTOPILOT_COMPONENT:
            self.clock.add(self.wall(), int(boot_ms))
        if self.mav.signing.sig_count:
            tel.signed_seen = True  # (frames with a signature block, checked or not)
        if kind == "HEARTBEAT" and msg.get_srcComponent() == AUTOPILOT_COMPONENT:
            tel.heartbeat_wall_s = self.wall()
            tel.heartbeats += 1
            tel.autopilot = msg.autopilot
            tel.custom_mode = msg.custom_mode
            tel.armed = bool(msg.base_mode & 128)
        elif kind == "LOCAL_POSITION_NED":
            if self.frame == "local_ned" and msg.time_boot_ms >= tel.position_time_ms:
                tel.position_time_ms = msg.time_boot_ms
                tel.position_wall_s = self.wall()
                tel.position_enu_m = ned_to_enu(msg.x, msg.y, msg.z)
                tel.velocity_enu_mps = ned_to_enu(msg.vx, msg.vy, msg.vz)
        elif kind == "GLOBAL_POSITION_INT":
            if msg.lat == 0 and msg.lon == 0:
                pass  # no position yet (ArduPilot reports 0, 0 before its first fix)
            elif self.frame == "global" and (msg.time_boot_ms >= tel.position_time_ms or msg.time_boot_ms < tel.position_time_ms - 10_000):
                # (a time_boot_ms far behind the last one: the autopilot rebooted)
                if self.mission_frame is None:
                    raise RuntimeError("frame 'global' without a mission frame (checked when the link is made)")
                x, y, z = self.mission_frame.to_enu(msg.lat * 1e-7, msg.lon * 1e-7, msg.alt * 1e-3)
                if self.altitude_reference == "relative":
                    z = msg.relative_alt * 1e-3
                tel.position_time_ms = msg.time_boot_ms
                tel.position_wall_s = self.wall()
                tel.position_enu_m = np.array([x, y, z], dtype=float)
                tel.velocity_enu_mps = ned_to_enu(msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01)
        elif kind == "HOME_POSITION":
            tel.home_known = True
            tel.home_global = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        elif kind == "GPS_GLOBAL_ORIGIN":
            tel.origin_global = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        elif kind == "GPS_RAW_INT":
            tel.gps_fix_type = msg.fix_type
            tel.satellites = msg.satellites_visible
        elif kind == "SYS_STATUS":
            tel.sys_status_count += 1
            tel.sensors_present = msg.onboard_control_sensors_present
            tel.sensors_health = msg.onboard_control_sensors_health
        elif kind == "EKF_STATUS_REPORT":
            tel.ekf_flags = msg.flags
        elif kind == "EXTENDED_SYS_STATE":
            tel.landed_state = msg.landed_state
        elif kind == "COMMAND_ACK":
            self.acks[msg.command] = msg.result
        elif kind == "STATUSTEXT":
            text = msg.text if isinstance(msg.text, str) else bytes(msg.text).decode("utf-8", "replace")
            tel.statustexts.append(text.rstrip("\x00"))
        return True

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float, what: str) -> None:
        """Pump messages until ``predicate()`` holds; :class:`LinkTimeout` naming ``what``."""
        deadline = self.wall() + timeout_s
        while not predicate():
            remaining = deadline - self.wall()
            if remaining <= 0:
                raise LinkTimeout(f"vehicle {self.target_system}: no {what} within {timeout_s:g} s{self._signing_hint()}")
            self.pump(min(remaining, 0.02 if self._stream is not None else 0.05))

    def _signing_hint(self) -> str:
        if self._signing_key is not None and self.mav.signing.badsig_count:
            return (
                f" ({self.mav.signing.badsig_count} frames from the vehicle carried a signature that does not "
                "match our signing key: check that both use the same key)"
            )
        if self._signing_key is None and (self.telemetry.signed_seen or self.mav.signing.sig_count):
            return (
                " (the vehicle signs its messages: it probably refuses our unsigned ones; give the "
                "signing key with --signing-key or vehicles.overrides[i].signing_key_file)"
            )
        return ""

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
            if (
                self._signing_key is not None
                and sig.badsig_count >= WRONG_KEY_MIN_FRAMES
                and sig.goodsig_count == 0
                and self.wall() - t0 >= WRONG_KEY_AFTER_S
            ):
                raise LinkError(
                    f"vehicle {self.target_system}: every frame from it for {self.wall() - t0:.0f} s "
                    f"({sig.badsig_count} frames) carried a signature that does not match our signing key: "
                    "the vehicle was set up with another key (check --signing-key / signing_key_file)"
                )
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
        if isinstance(self.conn, self.mavutil.mavtcp) and self.conn.port is None:
            return None  # TCP down: nothing to wait on until pump() reconnects
        fd = getattr(self.conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def link_age_s(self) -> float:
        """Seconds since the last autopilot heartbeat."""
        return self.wall() - self.telemetry.heartbeat_wall_s

    @property
    def lost(self) -> bool:
        """No autopilot heartbeat for :data:`LINK_LOSS_S` (after having heard one)."""
        return self.telemetry.heartbeats > 0 and self.link_age_s() > LINK_LOSS_S

    # -- readiness --------------------------------------------------------------------------
    def not_ready(self, require_gps: bool = True) -> list[str]:
        """What the vehicle still lacks to fly by setpoints, in words (empty: ready).

        GPS 3D fix (GPS_RAW_INT.fix_type ≥ 3; only with ``require_gps``: a vehicle flown in
        LOCAL_NED may navigate without GPS, e.g. on motion capture); EKF: EKF_STATUS_REPORT with attitude, velocity
        and absolute position and not in constant-position mode (ArduPilot), or, where the
        autopilot sends no such report (PX4, vehicle_sim), SYS_STATUS with the AHRS healthy;
        the pre-arm checks passed where SYS_STATUS reports them; home position
        (HOME_POSITION); EKF origin (GPS_GLOBAL_ORIGIN)."""
        t = self.telemetry
        missing = []
        if not require_gps:
            pass
        elif t.gps_fix_type is None:
            missing.append("GPS status (no GPS_RAW_INT yet)")
        elif t.gps_fix_type < 3:
            missing.append(f"GPS 3D fix (fix_type {t.gps_fix_type}, {t.satellites} satellites)")
        if t.ekf_flags is not None:
            if (t.ekf_flags & EKF_READY_FLAGS) != EKF_READY_FLAGS or t.ekf_flags & EKF_CONST_POS_MODE:
                missing.append(f"EKF position estimate (EKF_STATUS_REPORT flags {t.ekf_flags:#06x})")
        elif t.sensors_present is None:
            missing.append("system status (no SYS_STATUS yet)")
        elif t.sensors_present & MAV_SYS_STATUS_AHRS and not (t.sensors_health or 0) & MAV_SYS_STATUS_AHRS:
            missing.append("EKF/AHRS healthy (SYS_STATUS)")
        # PX4 reports its pre-arm result as the PREARM_CHECK health bit alone (never present or
        # enabled): set while the vehicle could arm in its current mode. Disarmed in OFFBOARD
        # (PX4 returns to it after landing a flight flown in OFFBOARD) it stays clear until a
        # setpoint stream runs, which the planner starts only once ready: not awaited there.
        if self.is_px4:
            prearm_reported = t.sensors_present is not None and not self.in_mode("OFFBOARD")
        else:
            prearm_reported = t.sensors_present is not None and bool(t.sensors_present & MAV_SYS_STATUS_PREARM_CHECK)
        if prearm_reported and not t.armed and not ((t.sensors_health or 0) & MAV_SYS_STATUS_PREARM_CHECK):
            reason = next((s for s in reversed(t.statustexts) if s.lower().startswith("prearm")), "")
            missing.append("pre-arm checks" + (f" ({reason})" if reason else ""))
        if self.is_px4 and t.position_enu_m is None:
            # PX4 sends HOME_POSITION before its EKF has aligned, and no GLOBAL_POSITION_INT
            # (no LOCAL_POSITION_NED with a valid position) until it has.
            missing.append(
                "position estimate (no GLOBAL_POSITION_INT yet)" if self.frame == "global" else "position estimate (no LOCAL_POSITION_NED yet)"
            )
        if not t.home_known:
            missing.append("home position (HOME_POSITION)")
        if t.origin_global is None:
            missing.append("EKF origin (GPS_GLOBAL_ORIGIN)")
        return missing

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

    def set_stream(self, fn: Callable[[float], tuple[np.ndarray | None, np.ndarray | None]] | None, period_s: float | None = None) -> None:
        """Stream ``fn(wall_s) -> (position ENU m | None, velocity ENU m/s | None)`` every
        ``period_s`` wall seconds from now on (sent at once); None stops the stream."""
        self._stream = fn
        if period_s is not None:
            self.stream_period_s = period_s
        self._stream_last = -math.inf
        self._stream_out()

    def _stream_out(self) -> None:
        if self._stream is None:
            return
        now = self.wall()
        if now - self._stream_last < self.stream_period_s:
            return
        # On a grid of the period (a late wake-up does not slow the average rate down), but
        # never more than one period behind (no burst after a stall).
        last = self._stream_last
        self._stream_last = now if last == -math.inf else max(last + self.stream_period_s, now - self.stream_period_s)
        pos, vel = self._stream(now)
        try:
            self.send_setpoint(pos, vel)
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
        """Request each message at its rate with SET_MESSAGE_INTERVAL; where the autopilot
        refuses it or does not answer (older firmware, some radios), fall back to
        REQUEST_DATA_STREAM for the message's ArduPilot stream group. Messages in ``optional``
        may be refused without a fallback (e.g. EKF_STATUS_REPORT on PX4). Returns notes of
        what fell back, for the log."""
        m = self.mavutil.mavlink
        optional = set(optional)
        notes: list[str] = []
        fallback: dict[int, float] = {}
        unanswered = False
        for msg_id, hz in rates_hz.items():
            try:
                if unanswered:  # one unanswered request is enough: do not spend 6 s on each
                    raise LinkTimeout("SET_MESSAGE_INTERVAL not answered")
                self.command(m.MAV_CMD_SET_MESSAGE_INTERVAL, [msg_id, 1e6 / hz], timeout_s=6.0, what=f"SET_MESSAGE_INTERVAL({msg_id})")
            except LinkTimeout:
                unanswered = True
                if msg_id in DATA_STREAM_OF:
                    group = DATA_STREAM_OF[msg_id]
                    fallback[group] = max(fallback.get(group, 0.0), hz)
                notes.append(f"message {msg_id}: no answer to SET_MESSAGE_INTERVAL, REQUEST_DATA_STREAM instead")
            except LinkError as exc:
                if msg_id in optional:
                    notes.append(f"message {msg_id}: not streamed ({exc})")
                    continue
                if msg_id in DATA_STREAM_OF:
                    group = DATA_STREAM_OF[msg_id]
                    fallback[group] = max(fallback.get(group, 0.0), hz)
                notes.append(f"message {msg_id}: SET_MESSAGE_INTERVAL refused, REQUEST_DATA_STREAM instead")
        for group, hz in fallback.items():
            self.mav.request_data_stream_send(self.target_system, AUTOPILOT_COMPONENT, group, max(1, int(math.ceil(hz))), 1)
        return notes

    def set_mode(self, name: str, timeout_s: float = MODE_CONFIRM_TIMEOUT_S) -> None:
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
        if self.telemetry.custom_mode != custom:
            self._poll_heartbeat()
        self.wait_for(lambda: self.telemetry.custom_mode == custom, timeout_s, f"heartbeat in mode {name}")

    def mode_name(self) -> str:
        """The current mode's name (from the last heartbeat), or its number."""
        table = PX4_MODES if self.is_px4 else ARDUPILOT_MODES
        cm = self.telemetry.custom_mode
        return next((n for n, v in table.items() if v == cm), str(cm))

    def in_mode(self, name: str) -> bool:
        """True when the last heartbeat reports mode ``name``."""
        table = PX4_MODES if self.is_px4 else ARDUPILOT_MODES
        return self.telemetry.custom_mode == table.get(name)

    def arm(self) -> None:
        """Arm and wait until the heartbeat says armed."""
        m = self.mavutil.mavlink
        tries = PX4_ARM_TRIES if self.is_px4 else 1
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
        (MAV_FRAME_GLOBAL_INT or MAV_FRAME_GLOBAL_RELATIVE_ALT_INT) by the link's frame."""
        m = self.mavutil.mavlink
        if position_enu_m is None and velocity_enu_mps is None:
            raise ValueError("a setpoint needs a position or a velocity")
        mask = (
            MASK_POSITION_VELOCITY
            if position_enu_m is not None and velocity_enu_mps is not None
            else (MASK_POSITION if velocity_enu_mps is None else MASK_VELOCITY)
        )
        vn, ve, vd = enu_to_ned(velocity_enu_mps) if velocity_enu_mps is not None else (0.0, 0.0, 0.0)
        self.setpoints_sent += 1
        if self.frame == "local_ned":
            n, e, d = enu_to_ned(position_enu_m) if position_enu_m is not None else (0.0, 0.0, 0.0)
            self.mav.set_position_target_local_ned_send(
                0, self.target_system, AUTOPILOT_COMPONENT, m.MAV_FRAME_LOCAL_NED, mask, n, e, d, vn, ve, vd, 0, 0, 0, 0, 0
            )
            return
        if self.mission_frame is None:
            raise RuntimeError("frame 'global' without a mission frame (checked when the link is made)")
        lat_e7 = lon_e7 = 0
        alt = 0.0
        if position_enu_m is not None:
            x, y, z = (float(v) for v in position_enu_m)
            g = self.mission_frame.to_global(x, y, z)
            lat_e7, lon_e7 = g.lat_e7, g.lon_e7
            alt = g.alt_amsl_m if self.altitude_reference == "amsl" else z
        frame = m.MAV_FRAME_GLOBAL_INT if self.altitude_reference == "amsl" else m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT
        home = self.telemetry.home_global
        if self.is_px4 and frame == m.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT and home is not None:
            # PX4 (v1.15 and earlier) converts a GLOBAL_RELATIVE_ALT_INT altitude to local z as
            # home − alt − EKF-origin altitude, i.e. with the sign of (home − origin altitude)
            # reversed: off by twice the local z of home (1-4 m on PX4 SITL). The same target
            # as an AMSL altitude (home's AMSL altitude from HOME_POSITION + z) is converted right.
            frame = m.MAV_FRAME_GLOBAL_INT
            alt = home[2] + alt
        self.mav.set_position_target_global_int_send(
            0, self.target_system, AUTOPILOT_COMPONENT, frame, mask, lat_e7, lon_e7, alt, vn, ve, vd, 0, 0, 0, 0, 0
        )

    def close(self) -> None:
        self._stream = None
        try:
            self.conn.close()
        except (OSError, AttributeError):  # (a TCP connection already dropped has no socket)
            pass
        if self._tlog is not None:
            self._tlog.close()
            self._tlog = None
