"""The one rule on every path a planner starts by, and the state fimnav leaves a drone in when
it stops (real processes, real MAVLink and Zenoh on 127.0.0.1; simulated ArduPilot and PX4
vehicles, docs/in-the-field.md).

- A planner started beside an airborne vehicle a ground station holds (ArduPilot LOITER, PX4
  POSCTL), in real time: it changes no mode and sends no setpoint; it publishes the drone's
  position flagged taken over until ``fimnav handback``; then it flies the mission to its end.
- A planner restarted (``--rejoin``) while its drone is taken over, in lockstep and in real time
  (``--rejoin --start-at``, as ``fimnav launch --realtime --on-failure restart`` starts it): the same.
- A real-time planner whose link returns (a UDP relay cut, then restored) after a ground station
  switched the vehicle to the pilot's hold meanwhile: the same, from the step the link returned.
- ``fimnav plan`` stopped by SIGINT or SIGTERM mid-mission: it tells the vehicle the
  mission's ``on_stop`` and the vehicle confirms it (its .tlog's last heartbeats), exit 130/143.

Checked against each vehicle's own .tlog (what reached the vehicle), not the planner's word.
"""

from __future__ import annotations

import json
import math
import os
import signal
import time
from pathlib import Path
from typing import Any

import pytest

from tests.external.helpers import SwarmPeer, UdpRelay, handback, start_vehicle, write_mission
from tests.external.test_takeover import LockstepHub
from tests.support.proc import Proc, fimnav, with_default_interrupt
from tests.support.wait import wait_for

pytestmark = pytest.mark.integration

SPEEDUP = 5.0
MAV_CMD_DO_SET_MODE = 176
#: The pilot's hold of each flavour, as a ground station sets it (DO_SET_MODE param2, param3)
#: and as the vehicle's heartbeat reports it (custom_mode).
PILOT_MODE = {"ardupilot": ((5, 0), 5, "LOITER"), "px4": ((3, 0), 3 << 16, "POSCTL")}
#: The guided mode's custom_mode of each flavour.
GUIDED = {"ardupilot": 4, "px4": 6 << 16}
#: custom_mode of the on_stop modes: (flavour, on_stop) -> (custom_mode, name).
ON_STOP_MODE = {
    ("ardupilot", "hold"): (5, "LOITER"),
    ("ardupilot", "land"): (9, "LAND"),
    ("ardupilot", "rtl"): (6, "RTL"),
    ("px4", "hold"): ((4 << 16) | (3 << 24), "AUTO.LOITER"),
    ("px4", "land"): ((4 << 16) | (6 << 24), "AUTO.LAND"),
    ("px4", "rtl"): ((4 << 16) | (5 << 24), "AUTO.RTL"),
}


