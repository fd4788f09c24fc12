"""Adding an autopilot flavour is one :class:`comms.autopilot.FlavourInfo` in the registry.

Two toy flavours are registered here, in the test only (``comms.autopilot.FLAVOURS`` patched
for the test's duration): an ArduPilot-like copter with another HEARTBEAT autopilot id and
other custom-mode numbers, and a PX4-like one (take-off on setpoints, main/sub mode numbers)
with other main-mode numbers. For each, a simulated vehicle of that flavour runs in-process on
a loopback UDP port (free port) and the planner's MAVLink client
(:class:`comms.mavlink_client.VehicleLink`) detects the flavour from the HEARTBEAT, waits until
the vehicle is ready, arms, takes off and flies a setpoint, by the toy profile's rules alone.
docs/autopilot-flavours.md walks through the same toy flavours.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from types import MappingProxyType

import numpy as np
import pytest

from comms import autopilot
from comms.autopilot import ARDUPILOT, PX4, FlavourInfo, Mode, client_mode_table, px4_custom_mode
from comms.mavlink_client import VehicleLink
from comms.mavlink_telemetry import MSG_EXTENDED_SYS_STATE, MSG_GPS_RAW_INT, MSG_HOME_POSITION, MSG_LOCAL_POSITION_NED, MSG_SYS_STATUS
from vehicle_sim.clock import RealTimeClock
from vehicle_sim.config import VehicleConfig
from vehicle_sim.host import VehicleHost, build_vehicle

#: An ArduPilot-like copter: its rules, HEARTBEAT.autopilot 13, every mode number + 20.
MODE_OFFSET = 20
TOY_COPTER: FlavourInfo = dataclasses.replace(
    ARDUPILOT,
    name="toycopter",
    display_name="ToyCopter",
    autopilot=13,
    modes=tuple(dataclasses.replace(m, custom_mode=m.custom_mode + MODE_OFFSET) for m in ARDUPILOT.modes),
    boot_mode=ARDUPILOT.boot_mode + MODE_OFFSET,
    air_boot_mode=ARDUPILOT.air_boot_mode + MODE_OFFSET,
    hold_mode=ARDUPILOT.hold_mode + MODE_OFFSET,
    guided_mode=ARDUPILOT.guided_mode + MODE_OFFSET,
    land_mode=ARDUPILOT.land_mode + MODE_OFFSET,
    rtl_mode=ARDUPILOT.rtl_mode + MODE_OFFSET,
)


def _shift_main(custom_mode: int, offset: int = 8) -> int:
    """A PX4 custom_mode with its main mode moved by ``offset`` (sub mode kept)."""
    return px4_custom_mode(((custom_mode >> 16) & 0xFF) + offset, (custom_mode >> 24) & 0xFF)


def _shift_mode(m: Mode) -> Mode:
    return dataclasses.replace(m, custom_mode=_shift_main(m.custom_mode))


#: A PX4-like autopilot: its rules (OFFBOARD-style guided mode entered on a setpoint stream,
#: take-off by setpoint, main/sub mode numbers), HEARTBEAT.autopilot 14, main modes + 8.
TOY_OFFBOARD: FlavourInfo = dataclasses.replace(
    PX4,
    name="toyoffboard",
    display_name="ToyOffboard",
    autopilot=14,
    modes=tuple(_shift_mode(m) for m in PX4.modes),
    boot_mode=_shift_main(PX4.boot_mode),
    air_boot_mode=_shift_main(PX4.air_boot_mode),
    hold_mode=_shift_main(PX4.hold_mode),
    guided_mode=_shift_main(PX4.guided_mode),
    takeoff_mode=None if PX4.takeoff_mode is None else _shift_main(PX4.takeoff_mode),
    land_mode=_shift_main(PX4.land_mode),
    rtl_mode=_shift_main(PX4.rtl_mode),
)

#: Sim seconds per wall second of the in-process vehicle.
SPEEDUP = 5.0
#: The client's deadline for each stage (wall s).
STAGE_TIMEOUT_S = 30.0
TAKEOFF_ALT_M = 5.0


@pytest.fixture(params=[TOY_COPTER, TOY_OFFBOARD], ids=lambda f: f.name)
def toy(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> Iterator[FlavourInfo]:
    """The toy flavour, registered for this test only."""
    info: FlavourInfo = request.param
    monkeypatch.setattr(autopilot, "FLAVOURS", MappingProxyType({**autopilot.FLAVOURS, info.name: info}))
    yield info


def test_toy_flavour_registered_only_in_the_test(toy: FlavourInfo) -> None:
    assert autopilot.flavour_info(toy.name) is toy
    assert autopilot.flavour_of_autopilot(toy.autopilot) == toy.name
    assert toy.name in autopilot.flavour_names()
    # Mode numbers differ from the flavour the toy copies: the client must take them from the profile.
    assert not set(client_mode_table(toy.name).values()) & {m.custom_mode for m in (ARDUPILOT.modes + PX4.modes)}


def test_client_arms_takes_off_and_flies_a_toy_flavour(toy: FlavourInfo) -> None:
    config = VehicleConfig(flavour=toy.name, sysid=7, start_enu_m=(3.0, -2.0, 0.0), ready_after_s=3.0)
    vehicle = build_vehicle(config, "udpin:127.0.0.1:0")
    host = VehicleHost([vehicle], RealTimeClock(SPEEDUP))
    host.start()
    _, host_name, port = vehicle.link.transport.address.split(":")
    link = VehicleLink(f"udpout:{host_name}:{port}", target_system=config.sysid)
    try:
        link.wait_heartbeat(STAGE_TIMEOUT_S)
        assert link.telemetry.autopilot == toy.autopilot
        assert link.flavour == toy.name and link.profile is toy
        rates = {MSG_LOCAL_POSITION_NED: 10.0, MSG_SYS_STATUS: 1.0, MSG_GPS_RAW_INT: 1.0, MSG_HOME_POSITION: 0.5, MSG_EXTENDED_SYS_STATE: 1.0}
        link.request_streams(rates, [MSG_EXTENDED_SYS_STATE])
        link.request_message(MSG_HOME_POSITION)
        link.wait_for(lambda: not link.not_ready(require_gps=False) and link.telemetry.home_known, STAGE_TIMEOUT_S, "vehicle ready")
        link.wait_for(lambda: link.telemetry.position_enu_m is not None, STAGE_TIMEOUT_S, "position")
        start = link.telemetry.position_enu_m
        assert start is not None and abs(float(start[2])) < 0.5
        guided = next(name for name, custom in client_mode_table(toy.name).items() if custom == toy.guided_mode)
        above = np.array([float(start[0]), float(start[1]), TAKEOFF_ALT_M])
        if toy.takeoff_by_setpoint:
            # PX4-like: the setpoint stream runs before the guided mode is entered, the vehicle
            # lifts off on it once armed.
            link.set_stream(lambda _t: (above, None), period_s=0.25 / SPEEDUP)
            link.wait_for(lambda: link.setpoints_sent >= 4, STAGE_TIMEOUT_S, "setpoint stream")
            link.set_mode(guided)
            link.arm()
        else:
            # ArduPilot-like: guided mode, arm, take-off command.
            link.set_mode(guided)
            link.arm()
            link.takeoff(TAKEOFF_ALT_M - link.home_z_m())
        assert link.in_mode(guided) and link.telemetry.armed
        link.wait_for(lambda: _z(link) >= TAKEOFF_ALT_M - 0.3, STAGE_TIMEOUT_S, f"take-off to {TAKEOFF_ALT_M:g} m")
        target = np.array([float(start[0]) + 6.0, float(start[1]) + 4.0, TAKEOFF_ALT_M + 2.0])
        link.set_stream(lambda _t: (target, None), period_s=0.25 / SPEEDUP)
        link.wait_for(lambda: _distance(link, target) < 0.5, STAGE_TIMEOUT_S, "setpoint reached")
        assert link.in_mode(guided) and link.telemetry.armed
        assert link.mode_name() == guided
    finally:
        link.close()
        host.close()


def _z(link: VehicleLink) -> float:
    pos = link.telemetry.position_enu_m
    return -np.inf if pos is None else float(pos[2])


def _distance(link: VehicleLink, target: np.ndarray) -> float:
    pos = link.telemetry.position_enu_m
    return np.inf if pos is None else float(np.linalg.norm(np.asarray(pos) - target))
