"""A pilot takes a drone over, and hands it back (real processes, real MAVLink and Zenoh on
127.0.0.1, vehicles and planner at x5).

A ground station (pymavlink, its own system id 255) switches the simulated ArduPilot vehicle to
LOITER mid-mission. The planner stops commanding it at once (no setpoint reaches the vehicle
after the planner saw the mode), says so, publishes the drone's position every step without a
measurement, and does not switch it back; ``fimnav handback`` gives it back: GUIDED again, the
planner plans from where the drone is and ends the mission with its end action. The take-over
latency (the vehicle in LOITER → the last setpoint it received) is printed (pytest -s).

The same in lockstep (:func:`test_lockstep_take_over_is_seen_at_the_next_tick_and_the_clock_goes_on`):
the mode change is seen with the next tick's position, and the taken-over planner still answers
every step, so the clock goes on.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.external.helpers import SwarmPeer, handback, start_vehicle, write_mission
from tests.support.proc import Proc, fimnav
from tests.support.wait import wait_for
from tests.support.zenoh import open_hub

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


@pytest.mark.slow  # about 18 s of wall time; the lockstep take-over below is in the default run
def test_a_pilot_takes_a_drone_over_and_hands_it_back(tmp_path: Path, procs: list[Proc]) -> None:
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    steps = 45
    mission = write_mission(tmp_path / "m.yaml", "takeover", [[10.0, 20.0, 8.0]], steps, "land")
    vehicle, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", str(SPEEDUP))
    peer = SwarmPeer("takeover", 1, {1: 75.0})
    gcs = None
    try:
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--speedup", str(SPEEDUP), "--zenoh-connect", peer.endpoint,
                           "--preflight-timeout", "60", "--mavlink", f"udpout:127.0.0.1:{port}", "--log", str(tmp_path / "p.jsonl")))
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


class LockstepHub:
    """The test's Zenoh router (every process a client of it, as in ``fimnav launch``), the
    lockstep clock on it (:class:`missions.launch.clock.LockstepClock`, stepped by the test) and a
    log of the planners' records."""

    def __init__(self, mission_id: str, count: int, dt_s: float) -> None:
        from comms import keys
        from missions.launch.clock import LockstepClock

        self.session, self.endpoint = open_hub("router")
        self.mission_id, self.count = mission_id, count
        self.records: list[Any] = []
        self._lock = threading.Lock()
        self._sub = self.session.declare_subscriber(keys.record(mission_id), self._on_record)
        self.clock = LockstepClock(self.session, mission_id, count, dt_s)
        self.client = ["--zenoh-config", json.dumps({"mode": "client", "listen": [], "connect": [self.endpoint]})]

    def _on_record(self, sample: Any) -> None:
        from comms.messages import decode

        _, msg = decode(bytes(sample.payload.to_bytes()), self.mission_id, self.count)
        with self._lock:
            self.records.append(msg)

    def records_of(self, uav: int) -> dict[int, Any]:
        """Drone ``uav``'s records by step."""
        with self._lock:
            return {r.step: r for r in self.records if r.sender == uav}

    def close(self) -> None:
        self.session.close()