def ground_station_sets(port: int, flavour: str) -> None:
    """A ground station (system 255) switches vehicle 1 to the flavour's pilot hold and sees it
    acknowledged."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    (p2, p3), _, _ = PILOT_MODE[flavour]
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
    try:
        gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
        gcs.mav.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, p2, p3, 0, 0, 0, 0)
        ack = gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=10.0, condition=f"COMMAND_ACK.command == {MAV_CMD_DO_SET_MODE}")
        assert ack is not None and ack.result == 0, ack
    finally:
        gcs.close()


def tlog_events(path: Path, sysid: int = 1) -> list[tuple[float, str, Any]]:
    """(wall time, kind, value) of a vehicle's .tlog: ``mode`` (custom_mode of each vehicle
    heartbeat of vehicle ``sysid``), ``setpoint`` (from the planner), ``set_mode`` (DO_SET_MODE,
    value: its sender's system id)."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    log = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    events: list[tuple[float, str, Any]] = []
    while (m := log.recv_match()) is not None:
        t, kind = float(m._timestamp), m.get_type()
        if kind == "HEARTBEAT" and m.get_srcComponent() == 1 and m.get_srcSystem() == sysid:
            events.append((t, "mode", (int(m.custom_mode), bool(m.base_mode & 128))))
        elif kind.startswith("SET_POSITION_TARGET"):
            events.append((t, "setpoint", None))
        elif kind == "COMMAND_LONG" and int(m.command) == MAV_CMD_DO_SET_MODE:
            events.append((t, "set_mode", m.get_srcSystem()))
    log.close()
    return events


def planner_alive(hub: LockstepHub) -> bool:
    """Whether the lockstep clock sees planner 1's liveliness token (what it heard is read first)."""
    hub.clock._drain(0.01)
    return 1 in hub.clock.alive


def lockstep_vehicle_and_planner(
    tmp_path: Path, procs: list[Proc], hub: LockstepHub, mission: Path, flavour: str, tlog: Path
) -> tuple[Proc, int, list[str]]:
    """A lockstep simulated vehicle of ``mission`` (drone 1, ``flavour``, its .tlog to ``tlog``)
    on the hub's Zenoh, started; returns it, its MAVLink port and the argv of its lockstep planner
    (log ``p1.jsonl`` in ``tmp_path``, 30 s step timeout)."""
    vehicle = Proc(fimnav("vehicle", "--mission", str(mission), "--sysid", "1", "--mavlink", "udpin:127.0.0.1:0", "--lockstep",
                          "--flavour", flavour, "--zenoh-connect", hub.endpoint, "--zenoh-mode", "client", "--tlog", str(tlog)))
    procs.append(vehicle)
    port = int(vehicle.ready(30.0)["vehicles"][0]["mavlink"].rsplit(":", 1)[1])
    argv = fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", f"udpout:127.0.0.1:{port}", "--lockstep", *hub.client,
                  "--log", str(tmp_path / "p1.jsonl"), "--step-timeout", "30")
    return vehicle, port, argv


def start_and_fly(procs: list[Proc], hub: LockstepHub, argv: list[str], steps: int) -> tuple[Proc, float]:
    """Start the lockstep planner ``argv``, let the clock's preflight see it and run its first
    ``steps`` steps; returns the planner and the clock's start (t0)."""
    planner = Proc(argv)
    procs.append(planner)
    t0 = hub.clock.preflight(60.0, lambda: any(p.p.poll() is not None for p in procs))
    for k in range(steps):
        hub.clock.run_step(k, t0, 30.0)
    return planner, t0


def kill_planner(planner: Proc, hub: LockstepHub) -> None:
    """SIGKILL planner 1 and wait until the lockstep clock sees its liveliness token gone."""
    planner.p.send_signal(signal.SIGKILL)
    planner.p.wait(10.0)
    wait_for(lambda: planner_alive(hub) is False, 20.0, "the clock to see planner 1 gone")


def end_until_exit(hub: LockstepHub, planner: Proc, steps: int, t0: float, timeout_s: float, what: str) -> None:
    """Send the end tick (re-sent, as the launcher does) until ``planner`` exits."""

    def ended() -> bool:
        hub.clock.end(steps, t0)
        return planner.p.poll() is not None

    wait_for(ended, timeout_s, what, interval_s=0.5)


def assert_untouched_until_handback(tlog: Path, flavour: str, handback_unix: float) -> None:
    """From the ground station's mode change until ``fimnav handback`` ran (UNIX s; the .tlog
    is stamped in UNIX time): no setpoint reached the vehicle, no mode change came from the
    planner and the vehicle's heartbeats stayed in the pilot's mode; it was flown again after."""
    events = tlog_events(tlog)
    t_gcs = next(t for t, kind, v in events if kind == "set_mode" and v == 255)
    t_back = handback_unix
    assert not [t for t, kind, v in events if kind == "set_mode" and v != 255 and t_gcs < t < t_back], "a mode change before the hand-back"
    # (a heartbeat the vehicle had queued before it took the command may still say GUIDED)
    t_held = next(t for t, kind, v in events if kind == "mode" and t > t_gcs and v[0] == PILOT_MODE[flavour][1])
    assert t_held < t_back
    assert not [kind for t, kind, v in events if t_gcs < t < t_back and kind == "setpoint"], "a setpoint reached the vehicle before the hand-back"
    between = [(kind, v) for t, kind, v in events if t_held <= t < t_back]
    modes = {v[0] for kind, v in between if kind == "mode"}
    assert modes == {PILOT_MODE[flavour][1]}, modes
    assert any(kind == "setpoint" for t, kind, v in events if t > t_back), "no setpoint after the hand-back"


