"""A Monte Carlo study as a library call: the runs of one or several missions, simulated in
chunks of trials on an executor, merged, with their fault penalties and, if asked, the optimum.

    specs = expand_runs(["paper/joint", "paper/heterogeneous"], criterion="both", trials=20)
    study = run_study(specs, workers=2)
    write_results(study.results, out, penalties=study.penalties, extras=study.extras)

``fimnav montecarlo`` is this and a table; ``docs/regenerate.py`` calls it directly. A run's
trials are cut into chunks by their number alone (:func:`missions.study.executors.chunk_bounds`)
and the chunks of a run are merged in trial order (:func:`merge_chunks`), so a study's results
are the same, bit for bit, on one worker or many, in this process or in a pool. Without
injected comms faults they are also those of :func:`missions.study.simulator.simulate` over
the whole run (trial m depends on (seed, m, drone) only); with them some batched sums run over
arrays of the chunk's shape (see :class:`missions.study.simulator.RunSpec`), so the chunking
sets the rounding there.
"""

from __future__ import annotations

import dataclasses
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np

from missions.format.loader import load_mission
from missions.study.executors import MAX_CHUNKS, MIN_CHUNK_TRIALS, Chunk, ChunkExecutor, Watch, chunk_bounds, local_executor
from missions.study.records import PenaltyReference, RunSpec, SimulationResult, fault_penalty_against, without_faults
from missions.study.results import PENALTY_REFERENCE, ResultsWriter, spec_name
from planner.params import Criterion

#: Fields of :class:`SimulationResult` with the trial axis second (step axis first).
TRIAL_AXIS_FIELDS: tuple[str, ...] = (
    "positions_m",
    "estimates_m",
    "estimate_error_m",
    "observable",
    "peb_m",
    "singular_fallback",
    "filtered",
    "loiter",
    "record_ages",
)


def expand_runs(
    missions: Sequence[str | os.PathLike[str]],
    overrides: Mapping[str, Any] | None = None,
    criterion: Literal["A", "D", "both"] | None = None,
    activation: Literal["safe", "paper", "both"] | None = None,
    trials: int | None = None,
    steps: int | None = None,
    policies: Sequence[str] | None = None,
) -> list[RunSpec]:
    """The runs of a study: every mission (a file or a shipped mission's name) × activation
    rule × criterion × policy, in that order, with ``overrides`` (``--set``) applied.

    Args:
        missions: mission files or names (``paper/joint``).
        overrides: dotted key → value, as ``fimnav montecarlo --set`` gives them.
        criterion: "A", "D", "both", or None for each mission's own.
        activation: constraint activation rule "safe", "paper", "both", or None for the mission's.
        trials, steps: M and K of every run; None: each mission's.
        policies: navigation policies (:data:`planner.policies.POLICIES`), or None for each
            mission's.

    Raises:
        UsageError: a mission or an override is invalid (one message naming it).
    """
    specs: list[RunSpec] = []
    activations = ("safe", "paper") if activation == "both" else (activation,)
    for path in missions:
        for rule in activations:
            ov = dict(overrides or {})
            if rule is not None:
                ov["constraints.activation"] = rule
            mission = load_mission(path, ov)
            criteria: tuple[Criterion, ...] = ("A", "D") if criterion == "both" else (criterion or mission.criterion,)
            for crit in criteria:
                for policy in policies or (mission.policy,):
                    changes = {"criterion": crit, "policy": policy}
                    same = crit == mission.criterion and policy == mission.policy
                    m = mission if same else load_mission(path, {**ov, **changes})
                    specs.append(RunSpec(m, crit, trials or m.trials, steps or m.steps))
    return specs


@dataclass(frozen=True)
class Study:
    """What :func:`run_study` returns, one entry per run in the order of the specs.

    Attributes:
        results: every run's :class:`SimulationResult` (all its trials).
        penalties: a run with injected comms faults: its PEB penalty against the same run
            without them (:func:`missions.study.simulator.fault_penalty`); else None.
        extras: with ``optimum``: ``{"optimum": ..., "final_peb_over_optimum": ...}``
            (:func:`missions.study.optimum.run_optimum_summary`); else None.
    """

    results: list[SimulationResult]
    penalties: list[dict[str, float | None] | None]
    extras: list[dict[str, Any] | None]


