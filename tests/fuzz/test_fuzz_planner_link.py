"""MAVLink fuzz of the planner's link parser (``comms.mavlink_client.VehicleLink``) over a real
UDP socket on 127.0.0.1 (issue 7, hostile input).

The link is opened as the launcher opens it (``udpout:`` to its vehicle). A test socket plays
the vehicle (system 1): after every batch of invalid frames (tests/fuzz/frames.py, mutated
from the telemetry an autopilot sends: HEARTBEAT, LOCAL/GLOBAL_POSITION, COMMAND_ACK,
STATUSTEXT, ... in MAVLink 2 and 1), the vehicle socket sends a *probe*: a HEARTBEAT with
custom mode i, a LOCAL_POSITION_NED with x = i, stamped i ms, and a STATUSTEXT "probe i".
Valid frames of *another* system (2) with other values are mixed into the fuzz stream.

The fuzz comes from the vehicle's own address (a corrupted link or a spoofed source: the
parser must cope), one frame in ten from a foreign host (dropped by the link since ad1f0f7).
A probe that a fuzz frame damaged would be re-sent (after 280 zero bytes, longer than any
frame, so the parser is back in phase); with datagram-bounded parsing none is needed.
The check is on the link's state after every batch: it equals the last probe
exactly (position, velocity, mode, armed, timestamp), no COMMAND_ACK or foreign STATUSTEXT ever
appears, and ``pump`` never raises.
"""

from __future__ import annotations

import select
import socket
import time

import numpy as np
import pytest

from comms.mavlink_client import VehicleLink
from tests.fuzz import frames as F
from tests.fuzz.udp import udp_drops
from tests.support.wait import wait_for

pytestmark = pytest.mark.integration

BATCH = 100


def probe_frames(i: int, pad: int = 0, sysid: int = 1) -> bytes:
    m = F.mavlink_module()
    enc, sink = F.encoder(sysid, 1)
    enc.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_ARDUPILOTMEGA, 128 if i % 2 else 0, 1000 + i, m.MAV_STATE_ACTIVE)
    enc.local_position_ned_send(i, float(i), 0.5, -2.0, 0.25, 0.0, 0.0)
    enc.statustext_send(6, (f"probe {i}" + "~" * pad).encode())
    return b"".join(sink.frames)


def foreign_frames(i: int) -> list[bytes]:
    """Valid telemetry of system 2 (another vehicle on the network): must be ignored."""
    m = F.mavlink_module()
    enc, sink = F.encoder(2, 1)
    enc.heartbeat_send(m.MAV_TYPE_QUADROTOR, m.MAV_AUTOPILOT_PX4, 128, 99, m.MAV_STATE_ACTIVE)
    enc.local_position_ned_send(10_000_000 + i, -500.0, -500.0, -500.0, 9.0, 9.0, 9.0)
    enc.command_ack_send(m.MAV_CMD_NAV_TAKEOFF, m.MAV_RESULT_ACCEPTED, 0, 0, 1, 191)
    enc.statustext_send(2, b"foreign")
    return sink.frames


def texts(link: VehicleLink) -> set[str]:
    return {t.split("~")[0] for t in link.statustexts}


def check_is_probe(link: VehicleLink, i: int) -> None:
    """The link's state is exactly what probe ``i`` said (and nothing else ever got in)."""
    tel = link.telemetry
    assert tel.custom_mode == 1000 + i and tel.armed == bool(i % 2) and tel.autopilot == 3, tel
    assert tel.position_time_ms == i
    np.testing.assert_array_equal(tel.position_enu_m, [0.5, float(i), 2.0])
    np.testing.assert_array_equal(tel.velocity_enu_mps, [0.0, 0.25, 0.0])
    assert link.acks == {}
    assert texts(link) <= {f"probe {k}" for k in range(i + 1)}


