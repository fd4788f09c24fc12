"""The real-time driver (external autopilots, docs/external-autopilots.md): steps on the wall
clock.

Step k begins at wall time ``t0 + k·dt/speedup`` on a grid shared by every planner of the
mission (UNIX time multiples of dt/speedup, or ``--start-at``); the own measurement is the
newest payload measurement not older than a bound; the peers' records of step k are gathered
until a deadline inside the step, never a barrier; the setpoint is a short trajectory towards
the planned position, re-sent at ≥ 4 Hz of mission time until the next step replaces it, so a
late step never leaves the vehicle without a setpoint. A lost vehicle link (no heartbeat for
2 s) is reported; the planner keeps publishing its last record flagged stale and sends no
setpoint; when the heartbeat returns it flies on if the vehicle is still in GUIDED/OFFBOARD,
and takes it as taken over (the one rule, planner/node/takeover.py) if it is armed in any other
mode."""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from comms.latency import DelayedView
from comms.mavlink_client import MAV_LANDED_STATE_NAMES, LinkError
from comms.messages import Record
from planner.node.config import NodeConfig, NodeError
from planner.node.core import OwnMeasurement, StepCore
from planner.node.io import NodeIO
from planner.node.realtime_preflight import STREAM_BEFORE_GUIDED_S, RealtimePreflight
from planner.node.takeover import TakeoverWatch

log = logging.getLogger("fimnav.plan")

#: A position older than this (wall s) is not planned on.
POSITION_MAX_AGE_S: float = 1.0

#: A setpoint stream: wall time (s, monotonic) → (position m, velocity m/s), ENU; None: not set.
Trajectory = Callable[[float], tuple[np.ndarray | None, np.ndarray | None]]


class PeerRecordGrid:
    """The peers' records on this planner's real-time step grid: planners started apart number
    their steps differently but share the grid, so a record's step here is its time stamp's.

    Args:
        uav: this planner's drone id (1-based). dt_wall_s: step length (wall s).
        view: the delayed view the records enter.
    """

    def __init__(self, uav: int, dt_wall_s: float, view: DelayedView) -> None:
        self.uav = uav
        self.dt_wall_s = dt_wall_s
        self.view = view
        #: UNIX time of step 0 (s), once the grid has started.
        self.t0_unix: float | None = None
        #: Drone id → the last step it said "stale" (its link is down: it answered, nothing new).
        self.stale_peers: dict[int, int] = {}

    def add(self, rec: Record) -> None:
        """A peer's record (any step numbering), re-indexed by its time stamp (UNIX s); before
        step 0 a record cannot enter any view. A stale record answers for its step without
        refreshing the peer's data (its saved record keeps ageing, widening the margin)."""
        if rec.sender == self.uav or self.t0_unix is None:
            return
        step = int(round((rec.time_s - self.t0_unix) / self.dt_wall_s))
        if step < 0:
            return
        if rec.stale:
            self.stale_peers[rec.sender] = step
            return
        self.view.add(dataclasses.replace(rec, step=step))

    def missing(self, k: int, alive: set[int]) -> list[int]:
        """Live peers (1-based ids in ``alive``) whose record of step k has not arrived."""
        return sorted(j for j in alive if j != self.uav and not self.view.has(j, k) and self.stale_peers.get(j) != k)


