"""The lockstep clock of a simulated distributed run (docs/distributed.md, "The lockstep
clock"): it steps everyone together, deterministically.

Protocol on Zenoh (:mod:`comms.keys`, :mod:`comms.messages`):

* pre-flight: ``Tick(-1, t)`` with t growing by :data:`WARMUP_DT_S` while the vehicles take
  off and fly to their start positions, until every planner has published ``Done(-1)``;
* mission: ``Tick(k, t_k)``, t_k = t_0 + k Δt, t_0 the first multiple of Δt after the
  pre-flight; ``Tick(k+1)`` goes out once every live planner has published ``Done(k)``.

A planner that dies (its liveliness token disappears) stops being waited for.
"""

from __future__ import annotations

import math
import queue
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from comms import keys
from comms.errors import FimnavError
from comms.messages import Done, MessageError, Tick, decode, encode
from comms.pubsub import declare_publisher

#: Simulated time per pre-flight tick (s), and wall time between pre-flight ticks (s): the
#: pre-flight (take-off, flight to the start) runs at 10x real time.
WARMUP_DT_S: float = 0.1
WARMUP_PERIOD_S: float = 0.01


class ClockError(FimnavError):
    """The swarm did not make progress within the deadline."""


@dataclass
class StepReport:
    """What the clock saw of one step."""

    step: int
    time_s: float
    done: frozenset[int]
    alive: frozenset[int]


class LockstepClock:
    """Publishes ticks and collects the planners' step reports.

    Args:
        session: an open Zenoh session.
        mission_id: the mission id. count: N. dt_s: the step length.
        wall: monotonic wall clock.
    """

    def __init__(self, session: Any, mission_id: str, count: int, dt_s: float, wall: Callable[[], float] = time.monotonic) -> None:
        self.mission_id = mission_id
        self.count = count
        self.dt = dt_s
        self.wall = wall
        self._q: queue.SimpleQueue[tuple[str, str, bytes | None]] = queue.SimpleQueue()
        self._pub = declare_publisher(session, keys.tick(mission_id))
        self._subs = [
            session.declare_subscriber(keys.done(mission_id), lambda s: self._q.put(("done", str(s.key_expr), bytes(s.payload.to_bytes())))),
            session.liveliness().declare_subscriber(
                keys.alive(mission_id),
                lambda s: self._q.put(("alive" if str(s.kind).endswith("PUT") else "gone", str(s.key_expr), None)),
                history=True,
            ),
        ]
        self.vehicles_alive: set[int] = set()
        self.alive: set[int] = set()
        self.ever_alive: set[int] = set()
        self.done: dict[int, set[int]] = {}
        self.seq = 0
        self.t = 0.0
        self.dropped = 0

    def _drain(self, timeout_s: float) -> None:
        try:
            item = self._q.get(timeout=timeout_s) if timeout_s > 0 else self._q.get_nowait()
        except queue.Empty:
            return
        while True:
            kind, key, data = item
            uav = keys.uav_of(key)
            if kind == "done" and data is not None:
                try:
                    _, msg = decode(data, self.mission_id, self.count)
                except MessageError:
                    self.dropped += 1
                else:
                    if isinstance(msg, Done) and msg.sender == uav:
                        self.done.setdefault(msg.step, set()).add(msg.sender)
            elif uav is not None and 1 <= uav <= self.count and "/alive/vehicle/" in key:
                (self.vehicles_alive.add if kind == "alive" else self.vehicles_alive.discard)(uav)
            elif uav is not None and 1 <= uav <= self.count and "/alive/planner/" in key:
                if kind == "alive":
                    self.alive.add(uav)
                    self.ever_alive.add(uav)
                else:
                    self.alive.discard(uav)
            try:
                item = self._q.get_nowait()
            except queue.Empty:
                return

    def _tick(self, step: int, t: float) -> None:
        self.seq += 1
        self._pub.put(encode(Tick(step, t), self.mission_id, self.seq))

    def _complete(self, step: int, expected: int | None) -> bool:
        done = self.done.get(step, set())
        if expected is not None:
            return len(done) >= expected
        return bool(self.ever_alive) and self.alive <= done

    def preflight(self, timeout_s: float, should_stop: Callable[[], bool] = lambda: False, vehicles: int | None = None) -> float:
        """Wait until every planner (and ``vehicles`` simulated vehicles) is up, then tick the
        pre-flight until every one of the N planners holds its start position; returns t_0."""
        deadline = self.wall() + timeout_s
        want_vehicles = self.count if vehicles is None else vehicles
        while len(self.ever_alive) < self.count or len(self.vehicles_alive) < want_vehicles:
            if should_stop():
                raise ClockError("stopped while the processes started")
            if self.wall() > deadline:
                missing = sorted(set(range(1, self.count + 1)) - self.ever_alive)
                raise ClockError(f"planners {missing} and {want_vehicles - len(self.vehicles_alive)} vehicles did not come up within {timeout_s:g} s")
            self._drain(0.05)
        next_tick = self.wall()
        while not self._complete(-1, self.count):
            if should_stop():
                raise ClockError("stopped during the pre-flight")
            now = self.wall()
            if now > deadline:
                missing = sorted(set(range(1, self.count + 1)) - self.done.get(-1, set()))
                raise ClockError(f"planners {missing} not at their start positions after {timeout_s:g} s of pre-flight")
            if now >= next_tick:
                self.t += WARMUP_DT_S
                self._tick(-1, self.t)
                next_tick = now + WARMUP_PERIOD_S
            self._drain(max(0.0, min(next_tick - self.wall(), 0.05)))
        return self.dt * (math.floor(self.t / self.dt + 1e-9) + 1)

    def end(self, steps: int, t0: float) -> None:
        """Publish the end-of-mission tick ``Tick(K, t_K)`` (K = ``steps``), once every live
        planner has reported step K − 1 done: a planner leaves the swarm only after it, so no
        planner's last record is overtaken by its liveliness going away (call again to re-send)."""
        self._tick(steps, t0 + steps * self.dt)

    def run_step(self, step: int, t0: float, timeout_s: float, should_stop: Callable[[], bool] = lambda: False) -> StepReport:
        """Tick step ``step`` and wait until every live planner reported it done."""
        t = t0 + step * self.dt
        self.t = t
        self._tick(step, t)
        deadline = self.wall() + timeout_s
        resend = self.wall() + 1.0
        while not self._complete(step, None):
            if should_stop():
                raise ClockError(f"stopped at step {step}")
            now = self.wall()
            if now > deadline:
                waiting = sorted(self.alive - self.done.get(step, set()))
                raise ClockError(f"step {step}: planners {waiting} did not finish within {timeout_s:g} s")
            if now >= resend:
                # A planner that joined late (restart) needs the current tick again.
                self._tick(step, t)
                resend = now + 1.0
            self._drain(0.05)
        report = StepReport(step, t, frozenset(self.done.get(step, set())), frozenset(self.alive))
        self.done.pop(step - 2, None)
        return report
