"""``fimnav launch``: the distributed swarm as separate processes on this machine.

The launcher validates the mission, starts one simulated vehicle (``fimnav vehicle``) and one
planner (``fimnav plan``) per drone as operating-system processes, runs the lockstep clock,
shows progress, and writes the results directory. It only starts, watches and records: every
decision is taken by the planners (DESIGN.md).

Networking is loopback only: the launcher's Zenoh session listens on 127.0.0.1 at a free port
and every child connects to it (peers then find each other by gossip); each vehicle listens
for its planner's MAVLink on its own free UDP port on 127.0.0.1.

Every child runs in its own process group; on success, on any failure, on Ctrl-C, SIGTERM or
SIGHUP the launcher stops them all (SIGTERM, then SIGKILL after a grace period): no orphan
process, no port left bound. A launcher that dies without stopping them (SIGKILL, a crash) is
noticed by every child through the watchdog pipe it inherits (:mod:`missions.forkspawn`), and
each child then stops by itself.

Children run the launcher's own code: they (and the planners' fork server) get its ``sys.path``
(``PYTHONPATH``, with ``PYTHONSAFEPATH`` on Python 3.11+ so that ``-m`` and ``-c`` put no
working directory in front of it) and run in the results' ``logs`` directory, which holds no
module.

A results directory holds one run: the launcher refuses a directory that holds a previous run's
files (:data:`RUN_ENTRIES`) unless asked to overwrite them, which removes them first.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from comms import keys
from comms.errors import FimnavError, UsageError
from comms.messages import Done, MessageError, Observation, Status, decode
from comms.session import SessionSettings, open_session
from missions.clock import ClockError, LockstepClock
from missions.forkspawn import LAUNCHER_FD_ENV, ForkedProcess, ForkServer, same_code_environment
from missions.loader import mission_to_yaml
from missions.results import write_results
from missions.schema import Mission
from missions.simulator import MAVLINK_KINEMATIC_TOL, RunSpec, SimulationResult, safety_margins
from planner.agent import records_as_arrays
from planner.fim import fisher_information, position_error_bound

log = logging.getLogger("fimnav.launch")

#: Grace period (s) between SIGTERM and SIGKILL when stopping children.
STOP_GRACE_S: float = 5.0

#: What the launcher does when a vehicle or a planner fails mid-mission (``--on-failure``):
#: ``abort`` stops the run (exit 1); ``continue`` flies on without that drone; ``restart`` also
#: restarts a failed planner (whose vehicle is alive) with ``fimnav plan --rejoin``.
ON_FAILURE = ("continue", "abort", "restart")

#: Restarts of one drone's planner before it is given up.
MAX_RESTARTS: int = 3


class LaunchError(FimnavError):
    """The distributed run failed; the message says which part and why."""


class Interrupted(FimnavError):
    """Ctrl-C, SIGTERM or SIGHUP: every child was stopped. The exit status is 128 + the
    signal's number (130, 143, 129), as a shell reports a command the signal ended."""

    exit_code = 128 + signal.SIGINT

    def __init__(self, message: str, signum: int = signal.SIGINT) -> None:
        super().__init__(message)
        self.signum = int(signum)
        self.exit_code = 128 + self.signum


#: What a run writes at the top of its results directory: a directory holding any of them holds
#: a run (refused, or with ``overwrite`` these, and only these, are removed first).
RUN_ENTRIES: tuple[str, ...] = ("mission.yaml", "summary.json", "logs", "tlogs", "runs", "figures", "view.rrd")


def previous_run(out: Path) -> list[str]:
    """The entries of :data:`RUN_ENTRIES` present in ``out`` (directories with a trailing
    ``/``), in that order; empty when ``out`` holds no run (or does not exist)."""
    found = []
    for name in RUN_ENTRIES:
        p = out / name
        if p.is_symlink() or p.exists():
            found.append(f"{name}/" if p.is_dir() and not p.is_symlink() else name)
    return found


def check_results_dir(out: Path, overwrite: bool = False) -> list[str]:
    """Check that ``out`` can take a run; return the previous run's entries there (removed by
    :func:`claim_results_dir` when ``overwrite``).

    Raises:
        UsageError: ``out`` is not a directory, or it holds a previous run and ``overwrite`` is
            false.
    """
    if out.exists() and not out.is_dir():
        raise UsageError(f"results directory {out}: expected a directory, found a file")
    found = previous_run(out)
    if found and not overwrite:
        raise UsageError(f"results directory {out} already holds a run ({', '.join(found)}); choose another --out or pass --overwrite")
    return found


def claim_results_dir(out: Path, overwrite: bool = False) -> None:
    """Make ``out`` this run's results directory, with empty ``logs/`` and ``tlogs/`` (with
    ``overwrite``, a previous run's files are removed first; nothing else in ``out`` is).

    Raises:
        UsageError: see :func:`check_results_dir`; or another launch claimed ``out`` meanwhile.
    """
    for name in check_results_dir(out, overwrite):
        p = out / name.rstrip("/")
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()
    try:
        (out / "logs").mkdir(parents=True)  # atomic: two launches cannot both create it
    except FileExistsError:
        raise UsageError(f"results directory {out}: another launch started writing it; choose another --out") from None
    (out / "tlogs").mkdir(exist_ok=True)


def unique_results_dir(parent: Path, name: str) -> Path:
    """Create and return ``parent/name``, or ``parent/name-2``, ``-3``, ... if taken (two
    launches in the same second get different directories: ``mkdir`` is atomic)."""
    parent.mkdir(parents=True, exist_ok=True)
    n = 1
    while True:
        path = parent / (name if n == 1 else f"{name}-{n}")
        try:
            path.mkdir()
        except FileExistsError:
            n += 1
            continue
        return path


