"""The loop that drives one or many simulated vehicles in one process.

One thread serves every vehicle of the process: it waits with ``select()`` on every MAVLink
socket (and on the lockstep clock's wake-up pipe) until input arrives or the next deadline, so
an idle vehicle costs a handful of wake-ups per second while the physics still runs on its
fixed grid (:meth:`SimVehicle.advance_to` integrates every missed physics step).

* Real time: at each wake-up every vehicle is advanced to the clock's sim time.
* Lockstep: input is answered between ticks (at the current sim time); each tick advances
  every vehicle to the tick's ``time_s`` and reports its position (GLOBAL_POSITION_INT and
  LOCAL_POSITION_NED stamped with the tick time).
* HEARTBEAT: 1 Hz of *wall* time in both modes (link liveness for ground stations), sent
  only by a loop that is running and only for healthy vehicles; in lockstep also with the first
  tick report after a mode or arming change (a planner sees a take-over before it commands).
"""

from __future__ import annotations

import logging
import math
import select
import threading
import time
from collections.abc import Callable, Sequence

from comms.messages import Tick
from vehicle_sim.clock import RealTimeClock, TickQueue
from vehicle_sim.config import VehicleConfig
from vehicle_sim.link import MavlinkLink, open_transport, read_signing_key
from vehicle_sim.payload import Payload
from vehicle_sim.vehicle import SimVehicle

log = logging.getLogger(__name__)

MAX_SLEEP_S = 0.1
HEARTBEAT_PERIOD_S = 1.0


def build_vehicle(
    config: VehicleConfig,
    connection: str,
    wall: Callable[[], float] = time.time,
    payload: Payload | None = None,
) -> SimVehicle:
    """Open the MAVLink connection ``connection`` and build the vehicle ``config`` behind it.

    Raises:
        UsageError: bad connection string, port in use, unreadable signing key or tlog.
        ValueError: a boot parameter (``config.params``) the vehicle refuses.
    """
    key = read_signing_key(config.signing_key_path) if config.signing_key_path else None
    transport = open_transport(connection)
    try:
        link = MavlinkLink(transport, config.sysid, 1, tlog_path=config.tlog_path, signing_key=key)
    except Exception:
        transport.close()
        raise
    try:
        return SimVehicle(config, link, wall=wall, payload=payload)
    except Exception:
        link.close()
        raise


class VehicleHost:
    """Run ``vehicles`` on ``clock`` until :meth:`stop`.

    Args:
        vehicles: the vehicles (distinct links).
        clock: :class:`RealTimeClock` or :class:`TickQueue`.
        wall: monotonic wall clock (s).
        on_tick: called as ``on_tick(vehicle, tick)`` after each lockstep advance (e.g. to
            take and publish the payload measurement of ``tick.step``); its exceptions are
            logged, never raised.
    """

    def __init__(
        self,
        vehicles: Sequence[SimVehicle],
        clock: RealTimeClock | TickQueue,
        wall: Callable[[], float] = time.monotonic,
        on_tick: Callable[[SimVehicle, Tick], None] | None = None,
    ) -> None:
        self.on_tick = on_tick
        self.vehicles = list(vehicles)
        self.clock = clock
        self.wall = wall
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.iterations = 0

    def stop(self) -> None:
        """Ask the loop to end (thread safe); it returns within ~0.1 s."""
        self._stop.set()

    def _advance(self, vehicle: SimVehicle, t_s: float, report: bool) -> None:
        if not vehicle.healthy:
            vehicle.poll()
            return
        try:
            vehicle.advance_to(t_s, report_position=report)
        except Exception:  # one broken vehicle must not stop the others
            vehicle.healthy = False
            log.exception("sysid %d: vehicle failed; heartbeats stop", vehicle.sysid)

    def run(self) -> None:
        """The loop (blocks until :meth:`stop`)."""
        next_hb = self.wall()
        while not self._stop.is_set():
            self.iterations += 1
            now = self.wall()
            if now >= next_hb:
                for v in self.vehicles:
                    v.heartbeat()
                    v.link.flush()
                next_hb = next_hb + HEARTBEAT_PERIOD_S if now - next_hb < HEARTBEAT_PERIOD_S else now + HEARTBEAT_PERIOD_S
            if isinstance(self.clock, TickQueue):
                for tick in self.clock.pop_all():
                    for v in self.vehicles:
                        self._advance(v, tick.time_s, True)
                        if self.on_tick is not None:
                            try:
                                self.on_tick(v, tick)
                            except Exception:  # a hook must not stop the loop
                                log.exception("sysid %d: on_tick hook failed", v.sysid)
                for v in self.vehicles:
                    if v.poll():
                        v.emit_due()
                wake = min(next_hb, now + MAX_SLEEP_S)
            else:
                t = self.clock.now_s()
                for v in self.vehicles:
                    self._advance(v, t, False)
                next_sim = min((v.next_due_s() for v in self.vehicles), default=math.inf)
                wake = min(self.clock.wall_at(next_sim), next_hb, now + MAX_SLEEP_S)
            fds: list[int] = [fd for v in self.vehicles for fd in v.link.filenos()]
            if isinstance(self.clock, TickQueue):
                fds.append(self.clock.fileno())
            timeout = max(0.0, wake - self.wall())
            try:
                select.select(fds, [], [], timeout)
            except (OSError, ValueError):
                self._stop.wait(min(timeout, 0.01))
        for v in self.vehicles:
            v.link.flush()

    def start(self) -> threading.Thread:
        """Run the loop in a daemon thread (tests, embedding); returns the thread."""
        self._thread = threading.Thread(target=self.run, name="vehicle-host", daemon=True)
        self._thread.start()
        return self._thread

    def join(self, timeout_s: float = 5.0) -> None:
        """Stop and wait for the loop thread started by :meth:`start`."""
        self.stop()
        if self._thread is not None:
            self._thread.join(timeout_s)

    def close(self) -> None:
        """Stop and close every link."""
        self.join()
        for v in self.vehicles:
            v.link.close()
