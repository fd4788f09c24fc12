"""Robustness: random bytes and bit-flipped frames never crash the vehicle nor change its state.

"Malformed" is decided by an independent pymavlink parser in the test: a mutated frame that
still decodes to a valid message (a CRC collision of a framing-byte flip) is not malformed
and is skipped.
"""

from __future__ import annotations

import dataclasses
import socket

import numpy as np
import pytest

from vehicle_sim.config import VehicleConfig
from vehicle_sim.link import mavlink_module

from tests.support.wait import wait_for
from tests.vehicle_sim.clients import mavlink as R, wait_msg
from tests.vehicle_sim.memlink import decode_all, gcs_encoder, memory_vehicle


def _state_without_time(v):
    s = v.state()
    return dataclasses.replace(s, t_s=0.0)


def _seed_frames(sysid: int) -> list[bytes]:
    """Valid state-changing frames: arm, disarm, modes, takeoff, setpoints, params, origin."""
    enc, sink = gcs_encoder()
    enc.command_long_send(sysid, 1, R.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0)
    enc.command_long_send(sysid, 1, R.MAV_CMD_DO_SET_MODE, 0, 1, 6, 0, 0, 0, 0, 0)
    enc.command_long_send(sysid, 1, R.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0)
    enc.command_long_send(sysid, 1, R.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 32, 1000, 0, 0, 0, 0, 0)
    enc.command_int_send(sysid, 1, 6, R.MAV_CMD_DO_REPOSITION, 0, 0, -1, 1, 0, 0, 10, 10, 20.0)
    enc.set_mode_send(sysid, 1, 9)
    enc.set_position_target_local_ned_send(0, sysid, 1, 1, 0b110111000000, 50, 20, -10, 1, 1, 0, 0, 0, 0, 0, 0)
    enc.set_position_target_global_int_send(0, sysid, 1, 6, 0b110111111000, 10, 10, 30, 0, 0, 0, 0, 0, 0, 0, 0)
    enc.param_set_send(sysid, 1, b"WPNAV_SPEED", 100.0, R.MAV_PARAM_TYPE_REAL32)
    enc.param_set_send(sysid, 1, b"FENCE_ENABLE", 0.0, R.MAV_PARAM_TYPE_INT8)
    enc.set_gps_global_origin_send(sysid, 10, 10, 10)
    enc.request_data_stream_send(sysid, 1, 0, 0, 0)
    enc.mission_item_int_send(sysid, 1, 0, 6, 16, 2, 0, 0, 0, 0, 0, 10, 10, 10.0)
    return list(sink.frames)


def _is_malformed(data: bytes) -> bool:
    m = mavlink_module()
    parser = m.MAVLink(None)
    parser.robust_parsing = True
    try:
        msgs = parser.parse_buffer(data) or []
    except Exception:  # noqa: BLE001 - the reference parser choking means "malformed" too
        return True
    return all(x.get_type() == "BAD_DATA" for x in msgs)


