"""The lockstep driver (simulation, docs/distributed.md): steps on the clock's ticks over Zenoh.

The clock publishes ``Tick(step=-1, t)`` during the pre-flight (take-off, fly to the start
position) and each participant answers ``Done(-1)`` once it holds its start position; then
``Tick(k, t_k)`` for k = 0..K-1, each after every live planner has published ``Done(k-1)``.
The vehicle advances to t_k on the tick and its payload publishes the measurement of step k;
the planner waits for telemetry stamped ≥ t_k and for that measurement, waits for every other
planner's record of step k (a barrier: the views are the simulator's), and publishes ``Done(k)``
once its setpoint is on the wire."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from typing import Any

import numpy as np

from comms.mavlink_client import LinkError
from comms.messages import Record
from planner.node.config import NodeConfig, NodeError
from planner.node.core import OwnMeasurement, StepCore
from planner.node.io import NodeIO
from planner.node.takeover import TakeoverWatch

log = logging.getLogger("fimnav.plan")

#: Distance (m) within which the vehicle counts as at its start position.
START_TOLERANCE_M: float = 0.05
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
#: Hold setpoints sent before entering a guided mode that needs a setpoint stream (PX4).
GUIDED_PRIMING_SETPOINTS = 5


class LockstepDriver:
    """Flies the mission on the lockstep clock.

    Args:
        config: the node's configuration. io: its link, swarm and clock. core: the step.
        takeover: the pilot take-over watch. predecessor_rows: a rejoining planner's step
        logs, drone index → rows (its predecessor's and its peers').
    """

    def __init__(
        self, config: NodeConfig, io: NodeIO, core: StepCore, takeover: TakeoverWatch, predecessor_rows: dict[int, list[dict[str, Any]]]
    ) -> None:
        self.config = config
        self.io = io
        self.swarm = io.swarm
        self.core = core
        self.takeover = takeover
        self.predecessor_rows = predecessor_rows
        self.uav = config.uav

    def run(self) -> dict[str, Any]:
        """Pre-flight (or rejoin), the steps, the end of mission; return the summary."""
        first = self._rejoin() if self.config.rejoin else self._start()
        if self.config.rejoin and first < self.config.steps:
            self._rebuild(first)
        done_steps = 0
        for k in range(first, self.config.steps):
            done_steps += self._step(k)
        self._await_end()
        end = self._end()
        return {
            "uav": self.uav,
            "steps": done_steps,
            "dropped": dict(self.swarm.inbox.dropped),
            "mode_changes": self.takeover.mode_changes,
            "taken_over": self.takeover.takeovers,
            "taken_over_steps": self.takeover.steps,
            "end": end,
        }

    # -- one step ---------------------------------------------------------------------------
    def _step(self, k: int) -> int:
        """Step ``k``; 1 if this planner planned and commanded it, 0 if not (taken over)."""
        wall = self.io.clock.wall
        self.swarm.step_now = k
        w0 = wall()
        t_k = self._await_step(k)
        w_tick = wall()
        own = self._own_position(t_k)
        # The vehicle's mode comes with the tick's position (vehicle_sim sends a heartbeat
        # with the first tick report after a mode change).
        self.takeover.watch(k)
        if self.takeover.still_taken_over(k, self._enter_guided):
            self._taken_over_step(k, t_k, own)
            self.core.prev_step_m = np.zeros(3)
            return 0
        meas = self._measurement(k)
        w_meas = wall()
        measurement = OwnMeasurement(meas.los, meas.range_m, meas.azimuth_rad, meas.elevation_rad, meas.extra_values)
        outcome = self.core.step(
            k, t_k, own, measurement, wall, self._wait_for_peer_records, lambda own_m, result: self._send_setpoint(k, own_m, result)
        )
        if not outcome.sent:
            self.takeover.steps += 1
            self.swarm.publish_done(k)
            return 0
        timing = {
            "wait_tick_s": w_tick - w0,
            "wait_measurement_s": w_meas - w_tick,
            "wait_peers_s": outcome.peers_in_s - w_meas,
            "compute_s": outcome.sent_s - outcome.peers_in_s,
            "measurement_to_setpoint_s": outcome.sent_s - w_meas,
        }
        self.core.log_step(k, t_k, own, outcome, timing)
        return 1

    def _send_setpoint(self, k: int, own_m: np.ndarray, result: Any) -> bool:
        """One setpoint for the whole step, unless the vehicle was taken over meanwhile (a
        heartbeat read while the step was planned, the 1 Hz one, may say so)."""
        link = self.io.require_link()
        link.pump(0.0)
        self.takeover.watch(k)
        if self.takeover.active:
            return False
        step = result.step
        u = np.asarray(step.displacement, dtype=float)
        nxt = np.asarray(step.next_position, dtype=float)
        # A target that moves along its velocity (ArduPilot GUIDED) starts here and reaches nxt
        # after dt; one that holds its point (PX4) is nxt with the velocity as a feed-forward.
        link.send_setpoint(own_m if self.io.profile.posvel_target_moves else nxt, u / self.config.dt_s)
        return True

    def _await_step(self, k: int) -> float:
        """Wait for the clock's tick of step ``k``; return t_k (mission s)."""
        # Step 0 starts when the whole swarm is at its start positions: pre-flight deadline.
        timeout = self.config.preflight_timeout_s if k == 0 else self.config.step_timeout_s
        self.io.wait(lambda: self.swarm.tick is not None and self.swarm.tick.step >= k, timeout, f"clock tick of step {k}")
        tick = self.swarm.tick
        if tick is None:
            raise NodeError(f"uav {self.uav}: internal: no clock tick after waiting for the one of step {k}")
        return tick.time_s if tick.step == k else tick.time_s - (tick.step - k) * self.config.dt_s

    def _own_position(self, t_k: float) -> np.ndarray:
        """The vehicle's position (m, ENU) from telemetry stamped at or after ``t_k``."""
        link = self.io.require_link()
        stamp = int(round(t_k * 1000.0))
        what = f"position telemetry at t = {t_k:g} s"
        self.io.wait(self._vehicle_alive(lambda: link.telemetry.position_time_ms >= stamp, what), self.config.step_timeout_s, what)
        if link.telemetry.position_enu_m is None:
            raise NodeError(f"uav {self.uav}: no position telemetry at t = {t_k:g} s")
        return link.telemetry.position_enu_m.astype(float)

    def _vehicle_alive(self, predicate: Callable[[], bool], what: str) -> Callable[[], bool]:
        """``predicate`` that raises NodeError when the vehicle's process leaves the swarm during
        this wait (its liveliness token goes: noticed at once). A vehicle that hangs instead
        fails the wait at the step timeout. (Heartbeat silence is no test here: a machine flying
        a hundred drones on two cores starves processes for more than 10 s at times, and a
        vehicle heartbeats on the wall clock.)"""
        link = self.io.require_link()

        def check() -> bool:
            if predicate():
                return True
            gone_at = self.swarm.vehicle_gone_at
            if gone_at is not None:
                raise NodeError(
                    f"uav {self.uav}: vehicle link lost: the vehicle's process left the swarm "
                    f"{self.io.clock.wall() - gone_at:.1f} s ago, its last heartbeat {link.link_age_s():.1f} s ago, "
                    f"while waiting for {what}"
                )
            return False

        return check

    def _measurement(self, k: int) -> Record:
        """The payload's measurement of step ``k`` (older ones are dropped)."""
        what = f"payload measurement of step {k}"
        measurements = self.swarm.measurements
        self.io.wait(self._vehicle_alive(lambda: k in measurements, what), self.config.step_timeout_s, what)
        for s in [s for s in measurements if s <= k]:
            meas = measurements.pop(s)
        return meas

    def _wait_for_peer_records(self, k: int) -> None:
        """Barrier of step k: the records of every other planner of the mission, except those
        that left. (Waiting only for the planners already seen alive would let a planner whose
        liveliness has not reached us yet be skipped, and the views would differ.)"""
        expected = [j for j in range(1, self.config.drone_count + 1) if j != self.uav]
        left, view = self.swarm.left, self.core.view
        self.io.wait(
            lambda: all(view.has(j, k) for j in expected if j not in left),
            self.config.step_timeout_s,
            f"records of step {k} from the planners",
            missing=lambda: sorted(j for j in expected if j not in left and not view.has(j, k)),
        )

    def _taken_over_step(self, k: int, t_k: float, own: np.ndarray) -> None:
        """Step ``k`` of a drone a pilot flies: no command; its telemetry position at t_k
        published as a record flagged taken over, without a measurement (the payload's of
        this step is dropped); the step answered (``Done``) so the clock goes on. The control
        draws of the step are skipped, so a handed-back planner draws those of its step."""
        measurements = self.swarm.measurements
        for s in [s for s in measurements if s <= k]:
            del measurements[s]
        self.core.track(k, own)
        self.swarm.publish_record(self.core.taken_over_record(k, t_k, own))
        self.core.skip_control_draws(1)
        self.takeover.steps += 1
        self.swarm.publish_done(k)

    def _enter_guided(self, hold_m: np.ndarray) -> None:
        """Switch to the guided mode at ``hold_m`` (m, ENU). Nothing is streamed in lockstep (the
        step's setpoint follows at once); a mode that needs setpoints flowing first (PX4
        OFFBOARD) gets a few hold setpoints."""
        link = self.io.require_link()
        if self.io.profile.guided_needs_setpoint_stream:
            for _ in range(GUIDED_PRIMING_SETPOINTS):
                link.send_setpoint(hold_m, None)
        link.set_mode(self.io.guided_mode)

    # -- before the first step --------------------------------------------------------------
    def _start(self) -> int:
        """Pre-flight, then report ready to the clock; the first step is 0."""
        self.preflight()
        self._flight_streams()
        self.swarm.publish_done(-1)
        log.info("uav %d ready at the start position", self.uav)
        return 0

    def preflight(self) -> None:
        """Heartbeat, streams, GUIDED, arm, take-off and flight to the start position. A vehicle
        found armed in another mode than the guided one is a pilot's (the one rule,
        :meth:`TakeoverWatch.found_at_start`): nothing is changed or commanded."""
        link = self.io.require_link()
        t = self.config.preflight_timeout_s
        link.wait_heartbeat(t)
        for msg_id, hz in LOCKSTEP_STREAM_HZ:
            link.request_interval(msg_id, hz)
        self.io.wait(lambda: link.telemetry.position_enu_m is not None, t, "position telemetry")
        if self.takeover.found_at_start("start"):
            return
        profile = self.io.profile
        if not link.telemetry.armed:
            position = link.telemetry.position_enu_m
            if profile.guided_needs_setpoint_stream:
                # PX4 accepts OFFBOARD only with a setpoint stream already running.
                for _ in range(GUIDED_PRIMING_SETPOINTS):
                    link.send_setpoint(position, None)
            link.set_mode(self.io.guided_mode)
            link.arm()
            if not profile.takeoff_by_setpoint:
                climb_to = float(self.config.start_position_m[2])
                link.takeoff(climb_to)

                def climbed() -> bool:
                    pos = link.telemetry.position_enu_m
                    return pos is not None and pos[2] >= climb_to - START_TOLERANCE_M

                self.io.wait(self._unless_taken_over(climbed), t, "take-off altitude")
        # (armed: in the guided mode already, found_at_start says)
        self.io.wait(self._unless_taken_over(lambda: self._hold_start() < START_TOLERANCE_M), t, "start position")

    def _unless_taken_over(self, predicate: Callable[[], bool]) -> Callable[[], bool]:
        """``predicate`` that also ends a pre-flight wait when a pilot takes the vehicle over
        meanwhile (it leaves the guided mode: the take-over watch records it at step 0)."""

        def check() -> bool:
            link = self.io.require_link()
            if link.left_guided or (link.telemetry.armed and not link.in_mode(self.io.guided_mode)):
                if self.takeover.found_at_start("start"):
                    return True
                raise NodeError(
                    f"uav {self.uav}: the vehicle left {self.io.guided_mode} during the pre-flight and is disarmed (mode {link.mode_name()})"
                )
            return predicate()

        return check

    def _hold_start(self) -> float:
        """Send the start position as setpoint; return the distance to it (m)."""
        link = self.io.require_link()
        start = self.config.start_m
        link.send_setpoint(start, None)
        pos = link.telemetry.position_enu_m
        return math.inf if pos is None else float(np.linalg.norm(pos - start))

    def _flight_streams(self) -> None:
        """Slow the health streams down for the flight (:data:`LOCKSTEP_FLIGHT_STREAM_HZ`); a
        message the autopilot refuses (EKF_STATUS_REPORT on PX4) keeps its rate."""
        link = self.io.require_link()
        for msg_id, hz in LOCKSTEP_FLIGHT_STREAM_HZ:
            try:
                link.request_interval(msg_id, hz)
            except LinkError as exc:
                log.debug("uav %d: message %d keeps its rate (%s)", self.uav, msg_id, exc)

    def _rejoin(self) -> int:
        """Take over a vehicle in flight from a planner that died; return the first step to fly.

        The clock's current step p is answered as done (this planner has neither its
        measurement, published before it subscribed, nor its peers' records) and the planner
        flies from p + 1; its peers wait for it again from its first record on. The control
        stream is advanced past the steps it missed, so its draws stay those of its step. At or
        after the mission's last step there is nothing left to fly: it returns the step count,
        and the vehicle gets the mission's end as every other drone does (:meth:`_end`)."""
        link = self.io.require_link()
        t = self.config.preflight_timeout_s
        link.wait_heartbeat(t)
        for msg_id, hz in LOCKSTEP_STREAM_HZ:
            link.request_interval(msg_id, hz)
        self._flight_streams()
        self.io.wait(lambda: link.telemetry.position_enu_m is not None, t, "position telemetry")
        if not link.telemetry.armed and not self.takeover.in_force:
            raise NodeError(f"uav {self.uav}: cannot rejoin: the vehicle is disarmed (mode {link.mode_name()})")
        self.io.wait(lambda: self.swarm.tick is not None and self.swarm.tick.step >= 0, t, "a clock tick of the mission to rejoin at")
        if self.swarm.tick is None:
            raise NodeError(f"uav {self.uav}: internal: no clock tick after waiting for one")
        p = self.swarm.tick.step
        # The one rule: a vehicle a pilot flies (armed in another mode, or a take-over the
        # launch says is in force) is left as it is; only one armed in GUIDED/OFFBOARD is flown.
        taken = self.takeover.found_at_start("rejoin")
        if p >= self.config.steps - 1:
            # The mission is at its last step or over: nothing left to fly, but the vehicle
            # still gets the mission's end (hold, land or return; left to a pilot who has it),
            # as every other drone does, rather than being left where its predecessor died.
            if p < self.config.steps:
                self.swarm.publish_done(p)
            log.warning(
                "uav %d rejoined at step %d of a %d-step mission: nothing left to fly; the end of mission (%s) follows",
                self.uav,
                p,
                self.config.steps,
                self.config.end_action,
            )
            return self.config.steps
        self.swarm.publish_done(p)
        self.core.skip_control_draws(p + 1)
        log.warning("uav %d rejoined at step %d (%s from step %d)", self.uav, p, "taken over" if taken else "flying", p + 1)
        return p + 1

    def _rebuild(self, first: int) -> None:
        """A rejoining planner's estimator, own-range window and own track, from its
        predecessor's step log and, when they are next to it (a launch's results directory),
        its peers' logs (:meth:`StepCore.rebuild`)."""
        done = self.core.rebuild(first, self.predecessor_rows)
        index = self.config.drone_index
        state = self.core.state
        peers = sum(len(v) for j, v in done.items() if j != index)
        where = f"; estimate {tuple(round(float(v), 2) for v in state.estimate_m)}" if state.observable else ""
        log.warning(
            "uav %d: estimator rebuilt from %d steps of its predecessor's log (steps up to %d) and %d records of %d peers' logs%s",
            self.uav,
            len(done.get(index, [])),
            self.core.used_steps[index],
            peers,
            sum(1 for j, v in done.items() if j != index and v),
            where,
        )

    # -- after the last step ----------------------------------------------------------------
    def _await_end(self) -> None:
        """Stay in the swarm until the clock's end tick (step K), i.e. until every planner has
        done the last step. Leaving at once would let this planner's liveliness token go
        before its last record reaches a slower peer, which would then fly its last step
        without it. A clock that sends no end tick only delays the end by the step timeout
        (with a warning)."""
        steps = self.config.steps
        try:
            self.io.wait(lambda: self.swarm.tick is not None and self.swarm.tick.step >= steps, self.config.step_timeout_s, "end-of-mission tick")
        except NodeError as exc:
            log.warning("%s; ending the mission anyway", exc)

    def _end(self) -> dict[str, Any]:
        """End of mission as the mission says: hold (stay in the guided mode at the last
        setpoint; a guided mode that needs a stream, PX4's, switches to its hold mode), land or
        return to launch, confirmed by the vehicle's mode; left to the pilot of a drone taken
        over."""
        link = self.io.require_link()
        action = self.config.end_action
        profile = self.io.profile
        if self.takeover.active:
            log.warning("uav %d: mission over while taken over (%s): the end action (%s) is left to the pilot", self.uav, link.mode_name(), action)
            return {"action": action, "confirmed": False, "reason": f"taken over ({link.mode_name()})"}
        try:
            if action == "land":
                link.set_mode(self.io.mode_name(profile.land_mode))
            elif action == "rtl":
                link.set_mode(self.io.mode_name(profile.rtl_mode))
            else:
                pos = link.telemetry.position_enu_m
                if pos is not None:
                    link.send_setpoint(pos, None)
                if profile.guided_needs_setpoint_stream:
                    link.set_mode(self.io.mode_name(profile.hold_mode))
        except LinkError as exc:
            raise NodeError(f"uav {self.uav}: end of mission ({action}) failed: {exc}") from None
        log.info("uav %d: mission over (%s)", self.uav, action)
        return {"action": action, "confirmed": True, "mode": link.mode_name()}
