"""Every fimnav command runs numpy's and scipy's BLAS on one thread, unless the environment
says otherwise (:mod:`missions.runtime.threads`): checked on the variables and on the threads of
a real process after a product of matrices large enough for OpenBLAS to use its pool."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from missions.runtime.threads import BLAS_THREAD_VARIABLES, one_blas_thread

ROOT = Path(__file__).resolve().parents[2]

#: fimnav's entry point on a command that loads numpy, then a 400 × 400 product (OpenBLAS splits
#: it over its pool when it has one), then the process's thread count and the variables.
SCRIPT = (
    f"VARS = {BLAS_THREAD_VARIABLES!r}\n"
    + """
import contextlib, io, json, os
from missions.cli.main import main
with contextlib.redirect_stdout(io.StringIO()):
    main(["missions", "list"])
import numpy as np
a = np.ones((400, 400))
a @ a
threads = int(next(line for line in open("/proc/self/status") if line.startswith("Threads:")).split()[1])
print(json.dumps({"threads": threads, **{k: os.environ.get(k) for k in VARS}}))
"""
)


def run_command(extra: dict[str, str]) -> dict[str, object]:
    env = {k: v for k, v in os.environ.items() if k not in BLAS_THREAD_VARIABLES}
    env.update(extra, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-c", SCRIPT], env=env, cwd=ROOT, capture_output=True, text=True, timeout=120, check=True)
    result: dict[str, object] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def test_unset_variables_become_one_and_set_ones_are_kept() -> None:
    environ = {"OMP_NUM_THREADS": "3"}
    one_blas_thread(environ)
    assert environ == {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "3", "MKL_NUM_THREADS": "1"}


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="counts threads in /proc (Linux)")
def test_a_command_runs_blas_on_one_thread_unless_told_otherwise() -> None:
    ours = run_command({})
    assert {k: ours[k] for k in BLAS_THREAD_VARIABLES} == dict.fromkeys(BLAS_THREAD_VARIABLES, "1")
    assert ours["threads"] == 1, ours  # the main thread only: no BLAS pool started
    # The user's own setting wins, and the same product then starts OpenBLAS's pool (where the
    # machine has more than one core to give it): the count above can fail.
    theirs = run_command({"OPENBLAS_NUM_THREADS": "2"})
    assert theirs["OPENBLAS_NUM_THREADS"] == "2" and theirs["OMP_NUM_THREADS"] == "1"
    if (os.cpu_count() or 1) > 1:
        assert isinstance(theirs["threads"], int) and theirs["threads"] > 1, theirs
