"""The wire format of fimnav's Zenoh messages: typed, versioned, compact, validated on receipt.

Every message starts with a 14-byte header::

    magic  b"FN"   2 bytes
    version  u8    SCHEMA_VERSION (1)
    kind     u8    MessageKind
    mission  u32   CRC-32 of the mission id: a record of another mission is refused
    sender   u16   1-based drone id (0 for the clock / launcher)
    seq      u32   per-sender sequence number

followed by a fixed body per kind (little endian, IEEE-754 doubles; step is signed: −1 is the pre-flight). A record and a payload
measurement share one body: step u32, time f64 (s), position 3×f64 (m, mission ENU), role u8
(bit 0 ranging, bit 1 bearing), flags u8 (bit 0 LOS, bit 1 stale, bit 2 taken over), range f64 (m),
azimuth f64, elevation f64 (rad); NaN stands for a quantity the role does not measure.

:func:`decode` checks everything a peer could get wrong or forge (length, magic, version, kind,
mission, finite and plausible values, role bits, angle ranges) and raises :class:`MessageError`
with the reason; receivers drop such a message with a warning and count it, never crash.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass
from enum import IntEnum
from types import MappingProxyType

import numpy as np

from planner.sensing import ROLES, SensingRole, role_from_flags

MAGIC = b"FN"
SCHEMA_VERSION = 1
SUPPORTED_VERSIONS = frozenset({1})
#: Largest plausible coordinate (m) in the mission frame.
MAX_COORD_M = 1.0e6

_HEADER = struct.Struct("<2sBBIHI")
_OBS = struct.Struct("<Id3dBBddd")
_TICK = struct.Struct("<id")
_DONE = struct.Struct("<i")
_STATUS_HEAD = struct.Struct("<Id3dBBBH")


class MessageKind(IntEnum):
    RECORD = 1
    MEASUREMENT = 2
    TICK = 3
    DONE = 4
    STATUS = 5


class MessageError(ValueError):
    """A received message is malformed, of another mission, or implausible."""


LOS_FLAG = 1
STALE_FLAG = 2
#: A pilot flies the drone (it left the planner's mode): the record is its position, no measurement.
TAKEN_OVER_FLAG = 4


#: Wire role byte -> sensing role, from the role table of :mod:`planner.sensing` (read-only).
_ROLE_OF_BITS: Mapping[int, SensingRole] = MappingProxyType({r.wire_bits: r for r in ROLES.values()})


def _known_role_bits() -> str:
    """``1 (ranging), 2 (bearing) or 3 (joint)``: the role bytes a record may carry."""
    items = [f"{bits} ({role.name})" for bits, role in sorted(_ROLE_OF_BITS.items())]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def mission_tag(mission_id: str) -> int:
    """The 32-bit tag of a mission id carried in every header (CRC-32)."""
    return zlib.crc32(mission_id.encode("utf-8")) & 0xFFFFFFFF


@dataclass(frozen=True)
class Header:
    kind: MessageKind
    mission: int
    sender: int
    seq: int


@dataclass(frozen=True)
class Observation:
    """A drone's record (kind RECORD) or its payload's measurement (kind MEASUREMENT).

    Attributes:
        sender: 1-based drone id. step: step index k. time_s: sim or wall time (s).
        position_m: where the measurement was taken, (3,) m, mission ENU.
        ranging, bearing: the drone's sensing role. los: the link was line of sight.
        stale: the sender republishes its last state (its vehicle link is down).
        taken_over: a pilot flies the drone (its vehicle left the planner's mode); the record
            is where it is, without a measurement.
        range_m, azimuth_rad, elevation_rad: the measurement (NaN where not measured).
    """

    sender: int
    step: int
    time_s: float
    position_m: tuple[float, float, float]
    ranging: bool
    bearing: bool
    los: bool
    range_m: float
    azimuth_rad: float
    elevation_rad: float
    stale: bool = False
    taken_over: bool = False


@dataclass(frozen=True)
class Tick:
    """Lockstep clock: advance to step ``step`` at time ``time_s``."""

    step: int
    time_s: float


@dataclass(frozen=True)
class Done:
    """Participant ``sender`` finished step ``step``."""

    sender: int
    step: int


@dataclass(frozen=True)
class Status:
    """A planner's step summary: its estimate and which peer records it used.

    ``saved_steps[j]`` is the step of drone j+1's record in its view (−1: none).
    """

    sender: int
    step: int
    time_s: float
    estimate_m: tuple[float, float, float]
    observable: bool
    singular: bool
    active_mask: int
    saved_steps: tuple[int, ...]


Message = Observation | Tick | Done | Status


def _header(kind: MessageKind, mission_id: str, sender: int, seq: int) -> bytes:
    return _HEADER.pack(MAGIC, SCHEMA_VERSION, int(kind), mission_tag(mission_id), sender, seq & 0xFFFFFFFF)


def encode(msg: Message, mission_id: str, seq: int, kind: MessageKind | None = None) -> bytes:
    """Serialise a message (``kind`` picks RECORD or MEASUREMENT for an Observation)."""
    if isinstance(msg, Observation):
        k = kind or MessageKind.RECORD
        role = role_from_flags(msg.ranging, msg.bearing).wire_bits if (msg.ranging or msg.bearing) else 0
        flags = (LOS_FLAG if msg.los else 0) | (STALE_FLAG if msg.stale else 0) | (TAKEN_OVER_FLAG if msg.taken_over else 0)
        body = _OBS.pack(msg.step, msg.time_s, *msg.position_m, role, flags, msg.range_m, msg.azimuth_rad, msg.elevation_rad)
        return _header(k, mission_id, msg.sender, seq) + body
    if isinstance(msg, Tick):
        return _header(MessageKind.TICK, mission_id, 0, seq) + _TICK.pack(msg.step, msg.time_s)
    if isinstance(msg, Done):
        return _header(MessageKind.DONE, mission_id, msg.sender, seq) + _DONE.pack(msg.step)
    if isinstance(msg, Status):
        head = _STATUS_HEAD.pack(
            msg.step, msg.time_s, *msg.estimate_m, int(msg.observable), int(msg.singular), msg.active_mask & 0xFF, len(msg.saved_steps)
        )
        return _header(MessageKind.STATUS, mission_id, msg.sender, seq) + head + np.asarray(msg.saved_steps, dtype="<i4").tobytes()
    raise TypeError(f"cannot encode {type(msg).__name__}")


def decode(data: bytes, mission_id: str, max_sender: int | None = None) -> tuple[Header, Message]:
    """Parse and validate one message of mission ``mission_id``.

    Args:
        data: the payload bytes.
        mission_id: the receiver's mission; a message of another mission is refused.
        max_sender: the number of drones N (sender ids must be in 1..N), if known.

    Raises:
        MessageError: with the reason, for anything malformed or implausible.
    """
    if len(data) < _HEADER.size:
        raise MessageError(f"truncated message: {len(data)} bytes, expected at least {_HEADER.size}")
    magic, version, kind, tag, sender, seq = _HEADER.unpack_from(data)
    if magic != MAGIC:
        raise MessageError(f"bad magic {magic!r}, expected {MAGIC!r}")
    if version not in SUPPORTED_VERSIONS:
        raise MessageError(f"unknown schema version {version}, this build speaks {sorted(SUPPORTED_VERSIONS)}")
    try:
        kind = MessageKind(kind)
    except ValueError:
        raise MessageError(f"unknown message kind {kind}") from None
    if tag != mission_tag(mission_id):
        raise MessageError(f"message of another mission (tag {tag:#010x}, expected {mission_tag(mission_id):#010x})")
    header = Header(kind, tag, sender, seq)
    body = memoryview(data)[_HEADER.size :]
    if kind in (MessageKind.RECORD, MessageKind.MEASUREMENT):
        _need(body, _OBS.size, kind)
        step, t, x, y, z, role, flags, rng, az, el = _OBS.unpack(body)
        _sender(sender, max_sender)
        _finite("time", t)
        for name, v in (("x", x), ("y", y), ("z", z)):
            _finite(f"position {name}", v)
            if abs(v) > MAX_COORD_M:
                raise MessageError(f"position {name} = {v:g} m is outside ±{MAX_COORD_M:g} m")
        if role not in _ROLE_OF_BITS:
            raise MessageError(f"role bits {role:#x}: expected {_known_role_bits()}")
        if flags & ~(LOS_FLAG | STALE_FLAG | TAKEN_OVER_FLAG):
            raise MessageError(f"unknown flag bits {flags:#x}")
        ranging, bearing = _ROLE_OF_BITS[role].ranging, _ROLE_OF_BITS[role].bearing
        # The paper's ranging model is additive Gaussian (eq. 3): a far, noisy range can be
        # negative. Any finite value of plausible size is a measurement.
        if ranging and not (math.isnan(rng) or (math.isfinite(rng) and abs(rng) <= 2 * MAX_COORD_M)):
            raise MessageError(f"range {rng!r}: expected a finite distance within ±{2 * MAX_COORD_M:g} m (or NaN: no measurement)")
        if not ranging and not math.isnan(rng):
            raise MessageError("range given by a drone without the ranging role")
        if bearing:
            for name, v, lim in (("azimuth", az, math.pi), ("elevation", el, 0.5 * math.pi)):
                if not (math.isnan(v) or (math.isfinite(v) and -lim - 1e-9 <= v <= lim + 1e-9)):
                    raise MessageError(f"{name} {v!r}: expected an angle in [-{lim:.4f}, {lim:.4f}] rad (or NaN)")
        elif not (math.isnan(az) and math.isnan(el)):
            raise MessageError("bearing given by a drone without the bearing role")
        return header, Observation(
            sender, step, t, (x, y, z), ranging, bearing, bool(flags & LOS_FLAG), rng, az, el, bool(flags & STALE_FLAG), bool(flags & TAKEN_OVER_FLAG)
        )
    if kind == MessageKind.TICK:
        _need(body, _TICK.size, kind)
        step, t = _TICK.unpack(body)
        _finite("time", t)
        return header, Tick(step, t)
    if kind == MessageKind.DONE:
        _need(body, _DONE.size, kind)
        _sender(sender, max_sender)
        return header, Done(sender, _DONE.unpack(body)[0])
    # STATUS
    if len(body) < _STATUS_HEAD.size:
        raise MessageError(f"truncated status: {len(body)} bytes")
    step, t, ex, ey, ez, obs, sing, active, n = _STATUS_HEAD.unpack_from(body)
    _sender(sender, max_sender)
    if max_sender is not None and n != max_sender:
        raise MessageError(f"status lists {n} peers, expected {max_sender}")
    _need(body, _STATUS_HEAD.size + 4 * n, kind)
    for v in (t, ex, ey, ez):
        _finite("status value", v)
    saved = tuple(int(s) for s in np.frombuffer(body[_STATUS_HEAD.size :], dtype="<i4", count=n))
    return header, Status(sender, step, t, (ex, ey, ez), bool(obs), bool(sing), active, saved)


def _need(body: memoryview, size: int, kind: MessageKind) -> None:
    if len(body) != size:
        raise MessageError(f"{kind.name.lower()} body of {len(body)} bytes, expected {size}")


def _finite(name: str, v: float) -> None:
    if not math.isfinite(v):
        raise MessageError(f"{name} is {v!r}, expected a finite number")


def _sender(sender: int, max_sender: int | None) -> None:
    if sender < 1 or (max_sender is not None and sender > max_sender):
        raise MessageError(f"sender id {sender} outside 1..{max_sender if max_sender is not None else 65535}")
