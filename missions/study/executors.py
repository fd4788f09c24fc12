"""Where a study's chunks of trials are simulated: the executor seam of :func:`missions.study.montecarlo.run_study`.

A run of M trials is cut into chunks of consecutive trials (:func:`chunk_bounds`, from M alone:
never from the number of workers), and a chunk is the unit of work: :func:`simulate_chunk`
simulates one, in whatever process the executor gives it. Every draw of trial m is seeded by
(seed, m, drone) (:mod:`planner.randomness`), so a chunk simulates its trials as the whole run
would, and the study merges the chunks of a run into one result
(:func:`missions.study.montecarlo.merge_chunks`): the same for any executor and any number of
workers.

An executor is anything with :meth:`ChunkExecutor.map`; two are here: :class:`InProcess`
(one after the other, in this process) and :class:`LocalPool` (worker processes on this
machine). Another (a cluster's) plugs in behind the same method.
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import AbstractContextManager
from dataclasses import dataclass
from typing import TYPE_CHECKING, Protocol

from missions.runtime.allocator import keep_freed_memory
from missions.runtime.signals import signals_deferred, worker_defaults
from planner.warm import available_cores, compile_aside, missing_groups, warm_estimator, warm_planning

if TYPE_CHECKING:  # the simulator (and its compiled kernels) is imported where a chunk runs
    from missions.study.records import RunSpec, SimulationResult
    from missions.study.simulator import SimStep

#: Fewest trials in a chunk: the simulator steps a chunk's trials together, one numpy call for
#: all of them, so a short chunk costs more per trial (paper/joint, 100 trials × 60 steps, one
#: process: chunks of 50 trials 0.95 × the time of one chunk of 100, of 25 1.11 ×, of 10 1.96 ×).
MIN_CHUNK_TRIALS: int = 50
#: Most chunks a run is cut into: two workers share a run of 100 trials or more.
MAX_CHUNKS: int = 4
#: A local pool runs ahead of the chunk whose result is due by at most this many chunks per
#: worker (:class:`LocalPool`): the results of chunks that end early wait in memory for theirs.
AHEAD_PER_WORKER: int = 3

#: What :func:`simulate_chunk` calls for the chunk holding a run's first trial when the study is
#: watched live: given the run, a context that yields the per-step observer
#: (:class:`missions.study.simulator.SimStep`; it sees that chunk's first trial as trial 0).
#: It runs in the executor's process, so it must be picklable (a module-level function or a
#: ``functools.partial`` of one).
Watch = Callable[["RunSpec"], AbstractContextManager[Callable[["SimStep"], None]]]


def chunk_bounds(trials: int, min_trials: int = MIN_CHUNK_TRIALS, max_chunks: int = MAX_CHUNKS) -> list[tuple[int, int]]:
    """``(first, count)`` of each chunk of a run of ``trials`` trials, counted from the run's
    first trial: as many chunks of consecutive trials as hold ``min_trials`` each, one at least
    and ``max_chunks`` at most, sizes differing by one at most, the larger first. Depends on
    the run alone (never on the number of workers)."""
    if min_trials < 1 or max_chunks < 1:
        raise ValueError(f"chunk_bounds: expected min_trials and max_chunks >= 1, found {min_trials}, {max_chunks}")
    n = max(1, min(int(max_chunks), int(trials) // int(min_trials)))
    size, rest = divmod(int(trials), n)
    bounds = []
    first = 0
    for c in range(n):
        count = size + (1 if c < rest else 0)
        bounds.append((first, count))
        first += count
    return bounds


@dataclass(frozen=True)
class Chunk:
    """One unit of work: trials ``spec.first_trial`` … ``+ spec.trials − 1`` of a run.

    Attributes:
        spec: the run's spec restricted to the chunk's trials.
        oracle_estimate: plan with the true source (:func:`missions.study.simulator.simulate`).
        watch: the live view of the chunk (its first trial), or None.
    """

    spec: RunSpec
    oracle_estimate: bool = False
    watch: Watch | None = None

    @property
    def trial_steps(self) -> int:
        """Trials × steps of the chunk: its share of the study's progress."""
        return self.spec.trials * self.spec.steps


def simulate_chunk(chunk: Chunk, progress: Callable[[int], object] | None = None) -> SimulationResult:
    """Simulate one chunk (in any process); ``progress(n)``: n more trial-steps done."""
    from missions.study.simulator import simulate

    trials = chunk.spec.trials

    def step_progress(steps: int) -> None:
        if progress is not None:
            progress(steps * trials)

    if chunk.watch is None:
        return simulate(chunk.spec, progress=step_progress, oracle_estimate=chunk.oracle_estimate)
    with chunk.watch(chunk.spec) as observer:
        return simulate(chunk.spec, progress=step_progress, oracle_estimate=chunk.oracle_estimate, observer=observer)


