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


def pytest_configure(config: pytest.Config) -> None:
    """Load the compiled planning, estimator and simulator kernels once, before any worker
    starts (the first run after a clean clone compiles them into numba's on-disk cache): the
    workers and every planner process a test starts then load them instead of each compiling
    them."""
    if not hasattr(config, "workerinput"):  # the controller, or a run without workers
        # Two processes at once (on a cold cache about 30 s of CPU each: the two cores halve
        # the wait): the planning kernels and the control step; the estimator's, then the simulator's (by then the
        # planning kernels are in the cache).
        warm = ("planner.node.warm", "planner.node.warm_estimator")
        scripts = [f"import {warm[0]}\n{WARM_CONTROL}", f"import {warm[1]}\n{WARM_SIMULATOR}"]
        compiling = [subprocess.Popen([sys.executable, "-c", code]) for code in scripts]
        for p, code in zip(compiling, scripts):
            if p.wait() != 0:  # its error, raised here, stops the run
                exec(code, {})


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
