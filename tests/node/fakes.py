"""In-memory fakes at the planner node's seams (its injected link, session and clock factories):
a Zenoh session that delivers what the test (or a scripted swarm) puts, a MAVLink link that
reports positions and records setpoints, and a simulated clock whose blocking wait advances
time and fires scheduled events."""

from __future__ import annotations

import heapq
import itertools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from comms.mavlink_client import Telemetry
from comms.messages import Message, MessageKind, decode, encode
from planner.node import NodeClock


def key_matches(pattern: str, key: str) -> bool:
    """Zenoh key-expression matching for ``*`` (one chunk) and ``**`` (any chunks)."""
    p, k = pattern.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(match(i + 1, jj) for jj in range(j, len(k) + 1))
        return j < len(k) and (p[i] == "*" or p[i] == k[j]) and match(i + 1, j + 1)

    return match(0, 0)


@dataclass
class _Payload:
    data: bytes

    def to_bytes(self) -> bytes:
        return self.data


@dataclass
class FakeSample:
    """What a Zenoh callback receives: key, payload and (liveliness) kind."""

    key_expr: str
    payload: _Payload
    kind: str = "SampleKind.PUT"


class _Handle:
    def __init__(self, on_undeclare: Callable[[], None] = lambda: None) -> None:
        self._on_undeclare = on_undeclare

    def undeclare(self) -> None:
        self._on_undeclare()


class FakePublisher:
    def __init__(self, session: FakeSession, key: str) -> None:
        self.session = session
        self.key = key

    def put(self, data: bytes) -> None:
        self.session.put(self.key, data)


class FakeLiveliness:
    """``session.liveliness()``: token subscribers, with the tokens already up as history."""

    def __init__(self, session: FakeSession) -> None:
        self.session = session

    def declare_subscriber(self, key: str, callback: Callable[[Any], None], history: bool = False) -> _Handle:
        self.session.liveliness_subscribers.append((key, callback))
        if history:
            for token in sorted(self.session.tokens):
                if key_matches(key, token):
                    callback(FakeSample(token, _Payload(b""), "SampleKind.PUT"))
        return _Handle()

    def declare_token(self, key: str) -> _Handle:
        self.session.tokens.add(key)
        return _Handle(lambda: self.session.tokens.discard(key))


class FakeSession:
    """An in-memory Zenoh session shared by the node and the test.

    Args:
        mission_id: the mission (to decode what the node publishes).
        tokens: liveliness tokens up before the node subscribes (delivered as history).
        on_publish: called with (key, decoded message) for everything the node publishes.
    """

    def __init__(self, mission_id: str, tokens: tuple[str, ...] = (), on_publish: Callable[[str, Message], None] | None = None) -> None:
        self.mission_id = mission_id
        self.tokens = set(tokens)
        self.on_publish = on_publish
        self.subscribers: list[tuple[str, Callable[[Any], None]]] = []
        self.liveliness_subscribers: list[tuple[str, Callable[[Any], None]]] = []
        #: Everything the node published: (key, message).
        self.published: list[tuple[str, Message]] = []
        self.closed = False
        self._seq = itertools.count(1)

    # -- the zenoh API the node uses ----------------------------------------------------------
    def declare_subscriber(self, key: str, callback: Callable[[Any], None]) -> _Handle:
        self.subscribers.append((key, callback))
        return _Handle()

    def declare_publisher(self, key: str, **_: Any) -> FakePublisher:
        return FakePublisher(self, key)

    def liveliness(self) -> FakeLiveliness:
        return FakeLiveliness(self)

    def close(self) -> None:
        self.closed = True

    # -- the node's puts and the test's side ------------------------------------------------------
    def put(self, key: str, data: bytes) -> None:
        """A put by the node: recorded (decoded), reported, delivered to matching subscribers."""
        _, msg = decode(data, self.mission_id)
        self.published.append((key, msg))
        if self.on_publish is not None:
            self.on_publish(key, msg)
        self._deliver(key, data)

    def send(self, key: str, msg: Message, kind: MessageKind | None = None) -> None:
        """The test (a peer, the clock, the payload) publishes ``msg`` on ``key``."""
        self._deliver(key, encode(msg, self.mission_id, next(self._seq), kind))

    def _deliver(self, key: str, data: bytes) -> None:
        for pattern, callback in list(self.subscribers):
            if key_matches(pattern, key):
                callback(FakeSample(key, _Payload(data)))

    def leave(self, key: str) -> None:
        """A liveliness token on ``key`` goes away."""
        self.tokens.discard(key)
        for pattern, callback in self.liveliness_subscribers:
            if key_matches(pattern, key):
                callback(FakeSample(key, _Payload(b""), "SampleKind.DELETE"))

    def of_kind(self, kind: type) -> list[Any]:
        """The messages of one type the node published, in order."""
        return [m for _, m in self.published if isinstance(m, kind)]


@dataclass
class FakeClockWatch:
    rate_value: float

    def rate(self) -> float:
        return self.rate_value

    def span_s(self) -> float:
        return 2.0