class ChunkExecutor(Protocol):
    """Simulates chunks somewhere: the seam between a study and the machines it runs on."""

    def map(self, chunks: Sequence[Chunk], progress: Callable[[int], object] | None = None) -> Iterator[SimulationResult]:
        """:func:`simulate_chunk` of every chunk, yielded in the order of ``chunks``;
        ``progress(n)``: n more trial-steps done (as often as the executor can tell).
        Leaving the iteration early (an error, a signal) stops the work still running."""
        ...


class InProcess:
    """Every chunk in this process, one after the other (progress at every step)."""

    def map(self, chunks: Sequence[Chunk], progress: Callable[[int], object] | None = None) -> Iterator[SimulationResult]:
        """See :meth:`ChunkExecutor.map`. On a cold cache the planning and estimator kernels
        are first compiled in child processes, a group each, at once, on the cores this
        process may use (once after an install; :func:`planner.warm.compile_aside`)."""
        if chunks:
            compile_aside(available_cores())
        for chunk in chunks:
            yield simulate_chunk(chunk, progress)


@dataclass(frozen=True)
class LocalPool:
    """Chunks in ``workers`` processes on this machine (``multiprocessing``, forked), a chunk at a
    time each; progress when a chunk is done."""

    workers: int

    def map(self, chunks: Sequence[Chunk], progress: Callable[[int], object] | None = None) -> Iterator[SimulationResult]:
        """See :meth:`ChunkExecutor.map`."""
        if not chunks:
            return
        # A ProcessPoolExecutor kept fed: workers + 1 chunks not yet done (a worker that ends a
        # chunk finds the next one queued), whichever chunk ended, so a long chunk at the head
        # holds up no worker; the results are yielded in the order of ``chunks``, those ending
        # early kept until their turn, at most AHEAD_PER_WORKER × workers chunks submitted and
        # not yet yielded (the memory they hold). Leaving early (an error, a signal, Ctrl-C)
        # kills the workers at once and then shuts the executor down: its manager thread sees
        # them gone and ends. (multiprocessing.Pool's terminate could wait forever on its task
        # queue's lock, held by an idle worker blocked reading the queue.)
        # The workers are forked at the first submit, with Ctrl-C, SIGTERM and SIGHUP held back
        # (signals_deferred): interrupted while it forks, the command would lose the signal
        # (raised in a fork hook, where Python ignores it) or leave behind a worker it had not
        # yet recorded. A signal held back is raised when the deferral ends.
        workers = min(self.workers, len(chunks))
        futures: dict[int, Future[SimulationResult]] = {}
        submitted = yielded = 0
        pool: ProcessPoolExecutor | None = None
        done = False

        def feed(pool: ProcessPoolExecutor) -> None:
            nonlocal submitted
            while (
                submitted < len(chunks)
                and submitted - yielded < AHEAD_PER_WORKER * workers
                and sum(not f.done() for f in futures.values()) < workers + 1
            ):
                futures[submitted] = pool.submit(simulate_chunk, chunks[submitted])
                submitted += 1

        # The planning and estimator kernels are loaded here, before the fork, so the workers
        # inherit them rather than each loading them (or, on a cold cache, each compiling them
        # all): missing ones are first compiled in child processes, a group each, at once, on
        # the cores this process may use (planner.warm). The wait for those can be interrupted
        # (the children are killed). The load from the cache is not (a signal inside numba
        # would end it with a traceback); a group still missing (one core) is left to the
        # workers, whose compile a signal does end.
        compile_aside(available_cores())
        if not missing_groups():
            with signals_deferred():
                warm_planning()
                warm_estimator()
        try:
            with signals_deferred():
                pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"), initializer=worker_defaults)
                futures[0] = pool.submit(simulate_chunk, chunks[0])
                submitted = 1
            while yielded < len(chunks):
                feed(pool)
                head = futures[yielded]
                if not head.done():
                    wait([f for f in futures.values() if not f.done()], return_when=FIRST_COMPLETED)
                    continue
                result = head.result()
                del futures[yielded]
                yielded += 1
                feed(pool)
                if progress is not None:
                    progress(chunks[yielded - 1].trial_steps)
                yield result
            done = True
        finally:
            if pool is not None:
                if not done:  # (shutdown's cancel_futures cancels the chunks not started)
                    # No public way to stop running workers before Python 3.14 (kill_workers).
                    for process in list((getattr(pool, "_processes", None) or {}).values()):
                        process.kill()
                pool.shutdown(wait=True, cancel_futures=True)


def local_executor(workers: int) -> ChunkExecutor:
    """:class:`InProcess` for one worker, else a :class:`LocalPool` of ``workers``. This process
    (and the pool's workers, forked from it) keeps the memory it frees for the next step's
    arrays (:func:`missions.runtime.allocator.keep_freed_memory`)."""
    keep_freed_memory()
    return InProcess() if workers <= 1 else LocalPool(workers)