def run_study(
    specs: Sequence[RunSpec],
    *,
    oracle_estimate: bool = False,
    baselines: Path | None = None,
    optimum: bool = False,
    workers: int = 1,
    executor: ChunkExecutor | None = None,
    chunk_trials: int = MIN_CHUNK_TRIALS,
    max_chunks: int = MAX_CHUNKS,
    progress: Callable[[int], object] | None = None,
    watch: Watch | None = None,
    warn: Callable[[str], None] | None = None,
) -> Study:
    """Run every spec's trials in chunks on ``executor`` and merge them; the runs with injected
    faults are compared with the same runs without them (simulated with the others, or read
    from ``baselines``).

    Args:
        specs: the runs (:func:`expand_runs`).
        oracle_estimate: plan with the true source (the paper's assumption).
        baselines: a results directory of the same runs without faults: a baseline found there
            (same mission, criterion, trials, steps, flags) is read, not simulated.
        optimum: add the optimal placement's PEB to each run (``extras``).
        workers: processes on this machine (:func:`missions.study.executors.local_executor`)
            when no ``executor`` is given.
        executor: where the chunks run (:class:`missions.study.executors.ChunkExecutor`).
        chunk_trials, max_chunks: the fewest trials in a chunk and the most chunks of a run
            (:func:`missions.study.executors.chunk_bounds`); with injected faults they set the
            batches, and so the rounding, of a run's trials.
        progress: called with the number of trial-steps just done (all runs and baselines:
            ``sum(trials × steps)`` in all, see :func:`study_size`).
        watch: the live view of each run's first trial (not of the baselines).
        warn: told why a baseline is simulated although ``baselines`` was given.

    Returns:
        The :class:`Study`: the results, the same whatever the executor and number of workers.
    """
    runs = list(
        _finished_runs(
            specs,
            optimum,
            oracle_estimate=oracle_estimate,
            baselines=baselines,
            workers=workers,
            executor=executor,
            chunk_trials=chunk_trials,
            max_chunks=max_chunks,
            progress=progress,
            watch=watch,
            warn=warn,
        )
    )
    return Study([done.result for done, _ in runs], [done.penalty for done, _ in runs], [extra for _, extra in runs])


def _finished_runs(specs: Sequence[RunSpec], optimum: bool, **study: Any) -> Iterator[tuple[RunDone, dict[str, Any] | None]]:
    """:func:`iter_study`'s runs (``study``: its keyword arguments), each with its optimum's
    summary (``optimum``; else None), checked to come in the order of ``specs``, all of them."""
    placements: dict[str, Any] = {}  # one optimum per mission whatever its policy
    count = 0
    for done in iter_study(specs, **study):
        if done.index != count:  # iter_study yields the runs in the order of the specs
            raise RuntimeError(f"run {done.index} of the study came before run {count}")
        count += 1
        extra = None
        if optimum:
            from missions.study.optimum import run_optimum_summary

            extra = run_optimum_summary(done.result, known=placements)
        yield done, extra
    if count != len(specs):
        raise RuntimeError(f"the executor returned {count} of {len(specs)} runs")


