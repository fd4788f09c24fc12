"""The real ``fimnav plan`` against a real ``fimnav vehicle --ready-after`` (ArduPilot and PX4
flavours), real time with a speed-up: the vehicle boots like a real copter (EKF aligning, no
GPS fix, no home, no EKF origin, arming refused), the planner says what it waits for, does not
arm before the vehicle is ready, then flies the mission.

The planner is started first and is already waiting for the vehicle's heartbeat when the
vehicle boots (the test holds the vehicle's UDP port until the planner's first heartbeat
arrives), so the planner sees the whole start-up whatever the machine's load. What happened is
read from the vehicle's .tlog (wall time stamps): the vehicle's own GPS_RAW_INT, HOME_POSITION,
STATUSTEXT and HEARTBEAT, and the planner's commands.
"""

from __future__ import annotations

import json
import os
import socket
import time
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from tests.external.helpers import SwarmPeer, write_mission
from tests.support.proc import Proc, fimnav

pytestmark = pytest.mark.integration

#: Sim seconds per wall second of both processes.
SPEEDUP = 5.0
#: Vehicle start-up (sim s): 3 s of wall time at SPEEDUP, long enough for the planner (already
#: connected when the vehicle boots) to request its streams and report what it waits for.
READY_AFTER_S = 15.0
MAV_CMD_COMPONENT_ARM_DISARM, MAV_CMD_NAV_TAKEOFF, MAV_CMD_DO_SET_MODE = 400, 22, 176


@dataclass
class StartUp:
    """What the vehicle's .tlog shows (wall seconds of the tlog stamps)."""

    first_s: float | None = None  # first frame sent by the vehicle
    fix_s: float | None = None  # first GPS_RAW_INT with a 3D fix
    home_s: float | None = None  # first HOME_POSITION sent by the vehicle
    armed_s: float | None = None  # first HEARTBEAT with the armed flag
    arm_commands_s: list[float] = field(default_factory=list)  # ARM commands from the planner
    fix_types_before: set[int] = field(default_factory=set)  # GPS_RAW_INT fix types before the fix
    sats_before: set[int] = field(default_factory=set)
    ekf_flags: list[int] = field(default_factory=list)  # EKF_STATUS_REPORT flags, changes only
    texts: list[tuple[float, str]] = field(default_factory=list)


def read_start_up(path: Path) -> StartUp:
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    s = StartUp()
    try:
        while (m := log.recv_match()) is not None:
            t, kind, ours = float(m._timestamp), m.get_type(), m.get_srcSystem() == 1 and m.get_srcComponent() == 1
            if ours and s.first_s is None:
                s.first_s = t
            if kind == "GPS_RAW_INT" and ours:
                if m.fix_type >= 3 and s.fix_s is None:
                    s.fix_s = t
                elif s.fix_s is None:
                    s.fix_types_before.add(int(m.fix_type))
                    s.sats_before.add(int(m.satellites_visible))
            elif kind == "HOME_POSITION" and ours and s.home_s is None:
                s.home_s = t
            elif kind == "HEARTBEAT" and ours and m.base_mode & 128 and s.armed_s is None:
                s.armed_s = t
            elif kind == "COMMAND_LONG" and not ours and m.command == MAV_CMD_COMPONENT_ARM_DISARM and m.param1 == 1:
                s.arm_commands_s.append(t)
            elif kind == "EKF_STATUS_REPORT" and ours and (not s.ekf_flags or s.ekf_flags[-1] != m.flags):
                s.ekf_flags.append(int(m.flags))
            elif kind == "STATUSTEXT" and ours:
                s.texts.append((t, m.text))
    finally:
        log.close()
    return s


