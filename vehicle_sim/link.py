"""MAVLink transport of a simulated vehicle: sockets, framing, signing, .tlog.

Connection strings are pymavlink's / MAVProxy's:

* ``udpin:HOST:PORT`` (alias ``udp:``): bind and answer every peer that has written to us;
* ``udpout:HOST:PORT``: send to HOST:PORT (from an ephemeral port of the address that routes
  there) and read the replies of HOST:PORT only;
* ``tcpin:HOST:PORT``: listen; several ground stations may connect at once;
* ``tcp:HOST:PORT``: connect (retried every second while refused).

PORT 0 binds an ephemeral port; :attr:`Transport.address` gives the actual one.

The sockets are non-blocking; :meth:`MavlinkLink.receive` drains what is pending and parses it
with one pymavlink parser per peer stream (robust parsing: a malformed frame becomes a
``BAD_DATA`` that is counted and dropped, never an exception). pymavlink is imported lazily
with ``MAVLINK20=1`` so frames are MAVLink 2 (dialect ``ardupilotmega``).

Signing (MAVLink 2): the replay protection belongs to the *link*, not to a peer socket. All
parsers of a link share one signing state: one table of the last timestamp accepted per
stream ``(link id, system id, component id)``, so a signed frame captured on the network and
sent again from another UDP port or TCP connection is refused like one replayed on the same
stream. A frame's signature is verified *before* its timestamp is recorded (pymavlink 2.4.50
records it first, which would let anyone without the key push a stream's timestamp into the
future and lock its sender out of every peer of the link). A stream not seen yet is accepted
if its timestamp is at most one minute behind the link's own (the wall clock, or the newest
valid timestamp received), as the MAVLink 2 signing specification says.

SETUP_SIGNING frames carry the key in clear: they are never written to the .tlog, in either
direction.
"""

from __future__ import annotations

import errno
import hashlib
import hmac
import logging
import os
import socket
import struct
import time
from collections.abc import Callable
from typing import Any, BinaryIO

from comms.errors import UsageError

log = logging.getLogger(__name__)

UDP_MAX = 65535
SIGNING_EPOCH_UNIX_S = 1420070400  # 2015-01-01, the MAVLink 2 signing epoch
SIGNING_NEW_STREAM_WINDOW = 60 * 100_000  # a new signed stream may lag 1 min (10 µs units)
MAVLINK_MSG_ID_SETUP_SIGNING = 256  # carries the signing key in clear: never logged


def mavlink_module() -> Any:
    """The pymavlink MAVLink 2 ``ardupilotmega`` dialect module."""
    os.environ["MAVLINK20"] = "1"
    os.environ.setdefault("MAVLINK_DIALECT", "ardupilotmega")
    from pymavlink.dialects.v20 import ardupilotmega

    return ardupilotmega


#: PROTOCOL_VERSION (id 300) is not generated in pymavlink 2.4.x dialects: encoded here.
PROTOCOL_VERSION_ID = 300
PROTOCOL_VERSION_CRC_EXTRA = 217


def protocol_version_message(
    version: int = 200, min_version: int = 100, max_version: int = 200, spec_hash: bytes = bytes(8), lib_hash: bytes = bytes(8)
) -> Any:
    """A pymavlink-packable PROTOCOL_VERSION message (id 300, CRC extra 217; payload
    ``<HHH8s8s``: version, min_version, max_version, spec_version_hash, library_version_hash)."""
    mavlink_module()  # MAVLink 2 and the dialect are set before pymavlink is imported
    from pymavlink.dialects.v20.ardupilotmega import MAVLink_message

    payload = struct.pack("<HHH8s8s", version, min_version, max_version, spec_hash, lib_hash)

    class _ProtocolVersion(MAVLink_message):
        id = PROTOCOL_VERSION_ID
        msgname = "PROTOCOL_VERSION"
        crc_extra = PROTOCOL_VERSION_CRC_EXTRA

        def __init__(self) -> None:
            super().__init__(PROTOCOL_VERSION_ID, "PROTOCOL_VERSION")
            self._fieldnames = ["version", "min_version", "max_version"]
            self.version, self.min_version, self.max_version = version, min_version, max_version

        def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
            return bytes(self._pack(mav, PROTOCOL_VERSION_CRC_EXTRA, payload, force_mavlink1=force_mavlink1))

    return _ProtocolVersion()


