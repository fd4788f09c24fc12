"""Process supervision of a ``fimnav launch`` run: starting the vehicles, payloads and planners
as child processes, watching them, dealing with the ones that fail, and stopping them all.

Every child runs in its own process group; :meth:`ChildSupervisor.stop_children` stops them all
(SIGTERM, then SIGKILL after a grace period): no orphan process, no port left bound. A launcher
that dies without stopping them (SIGKILL, a crash) is noticed by every child through the
watchdog pipe it inherits (:mod:`missions.launch.forkspawn`), and each child then stops by itself.

Children run the launcher's own code: they (and the planners' fork server) get its ``sys.path``
(``PYTHONPATH``, with ``PYTHONSAFEPATH`` on Python 3.11+ so that ``-m`` and ``-c`` put no
working directory in front of it) and run in the results' ``logs`` directory, which holds no
module.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from comms.errors import FimnavError
from missions.launch.accounting import step_logs_of
from missions.launch.clock import ClockError
from missions.launch.forkspawn import LAUNCHER_FD_ENV, ForkedProcess, ForkServer, same_code_environment

log = logging.getLogger("fimnav.launch")

#: Grace period (s) between SIGTERM and SIGKILL when stopping children.
STOP_GRACE_S: float = 5.0

#: What the launcher does when a vehicle or a planner fails mid-mission (``--on-failure``):
#: ``abort`` stops the run (exit 1); ``continue`` flies on without that drone; ``restart`` also
#: restarts a failed planner (whose vehicle is alive, or flown by an external autopilot) with
#: ``fimnav plan --rejoin`` (lockstep: at the clock's next step; real time: on the step grid).
ON_FAILURE = ("continue", "abort", "restart")

#: Restarts of one drone's planner before it is given up.
MAX_RESTARTS: int = 3


class LaunchError(FimnavError):
    """The distributed run failed; the message says which part and why."""


def child_environment(base: dict[str, str] | None = None, same_interpreter: bool = True) -> dict[str, str]:
    """The environment of a ``python -m missions`` child (from ``base``, default this
    process's): unbuffered output, and this process's ``sys.path`` with no working directory in
    front of it (:func:`missions.launch.forkspawn.same_code_environment`), so that the child imports the
    very code the launcher imported (on Python 3.10 ``-m`` still puts the working directory
    first: the launcher runs its children in the run's ``logs`` directory, which holds no
    module). ``same_interpreter`` False (another Python): only no working directory in front."""
    env = dict(os.environ if base is None else base, PYTHONUNBUFFERED="1", PYTHONSAFEPATH="1")
    env.pop(LAUNCHER_FD_ENV, None)
    return same_code_environment(env) if same_interpreter else env


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    """A port on 127.0.0.1 that is free now (the OS picks it)."""
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@dataclass
class Child:
    """A started child process and its log file."""

    name: str
    proc: subprocess.Popen[bytes] | ForkedProcess
    log_path: Path

    def tail(self, lines: int = 8) -> str:
        """The last ``lines`` lines of the child's log, indented (empty if unreadable)."""
        try:
            text = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return "\n".join("    " + line for line in text[-lines:])


def vehicle_groups(ids: Sequence[int], size: int) -> list[list[int]]:
    """Consecutive ids in groups of at most ``size`` (a vehicle process hosts consecutive
    system ids)."""
    groups: list[list[int]] = []
    for i in ids:
        if groups and groups[-1][-1] == i - 1 and len(groups[-1]) < size:
            groups[-1].append(i)
        else:
            groups.append([i])
    return groups


def ready_line(path: Path, pid: int) -> dict[str, Any] | None:
    """The ``{"event": "ready", "pid": PID, ...}`` JSON line the vehicle process ``pid`` prints,
    if it has yet (a line of another process, e.g. of an earlier run, is not it)."""
    try:
        text = path.read_text(errors="replace")
    except OSError:
        return None
    for line in text.splitlines():
        if line.startswith("{") and '"ready"' in line:
            try:
                obj = json.loads(line)
            except ValueError:
                continue
            if isinstance(obj, dict) and obj.get("event") == "ready" and obj.get("pid") == pid:
                return obj
    return None


class ChildSupervisor:
    """The child processes of one run: started, watched, failures dealt with, stopped.

    Args:
        out: the results directory (children log to ``out/logs/<name>.log``).
        python: the interpreter for the children.
        on_failure: one of :data:`ON_FAILURE` (checked by the launcher).
        fork_server: start the planners from a :class:`missions.launch.forkspawn.ForkServer` (only
            with this very interpreter).
        stop: set when the run is asked to stop (a signal); waits end early on it.
        taken_over: whether drone i's last record heard was flagged taken over (a pilot flies
            it): a planner restarted then keeps the take-over in force (``--taken-over``).
    """

    def __init__(
        self,
        out: Path,
        python: str,
        on_failure: str,
        fork_server: bool,
        stop: threading.Event,
        taken_over: Callable[[int], bool] | None = None,
    ) -> None:
        self.out = out
        # Children get absolute paths: they run in the logs directory (child_environment).
        self._abs_out = out.absolute()
        self.python = python
        self.on_failure = on_failure
        self._stop = stop
        self.children: list[Child] = []
        #: Every failure seen: {"process", "drones", "step", "status", "reason", "action"}.
        self.failures: list[dict[str, Any]] = []
        self.handled: set[int] = set()  # pids of failed children already dealt with
        self.planner_args: dict[int, list[str]] = {}
        self.vehicle_child: dict[int, Child] = {}
        #: Drones flown by an external autopilot: drone id → its connection (no vehicle child).
        self.external: dict[int, str] = {}
        self._taken_over = taken_over
        self._restarts: dict[int, int] = {}
        self.step = -1  # the clock's current step (-1: pre-flight)
        self.flying = False  # the mission has started (failures are survivable from then on)
        self._spawned: set[str] = set()  # names started once (a restart appends to the log)
        self._watchdog: tuple[int, int] | None = None  # (read, write) ends of the watchdog pipe
        # Planners are forked from a fork server that imported them once (missions.launch.forkspawn),
        # unless another interpreter is asked for.
        self.forks = ForkServer(python) if fork_server and python == sys.executable else None

    @contextlib.contextmanager
    def watchdog(self) -> Iterator[None]:
        """The watchdog pipe, open while the run lasts: the launcher holds the only write end
        (os.pipe is not inherited); every child gets the read end and stops when it reads end
        of file (at the end of the block, or when the launcher dies)."""
        self._watchdog = os.pipe()
        try:
            yield
        finally:
            for fd in self._watchdog:
                os.close(fd)  # any child still there reads end of file and stops
            self._watchdog = None

    def planners(self) -> list[Child]:
        """Every planner started (a restarted one appears once per start)."""
        return [c for c in self.children if c.name.startswith("planner")]

    def spawn(self, name: str, args: Sequence[str]) -> Child:
        """Start ``python -m missions ARGS`` as ``name``: own session, output in its log (a
        restarted planner appends to the log of the one it replaces), working directory the
        logs directory, the read end of the watchdog pipe inherited."""
        log_path = self.out / "logs" / f"{name}.log"
        cwd = self._abs_out / "logs"
        first = name not in self._spawned
        self._spawned.add(name)
        watch_r = self._watchdog[0] if self._watchdog is not None else None
        if self.forks is not None and name.startswith("planner"):
            # Forked from the pre-imported fork server: a separate process all the same.
            child = Child(name, self.forks.spawn(args, log_path, launcher_fd=watch_r, truncate=first, cwd=cwd), log_path)
            self.children.append(child)
            return child
        env = child_environment(same_interpreter=self.python == sys.executable)
        if watch_r is not None:
            env[LAUNCHER_FD_ENV] = str(watch_r)
        with log_path.open("wb" if first else "ab") as fh:
            proc = subprocess.Popen(
                [self.python, "-m", "missions", *args],
                stdin=subprocess.DEVNULL,
                stdout=fh,
                stderr=subprocess.STDOUT,
                start_new_session=True,
                env=env,
                cwd=cwd,
                pass_fds=(watch_r,) if watch_r is not None else (),
            )
        child = Child(name, proc, log_path)
        self.children.append(child)
        return child

    def stop_children(self) -> None:
        """Stop the planners first (SIGTERM: each tells its vehicle the mission's ``on_stop``
        and waits for it to confirm, docs/in-the-field.md), then every other child (the
        vehicles, payloads): SIGTERM to each process group, SIGKILL to what is left after the
        grace; then end the fork server, if any, and wait for it."""
        planners = [c for c in self.children if c.name.startswith("planner")]
        others = [c for c in self.children if not c.name.startswith("planner")]
        for group in (planners, others):
            self._stop_group(group)
        # Anything left in a group (a grandchild) goes too.
        for c in self.children:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(c.proc.pid, signal.SIGKILL)
        if self.forks is not None:
            self.forks.close()

    @staticmethod
    def _stop_group(children: list[Child]) -> None:
        """SIGTERM each child's process group, then SIGKILL what is left after the grace."""
        for c in children:
            if c.proc.poll() is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(c.proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        for c in children:
            remaining = max(0.0, deadline - time.monotonic())
            try:
                c.proc.wait(remaining)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(c.proc.pid, signal.SIGKILL)
                c.proc.wait()

    def check_children(self) -> None:
        """Deal with children that ended: before the mission or with ``abort``, any failure
        ends the run; otherwise it is recorded (and a planner restarted if asked), and the run
        only fails when no planner is left.

        Raises:
            LaunchError: the run cannot go on (the message names the child and its log's tail).
        """
        for c in list(self.children):
            code = c.proc.poll()
            if code is None or c.proc.pid in self.handled:
                continue
            vehicle = c.name.startswith("vehicle")
            if code == 0 and not vehicle:
                continue  # a planner that finished its mission
            if not self.flying or self.on_failure == "abort":
                during = " during the mission" if vehicle and self.flying else ""
                raise LaunchError(f"{self.describe(c)} exited with status {code}{during}:\n{c.tail()}")
            self.handled.add(c.proc.pid)
            self._on_failure(c, code)
        planners = self.planners()
        if planners and all(c.proc.poll() not in (None, 0) for c in planners):
            raise LaunchError(f"every planner failed; last: {planners[-1].name}:\n{planners[-1].tail()}")

    def _on_failure(self, c: Child, code: int) -> None:
        """Record a failed child; restart a failed planner if asked and its vehicle lives."""
        drones = [i for i, v in self.vehicle_child.items() if v is c] if c.name.startswith("vehicle") else [int(c.name.split("_")[1])]
        reason = next((line.strip() for line in reversed(c.tail(20).splitlines()) if line.strip()), "")
        step = self.step
        if c.name.startswith("planner"):
            # The step it failed at: the one after the last it logged (the launcher may notice
            # its exit a few steps later).
            flown = [k for (k, j) in step_logs_of(self.out, drones[0])]
            step = max(flown) + 1 if flown else step
        entry: dict[str, Any] = {
            "process": c.name,
            "drones": drones,
            "step": step,
            "status": code,
            "reason": reason[-300:],
            "action": "continued without it",
        }
        if c.name.startswith("planner"):
            i = drones[0]
            if i in self.external:
                entry["connection"] = self.external[i]
            vehicle = self.vehicle_child.get(i)
            # (an external autopilot has no process here: its replacement finds out)
            vehicle_alive = vehicle is None or vehicle.proc.poll() is None
            if self.on_failure == "restart" and vehicle_alive and self._restarts.get(i, 0) < MAX_RESTARTS:
                self._restarts[i] = self._restarts.get(i, 0) + 1
                # A pilot flies the drone: the replacement keeps the take-over in force.
                held = self._taken_over is not None and self._taken_over(i)
                self.spawn(c.name, [*self.planner_args[i], "--rejoin", *(["--taken-over"] if held else [])])
                entry["action"] = f"restarted (restart {self._restarts[i]} of at most {MAX_RESTARTS}){', taken over' if held else ''}"
            elif vehicle is not None and not vehicle_alive:
                entry["action"] = "drone lost with its vehicle"
        self.failures.append(entry)
        log.error("%s failed at step %d (status %s): %s; %s", self.describe(c), self.step, code, reason, entry["action"])

    def describe(self, c: Child) -> str:
        """The child's name, and for a planner of an external autopilot its drone and connection
        (``planner_1 (drone 1, external autopilot at tcp:127.0.0.1:5760)``)."""
        if c.name.startswith("planner"):
            i = int(c.name.split("_")[1])
            if i in self.external:
                return f"{c.name} (drone {i}, external autopilot at {self.external[i]})"
        return c.name

    def raise_child_failure(self) -> None:
        """Raise :class:`LaunchError` for the first child that failed and was not dealt with."""
        for c in self.children:
            code = c.proc.poll()
            if code not in (None, 0) and c.proc.pid not in self.handled:
                raise LaunchError(f"{self.describe(c)} exited with status {code}:\n{c.tail()}")

    def vehicle_ports(self, children: list[Child], timeout_s: float) -> dict[int, int]:
        """The MAVLink UDP port of every vehicle (by system id), from the vehicles' JSON ready
        lines, waited for up to ``timeout_s`` wall seconds.

        Raises:
            LaunchError: a vehicle process exited or did not report ready in time.
            ClockError: the run was asked to stop meanwhile.
        """
        ports: dict[int, int] = {}
        deadline = time.monotonic() + timeout_s
        pending = list(children)
        while pending:
            if self._stop.is_set():
                raise ClockError("stopped while the vehicles started")
            if time.monotonic() > deadline:
                raise LaunchError(f"{pending[0].name} did not report ready within {timeout_s:g} s:\n{pending[0].tail()}")
            for c in list(pending):
                code = c.proc.poll()
                if code is not None:
                    raise LaunchError(f"{c.name} exited with status {code} while starting:\n{c.tail()}")
                ready = ready_line(c.log_path, c.proc.pid)
                if ready is not None:
                    for v in ready.get("vehicles", []):
                        ports[int(v["sysid"])] = int(str(v["mavlink"]).rsplit(":", 1)[1])
                    pending.remove(c)
            if pending:
                self._stop.wait(0.05)  # polling the children's log files, with the deadline above
        return ports