def run_link_fuzz(n_frames: int, seed: int) -> dict[str, float]:
    corpus = F.mutations(np.random.default_rng(seed), F.telemetry_seeds(1) + F.telemetry_seeds(2), n_frames)
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    vehicle.settimeout(10)
    fuzz = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    link = VehicleLink(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}", target_system=1)
    try:
        link.pump(0.0)  # sends our heartbeat: the link's socket is bound now
        _, planner_addr = vehicle.recvfrom(65535)
        vehicle.sendto(probe_frames(0), planner_addr)
        link.wait_for(lambda: "probe 0" in texts(link) and link.telemetry.position_time_ms == 0, 10, "first probe")
        check_is_probe(link, 0)
        drops0 = udp_drops(planner_addr[1])
        resent = 0
        t0 = time.perf_counter()
        for i, batch in enumerate(F.batches(corpus.frames, BATCH), start=1):
            for j, f in enumerate(batch):
                # from the vehicle's own address (a corrupted link, or a spoofed source address:
                # the link's parser must cope), every 10th from a foreign host
                (fuzz if j % 10 == 9 else vehicle).sendto(f, planner_addr)
                if j % 25 == 0:
                    vehicle.sendto(b"".join(foreign_frames(i)), planner_addr)
            link.pump(0.0)  # loopback delivery is synchronous: this parses the whole batch
            check_is_probe(link, i - 1)  # nothing of the fuzz, nothing of system 2
            deadline = time.monotonic() + 20

            def probed(i: int = i) -> bool:
                tel = link.telemetry
                return f"probe {i}" in texts(link) and tel.custom_mode == 1000 + i and tel.position_time_ms == i

            while not probed():
                assert time.monotonic() < deadline, f"probe {i} never got through"
                if resent % 2:  # 280 non-magic bytes end any claimed frame: the parser resyncs
                    vehicle.sendto(bytes(280), planner_addr)
                vehicle.sendto(probe_frames(i, pad=resent % 11), planner_addr)
                resent += 1
                link.pump(0.02)
            link.pump(0.0)
            check_is_probe(link, i)
        elapsed = time.perf_counter() - t0
        drops = udp_drops(planner_addr[1]) - drops0
        assert drops == 0, f"the kernel dropped {drops} datagrams on the planner's socket"
        return {
            "frames": len(corpus.frames),
            "seconds": elapsed,
            "frames_per_s": len(corpus.frames) / elapsed,
            "probe_sends": resent,
            "probes": i,
            "valid_mutations_set_aside": corpus.valid_mutations,
        }
    finally:
        link.close()
        vehicle.close()
        fuzz.close()


def test_planner_link_survives_20k_invalid_frames() -> None:
    """The default run's size: 200 batches, every probe read exactly (checked in the run)."""
    figures = run_link_fuzz(20_000, seed=97)
    print(figures)
    assert figures["probes"] == 200, figures


@pytest.mark.slow
def test_planner_link_survives_100k_invalid_frames() -> None:
    """The soak: 1000 batches."""
    figures = run_link_fuzz(100_000, seed=99)
    print(figures)
    assert figures["probes"] == 1000, figures


def test_third_party_byte_does_not_eat_vehicle_frames() -> None:
    """A single byte 0xFD sent by a third party to the planner's port, then one datagram of
    the vehicle (HEARTBEAT + LOCAL_POSITION_NED + STATUSTEXT): the vehicle's frames must be
    read. (Found by this fuzz: with pymavlink's mavudp, the stray magic byte plus the
    vehicle's frame header claimed a 278-byte signed frame that ate the vehicle's datagram;
    fixed in ad1f0f7: the link reads datagrams itself, accepts only the vehicle's address and
    never lets an unfinished frame span datagrams.)"""
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    vehicle.settimeout(10)
    intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    link = VehicleLink(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}", target_system=1)
    try:
        link.pump(0.0)
        _, planner_addr = vehicle.recvfrom(65535)
        vehicle.sendto(probe_frames(0), planner_addr)
        link.wait_for(lambda: "probe 0" in texts(link), 10, "first probe")
        intruder.sendto(b"\xfd", planner_addr)
        vehicle.sendto(probe_frames(1), planner_addr)
        link.wait_for(lambda: "probe 1" in texts(link), 2, "the vehicle's datagram after the stray byte")
    finally:
        link.close()
        vehicle.close()
        intruder.close()