def parse_connection(conn: str) -> tuple[str, str, int]:
    """Split a pymavlink connection string into (kind, host, port).

    Raises:
        UsageError: not ``udpin:|udp:|udpout:|tcpin:|tcp:`` + ``HOST:PORT``.
    """
    parts = conn.split(":")
    kinds = ("udpin", "udp", "udpout", "tcpin", "tcp")
    if len(parts) != 3 or parts[0] not in kinds:
        raise UsageError(f"MAVLink connection {conn!r}: expected KIND:HOST:PORT with KIND one of {', '.join(kinds)}")
    kind, host, port_s = parts
    try:
        port = int(port_s)
    except ValueError:
        raise UsageError(f"MAVLink connection {conn!r}: port {port_s!r} is not an integer") from None
    if not 0 <= port <= 65535:
        raise UsageError(f"MAVLink connection {conn!r}: port {port} is outside 0..65535")
    if kind == "udp":
        kind = "udpin"
    if port == 0 and kind in ("udpout", "tcp"):
        raise UsageError(f"MAVLink connection {conn!r}: {kind} needs a destination port, found 0")
    return kind, host, port


class Transport:
    """Base of the socket transports. ``read`` returns (peer key, bytes) chunks."""

    kind = ""
    #: Peers that appeared since the owner last reset this counter.
    new_peers = 0

    def filenos(self) -> list[int]:
        """Sockets worth waiting on with select()."""
        raise NotImplementedError

    def read(self) -> list[tuple[object, bytes]]:
        """Drain pending input without blocking."""
        raise NotImplementedError

    def write(self, buf: bytes) -> None:
        """Send ``buf`` to every connected peer (never blocks, drops on error)."""
        raise NotImplementedError

    def close(self) -> None:
        """Close every socket."""
        raise NotImplementedError

    @property
    def address(self) -> str:
        """The connection string with the actual bound/target port."""
        raise NotImplementedError

    def peers(self) -> int:
        """Number of peers we can currently write to."""
        raise NotImplementedError


class UdpTransport(Transport):
    """``udpin`` (bind, reply to senders) or ``udpout`` (send to a fixed destination)."""

    def __init__(self, kind: str, host: str, port: int) -> None:
        self.kind = kind
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.clients: list[tuple[str, int]] = []
        try:
            if kind == "udpin":
                self.sock.bind((host, port))
                self.dest: tuple[str, int] | None = None
            else:
                self.dest = (socket.gethostbyname(host), port)
                # connected: the kernel binds the source address of the route (127.0.0.1 for
                # a loopback ground station, not 0.0.0.0) and delivers only the destination's
                # datagrams, so no other host can talk to the vehicle through this socket
                self.sock.connect(self.dest)
        except OSError as exc:
            self.sock.close()
            raise UsageError(f"MAVLink connection {kind}:{host}:{port}: {exc.strerror or exc}") from None
        self.sock.setblocking(False)
        self.host = host

    def filenos(self) -> list[int]:
        return [self.sock.fileno()]

    def read(self) -> list[tuple[object, bytes]]:
        out: list[tuple[object, bytes]] = []
        while True:
            try:
                data, addr = self.sock.recvfrom(UDP_MAX)
            except (BlockingIOError, InterruptedError):
                break
            except OSError as exc:
                if exc.errno == errno.ECONNREFUSED:
                    continue
                log.warning("udp receive error: %s", exc)
                break
            if self.kind == "udpin" and addr not in self.clients:
                self.clients.append(addr)
                self.new_peers += 1
            out.append((addr, data))
        return out

    def write(self, buf: bytes) -> None:
        targets = self.clients if self.dest is None else [self.dest]  # udpin: no fixed destination
        for addr in targets:
            try:
                self.sock.sendto(buf, addr)
            except OSError:
                pass

    def close(self) -> None:
        self.sock.close()

    @property
    def address(self) -> str:
        if self.kind == "udpin":
            host, port = self.sock.getsockname()[:2]
            return f"udpin:{host}:{port}"
        if self.dest is None:
            raise RuntimeError(f"UDP transport {self.kind}: no destination address")
        return f"udpout:{self.dest[0]}:{self.dest[1]}"

    def peers(self) -> int:
        return len(self.clients) if self.kind == "udpin" else 1


