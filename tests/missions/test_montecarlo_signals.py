"""``fimnav montecarlo --jobs N`` stopped by a signal sent to it alone (not to its process group):
Ctrl-C, SIGTERM or SIGHUP, it exits 128 + signal at once and leaves none of its worker processes
behind, nor, on a cold kernel cache, the processes compiling the kernels."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.proc import alive, child_pids, with_default_hangup, with_default_interrupt
from tests.support.wait import wait_for

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.integration


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc to find the worker processes")
@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130), (signal.SIGHUP, 129)])
def test_signal_to_montecarlo_stops_its_workers(tmp_path: Path, sig: signal.Signals, status: int) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    # Started as from a terminal (SIGINT and SIGHUP at their defaults): the suite's own process
    # may have them ignored, and the command honours an inherited ignored SIGHUP on purpose (nohup).
    proc = subprocess.Popen(
        with_default_hangup(with_default_interrupt([sys.executable, "-m", "missions", "montecarlo", "paper/heterogeneous", "paper/joint", "--criterion", "both",
                                "--trials", "20", "--no-figures", "--jobs", "2", "--out", str(tmp_path / "out")])),
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        workers: set[int] = set()

        def started() -> bool:
            nonlocal workers
            assert proc.poll() is None, proc.communicate()
            workers = child_pids(proc.pid)
            return len(workers) >= 2

        wait_for(started, 60.0, "the two workers to start", interval_s=0.05)
        proc.send_signal(sig)  # to the command alone, not its group
        _, err = proc.communicate(timeout=15)
        assert proc.returncode == status, err
        assert "Traceback" not in err
        wait_for(lambda: not any(alive(w) for w in workers), 5.0, "the workers to exit",
                 detail=lambda: f"workers left behind: {[w for w in workers if alive(w)]}", interval_s=0.05)
    finally:
        # the whole session, even when the command itself has exited (its workers may not have)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc to find the compiling processes")
@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_during_the_first_compile_stops_the_compiling_children(tmp_path: Path, sig: signal.Signals, status: int) -> None:
    # A cold kernel cache (an empty NUMBA_CACHE_DIR): the command first compiles the planning and
    # estimator kernels in two child processes (planner.warm, about 35 s); a signal to the command
    # alone meanwhile ends it at once, and the children with it.
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    argv = [sys.executable, "-m", "missions", "montecarlo", "paper/joint", "--trials", "4", "--steps", "2", "--no-figures", "--jobs", "2"]
    proc = subprocess.Popen(
        with_default_interrupt([*argv, "--out", str(tmp_path / "out")]),
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True,
    )
    try:
        compiling: set[int] = set()

        def started() -> bool:
            nonlocal compiling
            assert proc.poll() is None, proc.communicate()
            compiling = child_pids(proc.pid)
            return len(compiling) == 2

        wait_for(started, 60.0, "the two compiling children to start", interval_s=0.05)
        proc.send_signal(sig)  # to the command alone, not its group
        _, err = proc.communicate(timeout=15)
        assert proc.returncode == status, err
        assert "Traceback" not in err
        # The command said, before, what it was doing and how to do it ahead of time.
        assert "compiling the planning and estimator kernels into numba's cache first" in err and "fimnav compile" in err, err
        wait_for(lambda: not any(alive(c) for c in compiling), 5.0, "the compiling children to exit",
                 detail=lambda: f"left behind: {[c for c in compiling if alive(c)]}", interval_s=0.05)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
