"""The fork server of ``fimnav launch``: the launcher fixes a real-time start only once the
server has imported its preload, and the preload loads the compiled estimator, so planners
forked from it do not load (or, on a cold numba cache, compile) the estimator's kernels after
the start time was fixed and miss the mission's first steps (a real-time launch whose planners
all arrived after the last step reported every drone-step missing and an undefined PEB).

Each check runs in a fresh interpreter: ``multiprocessing``'s fork server is one per process.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

from missions.launch.forkspawn import PRELOAD
from tests.support.kernels import jit_only

REPO = Path(__file__).resolve().parents[2]


def run_python(code: str, *path: Path) -> subprocess.CompletedProcess[str]:
    """``code`` in a fresh interpreter with the repository (and ``path``) importable."""
    pythonpath = ":".join(str(p) for p in (*path, REPO))
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": pythonpath},
        capture_output=True,
        text=True,
        timeout=300,
    )


def test_wait_ready_returns_only_once_a_slow_preload_is_imported(tmp_path: Path) -> None:
    # A preload module that takes 2 s (as loading compiled kernels does) and then leaves a mark.
    mark = tmp_path / "imported"
    (tmp_path / "slow_preload.py").write_text(f"import time\ntime.sleep(2.0)\nopen({str(mark)!r}, 'w').close()\n")
    done = run_python(
        f"""
        import os, time
        import missions.launch.forkspawn as fs
        fs.PRELOAD = ("slow_preload",)
        server = fs.ForkServer()
        server.warm_up()
        t0 = time.monotonic()
        server.wait_ready()
        print(os.path.exists({str(mark)!r}), round(time.monotonic() - t0, 1))
        server.close()
        """,
        tmp_path,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    imported, waited = done.stdout.split()
    assert imported == "True", done.stdout
    assert float(waited) >= 1.0, done.stdout  # it did wait for the preload


@jit_only
def test_the_preload_loads_the_compiled_estimator() -> None:
    assert "planner.node.warm_estimator" in PRELOAD
    done = run_python(
        """
        from planner.estimator.kernels import update as ku
        assert not ku.update_batch.signatures
        import planner.node.warm_estimator
        print(len(ku.update_batch.signatures))
        """
    )
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout) >= 1, done.stdout


def test_a_slow_preload_is_announced_once_and_a_quick_one_not(tmp_path: Path) -> None:
    # A 2 s preload (a cold kernel cache takes a minute) against a 0.5 s notice threshold, then
    # the same server again, ready at once: one line the first time, none the second.
    (tmp_path / "slow_preload.py").write_text("import time\ntime.sleep(2.0)\n")
    done = run_python(
        """
        import missions.launch.forkspawn as fs
        fs.PRELOAD = ("slow_preload",)
        server = fs.ForkServer()
        server.warm_up()
        lines = []
        server.wait_ready(notice=lines.append, notice_after_s=0.5)
        print(len(lines))
        print(lines[0] if lines else "")
        again = []
        server.wait_ready(notice=again.append, notice_after_s=0.5)
        print(len(again))
        server.close()
        """,
        tmp_path,
    )
    assert done.returncode == 0, done.stderr[-2000:]
    first, line, second = done.stdout.splitlines()
    assert first == "1" and "compiling the planning and estimation kernels" in line and "once after an install" in line, done.stdout
    assert second == "0", done.stdout
