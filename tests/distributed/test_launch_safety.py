"""A ``fimnav launch`` and its drones' safety, end to end (real processes, real Zenoh and MAVLink
on 127.0.0.1; docs/in-the-field.md):

- Ctrl-C or SIGTERM of a real-time launch: every planner tells its vehicle the mission's
  ``on_stop`` before the vehicles are stopped; each vehicle's .tlog ends in that mode, armed
  (ArduPilot LOITER, PX4 AUTO.LOITER); exit 130 / 143.
- An external autopilot nobody answers at (a ``tcp:`` port with nothing behind it): one line
  naming the drone and its connection, no traceback; ``--on-failure continue`` flies the others
  to the end (exit 3), ``abort`` stops the run (exit 1) and every other drone gets its on_stop.
- An external autopilot killed mid-flight: its planner gives the drone up after the step
  timeout and the launch reports it (exit 3), the others fly on.
- A planner the launch restarts (lockstep, ``--on-failure restart``) while a ground station
  holds its drone comes up taken over (``--taken-over``), the summary says so, and
  ``fimnav handback --results`` gives the drone back.
"""

from __future__ import annotations

import json
import os
import signal
import socket
import time
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.external.test_pilot_rule import ON_STOP_MODE, tlog_events
from tests.support.launch import Launch, processes_mentioning
from tests.support.net import free_port
from tests.support.proc import Proc, fimnav, with_default_interrupt
from tests.support.wait import wait_for

pytestmark = pytest.mark.integration

SPEEDUP = 5.0


def write(path: Path, mission: dict[str, Any]) -> Path:
    path.write_text(yaml.safe_dump(mission))
    return path


def mission_of(mission_id: str, count: int, steps: int, **extra: Any) -> dict[str, Any]:
    """Ranging drones 20 m apart, a source far enough, dt 1 s."""
    return {
        "id": mission_id, "dt_s": 1.0, "steps": steps, "seed": 3,
        "drones": {"count": count, "roles": "ranging", "start": {"positions_m": [[10.0 + 20.0 * i, 20.0, 8.0] for i in range(count)]}},
        "source": {"position_m": [60.0, 90.0, 2.0]}, **extra,
    }


def steps_logged(out: Path, uav: int) -> int:
    path = out / "logs" / f"planner_{uav}.jsonl"
    return path.read_text().count("\n") if path.exists() else 0


def last_mode(tlog: Path, sysid: int) -> tuple[int, bool]:
    """(custom_mode, armed) of vehicle ``sysid``'s last heartbeat in its .tlog."""
    return [v for _, kind, v in tlog_events(tlog, sysid) if kind == "mode"][-1]


# 17 s each (the real-time start); PX4 under SIGTERM in the slow run: a PX4 planner stopped by
# SIGTERM is in the default run (tests/external/test_pilot_rule.py, fimnav plan stopped by a signal).
@pytest.mark.parametrize(
    ("flavour", "signum"),
    [("ardupilot", signal.SIGINT), pytest.param("px4", signal.SIGTERM, marks=pytest.mark.slow)],
    ids=["ardupilot-SIGINT", "px4-SIGTERM"],
)
def test_a_stopped_realtime_launch_leaves_every_vehicle_in_on_stop(tmp_path: Path, launches: list[Launch], flavour: str, signum: int) -> None:
    mission = write(tmp_path / "m.yaml", mission_of("stopped", 2, 300, vehicles={"flavour": flavour}))
    out = tmp_path / "run"
    run = Launch.command(with_default_interrupt(fimnav("launch", str(mission), "--out", str(out), "--realtime", "--speedup", str(SPEEDUP),
                                                       "--start-delay", "12", "--no-figures")), out, tmp_path)
    launches.append(run)
    wait_for(lambda: min(steps_logged(out, 1), steps_logged(out, 2)) >= 3, 90.0, "three steps of every drone")
    if signum == signal.SIGINT:
        os.killpg(run.proc.pid, signum)  # Ctrl-C: the terminal signals the launcher's group
    else:
        run.proc.send_signal(signum)
    code, _, stderr = run.wait(60.0)
    assert code == 128 + signum, stderr[-3000:]
    assert "Traceback" not in stderr
    mode, name = ON_STOP_MODE[(flavour, "hold")]
    for i in (1, 2):
        log = (out / "logs" / f"planner_{i}.log").read_text()
        assert f"stopping (SIGTERM): the vehicle is in {name} (on_stop hold), confirmed" in log, log[-2000:]
        assert last_mode(out / "tlogs" / f"vehicle_{i}.tlog", i) == (mode, True)


