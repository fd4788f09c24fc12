"""``fimnav plan`` against real ArduPilot SITL (copter): one drone flies a short mission at
speed-up 1 and sped up (SITL ``--speedup S``, the planner ``--speedup S``), and a SITL whose
clock runs at another rate than the planner's is refused before take-off.

Measured and printed (``-s``): SITL boot → ready (wall s, from the planner's start to its
``ready; EKF origin`` line) and tracking: per step, the distance between the position the
planner commanded at step k and the position the autopilot reported at step k + 1 (median,
max), the same for fimnav's simulated vehicle on the same mission. The planner assumes one
step of motion reaches its setpoint within v_max·Δt; the test asserts it.

Needs FIMNAV_SITL_ARDUCOPTER and FIMNAV_SITL_ARDUCOPTER_DEFAULTS (tests/sitl/sitl.py);
skipped with a one-line reason otherwise.
"""

from __future__ import annotations

import json
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

from tests.external.helpers import Proc, start_vehicle

try:
    from tests.sitl.sitl import sitl_config, start_sitl
except ImportError as exc:  # the helpers are not there: nothing to run against
    _CFG, _REASON = None, f"tests/sitl/sitl.py not importable ({exc})"
else:
    _CFG, _REASON = sitl_config()

pytestmark = [pytest.mark.sitl, pytest.mark.integration, pytest.mark.skipif(_CFG is None, reason=_REASON)]

#: The paper's heterogeneous geometry for one joint drone: start 150 m north of the source,
#: buildings B1, B2 between; 30 steps of 1 s; v_max 1 m/step.
START = [0.0, 150.0, 8.0]
STEPS = 30
V_MAX = 1.0


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    started: list[Proc] = []
    yield started
    for p in reversed(started):
        p.stop()


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
    from missions.loader import load_mission

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
    plan = Proc(["plan", "--mission", str(mission), "--uav", "1", "--mavlink", conn, "--speedup", f"{speedup:g}",
                 "--log", str(log), "--preflight-timeout", "180"])
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
        plan = Proc(["plan", "--mission", str(mission), "--uav", "1", "--mavlink", sitl.address, "--speedup", "5"])
        procs.append(plan)
        assert plan.wait(60.0) == 1, plan.tail()
    err = plan.err
    assert "the vehicle's clock runs at x1.0" in err and "mission clock at x5" in err, err[-2000:]
    assert "ready; EKF origin" not in err and "airborne" not in err and "Traceback" not in err
