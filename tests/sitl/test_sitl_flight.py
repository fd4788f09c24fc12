"""``fimnav plan`` against real ArduPilot SITL (copter): one drone flies a short mission at
speed-up 1 and sped up (SITL ``--speedup S``, the planner ``--speedup S``), and a SITL whose
clock runs at another rate than the planner's is refused before take-off; ``fimnav launch
--realtime`` flies a mixed fleet of two SITL copters (each with fimnav's simulated payload
following it over its SERIAL1) and two simulated vehicles.

Measured and printed (``-s``): SITL boot → ready (wall s, from the planner's start to its
``ready; EKF origin`` line) and tracking: per step, the distance between the position the
planner commanded at step k and the position the autopilot reported at step k + 1 (median,
max), the same for fimnav's simulated vehicle on the same mission. The planner assumes one
step of motion reaches its setpoint within v_max·Δt; the test asserts it.

Needs FIMNAV_SITL_ARDUCOPTER and FIMNAV_SITL_ARDUCOPTER_DEFAULTS (tests/sitl/sitl.py);
skipped with a one-line reason otherwise.
"""

from __future__ import annotations

import contextlib
import json
import socket
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.external.helpers import start_vehicle
from tests.sitl.sitl import SitlInstance, sitl_config, start_sitl, wait_for_bind
from tests.support.launch import Launch, processes_mentioning
from tests.support.net import free_port
from tests.support.proc import Proc, fimnav

_CFG, _REASON = sitl_config()

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

#: The paper's heterogeneous geometry for one joint drone: start 150 m north of the source,
#: buildings B1, B2 between; 30 steps of 1 s; v_max 1 m/step.
START = [0.0, 150.0, 8.0]
STEPS = 30
V_MAX = 1.0


def write_mission(path: Path, steps: int = STEPS) -> Path:
    path.write_text(yaml.safe_dump({
        "id": "sitl_one", "seed": 1, "dt_s": 1.0, "steps": steps, "criterion": "A",
        "drones": {"count": 1, "roles": ["joint"], "start": {"positions_m": [START]}},
        "source": {"position_m": [0.0, 0.0, 2.0]},
        "obstacles": [{"name": "B1", "min_m": [-40.0, 95.0, 0.0], "max_m": [-10.0, 115.0, 30.0]},
                      {"name": "B2", "min_m": [10.0, 70.0, 0.0], "max_m": [35.0, 90.0, 30.0]}],
        "constraints": {"speed_max_mps": V_MAX, "speed_min_mps": 0.5, "z_min_m": 2.0, "z_max_m": 25.0},
        "end_action": "land",
    }))
    return path


def home_below(mission: Path, enu: list[float]) -> str:
    """SITL's --home (lat,lon,alt,heading) on the ground below ``enu`` of the mission frame."""
    from comms.geodesy import MissionFrame
    from missions.format.loader import load_mission

    g = MissionFrame.of_mission(load_mission(mission)).to_global(enu[0], enu[1], 0.0)
    return f"{g.lat_deg:.8f},{g.lon_deg:.8f},{g.alt_amsl_m:.2f},0"


def tracking(log: Path) -> tuple[list[float], list[int]]:
    """(per step: |commanded position of step k − reported position at step k+1| in m, steps flown)."""
    rows = [json.loads(line) for line in log.read_text().splitlines()]
    err = [float(np.linalg.norm(np.subtract(a["next_position_m"], b["position_m"])))
           for a, b in zip(rows, rows[1:]) if b["step"] == a["step"] + 1]
    return err, [r["step"] for r in rows]


def fly(procs: list[Proc], mission: Path, conn: str, speedup: float, log: Path, timeout_s: float) -> tuple[dict, float, Proc]:
    """Run ``fimnav plan`` to the end; return its summary, the wall seconds from its start to
    its ``ready; EKF origin`` line, and the process."""
    t0 = time.monotonic()
    plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", conn, "--speedup", f"{speedup:g}",
                       "--log", str(log), "--preflight-timeout", "180"))
    procs.append(plan)
    plan.expect(r"ready; EKF origin", timeout_s, stream="err")
    ready_s = time.monotonic() - t0
    assert plan.wait(timeout_s) == 0, plan.tail()
    return json.loads(plan.out.strip().splitlines()[-1]), ready_s, plan


