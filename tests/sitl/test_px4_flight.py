"""``fimnav plan`` against real PX4 SITL (v1.15, the headless SIH quadrotor): one drone flies a
short mission in OFFBOARD at speed factor 1 and sped up (PX4_SIM_SPEED_FACTOR F, the planner
``--speedup F``) to its landing; a PX4 whose clock runs at another rate than the planner's is
refused before take-off; ``fimnav launch --realtime`` flies a mixed fleet of two PX4 SIH drones
(each with fimnav's simulated payload on PX4's GCS link) and two simulated vehicles.

Measured and printed (``-s``): PX4 boot → ready (wall s, from the planner's start to its
``ready; EKF origin`` line; PX4 is started just before) and tracking: per step, the distance
between the position the planner commanded at step k and the position the autopilot reported
at step k + 1 (median, max), the same for fimnav's simulated vehicle in its PX4 flavour on the
same mission. The planner assumes one step of motion reaches its setpoint within v_max·Δt;
the test asserts it.

Needs FIMNAV_SITL_PX4 and FIMNAV_SITL_PX4_ETC (tests/sitl/px4.py); skipped with a one-line
reason otherwise.
"""

from __future__ import annotations

import contextlib
import json
import re
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.external.helpers import read_tlog, start_vehicle
from tests.sitl.px4 import Px4Instance, px4_config, start_px4
from tests.sitl.test_sitl_flight import START, STEPS, V_MAX, tracking, write_mission
from tests.support.launch import Launch, processes_mentioning
from tests.support.proc import Proc, fimnav

_CFG, _REASON = px4_config()

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]


def home_below(mission: Path, enu: list[float]) -> tuple[float, float, float]:
    """(lat deg, lon deg, ground altitude m AMSL) below ``enu`` of the mission frame, for SIH."""
    from comms.geodesy import MissionFrame
    from missions.format.loader import load_mission

    g = MissionFrame.of_mission(load_mission(mission)).to_global(enu[0], enu[1], 0.0)
    return g.lat_deg, g.lon_deg, g.alt_amsl_m


def fly(procs: list[Proc], mission: Path, conn: str, sysid: int, speedup: float, log: Path, timeout_s: float,
        t0: float | None = None) -> tuple[dict, float, Proc]:
    """Run ``fimnav plan`` (drone 1, vehicle system id ``sysid``) to the end; return its
    summary, the wall seconds from ``t0`` (default: the planner's start) to its ``ready; EKF
    origin`` line, and the process."""
    start = time.monotonic()
    plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--sysid", str(sysid), "--mavlink", conn,
                       "--speedup", f"{speedup:g}", "--log", str(log), "--preflight-timeout", "180"))
    procs.append(plan)
    plan.expect(r"ready; EKF origin", timeout_s, stream="err")
    ready_s = time.monotonic() - (start if t0 is None else t0)
    assert plan.wait(timeout_s) == 0, plan.tail()
    return json.loads(plan.out.strip().splitlines()[-1]), ready_s, plan


def px4_texts(px4: Px4Instance) -> str:
    """PX4's console (commander's messages: arming, take-off, landing, disarm)."""
    return px4.log_tail(400_000)


