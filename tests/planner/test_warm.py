"""planner.warm: numba's cache told empty from full, the two kernel groups compiled at once in
child processes on a cold cache, and no child left behind whatever stops the caller.

The cold caches are empty temporary directories (``NUMBA_CACHE_DIR``), in fresh interpreters
(numba reads that variable when it is imported)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from planner.warm import compile_aside, in_cache
from tests.support.proc import alive, child_pids, with_default_interrupt
from tests.support.wait import wait_for

ROOT = Path(__file__).resolve().parents[2]


def python(code: str, cache: Path, **kw: object) -> subprocess.Popen[str]:
    """``code`` in a fresh interpreter with its own numba cache, started as from a terminal:
    SIGINT at its default action (Python's KeyboardInterrupt) even where the suite runs with it
    ignored (a background job, a pytest-xdist worker)."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(cache), PYTHONPATH=str(ROOT))
    argv = with_default_interrupt([sys.executable, "-c", textwrap.dedent(code)])
    return subprocess.Popen(argv, env=env, text=True, stdout=subprocess.PIPE, stderr=subprocess.PIPE, **kw)


def test_in_cache_tells_an_empty_cache_a_compiled_kernel_and_a_changed_source(tmp_path: Path) -> None:
    module = tmp_path / "src" / "tiny_kernel.py"
    module.parent.mkdir()
    module.write_text("from numba import njit\n\n@njit(cache=True)\ndef add_one(x):\n    return x + 1\n")
    code = f"""
        import os, sys
        sys.path.insert(0, {str(module.parent)!r})
        from planner.warm import in_cache
        import tiny_kernel
        print(in_cache(tiny_kernel.add_one))
        tiny_kernel.add_one(1.0)
        print(in_cache(tiny_kernel.add_one))
        """
    p = python(code, tmp_path / "cache")
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    assert out.split() == ["False", "True"]
    # The cache's entry belongs to the source it was compiled from: a changed file is uncompiled.
    module.write_text(module.read_text() + "\n# changed\n")
    stamp = module.stat().st_mtime + 10
    os.utime(module, (stamp, stamp))
    p = python(code, tmp_path / "cache")
    out, err = p.communicate(timeout=120)
    assert p.returncode == 0, err
    assert out.split() == ["False", "True"]


def test_in_cache_of_what_is_not_a_numba_kernel_is_true() -> None:
    assert in_cache(len) is True
    assert in_cache(lambda x: x) is True


def test_compile_aside_on_one_core_starts_nothing() -> None:
    assert compile_aside(1) == []
    assert compile_aside(0) == []


@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM, signal.SIGKILL], ids=["SIGINT", "SIGTERM", "SIGKILL"])
def test_a_caller_stopped_while_compiling_leaves_no_child(tmp_path: Path, signum: int) -> None:
    # SIGINT: KeyboardInterrupt, whose way out kills the children; SIGTERM (default action) and
    # SIGKILL end the caller at once: each child sees its stdin close and ends itself.
    p = python("from planner.warm import compile_aside\ncompile_aside(2)\n", tmp_path / "cache", start_new_session=True)
    children: set[int] = set()
    try:
        wait_for(lambda: len(child_pids(p.pid)) == 2, 60, "the two compiling children")
        children = child_pids(p.pid)
        p.send_signal(signum)
        p.wait(timeout=30)
        wait_for(lambda: not any(alive(c) for c in children), 30, "the compiling children to end")
    finally:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
            p.wait()
        for c in children:
            if alive(c):
                os.kill(c, signal.SIGKILL)


@pytest.mark.slow
def test_a_cold_cache_is_compiled_a_group_per_child_then_loaded(tmp_path: Path) -> None:
    # About 40 s on two cores: the two groups at once, then the caller loads both from the cache.
    code = """
        import time
        from planner.warm import compile_aside, missing_groups, warm_estimator, warm_planning
        print(missing_groups())
        print(compile_aside(2))
        print(missing_groups())
        t = time.process_time()
        warm_planning()
        warm_estimator()
        print(time.process_time() - t)
        """
    p = python(code, tmp_path / "cache")
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err
    lines = out.splitlines()
    assert lines[:3] == ["['planning', 'estimator']", "['planning', 'estimator']", "[]"]
    assert float(lines[3]) < 10.0  # a load from the cache, not a compile (30-40 s of CPU a group)


@pytest.mark.slow
def test_two_callers_on_one_cold_cache_compile_it_once(tmp_path: Path) -> None:
    # Two commands (or two Dask workers of one node) starting at once on a cold cache: one
    # compiles the two groups aside, the other waits for it and compiles nothing (about 40 s).
    code = "from planner.warm import compile_aside\nprint(compile_aside(2))\n"
    callers = [python(code, tmp_path / "cache") for _ in range(2)]
    peak = 0

    def both_done() -> bool:
        nonlocal peak
        peak = max(peak, sum(len(child_pids(c.pid)) for c in callers))
        return all(c.poll() is not None for c in callers)

    try:
        wait_for(both_done, 600, "both callers to finish", interval_s=0.05)
        outs = sorted(c.communicate()[0].strip() for c in callers)
        assert [c.returncode for c in callers] == [0, 0]
        assert outs == ["['planning', 'estimator']", "[]"]
        assert peak == 2  # never four compiling children
    finally:
        for c in callers:
            if c.poll() is None:
                c.kill()
                c.wait()
