"""Real-time flights: real ``fimnav plan`` processes against real ``fimnav vehicle`` processes
(ArduPilot and PX4 flavours) on 127.0.0.1, with the vehicles' clock sped up.

What is checked comes from both sides: the planner's summary and log (what it detected and
confirmed) and the vehicle's .tlog (what the autopilot actually received and did: setpoint
message types, frames and masks, modes, STATUSTEXTs such as the GUIDED velocity timeout or
the PX4 offboard-loss failsafe, landed state).
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.external.helpers import SwarmPeer, UdpRelay, handback, read_tlog, start_vehicle, write_mission
from tests.support.proc import Proc, fimnav
from tests.support.wait import wait_for

pytestmark = pytest.mark.integration

#: Sim seconds per wall second for vehicles and planners: dt = 1 s is 0.2 s of wall time, the
#: setpoint stream (5 Hz of mission time) is 25 Hz; ArduPilot's 3 s guided timeout is 0.6 s
#: and PX4's 1 s offboard-loss timeout 0.2 s of wall time, so a planner that stalls shows.
SPEEDUP = 5.0
ARDUPILOT_GUIDED, ARDUPILOT_RTL, ARDUPILOT_LAND = 4, 6, 9
PX4_OFFBOARD, PX4_LOITER, PX4_LAND = 6 << 16, (4 << 16) | (3 << 24), (4 << 16) | (6 << 24)
GLOBAL_RELATIVE_ALT_INT = 6
MASK_POS_VEL, MASK_POS = 3520, 3576
MAV_CMD_SET_MESSAGE_INTERVAL, MAV_CMD_NAV_TAKEOFF = 511, 22


def plan_argv(mission: Path, uav: int, peer: SwarmPeer, *extra: str, speedup: float = SPEEDUP) -> list[str]:
    return fimnav("plan", "--mission", str(mission), "--uav", str(uav), "--speedup", str(speedup),
                  "--zenoh-connect", peer.endpoint, "--preflight-timeout", "60", *extra)


def summary_of(p: Proc) -> dict:
    return json.loads(p.out.strip().splitlines()[-1])


def stop_and_read(vehicle: Proc, tlog: Path):  # noqa: ANN201
    vehicle.stop()
    return read_tlog(tlog)


@pytest.mark.slow  # the default run flies planners in real time in test_readiness, test_clock_rate, test_payload and below
def test_mixed_fleet_ardupilot_and_px4_full_sequence(tmp_path: Path, procs: list[Proc]) -> None:
    """Drone 1 on an ArduPilot-flavoured vehicle, drone 2 on a PX4-flavoured one, each with its
    own connection string in the mission and its flavour detected from HEARTBEAT.autopilot:
    streams, readiness, mode, arm, take-off, global setpoints re-sent often enough that no
    timeout fires, peers' records shared in real time, landing confirmed on both sides."""
    steps = 15
    # Half the usual speed-up: the peers' deadline (dt/2) is then 0.2 s of wall time, which a
    # loaded 2-core machine still meets for most steps.
    speedup = SPEEDUP / 2
    base = write_mission(tmp_path / "base.yaml", "mixed", [[10.0, 20.0, 8.0], [16.0, 20.0, 9.0]], steps, "land")
    v1, port1 = start_vehicle(procs, base, tmp_path / "v1.tlog", "--speedup", str(speedup), sysid=1)
    v2, port2 = start_vehicle(procs, base, tmp_path / "v2.tlog", "--speedup", str(speedup), "--flavour", "px4", sysid=2)
    mission = yaml.safe_load(base.read_text())
    mission["vehicles"] = {"overrides": [{"connection": f"udpout:127.0.0.1:{port1}"}, {"connection": f"udpout:127.0.0.1:{port2}", "flavour": "auto"}]}
    flown = tmp_path / "mission.yaml"
    flown.write_text(yaml.safe_dump(mission))
    peer = SwarmPeer("mixed", 2, {1: 70.0, 2: 72.0})
    try:
        planners = [Proc([*plan_argv(flown, i, peer, speedup=speedup), "--log", str(tmp_path / f"p{i}.jsonl")]) for i in (1, 2)]
        procs.extend(planners)
        for p in planners:
            assert p.wait(90.0) == 0, p.tail()
        records = peer.snapshot()
    finally:
        peer.close()
    s1, s2 = (summary_of(p) for p in planners)
    assert (s1["flavour"], s2["flavour"]) == ("ardupilot", "px4")
    assert "HEARTBEAT.autopilot = 3" in planners[0].err and "HEARTBEAT.autopilot = 12" in planners[1].err
    for s in (s1, s2):
        assert s["frame"] == "global" and s["steps"] == steps and s["link_losses"] == []
        assert s["end"]["confirmed"] and s["end"]["armed"] is False and s["end"]["landed_state"] == "ON_GROUND"
    assert s1["end"]["mode"] == "LAND" and s2["end"]["mode"] == "OFFBOARD"  # PX4 returns to OFFBOARD on disarming

    # The payload's measurements (published on their own schedule) went into the records.
    for uav, rng in ((1, 70.0), (2, 72.0)):
        mine = [r for r in records if r.sender == uav]
        assert len(mine) == steps and all(r.range_m == rng and not r.stale for r in mine)
    # The peers' records of step k arrived before the step's deadline (not a barrier).
    for i, other in ((1, 1), (2, 0)):
        log = [json.loads(line) for line in (tmp_path / f"p{i}.jsonl").read_text().splitlines()]
        on_time = sum(e["saved_steps"][other] == e["step"] for e in log)
        print(f"planner {i}: the peer's record of the step arrived before the deadline in {on_time}/{steps} steps")
        assert on_time >= 0.6 * steps, [(e["step"], e["saved_steps"], e["timing"]) for e in log]
        # the planner moved: the planned positions change from step to step
        assert len({tuple(e["next_position_m"]) for e in log}) == steps

    t1 = stop_and_read(v1, tmp_path / "v1.tlog")
    t2 = stop_and_read(v2, tmp_path / "v2.tlog")
    for t, frame in ((t1, GLOBAL_RELATIVE_ALT_INT), (t2, 5)):
        # Only global setpoints, position + velocity or position only: relative altitude to
        # ArduPilot; to PX4 as AMSL (home + z, MAV_FRAME_GLOBAL_INT = 5), which PX4 converts right.
        assert set(t.setpoints) <= {("SET_POSITION_TARGET_GLOBAL_INT", frame, m) for m in (MASK_POS_VEL, MASK_POS)}, t.setpoints
        assert t.setpoints.get(("SET_POSITION_TARGET_GLOBAL_INT", frame, MASK_POS_VEL), 0) >= steps
        assert t.commands.get(MAV_CMD_SET_MESSAGE_INTERVAL, 0) >= 5
        assert not [x for x in t.texts if "timeout" in x.lower() or "failsafe" in x.lower() or "fence" in x.lower()], t.texts
        assert t.landed_state == 1  # MAV_LANDED_STATE_ON_GROUND
    # The stream: at least 4 Hz of mission time between the first and the last setpoint
    # (median gap; the largest is printed: a loaded machine can stretch single gaps).
    for name, t in (("ardupilot", t1), ("px4", t2)):
        gaps = np.diff(t.setpoint_times_s) * speedup  # mission seconds
        print(f"{name}: {len(gaps) + 1} setpoints, gap median {np.median(gaps):.3f} s, max {gaps.max():.3f} s (mission time)")
        assert np.median(gaps) <= 0.25
    assert (ARDUPILOT_GUIDED, True) in t1.modes and t1.modes[-1] == (ARDUPILOT_LAND, False)
    assert t1.commands.get(MAV_CMD_NAV_TAKEOFF) == 1
    # PX4 lands armed in AUTO.LAND and, disarmed, returns to OFFBOARD (the user's last armable mode).
    assert (PX4_OFFBOARD, True) in t2.modes and t2.modes[-2:] == [(PX4_LAND, True), (PX4_OFFBOARD, False)]
    assert MAV_CMD_NAV_TAKEOFF not in t2.commands  # PX4 climbs in OFFBOARD on the stream


