"""Well-formed MAVLink commands carrying NaN, infinity or out-of-fence targets, sent to a real
vehicle_sim over UDP on 127.0.0.1: refused with the right COMMAND_ACK (or, for setpoints,
which have no ACK, ignored with a STATUSTEXT), and the vehicle's target does not move.

Expected results (MAVLink command protocol): a parameter the command cannot take is
MAV_RESULT_DENIED; a command valid in itself but not now (not armed, not flying) is
TEMPORARILY_REJECTED. NaN where the spec gives NaN a meaning (altitude of DO_REPOSITION:
"keep the current altitude"; PX4 take-off altitude: "default") is not an error.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from pymavlink import mavutil

from vehicle_sim.clock import RealTimeClock
from vehicle_sim.config import Geofence, VehicleConfig
from vehicle_sim.host import VehicleHost, build_vehicle
from vehicle_sim.vehicle import SimVehicle

from tests.fuzz.udp import recv_until

pytestmark = pytest.mark.integration

R = mavutil.mavlink
NAN, INF = math.nan, math.inf
FENCE = Geofence(z_min_m=2.0, z_max_m=30.0, x_min_m=-50, x_max_m=50, y_min_m=-50, y_max_m=50, action="reject")


class Rig:
    """One vehicle in a host thread and one pymavlink ground station."""

    def __init__(self, cfg: VehicleConfig) -> None:
        self.v: SimVehicle = build_vehicle(cfg, "udpin:127.0.0.1:0")
        self.host = VehicleHost([self.v], RealTimeClock(1.0))
        port = self.v.link.transport.sock.getsockname()[1]
        self.gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        self.host.start()
        self.gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
        recv_until(self.gcs, lambda m: m.get_type() == "HEARTBEAT" and m.get_srcSystem() == cfg.sysid, 10, "heartbeat")

    def drain(self) -> None:
        while self.gcs.recv_match(blocking=False) is not None:
            pass

    def ack(self, cmd: int, *p: float, use_int: bool = False, frame: int = R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT,
            x: int = 0, y: int = 0) -> tuple[int, list[str]]:
        """Send COMMAND_LONG / COMMAND_INT; return (result, STATUSTEXTs seen up to the ACK)."""
        q = list(p) + [0.0] * (7 - len(p))
        self.drain()
        if use_int:
            self.gcs.mav.command_int_send(1, 1, frame, cmd, 0, 0, q[0], q[1], q[2], q[3], x, y, q[6])
        else:
            self.gcs.mav.command_long_send(1, 1, cmd, 0, *q)
        texts: list[str] = []

        def done(m: Any) -> bool:
            if m.get_type() == "STATUSTEXT":
                texts.append(m.text)
            return m.get_type() == "COMMAND_ACK" and m.command == cmd

        a = recv_until(self.gcs, done, 5, f"COMMAND_ACK of {cmd}")
        # the reason is sent right after the ACK by the same handler: collect what has
        # arrived (a test that needs the reason waits for it with a deadline)
        while (m := self.gcs.recv_match(blocking=False)) is not None:
            if m.get_type() == "STATUSTEXT":
                texts.append(m.text)
        return int(a.result), texts

    def statustext(self, pattern: str, timeout_s: float = 5.0) -> str:
        return recv_until(self.gcs, lambda m: m.get_type() == "STATUSTEXT" and pattern in m.text, timeout_s, f"STATUSTEXT {pattern!r}").text

    def target(self) -> tuple[Any, ...]:
        c = self.v.flight.pm.command
        return (c.kind, None if c.position is None else tuple(c.position), None if c.velocity is None else tuple(c.velocity),
                self.v.mode.name, self.v.armed, self.v.setpoints.speed_override_mps)

    def close(self) -> None:
        self.host.close()
        self.gcs.close()


@pytest.fixture
def airborne() -> Iterator[Rig]:
    """ArduPilot-flavour vehicle hovering in GUIDED at (0, 0, 10) inside a 'reject' fence."""
    rig = Rig(VehicleConfig(airborne=True, start_enu_m=(0.0, 0.0, 10.0), profile="ideal", geofence=FENCE))
    try:
        r, _ = rig.ack(R.MAV_CMD_DO_SET_MODE, 1, 4)
        assert r == R.MAV_RESULT_ACCEPTED
        yield rig
    finally:
        rig.close()


@pytest.fixture
def grounded() -> Iterator[Rig]:
    """ArduPilot-flavour vehicle on the ground, GUIDED and armed (ready to take off)."""
    rig = Rig(VehicleConfig(profile="ideal", geofence=FENCE))
    try:
        assert rig.ack(R.MAV_CMD_DO_SET_MODE, 1, 4)[0] == R.MAV_RESULT_ACCEPTED
        assert rig.ack(R.MAV_CMD_COMPONENT_ARM_DISARM, 1)[0] == R.MAV_RESULT_ACCEPTED
        yield rig
    finally:
        rig.close()


@pytest.mark.parametrize("alt", [NAN, INF, -INF, 31.0 - 0.0 + 100.0])
def test_takeoff_to_nan_infinite_or_above_fence_is_denied(grounded: Rig, alt: float) -> None:
    before = grounded.target()
    result, texts = grounded.ack(R.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, alt)
    assert result == R.MAV_RESULT_DENIED, texts
    if not any(t.startswith("Takeoff:") for t in texts):  # the vehicle thread may not have sent it yet
        grounded.statustext("Takeoff:", 3.0)
    assert grounded.target() == before and not grounded.v.flying


def test_takeoff_within_fence_is_accepted(grounded: Rig) -> None:
    """The reference: the same command with a sane altitude is accepted."""
    assert grounded.ack(R.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 10.0)[0] == R.MAV_RESULT_ACCEPTED


@pytest.mark.parametrize(
    "cmd,params",
    [
        (R.MAV_CMD_COMPONENT_ARM_DISARM, (NAN,)),
        (R.MAV_CMD_COMPONENT_ARM_DISARM, (INF,)),
        (R.MAV_CMD_DO_SET_MODE, (NAN, 4)),
        (R.MAV_CMD_DO_SET_MODE, (1, NAN)),
        (R.MAV_CMD_DO_SET_MODE, (1, INF)),
        (R.MAV_CMD_DO_CHANGE_SPEED, (1, NAN)),
        (R.MAV_CMD_DO_CHANGE_SPEED, (1, INF)),
        (R.MAV_CMD_DO_CHANGE_SPEED, (1, -3.0)),
        (R.MAV_CMD_DO_FENCE_ENABLE, (NAN,)),
        (R.MAV_CMD_SET_MESSAGE_INTERVAL, (32, NAN)),
        (R.MAV_CMD_SET_MESSAGE_INTERVAL, (NAN, 1000)),
        (R.MAV_CMD_REQUEST_MESSAGE, (INF,)),
        (R.MAV_CMD_DO_REPOSITION, (NAN, 0, 0, 0, NAN, NAN, NAN)),  # COMMAND_LONG: ints needed
    ],
)
def test_command_long_with_non_finite_parameters_is_denied(airborne: Rig, cmd: int, params: tuple[float, ...]) -> None:
    before = airborne.target()
    result, texts = airborne.ack(cmd, *params)
    assert result == R.MAV_RESULT_DENIED, texts
    assert airborne.target() == before
    assert airborne.v.ignored_messages == 0


@pytest.mark.parametrize(
    "x,y,alt",
    [
        (0, 0, 1000.0),  # above the fence
        (int(47.3977 * 1e7), int(8.5456 * 1e7), 10.0),  # far outside the box (another city)
        (2_000_000_000, 0, 10.0),  # latitude beyond the pole
    ],
)
def test_reposition_outside_the_fence_or_infinite_is_denied(airborne: Rig, x: int, y: int, alt: float) -> None:
    before = airborne.target()
    result, texts = airborne.ack(R.MAV_CMD_DO_REPOSITION, -1, 0, 0, NAN, 0, 0, alt, use_int=True, x=x, y=y)
    assert result == R.MAV_RESULT_DENIED, texts
    assert airborne.target() == before


def test_reposition_with_infinite_altitude_is_denied(airborne: Rig) -> None:
    result, texts = airborne.ack(R.MAV_CMD_DO_REPOSITION, -1, 0, 0, NAN, 0, 0, INF, use_int=True)
    assert result == R.MAV_RESULT_DENIED, texts


def test_reposition_with_nan_altitude_keeps_the_altitude(airborne: Rig) -> None:
    """NaN altitude means "current altitude" (MAV_CMD_DO_REPOSITION): accepted, z unchanged."""
    o = airborne.v.config.origin
    lat, lon, _ = airborne.v.frames.world.topocentric_to_geodetic(5.0, 5.0, 0.0)
    result, texts = airborne.ack(R.MAV_CMD_DO_REPOSITION, -1, 0, 0, NAN, 0, 0, NAN, use_int=True,
                                 x=int(round(lat * 1e7)), y=int(round(lon * 1e7)))
    assert result == R.MAV_RESULT_ACCEPTED, (texts, o)
    target = airborne.v.flight.pm.command.position
    assert target is not None and abs(target[2] - 10.0) < 1e-9 and abs(target[0] - 5.0) < 0.05


def test_reposition_with_nan_flags_outside_guided_is_denied() -> None:
    rig = Rig(VehicleConfig(airborne=True, start_enu_m=(0.0, 0.0, 10.0), profile="ideal", geofence=FENCE))
    try:
        assert rig.ack(R.MAV_CMD_DO_SET_MODE, 1, 5)[0] == R.MAV_RESULT_ACCEPTED  # LOITER
        result, _ = rig.ack(R.MAV_CMD_DO_REPOSITION, -1, NAN, 0, NAN, 0, 0, 10.0, use_int=True)
        assert result == R.MAV_RESULT_DENIED
        assert rig.v.ignored_messages == 0
    finally:
        rig.close()


def _setpoint_local(rig: Rig, mask: int, pos: tuple[float, float, float], vel: tuple[float, float, float]) -> None:
    rig.gcs.mav.set_position_target_local_ned_send(0, 1, 1, R.MAV_FRAME_LOCAL_NED, mask, *pos, *vel, 0, 0, 0, 0, 0)


POS = 0b110111111000
VEL = 0b110111000111
POSVEL = 0b110111000000


@pytest.mark.parametrize(
    "mask,pos,vel",
    [
        (POS, (NAN, 0.0, -10.0), (0, 0, 0)),
        (POS, (0.0, INF, -10.0), (0, 0, 0)),
        (VEL, (0, 0, 0), (NAN, 0.0, 0.0)),
        (VEL, (0, 0, 0), (0.0, 0.0, -INF)),
        (POSVEL, (1.0, 1.0, -10.0), (0.0, NAN, 0.0)),
    ],
)
def test_local_setpoint_with_non_finite_values_is_ignored_with_statustext(airborne: Rig, mask: int, pos, vel) -> None:  # noqa: ANN001
    before = airborne.target()
    airborne.drain()
    _setpoint_local(airborne, mask, pos, vel)
    assert "non-finite" in airborne.statustext("Setpoint:")
    assert airborne.target() == before


def test_local_setpoint_outside_the_fence_is_refused_with_statustext(airborne: Rig) -> None:
    before = airborne.target()
    airborne.drain()
    _setpoint_local(airborne, POS, (0.0, 500.0, -10.0), (0, 0, 0))  # 500 m east
    assert "refused" in airborne.statustext("Fence:")
    _setpoint_local(airborne, POS, (0.0, 0.0, -100.0), (0, 0, 0))  # 100 m up
    assert airborne.target() == before
    # the reference: a setpoint inside the fence is taken
    _setpoint_local(airborne, POS, (3.0, 4.0, -12.0), (0, 0, 0))
    recv_until(airborne.gcs, lambda m: m.get_type() == "LOCAL_POSITION_NED", 5, "telemetry")
    np.testing.assert_allclose(airborne.v.flight.pm.command.position, [4.0, 3.0, 12.0])


@pytest.mark.parametrize("alt,lat", [(NAN, 0), (INF, 0), (10.0, 2_000_000_000)])
def test_global_setpoint_with_invalid_values_is_ignored_with_statustext(airborne: Rig, alt: float, lat: int) -> None:
    before = airborne.target()
    airborne.drain()
    airborne.gcs.mav.set_position_target_global_int_send(0, 1, 1, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, POS, lat, 0, alt,
                                                          0, 0, 0, 0, 0, 0, 0, 0)
    assert "invalid values" in airborne.statustext("Setpoint:")
    assert airborne.target() == before


@pytest.mark.parametrize("z", [NAN, INF])
def test_guided_mission_item_with_non_finite_altitude_is_invalid(airborne: Rig, z: float) -> None:
    before = airborne.target()
    airborne.drain()
    airborne.gcs.mav.mission_item_int_send(1, 1, 0, R.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT, R.MAV_CMD_NAV_WAYPOINT, 2, 0,
                                           0, 0, 0, 0, 0, 0, z)
    ack = recv_until(airborne.gcs, lambda m: m.get_type() == "MISSION_ACK", 5, "MISSION_ACK")
    assert ack.type == R.MAV_MISSION_INVALID
    assert airborne.target() == before


@pytest.mark.parametrize("value", [NAN, INF, -INF])
def test_param_set_non_finite_keeps_the_value(airborne: Rig, value: float) -> None:
    old = airborne.v.parameters.params["WPNAV_SPEED"].get()
    airborne.drain()
    airborne.gcs.mav.param_set_send(1, 1, b"WPNAV_SPEED", value, R.MAV_PARAM_TYPE_REAL32)
    pv = recv_until(airborne.gcs, lambda m: m.get_type() == "PARAM_VALUE" and m.param_id == "WPNAV_SPEED", 5, "PARAM_VALUE")
    assert pv.param_value == pytest.approx(old) and airborne.v.parameters.params["WPNAV_SPEED"].get() == old