class RealtimeDriver:
    """Flies the mission on the wall clock (see the module doc).

    Args:
        config: the node's configuration. io: its link, swarm and clock. core: the step.
        takeover: the pilot take-over watch. grid: the peers' records on the step grid.
        predecessor_rows: a rejoining planner's step logs, drone index → rows (its
            predecessor's and its peers').
    """

    def __init__(
        self,
        config: NodeConfig,
        io: NodeIO,
        core: StepCore,
        takeover: TakeoverWatch,
        grid: PeerRecordGrid,
        predecessor_rows: dict[int, list[dict[str, Any]]] | None = None,
    ) -> None:
        self.config = config
        self.io = io
        self.swarm = io.swarm
        self.core = core
        self.takeover = takeover
        self.grid = grid
        self.predecessor_rows = predecessor_rows or {}
        self.uav = config.uav
        self.dt_wall_s = config.dt_wall_s
        self.preflight = RealtimePreflight(config, io, lambda: self.link_down_since is not None, takeover)
        #: When the vehicle link was lost (monotonic s), while it is.
        self.link_down_since: float | None = None
        self.resume_needed = False
        self.link_losses: list[dict[str, float]] = []
        self.late_steps = 0
        self.position_gaps = 0
        self.stale_steps = 0
        io.on_served = self._check_link

    def run(self) -> dict[str, Any]:
        """Pre-flight (or rejoin), the steps on the grid, the end of mission; return the summary."""
        link = self.io.require_link()
        try:
            if self.config.rejoin:
                self.preflight.rejoin()
            else:
                self.preflight.run()
        except LinkError as exc:
            raise NodeError(f"uav {self.uav}: {'rejoin' if self.config.rejoin else 'pre-flight'} failed: {exc}") from None
        self.swarm.publish_done(-1)
        k = self._start_grid()
        if self.config.rejoin:
            self._rebuild(k)
        done_steps = 0
        while k < self.config.steps:
            advance, planned = self._step(k)
            done_steps += planned
            k += advance
        end = self._end()
        rate = self.preflight.vehicle_clock_rate
        return {
            "uav": self.uav,
            "steps": done_steps,
            "stale_steps": self.stale_steps,
            "late_steps": self.late_steps,
            "flavour": link.flavour,
            "frame": self.config.setpoint_frame,
            "link_losses": self.link_losses,
            "mode_changes": self.takeover.mode_changes,
            "taken_over": self.takeover.takeovers,
            "taken_over_steps": self.takeover.steps,
            "setpoints_sent": link.setpoints_sent,
            "dropped": dict(self.swarm.inbox.dropped),
            "end": end,
            "vehicle_clock_rate": None if rate is None else round(rate, 3),
        }

    def _rebuild(self, first: int) -> None:
        """A rejoining planner's estimator, own-range window and own track, from its
        predecessor's step log and its peers' logs next to it (:meth:`StepCore.rebuild`)."""
        done = self.core.rebuild(first, self.predecessor_rows)
        index = self.config.drone_index
        peers = sum(len(v) for j, v in done.items() if j != index)
        log.warning(
            "uav %d rejoined at step %d (%s); estimator rebuilt from %d steps of its predecessor's log and %d records of peers' logs",
            self.uav,
            first,
            "taken over" if self.takeover.active else "flying",
            len(done.get(index, [])),
            peers,
        )

    def _start_grid(self) -> int:
        """Fix the UNIX time of step 0 (``--start-at``, else the next multiple of dt/speedup a
        quarter step from now); return the first step to fly."""
        dtw = self.dt_wall_s
        now = self.io.clock.unix()
        start_at = self.config.start_at_unix
        t0 = start_at if start_at is not None else math.ceil((now + 0.25 * dtw) / dtw) * dtw
        self.grid.t0_unix = t0
        if self.config.rejoin:
            log.info("uav %d rejoining the step grid: step 0 at UNIX %.3f (dt %.3g s wall)", self.uav, t0, dtw)
        else:
            log.info("uav %d ready at the start position; step 0 at UNIX %.3f (dt %.3g s wall)", self.uav, t0, dtw)
        return max(0, math.ceil((now - t0) / dtw - 1e-9)) if start_at is not None else 0

    # -- one step ---------------------------------------------------------------------------
    def _step(self, k: int) -> tuple[int, int]:
        """Step ``k`` at its grid time; return (steps to advance, 1 if planned and commanded)."""
        dtw = self.dt_wall_s
        t0 = self.grid.t0_unix
        if t0 is None:
            raise NodeError(f"uav {self.uav}: internal: step {k} before the step grid started")
        t_k = t0 + k * dtw
        self._serve_until_unix(t_k)
        w0 = self.io.clock.unix()
        if w0 - t_k > dtw:
            skip = int((w0 - t_k) // dtw)
            self.late_steps += skip
            log.warning("uav %d: step %d is %.3f s late; skipping %d step(s), the vehicle follows the last setpoint", self.uav, k, w0 - t_k, skip)
            return skip, 0
        if self.resume_needed and self.link_down_since is None:
            try:
                self._resume(k)
            except LinkError as exc:
                log.error("uav %d: resuming failed (%s); retrying next step", self.uav, exc)
                self.resume_needed = True
        if self.link_down_since is not None and self.io.clock.wall() - self.link_down_since > self.config.step_timeout_s:
            raise NodeError(
                f"uav {self.uav}: vehicle link at {self.config.mavlink} lost for good: no heartbeat for "
                f"{self.io.clock.wall() - self.link_down_since:.0f} s (more than the step timeout); giving the drone up; "
                f"meanwhile {self.io.profile.link_loss_failsafe}"
            )
        if self.link_down_since is not None or self.resume_needed:
            self._publish_stale(k, w0)
            self.stale_steps += 1
            return 1, 0
        self.takeover.watch(k)
        if self.takeover.still_taken_over(k, self._enter_guided):
            self._taken_over_step(k, w0)
            return 1, 0
        own = self._fresh_position(k, w0)
        if own is None:
            self.stale_steps += 1
            return 1, 0
        self._planned_step(k, t_k, w0, own)
        return 1, 1

    def _planned_step(self, k: int, t_k: float, w0: float, own: np.ndarray) -> None:
        """Plan step ``k`` (began at UNIX ``w0``, due at ``t_k``) from ``own`` (m, ENU) and
        stream its trajectory; log it."""
        dtw = self.dt_wall_s
        unix = self.io.clock.unix
        link = self.io.require_link()
        outcome = self.core.step(
            k,
            w0,
            own,
            self._own_measurement(k, w0),
            unix,
            lambda step: self._collect_peers(step, t_k + self.config.peer_wait_fraction * dtw),
            lambda own_m, result: self._stream(link, own_m, np.asarray(result.step.next_position, dtype=float) - own_m),
        )
        timing = {
            "late_s": w0 - t_k,
            "wait_peers_s": outcome.peers_in_s - outcome.published_s,
            "compute_s": outcome.sent_s - outcome.peers_in_s,
            "measurement_to_setpoint_s": outcome.sent_s - w0,
        }
        self.core.log_step(k, w0, own, outcome, timing)

    def _stream(self, link: Any, own_m: np.ndarray, u_m: np.ndarray) -> bool:
        link.set_stream(self._trajectory(own_m, u_m, self.io.clock.wall()))
        return True

    def _fresh_position(self, k: int, w0: float) -> np.ndarray | None:
        """The vehicle's position (m, ENU) if fresh; else (heartbeats but no position: plan
        nothing on an old position) the last record is published as stale and None returned."""
        link = self.io.require_link()
        pos = link.telemetry.position_enu_m
        if pos is None:
            raise NodeError(f"uav {self.uav}: step {k}: no position telemetry from the vehicle")
        age = self.io.clock.wall() - link.telemetry.position_wall_s
        if age > POSITION_MAX_AGE_S:
            self.position_gaps += 1
            log.warning("uav %d: step %d: the last position is %.2f s old; publishing the last record as stale", self.uav, k, age)
            self._publish_stale(k, w0)
            return None
        return pos.astype(float)

    def _own_measurement(self, k: int, w0: float) -> OwnMeasurement:
        """The newest payload measurement if at most the configured age old at ``w0``; without
        one, a record with LOS and no values. Only the channels this drone has are kept."""
        max_age_wall = self.config.measurement_max_age_s / self.config.speedup
        meas = self.swarm.latest_measurement
        fresh = meas is not None and w0 - meas.time_s <= max_age_wall
        if not fresh:
            log.warning("uav %d: step %d without a payload measurement newer than %.3g s", self.uav, k, max_age_wall)
        planner, i = self.config.planner, self.config.drone_index
        nan = float("nan")
        return OwnMeasurement(
            bool(meas.los) if fresh and meas else True,
            meas.range_m if fresh and meas and planner.ranging[i] else nan,
            meas.azimuth_rad if fresh and meas and planner.bearing[i] else nan,
            meas.elevation_rad if fresh and meas and planner.bearing[i] else nan,
            meas.extra_values if fresh and meas else {},
        )

    def _collect_peers(self, k: int, deadline_unix: float) -> None:
        """Serve until the records of step k from the live peers are in or the deadline."""
        if not self._serve_until_unix(deadline_unix, lambda: not self.grid.missing(k, self.swarm.alive)):
            log.info("uav %d: step %d without the records of %s (deadline)", self.uav, k, self.grid.missing(k, self.swarm.alive))

    def _trajectory(self, own: np.ndarray, u: np.ndarray, t_from: float) -> Trajectory:
        """The streamed setpoint of one step: from ``own`` along ``u`` (m, ENU) over one
        step, position + velocity feed-forward u/dt; then the end point, zero velocity."""
        dt_w = self.dt_wall_s
        v = u / self.config.dt_s
        end = own + u
        zero = np.zeros(3)

        def at(t_wall: float) -> tuple[np.ndarray | None, np.ndarray | None]:
            f = (t_wall - t_from) / dt_w
            if f >= 1.0:
                return end, zero
            return own + u * max(f, 0.0), v

        return at

    def _publish_stale(self, k: int, w0: float, taken_over: bool = False) -> None:
        """The last own record again, for step ``k`` at UNIX ``w0``, flagged stale."""
        last = self.core.last_record
        if last is not None:
            if taken_over:
                self.swarm.publish_record(dataclasses.replace(last, step=k, time_s=w0, stale=True, taken_over=True))
            else:
                self.swarm.publish_record(dataclasses.replace(last, step=k, time_s=w0, stale=True))

    def _taken_over_step(self, k: int, w0: float) -> None:
        """Taken over: no command. The drone's position from telemetry is published every step,
        without a measurement (the pilot's flight is no planned sensing), so the others keep
        clear of where it is; without telemetry its last record, as stale."""
        link = self.io.require_link()
        pos = link.telemetry.position_enu_m
        if pos is not None and self.io.clock.wall() - link.telemetry.position_wall_s <= POSITION_MAX_AGE_S:
            self.swarm.publish_record(self.core.taken_over_record(k, w0, pos))
        else:
            self._publish_stale(k, w0, taken_over=True)
        self.takeover.steps += 1
        self.core.prev_step_m = np.zeros(3)

    def _enter_guided(self, hold_m: np.ndarray) -> None:
        """Back into the guided mode holding ``hold_m`` (m, ENU) with the setpoint stream until
        the step's trajectory; a mode that needs setpoints flowing first (PX4 OFFBOARD) gets
        the stream for :data:`STREAM_BEFORE_GUIDED_S` (mission s) before the mode change."""
        link = self.io.require_link()
        if self.io.profile.guided_needs_setpoint_stream:
            link.set_stream(lambda _t: (hold_m, None))
            wall = self.io.clock.wall
            since = wall()
            self.io.wait(lambda: wall() - since >= STREAM_BEFORE_GUIDED_S / self.config.speedup, self.config.step_timeout_s, "setpoint stream")
            link.set_mode(self.io.guided_mode)
        else:
            link.set_mode(self.io.guided_mode)
            link.set_stream(lambda _t: (hold_m, None))

    # -- serving and the link watch ---------------------------------------------------------
    def _serve_until_unix(self, t_unix: float, predicate: Callable[[], bool] | None = None) -> bool:
        """Serve MAVLink (the setpoint stream), Zenoh and the link watch until UNIX time
        ``t_unix`` or until ``predicate()``; return whether the predicate held."""
        unix = self.io.clock.unix
        while True:
            if predicate is not None and predicate():
                return True
            remaining = t_unix - unix()
            if remaining <= 0:
                return predicate() if predicate is not None else True
            self.io.sleep_io(remaining)

    def _check_link(self) -> None:
        """Notice a lost vehicle link (no heartbeat for 2 s) and its return; report both."""
        link = self.io.link
        if link is None:
            return
        wall = self.io.clock.wall
        if link.lost and self.link_down_since is None:
            self.link_down_since = wall()
            log.error(
                "uav %d: vehicle link lost (no heartbeat for %.1f s): publishing the last record as stale until it returns; meanwhile %s",
                self.uav,
                link.link_age_s(),
                self.io.profile.link_loss_failsafe,
            )
        elif self.link_down_since is not None and not link.lost:
            down = wall() - self.link_down_since
            self.link_losses.append({"down_s": round(down, 3)})
            log.warning("uav %d: vehicle link back after %.1f s; resuming", self.uav, down)
            self.link_down_since = None
            self.resume_needed = True

    def _resume(self, k: int) -> None:
        """After a link loss, at step ``k``: a vehicle still in GUIDED/OFFBOARD flies on (its
        stream, paused while the link was lost, goes on); one armed in another mode is taken
        over from step ``k`` (:meth:`TakeoverWatch.found_after_link_loss`: the planner cannot
        tell a failsafe's mode change during the loss from a pilot's, and takes neither), and
        one taken over before the loss stays so; both wait for ``fimnav handback``. A disarmed
        vehicle is refused (NodeError). No mode is changed here."""
        link = self.io.require_link()
        self.resume_needed = False
        self.io.wait(lambda: link.telemetry.custom_mode is not None, self.config.step_timeout_s, "heartbeat after the link loss")
        if not link.telemetry.armed:
            raise NodeError(
                f"uav {self.uav}: the vehicle is disarmed after the link loss (mode {link.mode_name()}; landed by "
                "its failsafe or rebooted): not taking off again without an operator"
            )
        # The autopilot may have rebooted (stream rates gone): ask for the streams again.
        self.preflight.request_streams()
        if self.takeover.active:
            log.warning("uav %d: link back, the vehicle in %s: still taken over, left to the pilot until fimnav handback", self.uav, link.mode_name())
            return
        if self.takeover.found_after_link_loss(k):
            return
        link.left_guided = False
        log.info("uav %d: resumed in %s", self.uav, self.io.guided_mode)

    # -- after the last step ----------------------------------------------------------------
    def _end(self) -> dict[str, Any]:
        """End of mission as the mission says, confirmed by the vehicle's mode and state: hold
        (ArduPilot: GUIDED at a position target, which never times out; a guided mode that
        needs a stream, PX4's: its hold mode, AUTO.LOITER), land (until landed and disarmed)
        or RTL (confirmed by the mode)."""
        link = self.io.require_link()
        action = self.config.end_action
        if self.link_down_since is not None:
            log.error("uav %d: mission over with the vehicle link down: its failsafe keeps control", self.uav)
            return {"action": action, "confirmed": False, "reason": "link lost"}
        if self.takeover.active:
            log.warning("uav %d: mission over while taken over (%s): the end action (%s) is left to the pilot", self.uav, link.mode_name(), action)
            return {"action": action, "confirmed": False, "reason": f"taken over ({link.mode_name()})"}
        try:
            self._end_action(action)
        except LinkError as exc:
            raise NodeError(f"uav {self.uav}: end of mission ({action}) failed: {exc}") from None
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
        log.info("uav %d: mission over (%s): vehicle in %s, %s", self.uav, action, end["mode"], "armed" if end["armed"] else "disarmed")
        return end

    def _end_action(self, action: str) -> None:
        """Command the end action and wait for the vehicle to confirm it (hold, land)."""
        link = self.io.require_link()
        profile = self.io.profile
        timeout_s = self.config.end_timeout_s
        pos = link.telemetry.position_enu_m
        if action == "hold":
            if pos is not None:
                hold = pos.astype(float)
                link.set_stream(lambda _t: (hold, None))
            if profile.guided_needs_setpoint_stream:
                link.set_mode(self.io.mode_name(profile.hold_mode))
            want = self.io.mode_name(profile.hold_mode) if profile.guided_needs_setpoint_stream else self.io.guided_mode
            self.io.wait(lambda: link.in_mode(want) and link.telemetry.armed, timeout_s, f"armed heartbeat in {want}")
        elif action == "land":
            link.set_mode(self.io.mode_name(profile.land_mode))
            link.set_stream(None)
            self.io.wait(lambda: not link.telemetry.armed and link.telemetry.landed_state in (None, 1), timeout_s, "landed and disarmed vehicle")
        else:
            link.set_mode(self.io.mode_name(profile.rtl_mode))
            link.set_stream(None)
