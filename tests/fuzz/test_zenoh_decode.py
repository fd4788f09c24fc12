"""Hostile Zenoh payloads at the decoder (``comms.messages.decode``) and at the planner's
inbox (``planner.node.inbox.Inbox.decode``): property tests with hypothesis.

Properties: any byte string either decodes or raises :class:`MessageError` (never another
exception); whatever decodes re-encodes to the same bytes (so nothing is silently
reinterpreted) and carries only finite, plausible values; every single corruption of a
valid record that the validator must catch (truncation, version, kind, mission tag, NaN or
infinite fields, role/flag bits, sender range) is refused; the inbox counts and drops
spoofed senders (sender ≠ key expression) and kinds on the wrong key.
"""

from __future__ import annotations

import dataclasses
import math
import struct
from types import MappingProxyType
from typing import ClassVar

import pytest
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from comms import keys
from comms.messages import (
    MAX_COORD_M,
    Done,
    MessageError,
    MessageKind,
    Record,
    Status,
    Tick,
    decode,
    encode,
    mission_tag,
)
from planner.node import Inbox
from planner.sensing import COMPONENTS, ROLES, SensingComponent, SensingRole, SensingTable

MISSION = "alpha"
N = 5
HEADER = 14

finite = st.floats(allow_nan=False, allow_infinity=False, min_value=-1e5, max_value=1e5)
angle = st.floats(min_value=-3.14, max_value=3.14)


def _draw_observation(draw: st.DrawFn, ranging: bool, bearing: bool, extra_values: dict[str, float] | None = None) -> Record:
    """A record of the given roles with drawn sender, step, time, position and measurements."""
    return Record(
        sender=draw(st.integers(1, N)), step=draw(st.integers(0, 10_000)), time_s=draw(finite),
        position_m=(draw(finite), draw(finite), draw(finite)), ranging=ranging, bearing=bearing, los=draw(st.booleans()),
        range_m=draw(finite) if ranging else math.nan,
        azimuth_rad=draw(angle) if bearing else math.nan,
        elevation_rad=draw(st.floats(min_value=-1.5, max_value=1.5)) if bearing else math.nan,
        stale=draw(st.booleans()),
        taken_over=draw(st.booleans()),
        **({} if extra_values is None else {"extra_values": extra_values}),
    )


@st.composite
def observations(draw: st.DrawFn) -> Record:
    ranging, bearing = draw(st.sampled_from([(True, False), (False, True), (True, True)]))
    return _draw_observation(draw, ranging, bearing)


def valid_record(sender: int = 2) -> bytes:
    return encode(Record(sender, 3, 1.5, (1.0, 2.0, 3.0), True, True, True, 10.0, 0.1, 0.2), MISSION, 7)


def _finite_values(msg: object) -> bool:
    if isinstance(msg, Record):
        return math.isfinite(msg.time_s) and all(math.isfinite(v) and abs(v) <= MAX_COORD_M for v in msg.position_m)
    if isinstance(msg, (Tick, Status)):
        return math.isfinite(msg.time_s)
    return True


@settings(max_examples=3000, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.binary(max_size=200))
def test_random_bytes_never_raise_anything_but_message_error(data: bytes) -> None:
    try:
        header, msg = decode(data, MISSION, N)
    except MessageError:
        return
    assert _finite_values(msg)


@settings(max_examples=2000, deadline=None)
@given(observations(), st.data())
def test_any_corruption_of_a_record_is_refused_or_reencodes_identically(obs: Record, data: st.DataObject) -> None:
    raw = bytearray(encode(obs, MISSION, 1))
    i = data.draw(st.integers(0, len(raw) - 1))
    raw[i] ^= data.draw(st.integers(1, 255))
    try:
        header, msg = decode(bytes(raw), MISSION, N)
    except MessageError:
        return
    # a mutation that still decodes must be a message that says exactly those bytes
    assert encode(msg, MISSION, header.seq, kind=header.kind) == bytes(raw)
    assert _finite_values(msg)


@settings(max_examples=500, deadline=None)
@given(observations())
def test_valid_records_round_trip(obs: Record) -> None:
    header, msg = decode(encode(obs, MISSION, 9), MISSION, N)
    assert header.kind == MessageKind.RECORD and header.seq == 9
    assert msg.sender == obs.sender and msg.position_m == obs.position_m and msg.step == obs.step


