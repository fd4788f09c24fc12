"""``fimnav launch`` runs for the end-to-end tests: the launcher in its own session, its processes
found by the results path they mention, and what a run writes read back."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.support.proc import Proc, fimnav

ROOT = Path(__file__).resolve().parents[2]
PAPER = ROOT / "missions" / "paper"


def _live_processes_where(read: str, matches: Callable[[bytes], bool]) -> list[int]:
    """PIDs of live (not zombie) processes but this one whose /proc/PID/``read`` ``matches``."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit() or int(entry.name) == os.getpid():
            continue
        try:
            content = (entry / read).read_bytes()
            state = (entry / "stat").read_text().split(")")[-1].split()[0]
        except OSError:
            continue
        if matches(content) and state != "Z":
            pids.append(int(entry.name))
    return pids


def processes_mentioning(text: str) -> list[int]:
    """PIDs of live processes whose command line contains ``text`` (from /proc)."""
    return _live_processes_where("cmdline", lambda cmd: text in cmd.replace(b"\0", b" ").decode(errors="replace"))


def processes_with_environment(entry: str) -> list[int]:
    """PIDs of live processes of this user whose environment holds ``entry`` (``NAME=value``)."""
    return _live_processes_where("environ", lambda environ: entry.encode() in environ.split(b"\0"))


class Launch:
    """``fimnav launch MISSION --out OUT ARGS`` from the repository, in its own session (a
    :class:`Proc` with this process's environment); with ``--no-figures`` unless ``figures``
    (the PNG figures cost 2-3 s of CPU per launch; the tests that read them ask for them)."""

    def __init__(self, mission: Path, out: Path, *args: str, figures: bool = False) -> None:
        self._start(fimnav("launch", str(mission), "--out", str(out), *args, *(() if figures else ("--no-figures",))), out, ROOT)

    @classmethod
    def command(cls, argv: Sequence[str], out: Path, cwd: Path) -> Launch:
        """A launch run by the command ``argv`` in ``cwd`` (results in ``out``)."""
        run = cls.__new__(cls)
        run._start(argv, out, cwd)
        return run

    def _start(self, argv: Sequence[str], out: Path, cwd: Path) -> None:
        self.out = out
        self.process = Proc(argv, cwd=cwd, env=None)

    @property
    def proc(self) -> subprocess.Popen[bytes]:
        """The launcher's process."""
        return self.process.p

    def wait(self, timeout_s: float = 240.0) -> tuple[int, str, str]:
        """(exit status, stdout, stderr) once the launcher has exited and its output ended; fails
        (after killing the run) if that takes more than ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        try:
            self.proc.wait(timeout_s)
            finished = self.process.join_output(max(deadline - time.monotonic(), 0.0))
        except subprocess.TimeoutExpired:
            finished = False
        if not finished:
            self.kill()
            self.process.join_output(10.0)
            pytest.fail(f"launch did not finish within {timeout_s:g} s:\n{self.process.err[-3000:]}")
        return int(self.proc.returncode), self.process.out, self.process.err

    def kill(self) -> None:
        """SIGKILL the launcher's process group and that of every process mentioning ``out``."""
        for pid in [self.proc.pid, *processes_mentioning(str(self.out))]:
            try:
                os.killpg(pid, signal.SIGKILL)
            except (ProcessLookupError, PermissionError):
                pass


def read_trajectories(out: Path, mission: Any) -> tuple[np.ndarray, np.ndarray]:
    """(positions (K+1, N, 3), estimates (K, N, 3)) from the run's trajectories CSV."""
    path = next((out / "runs").glob("*/trajectories.csv"))
    K, N = mission.steps, mission.drones.count
    pos = np.full((K + 1, N, 3), np.nan)
    est = np.full((K, N, 3), np.nan)
    for row in csv.DictReader(path.open()):
        k, j = int(row["step"]), int(row["drone"]) - 1
        pos[k, j] = [float(row["x_m"]), float(row["y_m"]), float(row["z_m"])]
        if k < K:
            est[k, j] = [float(row["estimate_x_m"]), float(row["estimate_y_m"]), float(row["estimate_z_m"])]
    return pos, est


def read_peb(out: Path) -> np.ndarray:
    """The mean PEB (m) of every step, from the run's peb.csv."""
    path = next((out / "runs").glob("*/peb.csv"))
    return np.array([float(r["peb_mean_m"]) for r in csv.DictReader(path.open())])