@pytest.mark.slow  # 16 s of real time; link loss against real ArduPilot SITL: tests/sitl/test_sitl_link_loss.py
@pytest.mark.parametrize("flavour", ["px4", "ardupilot"])
def test_link_loss_is_reported_records_go_stale_and_the_planner_resumes(tmp_path: Path, procs: list[Proc], flavour: str) -> None:
    """The radio link is cut mid-mission (a UDP relay stops forwarding): the planner notices
    within 3 s, publishes its last record flagged stale, sends no setpoint, and when the link
    returns: ArduPilot still in GUIDED, the planner resumes; PX4, whose offboard-loss failsafe
    switched to AUTO.LOITER meanwhile, is taken over (the planner cannot tell the failsafe's
    mode change from a pilot's) until ``fimnav handback``, then flown on. The mission is
    finished; end of mission 'hold' confirmed."""
    mission = write_mission(tmp_path / "m.yaml", "loss", [[10.0, 20.0, 8.0]], 60, "hold")
    vehicle, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", str(SPEEDUP), "--flavour", flavour)
    relay = UdpRelay(port)
    peer = SwarmPeer("loss", 1, {1: 80.0}, mode="router")
    try:
        planner = Proc(plan_argv(mission, 1, peer, "--mavlink", f"udpout:127.0.0.1:{relay.port}"))
        procs.append(planner)
        planner.expect(r"ready at the start position", 60.0, "err")
        wait_for(lambda: len(peer.snapshot()) >= 5, 20.0, "5 records of the planner", procs=[planner], interval_s=0.02)
        relay.cut.set()
        t_cut = time.monotonic()
        planner.expect(r"vehicle link lost", 10.0, "err")
        noticed_s = time.monotonic() - t_cut
        # Two stale records before the link returns (the summary's stale_steps below): on a fast
        # machine the first came so soon that a link restored at once was down for one step only.
        wait_for(lambda: sum(r.stale for r in peer.snapshot()) >= 2, 10.0, "two records marked stale", procs=[planner],
                 interval_s=0.02)
        relay.cut.clear()
        if flavour == "px4":
            planner.expect(r"taken over at step \d+ after the link loss: the vehicle is armed in AUTO.LOITER", 30.0, "err")
            r = handback(mission, 1, "--zenoh-connect", peer.endpoint)
            assert r.returncode == 0, r.stdout + r.stderr
            planner.expect(r"handed back at step \d+: in OFFBOARD", 20.0, "err")
        else:
            planner.expect(r"resumed in GUIDED", 30.0, "err")
        assert planner.wait(60.0) == 0, planner.tail()
        records = peer.snapshot()
    finally:
        peer.close()
        relay.close()
    print(f"link loss noticed {noticed_s:.2f} s after the cut")
    assert noticed_s < 3.0, noticed_s
    s = summary_of(planner)
    assert len(s["link_losses"]) == 1 and s["stale_steps"] >= 2
    assert s["end"]["confirmed"] and s["end"]["armed"] is True
    stale = [r for r in records if r.stale]
    first_stale = records.index(stale[0])
    # Stale records repeat the last state (position and measurement) at the current step.
    assert all(r.position_m == records[first_stale - 1].position_m for r in stale)
    assert [r.step for r in records] == sorted(r.step for r in records)
    assert not records[-1].stale
    t = stop_and_read(vehicle, tmp_path / "v.tlog")
    if flavour == "px4":
        assert s["end"]["mode"] == "AUTO.LOITER"
        assert "Failsafe: offboard lost, holding" in t.texts  # the vehicle's own failsafe
        (take,) = s["taken_over"]
        assert take["mode"] == "AUTO.LOITER" and take["reason"] == "after link loss" and take["handed_back_step"] > take["step"], take
        i = t.modes.index((PX4_LOITER, True))  # ... then the hand-back
        assert (PX4_OFFBOARD, True) in t.modes[i:]
        assert t.modes[-1] == (PX4_LOITER, True)
    else:
        assert s["end"]["mode"] == "GUIDED"
        assert t.modes[-1] == (ARDUPILOT_GUIDED, True)


