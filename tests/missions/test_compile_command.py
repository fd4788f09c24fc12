"""``fimnav compile``: every kernel group compiled afterwards (in numba's cache, or built ahead
of time), each group reported as compiled or loaded, a bad --jobs refused in one line. The cold
cache is an empty temporary directory (``NUMBA_CACHE_DIR``); the warm cache and the built modules
are the suite's (tests/conftest.py fills the one its run uses)."""

from __future__ import annotations

import os
import re
import subprocess
from pathlib import Path

import pytest

from planner import aot
from tests.support.proc import fimnav

ROOT = Path(__file__).resolve().parents[2]


def run(*args: str, cache: Path | None = None) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    if cache is not None:
        env["NUMBA_CACHE_DIR"] = str(cache)
    return subprocess.run(fimnav("compile", *args), env=env, text=True, capture_output=True, timeout=600)


def test_with_every_group_compiled_each_is_loaded_not_compiled() -> None:
    # The suite's warm-up compiled them: into numba's cache (the default run), or built ahead
    # of time (FIMNAV_AOT=1).
    loaded = r"already built \(.+\), loaded" if aot.enabled() else r"already in numba's cache, loaded"
    done = run()
    assert done.returncode == 0, done.stderr
    lines = done.stdout.splitlines()
    for group in ("planning", "estimator", "simulator"):
        assert re.search(rf"^{group} kernels: {loaded}: [0-9.]+ s$", done.stdout, re.M), done.stdout
    assert lines[-1].startswith("every kernel is compiled: ")


@pytest.mark.parametrize("jobs", ["0", "-3"])
def test_a_bad_jobs_is_refused_in_one_line(jobs: str) -> None:
    done = run("--jobs", jobs)
    assert done.returncode == 2
    assert done.stderr.strip().splitlines() == [f"fimnav compile: error: --jobs: expected a whole number of at least 1, found {jobs}"]
    assert done.stdout == ""


@pytest.mark.slow
def test_on_a_cold_cache_the_groups_compile_at_once_then_a_second_run_loads_them(tmp_path: Path) -> None:
    # About 40 s on two cores.
    first = run("--jobs", "2", cache=tmp_path / "cache")
    assert first.returncode == 0, first.stderr
    assert first.stdout.startswith("compiled the planning and estimator kernels in 2 processes, up to 2 at once: ")
    assert "simulator kernels: compiled by numba's JIT: " in first.stdout
    second = run(cache=tmp_path / "cache")
    assert second.returncode == 0, second.stderr
    for group in ("planning", "estimator", "simulator"):
        assert f"{group} kernels: already in numba's cache, loaded: " in second.stdout, second.stdout


def test_a_study_on_a_warm_cache_says_nothing_of_compiling(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    argv = fimnav("montecarlo", "paper/joint", "--trials", "1", "--steps", "1", "--no-figures", "--out", str(tmp_path / "out"))
    done = subprocess.run(argv, env=env, text=True, capture_output=True, timeout=300)
    assert done.returncode == 0, done.stderr
    assert "compiling" not in done.stderr, done.stderr
