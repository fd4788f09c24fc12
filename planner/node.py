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
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import select
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from comms import keys
from comms.latency import DelayedView
from comms.mavlink_client import LinkError, VehicleLink
from comms.messages import Done, MessageError, MessageKind, Observation, Status, Tick, decode, encode
from comms.pubsub import declare_publisher
from comms.session import SessionSettings, open_session
from planner import estimator as est
from planner.agent import plan
from planner.errors import FimnavError
from planner.randomness import CONTROL_DRAWS, control_rng

log = logging.getLogger("fimnav.plan")

#: Distance (m) within which the vehicle counts as at its start position.
START_TOLERANCE_M: float = 0.05


class NodeError(FimnavError):
    """The planner cannot go on (vehicle refused, lost peers beyond the deadline, ...)."""


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


class _Inbox:
    """Messages from Zenoh callbacks, handed to the node's single thread through a queue."""

    def __init__(self, mission_id: str, count: int) -> None:
        self.mission_id = mission_id
        self.count = count
        self.queue: queue.SimpleQueue[tuple[str, str, bytes | None]] = queue.SimpleQueue()
        self.dropped: Counter[str] = Counter()
        # Self-pipe: a callback makes it readable so the node's select() wakes at once.
        self.wake_r, self.wake_w = os.pipe()
        os.set_blocking(self.wake_r, False)
        os.set_blocking(self.wake_w, False)

    def _put(self, item: tuple[str, str, bytes | None]) -> None:
        self.queue.put(item)
        try:
            os.write(self.wake_w, b"z")
        except (BlockingIOError, OSError):
            pass  # already readable (or closing)

    def on_sample(self, sample: Any) -> None:
        self._put(("data", str(sample.key_expr), bytes(sample.payload.to_bytes())))

    def on_liveliness(self, sample: Any) -> None:
        self._put(("alive" if str(sample.kind).endswith("PUT") else "gone", str(sample.key_expr), None))

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
    """

    def __init__(
        self,
        mission: Any,
        options: NodeOptions,
        link_factory: Callable[[str, int], VehicleLink] | None = None,
        session_factory: Callable[[SessionSettings], Any] = open_session,
        wall: Callable[[], float] = time.monotonic,
    ) -> None:
        self.m = mission
        self.o = options
        self.wall = wall
        n = mission.drones.count
        if not 1 <= options.uav <= n:
            raise NodeError(f"--uav {options.uav}: the mission has drones 1..{n}")
        self.i = options.uav - 1
        self.n = n
        self.steps = options.steps or mission.steps
        self.dt = mission.dt_s
        self.channel = mission.channel.to_planner()
        self.limits = mission.limits()
        self.boxes = mission.obstacle_bounds()
        self.ranging = mission.drones.ranging_mask()
        self.bearing = mission.drones.bearing_mask()
        self.start = mission.drones.start_positions_m()[self.i]
        self.est_config = mission.estimator_config()
        self.ctrl_rng = control_rng(mission.seed, 0, self.i)
        self.view = DelayedView(self.i, n, mission.comms.d_hop_m, mission.comms.h_max, emulate=mission.comms.latency == "emulated")
        self.inbox = _Inbox(mission.id, n)
        self._link_factory = link_factory or (lambda conn, sysid: VehicleLink(conn, sysid))
        self._session_factory = session_factory
        self.session: Any = None
        self.link: VehicleLink | None = None
        self.alive: set[int] = set()
        self.tick: Tick | None = None
        self.measurements: dict[int, Observation] = {}
        self.seq = 0
        self._log: TextIO | None = None

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
        self._token = s.liveliness().declare_token(keys.alive(mid, "planner", self.o.uav))
        self._pub_record = declare_publisher(s, keys.record(mid, self.o.uav))
        self._pub_status = declare_publisher(s, keys.status(mid, self.o.uav))
        self._pub_done = declare_publisher(s, keys.done(mid, self.o.uav))
        if self.o.log_path is not None:
            self.o.log_path.parent.mkdir(parents=True, exist_ok=True)
            self._log = self.o.log_path.open("w")
        self.link = self._link_factory(self.o.mavlink, self.o.sysid or self.o.uav)

    def close(self) -> None:
        """Release the link, the Zenoh session and the log (idempotent)."""
        if self.link is not None:
            self.link.close()
            self.link = None
        if self.session is not None:
            try:
                self._token.undeclare()
            except Exception:  # noqa: BLE001 - closing anyway
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

    def _drain(self, timeout_s: float = 0.0) -> None:
        """Handle queued Zenoh messages (waiting up to ``timeout_s`` for the first)."""
        try:
            item = self.inbox.queue.get(timeout=timeout_s) if timeout_s > 0 else self.inbox.queue.get_nowait()
        except queue.Empty:
            return
        while True:
            kind, key, data = item
            if kind == "data":
                msg = self.inbox.decode(key, data)  # type: ignore[arg-type]
                if isinstance(msg, Observation):
                    if "/measurement/" in key:
                        self.measurements[msg.step] = msg
                    else:
                        self.view.add(msg)
                elif isinstance(msg, Tick):
                    if self.tick is None or msg.step >= self.tick.step:
                        self.tick = msg
            else:
                uav = keys.uav_of(key)
                if uav is not None and 1 <= uav <= self.n:
                    (self.alive.add if kind == "alive" else self.alive.discard)(uav)
                    if kind == "gone":
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
            fds = [self.inbox.wake_r] + ([link.fileno()] if link.fileno() is not None else [])
            try:
                select.select(fds, [], [], min(remaining, 0.25))
            except (OSError, ValueError):
                pass
            self.inbox.clear_wake()
            self._drain(0.0)
            link.pump(0.0)

    def _require_link(self) -> VehicleLink:
        if self.link is None:
            raise NodeError(f"uav {self.o.uav}: the vehicle link is closed")
        return self.link

    # -- flight -----------------------------------------------------------------------------
    def preflight(self) -> None:
        """Heartbeat, streams, GUIDED, arm, take-off and flight to the start position."""
        link = self.link
        assert link is not None
        t = self.o.preflight_timeout_s
        link.wait_heartbeat(t)
        if self.o.lockstep:
            # A simulated vehicle in lockstep reports its position on every tick: the streams
            # only need to be slow (every message is parsed here and logged by the vehicle).
            rates = {32: 1.0, 33: 0.2, 242: 0.2, 245: 0.2, 30: 0.2, 74: 0.2}  # + ATTITUDE, VFR_HUD
        else:
            rates = {32: 10.0, 33: 5.0, 242: 0.2, 245: 1.0}
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
                self._wait_preflight(lambda: link.telemetry.position_enu_m[2] >= climb_to - START_TOLERANCE_M, "take-off altitude")
        else:
            link.set_mode(mode)
        self._wait_preflight(lambda: self._hold_start() < START_TOLERANCE_M, "start position")

    def _hold_start(self) -> float:
        """Send the start position as setpoint; return the distance to it (m)."""
        link = self.link
        assert link is not None
        link.send_setpoint(self.start, None)
        pos = link.telemetry.position_enu_m
        return math.inf if pos is None else float(np.linalg.norm(pos - self.start))

    def _wait_preflight(self, predicate: Callable[[], bool], what: str) -> None:
        """Wait for a pre-flight condition; in lockstep, report Done(-1) only when ready."""
        self._wait(predicate, self.o.preflight_timeout_s, what)

    # -- the mission ------------------------------------------------------------------------
    def run(self) -> dict[str, Any]:
        """Fly the mission; return a summary (steps done, dropped messages)."""
        self._open()
        try:
            self._drain(0.0)
            self.preflight()
            self._publish(self._pub_done, Done(self.o.uav, -1))
            log.info("uav %d ready at the start position", self.o.uav)
            state = est.initial_state((), self.est_config)
            used = np.full(self.n, -1, dtype=np.int64)
            prev_step = np.zeros(3)
            done_steps = 0
            for k in range(self.steps):
                w0 = self.wall()
                t_k = self._await_step(k)
                w_tick = self.wall()
                own = self._own_position(t_k)
                meas = self._measurement(k)
                w_meas = self.wall()
                record = Observation(
                    self.o.uav, k, t_k, tuple(float(v) for v in own), bool(self.ranging[self.i]), bool(self.bearing[self.i]),
                    meas.los, meas.range_m, meas.azimuth_rad, meas.elevation_rad,
                )
                self.view.add(record)
                self._publish(self._pub_record, record, MessageKind.RECORD)
                self._wait(
                    lambda: all(self.view.has(j, k) for j in self.alive if j != self.o.uav),
                    self.o.step_timeout_s,
                    f"records of step {k} from the live planners",
                    missing=lambda: sorted(j for j in self.alive if j != self.o.uav and not self.view.has(j, k)),
                )
                w_peers = self.wall()
                view = self.view.advance(k)
                state, rows = self._estimate(state, view, used)
                used = np.maximum(used, view.saved_steps)
                result = self._plan(k, own, prev_step, view, state)
                step = result.step
                u = np.asarray(step.displacement, dtype=float)
                nxt = np.asarray(step.next_position, dtype=float)
                assert self.link is not None
                self.link.send_setpoint(nxt, u / self.dt)
                w_sent = self.wall()
                prev_step = u
                active_mask = int(sum(1 << b for b, a in enumerate(np.asarray(step.active)) if a))
                self._publish(
                    self._pub_status,
                    Status(self.o.uav, k, t_k, tuple(float(v) for v in state.estimate_m), bool(state.observable), bool(step.singular), active_mask, tuple(int(s) for s in view.saved_steps)),
                )
                self._publish(self._pub_done, Done(self.o.uav, k))
                timing = {"wait_tick_s": w_tick - w0, "wait_measurement_s": w_meas - w_tick, "wait_peers_s": w_peers - w_meas,
                          "compute_s": w_sent - w_peers, "measurement_to_setpoint_s": w_sent - w_meas}
                self._log_step(k, t_k, own, record, view, state, result, rows, timing)
                done_steps += 1
            self._end()
            return {"uav": self.o.uav, "steps": done_steps, "dropped": dict(self.inbox.dropped)}
        finally:
            self.close()

    def _await_step(self, k: int) -> float:
        if self.o.lockstep:
            # Step 0 starts when the whole swarm is at its start positions: pre-flight deadline.
            timeout = self.o.preflight_timeout_s if k == 0 else self.o.step_timeout_s
            self._wait(lambda: self.tick is not None and self.tick.step >= k, timeout, f"clock tick of step {k}")
            assert self.tick is not None
            return self.tick.time_s if self.tick.step == k else self.tick.time_s - (self.tick.step - k) * self.dt
        raise NodeError("real-time stepping is not available in this build; run with the lockstep clock")

    def _own_position(self, t_k: float) -> np.ndarray:
        link = self.link
        assert link is not None
        stamp = int(round(t_k * 1000.0))
        self._wait(lambda: link.telemetry.position_time_ms >= stamp, self.o.step_timeout_s, f"position telemetry at t = {t_k:g} s")
        assert link.telemetry.position_enu_m is not None
        return link.telemetry.position_enu_m.astype(float)

    def _measurement(self, k: int) -> Observation:
        self._wait(lambda: k in self.measurements, self.o.step_timeout_s, f"payload measurement of step {k}")
        for s in [s for s in self.measurements if s <= k]:
            meas = self.measurements.pop(s)
        return meas

    def _estimate(self, state: est.EstimatorState, view: Any, used: np.ndarray) -> tuple[est.EstimatorState, int]:
        new = view.saved_steps > used
        pos = np.full((self.n, 3), np.nan)
        rng = np.full(self.n, np.nan)
        az = np.full(self.n, np.nan)
        el = np.full(self.n, np.nan)
        los = np.zeros(self.n, dtype=bool)
        for j, rec in enumerate(view.records):
            if rec is not None and new[j]:
                pos[j] = rec.position_m
                rng[j], az[j], el[j], los[j] = rec.range_m, rec.azimuth_rad, rec.elevation_rad, rec.los
        meas = est.Measurements(positions_m=pos, range_m=rng, azimuth_rad=az, elevation_rad=el, los=los)
        return est.update(state, meas, self.channel, self.est_config), int(new.sum())

    def _plan(self, k: int, own: np.ndarray, prev_step: np.ndarray, view: Any, state: est.EstimatorState) -> Any:
        pos = np.zeros((self.n, 3))
        valid = np.zeros(self.n, dtype=bool)
        los = np.zeros(self.n, dtype=bool)
        for j, rec in enumerate(view.records):
            if rec is not None:
                pos[j], valid[j], los[j] = rec.position_m, True, rec.los
        own_mask = np.zeros(self.n, dtype=bool)
        own_mask[self.i] = True
        ages = np.where(valid, k - view.saved_steps, 0)
        uniforms = self.ctrl_rng.random(CONTROL_DRAWS)
        mc = self.m.controller
        bmin, bmax = self.boxes
        return plan(
            own, prev_step, own_mask, pos, valid, los, ages, view.hops, self.ranging, self.bearing,
            state.estimate_m, state.information, state.observable, self.channel, self.limits, self.m.criterion,
            bmin, bmax, self.m.comms.d_hop_m, uniforms, xi=mc.xi, perturbation_rad=mc.random_perturbation_rad,
        )

    def _log_step(self, k: int, t_k: float, own: np.ndarray, record: Observation, view: Any, state: Any, result: Any, rows: int, timing: dict[str, float]) -> None:
        if self._log is None:
            return
        step = result.step
        entry = {
            "step": k,
            "t_s": t_k,
            "position_m": [float(v) for v in own],
            "measurement": {"range_m": _num(record.range_m), "azimuth_rad": _num(record.azimuth_rad), "elevation_rad": _num(record.elevation_rad), "los": record.los},
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

    def _end(self) -> None:
        """End of mission as the mission says: hold (stay in GUIDED at the last setpoint),
        land or return to launch, confirmed by the vehicle's mode."""
        link = self.link
        assert link is not None
        action = self.m.end_action
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


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None