@pytest.mark.slow  # 10 s; signing in the default run: tests/security/test_mavlink_signing.py (vehicle process), tests/vehicle_sim/test_vehicle_link_signing.py (the link's rules)
def test_signed_link_flies_and_an_unsigned_planner_is_refused(tmp_path: Path, procs: list[Proc]) -> None:
    """A vehicle with MAVLink 2 signing on: a planner without the key stops at once with a
    message that says why; with another key it stops within seconds (every frame fails the
    signature check), not at its heartbeat timeout; with the key (mode 0600) it flies the
    mission and ends in RTL."""
    key = tmp_path / "signing.key"
    secret = os.urandom(32)
    key.write_bytes(secret)
    key.chmod(0o600)
    mission = write_mission(tmp_path / "m.yaml", "signed", [[10.0, 20.0, 8.0]], 10, "rtl")
    vehicle, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", str(SPEEDUP), "--signing-key", str(key))
    peer = SwarmPeer("signed", 1, {1: 75.0})
    try:
        unsigned = Proc(plan_argv(mission, 1, peer, "--mavlink", f"udpout:127.0.0.1:{port}"))
        procs.append(unsigned)
        assert unsigned.wait(30.0) == 1, unsigned.tail()
        assert "MAVLink 2 signing" in unsigned.err and "--signing-key" in unsigned.err
        assert "Traceback" not in unsigned.err
        wrong = tmp_path / "wrong.key"
        wrong.write_bytes(bytes(b ^ 0xFF for b in secret))
        wrong.chmod(0o600)
        t0 = time.monotonic()
        mismatched = Proc(plan_argv(mission, 1, peer, "--mavlink", f"udpout:127.0.0.1:{port}", "--signing-key", str(wrong),
                                    "--preflight-timeout", "60"))
        procs.append(mismatched)
        # Refused once every frame for 3 s failed the signature check, long before the 60 s timeout.
        assert mismatched.wait(30.0) == 1, mismatched.tail()
        assert time.monotonic() - t0 < 20.0
        assert "does not match our signing key" in mismatched.err and "another key" in mismatched.err, mismatched.tail()
        assert "Traceback" not in mismatched.err and "sig mismatch" not in mismatched.err
        signed = Proc(plan_argv(mission, 1, peer, "--mavlink", f"udpout:127.0.0.1:{port}", "--signing-key", str(key)))
        procs.append(signed)
        assert signed.wait(60.0) == 0, signed.tail()
    finally:
        peer.close()
    s = summary_of(signed)
    assert s["steps"] == 10 and s["end"]["mode"] == "RTL" and s["end"]["confirmed"]
    for text in (signed.out + signed.err, unsigned.out + unsigned.err, mismatched.out + mismatched.err):
        assert secret.hex() not in text and secret.hex().upper() not in text
    t = stop_and_read(vehicle, tmp_path / "v.tlog")
    assert t.setpoints.get(("SET_POSITION_TARGET_GLOBAL_INT", GLOBAL_RELATIVE_ALT_INT, MASK_POS_VEL), 0) >= 10
    assert not [x for x in t.texts if "timeout" in x.lower()], t.texts
    assert (ARDUPILOT_RTL, True) in t.modes