def child_environment(base: dict[str, str] | None = None, same_interpreter: bool = True) -> dict[str, str]:
    """The environment of a ``python -m missions`` child (from ``base``, default this
    process's): unbuffered output, and this process's ``sys.path`` with no working directory in
    front of it (:func:`missions.forkspawn.same_code_environment`), so that the child imports the
    very code the launcher imported (on Python 3.10 ``-m`` still puts the working directory
    first: the launcher runs its children in the run's ``logs`` directory, which holds no
    module). ``same_interpreter`` False (another Python): only no working directory in front."""
    env = dict(os.environ if base is None else base, PYTHONUNBUFFERED="1", PYTHONSAFEPATH="1")
    env.pop(LAUNCHER_FD_ENV, None)
    return same_code_environment(env) if same_interpreter else env


#: Wall time (s) between two refreshes of the progress bar's mean PEB and estimate error.
PROGRESS_STATS_PERIOD_S: float = 0.25


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
        try:
            text = self.log_path.read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return "\n".join("    " + line for line in text[-lines:])


@dataclass
class Collected:
    """What the launcher heard of the run (records and statuses by step)."""

    records: dict[tuple[int, int], Observation] = field(default_factory=dict)
    status: dict[tuple[int, int], Status] = field(default_factory=dict)
    dropped: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


