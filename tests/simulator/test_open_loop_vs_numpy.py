"""The compiled core against the numpy code it replaced (commit 48f7e03, vendored test-only in
:mod:`tests.reference_numpy`), call by call, open loop, on the reference runs of
``test_bit_identity.py`` (every paper mission × A/D × with and without faults,
``tests/simulator/reference_runs.py``): the estimator (:mod:`planner.estimator` against
:mod:`tests.reference_numpy.estimator`) and the planning step (:func:`planner.agent.plan`
against :mod:`tests.reference_numpy.planner`'s ``plan``).

Open loop: the drones are put where ``tests/data/simulator_reference.npz`` has them at every
step (its 40 recorded steps); at each step the in-process simulator measures, hears (delays,
loss, partition and late records included) and builds the records new to each drone there, and
both estimators take the same records, each carrying its own state (batch (trials, drones));
then both planners plan from the same view and the same estimator state, each carrying its
own state (the compiled :class:`planner.step.DroneState`; for numpy what 48f7e03's simulator
carried: the last step, the peers' drift, loitering, the last keep-out). After every call of
the estimator:

* the discrete outputs are identical: ``observable``, ``initialised``, ``suspect``,
  ``angles_used``, ``measurement_count``, and the range memory's cells (which cells are taken and
  how many ranges each holds: which cell each range joined);
* the estimates agree within 1e-9 m, except at the calls listed in :data:`DEPARTURES` (per run:
  which calls, how many (call, trial, drone) departures, the largest, as measured), each within
  the bound of its kind below;
* where the estimates agree, the Fisher information agrees within 1e-9 of its largest entry and
  the score statistic T within 1e-9 (1 + |T|) (:data:`INFO_RTOL`, :data:`CONSISTENCY_RTOL`).

Where a call departs (beyond 1e-9 m, or the range memory tie below), the compiled state is
re-synchronised from numpy's (its fields packed as the compiled kernels take them) before the
next call, so that each listed departure is one call's, not an accumulation.

What departs, and why (floating-point order: numpy's SIMD sums against the compiled loops;
measured with the suite's pinned numerics, :mod:`missions.runtime.numerics`, on the recorded
trajectories; ``python -m tests.simulator.test_open_loop_vs_numpy``, pinned the same way by
``tests/__init__.py``, prints each departure): 161 (call, trial, drone) departures of the 24 × 40 × 2 × 10 = 19200, all in elements that have used only ranges
so far (asserted): in ``ranging_los``, ``ranging_nlos``, ``dynamic_source``, and one
``heterogeneous`` drone that had heard only ranges at call 0; bearing and joint stay within
7e-12 m at every call.

* 98 at calls other than a re-check, 87 of them at calls 0-3 (and 10 at call 5, one at call
  36): estimates from a few coplanar ranges whose PEB is 121 m to infinite (J singular, not
  observable): the rounding is amplified by the conditioning, 1.0e-9..3.4e-5 m, at most
  1.2e-11 × PEB (:data:`ILL_CONDITIONED_PER_PEB`);
* 63 at the range memory's re-check calls (every fifth call: 4, 9, 14, ...), which polish two
  points on the memory's likelihood (stopping once a step is shorter than 1e-3 m, at most 15
  iterations) and re-linearise the prior there: 1.8e-9..6.6e-4 m, at most 9.4e-7 × PEB, well
  below that tolerance (:data:`RECHECK_M`);
* no discrete flip of the range memory (:data:`MEMORY_FLIPS`, kept for the ties the last bits
  decide: a range taken exactly as far from the centres of two cells joins the one whose
  distance rounds lower). The discrete outputs of the state never differ.

The planning step: at every step of every run the planned next positions agree within
1e-9 m (measured: at most 4.3e-12 m) and the decisions are identical (``singular``,
``filtered``, ``loiter``, the active constraint families): no departure.

The default run takes half the grid (:data:`DEFAULT_RUNS`: every mission, A with faults and D
without; about 10 s of CPU at load 5, the numpy estimator and planner most of it); the other
half is marked ``slow`` (the whole grid: about 21 s of CPU).
"""

from __future__ import annotations

