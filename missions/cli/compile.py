"""``fimnav compile``: compile fimnav's kernels now, not at the first use.

After an install (or an upgrade), the first command that plans, estimates or simulates compiles
the kernels into extension modules built ahead of time (:mod:`planner.aot`; about a minute on
two cores); every later command loads them at once. ``fimnav compile`` pays that once, at a time
of the user's choosing: in a container image's build, on each node of a cluster before its Dask
workers start, or on a drone's companion computer before it goes to the field, so that the
first ``fimnav launch`` or ``fimnav plan`` starts at once. It builds the planning, estimator and
simulator groups (each in a child process of its own, up to ``--jobs`` at once:
:func:`planner.warm.compile_aside`), tries again a group whose build failed before, then runs a
planning step, an estimator update and a two-step study of a shipped mission with and without
injected faults; it says for each group whether it was built or found, and why a group that
cannot be built here is numba's JIT's (into numba's cache, as with ``FIMNAV_AOT=0``).
"""

from __future__ import annotations

import argparse
import time
from typing import Any


def register(subparsers: Any) -> None:
    """Add the ``compile`` subcommand."""
    p = subparsers.add_parser(
        "compile",
        help="compile the planning, estimation and simulator kernels now (else done by the first command that needs them)",
        description=(
            "Compile fimnav's kernels, once after an install or an upgrade, so that the first "
            "launch, planner or study starts at once: the planning, estimator and simulator groups, "
            "each built ahead of time into an extension module in a child process of its own "
            "(FIMNAV_AOT=0: into numba's cache by its JIT). Groups already built are only loaded."
        ),
    )
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        metavar="N",
        help="processes compiling at once (default: the cores this process may use; 1: one group after the other)",
    )
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Build (or find) every kernel group and print one line per group."""
    from comms.errors import UsageError
    from planner import aot
    from planner.warm import available_cores

    jobs = available_cores() if args.jobs is None else args.jobs
    if jobs < 1:
        raise UsageError(f"--jobs: expected a whole number of at least 1, found {jobs}")
    t0 = time.monotonic()
    if aot.enabled():
        for group in aot.failed():  # a new attempt: a C compiler may have been installed since
            aot.forget_failure(group)
    _compile(jobs)
    print(f"every kernel is compiled: {time.monotonic() - t0:.1f} s in all", flush=True)
    return 0


def _compile(jobs: int) -> None:
    """Compile what is missing on up to ``jobs`` processes, load everything, and print one line
    per group: built ahead of time (or found), or, where that is off or impossible, compiled
    by numba's JIT into its cache (or found there)."""
    from missions.runtime.signals import signals_deferred
    from planner import aot, sim_kernels
    from planner.warm import compile_aside, group_names, in_cache, missing_groups, warm_estimator, warm_planning

    t0 = time.monotonic()
    missing = missing_groups()
    aside = compile_aside(jobs)  # a wait a signal may end (the children are killed)
    if aside:
        print(f"compiled the {group_names(aside)} kernels in {len(aside)} processes, up to {jobs} at once: {time.monotonic() - t0:.1f} s", flush=True)
    failed = aot.failed() if aot.enabled() else {}
    for group, why in failed.items():
        print(f"{group} kernels: {why}; numba's JIT compiles them instead, into its cache", flush=True)
    jit = [g for g in aot.GROUPS if not aot.enabled() or g in failed]
    with signals_deferred():  # a signal inside numba's compiler would end it with a traceback
        for group, load in (("planning", warm_planning), ("estimator", warm_estimator), ("simulator", _simulate_two_steps)):
            t = time.monotonic()
            cached = group != "simulator" or in_cache(aot.jit_kernel(sim_kernels.line_of_sight))
            load()
            if group in aside:
                continue
            if group not in jit:
                done = f"already built ({aot.path(group).parent}), loaded"
            elif group in missing or not cached:
                done = "compiled by numba's JIT"
            else:
                done = "already in numba's cache, loaded"
            print(f"{group} kernels: {done}: {time.monotonic() - t:.1f} s", flush=True)


def _simulate_two_steps() -> None:
    """Two steps of one trial of paper/heterogeneous, without and with injected faults: the
    in-process simulator's kernels (:mod:`planner.sim_kernels`) with a study's argument types."""
    from missions.format.loader import load_mission
    from missions.study.simulator import RunSpec, simulate

    for sets in ({}, {"comms.faults.loss": 0.2, "comms.faults.extra_delay_steps": 1}):
        simulate(RunSpec(load_mission("paper/heterogeneous", sets), "A", 1, 2))
