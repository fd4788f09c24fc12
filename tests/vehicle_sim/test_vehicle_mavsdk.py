"""MAVSDK (native binding, ``mavsdk`` >= 4, in the ``[test]`` extra) accepts
the simulated vehicle: discovery, AUTOPILOT_VERSION, parameters, arm, take-off, goto (ArduPilot)
and OFFBOARD (PX4). Positions are checked with pyproj's geodesic, not the vehicle's code."""

from __future__ import annotations


import pytest
from pyproj import Geod

from vehicle_sim.config import Origin

from tests.support.proc import Proc, fimnav
from tests.support.wait import wait_for

pytestmark = pytest.mark.integration
GEOD = Geod(ellps="WGS84")


def _start(*args: str, speedup: str = "5") -> tuple[Proc, str]:
    proc = Proc(fimnav("vehicle", "--mavlink", "tcpin:127.0.0.1:0", "--speedup", speedup, *args))
    line = proc.expect(r"\{\"event\": \"ready\".*\}\n", timeout_s=30).group(0)
    port = line.split('"mavlink": "')[1].split('"')[0].rsplit(":", 1)[1]
    return proc, port


def _system(port: str):
    from mavsdk import ComponentType, Configuration, Mavsdk

    m = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    assert int(m.add_any_connection(f"tcpout://127.0.0.1:{port}")) == 0  # SUCCESS
    system = m.first_autopilot(15.0)
    assert system is not None, "MAVSDK found no autopilot"
    return m, system


def test_mavsdk_ardupilot_arm_takeoff_goto():
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.info import Info
    from mavsdk.plugins.param import Param
    from mavsdk.plugins.telemetry import Telemetry

    proc, port = _start()
    m = None
    try:
        m, system = _system(port)
        assert system.get_system_id() == 1 and system.has_autopilot()
        version = Info(system).get_version()
        assert version.flight_sw_major == 4
        assert Param(system).get_param_float("WPNAV_SPEED") == pytest.approx(1000.0)
        action, telemetry = Action(system), Telemetry(system)
        action.set_takeoff_altitude(6.0)
        action.arm()
        action.takeoff()
        wait_for(lambda: abs(telemetry.position().relative_altitude_m - 6.0) < 0.1, 30, "take-off altitude", interval_s=0.05)
        o = Origin()
        lon, lat, _ = GEOD.fwd(o.lon_deg, o.lat_deg, 120.0, 30.0)
        action.goto_location(lat, lon, o.alt_m + 9.0, 0.0)

        def arrived():
            p = telemetry.position()
            return GEOD.inv(lon, lat, p.longitude_deg, p.latitude_deg)[2] < 0.3 and abs(p.relative_altitude_m - 9.0) < 0.1

        wait_for(arrived, 40, "goto target", interval_s=0.05)
    finally:
        if m is not None:
            m.destroy()
        proc.stop()


def test_mavsdk_px4_offboard():
    from mavsdk.plugins.action import Action
    from mavsdk.plugins.offboard import Offboard, PositionNedYaw
    from mavsdk.plugins.telemetry import Telemetry

    # real time: MAVSDK streams offboard setpoints at 20 Hz of wall time; the 1 s offboard-loss
    # failsafe must not fire when the loaded machine delays it
    proc, port = _start("--flavour", "px4", "--profile", "ideal", speedup="1")
    m = None
    try:
        m, system = _system(port)
        action, offboard, telemetry = Action(system), Offboard(system), Telemetry(system)
        action.arm()
        action.takeoff()
        wait_for(lambda: telemetry.position().relative_altitude_m > 2.0, 30, "PX4 take-off", interval_s=0.05)
        target = PositionNedYaw(north_m=8.0, east_m=-3.0, down_m=-5.0, yaw_deg=0.0)
        offboard.set_position_ned(target)  # PX4 needs a setpoint before OFFBOARD
        offboard.start()
        assert offboard.is_active()
        wait_for(lambda: (lambda p: abs(p.position.north_m - 8.0) < 0.05 and abs(p.position.east_m + 3.0) < 0.05
                          and abs(p.position.down_m + 5.0) < 0.05)(telemetry.position_velocity_ned()), 30, "OFFBOARD target",
                 interval_s=0.05)
        offboard.stop()
    finally:
        if m is not None:
            m.destroy()
        proc.stop()
