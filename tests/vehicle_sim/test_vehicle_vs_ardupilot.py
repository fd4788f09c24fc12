"""Differential check: ``fimnav vehicle`` (ArduPilot flavour) against the transcript recorded on
real ArduPilot SITL (ArduCopter V4.5.5, tests/data/ardupilot_sitl_4.5.5_transcript.json).

The same scripted ground station (tests/sitl/gcs_script.py) flies the vehicle as a real process
on a loopback TCP port: stream requests, the readiness wait, GUIDED before and after ready,
refused commands, arming, take-off, global and local setpoints, LAND and the disarm on
landing. Every point where a planner or a ground station could tell the two apart must match
(``gcs_script.compare``); the differences left are listed in docs/vehicle_sim.md, "Known
differences from ArduPilot SITL". No SITL needed (tests/sitl/test_sitl_transcript.py checks the
recorded transcript against SITL itself).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.sitl import gcs_script
from tests.sitl.record_transcript import REFERENCE, vehicle_argv
from tests.support.proc import Proc

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.integration

#: ×10: SITL's 30-40 s start-up (here 30 s of sim time) and the flight in about 11 s of wall time.
SPEEDUP = 10.0


def test_vehicle_answers_the_ground_station_as_ardupilot_sitl() -> None:
    ref = json.loads(REFERENCE.read_text(encoding="utf-8"))
    assert ref["vehicle"]["kind"] == "ardupilot_sitl" and ref["vehicle"]["version"] == "ArduCopter V4.5.5"
    p = Proc(vehicle_argv(SPEEDUP), cwd=str(ROOT))
    try:
        m = p.expect(r'"mavlink": "tcpin:127\.0\.0\.1:(\d+)"', timeout_s=30)
        got = gcs_script.run_sequence(f"tcp:127.0.0.1:{m.group(1)}", speedup=SPEEDUP,
                                      vehicle={"kind": "fimnav_vehicle", "flavour": "ardupilot"})
    finally:
        p.stop()
    assert gcs_script.compare(ref, got) == []
    # The points the fixes were about, spelled out (the comparison above covers them too).
    R = gcs_script.mavlink
    assert got["heartbeat"]["base_mode"] == 81 and got["arm"]["heartbeat"]["base_mode"] == 217
    assert got["arm"]["heartbeat"]["system_status"] == R.MAV_STATE_STANDBY  # armed on the ground
    assert got["takeoff"]["heartbeat_in_air"]["system_status"] == R.MAV_STATE_ACTIVE
    assert got["land"]["heartbeat"]["base_mode"] == 209  # LAND: no GUIDED_ENABLED flag
    assert got["before_ready"]["guided"]["ack"] == R.MAV_RESULT_ACCEPTED  # disarmed: no mode checks
    assert got["refusals"]["takeoff_disarmed"] == {"ack": R.MAV_RESULT_FAILED, "texts": []}
    assert got["refusals"]["unknown_mode"] == {"ack": R.MAV_RESULT_FAILED, "texts": ["No such mode 99"]}
    assert got["refusals"]["arm_in_land"]["texts"] == ["Arm: LAND mode not armable"]
    assert got["takeoff"]["landed_states"] == [R.MAV_LANDED_STATE_TAKEOFF, R.MAV_LANDED_STATE_IN_AIR]
    assert got["land"]["landed_states"] == [R.MAV_LANDED_STATE_LANDING, R.MAV_LANDED_STATE_ON_GROUND]
    assert got["land"]["texts"] == ["Disarming motors"]
    assert got["land"]["heartbeat_after"]["custom_mode"] == gcs_script.LAND