@pytest.mark.parametrize("speed", [pytest.param(5.0, id="x5"), pytest.param(1.0, id="x1", marks=pytest.mark.slow)])
def test_one_drone_flies_a_short_mission_against_px4_sih(tmp_path: Path, procs: list[Proc], speed: float) -> None:
    """30 steps of the heartbeat geometry (v_max 1 m/step, Δt 1 s), land: every step flown,
    landing confirmed (disarmed, ON_GROUND), OFFBOARD armed and PX4's own console saying it
    took off, landed and disarmed; the planner's step within v_max·Δt; then the same mission
    against fimnav's simulated PX4 flavour."""
    assert _CFG is not None
    mission = write_mission(tmp_path / "m.yaml")
    t0 = time.monotonic()
    with start_px4(_CFG, tmp_path / "px4", home=home_below(mission, START), speed=speed) as px4:
        summary, ready_s, plan = fly(procs, mission, px4.offboard, px4.sysid, speed, tmp_path / "px4.jsonl", 240.0 / speed + 60.0, t0)
        if speed > 1.0:
            # A second mission against the same PX4, which returned to OFFBOARD on landing.
            again, _, _ = fly(procs, write_mission(tmp_path / "m2.yaml", steps=5), px4.offboard, px4.sysid, speed,
                              tmp_path / "px4_again.jsonl", 120.0 / speed + 60.0)
            assert again["steps"] == 5 and again["end"]["confirmed"], again
        console = px4_texts(px4)
    assert "Traceback" not in plan.err
    assert summary["steps"] == STEPS and summary["late_steps"] <= 1, summary
    assert summary["flavour"] == "px4" and summary["frame"] == "global"
    # PX4 returns to the last armable mode the user chose (OFFBOARD) when it disarms after
    # AUTO.LAND (commander's UserModeIntention::onDisarm).
    assert summary["end"]["confirmed"] and summary["end"]["action"] == "land", summary
    assert summary["end"]["armed"] is False and summary["end"]["landed_state"] == "ON_GROUND", summary
    assert summary["end"]["mode"] in ("AUTO.LAND", "OFFBOARD"), summary
    assert summary["link_losses"] == [] and summary["mode_changes"] == [], summary
    assert abs(summary["vehicle_clock_rate"] / speed - 1.0) < 0.25, summary
    for line in ("Armed by external command", "Takeoff detected", "Landing detected", "Disarmed by landing"):
        assert line in console, (line, console[-3000:])
    assert "ready; EKF origin" in plan.err and "airborne in OFFBOARD" in plan.err
    err, steps = tracking(tmp_path / "px4.jsonl")
    assert steps == list(range(STEPS)), steps
    # fimnav's simulated vehicle, PX4 flavour (point mass), on the same mission and speed-up.
    v, port = start_vehicle(procs, mission, tmp_path / "v.tlog", "--speedup", f"{speed:g}", "--flavour", "px4")
    vsum, vready_s, _ = fly(procs, mission, f"udpout:127.0.0.1:{port}", 1, speed, tmp_path / "sim.jsonl", 120.0 / speed + 30.0)
    assert vsum["flavour"] == "px4" and vsum["end"]["confirmed"], vsum
    verr, _ = tracking(tmp_path / "sim.jsonl")
    print(f"\nPX4 SIH x{speed:g}: boot->ready {ready_s:.1f} s wall ({ready_s * speed:.0f} s sim); clock x{summary['vehicle_clock_rate']}; "
          f"end mode {summary['end']['mode']}; tracking median {np.median(err):.3f} m, max {max(err):.3f} m over {len(err)} steps; "
          f"fimnav vehicle px4 (pointmass): ready {vready_s:.1f} s, median {np.median(verr):.3f} m, max {max(verr):.3f} m")
    # The planner's one-step-of-motion assumption: the vehicle is within v_max·Δt of the
    # commanded position one step later.
    assert max(err) <= V_MAX * 1.0, err
    assert max(verr) <= V_MAX * 1.0, verr


def test_px4_at_another_speed_factor_is_refused_before_take_off(tmp_path: Path, procs: list[Proc]) -> None:
    assert _CFG is not None
    mission = write_mission(tmp_path / "m.yaml")
    with start_px4(_CFG, tmp_path / "px4", home=home_below(mission, START), speed=1.0) as px4:
        plan = Proc(fimnav("plan", "--mission", str(mission), "--uav", "1", "--sysid", str(px4.sysid), "--mavlink", px4.offboard,
                           "--speedup", "5"))
        procs.append(plan)
        assert plan.wait(60.0) == 1, plan.tail()
        console = px4_texts(px4)
    err = plan.err
    assert re.search(r"the vehicle's clock runs at x(0\.9\d|1\.0\d)", err) and "mission clock at x5" in err, err[-2000:]
    assert "ready; EKF origin" not in err and "airborne" not in err and "Traceback" not in err
    assert "Armed by external command" not in console


