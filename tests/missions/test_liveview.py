"""The live view's recording (missions.launch.liveview), read back from the .rrd with rerun's own reader
and compared with independent references: the in-process simulator's arrays, the distributed
run's trajectories, closed-form ellipsoids."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from missions.launch.liveview import STATE_COLOURS, SwarmView, ViewError, covariances, ellipsoid_axes, require_rerun, swarm_frame
from missions.format.loader import load_mission
from missions.study.simulator import RunSpec, SimStep, simulate
from planner.fim import fisher_information

ROOT = Path(__file__).resolve().parents[2]


def read_entity(path: Path, entity: str, component: str) -> dict[int, Any]:
    """Step → the last value of ``component`` logged on ``entity`` at that step, from an .rrd."""
    from rerun.chunk import RrdReader

    out: dict[int, Any] = {}
    for chunk in RrdReader(path).stream():
        if chunk.entity_path != entity:
            continue
        rb = chunk.to_record_batch()
        if component not in rb.schema.names or "step" not in rb.schema.names:
            continue
        for step, value in zip(rb.column("step").to_pylist(), rb.column(component).to_pylist()):
            if value is not None:
                out[int(step)] = value
    return out


def test_ellipsoid_axes_recover_a_known_covariance() -> None:
    """cov = R diag(a²) Rᵀ → half-axes a and a rotation that rebuilds cov (closed form)."""
    rot = Rotation.from_euler("zyx", [0.7, -0.3, 1.1])
    a = np.array([2.0, 5.0, 11.0])
    cov = rot.as_matrix() @ np.diag(a**2) @ rot.as_matrix().T
    got = ellipsoid_axes(cov)
    assert got is not None
    half, quat = got
    R = Rotation.from_quat(quat).as_matrix()
    np.testing.assert_allclose(np.sort(half), a, rtol=1e-12)
    np.testing.assert_allclose(R @ np.diag(half**2) @ R.T, cov, rtol=1e-10, atol=1e-10)
    assert np.linalg.det(R) == pytest.approx(1.0)
    assert ellipsoid_axes(np.full((3, 3), np.nan)) is None
    assert ellipsoid_axes(np.diag([1.0, 1.0, 2e6 ** 2])) is None  # too large to draw


def test_covariances_invert_and_flag_singular_information() -> None:
    J = np.stack([np.diag([4.0, 1.0, 0.25]), np.zeros((3, 3)), np.full((3, 3), np.nan)])
    cov = covariances(J)
    np.testing.assert_allclose(cov[0], np.diag([0.25, 1.0, 4.0]))
    assert np.isnan(cov[1]).all() and np.isnan(cov[2]).all()


def test_montecarlo_view_records_what_the_simulator_computed(tmp_path: Path) -> None:
    """Trial 1 of a seeded run, logged through the simulator's observer: the recorded drone
    positions are the simulator's positions (float32 precision of the recording), the PEB curve
    its mean PEB over drones, and each ellipsoid the inverse FIM of the drone's view at its
    estimate (recomputed here from the simulator's estimates and positions)."""
    mission = load_mission("paper/heterogeneous", {"steps": 12, "trials": 2})
    rrd = tmp_path / "view.rrd"
    view = SwarmView(mission, rrd, None, name="test")
    n = mission.drones.count
    seen: list[SimStep] = []

    def observe(s: SimStep) -> None:
        seen.append(SimStep(s.step, s.positions_m[0].copy(), s.estimates_m[0].copy(), s.view_positions_m[0].copy(),
                            s.view_valid[0].copy(), s.view_los[0].copy()))
        view.log(swarm_frame(mission, s.step, s.positions_m[0], ("alive",) * n, s.estimates_m[0], s.view_positions_m[0],
                             s.view_valid[0], s.view_los[0]))

    result = simulate(RunSpec(mission, "A", 2, 12), observer=observe)
    view.close()
    drones = read_entity(rrd, "/world/drones", "Points3D:positions")
    assert sorted(drones) == list(range(12))
    for k in range(12):
        np.testing.assert_allclose(np.asarray(drones[k]), result.positions_m[k, 0], atol=1e-4)
    peb = read_entity(rrd, "/peb/mean", "Scalars:scalars")
    np.testing.assert_allclose([np.ravel(peb[k])[0] for k in range(12)], result.peb_m[:, 0].mean(axis=1), rtol=1e-6)
    colours = read_entity(rrd, "/world/drones", "Points3D:colors")
    r, g, b = STATE_COLOURS["alive"]
    assert all(c == ((r << 24) | (g << 16) | (b << 8) | 255) for c in colours[11])
    # The last step's ellipsoids against the FIM recomputed from the simulator's own arrays.
    last = seen[-1]
    np.testing.assert_allclose(last.estimates_m, result.estimates_m[-1, 0])
    ch = mission.channel.to_planner()
    J = fisher_information(last.estimates_m, last.view_positions_m, mission.drones.ranging_mask()[None] & last.view_valid,
                           mission.drones.bearing_mask()[None] & last.view_valid, last.view_los, ch)
    want = np.sort(np.sqrt(np.linalg.eigvalsh(np.linalg.inv(J))), axis=1)
    halves = np.sort(np.asarray(read_entity(rrd, "/world/uncertainty", "Ellipsoids3D:half_sizes")[11]), axis=1)
    np.testing.assert_allclose(halves, want, rtol=1e-5)


def test_view_without_rerun_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(ViewError, match=r"pip install 'fimnav\[view\]'"):
        require_rerun()


@pytest.mark.parametrize("arg,error", [
    ("nothing-here", "no such results directory or recording"),
    ("empty", "no recorded view"),
    ("mission.yaml", "expected a results directory or a rerun recording"),
])
def test_fimnav_view_names_what_is_missing(tmp_path: Path, arg: str, error: str) -> None:
    (tmp_path / "empty").mkdir()
    (tmp_path / "mission.yaml").write_text("x: 1\n")
    proc = subprocess.run([sys.executable, "-m", "missions", "view", str(tmp_path / arg)], capture_output=True, text=True,
                          timeout=60, cwd=ROOT)
    assert proc.returncode == 2, proc.stderr
    assert error in proc.stderr and "Traceback" not in proc.stderr


def test_drone_states_show_as_colours_and_events(tmp_path: Path) -> None:
    """A drone going taken over, stale, lost and back is drawn in each state's colour, labelled,
    and each change is one event."""
    mission = load_mission("paper/heterogeneous", {"steps": 5})
    n = mission.drones.count
    rrd = tmp_path / "view.rrd"
    view = SwarmView(mission, rrd, None, name="states")
    pos = mission.drones.start_positions_m()
    sequence = ["alive", "taken over", "stale", "lost", "alive"]
    for k, state in enumerate(sequence):
        states = ("alive",) * 2 + (state,) + ("alive",) * (n - 3)
        view.log(swarm_frame(mission, k, pos, states, np.full((n, 3), np.nan), np.zeros((n, n, 3)), np.zeros((n, n), bool),
                             np.zeros((n, n), bool)))
    view.close()
    colours = read_entity(rrd, "/world/drones", "Points3D:colors")
    labels = read_entity(rrd, "/world/drones", "Points3D:labels")
    for k, state in enumerate(sequence):
        r, g, b = STATE_COLOURS[state]
        assert colours[k][2] == (r << 24) | (g << 16) | (b << 8) | 255
        assert labels[k][2] == ("UAV 3" if state == "alive" else f"UAV 3 ({state})")
    events = read_entity(rrd, "/events", "TextLog:text")
    assert [events[k][0] if isinstance(events[k], list) else events[k] for k in sorted(events)] == [
        f"step {k}: UAV 3 {s}" for k, s in enumerate(sequence) if k > 0]
