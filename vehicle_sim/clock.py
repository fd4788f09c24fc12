"""Clocks of the simulated vehicles: real time with a speed-up, or lockstep ticks.

* :class:`RealTimeClock`: sim time = speed-up × wall time elapsed since start.
* :class:`TickQueue`: sim time advances only when a tick arrives, in process
  (:meth:`TickQueue.push`), from :class:`vehicle_sim.bridge.ZenohBridge` (a mission's clock,
  :mod:`missions.launch.clock`) or from Zenoh as JSON (:class:`ZenohTickSource`, key
  ``fimnav/<mission_id>/clock/tick``, payload ``{"step": k, "t_s": t}``). The queue is thread
  safe and exposes a file descriptor that becomes readable when a tick is queued, so a select()
  loop wakes up at once.

A tick is :class:`comms.messages.Tick` (``step``, ``time_s``), the type the mission clock
publishes; only its encoding differs between the two Zenoh sources: the standalone vehicle's
JSON (:func:`parse_tick`, :func:`encode_tick`) and the mission's binary message
(:func:`comms.messages.decode`, with a header naming the mission).
"""

from __future__ import annotations

import json
import logging
import math
import os
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from comms.messages import Tick

log = logging.getLogger(__name__)


def tick_key(mission_id: str) -> str:
    """Zenoh key expression of the mission clock ticks."""
    return f"fimnav/{mission_id}/clock/tick"


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


def parse_tick(payload: bytes | str) -> Tick:
    """Decode a JSON tick payload ``{"step": int >= 0, "t_s": finite float >= 0}`` (UTF-8) into
    ``Tick(step, time_s=t_s)``.

    Raises:
        ValueError: with a message naming what was expected and what was found.
    """
    try:
        obj: Any = json.loads(payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise ValueError(f"tick: expected a JSON object, found undecodable payload ({exc})") from None
    if not isinstance(obj, dict):
        raise ValueError(f"tick: expected a JSON object, found {type(obj).__name__}")
    unknown = set(obj) - {"step", "t_s"}
    if unknown:
        raise ValueError(f"tick: unknown keys {sorted(unknown)}; expected 'step' and 't_s'")
    step, t_s = obj.get("step"), obj.get("t_s")
    if not isinstance(step, int) or isinstance(step, bool) or step < 0:
        raise ValueError(f"tick.step: expected an integer >= 0, found {step!r}")
    if isinstance(t_s, bool) or not isinstance(t_s, (int, float)) or not math.isfinite(t_s) or t_s < 0:
        raise ValueError(f"tick.t_s: expected a finite number >= 0, found {t_s!r}")
    return Tick(step, float(t_s))


def encode_tick(tick: Tick) -> bytes:
    """The JSON payload of ``tick`` (inverse of :func:`parse_tick`)."""
    return json.dumps({"step": tick.step, "t_s": tick.time_s}).encode()


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

    def push_payload(self, payload: bytes | str) -> bool:
        """Decode and queue a tick payload; a bad payload is dropped with a warning."""
        try:
            tick = parse_tick(payload)
        except ValueError as exc:
            with self._lock:
                self.dropped += 1
            log.warning("lockstep: dropped bad tick: %s", exc)
            return False
        return self.push(tick)

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


def zenoh_config(listen: Sequence[str] = ("tcp/127.0.0.1:0",), connect: Sequence[str] = ()) -> Any:
    """An embedded-peer zenoh 1.x config: mode peer, given listen/connect endpoints,
    multicast scouting off."""
    import zenoh

    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("peer"))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


class ZenohTickSource:
    """Feed a :class:`TickQueue` from the Zenoh key ``fimnav/<mission_id>/clock/tick``.

    Args:
        mission_id: the mission id of the key expression.
        clock: the tick queue to feed.
        listen, connect: zenoh endpoints (e.g. ``tcp/127.0.0.1:7447``).
    """

    def __init__(
        self,
        mission_id: str,
        clock: TickQueue,
        *,
        listen: Sequence[str] = ("tcp/127.0.0.1:0",),
        connect: Sequence[str] = (),
    ) -> None:
        import zenoh

        self.key = tick_key(mission_id)
        self.clock = clock
        self.session = zenoh.open(zenoh_config(listen, connect))
        self.subscriber = self.session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample: Any) -> None:
        try:
            payload = sample.payload.to_bytes()
        except Exception as exc:  # never let a bad sample kill the zenoh thread
            log.warning("lockstep: unreadable tick sample: %s", exc)
            return
        self.clock.push_payload(payload)

    def close(self) -> None:
        """Undeclare the subscriber and close the session."""
        try:
            self.subscriber.undeclare()
        finally:
            self.session.close()