def test_mixed_fleet_of_two_px4_sih_and_two_simulated_vehicles(tmp_path: Path, launches: list[Launch]) -> None:
    """The paper's heterogeneous mission, four drones, 30 steps, in real time at x4: drones 1
    and 2 are PX4 SIH quadrotors (MAV_SYS_ID 1 and 2, homes 6 m apart below their starts,
    each with ``fimnav payload`` on PX4's GCS link), 3 and 4 fimnav's simulated vehicles.
    Every drone arms (PX4 in OFFBOARD), reaches its start, flies every step and lands
    (confirmed); zero violations; every PX4 drone's simulated payload reaches its planner at
    every step; no process is left."""
    speed = 4.0
    steps = 30
    base = yaml.safe_load((Path(__file__).resolve().parents[2] / "missions" / "paper" / "heterogeneous.yaml").read_text())
    starts = [[-3.0, 150.0, 8.0], [3.0, 150.0, 10.0], [-9.0, 150.0, 6.0], [9.0, 150.0, 12.0]]
    base.update({"id": "px4_mixed", "steps": steps, "end_action": "land"})
    base["drones"] = {"count": 4, "roles": ["ranging", "bearing", "joint", "ranging"], "start": {"positions_m": starts}}
    mission = tmp_path / "mixed.yaml"
    mission.write_text(yaml.safe_dump(base))
    with contextlib.ExitStack() as stack:
        overrides: list[dict] = []
        used: set[int] = set()
        for i in (1, 2):
            px4 = stack.enter_context(start_px4(_CFG, tmp_path / f"px4_{i}", home=home_below(mission, starts[i - 1]), speed=speed,
                                                sysid=i, exclude=frozenset(used)))  # type: ignore[arg-type]
            used.add(px4.instance)
            overrides.append({"connection": px4.offboard, "payload_connection": px4.gcs})
        base["vehicles"] = {"overrides": [*overrides, {}, {}]}
        mission.write_text(yaml.safe_dump(base))
        out = tmp_path / "run"
        run = Launch(mission, out, "--realtime", "--speedup", f"{speed:g}", "--start-delay", "40")
        launches.append(run)
        code, stdout, stderr = run.wait(300.0)
        assert code == 0, stderr[-4000:]
    assert "Traceback" not in stderr
    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    assert summary["clock"] == f"realtime x{speed:g}" and summary["failures"] == []
    assert summary["violations"] == {k: 0 for k in summary["violations"]}
    errs = {}
    for i in (1, 2, 3, 4):
        text = (out / "logs" / f"planner_{i}.log").read_text()
        end = json.loads(text.strip().splitlines()[-1])
        assert end["end"]["confirmed"] and end["end"]["action"] == "land" and end["end"]["landed_state"] == "ON_GROUND", (i, end)
        assert "ready at the start position" in text
        rows = [json.loads(line) for line in (out / "logs" / f"planner_{i}.jsonl").read_text().splitlines()]
        assert [r["step"] for r in rows] == list(range(steps)), (i, [r["step"] for r in rows])
        errs[i], _ = tracking(out / "logs" / f"planner_{i}.jsonl")
        t = read_tlog(out / "tlogs" / f"vehicle_{i}.tlog")
        if i <= 2:
            assert "airborne in OFFBOARD" in text and end["flavour"] == "px4", (i, end)
            assert ((6 << 16), True) in t.modes, (i, t.modes)  # armed in OFFBOARD
            assert abs(end["vehicle_clock_rate"] / speed - 1.0) < 0.25, end
            assert all(r["measurement"]["range_m" if i == 1 else "azimuth_rad"] is not None for r in rows), i
            assert (out / "logs" / f"payload_{i}.log").exists()
        else:
            assert (4, True) in t.modes, (i, t.modes)  # simulated ArduPilot, armed in GUIDED
    assert not processes_mentioning(str(out))
    print(f"\nmixed fleet (2 PX4 SIH + 2 simulated) x{speed:g}: final PEB {summary['final_peb_mean_m']:.3f} m "
          f"(initial {summary['initial_peb_mean_m']:.3f} m); tracking median/max: "
          + ", ".join(f"{i}: {np.median(e):.3f}/{max(e):.3f} m" for i, e in errs.items()))