@dataclass
class FakeLink:
    """A vehicle link that reports the position the test sets and records every setpoint.

    Attributes:
        position_m: where the vehicle is (m, ENU). flavour: ``"ardupilot"`` or ``"px4"``.
        setpoints: every ``send_setpoint`` (position, velocity), in order.
        streams: every ``set_stream`` function (None: stream stopped), in order.
        follow_stream: each pump moves the vehicle onto the stream's position (real time).
    """

    position_m: np.ndarray
    wall: Callable[[], float]
    flavour: str = "ardupilot"
    mode: str = "GUIDED"
    armed: bool = True
    speedup: float = 1.0
    origin: tuple[float, float, float] = (0.0, 0.0, 0.0)
    follow_stream: bool = False
    telemetry: Telemetry = field(default_factory=Telemetry)
    setpoints: list[tuple[np.ndarray | None, np.ndarray | None]] = field(default_factory=list)
    streams: list[Callable[[float], tuple[np.ndarray | None, np.ndarray | None]] | None] = field(default_factory=list)
    modes_set: list[str] = field(default_factory=list)
    stream_period_s: float = 0.2
    forced_flavour: str | None = None
    lost: bool = False
    closed: bool = False
    left_guided: bool = False

    def __post_init__(self) -> None:
        self.clock = FakeClockWatch(self.speedup)
        self.telemetry.armed = self.armed
        self.telemetry.custom_mode = 4
        self.telemetry.heartbeats = 1
        self.telemetry.origin_global = self.origin
        self.telemetry.home_known = True
        self.report(self.position_m, -1)

    def report(self, position_m: np.ndarray, time_ms: int) -> None:
        """The vehicle reports ``position_m`` (m, ENU) stamped ``time_ms`` (its clock)."""
        self.position_m = np.array(position_m, dtype=float)
        self.telemetry.position_enu_m = self.position_m.copy()
        self.telemetry.position_time_ms = time_ms
        self.telemetry.position_wall_s = self.wall()

    @property
    def setpoints_sent(self) -> int:
        return len(self.setpoints)

    # -- the VehicleLink API the node uses ------------------------------------------------------
    def wait_heartbeat(self, timeout_s: float = 10.0) -> None:
        pass

    def check_signing(self) -> None:
        pass

    def request_interval(self, message_id: int, rate_hz: float) -> None:
        pass

    def request_streams(self, rates_hz: dict[int, float], optional: Any = ()) -> list[str]:
        return []

    def request_message(self, message_id: int) -> bool:
        return True

    def not_ready(self, require_gps: bool = True) -> list[str]:
        return []

    def set_mode(self, name: str, timeout_s: float = 30.0, ack_timeout_s: float = 15.0) -> None:
        self.mode = name
        self.modes_set.append(name)

    def heartbeat_in(self, mode: str) -> None:
        """A heartbeat in ``mode`` arrives (a pilot's mode change): as :class:`VehicleLink`
        does, leaving the guided mode ends the setpoint stream at once."""
        guided = self.profile.require_mode(self.profile.guided_mode).qualified_name
        if self.mode == guided and mode != guided:
            self.left_guided = True
            if self.streaming:
                self.streams.append(None)
        self.mode = mode

    @property
    def streaming(self) -> bool:
        return bool(self.streams) and self.streams[-1] is not None

    @property
    def profile(self) -> Any:
        from comms.autopilot import flavour_info

        return flavour_info(self.flavour)

    def mode_name(self) -> str:
        return self.mode

    def in_mode(self, name: str) -> bool:
        return self.mode == name

    def arm(self) -> None:
        self.armed = self.telemetry.armed = True

    def takeoff(self, altitude_m: float) -> None:
        pass

    def home_z_m(self) -> float:
        return 0.0

    def send_setpoint(self, position_enu_m: Any, velocity_enu_mps: Any) -> None:
        self.setpoints.append(
            (None if position_enu_m is None else np.array(position_enu_m, dtype=float), None if velocity_enu_mps is None else np.array(velocity_enu_mps, dtype=float))
        )

    def set_stream(self, fn: Any, period_s: float | None = None) -> None:
        self.streams.append(fn)

    def pump(self, timeout_s: float = 0.0) -> int:
        if self.follow_stream:
            fn = self.streams[-1] if self.streams else None
            if fn is not None:
                pos, _ = fn(self.wall())
                if pos is not None:
                    self.position_m = np.array(pos, dtype=float)
            self.report(self.position_m, self.telemetry.position_time_ms)
        return 0

    def fileno(self) -> int | None:
        return None

    def link_age_s(self) -> float:
        return 0.0

    def close(self) -> None:
        self.closed = True


class FakeClock:
    """A simulated clock: the node's blocking wait advances it (to the timeout or to the next
    scheduled event, whichever is first) and fires the events that are due.

    Args:
        unix_s: the UNIX time at the start (s). The monotonic clock starts at 0.
    """

    def __init__(self, unix_s: float) -> None:
        self.unix_s = unix_s
        self._offset = unix_s
        self._events: list[tuple[float, int, Callable[[], None]]] = []
        self._order = itertools.count()

    def unix(self) -> float:
        return self.unix_s

    def wall(self) -> float:
        return self.unix_s - self._offset

    def at(self, unix_s: float, action: Callable[[], None]) -> None:
        """Run ``action`` once the clock reaches ``unix_s``."""
        heapq.heappush(self._events, (unix_s, next(self._order), action))

    def wait_readable(self, fds: list[int], timeout_s: float) -> None:
        until = self.unix_s + max(timeout_s, 0.0)
        if self._events and self._events[0][0] < until:
            until = max(self._events[0][0], self.unix_s)
        self.unix_s = until
        while self._events and self._events[0][0] <= self.unix_s:
            _, _, action = heapq.heappop(self._events)
            action()

    def node_clock(self) -> NodeClock:
        return NodeClock(wall=self.wall, unix=self.unix, wait_readable=self.wait_readable)