class TcpInTransport(Transport):
    """``tcpin``: listen and serve every connected client."""

    kind = "tcpin"

    def __init__(self, host: str, port: int) -> None:
        self.listen = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listen.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            self.listen.bind((host, port))
        except OSError as exc:
            self.listen.close()
            raise UsageError(f"MAVLink connection tcpin:{host}:{port}: {exc.strerror or exc}") from None
        self.listen.listen(8)
        self.listen.setblocking(False)
        self.clients: dict[int, socket.socket] = {}

    def filenos(self) -> list[int]:
        return [self.listen.fileno(), *self.clients.keys()]

    def _accept(self) -> None:
        while True:
            try:
                conn, _ = self.listen.accept()
            except (BlockingIOError, InterruptedError):
                return
            except OSError as exc:
                log.warning("tcp accept error: %s", exc)
                return
            conn.setblocking(False)
            conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.clients[conn.fileno()] = conn
            self.new_peers += 1

    def read(self) -> list[tuple[object, bytes]]:
        self._accept()
        out: list[tuple[object, bytes]] = []
        for fd, conn in list(self.clients.items()):
            while True:
                try:
                    data = conn.recv(65536)
                except (BlockingIOError, InterruptedError):
                    break
                except OSError:
                    data = b""
                if not data:
                    conn.close()
                    del self.clients[fd]
                    out.append((("closed", fd), b""))
                    break
                out.append((fd, data))
        return out

    def write(self, buf: bytes) -> None:
        for fd, conn in list(self.clients.items()):
            try:
                conn.sendall(buf)
            except (BlockingIOError, InterruptedError):
                pass  # a slow client loses this frame, as on a lossy radio link
            except OSError:
                conn.close()
                del self.clients[fd]

    def close(self) -> None:
        for conn in self.clients.values():
            conn.close()
        self.clients.clear()
        self.listen.close()

    @property
    def address(self) -> str:
        host, port = self.listen.getsockname()[:2]
        return f"tcpin:{host}:{port}"

    def peers(self) -> int:
        return len(self.clients)


class TcpOutTransport(Transport):
    """``tcp``: connect to a listening ground station; retry every second while refused."""

    kind = "tcp"
    RETRY_S = 1.0

    def __init__(self, host: str, port: int, wall: Callable[[], float] = time.monotonic) -> None:
        self.dest = (host, port)
        self.sock: socket.socket | None = None
        self._wall = wall
        self._next_try = 0.0
        self._connect()

    def _connect(self) -> None:
        now = self._wall()
        if self.sock is not None or now < self._next_try:
            return
        self._next_try = now + self.RETRY_S
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.settimeout(0.2)
        try:
            sock.connect(self.dest)
        except OSError:
            sock.close()
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.sock = sock
        self.new_peers += 1

    def filenos(self) -> list[int]:
        return [] if self.sock is None else [self.sock.fileno()]

    def read(self) -> list[tuple[object, bytes]]:
        self._connect()
        if self.sock is None:
            return []
        out: list[tuple[object, bytes]] = []
        while True:
            try:
                data = self.sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                data = b""
            if not data:
                self.sock.close()
                self.sock = None
                out.append((("closed", 0), b""))
                break
            out.append((0, data))
        return out

    def write(self, buf: bytes) -> None:
        self._connect()
        if self.sock is None:
            return
        try:
            self.sock.sendall(buf)
        except (BlockingIOError, InterruptedError):
            pass
        except OSError:
            self.sock.close()
            self.sock = None

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
            self.sock = None

    @property
    def address(self) -> str:
        return f"tcp:{self.dest[0]}:{self.dest[1]}"

    def peers(self) -> int:
        return 0 if self.sock is None else 1


def open_transport(conn: str) -> Transport:
    """Open the socket transport named by a pymavlink connection string (see module doc)."""
    kind, host, port = parse_connection(conn)
    if kind in ("udpin", "udpout"):
        return UdpTransport(kind, host, port)
    if kind == "tcpin":
        return TcpInTransport(host, port)
    return TcpOutTransport(host, port)