import ast
import dataclasses
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest

import missions.study.simulator as simulator
from missions.study.simulator import RunSpec, _Simulation
from planner import estimator as cest
from planner.estimator.memory import RangeMemory
from planner.params import Channel, Criterion
from planner.sensing import SENSING, SensingComponent
from tests.reference_numpy import estimator as nest
from tests.reference_numpy.planner import agent as nplan
from tests.simulator.conftest import paper_mission
from tests.simulator.reference_runs import FAULTS, REFERENCE, STEPS, TRIALS, run_names
from tests.support.numerics import pinned

ROOT = Path(__file__).resolve().parents[2]
TOL_M = 1e-9
#: Where the estimates agree: the information within this × its largest entry (measured
#: ≤ 6.9e-12), the score statistic T within this × (1 + |T|) (measured ≤ 3.6e-11).
INFO_RTOL = 1e-9
CONSISTENCY_RTOL = 1e-9
#: Weight below which a memory cell is empty (planner.estimator.memory._EMPTY).
_EMPTY = 1e-6
FLAGS = ("observable", "initialised", "suspect", "angles_used", "measurement_count")

#: Where the estimates depart from numpy's by more than 1e-9 m, as measured: run → (calls
#: that depart, number of (call, trial, drone) departures, the largest |Δx| in m rounded up).
#: ``python -m tests.simulator.test_open_loop_vs_numpy`` prints each departure.
DEPARTURES: dict[str, tuple[tuple[int, ...], int, float]] = {
    "ranging_los_A_nofault": ((4,), 10, 1.3e-8),
    "ranging_los_A_faults": ((0, 1, 2, 4, 9, 14, 34, 39), 21, 4.3e-5),
    "ranging_los_D_nofault": ((14,), 10, 2.1e-6),
    "ranging_los_D_faults": ((0, 1, 2, 4, 9, 19, 34, 39), 22, 1.8e-5),
    "ranging_nlos_A_faults": ((0, 1, 2, 4, 14, 34, 39), 22, 3.4e-5),
    "ranging_nlos_D_nofault": ((5, 39), 20, 3.4e-5),
    "ranging_nlos_D_faults": ((0, 1, 4, 14, 24, 34), 22, 6.6e-4),
    "dynamic_source_A_faults": ((0, 1, 2, 4), 16, 1.7e-5),
    "dynamic_source_D_faults": ((0, 1, 3, 36), 16, 1.7e-5),
    "heterogeneous_A_faults": ((0,), 1, 2.0e-9),
    "heterogeneous_D_faults": ((0,), 1, 2.0e-9),
}
#: A departure at any other call than a re-check is an ill-determined estimate's rounding:
#: |Δx| ≤ this × numpy's PEB √tr J⁻¹ (measured: ≤ 1.2e-11 × PEB, PEB ≥ 121 m).
ILL_CONDITIONED_PER_PEB = 2e-11
#: A departure at a re-check call (the polish's stop decided by the last bit): |Δx| ≤ this, m
#: (measured: ≤ 6.6e-4 m, PEB ≥ 54 m).
RECHECK_M = 1e-3

#: The range memory's nearest-cell ties decided differently: run → {(call, trial, drone)}.
MEMORY_FLIPS: dict[str, set[tuple[int, int, int]]] = {}


def compiled_state(state: Any) -> cest.EstimatorState:
    """The compiled estimator's state holding the numpy state ``state``'s values (the two
    states have the same fields; the compiled one packs them on its next update)."""
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cest.EstimatorState):
        v = getattr(state, f.name)
        if f.name == "range_memory":
            v = RangeMemory(*(np.array(getattr(v, g.name)) for g in dataclasses.fields(RangeMemory)))
        elif f.name in ("window", "range_window"):
            v = cest.Measurements(v.positions_m, v.range_m, v.azimuth_rad, v.elevation_rad, v.los, dict(v.extra_values))
        values[f.name] = v
    return cest.EstimatorState(**values)


@dataclass(frozen=True)
class Departure:
    """A call whose estimates differ by more than TOL_M: |Δx| (m), the PEB √tr J⁻¹ of numpy's
    information there (m; inf where J is singular), whether numpy's element is observable and
    whether it has used only ranges so far (not ``angles_used``)."""

    diff_m: float
    peb_m: float
    observable: bool
    ranges_only: bool


