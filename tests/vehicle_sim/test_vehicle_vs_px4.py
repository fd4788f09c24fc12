"""Differential check: ``fimnav vehicle --flavour px4`` against the transcript recorded on real
PX4 SITL (PX4 1.15, SIH quadrotor, tests/data/px4_sitl_1.15_transcript.json).

The same scripted ground station (tests/sitl/gcs_script_px4.py) flies the vehicle as a real
process on a loopback UDP port, as fimnav's planner flies PX4: stream requests, the readiness
wait, refused commands, the setpoint stream then OFFBOARD, arming, the climb on the stream,
setpoints in three frames, a take-off command in the air, AUTO.LAND and the disarm. Every
difference found is listed in :data:`KNOWN` (documented in docs/vehicle_sim.md, "Known
differences from PX4 SITL"); anything else, or a known difference that went away, fails. No
PX4 needed (tests/sitl/record_transcript_px4.py records the reference).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.sitl import gcs_script_px4
from tests.sitl.record_transcript_px4 import REFERENCE, vehicle_argv
from tests.support.proc import Proc

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.integration

#: ×10: the vehicle's 35 s start-up and the flight in about 15 s of wall time.
SPEEDUP = 10.0

#: Differences left (each explained in docs/vehicle_sim.md, "Known differences from PX4 SITL").
KNOWN = {
    "before_ready.arm.ack",                 # PX4 TEMPORARILY_REJECTED, vehicle FAILED
    "refusals.arm_in_land.ack",             # the same, armed in AUTO.LAND
    "before_ready.request_origin.ack",      # PX4 has an origin (and home) before it is ready
    "frames.origin_is_home_latlon",         # PX4's EKF origin is not exactly home
    "refusals.unknown_mode.ack",            # PX4 ACCEPTED (and ignores) main mode 99
    "refusals.offboard_without_stream.ack",  # PX4 accepts OFFBOARD while disarmed without a stream
    "offboard.heartbeat_in_air.base_mode",  # base_mode flags GUIDED/AUTO
    "land.heartbeat.base_mode",
    "land.heartbeat_after.base_mode",
    "land.heartbeat_after.system_status",   # PX4 UNINIT after landing, vehicle STANDBY
    "offboard.takeoff_in_air.ack",          # PX4 takes NAV_TAKEOFF in the air: AUTO.TAKEOFF
    "offboard.mode_after_takeoff_cmd",
    "set_message_interval.rates_hz[LOCAL_POSITION_NED]",  # PX4 sends it before its EKF aligns
    "setpoints[global_relative_alt].reached",  # PX4 1.15 converts GLOBAL_RELATIVE_ALT_INT wrong
    "setpoints[global_relative_alt].relative_alt_m",
    "setpoints[global_relative_alt].alt_minus_home_alt_m",
}


def test_vehicle_answers_an_offboard_ground_station_as_px4_sitl() -> None:
    ref = json.loads(REFERENCE.read_text(encoding="utf-8"))
    assert ref["vehicle"]["kind"] == "px4_sitl" and ref["heartbeat"]["autopilot"] == 12
    p = Proc(vehicle_argv(SPEEDUP), cwd=str(ROOT))
    try:
        m = p.expect(r'"mavlink": "udpin:127\.0\.0\.1:(\d+)"', timeout_s=30)
        got = gcs_script_px4.run_sequence(f"udpout:127.0.0.1:{m.group(1)}", speedup=SPEEDUP,
                                          vehicle={"kind": "fimnav_vehicle", "flavour": "px4"})
    finally:
        p.stop()
    diffs = gcs_script_px4.compare(ref, got)
    keys = {d.split(": ", 1)[0] for d in diffs}
    assert keys == KNOWN, "\n".join(diffs)
    # The points fixed after the comparison, spelled out.
    R = gcs_script_px4.mavlink
    assert got["set_message_interval"]["acks"]["193"] == R.MAV_RESULT_FAILED  # EKF_STATUS_REPORT, as PX4
    assert got["land"]["heartbeat_after"]["custom_mode"] == gcs_script_px4.custom(gcs_script_px4.OFFBOARD)  # back to OFFBOARD
    assert got["land"]["landed_states"] == [R.MAV_LANDED_STATE_LANDING, R.MAV_LANDED_STATE_ON_GROUND]
    assert got["offboard"]["mode_ack"] == R.MAV_RESULT_ACCEPTED and got["offboard"]["arm_ack"] == R.MAV_RESULT_ACCEPTED
    # PX4's own relative-altitude error, measured: twice home's height above the EKF origin.
    leg = ref["setpoints"][2]
    assert abs(leg["relative_alt_m"] - 15.0) > 1.0
