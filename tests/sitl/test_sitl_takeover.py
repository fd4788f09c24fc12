"""A ground station takes a real ArduPilot SITL copter over from its planner, and
``fimnav handback`` gives it back (x5); a planner restarted meanwhile leaves it alone; Ctrl-C
of a real-time launch leaves it in LOITER (the mission's on_stop).

The planner flies SITL over SERIAL0; a ground station (pymavlink, system id 255) on SERIAL1
switches the copter to BRAKE (a mode that holds without stick input, which SITL has none of)
mid-mission. The planner stops its setpoints, publishes the drone's position without a
measurement, and does not switch back; after ``fimnav handback`` SITL is in GUIDED again and
the planner flies the mission to its landing. Printed (-s): the time from the GCS's mode
command to the planner's "taken over" line.

Needs FIMNAV_SITL_ARDUCOPTER and FIMNAV_SITL_ARDUCOPTER_DEFAULTS (tests/sitl/sitl.py).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import signal
import socket
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import yaml
from pymavlink import mavutil

from tests.external.helpers import SwarmPeer, handback
from tests.sitl.test_sitl_flight import _CFG, _REASON, START, home_below, sitl_with_serial1, write_mission
from tests.support.launch import Launch
from tests.support.proc import Proc, fimnav, with_default_interrupt
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


COPTER_LOITER = 5


@contextlib.contextmanager
def rc_sticks_centred(sitl: Any) -> Iterator[None]:
    """A pilot's transmitter at rest, sent 10 times a second while the block runs (as a receiver
    does) to SITL's RC input (its ``--rc-in-port``, 8 PWM values): SITL's own start values
    (AP_RCProtocol_UDP: the mode switch, channel 5, at 1800 µs; 6, 7 at 1000; 8 at 1800) with
    the throttle centred (1500 µs instead of 1000). Without it LOITER, which follows the pilot's
    climb-rate stick, descends at full rate."""
    port = int(sitl.argv[sitl.argv.index("--rc-in-port") + 1])
    packet = struct.pack("<8H", 1500, 1500, 1500, 1500, 1800, 1000, 1000, 1800)
    stop = threading.Event()

    def send() -> None:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            while True:
                s.sendto(packet, ("127.0.0.1", port))
                if stop.wait(0.1):
                    return

    thread = threading.Thread(target=send, daemon=True)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(2.0)


def heartbeats(gcs: Any, seconds: float) -> list[tuple[int, bool]]:
    """(custom_mode, armed) of the copter's heartbeats over ``seconds`` of wall time."""
    while gcs.recv_match(blocking=False) is not None:
        pass  # what queued up before: the next heartbeats are current
    seen = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        hb = gcs.recv_match(type="HEARTBEAT", blocking=True, timeout=max(0.1, end - time.monotonic()))
        if hb is not None and hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1:
            seen.append((int(hb.custom_mode), bool(hb.base_mode & 128)))
    return seen


def test_a_restarted_planner_leaves_a_braking_copter_alone(tmp_path: Path, procs: list[Proc]) -> None:
    """A ground station (SERIAL1) switches the copter to BRAKE mid-mission; the planner is killed
    (SIGKILL) and started again on the same SERIAL0: it comes up taken over ("taken over at
    start: the vehicle is armed in BRAKE"), changes nothing (the copter's heartbeats stay BRAKE
    for 5 s of wall time), and after ``fimnav handback`` flies the mission and lands."""
    steps = 40
    mission = write_mission(tmp_path / "m.yaml", steps=steps)
    log = tmp_path / "p.jsonl"
    peer = SwarmPeer("sitl_one", 1, {1: 75.0}, mode="router")
    with sitl_with_serial1(tmp_path / "sitl", SPEEDUP, home_below(mission, START), 1) as (sitl, serial1):
        argv = fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", sitl.address, "--speedup", f"{SPEEDUP:g}",
                      "--log", str(log), "--preflight-timeout", "180", "--zenoh-connect", peer.endpoint)
        first = Proc(argv)
        procs.append(first)
        gcs = None
        try:
            wait_for(lambda: log.exists() and len(log.read_text().splitlines()) >= 6, 150.0, "six planned steps", procs=[first])
            gcs = mavutil.mavlink_connection(serial1, source_system=255, source_component=190)
            assert gcs.wait_heartbeat(timeout=10) is not None
            gcs.mav.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, COPTER_BRAKE, 0, 0, 0, 0, 0)
            first.expect(r"taken over at step \d+: the vehicle left GUIDED \(now BRAKE\)", 20.0, stream="err")
            first.p.kill()
            first.p.wait(10.0)
            second = Proc(argv)
            procs.append(second)
            second.expect(r"taken over at start: the vehicle is armed in BRAKE, not GUIDED", 60.0, stream="err")
            seen = len(peer.snapshot())
            wait_for(lambda: sum(1 for r in peer.snapshot()[seen:] if r.sender == 1 and r.taken_over) >= 5, 30.0,
                     "five taken-over records of the restarted planner", procs=[second])
            held = heartbeats(gcs, 5.0)
            assert held and set(held) == {(COPTER_BRAKE, True)}, held
            t_back = time.monotonic()
            r = handback(mission, 1, "--zenoh-connect", peer.endpoint)
            assert r.returncode == 0, r.stdout + r.stderr
            second.expect(r"handed back at step \d+: in GUIDED, planning again", 30.0, stream="err")
            assert second.wait(150.0) == 0, second.tail()
        finally:
            if gcs is not None:
                gcs.close()
            peer.close()
    summary = json.loads(second.out.strip().splitlines()[-1])
    (take,) = summary["taken_over"]
    assert take["mode"] == "BRAKE" and take["at_start"] == "start" and take["handed_back_step"] > take["step"], take
    assert summary["end"]["confirmed"] and summary["end"]["landed_state"] == "ON_GROUND", summary["end"]
    assert "Traceback" not in second.err and "airborne in GUIDED" not in second.err
    print(f"\nSITL restart while taken over: BRAKE for {len(held)} heartbeats over 5 s after the restart; "
          f"handed back {time.monotonic() - t_back:.1f} s before landing; taken over for {take['handed_back_step'] - take['step']} steps")


