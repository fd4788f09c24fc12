"""The recorded reference of the in-process simulator: reduced runs of every paper mission,
A and D, with and without faults, recorded on the compiled core (the planning kernels of
planner/kernels.py and the estimator's of planner/estimator/kernels/). A structural change of
the code must replan every recorded step within 1e-9 m (``test_bit_identity.py``,
:func:`replay`). The equality of the compiled estimator and planning step with the numpy
code they replaced (commit 48f7e03) is guarded open loop on these recorded trajectories, call by call
(``test_open_loop_vs_numpy.py``).

    python -m tests.simulator.reference_runs      # rewrite tests/data/simulator_reference.npz

It records with the suite's pinned numerics (``tests/__init__.py``, :mod:`missions.runtime.numerics`:
numba's ``haswell`` target, OpenBLAS's Haswell kernels, numpy without AVX-512), which every
x86-64 machine with AVX2 and FMA runs the same way; the ranging runs' steps would part by metres
on another configuration.

Rewrite the reference only for a change that is meant to change the planner's behaviour, and
say so in that commit; then measure the open-loop comparison again on the new trajectories
(``python -m tests.simulator.test_open_loop_vs_numpy`` prints what its table lists).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from missions.study.simulator import RunSpec, SimulationResult, _Simulation, simulate
from planner.sensing import SENSING
from tests.simulator.conftest import paper_mission

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "simulator_reference.npz"

PAPER_NAMES = ("ranging_los", "ranging_nlos", "dynamic_source", "bearing", "joint", "heterogeneous")
#: Fault settings of the reference (name, dotted-key overrides): none, and loss with delay and
#: a partition together, so the fault buffers, late records and the partition rule are covered.
FAULTS: dict[str, dict[str, object]] = {
    "nofault": {},
    "faults": {
        "comms.faults.loss": 0.2,
        "comms.faults.extra_delay_steps": 2,
        "comms.faults.partition_start_step": 10,
        "comms.faults.partition_steps": 15,
    },
}
TRIALS = 2
STEPS = 40


def run_names() -> list[str]:
    """``<mission>_<A|D>_<fault setting>`` of every reference run."""
    return [f"{name}_{crit}_{fault}" for name in PAPER_NAMES for crit in ("A", "D") for fault in FAULTS]


def run(key: str) -> SimulationResult:
    """Simulate the reference run named ``key`` (see :func:`run_names`)."""
    name, crit, fault = key.rsplit("_", 2)
    return simulate(RunSpec(paper_mission(name, **FAULTS[fault]), crit, TRIALS, STEPS))


def replay(key: str, positions_m: np.ndarray) -> tuple[np.ndarray, SimulationResult]:
    """Simulate the reference run ``key`` on the recorded trajectory ``positions_m`` (K+1, M, N,
    3): at each step k every drone measures, hears, estimates and plans from where the reference
    has it, and the position its step reaches is compared with the reference's at k + 1 before
    the drones are put there. Returns the one-step errors (K, M, N), m, and the run's result (its
    PEB and estimates along the reference trajectory). The free-running simulation cannot follow
    a recording made with other floating-point operations: drones held at a constraint's
    boundary activate it or not by rounding, and the early ranging estimates amplify a 1e-14 m
    change of a position to 1e-9 m in one step."""
    name, crit, fault = key.rsplit("_", 2)
    sim = _Simulation(RunSpec(paper_mission(name, **FAULTS[fault]), crit, TRIALS, STEPS), None, False, False, SENSING)
    errors = np.empty((STEPS,) + positions_m.shape[1:-1])
    for k in range(STEPS):
        sim.step(k, None)
        errors[k] = np.linalg.norm(sim.positions[k + 1] - positions_m[k + 1], axis=-1)
        sim.pos = positions_m[k + 1].copy()
        sim.positions[k + 1] = positions_m[k + 1]
    return errors, sim.result(0.0)


def arrays(result: SimulationResult) -> dict[str, np.ndarray]:
    """What the reference keeps of a run: every position, the last estimates and the PEB curve."""
    return {"positions_m": result.positions_m, "last_estimates_m": result.estimates_m[-1], "peb_m": result.peb_m}


def main() -> None:
    data = {f"{key}/{field}": value for key in run_names() for field, value in arrays(run(key)).items()}
    REFERENCE.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(REFERENCE, **data)
    print(f"wrote {REFERENCE} ({REFERENCE.stat().st_size / 1e3:.0f} kB, {len(run_names())} runs)")


if __name__ == "__main__":
    main()
