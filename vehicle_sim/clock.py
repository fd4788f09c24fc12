"""Clocks of the simulated vehicles: real time with a speed-up, or lockstep ticks.

* :class:`RealTimeClock`: sim time = speed-up × wall time elapsed since start.
* :class:`TickQueue`: sim time advances only when a tick arrives, in process
  (:meth:`TickQueue.push`), from :class:`vehicle_sim.bridge.ZenohBridge` (a mission's clock,
  :mod:`missions.launch.clock`) or, for a vehicle without a mission, from
  :class:`ZenohTickSource`. The queue is thread safe and exposes a file descriptor that
  becomes readable when a tick is queued, so a select() loop wakes up at once.

A tick is :class:`comms.messages.Tick` (``step``, ``time_s``) on the key
:func:`comms.keys.tick` (``fimnav/<mission id>/clock/tick``), with one encoding whoever
publishes it: the binary message of :func:`comms.messages.encode`, whose header names the
mission. The Zenoh session comes from :func:`comms.session.open_session`.
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from collections.abc import Callable
from typing import Any

from comms import keys
from comms.messages import MessageError, Tick, decode
from comms.session import SessionSettings, open_session

log = logging.getLogger(__name__)


class RealTimeClock:
    """Sim time from the wall clock: ``t = speedup · (wall() - wall_start)`` seconds.

    Args:
        speedup: sim seconds per wall second (> 0).
        wall: monotonic wall clock (s), injectable for tests.
    """

    def __init__(self, speedup: float = 1.0, wall: Callable[[], float] = time.monotonic) -> None:
        if not (math.isfinite(speedup) and speedup > 0.0):
            raise ValueError(f"speed-up must be a finite positive number, found {speedup!r}")
        self.speedup = float(speedup)
        self.wall = wall
        self.wall_start = wall()

    def now_s(self) -> float:
        """Current sim time (s)."""
        return (self.wall() - self.wall_start) * self.speedup

    def wall_at(self, t_s: float) -> float:
        """Wall time at which sim time reaches ``t_s``."""
        return self.wall_start + t_s / self.speedup


class TickQueue:
    """Thread-safe queue of the lockstep ticks a vehicle host consumes; time never goes backwards.

    Not the mission's clock (:class:`missions.launch.clock.LockstepClock` publishes the ticks): this
    queue only receives them. A tick whose ``time_s`` is earlier than the last accepted one, or whose ``step`` is not
    larger, is dropped with a warning (a duplicate or out-of-order message).
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._queue: list[Tick] = []
        self.last: Tick | None = None
        self.dropped = 0
        self._r, self._w = os.pipe()
        os.set_blocking(self._r, False)
        os.set_blocking(self._w, False)

    def push(self, tick: Tick) -> bool:
        """Queue ``tick``; return False (and warn) when it is out of order."""
        with self._lock:
            if self.last is not None and (tick.step <= self.last.step or tick.time_s < self.last.time_s):
                self.dropped += 1
                log.warning("lockstep: dropped out-of-order tick %s after %s", tick, self.last)
                return False
            self.last = tick
            self._queue.append(tick)
        try:
            os.write(self._w, b"t")
        except BlockingIOError:
            pass
        return True

    def push_payload(self, payload: bytes, mission_id: str) -> bool:
        """Decode and queue a tick message of mission ``mission_id`` (:func:`comms.messages.decode`);
        a bad payload, another mission's or another kind of message is dropped with a warning."""
        try:
            _, msg = decode(payload, mission_id)
        except MessageError as exc:
            msg, why = None, str(exc)
        else:
            why = f"a {type(msg).__name__} on the tick key"
        if not isinstance(msg, Tick):
            with self._lock:
                self.dropped += 1
            log.warning("lockstep: dropped bad tick: %s", why)
            return False
        return self.push(msg)

    def pop_all(self) -> list[Tick]:
        """Take every queued tick, oldest first."""
        try:
            while os.read(self._r, 4096):
                pass
        except BlockingIOError:
            pass
        with self._lock:
            out, self._queue = self._queue, []
        return out

    def fileno(self) -> int:
        """Readable when a tick is queued."""
        return self._r

    def close(self) -> None:
        """Close the wake-up pipe."""
        for fd in (self._r, self._w):
            try:
                os.close(fd)
            except OSError:
                pass


class ZenohTickSource:
    """Feed a :class:`TickQueue` from the Zenoh key :func:`comms.keys.tick` of ``mission_id``
    (binary :class:`comms.messages.Tick` messages of that mission; others are dropped).

    Args:
        mission_id: the mission id of the key expression and of the messages.
        clock: the tick queue to feed.
        settings: the Zenoh session (:class:`comms.session.SessionSettings`; default: an
            embedded peer listening on an OS-chosen loopback port).
    """

    def __init__(self, mission_id: str, clock: TickQueue, settings: SessionSettings | None = None) -> None:
        self.mission_id = mission_id
        self.key = keys.tick(mission_id)
        self.clock = clock
        self.session = open_session(settings or SessionSettings())
        self.subscriber = self.session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            payload = bytes(sample.payload.to_bytes())
        except Exception as exc:  # never let a bad sample kill the zenoh thread
            log.warning("lockstep: unreadable tick sample: %s", exc)
            return
        self.clock.push_payload(payload, self.mission_id)

    def close(self) -> None:
        """Undeclare the subscriber and close the session."""
        try:
            self.subscriber.undeclare()
        finally:
            self.session.close()