def _peb(J: np.ndarray) -> float:
    """√tr J⁻¹ (m) of one 3 × 3 information, inf where it is singular."""
    ev = np.linalg.eigvalsh(J)
    return float(np.sqrt(np.sum(1.0 / ev))) if ev[0] > 0.0 else float("inf")


@dataclass
class OpenLoop:
    """What one run's comparison found, call by call."""

    key: str
    #: max over the batch of |x_compiled − x_numpy| per call, m.
    max_diff_m: list[float] = field(default_factory=list)
    #: (call, trial, drone) → the departure, where |Δx| exceeds TOL_M.
    departures: dict[tuple[int, int, int], Departure] = field(default_factory=dict)
    #: (call, trial, drone) where the memories' cells differ.
    memory_flips: set[tuple[int, int, int]] = field(default_factory=set)
    #: (call, field, trial, drone) where a discrete output differs.
    flag_mismatches: list[tuple[int, str, int, int]] = field(default_factory=list)
    #: (call, trial, drone, relative difference) of the information beyond INFO_RTOL.
    information: list[tuple[int, int, int, float]] = field(default_factory=list)
    #: (call, trial, drone, difference) of the score statistic beyond its tolerance.
    consistency: list[tuple[int, int, int, float]] = field(default_factory=list)
    #: max over the batch of the planned next positions' difference per step, m.
    plan_diff_m: list[float] = field(default_factory=list)
    #: (step, trial, drone) → |Δp|, m, where the planned next positions differ by more than TOL_M.
    plan_departures: dict[tuple[int, int, int], float] = field(default_factory=dict)
    #: (step, decision, trial, drone, ...) where a discrete decision of the planning step differs.
    plan_mismatches: list[tuple[Any, ...]] = field(default_factory=list)
    max_info_rel: float = 0.0
    max_consistency: float = 0.0
    #: the estimator's re-check period (EstimatorConfig.recheck_every), calls.
    recheck_every: int = 0
    numpy_s: float = 0.0
    compiled_s: float = 0.0


class _Twin:
    """Stands in for :mod:`planner.estimator` in the simulator during one run: each call
    updates the compiled state it is given and its own numpy state on the same records,
    compares them, and returns the compiled one (numpy's, packed, after a departure)."""

    Measurements = cest.Measurements

    def __init__(self, config: cest.EstimatorConfig, batch_shape: tuple[int, ...], out: OpenLoop) -> None:
        self.numpy_config = nest.EstimatorConfig(**{f.name: getattr(config, f.name) for f in dataclasses.fields(nest.EstimatorConfig)})
        self.numpy = nest.initial_state(batch_shape, self.numpy_config)
        self.out = out
        self.call = 0

    def update(
        self,
        state: cest.EstimatorState,
        measurements: cest.Measurements,
        channel: Channel,
        config: cest.EstimatorConfig,
        components: tuple[SensingComponent, ...],
        overwrite: bool = False,
    ) -> cest.EstimatorState:
        t0 = time.perf_counter()
        compiled = cest.update(state, measurements, channel, config, components, overwrite=overwrite)
        t1 = time.perf_counter()
        # The same records (numpy's Measurements has the same fields as the compiled one's).
        self.numpy = nest.update(self.numpy, cast(Any, measurements), channel, self.numpy_config, components)
        self.out.compiled_s += t1 - t0
        self.out.numpy_s += time.perf_counter() - t1
        departed = self._compare(compiled, self.numpy)
        self.call += 1
        return compiled_state(self.numpy) if departed else compiled

    def _compare(self, c: cest.EstimatorState, n: Any) -> bool:
        """Record the differences of call ``self.call``; True where the call departed."""
        out, k = self.out, self.call
        diff = np.linalg.norm(c.estimate_m - n.estimate_m, axis=-1)
        out.max_diff_m.append(float(diff.max()))
        for m, i in np.argwhere(diff > TOL_M):
            out.departures[(k, int(m), int(i))] = Departure(
                float(diff[m, i]), _peb(n.information[m, i]), bool(n.observable[m, i]), not bool(n.angles_used[m, i])
            )
        for name in FLAGS:
            for m, i in np.argwhere(np.asarray(getattr(c, name)) != np.asarray(getattr(n, name))):
                out.flag_mismatches.append((k, name, int(m), int(i)))
        cm, nm = c.range_memory, n.range_memory
        cells_differ = ((cm.weight >= _EMPTY) != (nm.weight >= _EMPTY)).any(-1) | (
            np.abs(cm.weight - nm.weight) > 1e-9 * np.maximum(nm.weight, 1.0)
        ).any(-1)
        for m, i in np.argwhere(cells_differ):
            out.memory_flips.add((k, int(m), int(i)))
        # Where the estimates agree, so do the information and the score statistic (where they
        # depart, both are evaluated at estimates that differ by the departure).
        agree = diff <= TOL_M
        scale = np.abs(n.information).max(axis=(-2, -1))
        rel = np.where(agree, np.abs(c.information - n.information).max(axis=(-2, -1)) / np.where(scale > 0.0, scale, 1.0), 0.0)
        out.max_info_rel = max(out.max_info_rel, float(rel.max()))
        for m, i in np.argwhere(rel > INFO_RTOL):
            out.information.append((k, int(m), int(i), float(rel[m, i])))
        dc = np.where(agree, np.abs(c.consistency - n.consistency), 0.0)
        out.max_consistency = max(out.max_consistency, float((dc / (1.0 + np.abs(n.consistency))).max()))
        for m, i in np.argwhere(dc > CONSISTENCY_RTOL * (1.0 + np.abs(n.consistency))):
            out.consistency.append((k, int(m), int(i), float(dc[m, i])))
        return bool((diff > TOL_M).any() or cells_differ.any())