def write_study(
    specs: Sequence[RunSpec],
    out: Path,
    *,
    command: Sequence[str] = (),
    figures: bool = True,
    optimum: bool = False,
    oracle_estimate: bool = False,
    baselines: Path | None = None,
    executor: ChunkExecutor | None = None,
    chunk_trials: int = MIN_CHUNK_TRIALS,
    max_chunks: int = MAX_CHUNKS,
    progress: Callable[[int], object] | None = None,
    watch: Watch | None = None,
    warn: Callable[[str], None] | None = None,
) -> list[dict[str, Any]]:
    """:func:`run_study` written into results directory ``out`` run by run (``fimnav
    montecarlo``): each run's directory as soon as the run is done
    (:class:`missions.study.results.ResultsWriter`), so the study holds one run in memory (and
    what its figures read of the others), not all of them; then ``summary.json`` and the
    figures. The same files as :func:`missions.study.results.write_results` of the study.
    Arguments as :func:`run_study`; returns the runs' summaries."""
    writer = ResultsWriter(out, command, figures)
    for done, extra in _finished_runs(
        specs,
        optimum,
        oracle_estimate=oracle_estimate,
        baselines=baselines,
        executor=executor,
        chunk_trials=chunk_trials,
        max_chunks=max_chunks,
        progress=progress,
        watch=watch,
        warn=warn,
    ):
        writer.add(done.result, done.penalty, extra)
    return writer.close()


@dataclass(frozen=True)
class RunDone:
    """One run of a study, as :func:`iter_study` yields it.

    Attributes:
        index: the run's place in the specs.
        result: its :class:`SimulationResult` (all its trials, merged).
        penalty: with injected faults, its PEB penalty against the same run without them
            (:func:`missions.study.simulator.fault_penalty`); else None.
    """

    index: int
    result: SimulationResult
    penalty: dict[str, float | None] | None


def iter_study(
    specs: Sequence[RunSpec],
    *,
    oracle_estimate: bool = False,
    baselines: Path | None = None,
    workers: int = 1,
    executor: ChunkExecutor | None = None,
    chunk_trials: int = MIN_CHUNK_TRIALS,
    max_chunks: int = MAX_CHUNKS,
    progress: Callable[[int], object] | None = None,
    watch: Watch | None = None,
    warn: Callable[[str], None] | None = None,
    penalties: bool = True,
) -> Iterator[RunDone]:
    """:func:`run_study`'s runs one at a time, each as soon as its chunks (and, with injected
    faults, its fault-free baseline's) are done, in the order of ``specs``: a caller that
    writes each run away holds one run in memory, not the study (``fimnav sweep``). The chunks
    of a run's baseline follow the run's own on the executor. Arguments as :func:`run_study`;
    ``penalties=False``: no baseline is simulated or read, every penalty is None (then
    :func:`study_size` with ``penalties=False`` is the progress total). Leaving the iteration
    early stops the executor's work."""
    faulty = [i for i, s in enumerate(specs) if s.mission.comms.faults.enabled] if penalties else []
    known = {i: known_baseline(baselines, specs[i], oracle_estimate, warn) for i in faulty}
    runs: list[RunSpec] = []
    #: for each entry of ``runs``: the spec it is (index), or the baseline of which spec (−1 − index)
    role: list[int] = []
    for i, spec in enumerate(specs):
        runs.append(spec)
        role.append(i)
        if i in known and known[i] is None:
            runs.append(dataclasses.replace(spec, mission=without_faults(spec.mission)))
            role.append(-1 - i)
    chunks: list[Chunk] = []
    owner: list[int] = []
    for r, spec in enumerate(runs):
        for first, count in chunk_bounds(spec.trials, chunk_trials, max_chunks):
            part = dataclasses.replace(spec, first_trial=spec.first_trial + first, trials=count)
            chunks.append(Chunk(part, oracle_estimate, watch if first == 0 and role[r] >= 0 else None))
            owner.append(r)
    parts: list[list[SimulationResult]] = [[] for _ in runs]
    waiting: dict[int, SimulationResult] = {}  # a run with faults whose baseline is still running
    for r, result in zip(owner, (executor or local_executor(workers)).map(chunks, progress)):
        parts[r].append(result)
        if sum(p.spec.trials for p in parts[r]) < runs[r].trials:
            continue
        merged = merge_chunks(runs[r], parts[r])
        parts[r] = []
        i = role[r]
        if i >= 0 and i in known and known[i] is None:
            waiting[i] = merged
        elif i >= 0:
            reference = known.get(i)
            yield RunDone(i, merged, fault_penalty_against(merged.spec.mission, merged, reference) if reference is not None else None)
        else:
            run = waiting.pop(-1 - i)
            yield RunDone(-1 - i, run, fault_penalty_against(run.spec.mission, run, merged))


