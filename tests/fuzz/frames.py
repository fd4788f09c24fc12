"""MAVLink fuzz corpus: valid seed frames of many message types and their random, truncated,
extended and bit-flipped mutations, drawn from a seeded ``numpy.random.Generator``.

"Invalid" is decided by an independent reference parser (a fresh pymavlink MAVLink 2 parser
with robust parsing, one per frame): a mutation that still decodes to a valid message — a
bit flip that lands on a field covered by a CRC collision, or a truncation at a boundary
that leaves a complete shorter frame — is *valid*, counted in :attr:`Corpus.valid_mutations`
and never sent, so every frame sent is one a correct receiver must drop. With the 16-bit
X.25 CRC, a random corruption passes the check with probability about 2^-16 per frame
(plus the CRC-extra mismatch on a message-id flip), so out of 10^5 mutations a handful can
be valid: they are set aside, not treated as failures (measured: 0 in 10^5, 6 in 10^6).

A receiver that parses each UDP peer as a byte stream can also complete a frame across
datagrams (a seed truncated by its last CRC byte, then a datagram starting with that byte):
mutations that would do so in the stream of the corpus sent before them are set aside too
(:class:`StreamReference`; measured: 788 in 10^6).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from vehicle_sim.link import mavlink_module


class _Sink:
    def __init__(self) -> None:
        self.frames: list[bytes] = []

    def write(self, buf: bytes) -> None:
        self.frames.append(bytes(buf))


def encoder(sysid: int = 255, compid: int = 190, *, mavlink1: bool = False) -> tuple[Any, _Sink]:
    """A pymavlink encoder writing frames into ``sink.frames``."""
    m = mavlink_module()
    sink = _Sink()
    enc = m.MAVLink(sink, srcSystem=sysid, srcComponent=compid)
    if mavlink1:
        enc.WIRE_PROTOCOL_VERSION = "1.0"
    return enc, sink


def command_seeds(target: int = 1) -> list[bytes]:
    """Valid frames a ground station sends to vehicle ``target``: every one of them would change
    the vehicle's state (mode, armed, target, params, streams, origin) or make it answer."""
    m = mavlink_module()
    frames: list[bytes] = []
    for v1 in (False, True):
        enc, sink = encoder(mavlink1=v1)
        enc.command_long_send(target, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0)
        enc.command_long_send(target, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0)
        enc.command_long_send(target, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, 9, 0, 0, 0, 0, 0)
        enc.command_long_send(target, 1, m.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
        enc.command_long_send(target, 1, m.MAV_CMD_NAV_RETURN_TO_LAUNCH, 0, 0, 0, 0, 0, 0, 0, 0)
        enc.command_long_send(target, 1, m.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 30.0)
        enc.command_long_send(target, 1, m.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 32, 1000, 0, 0, 0, 0, 0)
        enc.command_long_send(target, 1, m.MAV_CMD_DO_CHANGE_SPEED, 0, 1, 3.5, -1, 0, 0, 0, 0)
        enc.command_long_send(target, 1, m.MAV_CMD_DO_FENCE_ENABLE, 0, 0, 0, 0, 0, 0, 0, 0)
        enc.command_int_send(target, 1, 6, m.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, 0, 10, 10, 20.0)
        enc.command_int_send(target, 1, 0, 611, 0, 0, 0, 0, 0, 0, 473_000_000, 85_000_000, 500.0)
        enc.set_mode_send(target, 1, 9)
        enc.set_position_target_local_ned_send(0, target, 1, 1, 0b110111000000, 50, 20, -10, 1, 1, 0, 0, 0, 0, 0, 0)
        enc.set_position_target_local_ned_send(0, target, 1, 8, 0b110111000111, 0, 0, 0, 2, 0, -1, 0, 0, 0, 0, 0)
        enc.set_position_target_global_int_send(0, target, 1, 6, 0b110111111000, 10, 10, 30, 0, 0, 0, 0, 0, 0, 0, 0)
        enc.param_set_send(target, 1, b"WPNAV_SPEED", 100.0, m.MAV_PARAM_TYPE_REAL32)
        enc.param_set_send(target, 1, b"FENCE_ENABLE", 0.0, m.MAV_PARAM_TYPE_INT8)
        enc.param_set_send(target, 1, b"RTL_ALT", 3000.0, m.MAV_PARAM_TYPE_REAL32)
        enc.param_set_send(target, 1, b"GUID_TIMEOUT", 0.5, m.MAV_PARAM_TYPE_REAL32)
        enc.set_gps_global_origin_send(target, 10, 10, 10)
        enc.request_data_stream_send(target, 1, 0, 0, 0)
        enc.mission_item_int_send(target, 1, 0, 6, 16, 2, 0, 0, 0, 0, 0, 10, 10, 10.0)
        enc.mission_count_send(target, 1, 3)
        enc.mission_clear_all_send(target, 1)
        enc.mission_request_list_send(target, 1)
        enc.mission_request_int_send(target, 1, 0)
        enc.param_request_list_send(target, 1)
        enc.param_request_read_send(target, 1, b"WPNAV_SPEED", -1)
        enc.timesync_send(0, 12345)
        enc.heartbeat_send(m.MAV_TYPE_GCS, m.MAV_AUTOPILOT_INVALID, 0, 0, 0)
        frames += sink.frames
    return frames


def telemetry_seeds(sysid: int = 1) -> list[bytes]:
    """Valid frames an autopilot ``sysid`` sends (what the planner's link parses)."""
    m = mavlink_module()
    frames: list[bytes] = []
    for v1 in (False, True):
        enc, sink = encoder(sysid, 1, mavlink1=v1)
        enc.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 217, 4, m.MAV_STATE_ACTIVE)
        enc.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_PX4, 89, 6 << 16, m.MAV_STATE_STANDBY)
        enc.local_position_ned_send(123456, 10.0, -20.0, -30.0, 1.0, 2.0, -0.5)
        enc.global_position_int_send(123456, 473_977_000, 85_455_000, 520_000, 30_000, 100, 200, -50, 9000)
        enc.command_ack_send(m.MAV_CMD_NAV_TAKEOFF, m.MAV_RESULT_ACCEPTED, 0, 0, 1, 191)
        enc.command_ack_send(m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_RESULT_DENIED, 0, 0, 1, 191)
        enc.statustext_send(4, b"Fence: target outside fence, clamped")
        enc.home_position_send(473_977_000, 85_455_000, 500_000, 0, 0, 0, [1, 0, 0, 0], 0, 0, 0)
        enc.sys_status_send(0, 0, 0, 100, 16000, 1500, 90, 0, 0, 0, 0, 0, 0)
        enc.attitude_send(123456, 0.1, -0.1, 1.0, 0, 0, 0)
        enc.param_value_send(b"WPNAV_SPEED", 1000.0, m.MAV_PARAM_TYPE_REAL32, 20, 3)
        enc.timesync_send(5, 7)
        frames += sink.frames
    return frames


