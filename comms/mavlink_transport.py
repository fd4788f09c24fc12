"""The transport under the planner's MAVLink link (:class:`comms.mavlink_client.VehicleLink`):
opening pymavlink's connection, reading UDP and TCP so that no stray byte or dropped connection
can stall or mislead the planner, MAVLink 2 signing, and the .tlog of every frame in and out.

* UDP: the socket is read by us: with ``udpout`` only datagrams from the vehicle's address are
  accepted (others are counted), and a frame left unfinished at the end of a datagram is dropped
  before the next datagram is parsed.
* TCP: never blocks the planner: a closed or reset connection is dropped at once and opened
  again at most once per second (e.g. to an autopilot or SITL that restarts on the same port).
"""

from __future__ import annotations

import errno
import ipaddress
import os
import socket
import struct
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from comms.errors import FimnavError


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


def _reset_parser(mav: Any) -> None:
    """Drop what pymavlink's parser holds of an unfinished frame (back to its initial state)."""
    mav.buf = bytearray()
    mav.buf_index = 0
    mav.expected_length = 8  # HEADER_LEN_V1 + 2, the parser's initial state


class MavlinkTransport:
    """One open MAVLink connection (pymavlink ``mavutil``) with our UDP/TCP readers, signing
    and .tlog.

    Args:
        mavutil: pymavlink's mavutil (:func:`mavutil_module`).
        connection: pymavlink connection string (``udpout:127.0.0.1:14550``, ``tcp:...``,
            ``/dev/ttyUSB0,57600``).
        source_system, source_component: our MAVLink identity.
        signing_key: 32-byte MAVLink 2 signing key (everything sent is signed, unsigned input
            refused), or None.
        wall: monotonic clock (s), for the connect deadline and the TCP reconnect period.
        connect_timeout_s: how long a ``tcp:`` connection is retried while refused (s).
        tlog: write every frame received and sent to this .tlog (MAVProxy's format:
            big-endian µs UNIX time + frame), or None.

    Raises:
        LinkError: the connection cannot be opened.
    """

    def __init__(
        self,
        mavutil: Any,
        connection: str,
        source_system: int,
        source_component: int,
        signing_key: bytes | None,
        wall: Callable[[], float],
        connect_timeout_s: float,
        tlog: Path | None,
    ) -> None:
        self.mavutil = mavutil
        self.connection = connection
        self.wall = wall
        self.connect_timeout_s = connect_timeout_s
        #: UDP datagrams from another address than the vehicle's (dropped).
        self.foreign_datagrams = 0
        #: TCP connections opened again after a drop.
        self.reconnects = 0
        self._tlog: Any = None
        self.conn: Any = self._connect(source_system, source_component)
        self.mav: Any = self.conn.mav
        if isinstance(self.conn, mavutil.mavudp):
            _bind_loopback_sender(self.conn)
            self._datagram_receiver(self.conn)
        elif isinstance(self.conn, mavutil.mavtcp):
            self._tcp_transport(self.conn)
        if signing_key is not None:
            self.conn.setup_signing(signing_key, sign_outgoing=True, allow_unsigned_callback=lambda *_: False)
        if tlog is not None:
            self._start_tlog(tlog)

    def _connect(self, source_system: int, source_component: int) -> Any:
        """pymavlink's connection; a refused ``tcp:`` one is retried until the deadline."""
        tcp = self.connection.startswith("tcp:")
        deadline = self.wall() + (self.connect_timeout_s if tcp else 0.0)
        while True:
            try:
                return self.mavutil.mavlink_connection(
                    self.connection,
                    source_system=source_system,
                    source_component=source_component,
                    dialect="ardupilotmega",
                    **({"retries": 0} if tcp else {}),
                )
            except ConnectionRefusedError as exc:
                # A TCP autopilot or SITL that is not listening yet: try again until the deadline.
                if self.wall() >= deadline:
                    raise LinkError(f"cannot open MAVLink connection {self.connection!r} within {self.connect_timeout_s:g} s: {exc}") from None
                time.sleep(0.25)
            except Exception as exc:  # pymavlink raises bare OSError/ValueError/SerialException
                raise LinkError(f"cannot open MAVLink connection {self.connection!r}: {exc}") from None

    def _start_tlog(self, path: Path) -> None:
        """Log every frame in (each parsed message, stamped on receipt, :meth:`log_received`)
        and out (our own frames, stamped when written) to ``path``."""
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

    def log_received(self, msg: Any) -> None:
        """Write a received message to the .tlog (if any), stamped with its receipt time."""
        if self._tlog is not None and msg.get_type() != "BAD_DATA":
            try:
                self._tlog.write(struct.pack(">Q", int(getattr(msg, "_timestamp", time.time()) * 1e6)) + msg.get_msgbuf())
            except (ValueError, OSError):
                pass

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
                    _reset_parser(mav)
                    mav.have_prefix_error = False
                return data

        conn.recv = recv

    def _tcp_transport(self, conn: Any) -> None:
        """A TCP connection that never blocks the planner: a closed or reset connection is
        dropped at once (nothing printed, nothing raised) and opened again at most once per
        second from the link's pump (0.2 s connect timeout), e.g. to an autopilot or SITL that
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
                _reset_parser(mav)  # a frame cut by the old connection is gone
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

    def fileno(self) -> int | None:
        """The file descriptor to select() on for incoming MAVLink, if the transport has one."""
        if isinstance(self.conn, self.mavutil.mavtcp) and self.conn.port is None:
            return None  # TCP down: nothing to wait on until the pump reconnects
        fd = getattr(self.conn, "fd", None)
        return fd if isinstance(fd, int) and fd >= 0 else None

    def close(self) -> None:
        """Close the connection and the .tlog."""
        try:
            self.conn.close()
        except (OSError, AttributeError):  # (a TCP connection already dropped has no socket)
            pass
        if self._tlog is not None:
            self._tlog.close()
            self._tlog = None


def _bind_loopback_sender(conn: Any) -> None:
    """Bind a ``udpout`` socket to the loopback interface when its vehicle is on this machine.

    An unbound UDP socket is bound to 0.0.0.0 (every interface) by its first ``sendto``, and would
    then take datagrams from other hosts; a vehicle at 127.0.0.1 is reached from 127.0.0.1 alone
    (docs/security.md). A socket that is already bound, or a ``udpin``
    one, is left as it is."""
    if conn.udp_server:
        return
    try:
        host = conn.destination_addr[0]
        if not ipaddress.ip_address(host).is_loopback or conn.port.getsockname()[1] != 0:
            return
        conn.port.bind(("127.0.0.1", 0))
    except (ValueError, OSError, IndexError, TypeError):
        return  # a host name or an address family we do not rebind: pymavlink's default stands