def study_size(specs: Sequence[RunSpec], baselines: Path | None = None, oracle_estimate: bool = False, penalties: bool = True) -> int:
    """Trial-steps :func:`run_study` reports through ``progress`` for ``specs``: every run's,
    and (with ``penalties``) the fault-free baseline's of each run with faults that
    ``baselines`` does not hold."""
    total = 0
    for spec in specs:
        total += spec.trials * spec.steps
        if penalties and spec.mission.comms.faults.enabled and known_baseline(baselines, spec, oracle_estimate, None) is None:
            total += spec.trials * spec.steps
    return total


def merge_chunks(spec: RunSpec, parts: Sequence[SimulationResult]) -> SimulationResult:
    """One run's result from its chunks' (consecutive trials, in trial order): the per-trial
    arrays joined along the trial axis, the counts summed, the fault loss fraction made again
    from the summed counts; ``runtime_s`` is the chunks' total (their compute time).

    Raises:
        ValueError: the chunks are not the run's trials in order, or a field of
            :class:`SimulationResult` has no merge rule here.
    """
    first = spec.first_trial
    for p in parts:
        if p.spec.first_trial != first:
            raise ValueError(f"merge_chunks: {spec.label}: expected trial {first} next, found {p.spec.first_trial}")
        first += p.spec.trials
    if first != spec.first_trial + spec.trials:
        raise ValueError(f"merge_chunks: {spec.label}: the chunks hold {first - spec.first_trial} trials, the run {spec.trials}")
    rules = {*TRIAL_AXIS_FIELDS, "spec", "source_m", "margins_m", "active", "runtime_s", "extra", "power_offset_db"}
    unknown = sorted({f.name for f in dataclasses.fields(SimulationResult)} - rules)
    if unknown:
        raise ValueError(f"merge_chunks: no rule to merge SimulationResult.{', '.join(unknown)}")
    head = parts[0]
    if len(parts) == 1:
        return dataclasses.replace(head, spec=spec)
    joined = {name: np.concatenate([getattr(p, name) for p in parts], axis=1) for name in TRIAL_AXIS_FIELDS}
    extra = dict(head.extra)
    if "fault_decided" in extra:
        lost = sum(p.extra["fault_lost"] for p in parts)
        decided = sum(p.extra["fault_decided"] for p in parts)
        extra.update(fault_lost=lost, fault_decided=decided, fault_lost_fraction=int(lost) / max(int(decided), 1))
    return dataclasses.replace(
        head,
        spec=spec,
        margins_m={name: np.concatenate([p.margins_m[name] for p in parts], axis=1) for name in head.margins_m},
        active=np.sum([p.active for p in parts], axis=0),
        runtime_s=sum(p.runtime_s for p in parts),
        power_offset_db=None
        if head.power_offset_db is None
        else np.concatenate([p.power_offset_db for p in parts if p.power_offset_db is not None], axis=1),
        extra=extra,
        **joined,
    )


def known_baseline(directory: Path | None, spec: RunSpec, oracle: bool, warn: Callable[[str], None] | None) -> PenaltyReference | None:
    """The :class:`missions.study.simulator.PenaltyReference` of ``spec`` (a run with faults) in
    the results ``directory`` (``--baselines``), or None when there is none to use there: then
    the baseline is simulated, and ``warn`` is told why."""
    if directory is None:
        return None
    path = directory / "runs" / spec_name(spec) / PENALTY_REFERENCE
    if not path.is_file():
        why = f"no {path}"
    else:
        try:
            ref = PenaltyReference.load(path)
        except ValueError as exc:
            why = str(exc)
        else:
            if ref.matches(spec, oracle):
                return ref
            why = f"{path} is another run (mission, criterion, trials, steps or flags differ)"
    if warn is not None:
        warn(f"{why}; simulating {spec.label} without faults")
    return None
