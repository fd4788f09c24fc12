"""``fimnav montecarlo --jobs N`` stopped by a signal sent to it alone (not to its process group):
Ctrl-C, SIGTERM or SIGHUP, it exits 128 + signal at once and leaves none of its worker processes
behind, nor, on a cold kernel cache, the processes compiling the kernels."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.support.proc import alive, child_pids, with_default_hangup, with_default_interrupt
from tests.support.wait import wait_for

REPO = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.integration


def _signal_while_children_run(argv: list[str], env: dict[str, str], cwd: Path, sig: signal.Signals, status: int,
                               ready: Callable[[set[int]], bool], what: str) -> str:
    """Start ``argv`` in a session of its own, wait until its children make ``ready`` true, send
    ``sig`` to the command alone (not its group), check it exits ``status`` without a traceback
    and that those children exit too; returns its stderr. Whatever happens, the session is
    killed at the end."""
    proc = subprocess.Popen(argv, cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        children: set[int] = set()

        def started() -> bool:
            nonlocal children
            assert proc.poll() is None, proc.communicate()
            children = child_pids(proc.pid)
            return ready(children)

        wait_for(started, 60.0, f"the {what} to start", interval_s=0.05)
        proc.send_signal(sig)  # to the command alone, not its group
        _, err = proc.communicate(timeout=15)
        assert proc.returncode == status, err
        assert "Traceback" not in err
        wait_for(lambda: not any(alive(c) for c in children), 5.0, f"the {what} to exit",
                 detail=lambda: f"left behind: {[c for c in children if alive(c)]}", interval_s=0.05)
        return err
    finally:
        # the whole session, even when the command itself has exited (its children may not have)
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc to find the worker processes")
@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130), (signal.SIGHUP, 129)])
def test_signal_to_montecarlo_stops_its_workers(tmp_path: Path, sig: signal.Signals, status: int) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    # Started as from a terminal (SIGINT and SIGHUP at their defaults): the suite's own process
    # may have them ignored, and the command honours an inherited ignored SIGHUP on purpose (nohup).
    argv = with_default_hangup(with_default_interrupt([sys.executable, "-m", "missions", "montecarlo", "paper/heterogeneous", "paper/joint", "--criterion", "both",
                                                       "--trials", "20", "--no-figures", "--jobs", "2", "--out", str(tmp_path / "out")]))
    _signal_while_children_run(argv, env, tmp_path, sig, status, lambda workers: len(workers) >= 2, "two workers")


#: The first compile of each kernel path, in a command's own environment (whatever the suite
#: runs on): numba's JIT into an empty cache (the planning and estimator groups in two children,
#: about 35 s), and the default, the extension modules built ahead of time into an empty
#: directory (three groups, two children at once, about a minute), as after an editable install
#: or an edit of the kernels.
FIRST_COMPILES = {
    "jit": ({"FIMNAV_AOT": "0"}, "compiling the planning and estimator kernels first"),
    "built-ahead-of-time": ({"FIMNAV_AOT": "1"}, "compiling the planning, estimator and simulator kernels first"),
}


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc to find the compiling processes")
@pytest.mark.parametrize("path", FIRST_COMPILES)
@pytest.mark.parametrize(("sig", "status"), [(signal.SIGTERM, 143), (signal.SIGINT, 130)])
def test_signal_during_the_first_compile_stops_the_compiling_children(tmp_path: Path, sig: signal.Signals, status: int, path: str) -> None:
    # Empty kernel directories: the command first compiles in two child processes
    # (planner.warm.compile_aside); a signal to the command alone meanwhile ends it at once, and
    # the children with it.
    mode, notice = FIRST_COMPILES[path]
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""), "NUMBA_CACHE_DIR": str(tmp_path / "numba"),
           "FIMNAV_AOT_DIR": str(tmp_path / "aot"), **mode}
    argv = [sys.executable, "-m", "missions", "montecarlo", "paper/joint", "--trials", "4", "--steps", "2", "--no-figures", "--jobs", "2"]
    err = _signal_while_children_run(with_default_interrupt([*argv, "--out", str(tmp_path / "out")]), env, tmp_path, sig, status,
                                     lambda compiling: len(compiling) == 2, "two compiling children")
    # The command said, before, what it was doing and how to do it ahead of time.
    assert notice in err and "fimnav compile" in err, err
    assert not (tmp_path / "out").exists() or not list((tmp_path / "out").rglob("summary.json"))
