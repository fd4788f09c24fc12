"""Fixtures shared by the test directories: the processes a test starts (:func:`procs`) and the
launches it starts (:func:`launches`), all stopped at the end. (``MAVLINK20=1`` is set by
``tests/__init__.py``, imported before this file and before any test module.)"""

from __future__ import annotations

import os
import subprocess
import sys
from collections.abc import Iterator

import pytest

from tests.support.launch import Launch, processes_mentioning
from tests.support.proc import Proc
from tests.support.wait import wait_for

#: A two-step study with and without injected faults: loads (compiles, on a cold cache) the
#: in-process simulator's kernels (planner.sim_kernels).
WARM_SIMULATOR = """
from missions.format.loader import load_mission
from missions.study.simulator import RunSpec, simulate
for sets in ({}, {"comms.faults.loss": 0.2, "comms.faults.extra_delay_steps": 1}):
    simulate(RunSpec(load_mission("paper/heterogeneous", sets), "A", 1, 2))
"""


#: The control step as the tests call it (``planner.control.control_step`` on one drone, the
#: compiled ``control_batch``): a planner's step does not, so the planning warm-up leaves it out.
WARM_CONTROL = """
import numpy as np
from tests.planner.test_control import one_step
one_step(np.array([0.0, 0.0, 10.0]), np.array([0.5, 0.0, 0.0]), np.array([1.0, 2.0, 0.5]), peers=np.array([[3.0, 0.0, 10.0]]))
"""


#: The kernels the tests call directly (:mod:`tests.support.warm_kernels`), by group: compiled
#: in the process that has just compiled their inner functions.
WARM_TESTS_PLANNING = "import tests.support.warm_kernels as k\nk.compile_planning()"
WARM_TESTS_ESTIMATOR = "import tests.support.warm_kernels as k\nk.compile_estimator()"


def pytest_configure(config: pytest.Config) -> None:
    """Load the compiled planning, estimator and simulator kernels once, before any worker
    starts (the first run after a clean clone compiles them into numba's on-disk cache): the
    workers and every planner process a test starts then load them instead of each compiling
    them."""
    if not hasattr(config, "workerinput"):  # the controller, or a run without workers
        scripts = warm_up_scripts()
        compiling = [subprocess.Popen([sys.executable, "-c", code]) for code in scripts]
        for p, code in zip(compiling, scripts):
            if p.wait() != 0:  # its error, raised here, stops the run
                exec(code, {})


def warm_up_scripts() -> list[str]:
    """The two processes of :func:`pytest_configure`'s warm-up, run at once (the two cores
    halve the wait). On numba's JIT (the suite's default, ``FIMNAV_AOT=0``): the planning
    kernels, then the control step in the same process (it calls the planning kernels' inner
    functions, which a process links only where it compiled them itself: loaded from the cache,
    they would be compiled again); and the estimator's kernels, then the simulator's (by then
    the planning kernels are in the cache). On a cold cache on this project's 2-core machine:
    57-70 s wall and 90-107 s of CPU, against 102-120 s wall and 187-214 s of CPU when the first
    process went through a planner's start (:mod:`planner.node.warm`: both groups compiled in
    children, then the control step's inner functions again) while the second compiled the
    estimator's kernels a second time. Each process then compiles the kernels of its group
    that tests call directly (:mod:`tests.support.warm_kernels`), where their inner functions
    are already compiled: on a cold cache the tests that reached them first (4-15 s of CPU
    each, compiling them again in their worker) take their warm time, for 7-41 s more CPU
    in the warm-up (``benchmarks/bench_suite.py`` times it and whole cold runs). On the kernels built ahead of time (``FIMNAV_AOT=1``): a
    planner's start (which builds the missing extension modules) and the estimator's."""
    from planner import aot

    if aot.enabled():
        planning, estimator = "import planner.node.warm", "import planner.node.warm_estimator"
    else:
        planning, estimator = "import planner.warm as w\nw.warm_planning()", "import planner.warm as w\nw.warm_estimator()"
    return [f"{planning}\n{WARM_CONTROL}\n{WARM_TESTS_PLANNING}", f"{estimator}\n{WARM_SIMULATOR}\n{WARM_TESTS_ESTIMATOR}"]


def pytest_xdist_auto_num_workers(config: pytest.Config) -> int | None:
    """``-n auto`` (pyproject.toml's addopts): one worker per core plus one, as about a third of
    the suite waits on real time (real-time launches, vehicles' clocks): on two cores, two
    workers kept the cores 68 % busy and the run took 300 s, three took 238 s with every test
    passing. No workers with ``-s`` (a worker's output would not be shown) or when the run selects
    the ``sitl`` marker (real autopilots run one at a time, as their figures were measured).
    ``-n 0`` turns the workers off for any run."""
    if config.getoption("capture") == "no" or "sitl" in (config.getoption("markexpr") or ""):
        return 0
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return cores + 1


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    """Every process a test starts; each process group is stopped at the end."""
    started: list[Proc] = []
    yield started
    for p in reversed(started):
        p.stop()


@pytest.fixture
def launches() -> Iterator[list[Launch]]:
    """Started launches; at the end every process of every run must be gone (then killed)."""
    started: list[Launch] = []
    yield started
    leftovers = {}
    for run in started:
        if run.proc.poll() is None:
            run.kill()
            run.proc.wait(10)
        try:
            wait_for(lambda r=run: not processes_mentioning(str(r.out)), 15.0, f"the processes of {run.out} to exit")
        except AssertionError:
            leftovers[str(run.out)] = processes_mentioning(str(run.out))
            run.kill()
    assert not leftovers, f"processes left behind: {leftovers}"