def test_ctrl_c_of_a_realtime_launch_leaves_the_copter_in_loiter(tmp_path: Path, launches: list[Launch]) -> None:
    """``fimnav launch --realtime`` flies the SITL copter (its simulated payload on SERIAL1);
    Ctrl-C after a few steps: exit 130, the planner's log says the copter confirmed LOITER
    (on_stop hold), and a ground station connected afterwards sees it in LOITER, armed, at
    the same height, for 10 s of wall time (50 s of the copter's time at x5)."""
    steps = 200
    mission = write_mission(tmp_path / "m.yaml", steps=steps)
    with sitl_with_serial1(tmp_path / "sitl", SPEEDUP, home_below(mission, START), 1) as (sitl, serial1):
        spec = yaml.safe_load(mission.read_text())
        spec["vehicles"] = {"overrides": [{"connection": sitl.address, "payload_connection": serial1}]}
        mission.write_text(yaml.safe_dump(spec))
        out = tmp_path / "run"
        run = Launch.command(with_default_interrupt(fimnav("launch", str(mission), "--out", str(out), "--realtime", "--speedup",
                                                           f"{SPEEDUP:g}", "--start-delay", "60")), out, tmp_path)
        launches.append(run)
        steps_log = out / "logs" / "planner_1.jsonl"
        wait_for(lambda: steps_log.exists() and len(steps_log.read_text().splitlines()) >= 8, 240.0, "eight steps")
        # In the air the pilot's throttle stick rests centred (it was low for the arming).
        with rc_sticks_centred(sitl):
            os.killpg(run.proc.pid, signal.SIGINT)
            code, _, stderr = run.wait(60.0)
            assert code == 130, stderr[-3000:]
            text = (out / "logs" / "planner_1.log").read_text()
            line = next(x for x in text.splitlines() if "stopping (SIGTERM)" in x)
            assert "the vehicle is in LOITER (on_stop hold), confirmed" in line, line
            gcs = mavutil.mavlink_connection(serial1, source_system=255, source_component=190)
            try:
                assert gcs.wait_heartbeat(timeout=20) is not None
                pos0 = gcs.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=10)
                held = heartbeats(gcs, 10.0)
                pos1 = gcs.recv_match(type="GLOBAL_POSITION_INT", blocking=True, timeout=10)
            finally:
                gcs.close()
    assert held and set(held) == {(COPTER_LOITER, True)}, held
    # Still in the air where it stopped (the mission's start height, 8 m), not descending (mm).
    assert pos0 is not None and pos1 is not None and pos0.relative_alt > 5000 and abs(pos1.relative_alt - pos0.relative_alt) < 1000, (pos0, pos1)
    print(f"\nSITL Ctrl-C: {line.split('stopping ')[1]}; then LOITER, armed, for {len(held)} heartbeats over 10 s; "
          f"height above home {pos0.relative_alt / 1000:.1f} -> {pos1.relative_alt / 1000:.1f} m")
