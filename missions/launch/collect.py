"""What the launcher hears of a run over Zenoh: the drones' records and statuses by step (for
the progress bar, the live view and the results), and, in real time, which drones reported
being at their starts."""

from __future__ import annotations

import threading
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from comms import keys
from comms.messages import Done, MessageError, Record, Status, decode
from missions.format.schema import Mission
from missions.launch.view_peb import peb_of_view
from planner.config import PlannerConfig
from planner.radio.power_offset import offset_of_power_db

#: What was heard of step k: each drone's record and status (None: not heard), and the records
#: the statuses' views name, by (step, drone id).
Heard = tuple[dict[int, Record | None], dict[int, Status | None], dict[tuple[int, int], Record]]


@dataclass
class Collected:
    """What the launcher heard of the run (records and statuses by step)."""

    records: dict[tuple[int, int], Record] = field(default_factory=dict)
    status: dict[tuple[int, int], Status] = field(default_factory=dict)
    dropped: int = 0
    lock: threading.Lock = field(default_factory=threading.Lock)


class SwarmListener:
    """Zenoh subscriber callbacks that fill a :class:`Collected` (messages that do not decode,
    or whose sender is not the drone of their key, are counted as dropped)."""

    def __init__(self, mission: Mission, planner_config: PlannerConfig) -> None:
        self.mission = mission
        self._planner_config = planner_config
        #: The source's power offset b (planner.radio.power_offset) of the views' PEB.
        self._true_offset = offset_of_power_db(mission.source.power_offset_db, planner_config.channel.gamma)
        self.collected = Collected()
        self.ready: set[int] = set()  # real time: drones that reported ready at their start
        #: Drone id → (step, taken over) of its newest record heard.
        self._newest: dict[int, tuple[int, bool]] = {}

    def on_record(self, sample: Any) -> None:
        """Subscriber of the records."""
        self._collect(sample, "record")

    def on_status(self, sample: Any) -> None:
        """Subscriber of the statuses."""
        self._collect(sample, "status")

    def on_done(self, sample: Any) -> None:
        """Real time: a planner's ``Done(-1)`` says its drone is at its start."""
        try:
            _, msg = decode(bytes(sample.payload.to_bytes()), self.mission.id, self.mission.drones.count)
        except MessageError:
            return
        if isinstance(msg, Done) and msg.step == -1 and msg.sender == keys.uav_of(str(sample.key_expr)):
            with self.collected.lock:
                self.ready.add(msg.sender)

    def taken_over_now(self, uav: int) -> bool:
        """Whether drone ``uav``'s newest record heard is flagged taken over (a pilot flies it)."""
        with self.collected.lock:
            newest = self._newest.get(uav)
        return newest is not None and newest[1]

    def ready_count(self) -> int:
        """Real time: how many drones reported being at their starts."""
        with self.collected.lock:
            return len(self.ready)

    def _collect(self, sample: Any, kind: str) -> None:
        c = self.collected
        try:
            _, msg = decode(bytes(sample.payload.to_bytes()), self.mission.id, self.mission.drones.count)
        except MessageError:
            with c.lock:
                c.dropped += 1
            return
        uav = keys.uav_of(str(sample.key_expr))
        if getattr(msg, "sender", None) != uav:
            with c.lock:
                c.dropped += 1
            return
        with c.lock:
            if kind == "record" and isinstance(msg, Record):
                c.records.setdefault((msg.step, msg.sender), msg)
                newest = self._newest.get(msg.sender)
                if newest is None or msg.step >= newest[0]:
                    self._newest[msg.sender] = (msg.step, bool(msg.taken_over))
            elif kind == "status" and isinstance(msg, Status):
                c.status[(msg.step, msg.sender)] = msg

    def heard_at(self, k: int) -> Heard:
        """What was heard of step k: each drone's record and status (None: not heard), and the
        records the statuses' views name, by (step, drone)."""
        n = self.mission.drones.count
        collected = self.collected
        with collected.lock:
            own = {j: collected.records.get((k, j)) for j in range(1, n + 1)}
            stat = {j: collected.status.get((k, j)) for j in range(1, n + 1)}
            # Only the records the views name (copying every record each step is O(K²)).
            wanted = {(s, i + 1) for st in stat.values() if st is not None for i, s in enumerate(st.saved_steps) if s >= 0}
            recs = {key: collected.records[key] for key in wanted if key in collected.records}
        return own, stat, recs

    def live_stats(self, k: int) -> tuple[float, float]:
        """Mean PEB (m) and mean estimate error (m) over the drones at step k (for the progress
        bar): inf and nan when none is known."""
        m = self.mission
        _, stat, recs = self.heard_at(k)
        src = m.source.position_at(k * m.dt_s)
        pebs, errs = [], []
        for st in stat.values():
            if st is None:
                continue
            errs.append(float(np.linalg.norm(np.asarray(st.estimate_m) - src)))
            pebs.append(peb_of_view(self._planner_config, st.saved_steps, recs, src, self._true_offset))
        finite = [p for p in pebs if np.isfinite(p)]
        return (float(np.mean(finite)) if finite else float("inf")), (float(np.mean(errs)) if errs else float("nan"))