# Default run: one flavour per path (11-15 s each, real time); the other two in the slow run.
@pytest.mark.parametrize(
    ("flavour", "path"),
    [
        ("ardupilot", "start"),
        pytest.param("px4", "start", marks=pytest.mark.slow),
        pytest.param("ardupilot", "rejoin", marks=pytest.mark.slow),
        ("px4", "rejoin"),
    ],
)
def test_a_planner_started_beside_a_pilot_held_drone_takes_nothing(tmp_path: Path, procs: list[Proc], flavour: str, path: str) -> None:
    """Real time: the vehicle boots airborne, a ground station switches it to its pilot hold,
    then ``fimnav plan`` starts on it: as a new planner (``start``) or as a restarted one
    rejoining the mission's step grid under way (``rejoin``: ``--rejoin --start-at``, as
    ``fimnav launch --realtime --on-failure restart`` starts it). The planner says it is taken
    over at its start, changes no mode, sends no setpoint, publishes the drone's position
    flagged taken over; after ``fimnav handback`` it flies the mission to the end."""
    # 8 s at x5: the hand-back command starts up within it on a loaded machine (14 steps, 2.8 s,
    # did not); a rejoining planner starts 1 s into the grid and loads its compiled kernels
    # first, so it gets 14 s (with 8 s its mission had ended before the hand-back under load 5-6).
    steps = 40 if path == "start" else 70
    mission = write_mission(tmp_path / "m.yaml", "pilotheld", [[10.0, 20.0, 8.0]], steps, "hold")
    tlog = tmp_path / "v.tlog"
    vehicle, port = start_vehicle(procs, mission, tlog, "--speedup", str(SPEEDUP), "--flavour", flavour, "--airborne")
    ground_station_sets(port, flavour)
    peer = SwarmPeer("pilotheld", 1, {1: 75.0}, mode="router")
    try:
        # A rejoining planner joins a grid whose step 0 was 1 s (5 steps at x5) ago.
        rejoin = ["--rejoin", "--start-at", f"{time.time() - 1.0:.3f}"] if path == "rejoin" else []
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--speedup", str(SPEEDUP), "--zenoh-connect", peer.endpoint,
                           "--preflight-timeout", "60", "--mavlink", f"udpout:127.0.0.1:{port}", "--log", str(tmp_path / "p.jsonl"), *rejoin))
        procs.append(plan)
        name = PILOT_MODE[flavour][2]
        plan.expect(rf"taken over at {path}: the vehicle is armed in {name}", 30.0, stream="err")
        wait_for(lambda: sum(1 for r in peer.snapshot() if r.sender == 1 and r.taken_over) >= 3, 30.0, "three taken-over records",
                 procs=[plan])
        handback_unix = time.time()
        r = handback(mission, 1, "--zenoh-connect", peer.endpoint)
        assert r.returncode == 0, r.stdout + r.stderr
        plan.expect(r"handed back at step \d+", 20.0, stream="err")
        assert plan.wait(60.0) == 0, plan.tail()
        records = peer.snapshot()
    finally:
        peer.close()
    assert "airborne in" not in plan.err and "Traceback" not in plan.err, plan.err[-2000:]
    summary = json.loads(plan.out.strip().splitlines()[-1])
    (take,) = summary["taken_over"]
    assert take["mode"] == PILOT_MODE[flavour][2] and take["at_start"] == path, take
    assert take["step"] == 0 if path == "start" else take["step"] >= 5, take
    assert take["handed_back_step"] >= 3 and summary["end"]["confirmed"], summary
    held = [r for r in records if r.sender == 1 and r.taken_over]
    assert held and all(math.isnan(r.range_m) for r in held)
    vehicle.stop()
    assert_untouched_until_handback(tlog, flavour, handback_unix)


