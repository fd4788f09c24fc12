"""A ground station takes a real ArduPilot SITL copter over from its planner, and
``fimnav handback`` gives it back (x5).

The planner flies SITL over SERIAL0; a ground station (pymavlink, system id 255) on SERIAL1
switches the copter to BRAKE (a mode that holds without stick input, which SITL has none of)
mid-mission. The planner stops its setpoints, publishes the drone's position without a
measurement, and does not switch back; after ``fimnav handback`` SITL is in GUIDED again and
the planner flies the mission to its landing. Printed (-s): the time from the GCS's mode
command to the planner's "taken over" line.

Needs FIMNAV_SITL_ARDUCOPTER and FIMNAV_SITL_ARDUCOPTER_DEFAULTS (tests/sitl/sitl.py).
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import pytest
from pymavlink import mavutil

from tests.external.helpers import SwarmPeer, handback
from tests.sitl.test_sitl_flight import _CFG, _REASON, START, home_below, sitl_with_serial1, write_mission
from tests.support.proc import Proc, fimnav
from tests.support.wait import wait_for

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

SPEEDUP = 5.0
COPTER_BRAKE, COPTER_GUIDED = 17, 4
MAV_CMD_DO_SET_MODE = 176


def test_a_ground_station_takes_sitl_over_and_fimnav_handback_returns_it(tmp_path: Path, procs: list[Proc]) -> None:
    steps = 40
    mission = write_mission(tmp_path / "m.yaml", steps=steps)
    log = tmp_path / "p.jsonl"
    peer = SwarmPeer("sitl_one", 1, {1: 75.0})
    with sitl_with_serial1(tmp_path / "sitl", SPEEDUP, home_below(mission, START), 1) as (sitl, serial1):
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", sitl.address, "--speedup", f"{SPEEDUP:g}",
                           "--log", str(log), "--preflight-timeout", "180", "--zenoh-connect", peer.endpoint))
        procs.append(plan)
        gcs = None
        try:
            wait_for(lambda: log.exists() and len(log.read_text().splitlines()) >= 8, 150.0, "eight planned steps")
            gcs = mavutil.mavlink_connection(serial1, source_system=255, source_component=190)
            assert gcs.wait_heartbeat(timeout=10) is not None
            t_cmd = time.monotonic()
            gcs.mav.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, COPTER_BRAKE, 0, 0, 0, 0, 0)
            plan.expect(r"taken over at step \d+: the vehicle left GUIDED \(now BRAKE\)", 20.0, stream="err")
            noticed_s = time.monotonic() - t_cmd
            n_planned = len(log.read_text().splitlines())
            seen = len(peer.snapshot())
            wait_for(lambda: sum(1 for r in peer.snapshot()[seen:] if r.sender == 1 and math.isnan(r.range_m) and not r.stale) >= 8,
                     30.0, "eight records without a measurement")
            assert len(log.read_text().splitlines()) == n_planned, "the planner planned while taken over"
            while gcs.recv_match(blocking=False) is not None:
                pass  # drop what queued up since the mode command: the next heartbeat is current
            hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=5)
            assert hb is not None and hb.custom_mode == COPTER_BRAKE, hb.custom_mode if hb else None  # not switched back
            r = handback(mission, 1, "--zenoh-connect", peer.endpoint)
            assert r.returncode == 0, r.stdout + r.stderr
            plan.expect(r"handed back at step \d+: in GUIDED, planning again", 30.0, stream="err")
            assert plan.wait(150.0) == 0, plan.tail()
        finally:
            if gcs is not None:
                gcs.close()
            peer.close()
    summary = json.loads(plan.out.strip().splitlines()[-1])
    (take,) = summary["taken_over"]
    assert take["mode"] == "BRAKE" and take["handed_back_step"] > take["step"], take
    assert summary["end"] == {"action": "land", "confirmed": True, "mode": "LAND", "armed": False, "landed_state": "ON_GROUND"}
    assert "Traceback" not in plan.err
    print(f"\nSITL take-over: BRAKE commanded -> planner's 'taken over' line {noticed_s:.2f} s wall; "
          f"taken over for {take['handed_back_step'] - take['step']} steps")
