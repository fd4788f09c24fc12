"""The simulated vehicles' side of a distributed run: fimnav's Zenoh clock and payload topics.

* Ticks: the lockstep clock publishes :class:`comms.messages.Tick` (``step`` −1 during the
  pre-flight, then 0..K−1) on ``fimnav/<id>/clock/tick``. The bridge feeds them to the
  vehicles' :class:`vehicle_sim.clock.TickQueue` (which wants a strictly increasing tick
  index: the bridge numbers them itself and remembers each one's mission step).
* Payload: after the vehicles advanced to a mission tick k, each payload measures at its
  vehicle's *true* position and the bridge publishes the record
  (:class:`comms.messages.Record`, kind MEASUREMENT) on ``fimnav/<id>/measurement/<sysid>``.
  The source moves with mission time k·Δt (the in-process simulator's clock), not with the
  vehicle's boot time, which includes the pre-flight. A real RSS payload on a companion
  computer publishes the same record on the same key (docs/distributed.md).
* Presence: one liveliness token ``fimnav/<id>/alive/vehicle/<sysid>`` per hosted vehicle.
* Real time (no clock ticks, ``fimnav launch --realtime``): :meth:`ZenohBridge.start_realtime`
  measures every Δt of mission time (Δt/speed-up wall seconds, a tenth of a period before each
  multiple of that period on the UNIX clock, the grid the real-time planners step on) and publishes the record stamped
  with the UNIX time of the measurement, as a payload on a companion computer would.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from comms import keys
from comms.messages import MessageError, MessageKind, Record, Tick, decode, encode
from comms.pubsub import declare_publisher
from comms.session import SessionSettings, open_session
from vehicle_sim.clock import TickQueue

log = logging.getLogger(__name__)


class ZenohBridge:
    """Connects hosted vehicles to a mission's Zenoh clock and payload topics.

    Args:
        mission_id: the mission id. count: the mission's N (for validating senders).
        dt_s: the mission step length (s).
        clock: the vehicles' tick queue to feed; None in real time (no tick subscription).
        vehicles: the hosted vehicles (``sysid`` and ``payload`` attributes).
        settings: the Zenoh session settings.
    """

    def __init__(self, mission_id: str, count: int, dt_s: float, clock: TickQueue | None, vehicles: Sequence[Any], settings: SessionSettings) -> None:
        self.mission_id = mission_id
        self.count = count
        self.dt = dt_s
        self.clock = clock
        self._lock = threading.Lock()
        self._mission_step: dict[int, int] = {}
        self._next_index = 0
        self.dropped = 0
        self.seq = 0
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.session = open_session(settings)
        self._sub = self.session.declare_subscriber(keys.tick(mission_id), self._on_tick_sample) if clock is not None else None
        self._pubs = {v.sysid: declare_publisher(self.session, keys.measurement(mission_id, v.sysid)) for v in vehicles}
        self._tokens = [self.session.liveliness().declare_token(keys.alive(mission_id, "vehicle", v.sysid)) for v in vehicles]

    def start_realtime(self, vehicles: Sequence[Any], speedup: float, unix: Callable[[], float] = time.time) -> None:
        """Publish every vehicle's payload measurement every Δt/speed-up wall seconds, a tenth
        of a period before each multiple of that period on the UNIX clock; measurement n uses the payload's noise draws of
        step n and mission time n·Δt (a moving source moves on the measurement count)."""
        period = self.dt / speedup
        # Measured a tenth of a period before each multiple of the period: a planner stepping
        # on that grid finds a measurement a tenth of a step old, not one step old.
        lead = 0.1 * period

        def run() -> None:
            n = 0
            t_next = math.ceil((unix() + lead) / period) * period - lead
            while not self._stop.wait(max(0.0, t_next - unix())):
                for v in vehicles:
                    if v.payload is not None:
                        self._publish(v, n, t_next, [float(x) for x in v.position])
                n += 1
                t_next += period
                if unix() - t_next > period:  # starved: skip ahead, never publish a burst
                    t_next = math.ceil((unix() + lead) / period) * period - lead

        self._thread = threading.Thread(target=run, name="payload", daemon=True)
        self._thread.start()

    def _publish(self, vehicle: Any, step: int, time_s: float, position_m: Sequence[float]) -> None:
        """Measure with ``vehicle``'s payload at ``position_m`` (ENU m, true) and publish the
        record for ``step``, stamped ``time_s`` (UNIX s in real time, mission s in lockstep)."""
        m = vehicle.payload.measure(position_m, step, step * self.dt)
        nan = math.nan
        obs = Record(
            sender=vehicle.sysid,
            step=step,
            time_s=time_s,
            position_m=m.position_enu_m,
            ranging=bool(vehicle.payload.ranging[0]),
            bearing=bool(vehicle.payload.bearing[0]),
            los=m.los,
            range_m=nan if m.range_m is None else m.range_m,
            azimuth_rad=nan if m.azimuth_rad is None else m.azimuth_rad,
            elevation_rad=nan if m.elevation_rad is None else m.elevation_rad,
            extra_values=m.extra_values,
        )
        self.seq += 1
        self._pubs[vehicle.sysid].put(encode(obs, self.mission_id, self.seq, MessageKind.MEASUREMENT))

    def _on_tick_sample(self, sample: Any) -> None:
        try:
            _, msg = decode(bytes(sample.payload.to_bytes()), self.mission_id)
        except MessageError as exc:
            self.dropped += 1
            log.warning("dropped tick: %s", exc)
            return
        if not isinstance(msg, Tick):
            self.dropped += 1
            log.warning("dropped a %s on the tick key", type(msg).__name__)
            return
        clock = self.clock
        if clock is None:
            raise RuntimeError("a tick arrived without a lockstep clock (real time subscribes to no tick)")
        with self._lock:
            last = clock.last
            if last is not None and msg.time_s <= last.time_s:
                return  # a repeated tick (the clock re-sends for late joiners)
            index = self._next_index
            self._next_index += 1
            self._mission_step[index] = msg.step
        clock.push(Tick(index, msg.time_s))

    def on_tick(self, vehicle: Any, tick: Tick) -> None:
        """Host hook after ``vehicle`` advanced to ``tick``: publish its payload measurement."""
        with self._lock:
            step = self._mission_step.get(tick.step, -1)
            for old in [i for i in self._mission_step if i < tick.step - 64]:
                del self._mission_step[old]
        if step < 0 or vehicle.payload is None:
            return
        self._publish(vehicle, step, step * self.dt, vehicle.position)

    def close(self) -> None:
        """Stop the real-time payload, undeclare everything and close the session."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(5.0)
        for t in self._tokens:
            try:
                t.undeclare()
            except Exception:  # closing anyway
                pass
        self.session.close()