@pytest.mark.parametrize("flavour", ["ardupilot", pytest.param("px4", marks=pytest.mark.slow)])  # PX4's lockstep restart: slow run (7 s)
def test_a_lockstep_planner_restarted_while_taken_over_takes_nothing(tmp_path: Path, procs: list[Proc], flavour: str) -> None:
    """Lockstep: the planner flies 4 steps, a ground station takes the drone (pilot hold), the
    planner sees it at step 4 and is killed (SIGKILL) at step 6; ``fimnav plan --rejoin`` on the
    same vehicle comes up taken over ("taken over at rejoin"), commands nothing (the .tlog: no
    setpoint, no mode change between the ground station's and the hand-back's), answers every
    step; after ``fimnav handback`` it flies the mission to its end."""
    steps = 16
    mission = write_mission(tmp_path / "m.yaml", "rejoin-taken", [[10.0, 20.0, 8.0]], steps, "hold")
    hub = LockstepHub("rejoin-taken", 1, 1.0)
    tlog = tmp_path / "vehicle_1.tlog"
    try:
        vehicle, port, argv = lockstep_vehicle_and_planner(tmp_path, procs, hub, mission, flavour, tlog)
        first, t0 = start_and_fly(procs, hub, argv, 4)
        ground_station_sets(port, flavour)
        for k in range(4, 6):
            hub.clock.run_step(k, t0, 30.0)
        first.expect(r"taken over at step 4", 10.0, stream="err")
        kill_planner(first, hub)
        second = Proc([*argv, "--rejoin"])
        procs.append(second)
        wait_for(lambda: planner_alive(hub), 30.0, "the replacement to join the swarm", procs=[second])
        # The replacement rejoins at the clock's current step (6), answered done, from step 7.
        hub.clock.run_step(6, t0, 30.0)
        second.expect(r"taken over at rejoin: the vehicle is armed in", 30.0, stream="err")
        second.expect(r"rejoined at step 6 \(taken over from step 7\)", 30.0, stream="err")
        for k in range(7, 9):
            hub.clock.run_step(k, t0, 30.0)
        wait_for(lambda: 8 in hub.records_of(1), 10.0, "the record of step 8")
        assert hub.records_of(1)[8].taken_over
        handback_unix = time.time()
        r = handback(mission, 1, "--zenoh-connect", hub.endpoint)
        assert r.returncode == 0, r.stdout + r.stderr
        k = 9
        while "handed back at step" not in second.err:
            assert k < steps - 2, second.tail()
            hub.clock.run_step(k, t0, 30.0)
            k += 1
        for j in range(k, steps):
            hub.clock.run_step(j, t0, 30.0)
        end_until_exit(hub, second, steps, t0, 30.0, "the planner's end")
        records = hub.records_of(1)
    finally:
        hub.close()
    assert second.p.returncode == 0 and "Traceback" not in second.err, second.tail()
    summary = json.loads(second.out.strip().splitlines()[-1])
    (take,) = summary["taken_over"]
    assert take["at_start"] == "rejoin" and take["step"] == 7 and take["mode"] == PILOT_MODE[flavour][2], take
    assert all(records[j].taken_over for j in range(7, take["handed_back_step"])), "a step without its taken-over record"
    vehicle.stop()
    assert_untouched_until_handback(tlog, flavour, handback_unix)