def _mutations(rng: np.random.Generator, seeds: list[bytes], n: int) -> list[bytes]:
    out: list[bytes] = []
    while len(out) < n:
        kind = rng.integers(3)
        if kind == 0:  # random bytes, sometimes starting with a MAVLink magic
            data = bytearray(rng.integers(0, 256, size=int(rng.integers(1, 300)), dtype=np.uint8).tobytes())
            if rng.random() < 0.5:
                data[0] = 0xFD if rng.random() < 0.7 else 0xFE
        elif kind == 1:  # 1-4 flipped bits of a valid frame
            data = bytearray(seeds[int(rng.integers(len(seeds)))])
            for _ in range(int(rng.integers(1, 5))):
                i = int(rng.integers(len(data)))
                data[i] ^= 1 << int(rng.integers(8))
        else:  # truncated or extended valid frame
            data = bytearray(seeds[int(rng.integers(len(seeds)))])
            cut = int(rng.integers(1, len(data)))
            data = data[:cut] if rng.random() < 0.5 else data + rng.integers(0, 256, size=cut, dtype=np.uint8).tobytes()
        if _is_malformed(bytes(data)):
            out.append(bytes(data))
    return out


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_thousands_of_malformed_frames_change_nothing(flavour):
    cfg = VehicleConfig(flavour=flavour, airborne=True, start_enu_m=(1.0, 2.0, 6.0), profile="ideal")
    v, mem = memory_vehicle(cfg)
    seeds = _seed_frames(cfg.sysid)
    # the seeds are valid and do change the state (so the fuzz would notice a leak)
    probe, pmem = memory_vehicle(cfg)
    before = _state_without_time(probe)
    for f in seeds:
        pmem.inject(f)
    probe.advance_to(1.0)
    assert _state_without_time(probe) != before
    rng = np.random.default_rng(2024)
    frames = _mutations(rng, seeds, 5000)
    before = _state_without_time(v)
    for i in range(0, len(frames), 50):
        for f in frames[i : i + 50]:
            mem.inject(f, peer="gcs" if rng.random() < 0.5 else "other")
        v.advance_to(v.t + 0.02)
        assert _state_without_time(v) == before
    assert v.link.bad_frames >= 1000
    assert v.ignored_messages == 0 and v.healthy
    # still answers a valid command afterwards
    enc, sink = gcs_encoder()
    enc.command_long_send(cfg.sysid, 1, R.MAV_CMD_REQUEST_MESSAGE, 0, R.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
    mem.outbox.clear()
    mem.inject(sink.frames[-1], peer="fresh")
    v.advance_to(v.t + 0.02)
    from tests.vehicle_sim.memlink import decode_all

    types = {m.get_type() for m in decode_all(mem.outbox)}
    assert {"COMMAND_ACK", "AUTOPILOT_VERSION"} <= types


def test_well_formed_frames_with_absurd_values_are_refused(make_rig=None):
    cfg = VehicleConfig(airborne=True, start_enu_m=(0.0, 0.0, 5.0), profile="ideal")
    v, mem = memory_vehicle(cfg)
    enc, sink = gcs_encoder()
    nan = float("nan")
    enc.set_position_target_local_ned_send(0, 1, 1, 1, 0b110111111000, nan, 0, -5, 0, 0, 0, 0, 0, 0, 0, 0)
    enc.set_position_target_local_ned_send(0, 1, 1, 1, 0b110111000111, 0, 0, 0, float("inf"), 0, 0, 0, 0, 0, 0, 0)
    enc.set_position_target_local_ned_send(0, 1, 1, 99, 0b110111111000, 1, 1, -5, 0, 0, 0, 0, 0, 0, 0, 0)
    enc.set_position_target_local_ned_send(0, 1, 1, 1, 0b110111111110, 1, 1, -5, 0, 0, 0, 0, 0, 0, 0, 0)  # partial mask
    enc.set_position_target_global_int_send(0, 1, 1, 6, 0b110111111000, 2_000_000_000, 0, 5, 0, 0, 0, 0, 0, 0, 0, 0)
    enc.command_long_send(1, 1, R.MAV_CMD_DO_SET_MODE, 0, nan, nan, 0, 0, 0, 0, 0)
    enc.command_long_send(1, 1, R.MAV_CMD_SET_MESSAGE_INTERVAL, 0, nan, -5, 0, 0, 0, 0, 0)
    enc.command_long_send(1, 1, R.MAV_CMD_REQUEST_MESSAGE, 0, float("inf"), 0, 0, 0, 0, 0, 0)
    enc.param_set_send(1, 1, b"WPNAV_SPEED", nan, R.MAV_PARAM_TYPE_REAL32)
    enc.param_set_send(1, 1, b"\xff\xfe\x00", 1.0, R.MAV_PARAM_TYPE_REAL32)
    enc.request_data_stream_send(1, 1, 250, 65535, 1)
    before = _state_without_time(v)
    for f in sink.frames:
        mem.inject(f)
    v.advance_to(2.0)
    assert _state_without_time(v) == before
    assert v.ignored_messages == 0


@pytest.mark.integration
def test_fuzz_over_udp_keeps_the_vehicle_alive(make_rig):
    rig = make_rig(VehicleConfig(profile="ideal"), speedup=5.0)
    assert rig.set_mode("GUIDED") == 0 and rig.arm() == 0
    before = _state_without_time(rig.vehicle)
    rng = np.random.default_rng(7)
    frames = _mutations(rng, _seed_frames(1), 1000)
    host, port = rig.vehicle.link.transport.sock.getsockname()[:2]
    reads0 = rig.vehicle.link.reads_in
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        for i, f in enumerate(frames):
            s.sendto(f, (host, port))
            if i % 100 == 99:
                # Let the vehicle read what was sent before sending more (its socket buffer).
                wait_for(lambda n=i + 1: rig.vehicle.link.reads_in >= reads0 + n, 10.0, f"the vehicle to read {i + 1} datagrams", interval_s=0.005)
    assert rig.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_AUTOPILOT_VERSION) == 0
    wait_msg(rig.client, "HEARTBEAT", lambda m: m.get_srcSystem() == 1, timeout=3)
    assert _state_without_time(rig.vehicle) == before
    assert rig.vehicle.link.bad_frames >= 500 and rig.vehicle.healthy


