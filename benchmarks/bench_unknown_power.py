"""Benchmark of the per-step cost of ``source.power: unknown`` (not a test).

One planner (batch ``()``) and the simulator's batch (trials, drones) = (20, 10), paper
ranging_los, in the state after ``--warm`` steps of the mission (the estimators' windows full, the
range cells in use): the median wall time of the planning step (:func:`planner.agent.plan`, with
the power known: the compiled cost; unknown: the Schur-complement cost in numpy given to the
compiled step) and of one estimator call (known: :func:`planner.estimator.update`; unknown:
:func:`planner.radio.power_estimator.update`, which runs the known-power one too), both measured
in the same run.

    python benchmarks/bench_unknown_power.py [--warm 150] [--repeat 30]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from missions.format.loader import load_mission
from missions.study.simulator import RunSpec, _Simulation

MISSION = Path(__file__).resolve().parents[1] / "missions" / "paper" / "ranging_los.yaml"


def _median_ms(fn: Callable[[], object], repeat: int) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def _simulation(power: str, trials: int, warm: int) -> tuple[_Simulation, int]:
    """A simulation of ``trials`` trials after ``warm`` steps."""
    mission = load_mission(MISSION, {"source.power": power})
    sim = _Simulation(RunSpec(mission, "A", trials, warm + 2), None, False, False, mission.planner_config().sensing)
    for k in range(warm):
        sim.step(k, None)
    return sim, warm


def _costs(power: str, trials: int, warm: int, repeat: int) -> tuple[float, float, float, float]:
    """(plan batch, estimator batch, plan one drone, estimator one drone), ms."""
    sim, k = _simulation(power, trials, warm)
    from planner.agent import plan
    from planner.radio import power_estimator as pw
    from planner.step import StepScene

    sim._record(k, sim.sources[k])
    view = sim._delayed_view(k)
    before = sim.state
    sim._estimate(k, sim.sources[k], view)
    after = sim.state
    scene = StepScene(
        step_index=k,
        own_index=sim.own_index,
        own_position_m=sim.pos,
        own_range_m=sim.rec_range[k],
        own_los=sim.rec_los[k],
        view_positions_m=view.positions_m,
        view_valid=view.have,
        view_los=view.los,
        saved_steps=view.saved,
        hops=view.hops,
        estimate_m=after.estimate_m,
        information=after.information,
        observable=after.observable,
        perturbation_uniforms=sim.ctrl_u[k],
    )
    one = StepScene(**{f.name: _first(getattr(scene, f.name)) for f in dataclasses.fields(StepScene)})
    offset = pw.planning_offset(after)
    offset_one = None if offset is None else offset[0, 0]
    drone_one = type(sim.drone).from_kernel_arrays([a[:1] for a in sim.drone.kernel_arrays()], ())
    new = sim.saved >= 0  # every record the views hold, as one call's rows (10 per drone)
    from planner import estimator as est

    meas = est.Measurements(
        positions_m=np.where(new[..., None], view.positions_m, np.nan),
        range_m=np.where(new, sim.rec_range[k][:, None, :], np.nan),
        azimuth_rad=np.full(new.shape, np.nan),
        elevation_rad=np.full(new.shape, np.nan),
        los=view.los,
    )
    meas_one = est.Measurements(*(a[0, 0] for a in (meas.positions_m, meas.range_m, meas.azimuth_rad, meas.elevation_rad, meas.los)))
    state_one = _first_state(before)
    config = sim.config
    return (
        _median_ms(lambda: plan(config, scene, sim.drone, power_offset=offset), repeat),
        _median_ms(lambda: pw.update_source(before, meas, config), repeat),
        _median_ms(lambda: plan(config, one, drone_one, power_offset=offset_one), 5 * repeat),
        _median_ms(lambda: pw.update_source(state_one, meas_one, config), 5 * repeat),
    )


def _first(value: object) -> object:
    """Trial 0, drone 0 of a (M, N, ...) array (scalars as they are)."""
    if isinstance(value, np.ndarray) and value.ndim >= 2:
        return value[0, 0]
    return value


def _first_state(state: object) -> object:
    """Trial 0, drone 0 of an estimator state (every array field of batch (M, N))."""
    out = {}
    for f in dataclasses.fields(state):  # type: ignore[arg-type]
        v = getattr(state, f.name)
        if dataclasses.is_dataclass(v) and not isinstance(v, type):
            v = _first_state(v)
        elif isinstance(v, np.ndarray) and v.ndim >= 2:
            v = v[0, 0]
        out[f.name] = v
    return type(state)(**out)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--warm", type=int, default=150, help="mission steps before the timing (default 150)")
    parser.add_argument("--trials", type=int, default=20, help="trials of the batch (default 20)")
    parser.add_argument("--repeat", type=int, default=30, help="timed calls per batch case (default 30; 5x for one drone)")
    args = parser.parse_args(argv)
    rows = {power: _costs(power, args.trials, args.warm, args.repeat) for power in ("known", "unknown")}
    print(f"paper ranging_los after {args.warm} steps; medians, ms per call")
    print(f"{'power':8} {'plan (20x10)':>13} {'estimate (20x10)':>17} {'plan (1)':>9} {'estimate (1)':>13}")
    for power, (pb, eb, p1, e1) in rows.items():
        print(f"{power:8} {pb:13.2f} {eb:17.2f} {p1:9.3f} {e1:13.3f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