def test_lockstep_take_over_is_seen_at_the_next_tick_and_the_clock_goes_on(tmp_path: Path, procs: list[Proc]) -> None:
    """The same take-over in lockstep (real processes: one ``fimnav vehicle --lockstep``
    hosting two vehicles, two ``fimnav plan --lockstep``; the test's process steps the clock).
    The ground station switches vehicle 1 to LOITER between steps 5 and 6 (the clock paused):
    planner 1 sees it with step 6's position (vehicle_sim heartbeats with the first tick after
    a mode change) and never commands it again until handed back: the vehicle's .tlog has no
    setpoint between the mode change and the hand-back's GUIDED. It still answers every step
    (the clock never stalls) with its telemetry position flagged taken over, planner 2 flies on
    with those records; ``fimnav handback`` gives drone 1 back, it plans from where it is and
    lands at the end."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    steps, first_taken = 24, 6
    mission = write_mission(tmp_path / "m.yaml", "takeover-ls", [[10.0, 20.0, 8.0], [30.0, 20.0, 8.0]], steps, "land")
    hub = LockstepHub("takeover-ls", 2, 1.0)
    gcs = None
    try:
        vehicle = Proc(fimnav("vehicle", "--mission", str(mission), "--sysid", "1", "--count", "2", "--mavlink", "udpin:127.0.0.1:0",
                              "--mavlink", "udpin:127.0.0.1:0", "--lockstep", "--zenoh-connect", hub.endpoint, "--zenoh-mode", "client",
                              "--tlog", str(tmp_path / "vehicle_{sysid}.tlog")))
        procs.append(vehicle)
        ready = vehicle.ready(30.0)
        ports = {v["sysid"]: int(v["mavlink"].rsplit(":", 1)[1]) for v in ready["vehicles"]}
        plans = {}
        for uav in (1, 2):
            plans[uav] = Proc(fimnav("plan", "--mission", str(mission), "--uav", str(uav), "--mavlink", f"udpout:127.0.0.1:{ports[uav]}",
                                     "--lockstep", *hub.client, "--log", str(tmp_path / f"p{uav}.jsonl"), "--step-timeout", "30"))
            procs.append(plans[uav])
        t0 = hub.clock.preflight(60.0, lambda: any(p.p.poll() is not None for p in procs))
        for k in range(first_taken):
            hub.clock.run_step(k, t0, 30.0)
        # Between two steps (planners waiting for the next tick) the ground station takes drone 1.
        gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{ports[1]}", source_system=255, source_component=190)
        gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
        gcs.mav.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, ARDUPILOT_LOITER, 0, 0, 0, 0, 0)
        ack = gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=10.0,
                             condition=f"COMMAND_ACK.command == {MAV_CMD_DO_SET_MODE}")
        assert ack is not None and ack.result == 0 and ack.get_srcSystem() == 1, ack
        hand_back_at = first_taken + 4
        for k in range(first_taken, hand_back_at):
            hub.clock.run_step(k, t0, 30.0)  # answered by the taken-over planner too
        plans[1].expect(rf"taken over at step {first_taken}: the vehicle left GUIDED \(now LOITER\)", 5.0, stream="err")
        r = handback(mission, 1, "--zenoh-connect", hub.endpoint)
        assert r.returncode == 0, r.stdout + r.stderr
        k = hand_back_at
        while "handed back at step" not in plans[1].err:  # the command reaches the planner at one of the next steps
            assert k < steps - 4, plans[1].tail()
            hub.clock.run_step(k, t0, 30.0)
            k += 1
        for k in range(k, steps):
            hub.clock.run_step(k, t0, 30.0)
        deadline = time.monotonic() + 30.0
        while any(p.p.poll() is None for p in plans.values()):  # the end tick, re-sent as the launcher does
            assert time.monotonic() < deadline, [p.tail() for p in plans.values()]
            hub.clock.end(steps, t0)
            for p in plans.values():
                with contextlib.suppress(subprocess.TimeoutExpired):
                    p.p.wait(0.5)
        records = {uav: hub.records_of(uav) for uav in (1, 2)}
    finally:
        if gcs is not None:
            gcs.close()
        hub.close()
    for p in plans.values():
        assert p.p.returncode == 0 and "Traceback" not in p.err, p.tail()
    summaries = {uav: json.loads(p.out.strip().splitlines()[-1]) for uav, p in plans.items()}
    (take,) = summaries[1]["taken_over"]
    back = take["handed_back_step"]
    assert take["step"] == first_taken and take["mode"] == "LOITER" and hand_back_at <= back < steps - 4, take
    assert summaries[1]["taken_over_steps"] == back - first_taken and summaries[1]["steps"] == steps - (back - first_taken)
    assert summaries[1]["end"]["confirmed"] and summaries[1]["end"]["action"] == "land", summaries[1]["end"]
    assert summaries[2]["steps"] == steps and not summaries[2]["taken_over"] and summaries[2]["end"]["confirmed"], summaries[2]
    rows = [json.loads(line) for line in (tmp_path / "p1.jsonl").read_text().splitlines()]
    assert [r["step"] for r in rows] == [k for k in range(steps) if not first_taken <= k < back]
    # Every step has drone 1's record; while taken over, its position (held by LOITER) without a measurement.
    assert sorted(records[1]) == list(range(steps)) and sorted(records[2]) == list(range(steps))
    held = [records[1][k] for k in range(first_taken, back)]
    assert all(r.taken_over and math.isnan(r.range_m) and not r.stale for r in held)
    assert not any(records[1][k].taken_over for k in range(steps) if not first_taken <= k < back)
    spread_m = max(math.dist(r.position_m, held[0].position_m) for r in held)
    assert spread_m < 1.0, spread_m
    # Planner 1 planned again from where LOITER held the drone.
    assert math.dist(rows[first_taken]["position_m"], records[1][back].position_m) < 1e-9 and rows[first_taken]["step"] == back
    vehicle.stop()
    # The vehicle's .tlog: no setpoint from the moment the ground station's mode change arrived
    # until the planner's own GUIDED (the hand-back).
    t_cmd, t_back, setpoints = tlog_mode_commands(tmp_path / "vehicle_1.tlog")
    during = [t for t in setpoints if t_cmd <= t < t_back]
    before = max(t for t in setpoints if t < t_cmd)
    print(f"\nlockstep take-over: last setpoint {(t_cmd - before) * 1e3:.1f} ms wall before the mode change; {len(during)} setpoints in the "
          f"{t_back - t_cmd:.2f} s until the hand-back; taken over for {back - first_taken} steps")
    assert not during, during
    assert any(t >= t_back for t in setpoints)


def tlog_mode_commands(path: Path) -> tuple[float, float, list[float]]:
    """Wall times (tlog stamps) in a vehicle's .tlog: the ground station's (system 255)
    DO_SET_MODE, the planner's next DO_SET_MODE (the hand-back) and every setpoint."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    t_gcs = t_back = math.inf
    setpoints = []
    while (m := log.recv_match()) is not None:
        if m.get_type() == "COMMAND_LONG" and int(m.command) == MAV_CMD_DO_SET_MODE:
            if m.get_srcSystem() == 255 and t_gcs == math.inf:
                t_gcs = float(m._timestamp)
            elif m.get_srcSystem() != 255 and t_gcs < math.inf and t_back == math.inf:
                t_back = float(m._timestamp)
        elif m.get_type().startswith("SET_POSITION_TARGET"):
            setpoints.append(float(m._timestamp))
    assert t_gcs < t_back < math.inf, (t_gcs, t_back)
    return t_gcs, t_back, setpoints


def test_handback_names_what_is_wrong(tmp_path: Path) -> None:
    mission = write_mission(tmp_path / "m.yaml", "takeover", [[10.0, 20.0, 8.0]], 5, "land")
    for uav, args, fragment in ((2, [], "--uav: expected a drone id in 1..1, found 2"),
                                (1, ["--results", str(tmp_path / "nowhere")], "is a fimnav launch running there?")):
        r = handback(mission, uav, *args)
        assert r.returncode == 2 and fragment in r.stderr and len(r.stderr.strip().splitlines()) == 1, r.stderr
