"""The recorded reference of the in-process simulator: reduced runs of every paper mission,
A and D, with and without faults. A structural change of the code must leave them
bit-identical (``test_bit_identity.py``).

    python -m tests.simulator.reference_runs      # rewrite tests/data/simulator_reference.npz

Rewrite the reference only for a change that is meant to change the planner's behaviour, and
say so in that commit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from missions.study.simulator import RunSpec, SimulationResult, simulate
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