class _NumpyPlanner:
    """The planning step of commit 48f7e03's simulator (``missions/simulator.py`` ``_plan``
    there), on the vendored numpy planner: what each drone carried from one step to the next
    then (its last step, its peers' drift, loitering, its last keep-out)."""

    def __init__(self, sim: _Simulation) -> None:
        M, N = sim.pos.shape[:2]
        self.sim = sim
        self.prev_step = np.zeros((M, N, 3))
        self.drift = nplan.PeerDrift.empty((M, N, N))
        self.loitering: np.ndarray | None = None
        self.last_keepout: tuple[np.ndarray, np.ndarray] | None = None
        self.eye = np.broadcast_to(np.eye(N, dtype=bool), (M, N, N))

    def plan(self, k: int, view: Any) -> Any:
        """Step k of every drone from ``view`` (the simulator's delayed view) and the
        simulator's estimator state; returns the numpy planner's PlanResult."""
        sim = self.sim
        lo = max(0, k - nplan.OWN_RANGE_WINDOW + 1)
        own = nplan.own_ranges(np.moveaxis(sim.rec_range[lo : k + 1], 0, -1), np.moveaxis(sim.rec_los[lo : k + 1], 0, -1), sim.channel)
        self.drift = self.drift.update(view.positions_m, view.saved, view.have)
        ages = np.where(view.have, k - view.saved, 0)
        plan_view = nplan.PlanView(self.eye, view.positions_m, view.have, view.los, ages, view.hops, self.drift.drift_m)
        M, N = sim.pos.shape[:2]
        own_then = sim.positions[np.maximum(view.saved, 0), np.arange(M)[:, None, None], np.arange(N)[None, :, None]]
        planned = nplan.plan(
            sim.config,
            sim.pos,
            self.prev_step,
            plan_view,
            sim.state,
            sim.ctrl_u[k],
            step_index=k,
            oracle_slow=sim.spec.mission.source_is_slow(),
            own_ranges=own,
            loitering=self.loitering,
            last_keepout=self.last_keepout,
            lost_contact=view.cut,
            own_then_m=None if view.cut is None else own_then,
        )
        # Copies: the keep-out centre is a view of the estimate, which the compiled estimator's
        # next update overwrites in place (the simulator's overwrite=True).
        self.prev_step = np.array(planned.step.displacement)
        self.loitering = np.array(planned.loiter)
        self.last_keepout = (np.array(planned.keepout_centre_m), np.array(planned.keepout_m))
        return planned