def reference_messages(data: bytes) -> list[Any]:
    """The valid messages an independent, fresh pymavlink parser finds in ``data``.

    A frame whose message id is unknown to the dialect (``UNKNOWN_<id>``: its CRC cannot be
    checked without the CRC extra) is not valid: a receiver must ignore it, so it stays in
    the corpus."""
    m = mavlink_module()
    parser = m.MAVLink(None)
    parser.robust_parsing = True
    try:
        msgs = parser.parse_buffer(bytes(data)) or []
    except Exception:  # noqa: BLE001 - the reference parser choking means "nothing valid"
        return []
    return [x for x in msgs if x.get_type() != "BAD_DATA" and not x.get_type().startswith("UNKNOWN_")]


@dataclass
class Corpus:
    """Invalid frames to send, and what the generator learnt on the way."""

    frames: list[bytes] = field(default_factory=list)
    kinds: dict[str, int] = field(default_factory=lambda: {"random": 0, "bitflip": 0, "truncated": 0, "extended": 0})
    #: mutations that still decode to a valid message (CRC collisions etc.): never sent.
    valid_mutations: int = 0
    #: mutations invalid alone that complete a valid frame in the stream: never sent.
    valid_in_stream: int = 0
    #: message types of the seeds the bit-flipped / truncated frames were derived from.
    seed_types: set[str] = field(default_factory=set)