@pytest.mark.parametrize("speedup", [pytest.param(5.0, id="x5"), pytest.param(1.0, id="x1", marks=pytest.mark.slow)])
def test_one_drone_flies_a_short_mission_against_sitl(tmp_path: Path, procs: list[Proc], speedup: float) -> None:
    assert _CFG is not None
    mission = write_mission(tmp_path / "m.yaml")
    with start_sitl(_CFG, tmp_path / "sitl", speedup=speedup, home=home_below(mission, START)) as sitl:
        summary, ready_s, plan = fly(procs, mission, sitl.address, speedup, tmp_path / "sitl.jsonl", 240.0 / speedup + 60.0)
    assert summary["steps"] >= STEPS - 1 and summary["late_steps"] <= 1, summary
    assert summary["flavour"] == "ardupilot" and summary["frame"] == "global"
    assert summary["end"] == {"action": "land", "confirmed": True, "mode": "LAND", "armed": False, "landed_state": "ON_GROUND"}
    assert abs(summary["vehicle_clock_rate"] / speedup - 1.0) < 0.25, summary
    err, steps = tracking(tmp_path / "sitl.jsonl")
    # fimnav's simulated vehicle (point mass) on the same mission, same speed-up.
    v, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", f"{speedup:g}")
    vsum, _, _ = fly(procs, mission, f"udpout:127.0.0.1:{port}", speedup, tmp_path / "sim.jsonl", 120.0 / speedup + 30.0)
    verr, _ = tracking(tmp_path / "sim.jsonl")
    print(f"\nSITL x{speedup:g}: boot->ready {ready_s:.1f} s wall ({ready_s * speedup:.0f} s sim); clock x{summary['vehicle_clock_rate']}; "
          f"tracking median {np.median(err):.3f} m, max {max(err):.3f} m over {len(err)} steps; "
          f"fimnav vehicle (pointmass): median {np.median(verr):.3f} m, max {max(verr):.3f} m")
    # The planner's one-step-of-motion assumption: the vehicle is within v_max·Δt of the
    # commanded position one step later.
    assert max(err) <= V_MAX * 1.0, err
    assert max(verr) <= V_MAX * 1.0, verr


def test_sitl_at_another_speed_up_is_refused_before_take_off(tmp_path: Path, procs: list[Proc]) -> None:
    assert _CFG is not None
    mission = write_mission(tmp_path / "m.yaml")
    with start_sitl(_CFG, tmp_path / "sitl", speedup=1.0, home=home_below(mission, START)) as sitl:
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--mavlink", sitl.address, "--speedup", "5"))
        procs.append(plan)
        assert plan.wait(60.0) == 1, plan.tail()
    err = plan.err
    assert "the vehicle's clock runs at x1.0" in err and "mission clock at x5" in err, err[-2000:]
    assert "ready; EKF origin" not in err and "airborne" not in err and "Traceback" not in err


@contextlib.contextmanager
def sitl_with_serial1(workdir: Path, speedup: float, home: str, sysid: int) -> Iterator[tuple[SitlInstance, str]]:
    """A SITL copter as :func:`tests.sitl.sitl.start_sitl` starts one, with its SERIAL1 on a
    free TCP port too (the simulated payload's link); yields (instance, SERIAL1 address)."""
    assert _CFG is not None
    workdir.mkdir(parents=True, exist_ok=True)
    port, port1, rc_port = free_port(host="0.0.0.0"), free_port(host="0.0.0.0"), free_port(socket.SOCK_DGRAM, host="0.0.0.0")  # SITL binds every interface
    argv = [str(_CFG.binary), "--model", "+", "--speedup", f"{speedup:g}", "--defaults", str(_CFG.defaults), "--home", home,
            "--sysid", str(sysid), "-w", "--serial0", f"tcp:{port}:wait", "--serial1", f"tcp:{port1}", "--serial2", "none:",
            "--rc-in-port", str(rc_port)]
    log_path = workdir / "sitl-console.log"
    with open(log_path, "wb") as out:
        proc = subprocess.Popen(argv, cwd=workdir, stdin=subprocess.DEVNULL, stdout=out, stderr=subprocess.STDOUT, start_new_session=True)
    inst = SitlInstance(proc, f"tcp:127.0.0.1:{port}", port, speedup, workdir, log_path, argv)
    try:
        wait_for_bind(inst, 20.0)
        yield inst, f"tcp:127.0.0.1:{port1}"
    finally:
        inst.stop()


