"""Helpers of the partition test: the test's Zenoh client on each half of the swarm (the drones'
payloads + an observer of records and liveliness), the planners' step logs read back, and the
geometry of the flown positions. (``fimnav router`` processes: :func:`tests.support.zenoh.start_router`.)
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import yaml


@dataclass
class HalfWatch:
    """The test's Zenoh client on one half's router.

    * Payloads of the half's drones: each drone's measurement (``measurement/<uav>``, UNIX
      time stamp) is the true range from its latest record's position (its start before
      that) to the source, every ``period_s``.
    * Observer: every record heard (arrival, monotonic s; sender; record time, UNIX s) and
      every planner liveliness change (monotonic s, ``PUT``/``DELETE``, drone id).
    """

    mission_id: str
    count: int
    router: str
    uavs: Sequence[int]
    starts_m: np.ndarray  # (count, 3), m ENU
    source_m: np.ndarray  # (3,), m ENU
    period_s: float = 0.05
    records: list[tuple[float, int, float]] = field(default_factory=list)
    liveliness: list[tuple[float, str, int]] = field(default_factory=list)

    def __post_init__(self) -> None:
        from comms import keys
        from comms.pubsub import declare_publisher
        from comms.session import SessionSettings, open_session

        self._lock = threading.Lock()
        self._positions = {u: np.asarray(self.starts_m[u - 1], dtype=float) for u in self.uavs}
        self.session = open_session(SessionSettings(mode="client", listen=(), connect=(self.router,)))
        self._pubs = {u: declare_publisher(self.session, keys.measurement(self.mission_id, u)) for u in self.uavs}
        self._subs = [
            self.session.declare_subscriber(keys.record(self.mission_id), self._on_record),
            self.session.liveliness().declare_subscriber(keys.alive(self.mission_id, "planner"), self._on_alive, history=True),
        ]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _on_record(self, sample: Any) -> None:
        from comms.messages import decode

        _, msg = decode(bytes(sample.payload.to_bytes()), self.mission_id, self.count)
        with self._lock:
            self.records.append((time.monotonic(), int(msg.sender), float(msg.time_s)))
            if msg.sender in self._positions and not msg.stale:
                self._positions[msg.sender] = np.asarray(msg.position_m, dtype=float)

    def _on_alive(self, sample: Any) -> None:
        from comms import keys

        uav = keys.uav_of(str(sample.key_expr))
        kind = "PUT" if str(sample.kind).endswith("PUT") else "DELETE"
        with self._lock:
            self.liveliness.append((time.monotonic(), kind, int(uav) if uav is not None else -1))

    def _run(self) -> None:
        from comms.messages import MessageKind, Record, encode

        seq = 0
        nan = float("nan")
        while not self._stop.wait(self.period_s):
            with self._lock:
                positions = dict(self._positions)
            for uav, pos in positions.items():
                seq += 1
                rng = float(np.linalg.norm(pos - self.source_m))
                obs = Record(uav, seq, time.time(), tuple(float(v) for v in pos), True, False, True, rng, nan, nan)  # type: ignore[arg-type]
                self._pubs[uav].put(encode(obs, self.mission_id, seq, MessageKind.MEASUREMENT))

    def alive(self) -> set[int]:
        """Drone ids whose planner's liveliness token this half sees now."""
        with self._lock:
            events = list(self.liveliness)
        state: dict[int, bool] = {}
        for _, kind, uav in events:
            state[uav] = kind == "PUT"
        return {u for u, up in state.items() if up}

    def first_event(self, after: float, kind: str, uavs: Sequence[int]) -> float | None:
        """Monotonic time at which the last of ``uavs`` had a liveliness ``kind`` event after
        ``after`` (None if one has none yet)."""
        with self._lock:
            events = list(self.liveliness)
        times = []
        for u in uavs:
            t = [at for at, k, v in events if v == u and k == kind and at >= after]
            if not t:
                return None
            times.append(min(t))
        return max(times)

    def first_record(self, after: float, senders: Sequence[int]) -> float | None:
        """Monotonic arrival time of the first record of one of ``senders`` after ``after``."""
        with self._lock:
            t = [at for at, s, _ in self.records if s in senders and at >= after]
        return min(t) if t else None

    def records_between(self, t0: float, t1: float, senders: Sequence[int]) -> int:
        """Records of ``senders`` that arrived in [t0, t1] (monotonic s)."""
        with self._lock:
            return sum(1 for at, s, _ in self.records if s in senders and t0 <= at <= t1)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.session.close()


def read_steps(path: Path) -> list[dict[str, Any]]:
    """The complete lines of a planner's JSON-lines step log (a line being written is
    skipped)."""
    if not path.exists():
        return []
    out = []
    for line in path.read_text().splitlines():
        try:
            out.append(json.loads(line))
        except json.JSONDecodeError:
            continue
    return out


def ages(entry: dict[str, Any], peers: Sequence[int]) -> list[int]:
    """Ages (steps) of the saved records of ``peers`` (1-based ids) in one step-log entry
    (``step − saved step``; a peer never heard of has age step + 1)."""
    return [int(entry["step"]) - int(entry["saved_steps"][j - 1]) for j in peers]


def write_partition_mission(path: Path, mission_id: str, starts_m: list[list[float]], steps: int, source_m: Sequence[float], d_uav_m: float) -> Path:
    """A ranging mission of ``len(starts_m)`` drones, dt 1 s, end of mission ``hold``."""
    mission = {
        "id": mission_id, "dt_s": 1.0, "steps": steps, "end_action": "hold",
        "drones": {"count": len(starts_m), "roles": "ranging", "start": {"positions_m": starts_m}},
        "source": {"position_m": [float(v) for v in source_m]},
        "constraints": {"d_uav_m": d_uav_m},
    }
    path.write_text(yaml.safe_dump(mission))
    return path


def min_pair_distance(positions: np.ndarray) -> float:
    """Smallest distance (m) between two rows of ``positions`` (n, 3); inf for n < 2."""
    n = len(positions)
    if n < 2:
        return math.inf
    d = np.linalg.norm(positions[:, None, :] - positions[None, :, :], axis=-1)
    return float(d[np.triu_indices(n, 1)].min())


def min_pair_distance_between(start_m: np.ndarray, end_m: np.ndarray) -> float:
    """Smallest distance (m) between two drones while each moves on the straight segment
    from its row of ``start_m`` (n, 3) to its row of ``end_m`` (n, 3) over the same interval:
    the minimum over t in [0, 1] of |a + t (b − a)|, a and b the pair's offsets at the ends
    (closed form, t* = −a·(b − a) / |b − a|² clipped to [0, 1])."""
    n = len(start_m)
    if n < 2:
        return math.inf
    i, j = np.triu_indices(n, 1)
    a = start_m[i] - start_m[j]
    d = (end_m[i] - end_m[j]) - a
    dd = (d * d).sum(-1)
    t = np.clip(np.divide(-(a * d).sum(-1), dd, out=np.zeros_like(dd), where=dd > 0), 0.0, 1.0)
    return float(np.linalg.norm(a + t[:, None] * d, axis=-1).min())