class Launcher:
    """One distributed run of a mission.

    Args:
        mission: the validated mission (steps and seed already overridden).
        mission_path: the mission file the children load (the mission as run is written to
            the results directory and passed to them).
        out: the results directory.
        python: the interpreter for the children.
        progress: called after each step with (step, mean PEB, mean estimate error, alive).
        on_failure: one of :data:`ON_FAILURE`. Failures are recorded in :attr:`failures`
            (what failed, at which step, its exit status and last log line, what was done).
        realtime: fly on the wall clock instead of the lockstep clock: vehicles run in real
            time (sped up by ``speedup``), planners step every Δt/speedup wall seconds from a
            shared UNIX start time and wait for their peers only until a deadline. Drones with
            ``vehicles.overrides[i].connection`` get no simulated vehicle: their planner flies
            the autopilot at that connection (a mixed fleet).
        speedup: real time: mission seconds per wall second (1 for real vehicles).
        start_delay_s: real time: wall seconds from the launch to step 0 (None: 30 s plus 1 s
            per drone, the start-up, take-off and flight to the start of simulated vehicles).
        fork_server: start the planners from a fork server that has imported them once
            (:mod:`missions.forkspawn`; each is still its own process and process group);
            False: ``python -m missions plan`` with ``subprocess`` (about 0.45 s of CPU each
            to import).
        overwrite: a results directory holding a previous run: remove that run's files
            (:data:`RUN_ENTRIES`) first; False: refuse it (:func:`claim_results_dir`).
        notice: called with a one-line message on what the launcher waits for (real time:
            the start delay); default: logged.
        gcs: real time: a MAVLink endpoint (``udpout:127.0.0.1:14550``) that every simulated
            vehicle's MAVLink is forwarded to, its frames routed back by target system
            (:class:`missions.gcs.GcsRouter`); None: none.
        view: show the run live in a browser (:mod:`missions.liveview`): rerun's web viewer on
            127.0.0.1 (``view_port``, default a free port), the recording in ``out/view.rrd``.
    """

    def __init__(
        self,
        mission: Mission,
        out: Path,
        python: str = sys.executable,
        progress: Callable[[int, float, float, int], None] | None = None,
        preflight_timeout_s: float | None = None,
        step_timeout_s: float = 30.0,
        vehicles_per_process: int = 10,
        on_failure: str = "continue",
        realtime: bool = False,
        speedup: float = 1.0,
        start_delay_s: float | None = None,
        fork_server: bool = True,
        overwrite: bool = False,
        notice: Callable[[str], None] | None = None,
        gcs: str | None = None,
        view: bool = False,
        view_port: int | None = None,
    ) -> None:
        self.mission = mission
        self._planner_config = mission.planner_config()
        #: The live view (rerun): asked for, its port, and while running its server and recording.
        self.view = view
        self.view_port = view_port
        self._view_server: Any = None
        self._swarm_view: Any = None
        self._view_last: dict[int, tuple[float, float, float]] = {}
        #: Real time: the ground-station endpoint every simulated vehicle is forwarded to.
        self.gcs_endpoint = gcs
        self._gcs: Any = None
        self.out = out
        # Children get absolute paths: they run in the logs directory (child_environment).
        self._abs_out = out.absolute()
        self.overwrite = overwrite
        self.notice: Callable[[str], None] = notice if notice is not None else log.info
        self.python = python
        self.progress = progress
        # Start-up and pre-flight of 2N processes share two cores: the deadline grows with N.
        n = mission.drones.count
        self.preflight_timeout_s = preflight_timeout_s if preflight_timeout_s is not None else 120.0 + 2.0 * n
        self.step_timeout_s = step_timeout_s
        if vehicles_per_process < 1:
            raise LaunchError(f"vehicles per process: expected a positive integer, found {vehicles_per_process}")
        self.vehicles_per_process = vehicles_per_process
        if on_failure not in ON_FAILURE:
            raise LaunchError(f"on failure: expected one of {', '.join(ON_FAILURE)}, found {on_failure!r}")
        self.on_failure = on_failure
        if realtime and on_failure == "restart":
            raise LaunchError("on failure restart: only in lockstep (a real-time planner restarted mid-flight would fly its pre-flight again)")
        if not (np.isfinite(speedup) and speedup > 0):
            raise LaunchError(f"speed-up: expected a positive number, found {speedup!r}")
        self.realtime = realtime
        self.speedup = float(speedup)
        if mission.comms.faults.partition is not None:
            raise UsageError(
                "comms.faults.partition_start_step: a partition is simulated by fimnav montecarlo; the planner "
                "processes of fimnav launch are partitioned by cutting their network (docs/distributed.md, Partitions)"
            )
        if realtime:
            for i in range(n):
                v = mission.vehicles.for_drone(i)
                if v.connection is not None and v.payload == "simulated" and v.payload_connection is None:
                    raise UsageError(
                        f"drone {i + 1} flies the autopilot at {v.connection} and fimnav simulates its payload, which follows "
                        f"the autopilot over a second MAVLink connection: give vehicles.overrides[{i}].payload_connection "
                        f"(e.g. SITL's SERIAL1, tcp:127.0.0.1:5762), or payload: external if a real payload publishes its "
                        "measurements"
                    )
        self.start_delay_s = start_delay_s if start_delay_s is not None else 30.0 + 1.0 * n
        self.start_unix: float | None = None
        #: Every failure seen: {"process", "drones", "step", "status", "reason", "action"}.
        self.failures: list[dict[str, Any]] = []
        self._handled: set[int] = set()  # pids of failed children already dealt with
        self._planner_args: dict[int, list[str]] = {}
        self._vehicle_child: dict[int, Child] = {}
        self._restarts: dict[int, int] = {}
        self._step = -1  # the clock's current step (-1: pre-flight)
        self._flying = False  # the mission has started (failures are survivable from then on)
        self.children: list[Child] = []
        self.collected = Collected()
        self._stop = threading.Event()
        self._signal: int | None = None  # the signal that asked the run to stop
        self._spawned: set[str] = set()  # names started once (a restart appends to the log)
        self._watchdog: tuple[int, int] | None = None  # (read, write) ends of the watchdog pipe
        self._ready: set[int] = set()  # real time: drones that reported ready at their start
        # Planners are forked from a fork server that imported them once (missions.forkspawn),
        # unless another interpreter is asked for.
        self._forks = ForkServer(python) if fork_server and python == sys.executable else None

    # -- processes --------------------------------------------------------------------------
    def _spawn(self, name: str, args: Sequence[str]) -> Child:
        """Start ``python -m missions ARGS`` as ``name``: own session, output in its log (a
        restarted planner appends to the log of the one it replaces), working directory the
        logs directory, the read end of the watchdog pipe inherited."""
        log_path = self.out / "logs" / f"{name}.log"
        cwd = self._abs_out / "logs"
        first = name not in self._spawned
        self._spawned.add(name)
        watch_r = self._watchdog[0] if self._watchdog is not None else None
        if self._forks is not None and name.startswith("planner"):
            # Forked from the pre-imported fork server: a separate process all the same.
            child = Child(name, self._forks.spawn(args, log_path, launcher_fd=watch_r, truncate=first, cwd=cwd), log_path)
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
        """SIGTERM every child's process group, then SIGKILL what is left after the grace."""
        for c in self.children:
            if c.proc.poll() is None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(c.proc.pid, signal.SIGTERM)
        deadline = time.monotonic() + STOP_GRACE_S
        for c in self.children:
            remaining = max(0.0, deadline - time.monotonic())
            try:
                c.proc.wait(remaining)
            except subprocess.TimeoutExpired:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(c.proc.pid, signal.SIGKILL)
                c.proc.wait()
        # Anything left in a group (a grandchild) goes too.
        for c in self.children:
            with contextlib.suppress(ProcessLookupError, PermissionError):
                os.killpg(c.proc.pid, signal.SIGKILL)

    def _check_children(self) -> None:
        """Deal with children that ended: before the mission or with ``abort``, any failure
        ends the run; otherwise it is recorded (and a planner restarted if asked), and the run
        only fails when no planner is left."""
        for c in list(self.children):
            code = c.proc.poll()
            if code is None or c.proc.pid in self._handled:
                continue
            vehicle = c.name.startswith("vehicle")
            if code == 0 and not vehicle:
                continue  # a planner that finished its mission
            if not self._flying or self.on_failure == "abort":
                during = " during the mission" if vehicle and self._flying else ""
                raise LaunchError(f"{c.name} exited with status {code}{during}:\n{c.tail()}")
            self._handled.add(c.proc.pid)
            self._on_failure(c, code)
        planners = [c for c in self.children if c.name.startswith("planner")]
        if planners and all(c.proc.poll() not in (None, 0) for c in planners):
            raise LaunchError(f"every planner failed; last: {planners[-1].name}:\n{planners[-1].tail()}")

    def _on_failure(self, c: Child, code: int) -> None:
        """Record a failed child; restart a failed planner if asked and its vehicle lives."""
        drones = [i for i, v in self._vehicle_child.items() if v is c] if c.name.startswith("vehicle") else [int(c.name.split("_")[1])]
        reason = next((line.strip() for line in reversed(c.tail(20).splitlines()) if line.strip()), "")
        step = self._step
        if c.name.startswith("planner"):
            # The step it failed at: the one after the last it logged (the launcher may notice
            # its exit a few steps later).
            flown = [k for (k, j) in self._step_logs_of(drones[0])]
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
            vehicle_alive = self._vehicle_child[i].proc.poll() is None
            if self.on_failure == "restart" and vehicle_alive and self._restarts.get(i, 0) < MAX_RESTARTS:
                self._restarts[i] = self._restarts.get(i, 0) + 1
                self._spawn(c.name, [*self._planner_args[i], "--rejoin"])
                entry["action"] = f"restarted (restart {self._restarts[i]} of at most {MAX_RESTARTS})"
            elif not vehicle_alive:
                entry["action"] = "drone lost with its vehicle"
        self.failures.append(entry)
        log.error("%s failed at step %d (status %s): %s; %s", c.name, self._step, code, reason, entry["action"])

    def request_stop(self, signum: int | None = None) -> None:
        """Ask the run to stop (signal handlers call this with the signal's number)."""
        if signum is not None and self._signal is None:
            self._signal = signum
        self._stop.set()

    @property
    def stop_requested(self) -> bool:
        """A signal (or :meth:`request_stop`) asked the run to stop."""
        return self._stop.is_set()

    def interrupted(self) -> Interrupted:
        """The error that ends a run stopped by a signal (children already stopped or about to
        be): names the signal and where the partial logs are."""
        signum = self._signal if self._signal is not None else signal.SIGINT
        name = signal.Signals(signum).name
        return Interrupted(f"interrupted by {name}: every process was stopped; partial logs in {self.out / 'logs'}", signum)

    # -- zenoh collection -------------------------------------------------------------------
    def _on_record(self, sample: Any) -> None:
        self._collect(sample, "record")

    def _on_status(self, sample: Any) -> None:
        self._collect(sample, "status")

    def _on_done(self, sample: Any) -> None:
        """Real time: a planner's ``Done(-1)`` says its drone is at its start."""
        try:
            _, msg = decode(bytes(sample.payload.to_bytes()), self.mission.id, self.mission.drones.count)
        except MessageError:
            return
        if isinstance(msg, Done) and msg.step == -1 and msg.sender == keys.uav_of(str(sample.key_expr)):
            with self.collected.lock:
                self._ready.add(msg.sender)

    def _collect(self, sample: Any, kind: str) -> None:
        c = self.collected
        try:
            _, msg = decode(bytes(sample.payload.to_bytes()), self.mission.id, self.mission.drones.count)
        except MessageError:
            with c.lock:
                c.dropped += 1
            return
        uav = keys.uav_of(str(sample.key_expr))
        if getattr(msg, "sender", None) != uav:
            with c.lock:
                c.dropped += 1
            return
        with c.lock:
            if kind == "record" and isinstance(msg, Observation):
                c.records.setdefault((msg.step, msg.sender), msg)
            elif kind == "status" and isinstance(msg, Status):
                c.status[(msg.step, msg.sender)] = msg

    # -- the run ----------------------------------------------------------------------------
    def run(self) -> SimulationResult:
        """Start everything, fly the mission, stop everything; return the run's records."""
        m = self.mission
        claim_results_dir(self.out, self.overwrite)
        mission_file = self._abs_out / "mission.yaml"
        mission_file.write_text(mission_to_yaml(m))
        # The watchdog pipe: the launcher holds the only write end (os.pipe is not inherited);
        # every child gets the read end and stops when it reads end of file.
        self._watchdog = os.pipe()
        try:
            return self._run(mission_file)
        finally:
            for fd in self._watchdog:
                os.close(fd)  # any child still there reads end of file and stops
            self._watchdog = None

    def _run(self, mission_file: Path) -> SimulationResult:
        """:meth:`run` once the results directory and the watchdog pipe are set up."""
        m = self.mission
        n = m.drones.count
        if self._forks is not None:
            self._forks.warm_up(self._abs_out / "logs")  # imports the planners' modules while the vehicles start
        hub = f"tcp/127.0.0.1:{free_port()}"
        # Topology: a star. The launcher's session is a Zenoh router on a free loopback port and
        # every child (planners, vehicles) a client of it: O(N) links, and every message is
        # routed (Zenoh peers do not forward for each other, so in a mesh a message between two
        # children whose direct link has not formed yet is lost; a full mesh of 2N+1 peers also
        # costs O(N²) keep-alives). The mission's own endpoints (routers, other machines,
        # another launch) are connected by the router, so the swarm joins a larger network.
        base = SessionSettings.from_mission(m.zenoh, listen=(hub,))
        session = open_session(dataclasses.replace(base, mode="router"))
        # Where operator tools reach the swarm while it flies (fimnav handback --results OUT).
        (self._abs_out / "logs" / "zenoh.json").write_text(json.dumps({"connect": [hub]}) + "\n")
        t_start = time.perf_counter()
        try:
            if self.view:
                self._start_view()
            subs = [
                session.declare_subscriber(keys.record(m.id), self._on_record),
                session.declare_subscriber(keys.status(m.id), self._on_status),
            ]
            if self.realtime:
                subs.append(session.declare_subscriber(keys.done(m.id), self._on_done))
            clock = None if self.realtime else LockstepClock(session, m.id, n, m.dt_s)
            child_zenoh = dataclasses.replace(SessionSettings.from_mission(m.zenoh), mode="client", listen=(), connect=(hub,))
            vehicle_zenoh = ["--zenoh-connect", hub, "--zenoh-mode", "client"]
            timing = ["--speedup", f"{self.speedup:g}"] if self.realtime else ["--lockstep"]
            # Drones flown on an external autopilot (a mixed fleet, real time) get no vehicle.
            external = {i for i in range(1, n + 1) if m.vehicles.for_drone(i - 1).connection is not None} if self.realtime else set()
            # Vehicles bind port 0 and report the port the OS gave them (no race with the
            # ephemeral ports of a hundred other sockets); planners start once they are known.
            per = self.vehicles_per_process
            vehicle_children = []
            for ids in _runs([i for i in range(1, n + 1) if i not in external], per):
                first = ids[0]
                name = f"vehicle_{first}" if len(ids) == 1 else f"vehicles_{first}-{ids[-1]}"
                # The ideal profile is a closed form (exact at any rate): in lockstep, 10 Hz
                # physics only sets how promptly a guided timeout is seen (0.1 s), and costs a
                # fifth of the default 50 Hz on the step's critical path.
                ideal = all(m.vehicles.for_drone(i - 1).profile == "ideal" for i in ids)
                physics = ["--physics-hz", "10"] if ideal and not self.realtime else []
                tlog = self._abs_out / "tlogs" / ("vehicle_{sysid}.tlog" if len(ids) > 1 else f"vehicle_{first}.tlog")
                vc = self._spawn(
                    name,
                    [
                        "vehicle",
                        "--mission",
                        str(mission_file),
                        "--sysid",
                        str(first),
                        "--count",
                        str(len(ids)),
                        *[a for _ in ids for a in ("--mavlink", "udpin:127.0.0.1:0")],
                        *timing,
                        *physics,
                        *vehicle_zenoh,
                        "--tlog",
                        str(tlog),
                    ],
                )
                vehicle_children.append(vc)
                for i in ids:
                    self._vehicle_child[i] = vc
            ports = self._vehicle_ports(vehicle_children, self.preflight_timeout_s)
            if self.realtime and self.gcs_endpoint is not None:
                from missions.gcs import GcsRouter

                try:
                    self._gcs = GcsRouter(self.gcs_endpoint, ports)
                except OSError as exc:
                    raise LaunchError(f"--gcs {self.gcs_endpoint}: cannot open it ({exc})") from None
                self._gcs.start()
                self.notice(f"ground station port {self.gcs_endpoint}: vehicles {', '.join(str(i) for i in sorted(ports))} (system id = drone id)")
            if self.realtime:
                # On the UNIX grid of multiples of Δt/speed-up: the simulated payloads measure
                # just before each point of it (vehicle_sim.bridge).
                dtw = m.dt_s / self.speedup
                self.start_unix = float(np.ceil((time.time() + self.start_delay_s) / dtw) * dtw)
                timing = [*timing, "--start-at", f"{self.start_unix:.6f}", "--preflight-timeout", str(self.preflight_timeout_s)]
            for i in sorted(external):
                # A drone on an external autopilot: fimnav's simulated payload follows it over
                # its second MAVLink connection, unless a real payload publishes.
                if m.vehicles.for_drone(i - 1).payload == "simulated":
                    self._spawn(
                        f"payload_{i}",
                        [
                            "payload",
                            "--mission",
                            str(mission_file),
                            "--uav",
                            str(i),
                            "--speedup",
                            f"{self.speedup:g}",
                            *child_zenoh.to_cli(),
                            "--connect-timeout",
                            str(self.preflight_timeout_s),
                        ],
                    )
            for i in range(1, n + 1):
                # An external autopilot's link is logged by its planner (a simulated vehicle
                # writes its own .tlog).
                conn = (
                    ["--tlog", str(self._abs_out / "tlogs" / f"vehicle_{i}.tlog")] if i in external else ["--mavlink", f"udpout:127.0.0.1:{ports[i]}"]
                )
                self._planner_args[i] = [
                    "plan",
                    "--mission",
                    str(mission_file),
                    "--uav",
                    str(i),
                    *conn,
                    *timing,
                    *child_zenoh.to_cli(),
                    "--log",
                    str(self._abs_out / "logs" / f"planner_{i}.jsonl"),
                    "--step-timeout",
                    str(self.step_timeout_s),
                ]
                self._spawn(f"planner_{i}", self._planner_args[i])
            stop = self._should_stop
            if clock is None:
                self._fly_realtime()
                return self._result(time.perf_counter() - t_start)
            t0 = clock.preflight(self.preflight_timeout_s, stop)
            self._flying = True
            stats_at, peb, err = -math.inf, math.inf, math.nan
            for k in range(m.steps):
                self._step = k
                # The planners' own deadline expires first and names what they waited for.
                report = clock.run_step(k, t0, self.step_timeout_s + 15.0, stop)
                if self.progress is not None:
                    # The PEB of every view costs this process ~1 ms a step, on the cores the
                    # swarm steps on: refreshed a few times a second (and at the last step).
                    now = time.monotonic()
                    if now - stats_at >= PROGRESS_STATS_PERIOD_S or k == m.steps - 1:
                        peb, err = self._live_stats(k)
                        stats_at = now
                    self.progress(k, peb, err, len(report.alive))
                if self._swarm_view is not None:
                    self._view_step(k)
            # The end tick releases the planners: they end the mission (hold, land or RTL) and
            # exit. It is re-sent every second for a planner that missed it.
            clock.end(m.steps, t0)
            deadline = time.monotonic() + 30.0
            resend = time.monotonic() + 1.0
            for c in list(self.children):
                if c.name.startswith("planner") and c.proc.pid not in self._handled:
                    while c.proc.poll() is None:
                        if self._stop.is_set():
                            raise self.interrupted()
                        now = time.monotonic()
                        if now > deadline:
                            raise LaunchError(f"{c.name} did not finish its end of mission within 30 s:\n{c.tail()}")
                        if now >= resend:
                            clock.end(m.steps, t0)
                            resend = now + 1.0
                        with contextlib.suppress(subprocess.TimeoutExpired):
                            c.proc.wait(min(0.2, max(0.0, deadline - now)))
            self._check_children()
        except ClockError as exc:
            if self._stop.is_set():
                raise self.interrupted() from None
            self._raise_child_failure()
            raise LaunchError(str(exc)) from None
        finally:
            if self._gcs is not None:
                self._gcs.close()
            self._stop_view()
            self.stop_children()
            for s in locals().get("subs", []):
                with contextlib.suppress(Exception):
                    s.undeclare()
            session.close()
        return self._result(time.perf_counter() - t_start)

    def _fly_realtime(self) -> None:
        """Real time: say what the start delay waits for, then report progress on the wall
        clock until every planner has ended."""
        m = self.mission
        if self.start_unix is None:
            raise RuntimeError("real-time flight without a start time (start_unix is set when the planners are started)")
        dtw = m.dt_s / self.speedup
        self._flying = True
        reported = -1
        end_by = self.start_unix + m.steps * dtw + self.preflight_timeout_s + 120.0
        n = m.drones.count
        start_text = time.strftime("%H:%M:%S", time.localtime(self.start_unix))
        self.notice(
            f"waiting for {n} drone{'s' if n != 1 else ''} to be ready and at their starts: "
            f"step 0 at {start_text} (in {max(0.0, self.start_unix - time.time()):.0f} s)"
        )
        ready_seen = 0
        started = False
        while True:
            if self._should_stop():
                raise self.interrupted()
            planners = [c for c in self.children if c.name.startswith("planner")]
            now = time.time()
            if not started:
                with self.collected.lock:
                    ready = len(self._ready)
                if now >= self.start_unix:
                    started = True
                    if ready < n:
                        self.notice(f"step 0: {ready}/{n} drones at their starts; the others join when they get there")
                elif ready != ready_seen:
                    ready_seen = ready
                    self.notice(f"{ready}/{n} drones ready at their starts (step 0 in {self.start_unix - now:.0f} s)")
            ended = all(c.proc.poll() is not None for c in planners)
            if ended:
                self._check_children()  # failures are dated by the step in progress
            # Every step once the planners have ended (the last one's records are in by then).
            done = m.steps - 1 if ended else min(int((now - self.start_unix) / dtw) - 1, m.steps - 1)
            while reported < done:
                reported += 1
                self._step = reported
                if self.progress is not None:
                    peb, err = self._live_stats(reported)
                    self.progress(reported, peb, err, sum(c.proc.poll() is None for c in planners))
                if self._swarm_view is not None:
                    self._view_step(reported)
            if ended:
                return
            if now > end_by:
                raise LaunchError(f"the planners did not end the mission by {end_by - self.start_unix:.0f} s after step 0")
            self._stop.wait(0.1)  # polling the children, with the deadline above

    def _vehicle_ports(self, children: list[Child], timeout_s: float) -> dict[int, int]:
        """The MAVLink UDP port of every vehicle, from the vehicles' JSON ready lines."""
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
                ready = _ready_line(c.log_path, c.proc.pid)
                if ready is not None:
                    for v in ready.get("vehicles", []):
                        ports[int(v["sysid"])] = int(str(v["mavlink"]).rsplit(":", 1)[1])
                    pending.remove(c)
            if pending:
                self._stop.wait(0.05)  # polling the children's log files, with the deadline above
        return ports

    def _should_stop(self) -> bool:
        if self._stop.is_set():
            return True
        self._check_children()
        return False

    def _raise_child_failure(self) -> None:
        for c in self.children:
            code = c.proc.poll()
            if code not in (None, 0) and c.proc.pid not in self._handled:
                raise LaunchError(f"{c.name} exited with status {code}:\n{c.tail()}")

    def _heard_at(self, k: int) -> tuple[dict[int, Observation | None], dict[int, Status | None], dict[tuple[int, int], Observation]]:
        """What was heard of step k: each drone's record and status (None: not heard), and the
        records the statuses' views name, by (step, drone)."""
        n = self.mission.drones.count
        with self.collected.lock:
            own = {j: self.collected.records.get((k, j)) for j in range(1, n + 1)}
            stat = {j: self.collected.status.get((k, j)) for j in range(1, n + 1)}
            # Only the records the views name (copying every record each step is O(K²)).
            wanted = {(s, i + 1) for st in stat.values() if st is not None for i, s in enumerate(st.saved_steps) if s >= 0}
            recs = {key: self.collected.records[key] for key in wanted if key in self.collected.records}
        return own, stat, recs

    def _live_stats(self, k: int) -> tuple[float, float]:
        """Mean PEB and mean estimate error over the drones at step k (for the progress bar)."""
        m = self.mission
        _, stat, recs = self._heard_at(k)
        src = m.source.position_at(self._t(k))
        pebs, errs = [], []
        for st in stat.values():
            if st is None:
                continue
            errs.append(float(np.linalg.norm(np.asarray(st.estimate_m) - src)))
            pebs.append(self._peb_of_view(st.saved_steps, recs, src))
        finite = [p for p in pebs if np.isfinite(p)]
        return (float(np.mean(finite)) if finite else float("inf")), (float(np.mean(errs)) if errs else float("nan"))

    # -- the live view --------------------------------------------------------------------------
    def _start_view(self) -> None:
        """Start rerun's web viewer (a child bound to 127.0.0.1) and the run's recording."""
        from missions.liveview import SwarmView, ViewServer

        server = ViewServer(web_port=self.view_port, log_path=self.out / "logs" / "viewer.log")
        self._view_server = server.start()
        self._swarm_view = SwarmView(self.mission, self._abs_out / "view.rrd", server.grpc_url, name=self.mission.id)
        # Where tools and tests find the view while the swarm flies.
        (self._abs_out / "logs" / "view.json").write_text(json.dumps({"url": server.browser_url, "grpc": server.grpc_url}) + "\n")
        self.notice(f"live view: {server.browser_url}")

    def _stop_view(self) -> None:
        if self._swarm_view is not None:
            with contextlib.suppress(Exception):
                self._swarm_view.close()  # the recording is complete whatever ended the run
            self._swarm_view = None
        if self._view_server is not None:
            self._view_server.close()
            self._view_server = None

    def _view_step(self, k: int) -> None:
        """Log step k to the live view from what the launcher heard: each drone's record of
        step k (its position and state), its status (estimate and view)."""
        from missions.liveview import swarm_frame

        n = self.mission.drones.count
        own, stat, recs = self._heard_at(k)
        positions = np.full((n, 3), np.nan)
        states = []
        estimates = np.full((n, 3), np.nan)
        view_pos = np.zeros((n, n, 3))
        valid = np.zeros((n, n), dtype=bool)
        los = np.zeros((n, n), dtype=bool)
        for j in range(1, n + 1):
            r = own[j]
            if r is not None:
                self._view_last[j] = r.position_m
                states.append("taken over" if r.taken_over else "stale" if r.stale else "alive")
            else:
                states.append("lost")
            if j in self._view_last:
                positions[j - 1] = self._view_last[j]
            st = stat[j]
            if st is not None:
                estimates[j - 1] = st.estimate_m
                for i, s in enumerate(st.saved_steps):
                    rec = recs.get((s, i + 1)) if s >= 0 else None
                    if rec is not None:
                        view_pos[j - 1, i], valid[j - 1, i], los[j - 1, i] = rec.position_m, True, rec.los
        try:
            self._swarm_view.log(swarm_frame(self.mission, k, positions, states, estimates, view_pos, valid, los))
        except Exception as exc:  # the view must never end a flight
            log.warning("live view: step %d not logged (%s)", k, exc)

    def _t(self, k: int) -> float:
        return k * self.mission.dt_s

    def _peb_of_view(self, saved: Sequence[int], recs: dict[tuple[int, int], Observation], src: np.ndarray) -> float:
        config = self._planner_config
        pos, valid, los = records_as_arrays([recs.get((s, j + 1)) if s >= 0 else None for j, s in enumerate(saved)])
        J = fisher_information(src, pos, config.ranging & valid, config.bearing & valid, los, config.channel)
        return float(position_error_bound(J)[0])

    def _step_logs(self) -> dict[tuple[int, int], dict[str, Any]]:
        """Every planner's step log entries by (step, drone id): the authoritative record of
        what each planner saw and did (a Zenoh message published just before a planner exits
        can be lost; its own log cannot)."""
        out: dict[tuple[int, int], dict[str, Any]] = {}
        for j in range(1, self.mission.drones.count + 1):
            out.update(self._step_logs_of(j))
        return out

    def _step_logs_of(self, j: int) -> dict[tuple[int, int], dict[str, Any]]:
        """Planner ``j``'s step log entries by (step, j)."""
        out: dict[tuple[int, int], dict[str, Any]] = {}
        path = self.out / "logs" / f"planner_{j}.jsonl"
        with contextlib.suppress(OSError):
            for line in path.read_text().splitlines():
                try:
                    entry = json.loads(line)
                    out[(int(entry["step"]), j)] = entry
                except (ValueError, KeyError, TypeError):
                    continue  # a line cut by a killed planner
        return out

    def _result(self, runtime_s: float) -> SimulationResult:
        """The run as a one-trial :class:`SimulationResult` (same accounting as the simulator),
        from the planners' step logs, completed by what was heard over Zenoh."""
        m = self.mission
        n, K = m.drones.count, m.steps
        logs = self._step_logs()
        # Records (position where measured, LOS) of every drone and step.
        recs: dict[tuple[int, int], Observation] = dict(self.collected.records)
        nan = float("nan")
        for (k, j), e in logs.items():
            recs[(k, j)] = Observation(
                j,
                k,
                float(e.get("t_s", nan)),
                tuple(e["position_m"]),
                bool(m.drones.ranging_mask()[j - 1]),
                bool(m.drones.bearing_mask()[j - 1]),
                bool(e["measurement"]["los"]),
                nan,
                nan,
                nan,
            )
        positions = np.full((K + 1, 1, n, 3), np.nan)
        estimates = np.full((K, 1, n, 3), np.nan)
        observable = np.zeros((K, 1, n), dtype=bool)
        singular = np.zeros((K, 1, n), dtype=bool)
        filtered = np.zeros((K, 1, n), dtype=bool)
        ages = np.full((K, 1, n, n), -1, dtype=np.int16)
        peb = np.full((K, 1, n), np.inf)
        active = np.zeros((K, 4), dtype=np.int64)
        sources = np.array([m.source.position_at(self._t(k)) for k in range(K + 1)])
        for (k, j), r in recs.items():
            if 0 <= k < K:
                positions[k, 0, j - 1] = r.position_m
        for j in range(1, n + 1):
            last = logs.get((K - 1, j))
            if last is not None:
                positions[K, 0, j - 1] = last["next_position_m"]
        steps: dict[tuple[int, int], tuple[Any, ...]] = {}
        for (k, j), st in self.collected.status.items():
            steps[(k, j)] = (st.estimate_m, st.observable, st.singular, False, st.saved_steps, [bool((st.active_mask >> b) & 1) for b in range(4)])
        for (k, j), e in logs.items():
            act = e.get("active", {})
            steps[(k, j)] = (
                e["estimate_m"],
                e["observable"],
                e["singular"],
                e.get("filtered", False),
                e["saved_steps"],
                [bool(act.get(name, False)) for name in ("uav", "source", "obstacle", "altitude")],
            )
        for (k, j), (est_m, obs, sing, filt, saved, act) in steps.items():
            if not 0 <= k < K:
                continue
            estimates[k, 0, j - 1] = est_m
            observable[k, 0, j - 1] = obs
            singular[k, 0, j - 1] = sing
            filtered[k, 0, j - 1] = filt
            ages[k, 0, j - 1] = [k - s if s >= 0 else -1 for s in saved]
            peb[k, 0, j - 1] = self._peb_of_view(saved, recs, sources[k])
            active[k] += np.asarray(act, dtype=np.int64)
        # A drone a pilot flies (taken over) has no planner step: its estimate, observability
        # and view are those of its planner's last step, and its displacements are no command.
        taken = np.zeros((K + 1, 1, n), dtype=bool)
        for (k, j), r in self.collected.records.items():
            if 0 <= k < K and r.taken_over and (k, j) not in logs:
                taken[k, 0, j - 1] = True
        for k, _, i in zip(*np.nonzero(taken[1:K]), strict=True):
            k += 1
            if (k, i + 1) not in steps and not np.isnan(estimates[k - 1, 0, i]).any():
                estimates[k, 0, i], observable[k, 0, i], peb[k, 0, i] = estimates[k - 1, 0, i], observable[k - 1, 0, i], peb[k - 1, 0, i]
        missing = np.isnan(positions).any(-1)
        if missing.any():
            # Steps a drone did not fly (it died): hold its last known position for the record.
            for k in range(1, K + 1):
                positions[k] = np.where(np.isnan(positions[k]), positions[k - 1], positions[k])
        bmin, bmax = m.obstacle_bounds()
        margins = safety_margins(np.nan_to_num(positions), sources, m.limits(), bmin, bmax, MAVLINK_KINEMATIC_TOL)
        # A step no planner flew (its drone lost, or its planner dead until it rejoined) has no
        # speed or turn-rate bound to keep: its displacement is the record's gap, not a command.
        not_flown = missing[:K] | missing[1:] | taken[:K] | taken[1:]
        if self.realtime:
            # On the wall clock, positions are sampled at each step's (jittered) start: the
            # kinematic limits apply to the commanded steps, u_k = next_k − p_k (logged).
            u = np.full((K, 1, n, 3), np.nan)
            for (k, j), e in logs.items():
                if 0 <= k < K:
                    u[k, 0, j - 1] = np.asarray(e["next_position_m"]) - np.asarray(e["position_m"])
            not_flown |= np.isnan(u).any(-1)
            chain = np.concatenate([np.nan_to_num(positions[:1]), np.nan_to_num(positions[:1]) + np.cumsum(np.nan_to_num(u), axis=0)])
            commanded = safety_margins(chain, sources, m.limits(), bmin, bmax, MAVLINK_KINEMATIC_TOL)
            margins["speed"], margins["turn_rate"] = commanded["speed"], commanded["turn_rate"]
        margins["speed"][not_flown] = np.inf
        margins["turn_rate"][not_flown | np.concatenate([not_flown[:1], not_flown[:-1]])] = np.inf
        err = np.linalg.norm(estimates - sources[:K, None, None, :], axis=-1)
        return SimulationResult(
            spec=RunSpec(m, m.criterion, 1, K),
            positions_m=positions,
            estimates_m=np.nan_to_num(estimates),
            estimate_error_m=err,
            observable=observable,
            peb_m=peb,
            source_m=sources,
            margins_m=margins,
            active=active,
            singular_fallback=singular,
            filtered=filtered,
            record_ages=ages,
            runtime_s=runtime_s,
            extra={"distributed": 1.0, "dropped_messages": float(self.collected.dropped), "missing_drone_steps": float(missing[:K].sum())},
        )