def read_signing_key(path: str) -> bytes:
    """Read a 32-byte MAVLink 2 signing key: 32 raw bytes, or 64 hex digits (text).

    The key is a secret: a file that its group or others may read or write is refused
    (``chmod 600 FILE``), and the key never appears in a message. Same rules and messages as
    the planner's key (:func:`comms.mavlink_client.read_signing_key`, which this calls).

    Raises:
        UsageError: missing or unreadable file, not a regular file, permissions too open,
            wrong length / content.
    """
    from comms.mavlink_client import read_signing_key as read_key  # lazy: numpy, pyproj

    return read_key(path)


def signing_timestamp_now() -> int:
    """Current MAVLink 2 signing timestamp (10 µs units since 2015-01-01)."""
    return int(max(0.0, time.time() - SIGNING_EPOCH_UNIX_S) * 100_000)


def _frame_msg_id(buf: bytes) -> int | None:
    """Message id in the header of an encoded MAVLink 1 or 2 frame (None: not a frame)."""
    if len(buf) >= 10 and buf[0] == 0xFD:
        return buf[7] | (buf[8] << 8) | (buf[9] << 16)
    if len(buf) >= 6 and buf[0] == 0xFE:
        return buf[5]
    return None


class _Sink:
    """File-like target of the pymavlink encoder: forwards frames to the link."""

    def __init__(self, link: MavlinkLink) -> None:
        self.link = link

    def write(self, buf: bytes) -> None:
        self.link._write_frame(bytes(buf))


