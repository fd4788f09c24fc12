"""``fimnav launch``: the distributed swarm as separate processes on this machine.

The launcher validates the mission, starts one simulated vehicle (``fimnav vehicle``) and one
planner (``fimnav plan``) per drone as operating-system processes, runs the lockstep clock,
shows progress, and writes the results directory. It only starts, watches and records: every
decision is taken by the planners (docs/distributed.md, "The launcher").

Networking is loopback only: the launcher's Zenoh session listens on 127.0.0.1 at a free port
and every child connects to it (peers then find each other by gossip); each vehicle listens
for its planner's MAVLink on its own free UDP port on 127.0.0.1.

:class:`Launcher` composes the run's parts, each in its own module:

* :mod:`missions.runtime.rundir`: the results directory (a previous run is refused or overwritten);
* :mod:`missions.launch.supervisor`: the child processes (started, watched, failures dealt with,
  stopped: no orphan process, no port left bound, also when the launcher dies);
* :mod:`missions.runtime.signals`: Ctrl-C, SIGTERM and SIGHUP;
* :mod:`missions.launch.collect`: what is heard over Zenoh (records, statuses, readiness);
* :mod:`missions.launch.accounting`: the results, from the planners' step logs;
* :mod:`missions.launch.view`: the live view (``--view``).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import math
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from comms import keys
from comms.errors import UsageError
from comms.session import SessionSettings, open_session
from missions.format.loader import mission_to_yaml
from missions.format.schema import Mission
from missions.launch.accounting import launch_result, step_logs, taken_over
from missions.launch.clock import ClockError, LockstepClock
from missions.launch.collect import Collected, SwarmListener
from missions.launch.commands import payload_command, planner_command, vehicle_command
from missions.launch.supervisor import (
    MAX_RESTARTS,
    ON_FAILURE,
    STOP_GRACE_S,
    Child,
    ChildSupervisor,
    LaunchError,
    child_environment,
    free_port,
    vehicle_groups,
)
from missions.launch.view import LaunchView
from missions.runtime.rundir import RUN_ENTRIES, check_results_dir, claim_results_dir, previous_run, unique_results_dir
from missions.runtime.signals import STOP_SIGNALS, Interrupted, stop_on_signals
from missions.study.records import SimulationResult
from missions.study.results import write_results

__all__ = [
    "MAX_RESTARTS",
    "ON_FAILURE",
    "PROGRESS_STATS_PERIOD_S",
    "RUN_ENTRIES",
    "STOP_GRACE_S",
    "STOP_SIGNALS",
    "Child",
    "Collected",
    "Interrupted",
    "LaunchError",
    "Launcher",
    "check_results_dir",
    "child_environment",
    "claim_results_dir",
    "free_port",
    "launch",
    "previous_run",
    "stop_on_signals",
    "taken_over",
    "unique_results_dir",
]

log = logging.getLogger("fimnav.launch")

#: Wall time (s) between two refreshes of the progress bar's mean PEB and estimate error.
PROGRESS_STATS_PERIOD_S: float = 0.25

#: Wall time (s) the planners have to end the mission once the lockstep clock's end tick is sent.
END_OF_MISSION_S: float = 30.0


def _check_options(mission: Mission, vehicles_per_process: int, on_failure: str, realtime: bool, speedup: float) -> None:
    """Refuse options the run cannot take (before anything starts).

    Raises:
        LaunchError: a bad number of vehicles per process, failure policy or speed-up.
        UsageError: the mission asks for what ``fimnav launch`` does not do (a simulated
            partition; in real time, a simulated payload on an external autopilot without a
            second connection to it).
    """
    if vehicles_per_process < 1:
        raise LaunchError(f"vehicles per process: expected a positive integer, found {vehicles_per_process}")
    if on_failure not in ON_FAILURE:
        raise LaunchError(f"on failure: expected one of {', '.join(ON_FAILURE)}, found {on_failure!r}")
    if not (np.isfinite(speedup) and speedup > 0):
        raise LaunchError(f"speed-up: expected a positive number, found {speedup!r}")
    if mission.comms.faults.partition is not None:
        raise UsageError(
            "comms.faults.partition_start_step: a partition is simulated by fimnav montecarlo; the planner "
            "processes of fimnav launch are partitioned by cutting their network (docs/distributed.md, Partitions)"
        )
    if mission.policy != "fim":
        raise UsageError(
            f"policy: {mission.policy!r} is a baseline of fimnav montecarlo and fimnav sweep; the planner processes of fimnav launch fly 'fim'"
        )
    if realtime:
        for i in range(mission.drones.count):
            v = mission.vehicles.for_drone(i)
            if v.connection is not None and v.payload == "simulated" and v.payload_connection is None:
                raise UsageError(
                    f"drone {i + 1} flies the autopilot at {v.connection} and fimnav simulates its payload, which follows "
                    f"the autopilot over a second MAVLink connection: give vehicles.overrides[{i}].payload_connection "
                    f"(e.g. SITL's SERIAL1, tcp:127.0.0.1:5762), or payload: external if a real payload publishes its "
                    "measurements"
                )


class Launcher:
    """One distributed run of a mission.

    Args:
        mission: the validated mission (steps and seed already overridden).
        out: the results directory (the mission as run is written there and passed to the
            children).
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
            (:mod:`missions.launch.forkspawn`; each is still its own process and process group);
            False: ``python -m missions plan`` with ``subprocess`` (about 0.45 s of CPU each
            to import).
        overwrite: a results directory holding a previous run: remove that run's files
            (:data:`RUN_ENTRIES`) first; False: refuse it (:func:`claim_results_dir`).
        notice: called with a one-line message on what the launcher waits for (real time:
            the start delay); default: logged.
        gcs: real time: a MAVLink endpoint (``udpout:127.0.0.1:14550``) that every simulated
            vehicle's MAVLink is forwarded to, its frames routed back by target system
            (:class:`missions.launch.gcs.GcsRouter`); None: none.
        view: show the run live in a browser (:mod:`missions.launch.liveview`): rerun's web viewer on
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
        _check_options(mission, vehicles_per_process, on_failure, realtime, speedup)
        self.vehicles_per_process = vehicles_per_process
        self.on_failure = on_failure
        self.realtime = realtime
        self.speedup = float(speedup)
        self.start_delay_s = start_delay_s if start_delay_s is not None else 30.0 + 1.0 * n
        self.start_unix: float | None = None
        #: Real time: the ground-station endpoint every simulated vehicle is forwarded to.
        self.gcs_endpoint = gcs
        self._gcs: Any = None
        #: The live view (rerun): asked for, and its port.
        self.view = view
        self.view_port = view_port
        self._view = LaunchView(mission, out, view_port, self.notice) if view else None
        self._stop = threading.Event()
        self._signal: int | None = None  # the signal that asked the run to stop
        self.listener = SwarmListener(mission, self._planner_config)
        self.processes = ChildSupervisor(out, python, on_failure, fork_server, self._stop, taken_over=self.listener.taken_over_now)

    @property
    def collected(self) -> Collected:
        """What the launcher heard of the run over Zenoh."""
        return self.listener.collected

    @property
    def failures(self) -> list[dict[str, Any]]:
        """Every failure seen: {"process", "drones", "step", "status", "reason", "action"}."""
        return self.processes.failures

    @property
    def children(self) -> list[Child]:
        """Every child process started."""
        return self.processes.children

    # -- stopping ---------------------------------------------------------------------------
    def stop_children(self) -> None:
        """SIGTERM every child's process group, then SIGKILL what is left after the grace."""
        self.processes.stop_children()

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

    def _should_stop(self) -> bool:
        if self._stop.is_set():
            return True
        self.processes.check_children()
        return False

    # -- the run ----------------------------------------------------------------------------
    def run(self) -> SimulationResult:
        """Start everything, fly the mission, stop everything; return the run's records."""
        claim_results_dir(self.out, self.overwrite)
        mission_file = self._abs_out / "mission.yaml"
        mission_file.write_text(mission_to_yaml(self.mission))
        with self.processes.watchdog():
            return self._run(mission_file)

    def _open_router(self, hub: str) -> Any:
        """The launcher's Zenoh session, a router listening on ``hub``.

        Topology: a star. The launcher's session is a Zenoh router on a free loopback port and
        every child (planners, vehicles) a client of it: O(N) links, and every message is
        routed (Zenoh peers do not forward for each other, so in a mesh a message between two
        children whose direct link has not formed yet is lost; a full mesh of 2N+1 peers also
        costs O(N²) keep-alives). The mission's own endpoints (routers, other machines, another
        launch) are connected by the router, so the swarm joins a larger network."""
        base = SessionSettings.from_mission(self.mission.zenoh, listen=(hub,))
        session = open_session(dataclasses.replace(base, mode="router"))
        # Where operator tools reach the swarm while it flies (fimnav handback --results OUT).
        (self._abs_out / "logs" / "zenoh.json").write_text(json.dumps({"connect": [hub]}) + "\n")
        return session

    def _subscribe(self, session: Any) -> list[Any]:
        """Subscribe the listener to the records and statuses (and in real time the drones'
        readiness)."""
        m = self.mission
        subs = [
            session.declare_subscriber(keys.record(m.id), self.listener.on_record),
            session.declare_subscriber(keys.status(m.id), self.listener.on_status),
        ]
        if self.realtime:
            subs.append(session.declare_subscriber(keys.done(m.id), self.listener.on_done))
        return subs

    def _run(self, mission_file: Path) -> SimulationResult:
        """:meth:`run` once the results directory and the watchdog pipe are set up."""
        m = self.mission
        if self.processes.forks is not None:
            self.processes.forks.warm_up(self._abs_out / "logs")  # imports the planners' modules while the vehicles start
        hub = f"tcp/127.0.0.1:{free_port()}"
        session = self._open_router(hub)
        t_start = time.perf_counter()
        subs: list[Any] = []
        try:
            if self._view is not None:
                self._view.start()
            subs.extend(self._subscribe(session))
            clock = None if self.realtime else LockstepClock(session, m.id, m.drones.count, m.dt_s)
            self._start_children(mission_file, hub)
            if clock is None:
                self._fly_realtime()
                return self._result(time.perf_counter() - t_start)
            self._fly_lockstep(clock)
        except ClockError as exc:
            if self._stop.is_set():
                raise self.interrupted() from None
            self.processes.raise_child_failure()
            raise LaunchError(str(exc)) from None
        finally:
            if self._gcs is not None:
                self._gcs.close()
            if self._view is not None:
                self._view.stop()
            self.stop_children()
            for s in subs:
                with contextlib.suppress(Exception):
                    s.undeclare()
            session.close()
        return self._result(time.perf_counter() - t_start)

    # -- starting the children --------------------------------------------------------------
    def _start_children(self, mission_file: Path, hub: str) -> None:
        """Start the vehicles, wait for their MAVLink ports, then (real time: with the start
        time fixed) the simulated payloads of external autopilots and the planners."""
        m = self.mission
        n = m.drones.count
        child_zenoh = dataclasses.replace(SessionSettings.from_mission(m.zenoh), mode="client", listen=(), connect=(hub,))
        timing = ["--speedup", f"{self.speedup:g}"] if self.realtime else ["--lockstep"]
        # Drones flown on an external autopilot (a mixed fleet, real time) get no vehicle.
        external = {i for i in range(1, n + 1) if m.vehicles.for_drone(i - 1).connection is not None} if self.realtime else set()
        self.processes.external = {i: str(m.vehicles.for_drone(i - 1).connection) for i in sorted(external)}
        # Vehicles bind port 0 and report the port the OS gave them (no race with the
        # ephemeral ports of a hundred other sockets); planners start once they are known.
        vehicle_children = self._spawn_vehicles(mission_file, hub, timing, external)
        ports = self.processes.vehicle_ports(vehicle_children, self.preflight_timeout_s)
        if self.realtime and self.gcs_endpoint is not None:
            self._start_gcs(self.gcs_endpoint, ports)
        # The planners' modules and kernels loaded (compiled, the first time): they start at
        # once. A signal meanwhile stops the launch without waiting for a first compile.
        forks = self.processes.forks
        if forks is not None and not forks.wait_ready(notice=self.notice, stop=lambda: self.stop_requested):
            raise self.interrupted()
        if self.realtime:
            # On the UNIX grid of multiples of Δt/speed-up: the simulated payloads measure
            # just before each point of it (vehicle_sim.bridge).
            dtw = m.dt_s / self.speedup
            self.start_unix = float(np.ceil((time.time() + self.start_delay_s) / dtw) * dtw)
            timing = [*timing, "--start-at", f"{self.start_unix:.6f}", "--preflight-timeout", str(self.preflight_timeout_s)]
        self._spawn_payloads(mission_file, child_zenoh, external)
        self._spawn_planners(mission_file, child_zenoh, timing, external, ports)

    def _spawn_vehicles(self, mission_file: Path, hub: str, timing: list[str], external: set[int]) -> list[Child]:
        """Start the simulated vehicles, :attr:`vehicles_per_process` consecutive drones per
        process, every drone but the ``external`` ones."""
        m = self.mission
        vehicle_children = []
        for ids in vehicle_groups([i for i in range(1, m.drones.count + 1) if i not in external], self.vehicles_per_process):
            first = ids[0]
            name = f"vehicle_{first}" if len(ids) == 1 else f"vehicles_{first}-{ids[-1]}"
            # The ideal profile is a closed form (exact at any rate): in lockstep, 10 Hz
            # physics only sets how promptly a guided timeout is seen (0.1 s), and costs a
            # fifth of the default 50 Hz on the step's critical path.
            ideal = all(m.vehicles.for_drone(i - 1).profile == "ideal" for i in ids)
            physics = ["--physics-hz", "10"] if ideal and not self.realtime else []
            tlog = self._abs_out / "tlogs" / ("vehicle_{sysid}.tlog" if len(ids) > 1 else f"vehicle_{first}.tlog")
            vc = self.processes.spawn(name, vehicle_command(mission_file, ids, timing, physics, hub, tlog))
            vehicle_children.append(vc)
            for i in ids:
                self.processes.vehicle_child[i] = vc
        return vehicle_children

    def _start_gcs(self, endpoint: str, ports: dict[int, int]) -> None:
        """Real time: forward every simulated vehicle's MAVLink to the ground station."""
        from missions.launch.gcs import GcsRouter

        try:
            self._gcs = GcsRouter(endpoint, ports)
        except OSError as exc:
            raise LaunchError(f"--gcs {endpoint}: cannot open it ({exc})") from None
        self._gcs.start()
        self.notice(f"ground station port {endpoint}: vehicles {', '.join(str(i) for i in sorted(ports))} (system id = drone id)")

    def _spawn_payloads(self, mission_file: Path, child_zenoh: SessionSettings, external: set[int]) -> None:
        """A drone on an external autopilot: fimnav's simulated payload follows it over its
        second MAVLink connection, unless a real payload publishes."""
        for i in sorted(external):
            if self.mission.vehicles.for_drone(i - 1).payload == "simulated":
                self.processes.spawn(f"payload_{i}", payload_command(mission_file, i, self.speedup, child_zenoh, self.preflight_timeout_s))

    def _spawn_planners(self, mission_file: Path, child_zenoh: SessionSettings, timing: list[str], external: set[int], ports: dict[int, int]) -> None:
        """Start one planner per drone, to its simulated vehicle's port or (``external``) to the
        autopilot its mission names."""
        for i in range(1, self.mission.drones.count + 1):
            # An external autopilot's link is logged by its planner (a simulated vehicle
            # writes its own .tlog).
            conn = ["--tlog", str(self._abs_out / "tlogs" / f"vehicle_{i}.tlog")] if i in external else ["--mavlink", f"udpout:127.0.0.1:{ports[i]}"]
            step_log = self._abs_out / "logs" / f"planner_{i}.jsonl"
            self.processes.planner_args[i] = planner_command(mission_file, i, conn, timing, child_zenoh, step_log, self.step_timeout_s)
            self.processes.spawn(f"planner_{i}", self.processes.planner_args[i])

    # -- flying -----------------------------------------------------------------------------
    def _report_step(self, k: int, stats: tuple[float, float] | None, alive: int) -> None:
        """Progress and live view of step k (``stats``: the progress bar's mean PEB and error;
        None: computed now)."""
        if self.progress is not None:
            peb, err = stats if stats is not None else self.listener.live_stats(k)
            self.progress(k, peb, err, alive)
        if self._view is not None and self._view.running:
            self._view.step(k, self.listener.heard_at(k))

    def _fly_lockstep(self, clock: LockstepClock) -> None:
        """Lockstep: pre-flight, every step on the clock, then the end of the mission."""
        m = self.mission
        t0 = clock.preflight(self.preflight_timeout_s, self._should_stop)
        self.processes.flying = True
        stats_at, stats = -math.inf, (math.inf, math.nan)
        for k in range(m.steps):
            self.processes.step = k
            # The planners' own deadline expires first and names what they waited for.
            report = clock.run_step(k, t0, self.step_timeout_s + 15.0, self._should_stop)
            if self.progress is not None:
                # The PEB of every view costs this process ~1 ms a step, on the cores the
                # swarm steps on: refreshed a few times a second (and at the last step).
                now = time.monotonic()
                if now - stats_at >= PROGRESS_STATS_PERIOD_S or k == m.steps - 1:
                    stats = self.listener.live_stats(k)
                    stats_at = now
            self._report_step(k, stats, len(report.alive))
        self._end_lockstep(clock, t0)
        self.processes.check_children()

    def _end_lockstep(self, clock: LockstepClock, t0: float) -> None:
        """The end tick releases the planners: they end the mission (hold, land or RTL) and
        exit. It is re-sent every second for a planner that missed it.

        Raises:
            Interrupted: a signal asked the run to stop meanwhile.
            LaunchError: a planner did not exit within :data:`END_OF_MISSION_S`.
        """
        steps = self.mission.steps
        clock.end(steps, t0)
        deadline = time.monotonic() + END_OF_MISSION_S
        resend = time.monotonic() + 1.0
        for c in self.processes.planners():
            if c.proc.pid in self.processes.handled:
                continue
            while c.proc.poll() is None:
                if self._stop.is_set():
                    raise self.interrupted()
                now = time.monotonic()
                if now > deadline:
                    raise LaunchError(f"{c.name} did not finish its end of mission within {END_OF_MISSION_S:g} s:\n{c.tail()}")
                if now >= resend:
                    clock.end(steps, t0)
                    resend = now + 1.0
                with contextlib.suppress(subprocess.TimeoutExpired):
                    c.proc.wait(min(0.2, max(0.0, deadline - now)))

    def _notice_readiness(self, ready_seen: int, now: float) -> tuple[int, bool]:
        """Real time, before step 0: say how many drones are at their starts when that
        changes, and at step 0 how many are. Returns (the count said, step 0 has come)."""
        if self.start_unix is None:
            raise RuntimeError("real-time flight without a start time (start_unix is set when the planners are started)")
        n = self.mission.drones.count
        ready = self.listener.ready_count()
        if now >= self.start_unix:
            if ready < n:
                self.notice(f"step 0: {ready}/{n} drones at their starts; the others join when they get there")
            return ready_seen, True
        if ready != ready_seen:
            self.notice(f"{ready}/{n} drones ready at their starts (step 0 in {self.start_unix - now:.0f} s)")
            return ready, False
        return ready_seen, False

    def _fly_realtime(self) -> None:
        """Real time: say what the start delay waits for, then report progress on the wall
        clock until every planner has ended."""
        m = self.mission
        if self.start_unix is None:
            raise RuntimeError("real-time flight without a start time (start_unix is set when the planners are started)")
        dtw = m.dt_s / self.speedup
        self.processes.flying = True
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
            planners = self.processes.planners()
            now = time.time()
            if not started:
                ready_seen, started = self._notice_readiness(ready_seen, now)
            ended = all(c.proc.poll() is not None for c in planners)
            if ended:
                self.processes.check_children()  # failures are dated by the step in progress
            # Every step once the planners have ended (the last one's records are in by then).
            done = m.steps - 1 if ended else min(int((now - self.start_unix) / dtw) - 1, m.steps - 1)
            while reported < done:
                reported += 1
                self.processes.step = reported
                self._report_step(reported, None, sum(c.proc.poll() is None for c in planners))
            if ended:
                return
            if now > end_by:
                raise LaunchError(f"the planners did not end the mission by {end_by - self.start_unix:.0f} s after step 0")
            self._stop.wait(0.1)  # polling the children, with the deadline above

    # -- results ----------------------------------------------------------------------------
    def _result(self, runtime_s: float) -> SimulationResult:
        """The run as a one-trial :class:`SimulationResult` (same accounting as the simulator),
        from the planners' step logs, completed by what was heard over Zenoh
        (:func:`missions.launch.accounting.launch_result`)."""
        logs = step_logs(self.out, self.mission.drones.count)
        return launch_result(self.mission, self._planner_config, self.collected, logs, self.realtime, runtime_s)


def launch(
    mission: Mission, out: Path, progress: Callable[[int, float, float, int], None] | None = None, figures: bool = True, **kwargs: Any
) -> dict[str, Any]:
    """Fly ``mission`` distributed and write the results directory (its PNG figures too if
    ``figures``); return the summary. ``kwargs`` go to :class:`Launcher`.

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
    launched = {
        "distributed": True,
        "dropped_messages": int(result.extra["dropped_messages"]),
        "missing_drone_steps": int(result.extra["missing_drone_steps"]),
        "failures": launcher.failures,
        "clock": f"realtime x{launcher.speedup:g}" if launcher.realtime else "lockstep",
        "taken_over": taken_over(out, mission.drones.count),
    }
    return write_results([result], out, figures=figures, command=["fimnav", "launch", *sys.argv[2:]], extras=[launched])[0]
