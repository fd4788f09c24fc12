"""The planner node: one process per drone (``fimnav plan``), at the edge of the math core.

It flies one drone of a mission. Zenoh carries the swarm's records, the payload's measurements
and, in lockstep simulation, the clock; MAVLink carries the setpoints to its own autopilot.
Each step, in order (DESIGN.md): read own position (MAVLink) → take own measurement (payload)
→ publish own record → collect the peers' records for the step → delayed view → estimate the
source → control step under constraints → send the setpoint (position with velocity
feed-forward). The maths is :func:`planner.agent.plan`, the same function the in-process
simulator runs, so a lockstep run reproduces the simulator.

Lockstep protocol (docs/distributed.md): the clock publishes ``Tick(step=-1, t)`` during the
pre-flight (take-off, fly to the start position) and each participant answers ``Done(-1)`` once
it holds its start position; then ``Tick(k, t_k)`` for k = 0..K-1, each after every live
planner has published ``Done(k-1)``. The vehicle advances to t_k on the tick and its payload
publishes the measurement of step k; the planner waits for telemetry stamped ≥ t_k and for
that measurement, and publishes ``Done(k)`` once its setpoint is on the wire.

Real time (external autopilots, docs/external-autopilots.md): the planner detects the
autopilot (HEARTBEAT.autopilot), requests its streams, checks that the vehicle's clock runs
at the planner's speed-up (its time_boot_ms against the wall clock), waits until it is ready to
fly (GPS, EKF, home, EKF origin; the log says what is missing), takes off by the autopilot's rules
(ArduPilot: GUIDED, arm, NAV_TAKEOFF; PX4: setpoint stream first, OFFBOARD, arm) and flies to
its start. Step k then begins at wall time ``t0 + k·dt/speedup`` on a grid shared by every
planner of the mission (UNIX time multiples of dt/speedup, or ``--start-at``); the own
measurement is the newest payload measurement not older than a bound; the peers' records of
step k are gathered until a deadline inside the step, never a barrier; the setpoint is a
short trajectory towards the planned position, re-sent at ≥ 4 Hz of mission time until the
next step replaces it, so a late step never leaves the vehicle without a setpoint. A lost
vehicle link (no heartbeat for 2 s) is reported; the planner keeps publishing its last record
flagged stale, and resumes (back into GUIDED/OFFBOARD) when the heartbeat returns.

Pilot take-over, in both clocks (docs/in-the-field.md): a vehicle that leaves GUIDED/OFFBOARD
(a ground station or the RC switched it to LOITER, LAND, RTL, ...) is no longer commanded from
the moment the planner sees the mode; every step the planner publishes the drone's telemetry
position as a record flagged ``taken_over`` without a measurement (the others keep clear of
it) and, in lockstep, still answers the step (``Done(k)``: the clock never waits for a drone a
pilot flies). It never switches the vehicle back on its own: ``fimnav handback`` does, and the
planner plans again from where the drone is.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import math
import os
import queue
import select
import time
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TextIO

import numpy as np

from comms import keys
from comms.errors import FimnavError
from comms.geodesy import MissionFrame
from comms.latency import DelayedView
from comms.mavlink_client import (
    MAV_LANDED_STATE_NAMES,
    MSG_EKF_STATUS_REPORT,
    MSG_EXTENDED_SYS_STATE,
    MSG_GLOBAL_POSITION_INT,
    MSG_GPS_GLOBAL_ORIGIN,
    MSG_GPS_RAW_INT,
    MSG_HOME_POSITION,
    MSG_LOCAL_POSITION_NED,
    MSG_SYS_STATUS,
    Frame,
    LinkError,
    VehicleLink,
    read_signing_key,
)
from comms.messages import Done, MessageError, MessageKind, Observation, Status, Tick, decode, encode
from comms.pubsub import declare_publisher
from comms.session import SessionSettings, open_session
from planner import estimator as est
from planner.agent import OWN_RANGE_WINDOW, PlanView, own_range_lower_bound_m, plan
from planner.geometry import vec3
from planner.params import Channel
from planner.randomness import CONTROL_DRAWS, control_rng

log = logging.getLogger("fimnav.plan")

#: Distance (m) within which the vehicle counts as at its start position.
START_TOLERANCE_M: float = 0.05
#: The same in real time, for a vehicle with real dynamics (m).
START_TOLERANCE_REALTIME_M: float = 0.3
#: Real time: a position older than this (wall s) is not planned on.
POSITION_MAX_AGE_S: float = 1.0
#: Real time: how often (wall s) the log repeats what the vehicle still lacks to fly.
READY_REPORT_PERIOD_S: float = 5.0
#: Real time: the vehicle's clock (``time_boot_ms`` against the wall clock) may run this far
#: (relative) from the planner's ``--speedup`` before the planner refuses to take off.
CLOCK_RATE_TOLERANCE: float = 0.25
#: Real time: how long (wall s) the clock check may wait for enough ``time_boot_ms`` samples.
CLOCK_CHECK_TIMEOUT_S: float = 15.0
#: Lockstep telemetry rates (message id -> Hz of sim time): a simulated vehicle in lockstep
#: reports its position on every tick, so the streams only need to be slow (every message is
#: parsed here and logged by the vehicle). LOCAL_POSITION_NED, GLOBAL_POSITION_INT,
#: HOME_POSITION, EXTENDED_SYS_STATE, ATTITUDE, VFR_HUD.
LOCKSTEP_STREAM_HZ: tuple[tuple[int, float], ...] = ((32, 1.0), (33, 0.2), (242, 0.2), (245, 0.2), (30, 0.2), (74, 0.2))
#: Lockstep, once airborne: the health streams the pre-flight reads (SYS_STATUS, GPS_RAW_INT,
#: SYSTEM_TIME, BATTERY_STATUS, EKF_STATUS_REPORT; ArduPilot's defaults are 0.5-1 Hz) slowed to
#: 0.2 Hz of sim time. In lockstep the vehicles run ~20x real time and packed, sent and parsed
#: about 3.5 such messages per drone and step for nothing: the vehicles' process packs the
#: telemetry of every drone between a tick and the planners' measurements.
LOCKSTEP_FLIGHT_STREAM_HZ: tuple[tuple[int, float], ...] = ((1, 0.2), (24, 0.2), (2, 0.2), (147, 0.2), (193, 0.2))
#: What each autopilot's own failsafe does while the planner's link is lost (for the log).
FAILSAFE_NOTE = {
    "ardupilot": "ArduPilot keeps GUIDED: the last position target holds; a velocity part stops after "
    "GUID_TIMEOUT; a GCS failsafe (FS_GCS_ENABLE) acts only if this link is the GCS (SYSID_MYGCS)",
    "px4": "PX4 leaves OFFBOARD after COM_OF_LOSS_T and takes COM_OBL_RC_ACT (hold, land or RTL); a data-link loss (NAV_DLL_ACT) may follow",
}


class NodeError(FimnavError):
    """The planner cannot go on (vehicle refused, lost peers beyond the deadline, ...)."""


#: Steps of own positions a planner keeps (the partition planes need the step of a peer's
#: last record; for a peer silent for longer the plane is drawn from the current position).
OWN_TRACK_STEPS = 5000


@dataclass(frozen=True)
class NodeOptions:
    """How one planner node runs.

    Attributes:
        uav: drone id, 1-based (also the vehicle's MAVLink system id unless ``sysid``).
        mavlink: pymavlink connection string to the vehicle.
        zenoh: session settings.
        lockstep: step on the lockstep clock (simulation) rather than the wall clock.
        steps: number of steps (default: the mission's).
        sysid: the vehicle's system id (default: ``uav``).
        log_path: JSON-lines log of every step.
        step_timeout_s: how long to wait for a tick, a measurement or the peers' records.
        preflight_timeout_s: how long the take-off and the flight to the start may take.
        speedup: real time only: mission seconds per wall second (1 for a real vehicle; the
            ``--speedup`` of a simulated vehicle in tests).
        flavour: ``"auto"`` (from HEARTBEAT.autopilot), ``"ardupilot"`` or ``"px4"``; None:
            the mission's ``vehicles.overrides[i].flavour`` (absent: auto).
        setpoint_frame: ``"auto"``, ``"global"`` or ``"local_ned"``; None: the mission's.
        signing_key_file: MAVLink 2 signing key; None: the mission's (absent: no signing).
        stream_hz: real time: setpoint stream rate in mission-time Hz (≥ 4).
        peer_wait_fraction: real time: the peers' records of step k are awaited until
            ``t_k + peer_wait_fraction · dt``.
        measurement_max_age_s: real time: the newest payload measurement is used if it is
            at most this old (mission seconds; None: one step, dt).
        start_at_unix: real time: UNIX time of step 0 (None: the next multiple of dt/speedup
            after the planner is at its start, so planners started apart share the grid).
        end_timeout_s: real time: how long the end of mission (landing) may take (wall s).
        rejoin: lockstep: this planner replaces one that died mid-mission. It skips the
            pre-flight (the vehicle is airborne and armed), answers the clock's current step
            as skipped and flies from the next one, with a fresh estimator; its log is
            appended to, not overwritten.
        tlog_path: real time: write the MAVLink link to this .tlog (every frame in and out),
            as ``fimnav launch`` does for an external autopilot.
    """

    uav: int
    mavlink: str
    zenoh: SessionSettings = field(default_factory=SessionSettings)
    lockstep: bool = True
    steps: int | None = None
    sysid: int | None = None
    log_path: Path | None = None
    step_timeout_s: float = 30.0
    preflight_timeout_s: float = 120.0
    speedup: float = 1.0
    flavour: Literal["auto", "ardupilot", "px4"] | None = None
    setpoint_frame: Literal["auto", "global", "local_ned"] | None = None
    signing_key_file: Path | None = None
    stream_hz: float = 5.0
    peer_wait_fraction: float = 0.5
    measurement_max_age_s: float | None = None
    start_at_unix: float | None = None
    end_timeout_s: float = 120.0
    rejoin: bool = False
    tlog_path: Path | None = None

    def __post_init__(self) -> None:
        for name in ("speedup", "stream_hz", "step_timeout_s", "preflight_timeout_s", "end_timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise NodeError(f"{name}: expected a positive number, found {v!r}")
        if self.stream_hz < 4.0:
            raise NodeError(f"stream_hz: expected at least 4 Hz (the setpoint stream keeps the autopilot's timeouts away), found {self.stream_hz:g}")
        if not 0.0 < self.peer_wait_fraction < 1.0:
            raise NodeError(f"peer_wait_fraction: expected a fraction of the step in (0, 1), found {self.peer_wait_fraction!r}")
        if self.flavour not in (None, "auto", "ardupilot", "px4"):
            raise NodeError(f"flavour: expected auto, ardupilot or px4, found {self.flavour!r}")
        if self.setpoint_frame not in (None, "auto", "global", "local_ned"):
            raise NodeError(f"setpoint frame: expected auto, global or local_ned, found {self.setpoint_frame!r}")


class _Inbox:
    """Messages from Zenoh callbacks, handed to the node's single thread through a queue."""

    def __init__(self, mission_id: str, count: int) -> None:
        self.mission_id = mission_id
        self.count = count
        #: (kind, key expression, payload): kind "data", or "alive"/"gone" for a liveliness
        #: change (no payload: b"").
        self.queue: queue.SimpleQueue[tuple[str, str, bytes]] = queue.SimpleQueue()
        self.dropped: Counter[str] = Counter()
        # Self-pipe: a callback makes it readable so the node's select() wakes at once.
        self.wake_r, self.wake_w = os.pipe()
        os.set_blocking(self.wake_r, False)
        os.set_blocking(self.wake_w, False)

    def _put(self, item: tuple[str, str, bytes]) -> None:
        self.queue.put(item)
        try:
            os.write(self.wake_w, b"z")
        except (BlockingIOError, OSError):
            pass  # already readable (or closing)

    def on_sample(self, sample: Any) -> None:
        self._put(("data", str(sample.key_expr), bytes(sample.payload.to_bytes())))

    def on_liveliness(self, sample: Any) -> None:
        self._put(("alive" if str(sample.kind).endswith("PUT") else "gone", str(sample.key_expr), b""))

    def clear_wake(self) -> None:
        try:
            while os.read(self.wake_r, 4096):
                pass
        except (BlockingIOError, OSError):
            pass

    def close(self) -> None:
        for fd in (self.wake_r, self.wake_w):
            try:
                os.close(fd)
            except OSError:
                pass

    def decode(self, key: str, data: bytes) -> Any | None:
        """The message, or None (counted, warned) if it is invalid or spoofed."""
        try:
            header, msg = decode(data, self.mission_id, self.count)
        except MessageError as exc:
            reason = str(exc).split(":")[0][:60]
            self.dropped[reason] += 1
            log.warning("dropped message on %s: %s", key, exc)
            return None
        key_uav = keys.uav_of(key)
        sender = getattr(msg, "sender", None)
        if sender is not None and key_uav is not None and key_uav != sender:
            self.dropped["sender id does not match the key"] += 1
            log.warning("dropped message on %s: sender %s does not match the key expression", key, sender)
            return None
        if header.kind == MessageKind.MEASUREMENT and "/measurement/" not in key:
            self.dropped["measurement on a record key"] += 1
            return None
        if header.kind == MessageKind.RECORD and "/record/" not in key:
            self.dropped["record on another key"] += 1
            return None
        return msg


class PlannerNode:
    """One drone's planner: MAVLink to its vehicle, Zenoh to the swarm.

    Args:
        mission: the mission (``missions.schema.Mission``; duck-typed here).
        options: how to run.
        link_factory: builds the :class:`VehicleLink` (injectable for tests).
        session_factory: opens the Zenoh session (injectable for tests).
        wall: monotonic wall clock (s).
        unix: UNIX wall clock (s): the real-time step grid and record times.
    """

    def __init__(
        self,
        mission: Any,
        options: NodeOptions,
        link_factory: Callable[[str, int], VehicleLink] | None = None,
        session_factory: Callable[[SessionSettings], Any] = open_session,
        wall: Callable[[], float] = time.monotonic,
        unix: Callable[[], float] = time.time,
    ) -> None:
        self.m = mission
        self.o = options
        self.wall = wall
        self.unix = unix
        n = mission.drones.count
        if not 1 <= options.uav <= n:
            raise NodeError(f"--uav {options.uav}: the mission has drones 1..{n}")
        self.i = options.uav - 1
        self.n = n
        self.steps = options.steps or mission.steps
        self.dt = mission.dt_s
        #: The mission's planning parameters, one source for each (:class:`planner.config.PlannerConfig`).
        self.config = mission.planner_config()
        self.start = mission.drones.start_positions_m()[self.i]
        self.ctrl_rng = control_rng(mission.seed, 0, self.i)
        self.view = DelayedView(
            self.i,
            n,
            mission.comms.d_hop_m,
            mission.comms.h_max,
            emulate=mission.comms.latency == "emulated",
            faults=mission.comms.faults.to_model(),
            seed=mission.seed,
        )
        self.inbox = _Inbox(mission.id, n)
        resolved = mission.vehicles.for_drone(self.i)
        self.flavour_setting = options.flavour or resolved.autopilot
        frame = options.setpoint_frame or resolved.setpoint_frame
        self.frame: Frame = ("local_ned" if options.lockstep else "global") if frame == "auto" else frame
        key_file = options.signing_key_file or resolved.signing_key_file
        # Read (and permission-check) the key before anything opens: a refused key starts nothing.
        self._signing_key = read_signing_key(key_file) if key_file is not None else None
        self.mission_frame = MissionFrame.of_mission(mission)
        self._link_factory = link_factory or self._default_link
        # Real-time state.
        self.t0_unix: float | None = None
        self.dt_wall = self.dt / options.speedup
        self.latest_measurement: Observation | None = None
        self.link_down_since: float | None = None
        self.resume_needed = False
        self.link_losses: list[dict[str, float]] = []
        self.last_record: Observation | None = None
        self.late_steps = 0
        self.mode_changes: list[str] = []
        self.stale_peers: dict[int, int] = {}  # drone id -> last step it said "stale"
        self.position_gaps = 0
        self._reported_mode: str | None = None
        #: The pilot's take-over in force ({"step", "mode"}), or None; every one.
        self.taken_over: dict[str, Any] | None = None
        self.takeovers: list[dict[str, Any]] = []
        self.taken_over_steps = 0
        #: Operator commands from ``fimnav/<id>/control/<uav>`` (Zenoh thread → main loop).
        self.control: queue.SimpleQueue[str] = queue.SimpleQueue()
        self.vehicle_clock_rate: float | None = None
        self._session_factory = session_factory
        self.session: Any = None
        self.link: VehicleLink | None = None
        self.alive: set[int] = set()
        #: Planners whose liveliness token went away (and did not come back).
        self.left: set[int] = set()
        #: The step this planner was at when each of them left (its records up to then are late
        #: ones, not a rejoin).
        self.left_at: dict[int, int] = {}
        #: Lockstep: when this drone's vehicle's liveliness token went (monotonic s), if it did.
        self.vehicle_gone_at: float | None = None
        self.step_now = -1
        self.tick: Tick | None = None
        self.measurements: dict[int, Observation] = {}
        #: This drone's own last ranges and LOS flags (the second source keep-out, planner.agent).
        self.own_ranges: deque[tuple[float, bool]] = deque(maxlen=OWN_RANGE_WINDOW)
        #: This drone's own positions by step (m, ENU), the last OWN_TRACK_STEPS: where it was
        #: when each peer's last record was taken (the partition planes, planner.agent.plan).
        self.own_track: dict[int, np.ndarray] = {}
        #: A rejoining planner's step logs: its predecessor's and its peers' (drone index → rows).
        self.predecessor_rows: dict[int, list[dict[str, Any]]] = {}
        self.seq = 0
        self._log: TextIO | None = None

    def _default_link(self, conn: str, sysid: int) -> VehicleLink:
        forced = None if self.flavour_setting == "auto" else self.flavour_setting
        return VehicleLink(
            conn,
            sysid,
            signing_key=self._signing_key,
            wall=self.wall,
            frame=self.frame,
            mission_frame=self.mission_frame,
            altitude_reference=self.m.altitude_reference,
            flavour=forced,
            tlog=self.o.tlog_path,
        )

    # -- plumbing ---------------------------------------------------------------------------
    def _open(self) -> None:
        mid = self.m.id
        self.session = self._session_factory(self.o.zenoh)
        s = self.session
        self._subs = [
            s.declare_subscriber(keys.record(mid), self.inbox.on_sample),
            s.declare_subscriber(keys.measurement(mid, self.o.uav), self.inbox.on_sample),
            s.declare_subscriber(keys.tick(mid), self.inbox.on_sample),
            s.liveliness().declare_subscriber(keys.alive(mid, "planner"), self.inbox.on_liveliness, history=True),
        ]
        if self.o.lockstep:
            # The simulated vehicle's bridge holds a token: its process dying is seen at once.
            self._subs.append(
                s.liveliness().declare_subscriber(keys.alive(mid, "vehicle", self.o.sysid or self.o.uav), self.inbox.on_liveliness, history=True)
            )
        self._subs.append(s.declare_subscriber(keys.control(mid, self.o.uav), self._on_control))
        self._token = s.liveliness().declare_token(keys.alive(mid, "planner", self.o.uav))
        self._pub_record = declare_publisher(s, keys.record(mid, self.o.uav))
        self._pub_status = declare_publisher(s, keys.status(mid, self.o.uav))
        self._pub_done = declare_publisher(s, keys.done(mid, self.o.uav))
        if self.o.log_path is not None:
            self.o.log_path.parent.mkdir(parents=True, exist_ok=True)
            if self.o.rejoin:
                # Its own log (the predecessor's) and, named as a launch names them, its peers'.
                path = self.o.log_path
                self.predecessor_rows = {self.i: read_step_log(path)}
                if path.name == f"planner_{self.o.uav}.jsonl":
                    for j in range(self.n):
                        peer = path.with_name(f"planner_{j + 1}.jsonl")
                        if j != self.i and peer.exists():
                            self.predecessor_rows[j] = read_step_log(peer)
            self._log = self.o.log_path.open("a" if self.o.rejoin else "w")
        self.link = self._link_factory(self.o.mavlink, self.o.sysid or self.o.uav)

    def close(self) -> None:
        """Release the link, the Zenoh session and the log (idempotent)."""
        if self.link is not None:
            self.link.close()
            self.link = None
        if self.session is not None:
            try:
                self._token.undeclare()
            except Exception:  # closing anyway
                pass
            self.session.close()
            self.session = None
        if self._log is not None:
            self._log.close()
            self._log = None
        self.inbox.close()

    def _publish(self, publisher: Any, msg: Any, kind: MessageKind | None = None) -> None:
        self.seq += 1
        publisher.put(encode(msg, self.m.id, self.seq, kind))

    def _on_control(self, sample: Any) -> None:
        """An operator command (Zenoh callback thread): queued for the main loop, which checks it."""
        try:
            self.control.put(bytes(sample.payload.to_bytes()).decode("utf-8", "replace"))
        except Exception as exc:  # a bad sample must not kill the callback thread
            log.warning("uav %d: unreadable control message ignored (%s)", self.o.uav, exc)

    def _handback_requested(self) -> bool:
        """Whether a valid ``{"command": "handback"}`` arrived since the last call; anything
        else is logged (naming what was wrong) and ignored."""
        asked = False
        while True:
            try:
                text = self.control.get_nowait()
            except queue.Empty:
                return asked
            try:
                msg = json.loads(text)
            except ValueError:
                log.warning("uav %d: control message is not JSON, ignored: %.80r", self.o.uav, text)
                continue
            if isinstance(msg, dict) and msg.get("command") == "handback":
                asked = True
            else:
                log.warning('uav %d: control message without a known command (expected {"command": "handback"}), ignored: %.80r', self.o.uav, text)

    def _drain(self, timeout_s: float = 0.0) -> None:
        """Handle queued Zenoh messages (waiting up to ``timeout_s`` for the first)."""
        try:
            item = self.inbox.queue.get(timeout=timeout_s) if timeout_s > 0 else self.inbox.queue.get_nowait()
        except queue.Empty:
            return
        while True:
            kind, key, data = item
            if kind == "data":
                msg = self.inbox.decode(key, data)
                if isinstance(msg, Observation):
                    if "/measurement/" in key:
                        if self.o.lockstep:
                            self.measurements[msg.step] = msg
                        elif self.latest_measurement is None or msg.time_s >= self.latest_measurement.time_s:
                            self.latest_measurement = msg
                    elif self.o.lockstep:
                        if msg.sender in self.left and msg.step > self.left_at.get(msg.sender, -1):
                            # A planner that left is waited for again once its records flow
                            # (a restarted planner skips the step it joins at).
                            self.left.discard(msg.sender)
                            log.warning("planner %d rejoined the swarm at step %d", msg.sender, msg.step)
                        self.view.add(msg)
                    else:
                        self._add_realtime_record(msg)
                elif isinstance(msg, Tick) and (self.tick is None or msg.step >= self.tick.step):
                    self.tick = msg
            elif "/alive/vehicle/" in key:
                if kind == "gone" and self.vehicle_gone_at is None:
                    self.vehicle_gone_at = self.wall()
                    log.error("uav %d: the vehicle's process left the swarm (liveliness token gone)", self.o.uav)
                elif kind == "alive":
                    self.vehicle_gone_at = None
            else:
                uav = keys.uav_of(key)
                if uav is not None and 1 <= uav <= self.n:
                    (self.alive.add if kind == "alive" else self.alive.discard)(uav)
                    if kind == "gone" and uav != self.o.uav:
                        self.left.add(uav)
                        self.left_at[uav] = self.step_now
                    elif kind == "alive" and uav in self.left and not self.o.lockstep:
                        # (in lockstep a planner that left counts again from its first record)
                        self.left.discard(uav)
                        log.warning("planner %d is back in the swarm", uav)
                        log.warning("planner %d left the swarm", uav)
            try:
                item = self.inbox.queue.get_nowait()
            except queue.Empty:
                return

    def _wait(self, predicate: Callable[[], bool], timeout_s: float, what: str, missing: Callable[[], Any] | None = None) -> None:
        """Serve Zenoh and MAVLink until ``predicate()``; NodeError naming ``what`` on timeout.

        Blocks in select() on the MAVLink socket and the Zenoh self-pipe: no busy polling."""
        link = self._require_link()
        deadline = self.wall() + timeout_s
        self._drain(0.0)
        link.pump(0.0)
        while not predicate():
            remaining = deadline - self.wall()
            if remaining <= 0:
                detail = f" (missing: {missing()})" if missing is not None else ""
                raise NodeError(f"uav {self.o.uav}: no {what} within {timeout_s:g} s{detail}")
            self._sleep_io(min(remaining, 0.25))

    def _sleep_io(self, timeout_s: float) -> None:
        """Block in select() on the MAVLink socket and the Zenoh self-pipe for at most
        ``timeout_s`` (and at most one setpoint-stream period), then serve both."""
        link = self._require_link()
        if not self.o.lockstep:
            timeout_s = min(timeout_s, link.stream_period_s)
        fd = link.fileno()
        fds = [self.inbox.wake_r] + ([fd] if fd is not None else [])
        try:
            select.select(fds, [], [], max(timeout_s, 0.0))
        except (OSError, ValueError):
            pass
        self.inbox.clear_wake()
        self._drain(0.0)
        link.pump(0.0)
        if not self.o.lockstep:
            self._check_link()

    def _require_link(self) -> VehicleLink:
        if self.link is None:
            raise NodeError(f"uav {self.o.uav}: the vehicle link is closed")
        return self.link

    # -- flight -----------------------------------------------------------------------------
    def preflight(self) -> None:
        """Heartbeat, streams, GUIDED, arm, take-off and flight to the start position."""
        link = self._require_link()
        t = self.o.preflight_timeout_s
        link.wait_heartbeat(t)
        rates = dict(LOCKSTEP_STREAM_HZ) if self.o.lockstep else {32: 10.0, 33: 5.0, 242: 0.2, 245: 1.0}
        for msg_id, hz in rates.items():
            link.request_interval(msg_id, hz)
        self._wait(lambda: link.telemetry.position_enu_m is not None, t, "position telemetry")
        mode = "OFFBOARD" if link.is_px4 else "GUIDED"
        if not link.telemetry.armed:
            if link.is_px4:
                # PX4 accepts OFFBOARD only with a setpoint stream already running.
                for _ in range(5):
                    link.send_setpoint(link.telemetry.position_enu_m, None)
            link.set_mode(mode)
            link.arm()
            climb_to = float(self.start[2])
            if not link.is_px4:
                link.takeoff(climb_to)

                def climbed() -> bool:
                    pos = link.telemetry.position_enu_m
                    return pos is not None and pos[2] >= climb_to - START_TOLERANCE_M

                self._wait_preflight(climbed, "take-off altitude")
        else:
            link.set_mode(mode)
        self._wait_preflight(lambda: self._hold_start() < START_TOLERANCE_M, "start position")

    def _hold_start(self) -> float:
        """Send the start position as setpoint; return the distance to it (m)."""
        link = self._require_link()
        link.send_setpoint(self.start, None)
        pos = link.telemetry.position_enu_m
        return math.inf if pos is None else float(np.linalg.norm(pos - self.start))

    def _wait_preflight(self, predicate: Callable[[], bool], what: str) -> None:
        """Wait for a pre-flight condition; in lockstep, report Done(-1) only when ready."""
        self._wait(predicate, self.o.preflight_timeout_s, what)

    # -- the mission ------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        """Fly the mission; return a summary (steps done, dropped messages)."""
        try:
            self._open()
            self._drain(0.0)
            if not self.o.lockstep:
                return self._run_realtime()
            first = self._rejoin() if self.o.rejoin else self._start()
            state = est.initial_state((), self.config.estimator)
            used = np.full(self.n, -1, dtype=np.int64)
            if self.o.rejoin:
                state = self._rebuild(state, first, used)
            prev_step = np.zeros(3)
            done_steps = 0
            for k in range(first, self.steps):
                self.step_now = k
                w0 = self.wall()
                t_k = self._await_step(k)
                w_tick = self.wall()
                own = self._own_position(t_k)
                # The vehicle's mode comes with the tick's position (vehicle_sim sends a heartbeat
                # with the first tick report after a mode change).
                self._watch_mode(k)
                if self.taken_over is not None and not (self._handback_requested() and self._hand_back(k)):
                    self._taken_over_step(k, t_k, own)
                    prev_step = np.zeros(3)
                    continue
                meas = self._measurement(k)
                w_meas = self.wall()
                record = Observation(
                    self.o.uav,
                    k,
                    t_k,
                    vec3(own),
                    bool(self.config.ranging[self.i]),
                    bool(self.config.bearing[self.i]),
                    meas.los,
                    meas.range_m,
                    meas.azimuth_rad,
                    meas.elevation_rad,
                )
                self.view.add(record)
                self.own_ranges.append((record.range_m, record.los))
                self._track(k, own)
                self._publish(self._pub_record, record, MessageKind.RECORD)
                self._wait_for_peer_records(k)
                w_peers = self.wall()
                view, state, rows, used, result = self._view_estimate_plan(k, own, prev_step, state, used)
                step = result.step
                u = np.asarray(step.displacement, dtype=float)
                nxt = np.asarray(step.next_position, dtype=float)
                if self.link is None:
                    raise NodeError(f"uav {self.o.uav}: the vehicle link is closed")
                # A heartbeat read while the step was planned (the 1 Hz one) may say the vehicle
                # was taken over meanwhile: then this step's setpoint is not sent.
                self.link.pump(0.0)
                self._watch_mode(k)
                if self.taken_over is not None:
                    self.taken_over_steps += 1
                    self._publish(self._pub_done, Done(self.o.uav, k))
                    prev_step = np.zeros(3)
                    continue
                # One setpoint for the whole step. ArduPilot's GUIDED moves a position+velocity
                # target along its velocity (from here it reaches nxt after dt); PX4 holds the
                # point and takes the velocity as a feed-forward.
                self.link.send_setpoint(nxt if self.link.is_px4 else own, u / self.dt)
                w_sent = self.wall()
                prev_step = u
                active_mask = int(sum(1 << b for b, a in enumerate(np.asarray(step.active)) if a))
                self._publish(
                    self._pub_status,
                    Status(
                        self.o.uav,
                        k,
                        t_k,
                        vec3(state.estimate_m),
                        bool(state.observable),
                        bool(step.singular),
                        active_mask,
                        tuple(int(s) for s in view.saved_steps),
                    ),
                )
                self._publish(self._pub_done, Done(self.o.uav, k))
                timing = {
                    "wait_tick_s": w_tick - w0,
                    "wait_measurement_s": w_meas - w_tick,
                    "wait_peers_s": w_peers - w_meas,
                    "compute_s": w_sent - w_peers,
                    "measurement_to_setpoint_s": w_sent - w_meas,
                }
                self._log_step(k, t_k, own, record, view, state, result, rows, timing)
                done_steps += 1
            self._await_end()
            end = self._end()
            return {
                "uav": self.o.uav,
                "steps": done_steps,
                "dropped": dict(self.inbox.dropped),
                "mode_changes": self.mode_changes,
                "taken_over": self.takeovers,
                "taken_over_steps": self.taken_over_steps,
                "end": end,
            }
        finally:
            self.close()

    def _await_end(self) -> None:
        """Lockstep: stay in the swarm until the clock's end tick (step K), i.e. until every
        planner has done the last step. Leaving at once would let this planner's liveliness
        token go before its last record reaches a slower peer, which would then fly its last
        step without it. A clock that sends no end tick only delays the end by the step
        timeout (with a warning)."""
        try:
            self._wait(lambda: self.tick is not None and self.tick.step >= self.steps, self.o.step_timeout_s, "end-of-mission tick")
        except NodeError as exc:
            log.warning("%s; ending the mission anyway", exc)

    def _start(self) -> int:
        """Pre-flight, then report ready to the clock; the first step is 0."""
        self.preflight()
        self._flight_streams()
        self._publish(self._pub_done, Done(self.o.uav, -1))
        log.info("uav %d ready at the start position", self.o.uav)
        return 0

    def _flight_streams(self) -> None:
        """Lockstep: slow the health streams down for the flight (:data:`LOCKSTEP_FLIGHT_STREAM_HZ`);
        a message the autopilot refuses (EKF_STATUS_REPORT on PX4) keeps its rate."""
        link = self._require_link()
        for msg_id, hz in LOCKSTEP_FLIGHT_STREAM_HZ:
            try:
                link.request_interval(msg_id, hz)
            except LinkError as exc:
                log.debug("uav %d: message %d keeps its rate (%s)", self.o.uav, msg_id, exc)

    def _rejoin(self) -> int:
        """Take over a vehicle in flight from a planner that died; return the first step to fly.

        The clock's current step p is answered as done (this planner has neither its
        measurement, published before it subscribed, nor its peers' records) and the planner
        flies from p + 1; its peers wait for it again from its first record on. The control
        stream is advanced past the steps it missed, so its draws stay those of its step."""
        link = self._require_link()
        t = self.o.preflight_timeout_s
        link.wait_heartbeat(t)
        for msg_id, hz in LOCKSTEP_STREAM_HZ:
            link.request_interval(msg_id, hz)
        self._flight_streams()
        self._wait(lambda: link.telemetry.position_enu_m is not None, t, "position telemetry")
        if not link.telemetry.armed:
            raise NodeError(f"uav {self.o.uav}: cannot rejoin: the vehicle is disarmed (mode {link.mode_name()})")
        self._wait(lambda: self.tick is not None and self.tick.step >= 0, t, "a clock tick of the mission to rejoin at")
        if self.tick is None:
            raise NodeError(f"uav {self.o.uav}: internal: no clock tick after waiting for one")
        p = self.tick.step
        if p >= self.steps - 1:
            raise NodeError(f"uav {self.o.uav}: cannot rejoin at step {p}: the mission has {self.steps} steps")
        link.set_mode("OFFBOARD" if link.is_px4 else "GUIDED")
        self._publish(self._pub_done, Done(self.o.uav, p))
        self.ctrl_rng.random((p + 1) * CONTROL_DRAWS)
        log.warning("uav %d rejoined at step %d (flying from step %d)", self.o.uav, p, p + 1)
        return p + 1

    def _rebuild(self, state: est.EstimatorState, first: int, used: np.ndarray) -> est.EstimatorState:
        """A rejoining planner's estimator, own-range window and own track, from its
        predecessor's step log and, when they are next to it (a launch's results directory),
        its peers' logs (:func:`replay_step_logs`). ``used`` (per drone, the newest step fed
        to the estimator) is updated in place."""
        state, done = replay_step_logs(state, self.predecessor_rows, self.n, first, self.config.channel, self.config.estimator)
        for step, pos, rng, los in done.get(self.i, []):
            self.own_ranges.append((rng, los))
            self._track(step, pos)
        for j, steps in done.items():
            if steps:
                used[j] = steps[-1][0]
        own = len(done.get(self.i, []))
        peers = sum(len(v) for j, v in done.items() if j != self.i)
        where = f"; estimate {tuple(round(float(v), 2) for v in state.estimate_m)}" if state.observable else ""
        log.warning(
            "uav %d: estimator rebuilt from %d steps of its predecessor's log (steps up to %d) and %d records of %d peers' logs%s",
            self.o.uav,
            own,
            used[self.i],
            peers,
            sum(1 for j, v in done.items() if j != self.i and v),
            where,
        )
        return state

    def _await_step(self, k: int) -> float:
        if self.o.lockstep:
            # Step 0 starts when the whole swarm is at its start positions: pre-flight deadline.
            timeout = self.o.preflight_timeout_s if k == 0 else self.o.step_timeout_s
            self._wait(lambda: self.tick is not None and self.tick.step >= k, timeout, f"clock tick of step {k}")
            if self.tick is None:
                raise NodeError(f"uav {self.o.uav}: internal: no clock tick after waiting for the one of step {k}")
            return self.tick.time_s if self.tick.step == k else self.tick.time_s - (self.tick.step - k) * self.dt
        raise NodeError("internal: _await_step is the lockstep clock; real time steps in _run_realtime")

    def _own_position(self, t_k: float) -> np.ndarray:
        link = self._require_link()
        stamp = int(round(t_k * 1000.0))
        self._wait(
            self._vehicle_alive(lambda: link.telemetry.position_time_ms >= stamp, f"position telemetry at t = {t_k:g} s"),
            self.o.step_timeout_s,
            f"position telemetry at t = {t_k:g} s",
        )
        if link.telemetry.position_enu_m is None:
            raise NodeError(f"uav {self.o.uav}: no position telemetry at t = {t_k:g} s")
        return link.telemetry.position_enu_m.astype(float)

    def _vehicle_alive(self, predicate: Callable[[], bool], what: str) -> Callable[[], bool]:
        """``predicate`` that raises NodeError when the vehicle's process leaves the swarm during
        this wait (its liveliness token goes: noticed at once). A vehicle that hangs instead
        fails the wait at the step timeout. (Heartbeat silence is no test here: a machine flying
        a hundred drones on two cores starves processes for more than 10 s at times, and a
        vehicle heartbeats on the wall clock.)"""
        link = self._require_link()

        def check() -> bool:
            if predicate():
                return True
            if self.vehicle_gone_at is not None:
                raise NodeError(
                    f"uav {self.o.uav}: vehicle link lost: the vehicle's process left the swarm "
                    f"{self.wall() - self.vehicle_gone_at:.1f} s ago, its last heartbeat {link.link_age_s():.1f} s ago, "
                    f"while waiting for {what}"
                )
            return False

        return check

    def _measurement(self, k: int) -> Observation:
        self._wait(
            self._vehicle_alive(lambda: k in self.measurements, f"payload measurement of step {k}"),
            self.o.step_timeout_s,
            f"payload measurement of step {k}",
        )
        for s in [s for s in self.measurements if s <= k]:
            meas = self.measurements.pop(s)
        return meas

    def _wait_for_peer_records(self, k: int) -> None:
        """Lockstep barrier of step k: the records of every other planner of the mission,
        except those that left. (Waiting only for the planners already seen alive would let a
        planner whose liveliness has not reached us yet be skipped, and the views would differ.)"""
        expected = [j for j in range(1, self.n + 1) if j != self.o.uav]
        self._wait(
            lambda: all(self.view.has(j, k) for j in expected if j not in self.left),
            self.o.step_timeout_s,
            f"records of step {k} from the planners",
            missing=lambda: sorted(j for j in expected if j not in self.left and not self.view.has(j, k)),
        )

    def _serve_until_peers(self, k: int, t_unix: float) -> bool:
        """:meth:`_serve_until_unix` until the records of step k from the live peers are in
        (:meth:`_missing_peers`) or UNIX time ``t_unix``; return whether they are all in."""
        return self._serve_until_unix(t_unix, lambda: not self._missing_peers(k))

    def _missing_peers(self, k: int) -> list[int]:
        """Live peers (1-based ids) whose record of step k has not arrived."""
        return sorted(j for j in self.alive if j != self.o.uav and not self.view.has(j, k) and self.stale_peers.get(j) != k)

    def _view_estimate_plan(
        self, k: int, own: np.ndarray, prev_step: np.ndarray, state: est.EstimatorState, used: np.ndarray
    ) -> tuple[Any, est.EstimatorState, int, np.ndarray, Any]:
        """Step k after the records are in: delayed view, source estimate (with the records
        not used before), control step. Returns (view, state, new rows, used steps, plan)."""
        view = self.view.advance(k)
        state, rows = self._estimate(state, view, used)
        used = np.maximum(used, view.saved_steps)
        return view, state, rows, used, self._plan(k, own, prev_step, view, state)

    def _estimate(self, state: est.EstimatorState, view: Any, used: np.ndarray) -> tuple[est.EstimatorState, int]:
        """Feed the estimator the view's records new since ``used`` (one row per drone, in
        drone order) and then the peers' records that arrived late, after a newer one
        (``view.late_records``: old evidence about the source is still evidence), in the
        order of the in-process simulator. Returns the state and the number of rows fed."""
        new = view.saved_steps > used
        late = view.late_records
        rows = self.n + len(late)
        pos = np.full((rows, 3), np.nan)
        rng = np.full(rows, np.nan)
        az = np.full(rows, np.nan)
        el = np.full(rows, np.nan)
        los = np.zeros(rows, dtype=bool)
        fed = [(j, rec) for j, rec in enumerate(view.records) if rec is not None and new[j]] + [(self.n + r, rec) for r, rec in enumerate(late)]
        for row, rec in fed:
            pos[row] = rec.position_m
            rng[row], az[row], el[row], los[row] = rec.range_m, rec.azimuth_rad, rec.elevation_rad, rec.los
        meas = est.Measurements(positions_m=pos, range_m=rng, azimuth_rad=az, elevation_rad=el, los=los)
        return est.update(state, meas, self.config.channel, self.config.estimator), int(new.sum()) + len(late)

    def _taken_over_record(self, k: int, t_s: float, position_m: np.ndarray) -> Observation:
        """The record of step k while a pilot flies the drone: its position (m, ENU) at time
        ``t_s``, flagged taken over, without a measurement (the pilot's flight is no planned
        sensing)."""
        nan = float("nan")
        return Observation(
            self.o.uav,
            k,
            t_s,
            vec3(position_m),
            bool(self.config.ranging[self.i]),
            bool(self.config.bearing[self.i]),
            True,
            nan,
            nan,
            nan,
            taken_over=True,
        )

    def _track(self, k: int, own: np.ndarray) -> None:
        """Remember the own position of step k (the last OWN_TRACK_STEPS steps)."""
        self.own_track[k] = np.array(own, dtype=float)
        self.own_track.pop(k - OWN_TRACK_STEPS, None)

    def _plan(self, k: int, own: np.ndarray, prev_step: np.ndarray, view: Any, state: est.EstimatorState) -> Any:
        plan_view = PlanView.from_records(self.i, view.records, view.saved_steps, k, view.hops)
        # Peers whose planner left the liveliness view (a partition, not distance): kept apart
        # by the bisector planes of the step of their last record (planner.agent.plan).
        lost = np.array([j + 1 in self.left and plan_view.valid[j] for j in range(self.n)], dtype=bool)
        own_then = None
        if lost.any():
            own_then = np.array([self.own_track.get(int(view.saved_steps[j]), own) for j in range(self.n)], dtype=float)
        uniforms = self.ctrl_rng.random(CONTROL_DRAWS)
        own_lower = own_range_lower_bound_m(
            np.array([r for r, _ in self.own_ranges], dtype=float), np.array([los for _, los in self.own_ranges], dtype=bool), self.config.channel
        )
        return plan(
            self.config,
            own,
            prev_step,
            plan_view,
            state,
            uniforms,
            step_index=k,
            own_distance_lower_m=own_lower,
            lost_contact=lost if own_then is not None else None,
            own_then_m=own_then,
        )

    def _log_step(
        self, k: int, t_k: float, own: np.ndarray, record: Observation, view: Any, state: Any, result: Any, rows: int, timing: dict[str, float]
    ) -> None:
        if self._log is None:
            return
        step = result.step
        entry = {
            "step": k,
            "t_s": t_k,
            "position_m": [float(v) for v in own],
            "measurement": {
                "range_m": _num(record.range_m),
                "azimuth_rad": _num(record.azimuth_rad),
                "elevation_rad": _num(record.elevation_rad),
                "los": record.los,
            },
            "saved_steps": [int(s) for s in view.saved_steps],
            "hops": [int(h) for h in view.hops],
            "new_records": rows,
            "estimate_m": [float(v) for v in state.estimate_m],
            "observable": bool(state.observable),
            "cost": _num(float(result.cost.value)),
            "next_position_m": [float(v) for v in step.next_position],
            "active": {name: bool(a) for name, a in zip(("uav", "source", "obstacle", "altitude"), np.asarray(step.active))},
            "singular": bool(step.singular),
            "filtered": bool(step.filtered),
            "timing": {name: round(v, 6) for name, v in timing.items()},
        }
        self._log.write(json.dumps(entry) + "\n")
        self._log.flush()  # the step log is the record of what was flown: it must survive a kill

    def _taken_over_step(self, k: int, t_k: float, own: np.ndarray) -> None:
        """Lockstep step ``k`` of a drone a pilot flies: no command; its telemetry position at
        t_k published as a record flagged taken over, without a measurement (the payload's of
        this step is dropped); the step answered (``Done``) so the clock goes on. The control
        draws of the step are skipped, so a handed-back planner draws those of its step."""
        for s in [s for s in self.measurements if s <= k]:
            del self.measurements[s]
        self._track(k, own)
        self._publish(self._pub_record, self._taken_over_record(k, t_k, own), MessageKind.RECORD)
        self.ctrl_rng.random(CONTROL_DRAWS)
        self.taken_over_steps += 1
        self._publish(self._pub_done, Done(self.o.uav, k))

    def _end(self) -> dict[str, Any]:
        """End of mission as the mission says: hold (stay in GUIDED at the last setpoint),
        land or return to launch, confirmed by the vehicle's mode; left to the pilot of a
        drone taken over."""
        link = self._require_link()
        action = self.m.end_action
        if self.taken_over is not None:
            log.warning("uav %d: mission over while taken over (%s): the end action (%s) is left to the pilot", self.o.uav, link.mode_name(), action)
            return {"action": action, "confirmed": False, "reason": f"taken over ({link.mode_name()})"}
        try:
            if action == "land":
                link.set_mode("AUTO.LAND" if link.is_px4 else "LAND")
            elif action == "rtl":
                link.set_mode("AUTO.RTL" if link.is_px4 else "RTL")
            else:
                pos = link.telemetry.position_enu_m
                if pos is not None:
                    link.send_setpoint(pos, None)
                if link.is_px4:
                    link.set_mode("AUTO.LOITER")
        except LinkError as exc:
            raise NodeError(f"uav {self.o.uav}: end of mission ({action}) failed: {exc}") from None
        log.info("uav %d: mission over (%s)", self.o.uav, action)
        return {"action": action, "confirmed": True, "mode": link.mode_name()}

    # -- real time --------------------------------------------------------------------------
    def _add_realtime_record(self, rec: Observation) -> None:
        """A peer's record, re-indexed onto this planner's step grid by its time stamp (UNIX
        s): planners started apart number their steps differently but share the grid."""
        if rec.sender == self.o.uav or self.t0_unix is None:
            return  # before our step 0 a record cannot enter any view
        step = int(round((rec.time_s - self.t0_unix) / self.dt_wall))
        if step < 0:
            return
        if rec.stale:
            # Nothing new of that drone (its vehicle link is down): it has answered for this
            # step, but its saved record keeps ageing (the age widens the safety margin).
            self.stale_peers[rec.sender] = step
            return
        self.view.add(dataclasses.replace(rec, step=step))

    def _check_link(self) -> None:
        """Notice a lost vehicle link (no heartbeat for 2 s) and its return; report both."""
        link = self.link
        if link is None:
            return
        if link.lost and self.link_down_since is None:
            self.link_down_since = self.wall()
            log.error(
                "uav %d: vehicle link lost (no heartbeat for %.1f s): publishing the last record as stale until it returns; meanwhile %s",
                self.o.uav,
                link.link_age_s(),
                FAILSAFE_NOTE[link.flavour],
            )
        elif self.link_down_since is not None and not link.lost:
            down = self.wall() - self.link_down_since
            self.link_losses.append({"down_s": round(down, 3)})
            log.warning("uav %d: vehicle link back after %.1f s; resuming", self.o.uav, down)
            self.link_down_since = None
            self.resume_needed = True

    def _serve_until_unix(self, t_unix: float, predicate: Callable[[], bool] | None = None) -> bool:
        """Serve MAVLink (the setpoint stream), Zenoh and the link watch until UNIX time
        ``t_unix`` or until ``predicate()``; return whether the predicate held."""
        while True:
            if predicate is not None and predicate():
                return True
            remaining = t_unix - self.unix()
            if remaining <= 0:
                return predicate() if predicate is not None else True
            self._sleep_io(remaining)

    def _wait_rt(self, predicate: Callable[[], bool], timeout_s: float, what: str, missing: Callable[[], Any] | None = None) -> None:
        """:meth:`_wait` that also fails at once, naming ``what``, when the link is lost."""

        def ok() -> bool:
            if self.link_down_since is not None:
                raise NodeError(f"uav {self.o.uav}: vehicle link lost while waiting for {what}")
            return predicate()

        self._wait(ok, timeout_s, what, missing)

    def _ready_wait(self) -> None:
        """Wait until the vehicle can fly by setpoints, saying what it waits for."""
        link = self._require_link()
        deadline = self.wall() + self.o.preflight_timeout_s
        last_report = -math.inf
        last_request = self.wall()
        while True:
            self._clock_verdict()  # a vehicle on another clock is refused at once, not after its readiness
            missing = link.not_ready(require_gps=self.frame == "global")
            if not missing:
                return
            now = self.wall()
            if now >= deadline:
                raise NodeError(
                    f"uav {self.o.uav}: vehicle not ready to fly after {self.o.preflight_timeout_s:g} s; still waiting for: {'; '.join(missing)}"
                )
            if now - last_report >= READY_REPORT_PERIOD_S:
                log.info("uav %d: waiting for the vehicle: %s", self.o.uav, "; ".join(missing))
                last_report = now
            if now - last_request >= READY_REPORT_PERIOD_S:
                last_request = now
                if not link.telemetry.home_known:
                    link.request_message(MSG_HOME_POSITION)
                if link.telemetry.origin_global is None:
                    link.request_message(MSG_GPS_GLOBAL_ORIGIN)
            self._sleep_io(min(0.25, deadline - now))

    def _check_clock(self) -> None:
        """Refuse (NodeError) a vehicle whose clock runs at another rate than this planner's
        mission clock (``--speedup``): e.g. a SITL at ×1 under a planner at ×5, whose steps
        would be five times too short for the vehicle. The rate is the vehicle's
        ``time_boot_ms`` against the wall clock (:class:`comms.mavlink_client.ClockWatch`)
        over at least 1.5 wall seconds; a real autopilot's is 1. Checked as soon as it can be
        measured (during the readiness wait) and required before take-off."""
        if self.vehicle_clock_rate is None:
            self._wait(lambda: self._clock_verdict(), CLOCK_CHECK_TIMEOUT_S, "time_boot_ms stamps to measure the vehicle's clock rate")

    def _clock_verdict(self) -> bool:
        """Whether the vehicle's clock rate is known (and matches; NodeError if not)."""
        if self.vehicle_clock_rate is not None:
            return True
        link = self._require_link()
        rate = link.clock.rate()
        if rate is None:
            return False
        s = self.o.speedup
        span = link.clock.span_s()
        log.info("uav %d: vehicle clock x%.2f of wall time (time_boot_ms over %.1f s); this planner x%g", self.o.uav, rate, span, s)
        if abs(rate / s - 1.0) > CLOCK_RATE_TOLERANCE:
            raise NodeError(
                f"uav {self.o.uav}: the vehicle's clock runs at x{rate:.2f} of wall time (its time_boot_ms over {span:.1f} s) "
                f"but this planner's mission clock at x{s:g} (--speedup): start the vehicle (SITL --speedup, fimnav vehicle "
                f"--speedup) and the planner at the same speed-up; not taking off"
            )
        self.vehicle_clock_rate = rate
        return True

    def _preflight_realtime(self) -> None:
        """Heartbeat, flavour, streams, readiness, mode, arm, take-off and flight to the
        start, by the rules of the detected autopilot."""
        link = self._require_link()
        t = self.o.preflight_timeout_s
        link.wait_heartbeat(t)
        link.check_signing()
        detected = link.telemetry.autopilot
        if link.forced_flavour is not None:
            log.info("uav %d: autopilot %s (forced; HEARTBEAT.autopilot = %s)", self.o.uav, link.flavour, detected)
        else:
            log.info("uav %d: autopilot %s (HEARTBEAT.autopilot = %s)", self.o.uav, link.flavour, detected)
        s = self.o.speedup
        link.stream_period_s = 1.0 / (self.o.stream_hz * s)
        self._request_streams()
        link.request_message(MSG_HOME_POSITION)
        link.request_message(MSG_GPS_GLOBAL_ORIGIN)
        self._ready_wait()
        self._check_clock()
        origin = link.telemetry.origin_global
        if origin is None:
            raise NodeError(f"uav {self.o.uav}: the vehicle is ready but sent no EKF origin (GPS_GLOBAL_ORIGIN)")
        shared = self.mission_frame.matches(*origin)
        log.info(
            "uav %d: ready; EKF origin %.7f, %.7f, %.2f m (%s the mission origin); setpoints in %s",
            self.o.uav,
            *origin,
            "is" if shared else "is not",
            "SET_POSITION_TARGET_GLOBAL_INT" if self.frame == "global" else "LOCAL_NED",
        )
        if self.frame == "local_ned" and not shared:
            raise NodeError(
                f"uav {self.o.uav}: setpoint_frame local_ned needs the vehicle's EKF origin at the mission origin "
                f"({self.m.origin.lat_deg:.7f}, {self.m.origin.lon_deg:.7f}, {self.m.origin.alt_m:g} m); it is at "
                f"({origin[0]:.7f}, {origin[1]:.7f}, {origin[2]:g} m): use setpoint_frame global"
            )
        self._wait(lambda: link.telemetry.position_enu_m is not None, t, "position telemetry")
        pos = link.telemetry.position_enu_m
        if pos is None:
            raise NodeError(f"uav {self.o.uav}: no position telemetry after waiting for it")
        climb_to = float(self.m.takeoff_alt_m if self.m.takeoff_alt_m is not None else self.start[2])
        tol = START_TOLERANCE_REALTIME_M
        # Take-off done at 95 % of the climb (an autopilot's altitude settles slowly at the end).
        climb_tol = max(tol, 0.05 * (climb_to - float(pos[2])))
        if link.is_px4:
            # PX4: the setpoint stream must run (> 2 Hz, PX4 ≥ 1.14 wants it for a second)
            # before OFFBOARD is accepted; the stream is a hold above the current position.
            above = np.array([pos[0], pos[1], max(climb_to, float(pos[2]))])
            link.set_stream(lambda _t: (above, None))
            stream_since = self.wall()
            self._wait(lambda: self.wall() - stream_since >= 1.2 / s, t, "setpoint stream before OFFBOARD")
            if not link.in_mode("OFFBOARD"):
                link.set_mode("OFFBOARD")
            if not link.telemetry.armed:
                link.arm()
            self._wait_rt(lambda: self._z() >= climb_to - climb_tol, t, f"take-off to {climb_to:g} m")
        else:
            if not link.in_mode("GUIDED"):
                link.set_mode("GUIDED")
            if not link.telemetry.armed:
                link.arm()
                # NAV_TAKEOFF altitude is above home; no setpoint until it is reached (a setpoint
                # would end the take-off in ArduPilot).
                link.takeoff(climb_to - link.home_z_m())
                self._wait_rt(lambda: self._z() >= climb_to - climb_tol, t, f"take-off to {climb_to:g} m")
        start = self.start.copy()
        link.set_stream(lambda _t: (start, None))
        log.info("uav %d: airborne in %s, flying to the start position", self.o.uav, link.mode_name())
        self._wait_rt(lambda: self._distance_to(start) < tol, t, "start position")

    def _request_streams(self) -> None:
        """The telemetry the real-time planner reads, at rates in the autopilot's time (Hz)."""
        link = self._require_link()
        pos_msg = MSG_GLOBAL_POSITION_INT if self.frame == "global" else MSG_LOCAL_POSITION_NED
        rates = {pos_msg: 10.0, MSG_SYS_STATUS: 1.0, MSG_GPS_RAW_INT: 1.0, MSG_HOME_POSITION: 0.5, MSG_EXTENDED_SYS_STATE: 1.0}
        optional = [MSG_EXTENDED_SYS_STATE]
        if not link.is_px4:
            rates[MSG_EKF_STATUS_REPORT] = 1.0
            optional.append(MSG_EKF_STATUS_REPORT)
        for note in link.request_streams(rates, optional):
            log.info("uav %d: %s", self.o.uav, note)

    def _z(self) -> float:
        pos = self._require_link().telemetry.position_enu_m
        return -math.inf if pos is None else float(pos[2])

    def _distance_to(self, target: np.ndarray) -> float:
        pos = self._require_link().telemetry.position_enu_m
        return math.inf if pos is None else float(np.linalg.norm(pos - target))

    def _resume(self) -> None:
        """After a link loss: back into GUIDED/OFFBOARD (the stream is already running)."""
        link = self._require_link()
        self.resume_needed = False
        self._wait(lambda: link.telemetry.custom_mode is not None, self.o.step_timeout_s, "heartbeat after the link loss")
        if not link.telemetry.armed:
            raise NodeError(
                f"uav {self.o.uav}: the vehicle is disarmed after the link loss (mode {link.mode_name()}; landed by "
                "its failsafe or rebooted): not taking off again without an operator"
            )
        # The autopilot may have rebooted (stream rates gone): ask for the streams again.
        self._request_streams()
        mode = "OFFBOARD" if link.is_px4 else "GUIDED"
        if not link.in_mode(mode):
            log.warning("uav %d: vehicle in %s after the link loss; switching back to %s", self.o.uav, link.mode_name(), mode)
            link.set_mode(mode)
        log.info("uav %d: resumed in %s", self.o.uav, mode)

    def _watch_mode(self, k: int) -> None:
        """A vehicle that left GUIDED/OFFBOARD while the link is up has been taken over (a
        pilot, a ground station or a failsafe). The planner stops commanding it at once (the
        setpoint stream ends), says so, and never switches it back on its own: only
        ``fimnav handback`` does (:meth:`_hand_back`). Mode changes while taken over are
        reported too."""
        link = self._require_link()
        want = "OFFBOARD" if link.is_px4 else "GUIDED"
        now = link.mode_name()
        if not link.in_mode(want) and now != self._reported_mode:
            self.mode_changes.append(now)
            if self.taken_over is None:
                link.set_stream(None)
                self.taken_over = {"step": k, "mode": now}
                self.takeovers.append(dict(self.taken_over))
                log.warning(
                    "uav %d: taken over at step %d: the vehicle left %s (now %s); not commanding it; publishing its "
                    "position without measurements; hand it back with: fimnav handback MISSION --uav %d",
                    self.o.uav,
                    k,
                    want,
                    now,
                    self.o.uav,
                )
            else:
                log.warning("uav %d: taken over, the vehicle is now in %s", self.o.uav, now)
        self._reported_mode = now if not link.in_mode(want) else None

    def _hand_back(self, k: int) -> bool:
        """``fimnav handback``: switch the vehicle back to GUIDED/OFFBOARD at its position and
        plan again from step ``k``; False (logged) when the vehicle refuses or is not armed.
        Real time holds the position with the setpoint stream until the step's trajectory;
        lockstep streams nothing (step k's setpoint follows at once): PX4 gets a few hold
        setpoints first, as it enters OFFBOARD only with setpoints flowing."""
        link = self._require_link()
        mode = "OFFBOARD" if link.is_px4 else "GUIDED"
        pos = link.telemetry.position_enu_m
        if not link.telemetry.armed or pos is None:
            log.error("uav %d: hand-back refused: the vehicle is %s", self.o.uav, "disarmed" if not link.telemetry.armed else "without a position")
            return False
        hold = pos.astype(float)
        try:
            if link.is_px4:
                if self.o.lockstep:
                    for _ in range(5):
                        link.send_setpoint(hold, None)
                else:
                    link.set_stream(lambda _t: (hold, None))  # PX4 enters OFFBOARD only with setpoints flowing
                link.set_mode(mode)
            else:
                link.set_mode(mode)
                if not self.o.lockstep:
                    link.set_stream(lambda _t: (hold, None))
        except LinkError as exc:
            link.set_stream(None)
            log.error("uav %d: hand-back refused: %s", self.o.uav, exc)
            return False
        if self.taken_over is None:
            raise NodeError(f"uav {self.o.uav}: internal: hand-back at step {k} of a drone not taken over")
        self.takeovers[-1]["handed_back_step"] = k
        self.taken_over = None
        self._reported_mode = None
        log.warning("uav %d: handed back at step %d: in %s, planning again", self.o.uav, k, mode)
        return True

    def _trajectory(self, own: np.ndarray, u: np.ndarray, t_from: float) -> Callable[[float], tuple[np.ndarray | None, np.ndarray | None]]:
        """The streamed setpoint of one step: from ``own`` along ``u`` (m, ENU) over one
        step, position + velocity feed-forward u/dt; then the end point, zero velocity."""
        dt_w = self.dt_wall
        v = u / self.dt
        end = own + u
        zero = np.zeros(3)

        def at(t_wall: float) -> tuple[np.ndarray | None, np.ndarray | None]:
            f = (t_wall - t_from) / dt_w
            if f >= 1.0:
                return end, zero
            return own + u * max(f, 0.0), v

        return at

    def _run_realtime(self) -> dict[str, Any]:
        """Fly the mission on the wall clock (see the module doc)."""
        link = self._require_link()
        try:
            self._preflight_realtime()
        except LinkError as exc:
            raise NodeError(f"uav {self.o.uav}: pre-flight failed: {exc}") from None
        self._publish(self._pub_done, Done(self.o.uav, -1))
        dtw = self.dt_wall
        now = self.unix()
        self.t0_unix = self.o.start_at_unix if self.o.start_at_unix is not None else math.ceil((now + 0.25 * dtw) / dtw) * dtw
        log.info("uav %d ready at the start position; step 0 at UNIX %.3f (dt %.3g s wall)", self.o.uav, self.t0_unix, dtw)
        max_age_wall = (self.o.measurement_max_age_s if self.o.measurement_max_age_s is not None else self.dt) / self.o.speedup
        state = est.initial_state((), self.config.estimator)
        used = np.full(self.n, -1, dtype=np.int64)
        prev_step = np.zeros(3)
        done_steps = stale_steps = 0
        k = max(0, math.ceil((now - self.t0_unix) / dtw - 1e-9)) if self.o.start_at_unix is not None else 0
        while k < self.steps:
            t_k = self.t0_unix + k * dtw
            self._serve_until_unix(t_k)
            w0 = self.unix()
            if w0 - t_k > dtw:
                skip = int((w0 - t_k) // dtw)
                self.late_steps += skip
                log.warning(
                    "uav %d: step %d is %.3f s late; skipping %d step(s), the vehicle follows the last setpoint", self.o.uav, k, w0 - t_k, skip
                )
                k += skip
                continue
            if self.resume_needed and self.link_down_since is None:
                try:
                    self._resume()
                except LinkError as exc:
                    log.error("uav %d: resuming failed (%s); retrying next step", self.o.uav, exc)
                    self.resume_needed = True
            if self.link_down_since is not None or self.resume_needed:
                if self.last_record is not None:
                    stale = dataclasses.replace(self.last_record, step=k, time_s=w0, stale=True)
                    self._publish(self._pub_record, stale, MessageKind.RECORD)
                stale_steps += 1
                k += 1
                continue
            self._watch_mode(k)
            if self.taken_over is not None and not (self._handback_requested() and self._hand_back(k)):
                # Taken over: no command. The drone's position from telemetry is published every
                # step, without a measurement (the pilot's flight is no planned sensing), so the
                # others keep clear of where it is; without telemetry its last record, as stale.
                pos = link.telemetry.position_enu_m
                if pos is not None and self.wall() - link.telemetry.position_wall_s <= POSITION_MAX_AGE_S:  # a fresh position
                    self._publish(self._pub_record, self._taken_over_record(k, w0, pos), MessageKind.RECORD)
                elif self.last_record is not None:
                    self._publish(
                        self._pub_record, dataclasses.replace(self.last_record, step=k, time_s=w0, stale=True, taken_over=True), MessageKind.RECORD
                    )
                self.taken_over_steps += 1
                prev_step = np.zeros(3)
                k += 1
                continue
            pos = link.telemetry.position_enu_m
            if pos is None:
                raise NodeError(f"uav {self.o.uav}: step {k}: no position telemetry from the vehicle")
            age = self.wall() - link.telemetry.position_wall_s
            if age > POSITION_MAX_AGE_S:
                # Heartbeats but no position: plan nothing on an old position.
                self.position_gaps += 1
                log.warning("uav %d: step %d: the last position is %.2f s old; publishing the last record as stale", self.o.uav, k, age)
                if self.last_record is not None:
                    self._publish(self._pub_record, dataclasses.replace(self.last_record, step=k, time_s=w0, stale=True), MessageKind.RECORD)
                stale_steps += 1
                k += 1
                continue
            own = pos.astype(float)
            meas = self.latest_measurement
            fresh = meas is not None and w0 - meas.time_s <= max_age_wall
            if not fresh:
                log.warning("uav %d: step %d without a payload measurement newer than %.3g s", self.o.uav, k, max_age_wall)
            nan = float("nan")
            record = Observation(
                self.o.uav,
                k,
                w0,
                vec3(own),
                bool(self.config.ranging[self.i]),
                bool(self.config.bearing[self.i]),
                bool(meas.los) if fresh and meas else True,
                meas.range_m if fresh and meas and self.config.ranging[self.i] else nan,
                meas.azimuth_rad if fresh and meas and self.config.bearing[self.i] else nan,
                meas.elevation_rad if fresh and meas and self.config.bearing[self.i] else nan,
            )
            self.last_record = record
            self.view.add(record)
            self.own_ranges.append((record.range_m, record.los))
            self._track(k, own)
            self._publish(self._pub_record, record, MessageKind.RECORD)
            w_meas = self.unix()
            if not self._serve_until_peers(k, t_k + self.o.peer_wait_fraction * dtw):
                log.info("uav %d: step %d without the records of %s (deadline)", self.o.uav, k, self._missing_peers(k))
            w_peers = self.unix()
            view, state, rows, used, result = self._view_estimate_plan(k, own, prev_step, state, used)
            step = result.step
            u = np.asarray(step.next_position, dtype=float) - own
            link.set_stream(self._trajectory(own, u, self.wall()))
            w_sent = self.unix()
            prev_step = np.asarray(step.displacement, dtype=float)
            active_mask = int(sum(1 << b for b, a in enumerate(np.asarray(step.active)) if a))
            self._publish(
                self._pub_status,
                Status(
                    self.o.uav,
                    k,
                    w0,
                    vec3(state.estimate_m),
                    bool(state.observable),
                    bool(step.singular),
                    active_mask,
                    tuple(int(s) for s in view.saved_steps),
                ),
            )
            self._publish(self._pub_done, Done(self.o.uav, k))
            timing = {"late_s": w0 - t_k, "wait_peers_s": w_peers - w_meas, "compute_s": w_sent - w_peers, "measurement_to_setpoint_s": w_sent - w0}
            self._log_step(k, w0, own, record, view, state, result, rows, timing)
            done_steps += 1
            k += 1
        end = self._end_realtime()
        return {
            "uav": self.o.uav,
            "steps": done_steps,
            "stale_steps": stale_steps,
            "late_steps": self.late_steps,
            "flavour": link.flavour,
            "frame": self.frame,
            "link_losses": self.link_losses,
            "mode_changes": self.mode_changes,
            "taken_over": self.takeovers,
            "taken_over_steps": self.taken_over_steps,
            "setpoints_sent": link.setpoints_sent,
            "dropped": dict(self.inbox.dropped),
            "end": end,
            "vehicle_clock_rate": None if self.vehicle_clock_rate is None else round(self.vehicle_clock_rate, 3),
        }

    def _end_realtime(self) -> dict[str, Any]:
        """End of mission as the mission says, confirmed by the vehicle's mode and state:
        hold (ArduPilot: GUIDED at a position target, which never times out; PX4:
        AUTO.LOITER), land (LAND / AUTO.LAND until landed and disarmed) or RTL (RTL /
        AUTO.RTL, confirmed by the mode)."""
        link = self._require_link()
        action = self.m.end_action
        if self.link_down_since is not None:
            log.error("uav %d: mission over with the vehicle link down: its failsafe keeps control", self.o.uav)
            return {"action": action, "confirmed": False, "reason": "link lost"}
        if self.taken_over is not None:
            log.warning("uav %d: mission over while taken over (%s): the end action (%s) is left to the pilot", self.o.uav, link.mode_name(), action)
            return {"action": action, "confirmed": False, "reason": f"taken over ({link.mode_name()})"}
        pos = link.telemetry.position_enu_m
        try:
            if action == "hold":
                if pos is not None:
                    hold = pos.astype(float)
                    link.set_stream(lambda _t: (hold, None))
                if link.is_px4:
                    link.set_mode("AUTO.LOITER")
                want = "AUTO.LOITER" if link.is_px4 else "GUIDED"
                self._wait(lambda: link.in_mode(want) and link.telemetry.armed, self.o.end_timeout_s, f"armed heartbeat in {want}")
            elif action == "land":
                link.set_mode("AUTO.LAND" if link.is_px4 else "LAND")
                link.set_stream(None)
                self._wait(
                    lambda: not link.telemetry.armed and link.telemetry.landed_state in (None, 1), self.o.end_timeout_s, "landed and disarmed vehicle"
                )
            else:
                link.set_mode("AUTO.RTL" if link.is_px4 else "RTL")
                link.set_stream(None)
        except LinkError as exc:
            raise NodeError(f"uav {self.o.uav}: end of mission ({action}) failed: {exc}") from None
        finally:
            # The stream ends with the planner; ArduPilot holds a position-only target in
            # GUIDED without one, PX4 holds in AUTO.LOITER.
            link.set_stream(None)
        landed = link.telemetry.landed_state
        end = {
            "action": action,
            "confirmed": True,
            "mode": link.mode_name(),
            "armed": link.telemetry.armed,
            "landed_state": MAV_LANDED_STATE_NAMES.get(landed, str(landed)) if landed is not None else None,
        }
        log.info("uav %d: mission over (%s): vehicle in %s, %s", self.o.uav, action, end["mode"], "armed" if end["armed"] else "disarmed")
        return end


def replay_step_logs(
    state: est.EstimatorState,
    rows_by_drone: Mapping[int, Sequence[dict[str, Any]]],
    n: int,
    first: int,
    channel: Channel,
    config: est.EstimatorConfig,
) -> tuple[est.EstimatorState, dict[int, list[tuple[int, np.ndarray, float, bool]]]]:
    """Feed the records of the steps before ``first`` found in step logs to the estimator, step
    by step in order (eqs. 3-5 measurements at the logged positions, m, ENU): a rejoining
    planner's own log (its predecessor's), and its peers' logs when they are at hand (a launch
    keeps every planner's log in one results directory). A step logged twice (an earlier
    rejoin) counts once; a torn line is skipped (:func:`read_step_log`).

    Args:
        rows_by_drone: drone index (0-based) → that drone's logged rows.
        n: drones in the mission. first: the first step not to replay.

    Returns:
        The updated state and, per drone index, its replayed steps as (step, position m,
        range m or NaN, LOS).
    """
    nan = np.nan
    table: dict[int, dict[int, dict[str, Any]]] = {}
    for j, rows in rows_by_drone.items():
        for r in rows:
            if 0 <= r["step"] < first:
                table.setdefault(int(r["step"]), {}).setdefault(j, r)
    done: dict[int, list[tuple[int, np.ndarray, float, bool]]] = {j: [] for j in rows_by_drone}
    for step in sorted(table):
        pos = np.full((n, 3), nan)
        rng, az, el = np.full(n, nan), np.full(n, nan), np.full(n, nan)
        los = np.zeros(n, dtype=bool)
        for j, r in table[step].items():
            m = r["measurement"]
            pos[j] = r["position_m"]
            rng[j] = nan if m.get("range_m") is None else m["range_m"]
            az[j] = nan if m.get("azimuth_rad") is None else m["azimuth_rad"]
            el[j] = nan if m.get("elevation_rad") is None else m["elevation_rad"]
            los[j] = bool(m.get("los"))
            done[j].append((step, pos[j].copy(), float(rng[j]), bool(los[j])))
        state = est.update(state, est.Measurements(positions_m=pos, range_m=rng, azimuth_rad=az, elevation_rad=el, los=los), channel, config)
    return state, done


def read_step_log(path: Path) -> list[dict[str, Any]]:
    """The rows of a planner's step log (JSON lines with a ``step``); a missing file or a
    torn last line (the planner was killed while writing it) gives what could be read."""
    rows: list[dict[str, Any]] = []
    try:
        text = path.read_text()
    except OSError:
        return rows
    for line in text.splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("step"), int) and "position_m" in row and "measurement" in row:
            rows.append(row)
    return rows


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
