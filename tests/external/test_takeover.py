"""A pilot takes a drone over, and hands it back (real processes, real MAVLink and Zenoh on
127.0.0.1, vehicles and planner at x5).

A ground station (pymavlink, its own system id 255) switches the simulated ArduPilot vehicle to
LOITER mid-mission. The planner stops commanding it at once (no setpoint reaches the vehicle
after the planner saw the mode), says so, publishes the drone's position every step without a
measurement, and does not switch it back; ``fimnav handback`` gives it back: GUIDED again, the
planner plans from where the drone is and ends the mission with its end action. The take-over
latency (the vehicle in LOITER → the last setpoint it received) is printed (pytest -s).
"""

from __future__ import annotations

import json
import math
import os
from pathlib import Path

import pytest

from .helpers import Proc, SwarmPeer, handback, start_vehicle, write_mission
from tests.distributed.test_launch import wait_for

pytestmark = pytest.mark.integration

SPEEDUP = 5.0
ARDUPILOT_LOITER = 5
MAV_CMD_DO_SET_MODE = 176


def tlog_times(path: Path) -> tuple[list[tuple[float, int]], list[float]]:
    """(wall time, custom mode) of every vehicle heartbeat and the wall times of every setpoint."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    modes, setpoints = [], []
    while (m := log.recv_match()) is not None:
        if m.get_type() == "HEARTBEAT" and m.get_srcComponent() == 1 and m.get_srcSystem() == 1:
            modes.append((float(m._timestamp), int(m.custom_mode)))
        elif m.get_type().startswith("SET_POSITION_TARGET"):
            setpoints.append(float(m._timestamp))
    return modes, setpoints


def test_a_pilot_takes_a_drone_over_and_hands_it_back(tmp_path: Path, procs: list[Proc]) -> None:
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    steps = 45
    mission = write_mission(tmp_path / "m.yaml", "takeover", [[10.0, 20.0, 8.0]], steps, "land")
    vehicle, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", str(SPEEDUP))
    peer = SwarmPeer("takeover", 1, {1: 75.0})
    gcs = None
    try:
        plan = Proc(["plan", "--mission", str(mission), "--uav", "1", "--speedup", str(SPEEDUP), "--zenoh-connect", peer.endpoint,
                     "--preflight-timeout", "60", "--mavlink", f"udpout:127.0.0.1:{port}", "--log", str(tmp_path / "p.jsonl")])
        procs.append(plan)
        log = tmp_path / "p.jsonl"
        wait_for(lambda: log.exists() and len(log.read_text().splitlines()) >= 10, 60.0, "ten planned steps")
        # The ground station switches the drone to LOITER.
        gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
        gcs.mav.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, ARDUPILOT_LOITER, 0, 0, 0, 0, 0)
        plan.expect(r"taken over at step (\d+): the vehicle left GUIDED \(now LOITER\)", 20.0, stream="err")
        n_planned = len(log.read_text().splitlines())
        # While taken over: records with the drone's position and no measurement, no planning.
        wait_for(lambda: sum(1 for r in peer.snapshot() if r.sender == 1 and math.isnan(r.range_m) and not r.stale) >= 10,
                 20.0, "ten records without a measurement")
        assert len(log.read_text().splitlines()) == n_planned, "the planner planned while taken over"
        assert "handed back" not in plan.err and "switching back" not in plan.err
        # A malformed control message is named and ignored.
        from comms import keys

        peer.session.put(keys.control("takeover", 1), b"{not json")
        peer.session.put(keys.control("takeover", 1), b'{"command": "land"}')
        plan.expect(r"control message is not JSON, ignored", 10.0, stream="err")
        plan.expect(r"control message without a known command", 10.0, stream="err")
        assert "handed back" not in plan.err
        # Handed back by the documented command.
        r = handback(mission, 1, "--zenoh-connect", peer.endpoint)
        assert r.returncode == 0, r.stdout + r.stderr
        plan.expect(r"handed back at step \d+: in GUIDED, planning again", 20.0, stream="err")
        assert plan.wait(90.0) == 0, plan.tail()
    finally:
        if gcs is not None:
            gcs.close()
        peer.close()
    summary = json.loads(plan.out.strip().splitlines()[-1])
    (take,) = summary["taken_over"]
    assert take["mode"] == "LOITER" and take["handed_back_step"] > take["step"], take
    assert summary["end"]["confirmed"] and summary["end"]["action"] == "land", summary["end"]
    assert "Traceback" not in plan.err
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    assert rows[-1]["step"] == steps - 1 and all(r["step"] < take["step"] or r["step"] >= take["handed_back_step"] for r in rows)
    vehicle.stop()
    modes, setpoints = tlog_times(tmp_path / "v.tlog")
    t_loiter = next(t for t, m in modes if m == ARDUPILOT_LOITER)
    t_back = next(t for t, m in modes if t > t_loiter and m != ARDUPILOT_LOITER)
    during = [t for t in setpoints if t_loiter <= t < t_back]
    latency = (max(during) - t_loiter) if during else 0.0
    print(f"\ntake-over: vehicle in LOITER -> last setpoint {latency:.3f} s wall ({latency * SPEEDUP:.2f} s mission time); "
          f"{len(during)} setpoints after the mode change; taken over for {take['handed_back_step'] - take['step']} steps")
    # The planner sees the mode in the next heartbeat (1 Hz wall) and stops at once.
    assert latency < 1.5, latency
    assert not [t for t in during if t > t_loiter + 1.5]


def test_handback_names_what_is_wrong(tmp_path: Path) -> None:
    mission = write_mission(tmp_path / "m.yaml", "takeover", [[10.0, 20.0, 8.0]], 5, "land")
    for uav, args, fragment in ((2, [], "--uav: expected a drone id in 1..1, found 2"),
                                (1, ["--results", str(tmp_path / "nowhere")], "is a fimnav launch running there?")):
        r = handback(mission, uav, *args)
        assert r.returncode == 2 and fragment in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