def _link_and_vehicle() -> tuple[VehicleLink, socket.socket, tuple[str, int]]:
    vehicle = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    vehicle.bind(("127.0.0.1", 0))
    vehicle.settimeout(10)
    link = VehicleLink(f"udpout:127.0.0.1:{vehicle.getsockname()[1]}", target_system=1)
    link.pump(0.0)
    _, planner_addr = vehicle.recvfrom(65535)
    vehicle.sendto(probe_frames(0), planner_addr)
    link.wait_for(lambda: "probe 0" in texts(link), 10, "first probe")
    return link, vehicle, planner_addr


def test_stray_byte_from_the_vehicle_address_ends_with_its_datagram() -> None:
    """A lone magic byte in a datagram of the vehicle's own address (a corrupted packet) is
    dropped with its datagram: the next datagram's frames are read."""
    link, vehicle, planner_addr = _link_and_vehicle()
    try:
        vehicle.sendto(b"\xfd", planner_addr)
        link.pump(0.05)
        vehicle.sendto(probe_frames(1), planner_addr)
        link.wait_for(lambda: "probe 1" in texts(link), 2, "the vehicle's datagram after the stray byte")
    finally:
        link.close()
        vehicle.close()


def test_every_frame_of_a_multi_frame_datagram_is_read_when_datagrams_queue_up() -> None:
    """Two datagrams of three frames each (HEARTBEAT, LOCAL_POSITION_NED, STATUSTEXT), queued
    before the link reads (ArduPilot packs several frames in one UDP datagram): all six
    frames must be read. (Found by this test after ad1f0f7: pymavlink's bytes_needed()
    returns 1 when the buffer holds more than a frame, so the next datagram was read and the
    buffer reset, losing the first datagram's STATUSTEXT; fixed in 5a9581b.)"""
    link, vehicle, planner_addr = _link_and_vehicle()
    try:
        vehicle.sendto(probe_frames(1), planner_addr)
        vehicle.sendto(probe_frames(2), planner_addr)
        for _ in range(10):
            link.pump(0.02)
        assert {"probe 1", "probe 2"} <= texts(link)
    finally:
        link.close()
        vehicle.close()


class _SlowClock:
    """pymavlink's ``time`` module as a slow computer sees it: each ``time()`` call is 50 µs
    after the last (a float UNIX time has 0.24 µs steps: on a fast machine two calls often
    return the same value, on a slow one never)."""

    def __init__(self) -> None:
        self.t = time.time()

    def time(self) -> float:
        self.t += 5e-5
        return self.t

    def sleep(self, s: float) -> None:
        time.sleep(s)


def test_a_pump_without_waiting_reads_what_is_queued_on_a_slow_computer(monkeypatch: pytest.MonkeyPatch) -> None:
    """``pump(0.0)`` with a datagram queued reads it however slow the computer. (pymavlink's
    ``recv_match(timeout=0)`` returns before reading once its clock has moved between two
    calls: on a 2-3 × slower machine the planner read nothing between its waits, lost a
    restarted TCP vehicle for good and measured an x5 vehicle's clock at x1.3-x4.)"""
    from pymavlink import mavutil

    link, vehicle, planner_addr = _link_and_vehicle()
    try:
        vehicle.sendto(probe_frames(1), planner_addr)
        fd = link.fileno()
        assert fd is not None
        wait_for(lambda: select.select([fd], [], [], 0.0)[0], 10.0, "the probe to reach the planner's socket", interval_s=0.01)
        monkeypatch.setattr(mavutil, "time", _SlowClock())
        assert link.pump(0.0) >= 3
        assert "probe 1" in texts(link)
    finally:
        link.close()
        vehicle.close()
