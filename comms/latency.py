"""Receiving-side hop-latency emulation: what a planner is allowed to see of its peers.

On loopback every record arrives at once; :class:`DelayedView` then applies the paper's
multi-hop latency with the math core's logic (:mod:`planner.network`): at step k drone i sees
drone j's record of step ℓ = k − h_ij + 1, with h_ij the hop count on the disk graph of radius
d_hop over the drones' current positions; beyond h_max hops, or when j is unreachable, drone i
keeps the last record of j it saved. With ``emulate=False`` (real radio networks, where the
latency is real) the view is simply the newest record received from each peer.

Injected faults (``faults``, :mod:`comms.faults`): receiver i decides, from its own seeded
stream, whether each peer record is lost or delayed by extra steps; a lost record still counts
as arrived for the lockstep barrier (:meth:`DelayedView.has`) and still places its sender in the
disk graph, but never enters the view; the planner falls back on its saved record (the memory
buffer). Without emulation the faults apply with one hop to every peer.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from comms.faults import FaultBuffer, FaultModel
from comms.messages import Record
from planner.network import NEVER, hop_counts, update_saved_steps


@dataclass(frozen=True)
class View:
    """Drone i's view at one step.

    Attributes:
        records: per drone (0-based index), the record in the view, or None.
        saved_steps: (N,) step of each record (−1: none).
        hops: (N,) hop count from drone i (−1: unreachable), or all −1 without emulation.
        late_records: with injected faults, the peers' records delivered at this step for the
            first time but older than the one saved (overtaken by a newer record while late):
            they never enter the view, but they are evidence about the source for the
            estimator. Oldest first, then by sender (:attr:`comms.faults.FaultBuffer.late_steps`).
    """

    records: tuple[Record | None, ...]
    saved_steps: np.ndarray
    hops: np.ndarray
    late_records: tuple[Record, ...] = ()


class DelayedView:
    """Memory buffer of one drone's peers' records, with the hop-latency rule.

    Args:
        own_index: drone i (0-based). count: N. d_hop_m, h_max: the mission's comms.
        emulate: apply the hop latency (True) or use the newest records (False).
        faults: injected loss and extra delay (None or disabled: none).
        seed, trial: the mission seed and trial of the fault decisions (the receiver's stream).
    """

    def __init__(
        self,
        own_index: int,
        count: int,
        d_hop_m: float,
        h_max: int,
        emulate: bool = True,
        faults: FaultModel | None = None,
        seed: int = 0,
        trial: int = 0,
    ) -> None:
        self.own = own_index
        self.count = count
        self.d_hop_m = d_hop_m
        self.h_max = h_max
        self.emulate = emulate
        self.faults: FaultBuffer | None = None
        if faults is not None and faults.enabled:
            self.faults = FaultBuffer(faults, seed, [trial], [own_index], count, h_max if emulate else 1)
        self._history: list[dict[int, Record]] = [{} for _ in range(count)]
        self._saved = np.full(count, NEVER, dtype=np.int64)
        self._last_position = np.full((count, 3), np.nan)

    def add(self, record: Record) -> None:
        """Store a received record (own or peer's); duplicates replace nothing."""
        j = record.sender - 1
        if not 0 <= j < self.count:
            raise ValueError(f"record of drone {record.sender} outside 1..{self.count}")
        self._history[j].setdefault(record.step, record)

    def has(self, sender: int, step: int) -> bool:
        """Whether the record of drone ``sender`` (1-based) for ``step`` has arrived."""
        return step in self._history[sender - 1]

    def advance(self, step: int) -> View:
        """The view at step k (call once per step, after the step's records have arrived)."""
        current = np.array(
            [r.position_m if (r := h.get(step)) is not None else self._last_position[j] for j, h in enumerate(self._history)],
            dtype=float,
        )
        known = np.isfinite(current).all(-1)
        self._last_position = np.where(known[:, None], current, self._last_position)
        if self.emulate:
            # Hop counts over the drones' current positions; drones never heard of are far away.
            pos = np.where(known[:, None], current, 1e12 * (1 + np.arange(self.count))[:, None])
            hops_all = hop_counts(pos, self.d_hop_m, max_hops=self.h_max + 1)
            hops = hops_all[self.own]
            if self.faults is not None:
                new = self.faults.update(self._saved[None, None], hops[None, None], step)[0, 0]
            else:
                # A delayed record ℓ is only usable if it has arrived; ℓ itself comes from the rule.
                saved_all = np.full((self.count, self.count), NEVER, dtype=np.int64)
                saved_all[self.own] = self._saved
                new = update_saved_steps(saved_all, hops_all, step, self.h_max)[self.own]
        elif self.faults is not None:
            # No hop latency: every peer is one hop away, the injected faults still apply.
            one_hop = np.where(np.arange(self.count) == self.own, 0, 1)
            new = self.faults.update(self._saved[None, None], one_hop[None, None], step)[0, 0]
            hops = np.full(self.count, -1, dtype=np.int64)
        else:
            newest = np.array([max(h) if h else NEVER for h in self._history], dtype=np.int64)
            new = np.maximum(self._saved, np.minimum(newest, step))
            hops = np.full(self.count, -1, dtype=np.int64)
        records = []
        for j in range(self.count):
            rec = self._history[j].get(int(new[j])) if new[j] >= 0 else None
            if rec is None and new[j] >= 0:
                # The rule names a record that never arrived (lost): keep what was saved.
                new[j] = self._saved[j]
                rec = self._history[j].get(int(new[j])) if new[j] >= 0 else None
            records.append(rec)
        late: list[Record] = []
        if self.faults is not None:
            for s_, j in zip(*np.nonzero(self.faults.late_steps[:, 0, 0, :] >= 0)):
                rec = self._history[int(j)].get(int(self.faults.late_steps[s_, 0, 0, j]))
                if rec is not None:  # else it never arrived over the network
                    late.append(rec)
        self._saved = new
        self._prune(step)
        return View(tuple(records), new.copy(), hops, tuple(late))

    def _prune(self, step: int) -> None:
        """Forget records that can no longer enter a view (older than the saved ones and
        older than the hop window)."""
        horizon = step - self.h_max
        if self.faults is not None:
            # The fault window (hop and extra delay) and the newest record that left it.
            horizon = min(horizon, step - self.faults.window + 1)
        for j, h in enumerate(self._history):
            keep_from = min(horizon, int(self._saved[j]))
            if self.faults is not None:
                best = int(self.faults.old_best[0, 0, j])
                keep_from = keep_from if best < 0 else min(keep_from, best)
            for s in [s for s in h if s < keep_from]:
                del h[s]