@given(st.binary(min_size=0, max_size=200).filter(lambda b: len(b) != len(valid_record())))
def test_truncated_or_padded_records_are_refused(tail: bytes) -> None:
    raw = valid_record()
    cut = raw[: len(tail) % len(raw)] if len(tail) < len(raw) else raw + tail[: len(tail) - len(raw)]
    assume(len(cut) != len(raw))
    with pytest.raises(MessageError):
        decode(cut, MISSION, N)


@pytest.mark.parametrize("version", [0, 2, 3, 255])
def test_unknown_schema_versions_are_refused(version: int) -> None:
    raw = bytearray(valid_record())
    raw[2] = version
    with pytest.raises(MessageError, match="unknown schema version"):
        decode(bytes(raw), MISSION, N)


@pytest.mark.parametrize("kind", [0, 6, 77, 255])
def test_unknown_kinds_are_refused(kind: int) -> None:
    raw = bytearray(valid_record())
    raw[3] = kind
    with pytest.raises(MessageError, match="unknown message kind"):
        decode(bytes(raw), MISSION, N)


def test_records_of_another_mission_are_refused() -> None:
    other = encode(Record(2, 3, 1.5, (1.0, 2.0, 3.0), True, False, True, 10.0, math.nan, math.nan), "bravo", 7)
    assert mission_tag("bravo") != mission_tag(MISSION)
    with pytest.raises(MessageError, match="another mission"):
        decode(other, MISSION, N)


# Offsets in a record (header 14 bytes, body <Id3dBBddd): step 14, time 18, x 26, y 34, z 42,
# role 50, flags 51, range 52, azimuth 60, elevation 68.
FIELDS = {"time": 18, "x": 26, "y": 34, "z": 42, "range": 52, "azimuth": 60, "elevation": 68}


@pytest.mark.parametrize(
    ("field", "value"),
    # time is only required finite (sim or wall seconds): 1e300 s is a valid time
    [(f, v) for f in sorted(FIELDS) for v in (math.inf, -math.inf, 1e300) if not (f == "time" and math.isfinite(v))],
)
def test_infinite_or_huge_values_are_refused(field: str, value: float) -> None:
    raw = bytearray(valid_record())
    struct.pack_into("<d", raw, FIELDS[field], value)
    with pytest.raises(MessageError):
        decode(bytes(raw), MISSION, N)


@pytest.mark.parametrize("field", ["time", "x", "y", "z"])
def test_nan_position_or_time_is_refused(field: str) -> None:
    raw = bytearray(valid_record())
    struct.pack_into("<d", raw, FIELDS[field], math.nan)
    with pytest.raises(MessageError, match="finite"):
        decode(bytes(raw), MISSION, N)


def test_nan_measurement_means_not_measured_and_is_handled_by_the_estimator_contract() -> None:
    """NaN range/angles are the wire's 'not measured' (module doc): they decode as NaN."""
    raw = bytearray(valid_record())
    struct.pack_into("<d", raw, FIELDS["range"], math.nan)
    _, msg = decode(bytes(raw), MISSION, N)
    assert math.isnan(msg.range_m)


@pytest.mark.parametrize("sender", [0, N + 1, 65535])
def test_sender_out_of_range_is_refused(sender: int) -> None:
    raw = bytearray(valid_record())
    struct.pack_into("<H", raw, 8, sender)
    with pytest.raises(MessageError, match="sender id"):
        decode(bytes(raw), MISSION, N)


@pytest.mark.parametrize("role,flags", [(0, 1), (4, 1), (255, 1), (3, 8), (3, 255)])
def test_unknown_role_or_flag_bits_are_refused(role: int, flags: int) -> None:
    raw = bytearray(valid_record())
    raw[50], raw[51] = role, flags
    with pytest.raises(MessageError):
        decode(bytes(raw), MISSION, N)


def test_status_with_a_huge_peer_count_is_refused() -> None:
    st_raw = encode(Status(1, 2, 0.5, (1.0, 2.0, 3.0), True, False, 0, (1, 1, 1, 1, 1)), MISSION, 1)
    raw = bytearray(st_raw)
    struct.pack_into("<H", raw, HEADER + 39, 65535)
    with pytest.raises(MessageError):
        decode(bytes(raw), MISSION, N)


