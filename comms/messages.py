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

A record of a role with components beyond range and bearing (:class:`planner.sensing.SensingTable`:
their bits in the role byte) ends with an extension: count u8, then that many f64 values, the
``value_names`` of those components in registry order. A record of range and bearing only has
no extension, so its bytes do not depend on whether a table has more components.

:func:`decode` checks everything a peer could get wrong or forge (length, magic, version, kind,
mission, finite and plausible values, role bits, angle ranges) and raises :class:`MessageError`
with the reason; receivers drop such a message with a warning and count it, never crash.
"""

from __future__ import annotations

import math
import struct
import zlib
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import IntEnum
from types import MappingProxyType

import numpy as np

from planner.sensing import BEARING, RANGE, SENSING, SensingComponent, SensingTable

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
_EXTENSION_COUNT = struct.Struct("<B")


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


def _known_role_bits(sensing: SensingTable) -> str:
    """``1 (ranging), 2 (bearing) or 3 (joint)``: the role bytes a record may carry."""
    items = [f"{bits} ({name})" for bits, name in sorted((sensing.wire_bits(r.components), r.name) for r in sensing.roles.values())]
    return items[0] if len(items) == 1 else ", ".join(items[:-1]) + " or " + items[-1]


def _extra_components_of_bits(bits: int, sensing: SensingTable) -> tuple[SensingComponent, ...]:
    """The components beyond range and bearing whose bit the role byte ``bits`` has."""
    return tuple(c for c in sensing.extra_components if bits & c.wire_bit)


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
class Record:
    """A drone's record (kind RECORD) or its payload's measurement (kind MEASUREMENT).

    Attributes:
        sender: 1-based drone id. step: step index k. time_s: sim or wall time (s).
        position_m: where the measurement was taken, (3,) m, mission ENU.
        ranging, bearing: the drone's sensing role. los: the link was line of sight.
        stale: the sender republishes its last state (its vehicle link is down).
        taken_over: a pilot flies the drone (its vehicle left the planner's mode); the record
            is where it is, without a measurement.
        range_m, azimuth_rad, elevation_rad: the measurement (NaN where not measured).
        extra_values: the values of the sender's components beyond range and bearing, by value
            name (:attr:`planner.sensing.SensingComponent.value_names`; NaN where not measured);
            empty for a role of range and bearing only (read-only mapping).
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
    extra_values: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}), hash=False)


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


Message = Record | Tick | Done | Status


def _header(kind: MessageKind, mission_id: str, sender: int, seq: int) -> bytes:
    return _HEADER.pack(MAGIC, SCHEMA_VERSION, int(kind), mission_tag(mission_id), sender, seq & 0xFFFFFFFF)


def _extension(msg: Record, sensing: SensingTable) -> tuple[list[str], list[float]]:
    """The components beyond range and bearing a Record's ``extra_values`` carry (names)
    and their values in wire order.

    Raises:
        ValueError: a value name of no such component of ``sensing``, or a component with only
            some of its values.
    """
    given = dict(msg.extra_values)
    names: list[str] = []
    values: list[float] = []
    for component in sensing.extra_components:
        present = [name in given for name in component.value_names]
        if any(present) and not all(present):
            raise ValueError(f"record extra_values: expected all of {list(component.value_names)} of {component.name!r}, found {sorted(given)}")
        if all(present) and component.value_names:
            names.append(component.name)
            values.extend(float(given.pop(name)) for name in component.value_names)
    if given:
        raise ValueError(f"record extra_values: expected value names among {list(sensing.extra_value_names)}, found {sorted(given)}")
    return names, values


def encode(msg: Message, mission_id: str, seq: int, kind: MessageKind | None = None, sensing: SensingTable = SENSING) -> bytes:
    """Serialise a message (``kind`` picks RECORD or MEASUREMENT for a Record; ``sensing``:
    the role table whose bits a record's role byte carries).

    Raises:
        ValueError: a Record whose components form no role of ``sensing``, or whose
            ``extra_values`` do not match its components.
    """
    if isinstance(msg, Record):
        k = kind or MessageKind.RECORD
        extra_names, extra = _extension(msg, sensing)
        taken = [name for name, has in ((RANGE.name, msg.ranging), (BEARING.name, msg.bearing)) if has] + extra_names
        role = sensing.wire_bits(taken)
        if taken and sensing.role_of_bits(role) is None:
            raise ValueError(f"record: no sensing role takes the components {taken}")
        flags = (LOS_FLAG if msg.los else 0) | (STALE_FLAG if msg.stale else 0) | (TAKEN_OVER_FLAG if msg.taken_over else 0)
        body = _OBS.pack(msg.step, msg.time_s, *msg.position_m, role, flags, msg.range_m, msg.azimuth_rad, msg.elevation_rad)
        if extra:
            body += _EXTENSION_COUNT.pack(len(extra)) + struct.pack(f"<{len(extra)}d", *extra)
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


def decode(data: bytes, mission_id: str, max_sender: int | None = None, sensing: SensingTable = SENSING) -> tuple[Header, Message]:
    """Parse and validate one message of mission ``mission_id``.

    Args:
        data: the payload bytes.
        mission_id: the receiver's mission; a message of another mission is refused.
        max_sender: the number of drones N (sender ids must be in 1..N), if known.
        sensing: the role table a record's role byte and extension are read with.

    Raises:
        MessageError: with the reason, for anything malformed or implausible.
    """
    header, body = _decode_header(data, mission_id)
    kind = header.kind
    if kind in (MessageKind.RECORD, MessageKind.MEASUREMENT):
        return header, _decode_record(header, body, max_sender, sensing)
    if kind == MessageKind.TICK:
        _need(body, _TICK.size, kind)
        step, t = _TICK.unpack(body)
        _finite("time", t)
        return header, Tick(step, t)
    if kind == MessageKind.DONE:
        _need(body, _DONE.size, kind)
        _sender(header.sender, max_sender)
        return header, Done(header.sender, _DONE.unpack(body)[0])
    return header, _decode_status(header, body, max_sender)


