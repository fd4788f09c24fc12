"""The planner node's Zenoh side: the session, its subscriptions and publishers, and what the
swarm has said so far (the clock's newest tick, the payload's measurements, which planners are
alive or left, the operator's commands). Callbacks only queue (:class:`~planner.node.inbox.Inbox`);
:meth:`Swarm.drain` handles the queue on the node's single thread."""

from __future__ import annotations

import json
import logging
import queue
from collections.abc import Callable
from typing import Any

from comms import keys
from comms.messages import Done, MessageKind, Record, Status, Tick, encode
from comms.pubsub import declare_publisher
from comms.session import SessionSettings
from planner.node.config import NodeConfig
from planner.node.inbox import Inbox

log = logging.getLogger("fimnav.plan")


class Swarm:
    """One planner's view of and voice in the swarm.

    Args:
        config: the node's configuration.
        session_factory: opens the Zenoh session (in-memory fakes in tests).
        wall: monotonic wall clock (s).
        on_peer_record: receives every peer record that passes the inbox's checks (lockstep:
            after the rejoin bookkeeping); it places the record in the delayed view.
    """

    def __init__(
        self,
        config: NodeConfig,
        session_factory: Callable[[SessionSettings], Any],
        wall: Callable[[], float],
        on_peer_record: Callable[[Record], None],
    ) -> None:
        self.config = config
        self.inbox = Inbox(config.mission_id, config.drone_count)
        self._session_factory = session_factory
        self._wall = wall
        self._on_peer_record = on_peer_record
        self.session: Any = None
        self._token: Any = None
        self._publishers: dict[str, Any] = {}
        self._subscribers: list[Any] = []
        self._sequence = 0
        #: Planners (1-based ids) whose liveliness token is up.
        self.alive: set[int] = set()
        #: Planners whose liveliness token went away (and did not come back).
        self.left: set[int] = set()
        #: The step this planner was at when each of them left (its records up to then are late
        #: ones, not a rejoin).
        self.left_at: dict[int, int] = {}
        #: The step this planner is at (lockstep), for :attr:`left_at`.
        self.step_now = -1
        #: Lockstep: when this drone's vehicle's liveliness token went (monotonic s), if it did.
        self.vehicle_gone_at: float | None = None
        #: The clock's newest tick (lockstep).
        self.tick: Tick | None = None
        #: Lockstep: the payload's measurements by step, not yet taken.
        self.measurements: dict[int, Record] = {}
        #: Real time: the payload's newest measurement.
        self.latest_measurement: Record | None = None
        #: Operator commands from ``fimnav/<id>/control/<uav>`` (Zenoh thread → main loop).
        self.control: queue.SimpleQueue[str] = queue.SimpleQueue()

    def open(self) -> None:
        """Open the session, subscribe (records, own measurements, the clock, liveliness,
        control), declare this planner's liveliness token and its publishers."""
        mid, uav = self.config.mission_id, self.config.uav
        self.session = self._session_factory(self.config.zenoh)
        s = self.session
        self._subscribers = [
            s.declare_subscriber(keys.record(mid), self.inbox.on_sample),
            s.declare_subscriber(keys.measurement(mid, uav), self.inbox.on_sample),
            s.declare_subscriber(keys.tick(mid), self.inbox.on_sample),
            s.liveliness().declare_subscriber(keys.alive(mid, "planner"), self.inbox.on_liveliness, history=True),
        ]
        if self.config.lockstep:
            # The simulated vehicle's bridge holds a token: its process dying is seen at once.
            self._subscribers.append(
                s.liveliness().declare_subscriber(keys.alive(mid, "vehicle", self.config.sysid), self.inbox.on_liveliness, history=True)
            )
        self._subscribers.append(s.declare_subscriber(keys.control(mid, uav), self._on_control))
        self._token = s.liveliness().declare_token(keys.alive(mid, "planner", uav))
        self._publishers = {
            "record": declare_publisher(s, keys.record(mid, uav)),
            "status": declare_publisher(s, keys.status(mid, uav)),
            "done": declare_publisher(s, keys.done(mid, uav)),
        }

    def close(self) -> None:
        """Withdraw the liveliness token and close the session and the inbox (idempotent)."""
        if self.session is not None:
            try:
                self._token.undeclare()
            except Exception:  # closing anyway
                pass
            self.session.close()
            self.session = None
        self.inbox.close()

    # -- publishing -------------------------------------------------------------------------
    def _publish(self, name: str, msg: Any, kind: MessageKind | None = None) -> None:
        self._sequence += 1
        self._publishers[name].put(encode(msg, self.config.mission_id, self._sequence, kind))

    def publish_record(self, record: Record) -> None:
        """This drone's record of a step (own position and measurement)."""
        self._publish("record", record, MessageKind.RECORD)

    def publish_status(self, status: Status) -> None:
        """This planner's status of a step (estimate, constraints)."""
        self._publish("status", status)

    def publish_done(self, step: int) -> None:
        """``Done(step)``: this planner has finished the step (its setpoint is on the wire)."""
        self._publish("done", Done(self.config.uav, step))

    # -- receiving --------------------------------------------------------------------------
    def _on_control(self, sample: Any) -> None:
        """An operator command (Zenoh callback thread): queued for the main loop, which checks it."""
        try:
            self.control.put(bytes(sample.payload.to_bytes()).decode("utf-8", "replace"))
        except Exception as exc:  # a bad sample must not kill the callback thread
            log.warning("uav %d: unreadable control message ignored (%s)", self.config.uav, exc)

    def handback_requested(self) -> bool:
        """Whether a valid ``{"command": "handback"}`` arrived since the last call; anything
        else is logged (naming what was wrong) and ignored."""
        uav = self.config.uav
        asked = False
        while True:
            try:
                text = self.control.get_nowait()
            except queue.Empty:
                return asked
            try:
                msg = json.loads(text)
            except ValueError:
                log.warning("uav %d: control message is not JSON, ignored: %.80r", uav, text)
                continue
            if isinstance(msg, dict) and msg.get("command") == "handback":
                asked = True
            else:
                log.warning('uav %d: control message without a known command (expected {"command": "handback"}), ignored: %.80r', uav, text)

    def drain(self, timeout_s: float = 0.0) -> None:
        """Handle queued Zenoh messages (waiting up to ``timeout_s`` for the first)."""
        try:
            item = self.inbox.queue.get(timeout=timeout_s) if timeout_s > 0 else self.inbox.queue.get_nowait()
        except queue.Empty:
            return
        while True:
            kind, key, data = item
            if kind == "data":
                self._on_data(key, data)
            elif "/alive/vehicle/" in key:
                self._on_vehicle_liveliness(kind)
            else:
                self._on_planner_liveliness(kind, key)
            try:
                item = self.inbox.queue.get_nowait()
            except queue.Empty:
                return

    def _on_data(self, key: str, data: bytes) -> None:
        msg = self.inbox.decode(key, data)
        if isinstance(msg, Record):
            if "/measurement/" in key:
                if self.config.lockstep:
                    self.measurements[msg.step] = msg
                elif self.latest_measurement is None or msg.time_s >= self.latest_measurement.time_s:
                    self.latest_measurement = msg
                return
            if self.config.lockstep and msg.sender in self.left and msg.step > self.left_at.get(msg.sender, -1):
                # A planner that left is waited for again once its records flow
                # (a restarted planner skips the step it joins at).
                self.left.discard(msg.sender)
                log.warning("planner %d rejoined the swarm at step %d", msg.sender, msg.step)
            self._on_peer_record(msg)
        elif isinstance(msg, Tick) and (self.tick is None or msg.step >= self.tick.step):
            self.tick = msg

    def _on_vehicle_liveliness(self, kind: str) -> None:
        if kind == "gone" and self.vehicle_gone_at is None:
            self.vehicle_gone_at = self._wall()
            log.error("uav %d: the vehicle's process left the swarm (liveliness token gone)", self.config.uav)
        elif kind == "alive":
            self.vehicle_gone_at = None

    def _on_planner_liveliness(self, kind: str, key: str) -> None:
        uav = keys.uav_of(key)
        if uav is None or not 1 <= uav <= self.config.drone_count:
            return
        (self.alive.add if kind == "alive" else self.alive.discard)(uav)
        if kind == "gone" and uav != self.config.uav:
            self.left.add(uav)
            self.left_at[uav] = self.step_now
        elif kind == "alive" and uav in self.left and not self.config.lockstep:
            # (in lockstep a planner that left counts again from its first record)
            self.left.discard(uav)
            log.warning("planner %d is back in the swarm", uav)
            log.warning("planner %d left the swarm", uav)