def _compare_plans(out: OpenLoop, k: int, step: Any, loiter: np.ndarray, theirs: Any) -> None:
    """Record how step k's planned steps differ (next positions, m; discrete decisions)."""
    ts = theirs.step
    diff = np.linalg.norm(step.next_position - ts.next_position, axis=-1)
    out.plan_diff_m.append(float(diff.max()))
    for m, i in np.argwhere(diff > TOL_M):
        out.plan_departures[(k, int(m), int(i))] = float(diff[m, i])
    for name, a, b in (
        ("singular", step.singular, ts.singular),
        ("filtered", step.filtered, ts.filtered),
        ("loiter", loiter, theirs.loiter),
        ("active", step.active, ts.active),
    ):
        for idx in np.argwhere(np.asarray(a) != np.asarray(b)):
            out.plan_mismatches.append((k, name, *(int(v) for v in idx)))


def open_loop(key: str, positions_m: np.ndarray) -> OpenLoop:
    """Run the reference run ``key`` open loop on the recorded trajectory ``positions_m``
    (K+1, M, N, 3), both estimators and both planning steps side by side (module doc); the
    drones go where the recording has them, whatever they planned."""
    name, crit, fault = key.rsplit("_", 2)
    criterion = cast(Criterion, crit)
    sim = _Simulation(RunSpec(paper_mission(name, **FAULTS[fault]), criterion, TRIALS, STEPS), None, False, False, SENSING)
    out = OpenLoop(key, recheck_every=sim.estimator_config.recheck_every)
    twin = _Twin(sim.estimator_config, sim.pos.shape[:2], out)
    numpy_planner = _NumpyPlanner(sim)
    module = simulator.est
    simulator.est = twin  # type: ignore[assignment]
    try:
        for k in range(STEPS):
            src = sim.sources[k]
            sim._record(k, src)
            view = sim._delayed_view(k)
            sim._estimate(k, src, view)
            step = sim._plan(k, src, view)
            theirs = numpy_planner.plan(k, view)
            _compare_plans(out, k, step, sim.loiter[k], theirs)
            sim.pos = positions_m[k + 1].copy()
            sim.positions[k + 1] = positions_m[k + 1]
    finally:
        simulator.est = module
    assert twin.call == STEPS
    return out


@pytest.fixture(scope="module")
def reference() -> dict[str, np.ndarray]:
    with np.load(REFERENCE) as data:
        return {key: data[key] for key in data.files if key.endswith("/positions_m")}


#: The default run's half of the grid: every mission, A with faults and D without (the other
#: half is marked slow: ``pytest -m slow tests/simulator/test_open_loop_vs_numpy.py``).
DEFAULT_RUNS = tuple(key for key in run_names() if key.endswith(("_A_faults", "_D_nofault")))