def _decode_header(data: bytes, mission_id: str) -> tuple[Header, memoryview]:
    """The header of a message of mission ``mission_id`` and the body after it."""
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
    return Header(kind, tag, sender, seq), memoryview(data)[_HEADER.size :]


def _decode_record(header: Header, body: memoryview, max_sender: int | None, sensing: SensingTable) -> Record:
    """The :class:`Record` of a RECORD or MEASUREMENT body: position within ±MAX_COORD_M,
    a known role, known flags, and a measurement that fits the role."""
    if len(body) < _OBS.size:
        _need(body, _OBS.size, header.kind)
    step, t, x, y, z, role, flags, rng, az, el = _OBS.unpack_from(body)
    _sender(header.sender, max_sender)
    _finite("time", t)
    for name, v in (("x", x), ("y", y), ("z", z)):
        _finite(f"position {name}", v)
        if abs(v) > MAX_COORD_M:
            raise MessageError(f"position {name} = {v:g} m is outside ±{MAX_COORD_M:g} m")
    found = sensing.role_of_bits(role)
    if found is None:
        raise MessageError(f"role bits {role:#x}: expected {_known_role_bits(sensing)}")
    if flags & ~(LOS_FLAG | STALE_FLAG | TAKEN_OVER_FLAG):
        raise MessageError(f"unknown flag bits {flags:#x}")
    extra_values = _decode_extension(body[_OBS.size :], _extra_components_of_bits(role, sensing), header.kind)
    _check_measurement(found.ranging, found.bearing, rng, az, el)
    los, stale, taken_over = bool(flags & LOS_FLAG), bool(flags & STALE_FLAG), bool(flags & TAKEN_OVER_FLAG)
    return Record(header.sender, step, t, (x, y, z), found.ranging, found.bearing, los, rng, az, el, stale, taken_over, extra_values)


def _check_measurement(ranging: bool, bearing: bool, rng: float, az: float, el: float) -> None:
    """A record's range and angles fit its role: finite and plausible where measured, NaN where
    not measured, absent (NaN) for a component the role does not have."""
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


def _decode_status(header: Header, body: memoryview, max_sender: int | None) -> Status:
    """The :class:`Status` of a STATUS body (``max_sender``: N, the peers it must list)."""
    if len(body) < _STATUS_HEAD.size:
        raise MessageError(f"truncated status: {len(body)} bytes")
    step, t, ex, ey, ez, obs, sing, active, n = _STATUS_HEAD.unpack_from(body)
    _sender(header.sender, max_sender)
    if max_sender is not None and n != max_sender:
        raise MessageError(f"status lists {n} peers, expected {max_sender}")
    _need(body, _STATUS_HEAD.size + 4 * n, header.kind)
    for v in (t, ex, ey, ez):
        _finite("status value", v)
    saved = tuple(int(s) for s in np.frombuffer(body[_STATUS_HEAD.size :], dtype="<i4", count=n))
    return Status(header.sender, step, t, (ex, ey, ez), bool(obs), bool(sing), active, saved)


def _decode_extension(tail: memoryview, components: tuple[SensingComponent, ...], kind: MessageKind) -> Mapping[str, float]:
    """The values of a record's extension (``tail``: the bytes after the fixed body) for the
    components beyond range and bearing of its role byte, by value name (read-only).

    Raises:
        MessageError: an extension where the role has no such component, a count or length
            that does not match the role's values, or a value that is neither finite nor NaN.
    """
    names = [name for c in components for name in c.value_names]
    if not names:
        if len(tail):
            raise MessageError(f"{kind.name.lower()} body of {_OBS.size + len(tail)} bytes, expected {_OBS.size}")
        return MappingProxyType({})
    if len(tail) < _EXTENSION_COUNT.size:
        raise MessageError(f"{kind.name.lower()} extension missing: the role carries {names}")
    (count,) = _EXTENSION_COUNT.unpack_from(tail)
    if count != len(names):
        raise MessageError(f"extension count {count}: expected {len(names)} values {names}")
    size = _EXTENSION_COUNT.size + 8 * count
    if len(tail) != size:
        raise MessageError(f"extension of {len(tail)} bytes, expected {size} (count and the values {names})")
    values = struct.unpack_from(f"<{count}d", tail, _EXTENSION_COUNT.size)
    for name, v in zip(names, values, strict=True):
        if not (math.isnan(v) or math.isfinite(v)):
            raise MessageError(f"extension value {name} {v!r}: expected a finite number (or NaN: no measurement)")
    return MappingProxyType(dict(zip(names, values, strict=True)))


def _need(body: memoryview, size: int, kind: MessageKind) -> None:
    if len(body) != size:
        raise MessageError(f"{kind.name.lower()} body of {len(body)} bytes, expected {size}")


def _finite(name: str, v: float) -> None:
    if not math.isfinite(v):
        raise MessageError(f"{name} is {v!r}, expected a finite number")


def _sender(sender: int, max_sender: int | None) -> None:
    if sender < 1 or (max_sender is not None and sender > max_sender):
        raise MessageError(f"sender id {sender} outside 1..{max_sender if max_sender is not None else 65535}")