def test_mixed_fleet_of_two_sitl_copters_and_two_simulated_vehicles(tmp_path: Path, launches: list[Launch]) -> None:
    """The paper's heterogeneous mission, four drones, 30 steps, in real time at x{SPEEDUP}:
    drones 1 and 2 are SITL copters (own system ids, homes 6 m apart below their starts),
    3 and 4 fimnav's simulated vehicles. Every drone arms, takes off in GUIDED, reaches its
    start and flies every step, ends with the mission's end action (land); results and every
    drone's .tlog are written; zero violations; every SITL drone's simulated payload reaches
    its planner at every step; no process is left. The swarm's final PEB is that of the same
    mission flown by simulated vehicles only (three runs) within their run-to-run spread."""
    speedup = 4.0
    steps = 30
    base = yaml.safe_load((Path(__file__).resolve().parents[2] / "missions" / "paper" / "heterogeneous.yaml").read_text())
    starts = [[-3.0, 150.0, 8.0], [3.0, 150.0, 10.0], [-9.0, 150.0, 6.0], [9.0, 150.0, 12.0]]
    base.update({"id": "sitl_mixed", "steps": steps, "end_action": "land"})
    base["drones"] = {"count": 4, "roles": ["ranging", "bearing", "joint", "ranging"], "start": {"positions_m": starts}}
    mission = tmp_path / "mixed.yaml"
    mission.write_text(yaml.safe_dump(base))
    with contextlib.ExitStack() as stack:
        overrides: list[dict] = []
        for i in (1, 2):
            sitl, serial1 = stack.enter_context(sitl_with_serial1(tmp_path / f"sitl{i}", speedup, home_below(mission, starts[i - 1]), i))
            overrides.append({"connection": sitl.address, "payload_connection": serial1})
        base["vehicles"] = {"overrides": [*overrides, {}, {}]}
        mission.write_text(yaml.safe_dump(base))
        out = tmp_path / "run"
        run = Launch(mission, out, "--realtime", "--speedup", f"{speedup:g}", "--start-delay", "40")
        launches.append(run)
        code, stdout, stderr = run.wait(300.0)
        assert code == 0, stderr[-4000:]
    assert "Traceback" not in stderr
    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    assert summary["clock"] == f"realtime x{speedup:g}" and summary["failures"] == []
    assert summary["violations"] == {k: 0 for k in summary["violations"]}
    from tests.external.helpers import read_tlog

    for i in (1, 2, 3, 4):
        text = (out / "logs" / f"planner_{i}.log").read_text()
        end = json.loads(text.strip().splitlines()[-1])
        assert end["end"]["confirmed"] and end["end"]["action"] == "land" and end["end"]["landed_state"] == "ON_GROUND", (i, end)
        assert "airborne in GUIDED" in text and "ready at the start position" in text
        rows = [json.loads(line) for line in (out / "logs" / f"planner_{i}.jsonl").read_text().splitlines()]
        assert [r["step"] for r in rows] == list(range(steps)), (i, [r["step"] for r in rows])
        t = read_tlog(out / "tlogs" / f"vehicle_{i}.tlog")
        assert (4, True) in t.modes, (i, t.modes)  # armed in GUIDED
        if i <= 2:
            # SITL: the simulated payload measured at every step, a real ArduPilot flew it.
            assert abs(end["vehicle_clock_rate"] / speedup - 1.0) < 0.25, end
            assert all(r["measurement"]["range_m" if i == 1 else "azimuth_rad"] is not None for r in rows), i
            assert any("ArduPilot" in x or "ArduCopter" in x for x in t.texts), t.texts[:5]
            assert (out / "logs" / f"payload_{i}.log").exists()
    assert not processes_mentioning(str(out))
    # The same mission flown by fimnav's simulated vehicles only, in real time at the same
    # speed-up, three times: the spread of their final PEBs is the run-to-run noise.
    del base["vehicles"]
    mission.write_text(yaml.safe_dump(base))
    sim_pebs = []
    for k in range(3):
        sim = Launch(mission, tmp_path / f"sim{k}", "--realtime", "--speedup", f"{speedup:g}")
        launches.append(sim)
        code, _, sim_err = sim.wait(200.0)
        assert code == 0, sim_err[-3000:]
        sim_pebs.append(json.loads((tmp_path / f"sim{k}" / "summary.json").read_text())["runs"][0]["final_peb_mean_m"])
    peb = summary["final_peb_mean_m"]
    print(f"\nmixed fleet (2 SITL + 2 simulated) x{speedup:g}: final PEB {peb:.3f} m (initial {summary['initial_peb_mean_m']:.3f} m); "
          f"simulated only: {', '.join(f'{x:.3f}' for x in sim_pebs)} m")
    # Within run-to-run noise: the spread of the three simulated-only runs, at least 2 %.
    noise = max(float(np.ptp(sim_pebs)), 0.02 * float(np.median(sim_pebs)))
    assert abs(peb - float(np.median(sim_pebs))) <= noise, (peb, sim_pebs)