class MavlinkLink:
    """One vehicle's MAVLink endpoint: transport + per-peer parsers + encoder + .tlog.

    Args:
        transport: the socket transport.
        sysid, compid: our MAVLink ids (compid 1 = autopilot).
        tlog_path: append every valid frame in and out as ``uint64 BE µs`` + frame (the
            .tlog format of MAVProxy / ``mavlogdump.py``), except SETUP_SIGNING (it carries
            the key); None for no log.
        signing_key: 32-byte key: sign what we send, refuse unsigned input
            (RADIO_STATUS excepted, as ArduPilot does); a signed frame is accepted once
            per link (timestamps per stream must increase, across all peer sockets).
    """

    def __init__(
        self,
        transport: Transport,
        sysid: int,
        compid: int = 1,
        *,
        tlog_path: str | None = None,
        signing_key: bytes | None = None,
    ) -> None:
        self.mavlink = mavlink_module()
        self.transport = transport
        self.sysid = sysid
        self.compid = compid
        self.signing_key = signing_key
        self.encoder = self.mavlink.MAVLink(_Sink(self), srcSystem=sysid, srcComponent=compid)
        if signing_key is not None:
            sig = self.encoder.signing
            sig.secret_key = signing_key
            sig.sign_outgoing = True
            sig.link_id = 0
            sig.timestamp = signing_timestamp_now()
        self._parsers: dict[object, Any] = {}
        #: Signing state of the link's input, shared by every peer's parser: the stream
        #: timestamp table (replay protection) and the good/bad signature counters.
        self.rx_signing: Any = self.mavlink.MAVLinkSigning()
        if signing_key is not None:
            self.rx_signing.secret_key = signing_key
            self.rx_signing.allow_unsigned_callback = self._allow_unsigned
        self.bad_frames = 0
        self.frames_in = 0
        self.frames_out = 0
        #: Datagrams (or stream reads) taken from the transport, valid or not.
        self.reads_in = 0
        #: Frames not written to the .tlog because they carry the signing key (SETUP_SIGNING).
        self.frames_not_logged = 0
        self._tlog: BinaryIO | None = None
        if tlog_path is not None:
            try:
                self._tlog = open(tlog_path, "ab")  # noqa: SIM115 - closed by close()
            except OSError as exc:
                raise UsageError(f"tlog {tlog_path!r}: {exc.strerror or exc}") from None

    def _allow_unsigned(self, _mav: Any, msg_id: int) -> bool:
        return bool(msg_id == self.mavlink.MAVLINK_MSG_ID_RADIO_STATUS)

    def _parser(self, peer: object) -> Any:
        parser = self._parsers.get(peer)
        if parser is None:
            parser = self.mavlink.MAVLink(None, srcSystem=self.sysid, srcComponent=self.compid)
            parser.robust_parsing = True
            parser.signing = self.rx_signing
            parser.check_signature = self._check_signature
            self._parsers[peer] = parser
        return parser

    def _check_signature(self, msgbuf: bytearray, src_system: int, src_component: int) -> bool:
        """Accept a signed frame (replaces pymavlink's ``MAVLink.check_signature`` on every
        parser of the link): the signature must match the key, and then the 48-bit timestamp
        (10 µs since 2015-01-01) must be newer than the last one accepted on the link for
        its stream ``(link id, system, component)`` — whichever peer socket brought it —
        or, for a new stream, at most one minute behind the link's own timestamp."""
        sig = self.rx_signing
        key = sig.secret_key
        if key is None or len(msgbuf) < 13:
            return False
        if not hmac.compare_digest(hashlib.sha256(bytes(key) + bytes(msgbuf[:-6])).digest()[:6], bytes(msgbuf[-6:])):
            log.debug("signed frame from %d/%d: bad signature", src_system, src_component)
            return False
        link_id = msgbuf[-13]
        timestamp = int.from_bytes(bytes(msgbuf[-12:-6]), "little")
        stream = (link_id, src_system, src_component)
        last = sig.stream_timestamps.get(stream)
        if last is not None:
            if timestamp <= last:
                log.debug("signed frame from %d/%d link %d: old timestamp (replay?)", src_system, src_component, link_id)
                return False
        else:
            local = max(signing_timestamp_now(), sig.timestamp, self.encoder.signing.timestamp)
            if timestamp + SIGNING_NEW_STREAM_WINDOW < local:
                log.debug("signed frame from %d/%d link %d: new stream too old", src_system, src_component, link_id)
                return False
        sig.stream_timestamps[stream] = timestamp
        sig.timestamp = max(sig.timestamp, timestamp)
        # our own timestamp never falls behind a valid one received (MAVLink 2 signing)
        self.encoder.signing.timestamp = max(self.encoder.signing.timestamp, timestamp)
        return True

    def filenos(self) -> list[int]:
        """File descriptors to wait on."""
        return self.transport.filenos()

    def parse(self, peer: object, data: bytes) -> list[Any]:
        """Parse ``data`` from ``peer``; return the valid messages (malformed ones counted)."""
        parser = self._parser(peer)
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception as exc:  # any parser failure is a bad frame, not a crash
            log.debug("parser reset after %s", exc)
            self.bad_frames += 1
            self._parsers.pop(peer, None)
            return []
        good = []
        for m in msgs:
            if m.get_type() == "BAD_DATA":
                self.bad_frames += 1
                continue
            good.append(m)
            self.frames_in += 1
            if self._tlog is not None:
                if m.get_msgId() == MAVLINK_MSG_ID_SETUP_SIGNING:
                    self.frames_not_logged += 1
                else:
                    self._log(self._tlog, m.get_msgbuf())
        return good

    def receive(self) -> list[Any]:
        """Drain the transport and return the valid messages received, in order."""
        out: list[Any] = []
        for peer, data in self.transport.read():
            self.reads_in += 1
            if not data:
                if isinstance(peer, tuple) and peer and peer[0] == "closed":
                    self._parsers.pop(peer[1], None)
                continue
            out.extend(self.parse(peer, data))
        return out

    def send(self, msg: Any) -> None:
        """Encode ``msg`` (a pymavlink message object) and send it to every peer."""
        self.encoder.send(msg)

    def _write_frame(self, buf: bytes) -> None:
        self.frames_out += 1
        self.transport.write(buf)
        if self._tlog is not None:
            if _frame_msg_id(buf) == MAVLINK_MSG_ID_SETUP_SIGNING:
                self.frames_not_logged += 1
            else:
                self._log(self._tlog, buf)

    @staticmethod
    def _log(tlog: BinaryIO, buf: bytes) -> None:
        """One .tlog entry: the big-endian UNIX time in microseconds, then the frame."""
        usec = int(time.time() * 1e6) & ~3
        tlog.write(struct.pack(">Q", usec) + bytes(buf))

    def flush(self) -> None:
        """Flush the .tlog."""
        if self._tlog is not None:
            self._tlog.flush()

    def close(self) -> None:
        """Close sockets and the .tlog."""
        self.transport.close()
        if self._tlog is not None:
            self._tlog.close()
            self._tlog = None