@pytest.mark.parametrize("mode", [0o640, pytest.param(0o604, marks=pytest.mark.slow)])
def test_group_or_world_readable_key_is_refused(tmp_path: Path, procs: list[Proc], mode: int) -> None:
    """A signing key others can read is refused before anything starts, from the command
    line and from the mission, with what to do; the key never appears in the message."""
    key = tmp_path / "k.key"
    secret = os.urandom(32).hex()
    key.write_text(secret + "\n")
    key.chmod(mode)
    mission = write_mission(tmp_path / "m.yaml", "perm", [[10.0, 20.0, 8.0]], 5, "hold")
    cli = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", "udpout:127.0.0.1:9", "--signing-key", str(key)))
    procs.append(cli)
    assert cli.wait(30.0) == 2, cli.tail()
    m = yaml.safe_load(mission.read_text())
    m["vehicles"] = {"overrides": [{"connection": "udpout:127.0.0.1:9", "signing_key_file": str(key)}]}
    from_mission = write_mission(tmp_path / "m2.yaml", "perm", [[10.0, 20.0, 8.0]], 5, "hold", vehicles=m["vehicles"])
    via_mission = Proc(fimnav("plan", "--mission", str(from_mission), "--uav", "1", "--preflight-timeout", "5"))
    procs.append(via_mission)
    assert via_mission.wait(30.0) == 2, via_mission.tail()
    for p in (cli, via_mission):
        assert f"permissions {mode:04o}" in p.err and "chmod 600" in p.err, p.err
        assert secret not in p.err + p.out and "Traceback" not in p.err