@pinned  # DEPARTURES and the bounds were measured with the suite's pinned numerics
@pytest.mark.parametrize("key", [key if key in DEFAULT_RUNS else pytest.param(key, marks=pytest.mark.slow) for key in run_names()])
def test_the_compiled_core_is_numpys_call_by_call(reference: dict[str, np.ndarray], key: str) -> None:
    found = open_loop(key, reference[f"{key}/positions_m"])
    assert found.flag_mismatches == [], f"{key}: discrete outputs differ (call, field, trial, drone): {found.flag_mismatches[:10]}"
    assert found.memory_flips == MEMORY_FLIPS.get(key, set()), (
        f"{key}: range memory cells differ at (call, trial, drone) {sorted(found.memory_flips)}"
    )
    calls, count, largest = DEPARTURES.get(key, ((), 0, TOL_M))
    departed = {c: f"{d.diff_m:.2e} m" for c, d in found.departures.items() if c[0] not in calls}
    assert not departed, f"{key}: estimates depart by > {TOL_M} m at unlisted calls (call, trial, drone): {departed}"
    assert len(found.departures) <= count, f"{key}: {len(found.departures)} departures, {count} measured"
    assert max(found.max_diff_m) <= largest, f"{key}: estimates depart by {max(found.max_diff_m):.2e} m, at most {largest:.1e} measured"
    every = found.recheck_every
    assert every > 0
    for (k, m, i), d in found.departures.items():
        assert d.ranges_only, f"{key}: call {k}, trial {m}, drone {i} departs by {d.diff_m:.2e} m with angles used"
        if k % every == every - 1:  # a re-check call
            assert d.diff_m <= RECHECK_M, f"{key}: re-check call {k}, trial {m}, drone {i}: |Δx| {d.diff_m:.2e} m"
        else:
            assert d.diff_m <= ILL_CONDITIONED_PER_PEB * d.peb_m, f"{key}: call {k}, trial {m}, drone {i}: |Δx| {d.diff_m:.2e} m, PEB {d.peb_m:.2e} m"
    assert found.information == [], f"{key}: information beyond rtol {INFO_RTOL} at (call, trial, drone, rel): {found.information[:10]}"
    assert found.consistency == [], f"{key}: score statistic beyond its tolerance at (call, trial, drone, |Δ|): {found.consistency[:10]}"
    # Not vacuous: numpy's estimator ran every call and produced estimates the compiled one met.
    assert len(found.max_diff_m) == STEPS
    # The planning step of the same run: at every step the compiled planner.agent.plan and
    # 48f7e03's numpy plan (each its own carried state; the same view and estimator state)
    # plan within 1e-9 m with the same decisions.
    assert len(found.plan_diff_m) == STEPS
    worst = max(found.plan_diff_m)
    assert not found.plan_departures, (
        f"{key}: planned positions differ by up to {worst:.2e} m at (step, trial, drone) {sorted(found.plan_departures)[:10]}"
    )
    assert found.plan_mismatches == [], f"{key}: decisions differ (step, decision, trial, drone[, family]): {found.plan_mismatches[:10]}"


def test_production_code_never_imports_the_test_references() -> None:
    """The vendored numpy estimator is the tests' alone: no module of the packages imports
    ``tests`` (an AST scan of every import statement, function-level ones included)."""
    found = _imports_of_tests(ROOT)
    assert found == [], found


def test_the_scan_finds_an_import_of_the_references(tmp_path: Path) -> None:
    (tmp_path / "planner").mkdir()
    (tmp_path / "planner" / "m.py").write_text("def f():\n    from tests.reference_numpy import estimator\n")
    assert _imports_of_tests(tmp_path) == ["planner/m.py: tests.reference_numpy"]


def _imports_of_tests(root: Path) -> list[str]:
    """``path: module`` of every import of ``tests`` in the packages under ``root``."""
    found = []
    for package in ("planner", "comms", "vehicle_sim", "missions"):
        for path in sorted((root / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                names = [a.name for a in node.names] if isinstance(node, ast.Import) else []
                if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                    names = [node.module]
                found += [f"{path.relative_to(root).as_posix()}: {n}" for n in names if n.split(".")[0] == "tests"]
    return found


def _measure() -> None:
    """Print, per run, what the comparison finds (the source of DEPARTURES and the docs' table)."""
    with np.load(REFERENCE) as data:
        keys = sys.argv[1:] or run_names()
        for key in keys:
            found = open_loop(key, data[f"{key}/positions_m"])
            print(
                f"{key:26s} max|Δx| {max(found.max_diff_m):.1e} m, departures {len(found.departures)}, "
                f"memory flips {sorted(found.memory_flips)}, flags {len(found.flag_mismatches)}, info rel {found.max_info_rel:.1e}, score {found.max_consistency:.1e}, "
                f"numpy {found.numpy_s:.2f} s, compiled {found.compiled_s:.2f} s; plan max|Δp| {max(found.plan_diff_m):.1e} m, "
                f"departures {len(found.plan_departures)}, decisions {found.plan_mismatches[:5]}"
            )
            for c, d in sorted(found.departures.items()):
                print(f"    {c}: {d.diff_m:.2e} m, PEB {d.peb_m:.2e} m, observable {d.observable}, ranges only {d.ranges_only}")


if __name__ == "__main__":
    _measure()
