"""Lockstep clock: in-process ticks over real UDP MAVLink, and ticks from real Zenoh on loopback."""

from __future__ import annotations

import time

import numpy as np
import pytest

from comms import keys
from comms.messages import Done, Tick, encode
from comms.session import SessionSettings, open_session
from vehicle_sim.clock import TickQueue, ZenohTickSource
from vehicle_sim.config import Origin, VehicleConfig

from tests.support.net import free_port
from tests.support.wait import wait_for
from tests.vehicle_sim.clients import mavlink as R, wait_msg

pytestmark = pytest.mark.integration


def test_lockstep_posvel_steps_are_exact_over_udp(make_rig):
    """A planner-like client: read the step-k position p, send (p, v) (ArduPilot GUIDED moves
    the target along v), tick k+1; the ideal vehicle reports p + v dt (float32 rounding of the
    fields aside), stamped (k+1) dt."""
    cfg = VehicleConfig(profile="ideal", airborne=True, start_enu_m=(5.0, 150.0, 8.0), origin=Origin(45, 7, 100))
    rig = make_rig(cfg, lockstep=True)
    clock: TickQueue = rig.host.clock  # type: ignore[assignment]
    c = rig.client
    rng = np.random.default_rng(11)
    dt = 1.0
    clock.push(Tick(0, 0.0))
    m = wait_msg(c, "LOCAL_POSITION_NED", lambda m: m.time_boot_ms == 0)
    for k in range(20):
        p_ned = np.array([m.x, m.y, m.z], dtype=float)
        v_ned = rng.normal(size=3)
        v_ned *= rng.uniform(0.5, 1.0) / np.linalg.norm(v_ned)
        target = p_ned + v_ned * dt
        c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111000000,
                                                 *p_ned, *v_ned, 0, 0, 0, 0, 0)
        clock.push(Tick(k + 1, (k + 1) * dt))
        m = wait_msg(c, "LOCAL_POSITION_NED", lambda m, k=k: m.time_boot_ms == (k + 1) * 1000)
        np.testing.assert_allclose([m.x, m.y, m.z], target, rtol=0, atol=5e-5)
        n, e, d = target
        np.testing.assert_allclose(rig.vehicle.position, [e, n, -d], rtol=0, atol=5e-5)
    # between ticks nothing moves
    t = rig.vehicle.t
    assert rig.command(R.MAV_CMD_REQUEST_MESSAGE, R.MAVLINK_MSG_ID_HOME_POSITION) == 0
    assert rig.vehicle.t == t
    # an out-of-order tick is dropped
    assert not clock.push(Tick(3, 3.0))


def test_a_setpoint_sent_before_a_tick_applies_before_it(make_rig, monkeypatch):
    """The planner sends its setpoint for step k, then reports done; tick k+1 comes by a longer
    path. When both wait for the vehicle's loop in the same select(), the setpoint must still
    apply first: here the loop is held while the setpoint datagram and the tick arrive, then
    released, and the position reported at the tick is the setpoint's."""
    import threading

    import vehicle_sim.host as host_module

    cfg = VehicleConfig(profile="ideal", airborne=True, start_enu_m=(5.0, 150.0, 8.0), origin=Origin(45, 7, 100))
    rig = make_rig(cfg, lockstep=True)
    clock: TickQueue = rig.host.clock  # type: ignore[assignment]
    c = rig.client
    clock.push(Tick(0, 0.0))
    m = wait_msg(c, "LOCAL_POSITION_NED", lambda m: m.time_boot_ms == 0)

    real_select = host_module.select.select
    held, release = threading.Event(), threading.Event()

    class Gate:
        @staticmethod
        def select(*args):  # noqa: ANN002, ANN205
            if not release.is_set():
                held.set()
                release.wait(10.0)
            return real_select(*args)

    monkeypatch.setattr(host_module, "select", Gate)
    assert held.wait(5.0), "the vehicle loop did not reach select()"
    target = np.array([m.x + 0.6, m.y - 0.3, m.z - 0.2])
    c.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, 0b110111000000, *target, 0, 0, 0, 0, 0, 0, 0, 0)
    fds = rig.vehicle.link.filenos()
    deadline = time.monotonic() + 5.0
    while not real_select(fds, [], [], 0.05)[0]:
        assert time.monotonic() < deadline, "the setpoint did not reach the vehicle's socket"
    clock.push(Tick(1, 1.0))
    release.set()
    m = wait_msg(c, "LOCAL_POSITION_NED", lambda m: m.time_boot_ms == 1000)
    np.testing.assert_array_equal([m.x, m.y, m.z], target.astype(np.float32).astype(float))


@pytest.mark.parametrize(
    "payload, fragment",
    [
        (b"garbage", "dropped bad tick"),
        (encode(Tick(1, 1.0), "other-mission", 1), "message of another mission"),
        (encode(Done(1, 1), "m42", 1), "a Done on the tick key"),
    ],
)
def test_bad_tick_payloads_are_dropped(payload, fragment, caplog):
    """One encoding on the tick key, the mission clock's binary message of this mission: any
    other payload is dropped with a warning naming why, and counted."""
    clock = TickQueue()
    try:
        with caplog.at_level("WARNING", logger="vehicle_sim.clock"):
            assert clock.push_payload(payload, "m42") is False
        assert fragment in caplog.text and clock.dropped == 1 and clock.last is None
        assert clock.push_payload(encode(Tick(3, 1.5), "m42", 2), "m42") is True
        assert clock.last == Tick(3, 1.5)
    finally:
        clock.close()


def test_zenoh_ticks_drive_the_vehicle_and_bad_ticks_are_dropped(make_rig, caplog):
    cfg = VehicleConfig(profile="ideal", airborne=True, start_enu_m=(0.0, 0.0, 5.0))
    rig = make_rig(cfg, lockstep=True)
    clock: TickQueue = rig.host.clock  # type: ignore[assignment]
    port = free_port()
    source = ZenohTickSource("m42", clock, SessionSettings(listen=(f"tcp/127.0.0.1:{port}",)))
    pub_session = open_session(SessionSettings(listen=(), connect=(f"tcp/127.0.0.1:{port}",)))
    try:
        pub = pub_session.declare_publisher(keys.tick("m42"))
        # discovery takes a moment: repeat tick 1 until it lands (duplicates are dropped)
        wait_for(lambda: pub.put(encode(Tick(1, 1.0), "m42", 1)) or rig.vehicle.t >= 1.0, 10.0, "a zenoh tick", interval_s=0.05)
        c = rig.client
        wait_msg(c, "LOCAL_POSITION_NED", lambda m: m.time_boot_ms == 1000)
        with caplog.at_level("WARNING", logger="vehicle_sim.clock"):
            pub.put(encode(Tick(2, 2.0), "other", 2))
            pub.put(b"garbage")
            pub.put(encode(Tick(2, 2.5), "m42", 3))
            wait_for(lambda: rig.vehicle.t == 2.5, 5, "tick 2", interval_s=0.005)
        assert "dropped bad tick" in caplog.text and "message of another mission" in caplog.text
        assert clock.last == Tick(2, 2.5)
        wait_msg(c, "LOCAL_POSITION_NED", lambda m: m.time_boot_ms == 2500)
    finally:
        pub_session.close()
        source.close()
