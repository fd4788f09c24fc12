"""The documented results rest on determinism: the same ``fimnav montecarlo`` command run twice
gives identical summaries (every number but the run times), whatever the number of worker
processes or BLAS threads. ``docs/regenerate.py`` regenerates the docs' tables on this promise.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "missions" / "paper"

#: Fields that measure the machine, not the result.
TIMING = {"runtime_s", "drone_steps_per_s", "baseline_runtime_s"}


def _montecarlo(out: Path, jobs: int, threads: str | None, extra: tuple[str, ...]) -> list[dict[str, Any]]:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    if threads is not None:
        env.update(OPENBLAS_NUM_THREADS=threads, OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads)
    argv = [sys.executable, "-m", "missions", "montecarlo", str(PAPER / "ranging_nlos.yaml"), str(PAPER / "heterogeneous.yaml"),
            "--trials", "2", "--steps", "40", "--criterion", "both", "--no-figures", "--jobs", str(jobs), "--out", str(out), *extra]
    proc = subprocess.run(argv, capture_output=True, text=True, timeout=240, cwd=out.parent, env=env)
    assert proc.returncode == 0, proc.stderr
    return [_without_timing(run) for run in json.loads((out / "summary.json").read_text())["runs"]]


def _without_timing(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _without_timing(v) for k, v in obj.items() if k not in TIMING}
    return obj


@pytest.mark.parametrize("extra", [pytest.param((), marks=pytest.mark.slow), ("--set", "comms.faults.loss=0.2", "--set", "comms.faults.extra_delay_steps=2")], ids=["no-faults", "faults"])
def test_same_command_twice_gives_identical_summaries(tmp_path: Path, extra: tuple[str, ...]) -> None:
    first = _montecarlo(tmp_path / "first", jobs=2, threads=None, extra=extra)
    second = _montecarlo(tmp_path / "second", jobs=1, threads="1", extra=extra)
    assert [r["run"] for r in first] == ["paper_ranging_nlos_A", "paper_ranging_nlos_D", "paper_heterogeneous_A", "paper_heterogeneous_D"]
    # not a vacuous comparison: the runs moved and differ from each other
    assert len({r["final_peb_mean_m"] for r in first}) == 4
    assert all(r["final_peb_mean_m"] < r["initial_peb_mean_m"] for r in first)
    assert first == second