def test_a_lockstep_planner_restarted_after_the_last_step_gives_its_drone_the_mission_end(tmp_path: Path, procs: list[Proc]) -> None:
    """Lockstep: the planner flies 4 steps and is killed (SIGKILL); the swarm's clock runs the
    mission to its end without it. ``fimnav plan --rejoin`` on the same vehicle (as ``fimnav
    launch --on-failure restart`` starts it, late on a loaded machine) has nothing left to fly:
    it gives the vehicle the mission's end action, as every other drone gets it (land: the
    vehicle's .tlog ends in LAND, commanded by the planner), and exits 0 with no step flown,
    not with an error a launcher would restart again and that would leave the drone holding
    where its first planner died."""
    steps = 8
    mission = write_mission(tmp_path / "m.yaml", "rejoin-late", [[10.0, 20.0, 8.0]], steps, "land")
    hub = LockstepHub("rejoin-late", 1, 1.0)
    tlog = tmp_path / "vehicle_1.tlog"
    try:
        vehicle, _, argv = lockstep_vehicle_and_planner(tmp_path, procs, hub, mission, "ardupilot", tlog)
        first, t0 = start_and_fly(procs, hub, argv, 4)
        kill_planner(first, hub)
        for k in range(4, steps):
            hub.clock.run_step(k, t0, 30.0)
        second = Proc([*argv, "--rejoin"])
        procs.append(second)
        end_until_exit(hub, second, steps, t0, 60.0, "the replacement's end")
    finally:
        hub.close()
    assert second.p.returncode == 0 and "Traceback" not in second.err, second.tail()
    assert f"rejoined at step {steps} of a {steps}-step mission: nothing left to fly" in second.err, second.err[-2000:]
    summary = json.loads(second.out.strip().splitlines()[-1])
    assert summary["steps"] == 0
    assert summary["end"] == {"action": "land", "confirmed": True, "mode": "LAND"}, summary["end"]
    vehicle.stop()
    events = tlog_events(tlog)
    assert [v for t, kind, v in events if kind == "set_mode"][-1] == 1  # the command came from the planner
    modes = [v for t, kind, v in events if kind == "mode"]
    assert modes[-1][0] == ON_STOP_MODE[("ardupilot", "land")][0], modes[-3:]


@pytest.mark.slow  # 12-18 s each (the 2 s loss threshold, the hand-back's start-up, the mission's end); default run: tests/node/test_link_return_node.py, tests/external/test_setpoint_race.py
@pytest.mark.parametrize("flavour", ["ardupilot", "px4"])
def test_a_vehicle_found_in_a_pilots_mode_when_the_link_returns_is_left_to_the_pilot(tmp_path: Path, procs: list[Proc], flavour: str) -> None:
    """Real time through a UDP relay: the planner flies; the relay is cut (a radio link gone
    both ways); while it is cut a ground station connected to the vehicle directly switches it
    to the pilot's hold (the PX4 vehicle had left OFFBOARD for its offboard-loss hold already);
    the relay is restored. The planner cannot tell the pilot's mode from a failsafe's: it
    takes the drone as taken over from the step the link returned ("after link loss"),
    changes no mode and sends no setpoint (the vehicle's .tlog) until ``fimnav handback``;
    then it flies the mission to its end."""
    steps = 50  # ~10 steps flown, 10 lost, 10-20 taken over (the hand-back's start-up under load), the rest to spare
    mission = write_mission(tmp_path / "m.yaml", "linkback", [[10.0, 20.0, 8.0]], steps, "hold")
    tlog = tmp_path / "v.tlog"
    # (the simulated ArduPilot boots airborne in GUIDED, which the planner flies as it is; the
    # PX4 one boots in its hold, so it is taken off by the planner)
    vehicle, port = start_vehicle(procs, mission, tlog, "--speedup", str(SPEEDUP), "--flavour", flavour,
                                  *(["--airborne"] if flavour == "ardupilot" else []))
    relay = UdpRelay(port)
    peer = SwarmPeer("linkback", 1, {1: 75.0}, mode="router")
    name = PILOT_MODE[flavour][2]
    try:
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--speedup", str(SPEEDUP), "--zenoh-connect", peer.endpoint,
                           "--preflight-timeout", "60", "--mavlink", f"udpout:127.0.0.1:{relay.port}", "--log", str(tmp_path / "p.jsonl")))
        procs.append(plan)
        plan.expect(r"ready at the start position", 60.0, stream="err")
        wait_for(lambda: sum(1 for r in peer.snapshot() if r.sender == 1) >= 3, 20.0, "three records of the planner", procs=[plan],
                 interval_s=0.02)
        relay.cut.set()
        plan.expect(r"vehicle link lost", 10.0, stream="err")
        ground_station_sets(port, flavour)  # directly to the vehicle, while the planner's link is cut
        relay.restore()
        taken = int(plan.expect(rf"taken over at step (\d+) after the link loss: the vehicle is armed in {name}", 20.0, stream="err").group(1))
        wait_for(lambda: sum(1 for r in peer.snapshot() if r.sender == 1 and r.taken_over and r.step > taken) >= 2, 20.0,
                 "two more records flagged taken over", procs=[plan], interval_s=0.02)
        handback_unix = time.time()
        r = handback(mission, 1, "--zenoh-connect", peer.endpoint)
        assert r.returncode == 0, r.stdout + r.stderr
        back = int(plan.expect(r"handed back at step (\d+)", 20.0, stream="err").group(1))
        assert plan.wait(60.0) == 0, plan.tail()
    finally:
        peer.close()
        relay.close()
    assert "Traceback" not in plan.err and "switching back" not in plan.err, plan.err[-2000:]
    summary = json.loads(plan.out.strip().splitlines()[-1])
    assert summary["taken_over"] == [{"step": taken, "mode": name, "reason": "after link loss", "handed_back_step": back}], summary
    assert len(summary["link_losses"]) == 1 and summary["end"]["confirmed"], summary
    print(f"\n{flavour}: taken over at step {taken} after the link loss, handed back at step {back} of {steps}")
    vehicle.stop()
    assert_untouched_until_handback(tlog, flavour, handback_unix)