@pytest.mark.slow  # ~40 s: the planner's TCP connection is retried for 30 s before it gives up
@pytest.mark.parametrize("on_failure", ["continue", "abort"])
def test_an_unreachable_external_autopilot_is_a_failed_drone(tmp_path: Path, launches: list[Launch], on_failure: str) -> None:
    port = free_port(socket.SOCK_STREAM)  # nothing listens there
    conn = f"tcp:127.0.0.1:{port}"
    mission = write(tmp_path / "m.yaml", mission_of("unreachable", 2, 250, vehicles={"overrides": [{}, {"connection": conn, "payload": "external"}]}))
    out = tmp_path / "run"
    run = Launch(mission, out, "--realtime", "--speedup", str(SPEEDUP), "--start-delay", "10", "--on-failure", on_failure)
    launches.append(run)
    code, stdout, stderr = run.wait(180.0)
    assert "Traceback" not in stderr and "KeyError" not in stderr, stderr[-3000:]
    named = f"planner_2 (drone 2, external autopilot at {conn})"
    if on_failure == "continue":
        assert code == 3, stderr[-3000:]
        line = next(x for x in stderr.splitlines() if named in x)
        assert "failed" in line and "vehicle unreachable" in line and conn in line, line
        summary = json.loads((out / "summary.json").read_text())["runs"][0]
        (failure,) = summary["failures"]
        assert failure["drones"] == [2] and failure["connection"] == conn and failure["action"] == "continued without it", failure
        assert steps_logged(out, 1) >= 250 - 4  # the simulated drone flew the mission
    else:
        assert code == 1, stderr[-3000:]
        assert f"fimnav launch: error: {named} exited with status 1" in stderr, stderr[-3000:]
        assert "vehicle unreachable" in stderr
        # The other drone was told its on_stop before its vehicle was stopped.
        log = (out / "logs" / "planner_1.log").read_text()
        assert "stopping (SIGTERM): the vehicle is in LOITER (on_stop hold), confirmed" in log, log[-2000:]
        assert last_mode(out / "tlogs" / "vehicle_1.tlog", 1) == (5, True)


@pytest.mark.slow  # ~35 s of real time
def test_an_external_autopilot_killed_mid_flight_is_a_failed_drone(tmp_path: Path, launches: list[Launch], procs: list[Proc]) -> None:
    port = free_port(socket.SOCK_STREAM)
    conn = f"tcp:127.0.0.1:{port}"
    mission = write(tmp_path / "m.yaml", mission_of("killed", 2, 150, vehicles={"overrides": [{}, {"connection": conn, "payload": "external"}]}))
    external = Proc(fimnav("vehicle", "--mission", str(mission), "--sysid", "2", "--mavlink", f"tcpin:127.0.0.1:{port}", "--speedup", str(SPEEDUP)))
    procs.append(external)
    external.ready(30.0)
    out = tmp_path / "run"
    run = Launch(mission, out, "--realtime", "--speedup", str(SPEEDUP), "--start-delay", "10", "--step-timeout", "5")
    launches.append(run)
    wait_for(lambda: steps_logged(out, 2) >= 5, 90.0, "five steps of the external drone")
    external.p.send_signal(signal.SIGKILL)
    killed = time.monotonic()
    code, _, stderr = run.wait(120.0)
    assert code == 3, stderr[-3000:]
    assert "Traceback" not in stderr
    line = next(x for x in stderr.splitlines() if "planner_2 (drone 2, external autopilot at" in x)
    assert f"vehicle link at {conn} lost for good" in line and "continued without it" in line, line
    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    (failure,) = summary["failures"]
    assert failure["drones"] == [2] and failure["connection"] == conn, failure
    assert steps_logged(out, 1) >= 150 - 4
    print(f"\nexternal autopilot killed: the launch ended {time.monotonic() - killed:.1f} s later")


