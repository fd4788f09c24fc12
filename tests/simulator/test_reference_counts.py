"""The kernels compiled without numba's reference counting (``_nrt=False``: the planning
kernels' inner functions, most of the estimator's) borrow their array arguments from their
callers. A mistake there (such a function handing an array back to a counted caller, or
keeping one a counted callee returned) would leak every array of a call or free one still in
use. numba's own allocation statistics count every array the compiled code allocates and
frees: a simulation run a second time must leave exactly as many alive as the first.

Runs the JIT kernels (the default test run, ``FIMNAV_AOT=0``): numba's statistics do not
see the modules built ahead of time, so under ``FIMNAV_AOT=1`` the test says so and skips.
"""

from __future__ import annotations

import gc
import os
import subprocess
import sys
from pathlib import Path

import pytest
from numba.core.registry import CPUDispatcher
from numba.core.runtime import _nrt_python, rtsys

import planner.kernels
from missions.study.simulator import RunSpec, simulate
from planner.estimator.kernels import update
from tests.simulator.conftest import paper_mission

ROOT = Path(__file__).resolve().parents[2]


def _alive() -> tuple[int, int]:
    """(allocations, meminfos) the compiled code made and has not freed."""
    s = rtsys.get_allocation_stats()
    return s.alloc - s.free, s.mi_alloc - s.mi_free


@pytest.mark.parametrize("name", ["ranging_los", "joint"])
def test_a_simulation_run_twice_leaves_no_compiled_array_behind(name: str) -> None:
    if not (isinstance(planner.kernels.plan_batch, CPUDispatcher) and isinstance(update.update_batch, CPUDispatcher)):
        pytest.skip("the kernels are the ones built ahead of time (FIMNAV_AOT=1): numba's allocation statistics do not see them")
    spec = RunSpec(paper_mission(name), "A", 2, 40)
    _nrt_python.memsys_enable_stats()
    try:
        simulate(spec)  # every kernel compiled or loaded, every first-call cache filled
        gc.collect()
        before, made = _alive(), rtsys.get_allocation_stats().mi_alloc
        result = simulate(spec)
        del result
        gc.collect()
        after = _alive()
        # The run allocated through numba (the check can see a leak) and left nothing of it.
        assert rtsys.get_allocation_stats().mi_alloc - made > 1000
        assert after == before
    finally:
        _nrt_python.memsys_disable_stats()


_RETURN_TYPES = r"""
import importlib, os, sys
from numba.core import types
from numba.core.registry import CPUDispatcher
from missions.study.simulator import RunSpec, simulate
from tests.simulator.conftest import paper_mission

for name in ("ranging_los", "joint", "heterogeneous", "bearing"):
    simulate(RunSpec(paper_mission(name), "A", 2, 30))
    simulate(RunSpec(paper_mission(name), "D", 1, 10))

def has_array(t):
    return isinstance(t, types.Array) or (isinstance(t, types.BaseTuple) and any(has_array(x) for x in t.types))

checked = 0
for m in ("planner.kernels", "planner.estimator.kernels.update", "planner.estimator.kernels.memory",
          "planner.estimator.kernels.robust", "planner.estimator.kernels.pseudolinear", "planner.estimator.kernels.linalg"):
    for n, obj in vars(importlib.import_module(m)).items():
        if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == m and obj.targetoptions.get("_nrt") is False:
            for cr in obj.overloads.values():
                checked += 1
                if has_array(cr.signature.return_type):
                    print("returns an array:", m, n, cr.signature.return_type)
print("checked", checked)
"""


@pytest.mark.slow
def test_no_kernel_compiled_without_counting_returns_an_array(tmp_path: Path) -> None:
    """Every inner kernel compiled without reference counting, as four paper missions compile
    them (numba's cache empty, so that each is compiled here and its types are known), returns
    no array: one it returned would be counted by its caller and not by itself."""
    env = dict(os.environ, FIMNAV_AOT="0", NUMBA_CACHE_DIR=str(tmp_path / "cache"), PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", _RETURN_TYPES], cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert not [line for line in lines if line.startswith("returns an array")], lines
    assert int(lines[-1].split()[1]) > 100  # the compiled overloads were seen