def _runs(ids: Sequence[int], size: int) -> list[list[int]]:
    """Consecutive ids in groups of at most ``size`` (a vehicle process hosts consecutive
    system ids)."""
    groups: list[list[int]] = []
    for i in ids:
        if groups and groups[-1][-1] == i - 1 and len(groups[-1]) < size:
            groups[-1].append(i)
        else:
            groups.append([i])
    return groups


def _ready_line(path: Path, pid: int) -> dict[str, Any] | None:
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


#: The signals that stop a run: Ctrl-C, ``kill``, and the hang-up of the launcher's terminal
#: (its children, in their own sessions, never see that one).
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@contextlib.contextmanager
def stop_on_signals(launcher: Launcher) -> Iterator[None]:
    """SIGINT, SIGTERM and SIGHUP ask the launcher to stop (children are then stopped cleanly).
    An ignored SIGHUP stays ignored (``nohup fimnav launch``: the run outlives the terminal);
    SIGINT is handled even if inherited ignored (a launch started from a background job)."""
    previous = {}
    for s in STOP_SIGNALS:
        current = signal.getsignal(s)
        if s == signal.SIGHUP and current == signal.SIG_IGN:
            continue
        previous[s] = current

    def handler(signum: int, frame: Any) -> None:
        launcher.request_stop(signum)

    for s in previous:
        signal.signal(s, handler)
    try:
        yield
    finally:
        for s, h in previous.items():
            signal.signal(s, h)