def test_geodesy_round_trip_and_against_vehicle_sim() -> None:
    """Mission ENU ↔ WGS-84 (comms.geodesy) round-trips to 1 µm and agrees with the
    simulated vehicle's topocentric convention (the same MissionFrame) to 1 mm at 1 km."""
    from comms.geodesy import MissionFrame

    frame = MissionFrame(-35.363261, 149.165230, 584.0)
    ref = frame
    for x, y, z in ((0.0, 0.0, 0.0), (10.0, 20.0, 8.0), (-1000.0, 700.0, 120.0), (1000.0, -1000.0, 3.0)):
        g = frame.to_global(x, y, z)
        assert math.isclose(g.alt_amsl_m, 584.0 + z, abs_tol=1e-9)
        back = frame.to_enu(g.lat_deg, g.lon_deg, g.alt_amsl_m)
        assert max(abs(a - b) for a, b in zip(back, (x, y, z))) < 1e-6
        # vehicle_sim maps a setpoint's lat/lon at the origin's height, z = alt - origin alt
        rx, ry, _ = ref.geodetic_to_topocentric(g.lat_deg, g.lon_deg, 584.0)
        assert math.hypot(rx - x, ry - y) < 1e-3
    assert frame.matches(-35.363261, 149.165230, 584.0) and not frame.matches(-35.3632, 149.165230, 584.0)


@pytest.mark.parametrize("flavour", ["ardupilot", pytest.param("px4", marks=pytest.mark.slow)])
def test_killed_planner_leaves_the_vehicle_holding_within_its_timeout(tmp_path: Path, procs: list[Proc], flavour: str) -> None:
    """kill -9 of the planner mid-mission: the setpoint stream stops and the vehicle's own
    timeout takes over within GUID_TIMEOUT (ArduPilot: holds its last position target) or
    COM_OF_LOSS_T (PX4: offboard-loss failsafe, AUTO.LOITER); it stays armed in the air.
    Watched by a second MAVLink peer of the vehicle (the test)."""
    from comms.mavlink_client import VehicleLink

    mission = write_mission(tmp_path / "m.yaml", "kill", [[10.0, 20.0, 8.0]], 200, "hold")
    vehicle, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", str(SPEEDUP), "--flavour", flavour)
    peer = SwarmPeer("kill", 1, {1: 80.0})
    watch = VehicleLink(f"udpout:127.0.0.1:{port}", 1, source_system=200)
    try:
        # (LOCAL_NED here: the simulated vehicle's EKF origin is the mission origin, checked)
        planner = Proc(plan_argv(mission, 1, peer, "--mavlink", f"udpout:127.0.0.1:{port}", "--setpoint-frame", "local_ned"))
        procs.append(planner)
        planner.expect(r"ready at the start position", 60.0, "err")
        assert "(is the mission origin); setpoints in LOCAL_NED" in planner.err
        deadline = time.monotonic() + 20.0
        while len(peer.snapshot()) < 5:
            assert time.monotonic() < deadline, planner.tail()
            watch.pump(0.02)
        watch.statustexts.clear()
        os.killpg(planner.p.pid, 9)
        t_kill = time.monotonic()
        want = "Guided: velocity timeout, holding" if flavour == "ardupilot" else "Failsafe: offboard lost, holding"
        watch.wait_for(lambda: want in watch.statustexts, 10.0, want)
        held_after_s = time.monotonic() - t_kill
        watch.wait_for(lambda: watch.telemetry.velocity_enu_mps is not None and float(np.linalg.norm(watch.telemetry.velocity_enu_mps)) < 0.05, 10.0, "vehicle at rest")
        mode = "GUIDED" if flavour == "ardupilot" else "AUTO.LOITER"
        watch.wait_for(lambda: watch.in_mode(mode) and watch.telemetry.armed, 10.0, f"armed heartbeat in {mode}")
        tel = watch.telemetry
        assert tel.position_enu_m is not None and tel.position_enu_m[2] > 5.0  # still in the air
    finally:
        watch.close()
        peer.close()
    timeout_s = 3.0 if flavour == "ardupilot" else 1.0  # GUID_TIMEOUT / COM_OF_LOSS_T (sim s)
    print(f"{flavour}: vehicle holding {held_after_s:.2f} s (wall) after kill -9; timeout {timeout_s / SPEEDUP:.2f} s wall")
    assert held_after_s < timeout_s / SPEEDUP + 1.0