class StreamReference:
    """An independent pymavlink parser fed the corpus in order, as one peer's stream: a
    receiver that parses a UDP peer as a byte stream (vehicle_sim does, as ArduPilot and PX4
    do) can complete a frame with the first bytes of the next datagram. E.g. a seed frame
    truncated by its last CRC byte, followed by a datagram that starts with that byte, is a
    valid frame in the stream (found by the million-frame run: a forced DISARM re-formed
    that way). :meth:`accepts` tries a candidate on a copy of the parser state and keeps it
    only if nothing valid comes out."""

    def __init__(self) -> None:
        self.m = mavlink_module()
        self.parser = self._new()

    def _new(self) -> Any:
        p = self.m.MAVLink(None)
        p.robust_parsing = True
        return p

    def _clone(self) -> Any:
        c = self._new()
        src = self.parser
        c.buf = bytearray(src.buf[src.buf_index :])
        c.buf_index = 0
        c.expected_length = src.expected_length
        c.have_prefix_error = src.have_prefix_error
        return c

    def accepts(self, data: bytes) -> bool:
        """True (and the stream advanced) when ``data`` yields no valid message in the stream."""
        trial = self._clone()
        try:
            msgs = trial.parse_buffer(data) or []
        except Exception:  # noqa: BLE001 - a receiver drops its buffer on a parser error
            self.parser = self._new()
            return True
        if any(x.get_type() != "BAD_DATA" and not x.get_type().startswith("UNKNOWN_") for x in msgs):
            return False
        self.parser = trial
        return True


def mutations(rng: np.random.Generator, seeds: list[bytes], n: int) -> Corpus:
    """``n`` invalid frames: random bytes (half of them starting with a MAVLink magic),
    1-8 flipped bits of a valid seed frame, a truncated seed frame, or a seed frame with
    random bytes appended inside the claimed length (its CRC no longer matches).

    Each is invalid on its own (fresh reference parser) *and* in the stream of the frames
    before it, sent from one peer (:class:`StreamReference`)."""
    corpus = Corpus()
    stream = StreamReference()
    for s in seeds:
        corpus.seed_types.update(x.get_type() for x in reference_messages(s))
    while len(corpus.frames) < n:
        kind = int(rng.integers(4))
        if kind == 0:
            data = bytearray(rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
            if rng.random() < 0.5:
                data[0] = 0xFD if rng.random() < 0.7 else 0xFE
            name = "random"
        elif kind == 1:
            data = bytearray(seeds[int(rng.integers(len(seeds)))])
            nbits = int(rng.integers(1, 9))
            for bit in rng.choice(8 * len(data), size=nbits, replace=False):  # distinct bits
                data[int(bit) // 8] ^= 1 << (int(bit) % 8)
            name = "bitflip"
        elif kind == 2:
            data = bytearray(seeds[int(rng.integers(len(seeds)))])
            data = data[: int(rng.integers(1, len(data)))]
            name = "truncated"
        else:
            # the payload-length byte is raised so the frame claims more bytes, which are random
            data = bytearray(seeds[int(rng.integers(len(seeds)))])
            extra = int(rng.integers(1, 40))
            data[1] = min(255, data[1] + extra)
            data += rng.integers(0, 256, size=extra, dtype=np.uint8).tobytes()
            name = "extended"
        if reference_messages(bytes(data)):
            corpus.valid_mutations += 1
            continue
        if not stream.accepts(bytes(data)):
            corpus.valid_in_stream += 1
            continue
        corpus.frames.append(bytes(data))
        corpus.kinds[name] += 1
    return corpus


def batches(frames: list[bytes], size: int) -> Iterator[list[bytes]]:
    """Consecutive slices of ``frames`` of at most ``size``."""
    for i in range(0, len(frames), size):
        yield frames[i : i + size]