def taken_over(out: Path, n: int) -> dict[str, list[dict[str, Any]]]:
    """Drone id → its planner's take-overs (``{"step", "mode", "handed_back_step"?}``), from
    the summary line that ends each planner's log (a pilot or ground station switched its
    vehicle out of GUIDED/OFFBOARD; docs/in-the-field.md)."""
    found: dict[str, list[dict[str, Any]]] = {}
    for i in range(1, n + 1):
        try:
            lines = (out / "logs" / f"planner_{i}.log").read_text().strip().splitlines()
            last = json.loads(lines[-1]) if lines else None
        except (OSError, ValueError):
            continue
        if isinstance(last, dict) and last.get("taken_over"):
            found[str(i)] = last["taken_over"]
    return found


def launch(mission: Mission, out: Path, progress: Callable[[int, float, float, int], None] | None = None, **kwargs: Any) -> dict[str, Any]:
    """Fly ``mission`` distributed and write the results directory; return the summary.

    Raises:
        UsageError: ``out`` holds a previous run (see :func:`claim_results_dir`).
        LaunchError: the run failed. Interrupted: a signal stopped it (every child stopped).
    """
    launcher = Launcher(mission, out, progress=progress, **kwargs)
    with stop_on_signals(launcher):
        try:
            result = launcher.run()
        except KeyboardInterrupt:
            launcher.stop_children()
            launcher.request_stop(signal.SIGINT)
            raise launcher.interrupted() from None
        if launcher.stop_requested:
            raise launcher.interrupted()  # a signal while the last records were gathered
    summaries = write_results([result], out, command=["fimnav", "launch", *sys.argv[2:]])
    summary = summaries[0]
    summary.update(
        distributed=True,
        dropped_messages=int(result.extra["dropped_messages"]),
        missing_drone_steps=int(result.extra["missing_drone_steps"]),
        failures=launcher.failures,
        clock=f"realtime x{launcher.speedup:g}" if launcher.realtime else "lockstep",
        taken_over=taken_over(out, mission.drones.count),
    )
    (out / "summary.json").write_text(json.dumps({"command": ["fimnav", "launch", *sys.argv[2:]], "runs": [summary]}, indent=2) + "\n")
    return summary
