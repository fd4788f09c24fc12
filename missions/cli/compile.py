"""``fimnav compile``: compile fimnav's kernels into numba's cache now, not at the first use.

After an install (or an upgrade), the first command that plans, estimates or simulates compiles
the kernels it needs into numba's on-disk cache (about 35 s on two cores); every later command
loads them in about a second. ``fimnav compile`` pays that once, at a time of the user's
choosing: in a container image's build, on each node of a cluster before its Dask workers
start, or on a drone's companion computer before it goes to the field, so that the first
``fimnav launch`` or ``fimnav plan`` starts at once. It compiles the planning and the estimator
kernels (each group in a child process of its own, at once, when both are missing and
``--jobs`` allows: :func:`planner.warm.compile_aside`), then the in-process simulator's, with
a two-step study of a shipped mission with and without injected faults; it says for each group
whether it was compiled or already in the cache.
"""

from __future__ import annotations

import argparse
import time
from typing import Any


def register(subparsers: Any) -> None:
    """Add the ``compile`` subcommand."""
    p = subparsers.add_parser(
        "compile",
        help="compile the planning, estimation and simulator kernels into numba's cache now (else done by the first command that needs them)",
        description=(
            "Compile fimnav's kernels into numba's on-disk cache, once after an install or an "
            "upgrade, so that the first launch, planner or study starts at once: the planning and "
            "estimator kernels (a child process each, at once, on two cores or more), then the "
            "in-process simulator's. Kernels already in the cache are only loaded."
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
    """Compile (or load) every kernel group and print one line per group."""
    from comms.errors import UsageError
    from missions.runtime.signals import signals_deferred
    from planner import sim_kernels
    from planner.warm import available_cores, compile_aside, in_cache, missing_groups, warm_estimator, warm_planning

    jobs = available_cores() if args.jobs is None else args.jobs
    if jobs < 1:
        raise UsageError(f"--jobs: expected a whole number of at least 1, found {jobs}")
    t0 = time.monotonic()
    missing = missing_groups()
    aside = compile_aside(jobs)  # a wait a signal may end (the children are killed)
    if aside:
        print(f"compiled the {' and '.join(aside)} kernels at once in {len(aside)} processes: {time.monotonic() - t0:.1f} s", flush=True)
    with signals_deferred():  # a signal inside numba's compiler would end it with a traceback
        for group, load in (("planning", warm_planning), ("estimator", warm_estimator)):
            t = time.monotonic()
            load()
            if group not in aside:
                done = "compiled" if group in missing else "already in numba's cache, loaded"
                print(f"{group} kernels: {done}: {time.monotonic() - t:.1f} s", flush=True)
        t = time.monotonic()
        cached = in_cache(sim_kernels.line_of_sight)
        _simulate_two_steps()
    done = "already in numba's cache, loaded" if cached else "compiled"
    print(f"simulator kernels: {done}: {time.monotonic() - t:.1f} s", flush=True)
    print(f"every kernel is in numba's cache: {time.monotonic() - t0:.1f} s in all", flush=True)
    return 0


def _simulate_two_steps() -> None:
    """Two steps of one trial of paper/heterogeneous, without and with injected faults: the
    in-process simulator's kernels (:mod:`planner.sim_kernels`) with a study's argument types."""
    from missions.format.loader import load_mission
    from missions.study.simulator import RunSpec, simulate

    for sets in ({}, {"comms.faults.loss": 0.2, "comms.faults.extra_delay_steps": 1}):
        simulate(RunSpec(load_mission("paper/heterogeneous", sets), "A", 1, 2))
