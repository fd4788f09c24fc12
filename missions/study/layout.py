"""The names in a results directory (:mod:`missions.study.results`): a run's directory and
legend name, and the file of a fault-free run's PEB penalty reference. Read by the results
writer and by the figures, which the writer draws."""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from missions.study.records import RunSpec, SimulationResult

#: File name of a fault-free run's :class:`missions.study.simulator.PenaltyReference` in its
#: ``runs/<run>/`` directory.
PENALTY_REFERENCE = "penalty_reference.npz"


def run_name(result: SimulationResult) -> str:
    """Directory and legend name of a run: ``<mission id>_<criterion>[_paper][_<policy>]``."""
    return spec_name(result.spec)


def spec_name(spec: RunSpec) -> str:
    """:func:`run_name` of the run of ``spec``: ``<mission id>_<criterion>``, then ``_paper``
    with the paper's activation rule and ``_<policy>`` with a baseline policy."""
    suffix = "_paper" if spec.mission.constraints.activation == "paper" else ""
    policy = spec.mission.policy
    return f"{spec.mission.id}_{spec.criterion}{suffix}" + ("" if policy == "fim" else f"_{policy}")