def test_tick_with_nan_time_is_refused() -> None:
    raw = bytearray(encode(Tick(3, 0.3), MISSION, 1))
    struct.pack_into("<d", raw, HEADER + 4, math.nan)
    with pytest.raises(MessageError):
        decode(bytes(raw), MISSION, N)


# ---------------------------------------------------------------------- the planner's inbox


def test_inbox_drops_spoofed_sender_and_counts_it() -> None:
    inbox = Inbox(MISSION, N)
    try:
        assert inbox.decode(keys.record(MISSION, 2), valid_record(2)) is not None
        assert inbox.decode(keys.record(MISSION, 3), valid_record(2)) is None  # sender 2 on drone 3's key
        assert inbox.decode(keys.measurement(MISSION, 2), valid_record(2)) is None  # a record on a measurement key
        assert inbox.decode(keys.done(MISSION, 2), valid_record(2)) is None
        assert inbox.decode(keys.record(MISSION, 2), b"garbage") is None
        assert sum(inbox.dropped.values()) == 4
    finally:
        inbox.close()


@settings(max_examples=1000, deadline=None)
@given(st.binary(max_size=120), st.sampled_from(["record/1", "record/4", "measurement/2", "clock/tick", "clock/done/3", "status/1"]))
def test_inbox_never_raises_and_counts_every_drop(data: bytes, tail: str) -> None:
    inbox = Inbox(MISSION, N)
    try:
        msg = inbox.decode(f"fimnav/{MISSION}/{tail}", data)
        assert (msg is None) == (sum(inbox.dropped.values()) == 1)
    finally:
        inbox.close()


def test_done_message_is_valid_reference() -> None:
    """The reference for the property above: valid messages pass the inbox."""
    inbox = Inbox(MISSION, N)
    try:
        assert inbox.decode(keys.done(MISSION, 3), encode(Done(3, 4), MISSION, 1)) == Done(3, 4)
        assert inbox.decode(keys.tick(MISSION), encode(Tick(4, 0.4), MISSION, 1)) == Tick(4, 0.4)
    finally:
        inbox.close()


# ----------------------------------------------------------------- the record's extension
def test_range_and_bearing_records_keep_their_bytes() -> None:
    """A record of range and bearing only has no extension: its bytes are pinned."""
    assert valid_record().hex() == (
        "464e01016a39e0d002000700000003000000000000000000f83f000000000000f03f00000000000000400000000000000840"
        "030100000000000024409a9999999999b93f9a9999999999c93f"
    )
    # ... and do not depend on a table having more components.
    assert encode(Record(2, 3, 1.5, (1.0, 2.0, 3.0), True, True, True, 10.0, 0.1, 0.2), MISSION, 7, sensing=TOY_TABLE) == valid_record()


class _Squared(SensingComponent):
    """Wire-only toy component (one value)."""

    name: ClassVar[str] = "range_squared"
    wire_bit: ClassVar[int] = 4
    value_names: ClassVar[tuple[str, ...]] = ("range_squared_m2",)


class _Pair(SensingComponent):
    """Wire-only toy component (two values)."""

    name: ClassVar[str] = "pair"
    wire_bit: ClassVar[int] = 8
    value_names: ClassVar[tuple[str, ...]] = ("first_m", "second_m")


TOY_TABLE = SensingTable(
    MappingProxyType(
        {
            **ROLES,
            "squared": SensingRole("squared", ("range_squared",), "toy"),
            "joint_squared": SensingRole("joint_squared", ("range", "bearing", "range_squared"), "toy"),
            "pair_squared": SensingRole("pair_squared", ("bearing", "range_squared", "pair"), "toy"),
        }
    ),
    COMPONENTS + (_Squared(), _Pair()),
)
TOY_ROLES = {"squared": (False, False, ("range_squared_m2",)), "joint_squared": (True, True, ("range_squared_m2",)),
             "pair_squared": (False, True, ("range_squared_m2", "first_m", "second_m"))}


@st.composite
def toy_observations(draw: st.DrawFn) -> Record:
    ranging, bearing, names = TOY_ROLES[draw(st.sampled_from(sorted(TOY_ROLES)))]
    value = st.one_of(finite, st.just(math.nan))
    return _draw_observation(draw, ranging, bearing, {name: draw(value) for name in names})


#: End of a record's fixed body (header 14 + body 62 bytes): an extension starts here.
BODY_END = 76