@pytest.mark.slow
def test_vehicle_restarted_on_the_same_tcp_port_is_reconnected_and_resumed(tmp_path: Path, procs: list[Proc]) -> None:
    """kill -9 of the vehicle process mid-mission on a TCP link, then a new vehicle on the
    same port (booting in the air, as an autopilot that rebooted in flight would not, but as
    a SITL restarted with a hover state does): the planner reports the loss, reconnects the
    TCP connection itself without blocking its loop, asks for its streams again and resumes."""
    mission = write_mission(tmp_path / "m.yaml", "tcp", [[10.0, 20.0, 8.0]], 60, "hold")
    args = ["--speedup", str(SPEEDUP)]
    first = Proc(fimnav("vehicle", "--mission", str(mission), "--mavlink", "tcpin:127.0.0.1:0", "--profile", "pointmass", *args))
    procs.append(first)
    ready = first.ready(30.0)
    port = int(ready["vehicles"][0]["mavlink"].rsplit(":", 1)[1])
    peer = SwarmPeer("tcp", 1, {1: 80.0})
    try:
        planner = Proc(plan_argv(mission, 1, peer, "--mavlink", f"tcp:127.0.0.1:{port}"))
        procs.append(planner)
        planner.expect(r"ready at the start position", 60.0, "err")
        first.stop()
        planner.expect(r"vehicle link lost", 10.0, "err")
        second = Proc(fimnav("vehicle", "--mission", str(mission), "--mavlink", f"tcpin:127.0.0.1:{port}", "--profile", "pointmass", "--airborne", *args))
        procs.append(second)
        second.expect(r"\{\"event\": \"ready\"", 30.0)
        planner.expect(r"vehicle link back after", 20.0, "err")
        planner.expect(r"resumed in GUIDED", 20.0, "err")
        assert planner.wait(60.0) == 0, planner.tail()
    finally:
        peer.close()
    s = summary_of(planner)
    assert len(s["link_losses"]) == 1 and s["end"]["mode"] == "GUIDED" and s["end"]["armed"] is True
    assert s["steps"] + s["stale_steps"] + s["late_steps"] == 60
    assert "Attempting reconnect" not in planner.out and "EOF on TCP" not in planner.out  # stdout is the summary only
    assert len(planner.out.strip().splitlines()) == 1


def test_local_ned_is_refused_when_the_ekf_origin_is_not_the_mission_origin(tmp_path: Path, procs: list[Proc]) -> None:
    """A vehicle whose EKF origin is 100 m off the mission origin: LOCAL_NED setpoints would
    land 100 m off, so the planner refuses them before arming; global setpoints are fine."""
    mission = write_mission(tmp_path / "m.yaml", "origin", [[10.0, 20.0, 8.0]], 3, "hold")
    _, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", str(SPEEDUP), "--origin=-35.3623610,149.165230,584")
    peer = SwarmPeer("origin", 1, {1: 80.0})
    try:
        p = Proc(plan_argv(mission, 1, peer, "--mavlink", f"udpout:127.0.0.1:{port}", "--setpoint-frame", "local_ned"))
        procs.append(p)
        assert p.wait(60.0) == 1, p.tail()
    finally:
        peer.close()
    assert "setpoint_frame local_ned needs the vehicle's EKF origin at the mission origin" in p.err and "use setpoint_frame global" in p.err
    assert "Arming" not in p.err and "Traceback" not in p.err