@pytest.mark.slow  # ~30 s
def test_a_restarted_planner_keeps_the_take_over_and_is_handed_back(tmp_path: Path, launches: list[Launch]) -> None:
    """Lockstep launch, ``--on-failure restart``: a ground station switches drone 1 to LOITER, its
    planner is killed; the launch restarts it taken over (``--taken-over``): it commands
    nothing, publishes records flagged taken over; ``fimnav handback --results`` gives the
    drone back and it flies the mission to the end; the summary lists the take-over."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    from tests.external.helpers import handback
    from tests.external.test_pilot_rule import MAV_CMD_DO_SET_MODE

    steps = 1000
    mission = write(tmp_path / "m.yaml", mission_of("restart-held", 2, steps))
    out = tmp_path / "run"
    run = Launch(mission, out, "--on-failure", "restart", "--step-timeout", "20", "--vehicles-per-process", "1")
    launches.append(run)
    wait_for(lambda: steps_logged(out, 1) >= 5, 90.0, "five steps")
    ready = json.loads(next(x for x in (out / "logs" / "vehicle_1.log").read_text().splitlines() if '"ready"' in x))
    port = int(ready["vehicles"][0]["mavlink"].rsplit(":", 1)[1])
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
    try:
        gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
        gcs.mav.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, 5, 0, 0, 0, 0, 0)
        log = out / "logs" / "planner_1.log"
        wait_for(lambda: "taken over at step" in log.read_text(), 30.0, "the take-over")
        # A few steps on (the launch hears drone 1's records flagged taken over), the ground
        # station flies the drone in GUIDED ("fly to here"): still the pilot's.
        at = steps_logged(out, 2)
        wait_for(lambda: steps_logged(out, 2) >= at + 5, 30.0, "five more steps")
        gcs.mav.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0)
        ack = gcs.recv_match(type="COMMAND_ACK", blocking=True, timeout=10.0, condition=f"COMMAND_ACK.command == {MAV_CMD_DO_SET_MODE}")
        assert ack is not None and ack.result == 0, ack
        os.kill(planner_pid(out, 1), signal.SIGKILL)
        wait_for(lambda: "taken over at rejoin" in log.read_text(), 60.0, "the restarted planner to come up taken over")
        assert "the vehicle is armed in GUIDED and the launch restarted this planner while a pilot flew it" in log.read_text()
        r = handback(mission, 1, "--results", str(out))
        assert r.returncode == 0, r.stdout + r.stderr
        wait_for(lambda: "handed back at step" in log.read_text().split("taken over at rejoin")[-1], 30.0, "the hand-back")
    finally:
        gcs.close()
    code, _, stderr = run.wait(240.0)
    assert code == 3, stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    (failure,) = summary["failures"]
    assert failure["process"] == "planner_1" and failure["action"].endswith(", taken over"), failure
    (take,) = summary["taken_over"]["1"]
    assert take["at_start"] == "rejoin" and take["mode"] == "GUIDED" and take["handed_back_step"] > take["step"], take


def planner_pid(out: Path, uav: int) -> int:
    """The live planner process of drone ``uav`` of the run at ``out``."""
    for pid in processes_mentioning(str(out)):
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace") + " "
        if " plan " in cmd and f"--uav {uav} " in cmd:
            return pid
    pytest.fail(f"no planner of drone {uav}")


@pytest.mark.slow  # ~80 s of real time
def test_realtime_restart_rejoins_the_grid_and_keeps_a_take_over(tmp_path: Path, launches: list[Launch]) -> None:
    """``fimnav launch --realtime --on-failure restart``: planner 2 is killed while it flies:
    restarted, it rejoins the step grid where the mission is (no take-off, no flight to its
    start) and flies to the end; planner 1 is killed while a ground station holds its drone in
    LOITER: restarted, it comes up taken over and commands nothing until ``fimnav handback``."""
    os.environ["MAVLINK20"] = "1"
    from pymavlink import mavutil

    from tests.external.helpers import handback
    from tests.external.test_pilot_rule import MAV_CMD_DO_SET_MODE

    steps = 300
    mission = write(tmp_path / "m.yaml", mission_of("rt-restart", 2, steps))
    out = tmp_path / "run"
    run = Launch(mission, out, "--realtime", "--speedup", str(SPEEDUP), "--start-delay", "12", "--on-failure", "restart",
                 "--vehicles-per-process", "1")
    launches.append(run)
    wait_for(lambda: min(steps_logged(out, 1), steps_logged(out, 2)) >= 5, 90.0, "five steps of each drone")
    os.kill(planner_pid(out, 2), signal.SIGKILL)
    log2 = out / "logs" / "planner_2.log"
    wait_for(lambda: "rejoined at step" in log2.read_text(), 60.0, "planner 2 to rejoin")
    killed_at = steps_logged(out, 2)
    ready = json.loads(next(x for x in (out / "logs" / "vehicle_1.log").read_text().splitlines() if '"ready"' in x))
    port = int(ready["vehicles"][0]["mavlink"].rsplit(":", 1)[1])
    gcs = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
    log1 = out / "logs" / "planner_1.log"
    try:
        gcs.mav.heartbeat_send(6, 8, 0, 0, 0)
        gcs.mav.command_long_send(1, 1, MAV_CMD_DO_SET_MODE, 0, 1, 5, 0, 0, 0, 0, 0)
        wait_for(lambda: "taken over at step" in log1.read_text(), 30.0, "the take-over")
        os.kill(planner_pid(out, 1), signal.SIGKILL)
        wait_for(lambda: "taken over at rejoin" in log1.read_text(), 60.0, "planner 1 to come up taken over")
        handback_unix = time.time()
        r = handback(mission, 1, "--results", str(out))
        assert r.returncode == 0, r.stdout + r.stderr
        wait_for(lambda: "handed back at step" in log1.read_text().split("taken over at rejoin")[-1], 30.0, "the hand-back")
    finally:
        gcs.close()
    code, _, stderr = run.wait(240.0)
    assert code == 3, stderr[-3000:]
    assert "Traceback" not in stderr
    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    actions = {f["process"]: f["action"] for f in summary["failures"]}
    assert actions["planner_2"].startswith("restarted") and actions["planner_1"].startswith("restarted"), actions
    text2 = log2.read_text()
    assert "rejoined at step" in text2 and "(flying)" in text2 and text2.count("airborne in") == 1, text2[-2000:]
    flown2 = [json.loads(x)["step"] for x in (out / "logs" / "planner_2.jsonl").read_text().splitlines()]
    assert flown2 == sorted(flown2) and flown2[-1] >= steps - 3 and len(flown2) > killed_at
    (take,) = summary["taken_over"]["1"]
    assert take["at_start"] == "rejoin" and take["mode"] == "LOITER" and take["handed_back_step"] > take["step"], take
    # Vehicle 1's .tlog: from its first heartbeat in LOITER (what tells a planner; 0.1 s for one
    # in flight on loopback) until fimnav handback ran, no setpoint and no mode change from a
    # planner, through the kill and the restart.
    events = tlog_events(out / "tlogs" / "vehicle_1.tlog")
    t_gcs = next(t for t, kind, v in events if kind == "set_mode" and v == 255)
    t_held = next(t for t, kind, v in events if kind == "mode" and t > t_gcs and v[0] == 5)
    sent = [kind for t, kind, v in events if t_held + 0.1 < t < handback_unix and (kind == "setpoint" or (kind == "set_mode" and v != 255))]
    assert not sent, sent