@pytest.mark.parametrize(
    ("flavour", "signame", "on_stop"),
    [
        ("ardupilot", "SIGINT", "hold"),
        ("px4", "SIGTERM", "hold"),
        pytest.param("ardupilot", "SIGTERM", "land", marks=pytest.mark.slow),
        pytest.param("px4", "SIGINT", "rtl", marks=pytest.mark.slow),
    ],
)
def test_fimnav_plan_stopped_by_a_signal_leaves_the_vehicle_in_on_stop(
    tmp_path: Path, procs: list[Proc], flavour: str, signame: str, on_stop: str
) -> None:
    """Real time: ``fimnav plan`` flies; SIGINT (Ctrl-C) or SIGTERM mid-mission; it tells the
    vehicle the mission's on_stop and waits for it: the vehicle's .tlog ends in that mode,
    armed, and no setpoint follows the command; the exit status is 128 + the signal."""
    mission = write_mission(tmp_path / "m.yaml", "onstop", [[10.0, 20.0, 8.0]], 200, "hold", on_stop=on_stop)
    tlog = tmp_path / "v.tlog"
    vehicle, port = start_vehicle(procs, mission, tlog, "--speedup", str(SPEEDUP), "--flavour", flavour)
    peer = SwarmPeer("onstop", 1, {1: 75.0})
    try:
        plan = Proc(with_default_interrupt(fimnav("plan", "--mission", str(mission), "--uav", "1", "--speedup", str(SPEEDUP),
                                                  "--zenoh-connect", peer.endpoint, "--preflight-timeout", "60",
                                                  "--mavlink", f"udpout:127.0.0.1:{port}", "--log", str(tmp_path / "p.jsonl"))))
        procs.append(plan)
        log = tmp_path / "p.jsonl"
        wait_for(lambda: log.exists() and len(log.read_text().splitlines()) >= 4, 60.0, "four planned steps", procs=[plan])
        sig = getattr(signal, signame)
        plan.p.send_signal(sig)
        assert plan.wait(15.0) == 128 + sig, plan.tail()
    finally:
        peer.close()
    code, name = ON_STOP_MODE[(flavour, on_stop)]
    assert f"stopping ({signame}): the vehicle is in {name} (on_stop {on_stop}), confirmed" in plan.err, plan.err[-2000:]
    assert "Traceback" not in plan.err
    vehicle.stop()
    events = tlog_events(tlog)
    t_cmd = max(t for t, kind, v in events if kind == "set_mode" and v == 1)
    after = [(kind, v) for t, kind, v in events if t > t_cmd]
    modes = [v for kind, v in after if kind == "mode"]
    assert modes and modes[-1][0] == code, (modes[-3:], code)
    if on_stop == "hold":
        assert modes[-1][1], "the vehicle disarmed"
    # The stream ended when the vehicle confirmed (its first heartbeat in the mode reached the
    # planner at once on loopback; 0.5 s allows for a loaded machine).
    t_left = min(t for t, kind, v in events if kind == "mode" and t > t_cmd and v[0] == code)
    late = [t - t_left for t, kind, v in events if kind == "setpoint" and t > t_left + 0.5]
    assert not late, f"setpoints {late} s after the vehicle confirmed"