def planner_then_vehicle(tmp_path: Path, procs: list[Proc], flavour: str, peer: SwarmPeer, mission: Path) -> tuple[Proc, Path]:
    """Start the planner towards a UDP port the test holds, wait for its first heartbeat there,
    then free the port and boot the vehicle on it."""
    hold = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    hold.bind(("127.0.0.1", 0))
    port = hold.getsockname()[1]
    tlog = tmp_path / f"{flavour}.tlog"
    try:
        planner = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--speedup", str(SPEEDUP),
                              "--zenoh-connect", peer.endpoint, "--preflight-timeout", "60",
                              "--mavlink", f"udpout:127.0.0.1:{port}"))
        procs.append(planner)
        hold.settimeout(0.2)
        deadline = time.monotonic() + 60.0
        while True:  # the planner is up and waiting for the vehicle's heartbeat
            assert time.monotonic() < deadline and planner.p.poll() is None, planner.tail()
            try:
                hold.recvfrom(65535)
                break
            except socket.timeout:
                continue
    finally:
        hold.close()
    vehicle = Proc(fimnav("vehicle", "--mission", str(mission), "--sysid", "1", "--mavlink", f"udpin:127.0.0.1:{port}",
                          "--profile", "pointmass", "--tlog", str(tlog), "--speedup", str(SPEEDUP), "--flavour", flavour,
                          "--ready-after", str(READY_AFTER_S)))
    procs.append(vehicle)
    vehicle.expect(r"\{\"event\": \"ready\"", 30.0)
    return planner, tlog


# ArduPilot readiness is also checked against the recorded SITL transcript (test_vehicle_vs_ardupilot).
@pytest.mark.parametrize("flavour", [pytest.param("ardupilot", marks=pytest.mark.slow), "px4"])
def test_planner_waits_for_a_starting_vehicle_then_flies(tmp_path: Path, procs: list[Proc], flavour: str) -> None:
    steps = 3
    mission = write_mission(tmp_path / "m.yaml", f"ready{flavour}", [[10.0, 20.0, 6.0]], steps, "land")
    peer = SwarmPeer(f"ready{flavour}", 1, {1: 70.0})
    try:
        planner, tlog = planner_then_vehicle(tmp_path, procs, flavour, peer, mission)
        assert planner.wait(90.0) == 0, planner.tail()
    finally:
        peer.close()
    summary = json.loads(planner.out.strip().splitlines()[-1])
    assert summary["steps"] == steps and summary["end"]["confirmed"], summary
    assert summary["end"]["armed"] is False and summary["end"]["landed_state"] == "ON_GROUND"

    # The planner said what it waited for, then went on once the vehicle was ready.
    err = planner.err
    waiting = [line for line in err.splitlines() if "waiting for the vehicle:" in line]
    assert waiting, err[-3000:]
    assert "GPS 3D fix (fix_type " in waiting[0] and "home position (HOME_POSITION)" in waiting[0], waiting[0]
    assert "EKF origin (GPS_GLOBAL_ORIGIN)" in waiting[0], waiting[0]
    if flavour == "ardupilot":
        assert "EKF position estimate (EKF_STATUS_REPORT flags" in waiting[0], waiting[0]
    assert err.index("waiting for the vehicle:") < err.index("ready; EKF origin") < err.index("ready at the start position")
    assert "Traceback" not in err

    procs[-1].stop()  # the vehicle: its .tlog is complete
    s = read_start_up(tlog)
    assert s.first_s is not None and s.fix_s is not None and s.home_s is not None and s.armed_s is not None, s
    # The start-up took READY_AFTER_S of sim time (± one heartbeat period and scheduling).
    start_up_wall_s = s.fix_s - s.first_s
    print(f"{flavour}: vehicle ready {start_up_wall_s:.2f} s (wall) after its first frame; "
          f"armed {s.armed_s - s.fix_s:.2f} s after; EKF flags {[hex(f) for f in s.ekf_flags]}")
    assert READY_AFTER_S / SPEEDUP - 1.2 <= start_up_wall_s <= READY_AFTER_S / SPEEDUP + 0.5, start_up_wall_s
    assert s.fix_types_before and max(s.fix_types_before) < 3 and s.sats_before == {0}, (s.fix_types_before, s.sats_before)
    assert s.home_s >= s.fix_s  # no home before the fix
    # Never armed, never asked to arm, before the vehicle was ready.
    assert s.arm_commands_s and min(s.arm_commands_s) >= s.home_s, (s.arm_commands_s, s.home_s)
    assert s.armed_s >= s.home_s
    if flavour == "ardupilot":
        from comms.mavlink_client import EKF_CONST_POS_MODE, EKF_READY_FLAGS

        def good(f: int) -> bool:
            return (f & EKF_READY_FLAGS) == EKF_READY_FLAGS and not f & EKF_CONST_POS_MODE

        assert s.ekf_flags and not good(s.ekf_flags[0]) and good(s.ekf_flags[-1]), s.ekf_flags
        assert any(text == "EKF3 IMU0 is using GPS" and t >= s.fix_s for t, text in s.texts), s.texts