HOSTILE = (float("nan"), float("inf"), float("-inf"), 1e30, -1e30, -1.0, 0.0, 3.5)
INT32 = (0, 2**31 - 1, -(2**31))


@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
@pytest.mark.parametrize("state", ["disarmed", "armed", "airborne"])
def test_every_command_answers_hostile_parameters_with_one_ack(flavour: str, state: str) -> None:
    """Each supported command, with each parameter slot in turn set to NaN, ±inf, ±1e30, -1,
    0 or a fraction (COMMAND_LONG and COMMAND_INT) and x/y at the int32 limits (COMMAND_INT),
    is answered with exactly one COMMAND_ACK and never reaches an exception net. The vehicle
    starts on the ground disarmed, on the ground armed (GUIDED on ArduPilot), or hovering."""
    m = mavlink_module()
    commands = [
        m.MAV_CMD_COMPONENT_ARM_DISARM, m.MAV_CMD_NAV_TAKEOFF, m.MAV_CMD_NAV_LAND, m.MAV_CMD_NAV_RETURN_TO_LAUNCH,
        m.MAV_CMD_DO_SET_MODE, m.MAV_CMD_SET_MESSAGE_INTERVAL, m.MAV_CMD_GET_MESSAGE_INTERVAL, m.MAV_CMD_REQUEST_MESSAGE,
        m.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, m.MAV_CMD_REQUEST_PROTOCOL_VERSION, m.MAV_CMD_GET_HOME_POSITION,
        m.MAV_CMD_DO_REPOSITION, m.MAV_CMD_DO_CHANGE_SPEED, m.MAV_CMD_DO_FENCE_ENABLE, 611,
    ]
    v, t = memory_vehicle(VehicleConfig(flavour=flavour, airborne=state == "airborne", profile="ideal"))
    enc, sink = gcs_encoder()
    if state == "armed":
        if flavour == "ardupilot":
            enc.command_long_send(1, 1, m.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        enc.command_long_send(1, 1, m.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
        for frame in sink.frames:
            t.inject(frame)
        v.poll()
        assert v.armed and not v.flying
        sink.frames.clear()
    for cmd in commands:
        for slot in range(7):
            for value in HOSTILE:
                p = [0.0] * 7
                p[slot] = value
                enc.command_long_send(1, 1, cmd, 0, *p)
                if slot not in (4, 5):  # x, y of COMMAND_INT are int32
                    enc.command_int_send(1, 1, 6, cmd, 0, 0, p[0], p[1], p[2], p[3], 0, 0, p[6])
        for x in INT32:
            for y in INT32:
                enc.command_int_send(1, 1, 6, cmd, 0, 0, -1, 0, 0, float("nan"), x, y, 10.0)
    for frame in sink.frames:
        t.outbox.clear()
        t.inject(frame)
        assert v.poll() == 1
        acks = [a for a in decode_all(t.outbox) if a.get_type() == "COMMAND_ACK"]
        assert len(acks) == 1, (frame.hex(), [a.to_dict() for a in acks])
    assert v.ignored_messages == 0


def test_a_command_handler_that_raises_still_answers_failed(monkeypatch: pytest.MonkeyPatch) -> None:
    """The exception net: a handler bug is counted, and the sender still gets its ACK."""
    m = mavlink_module()
    v, t = memory_vehicle()

    def broken(*_a: object) -> int:
        raise ZeroDivisionError("bug")

    monkeypatch.setitem(v.commands._handlers, m.MAV_CMD_DO_CHANGE_SPEED, broken)
    enc, sink = gcs_encoder()
    enc.command_long_send(1, 1, m.MAV_CMD_DO_CHANGE_SPEED, 0, 1, 5, 0, 0, 0, 0, 0)
    t.inject(sink.frames[0])
    v.poll()
    out = decode_all(t.outbox)
    acks = [a for a in out if a.get_type() == "COMMAND_ACK"]
    assert [(a.command, a.result) for a in acks] == [(m.MAV_CMD_DO_CHANGE_SPEED, m.MAV_RESULT_FAILED)]
    assert any(x.get_type() == "STATUSTEXT" and "internal error" in x.text for x in out)
    assert v.ignored_messages == 1