def toy_record() -> bytes:
    obs = Record(2, 3, 1.5, (1.0, 2.0, 3.0), False, True, True, math.nan, 0.1, 0.2, extra_values={"range_squared_m2": 100.0, "first_m": 1.0, "second_m": 2.0})
    return encode(obs, MISSION, 7, sensing=TOY_TABLE)


@settings(max_examples=500, deadline=None)
@given(toy_observations())
def test_extended_records_round_trip(obs: Record) -> None:
    raw = encode(obs, MISSION, 9, sensing=TOY_TABLE)
    header, msg = decode(raw, MISSION, N, sensing=TOY_TABLE)
    assert isinstance(msg, Record)
    assert list(msg.extra_values) == [n for n in TOY_TABLE.extra_value_names if n in obs.extra_values]
    assert all(v == obs.extra_values[k] or (math.isnan(v) and math.isnan(obs.extra_values[k])) for k, v in msg.extra_values.items())
    assert encode(msg, MISSION, header.seq, kind=header.kind, sensing=TOY_TABLE) == raw
    # A receiver whose table lacks the components refuses the record (its role bits).
    with pytest.raises(MessageError, match="role bits"):
        decode(raw, MISSION, N)


@settings(max_examples=1500, deadline=None)
@given(toy_observations(), st.data())
def test_any_corruption_of_an_extended_record_is_refused_or_reencodes_identically(obs: Record, data: st.DataObject) -> None:
    raw = bytearray(encode(obs, MISSION, 1, sensing=TOY_TABLE))
    i = data.draw(st.integers(0, len(raw) - 1))
    raw[i] ^= data.draw(st.integers(1, 255))
    try:
        header, msg = decode(bytes(raw), MISSION, N, sensing=TOY_TABLE)
    except MessageError:
        return
    assert encode(msg, MISSION, header.seq, kind=header.kind, sensing=TOY_TABLE) == bytes(raw)
    assert _finite_values(msg)


@settings(max_examples=1000, deadline=None)
@given(st.binary(max_size=30))
def test_random_tails_of_an_extended_record_are_refused_or_reencode_identically(tail: bytes) -> None:
    raw = toy_record()[:BODY_END] + tail  # the fixed body ends at byte 76
    try:
        header, msg = decode(raw, MISSION, N, sensing=TOY_TABLE)
    except MessageError:
        return
    assert encode(msg, MISSION, header.seq, kind=header.kind, sensing=TOY_TABLE) == raw


@pytest.mark.parametrize(
    ("tail", "match"),
    [
        (b"", "extension missing"),
        (bytes([2]) + struct.pack("<2d", 1.0, 2.0), "extension count 2: expected 3 values"),
        (bytes([3]) + struct.pack("<2d", 1.0, 2.0), "extension of 17 bytes, expected 25"),
        (bytes([3]) + struct.pack("<3d", 1.0, 2.0, 3.0) + b"\0", "extension of 26 bytes, expected 25"),
        (bytes([3]) + struct.pack("<3d", 1.0, math.inf, 3.0), "extension value first_m inf"),
        (bytes([3]) + struct.pack("<3d", -math.inf, 2.0, 3.0), "extension value range_squared_m2 -inf"),
    ],
)
def test_malformed_extensions_are_refused_naming_the_field(tail: bytes, match: str) -> None:
    with pytest.raises(MessageError, match=match):
        decode(toy_record()[:BODY_END] + tail, MISSION, N, sensing=TOY_TABLE)


def test_an_extension_on_a_range_and_bearing_record_is_refused() -> None:
    raw = valid_record() + bytes([1]) + struct.pack("<d", 1.0)
    for table in (None, TOY_TABLE):
        with pytest.raises(MessageError, match="record body of 71 bytes, expected 62"):
            decode(raw, MISSION, N) if table is None else decode(raw, MISSION, N, sensing=table)


def test_encode_refuses_extra_values_that_do_not_match_a_role() -> None:
    base = Record(2, 3, 1.5, (1.0, 2.0, 3.0), True, True, True, 10.0, 0.1, 0.2)
    for extra, match in (({"nope": 1.0}, "value names among"), ({"first_m": 1.0}, "all of"), ({"range_squared_m2": 1.0, "first_m": 1.0, "second_m": 2.0}, "no sensing role")):
        with pytest.raises(ValueError, match=match):
            encode(dataclasses.replace(base, extra_values=extra), MISSION, 1, sensing=TOY_TABLE)
