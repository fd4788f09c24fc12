"""A results directory that cannot be made or written is one clear line naming it and exit 2,
for every command that writes one (``fimnav montecarlo``, ``fimnav launch``), never a
traceback: as a user meets it (a directory /proc will not hold, a file in the way, a file
where a parent should be, a full disk). The suite runs as root, for whom a chmod'ed directory
is still writable: these cases fail for root too."""

from __future__ import annotations

import json
import os
import platform
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from comms.errors import UsageError
from missions.runtime.rundir import make_results_dir, writing
from missions.study.results import write_results
from missions.study.simulator import RunSpec, simulate
from tests.simulator.conftest import paper_mission
from tests.support.launch import PAPER, Launch

REPO = Path(__file__).resolve().parents[2]


def fimnav(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run([sys.executable, "-m", "missions", *args], capture_output=True, text=True, timeout=120, cwd=cwd, env=env)


def one_error_line(proc: subprocess.CompletedProcess[str], command: str) -> str:
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith(f"fimnav {command}: error: results directory "), proc.stderr
    return lines[0]


@pytest.fixture
def a_file(tmp_path: Path) -> Path:
    path = tmp_path / "a_file"
    path.write_text("not a directory\n")
    return path


@pytest.mark.parametrize("command", ["montecarlo", "launch"])
def test_an_unmakeable_out_is_one_line(tmp_path: Path, a_file: Path, command: str) -> None:
    size = ["--trials", "1", "--steps", "2"] if command == "montecarlo" else ["--steps", "2"]
    cases = {
        "/proc/fimnav-results": "cannot make it: No such file or directory in /proc",
        str(a_file / "run"): f"cannot make it: {a_file} is a file, not a directory",
        str(a_file): "expected a directory, found a file",
    }
    for out, why in cases.items():
        line = one_error_line(fimnav(command, "paper/joint", *size, "--out", out, cwd=tmp_path), command)
        assert f"results directory {out}: {why}" in line, line
    assert a_file.read_text() == "not a directory\n"  # nothing lost


@pytest.mark.parametrize("command", ["montecarlo", "launch"])
def test_the_default_results_directory_under_a_file_is_one_line(tmp_path: Path, command: str) -> None:
    """Without --out the command makes ``results/...`` in the working directory: a file named
    ``results`` there is in the way."""
    (tmp_path / "results").write_text("")
    size = ["--trials", "1", "--steps", "2"] if command == "montecarlo" else ["--steps", "2"]
    line = one_error_line(fimnav(command, "paper/joint", *size, cwd=tmp_path), command)
    assert "results is a file, not a directory" in line or "expected a directory, found a file" in line, line


def test_a_full_disk_while_writing_is_one_line(tmp_path: Path) -> None:
    """/dev/full takes the summary: ENOSPC on write, as on a full disk."""
    if not Path("/dev/full").exists():
        pytest.skip("needs /dev/full (Linux) to stand for a full disk")
    out = tmp_path / "out"
    out.mkdir()
    (out / "summary.json").symlink_to("/dev/full")
    result = simulate(RunSpec(paper_mission("joint"), "A", 1, 2))
    with pytest.raises(UsageError, match=r"results directory .*out: cannot write.*: No space left on device; choose another --out"):
        write_results([result], out, figures=False)


def test_make_results_dir_makes_parents_and_checks_writing(tmp_path: Path) -> None:
    out = make_results_dir(tmp_path / "a" / "b")
    assert out.is_dir() and list(out.iterdir()) == []  # the probe file is gone
    assert make_results_dir(out) == out  # an existing directory is fine
    with pytest.raises(UsageError, match=r"cannot write \(.*x\): Read-only file system"):
        with writing(tmp_path):
            raise OSError(30, "Read-only file system", str(tmp_path / "x"))


@pytest.mark.integration
def test_a_launch_has_one_summary_writer(tmp_path: Path, launches: list[Launch]) -> None:
    """``fimnav launch`` writes its summary through the results writer, once: the top-level
    summary.json has the version fields of every results directory, and its run is the run's
    own summary.json, launch fields included."""
    out = tmp_path / "run"
    run = Launch(PAPER / "joint.yaml", out, "--steps", "2", "--set", "drones.count=2")
    launches.append(run)
    code, _, stderr = run.wait(120.0)
    assert code == 0, stderr[-3000:]
    doc = json.loads((out / "summary.json").read_text())
    assert doc["python"] == platform.python_version() and doc["numpy"] == np.__version__
    assert doc["command"][:2] == ["fimnav", "launch"]
    (summary,) = doc["runs"]
    assert json.loads((out / "runs" / summary["run"] / "summary.json").read_text()) == summary
    assert summary["distributed"] is True and summary["clock"] == "lockstep" and summary["failures"] == []
