"""The planner measures its vehicle's clock (``time_boot_ms`` against the wall clock) before
take-off and refuses a vehicle that runs at another rate than its mission clock (``--speedup``):
real ``fimnav vehicle`` and ``fimnav plan`` processes on 127.0.0.1. (Against ArduPilot SITL:
tests/sitl/test_sitl_flight.py.)"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from comms.mavlink_client import ClockWatch

from tests.external.helpers import read_tlog, start_vehicle, write_mission
from tests.support.proc import Proc, fimnav

pytestmark = pytest.mark.integration


def test_clock_watch_measures_the_rate_and_ignores_delayed_messages() -> None:
    c = ClockWatch()
    assert c.rate() is None
    for i in range(40):  # 2 wall seconds at 20 Hz of a vehicle at x5, two messages held up 0.3 s
        wall = i * 0.05 + (0.3 if i in (10, 25) else 0.0)
        c.add(wall, int(i * 0.05 * 5 * 1000))
    r = c.rate()
    assert r is not None and abs(r - 5.0) < 0.1
    c.add(2.1, 50)  # a reboot: time_boot_ms back to 0.05 s
    assert c.rate() is None and len(c.samples) == 1


def test_a_vehicle_at_another_speed_up_is_refused_before_take_off(tmp_path: Path, procs: list[Proc]) -> None:
    mission = write_mission(tmp_path / "m.yaml", "clock", [[0.0, 0.0, 5.0]], 5, "land")
    vehicle, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", "1")
    planner = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", f"udpout:127.0.0.1:{port}", "--speedup", "5"))
    procs.append(planner)
    assert planner.wait(30.0) == 1, planner.tail()
    err = planner.err
    assert "the vehicle's clock runs at x1.0" in err and "mission clock at x5" in err, err[-2000:]
    assert "Arming" not in err and "airborne" not in err and "Traceback" not in err
    # Nothing was armed: no COMMAND_LONG arm (400) and no take-off (22) reached the vehicle.
    vehicle.stop()
    cmds = read_tlog(tmp_path / "v.tlog").commands
    assert 400 not in cmds and 22 not in cmds, cmds


def test_a_vehicle_at_the_same_speed_up_is_measured_and_flown(tmp_path: Path, procs: list[Proc]) -> None:
    mission = write_mission(tmp_path / "m.yaml", "clock", [[0.0, 0.0, 5.0]], 3, "hold")
    vehicle, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", "5")
    planner = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", f"udpout:127.0.0.1:{port}", "--speedup", "5"))
    procs.append(planner)
    assert planner.wait(60.0) == 0, planner.tail()
    summary = json.loads(planner.out.strip().splitlines()[-1])
    assert abs(summary["vehicle_clock_rate"] - 5.0) < 0.5, summary
    assert "vehicle clock x" in planner.err
