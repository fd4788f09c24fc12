"""Receiving-side loss and delay injection for the peers' records.

Deterministic fault emulation shared by the planner node (:class:`comms.latency.DelayedView`)
and the in-process simulator (:func:`missions.study.simulator.simulate`), so that both see the same
faults for a seed.

Model. For every receiver i, sender j ≠ i and record step s, receiver i decides, from its own
stream ``planner.randomness.stream(seed, trial, i, FAULT_STREAM)``:

* lost, with probability ``loss``: the record never enters i's memory buffer;
* otherwise an extra delay d_ijs, a uniform integer in 0..D (``max_extra_delay_steps``).

The decisions are drawn when step s is reached, :data:`FAULT_DRAWS` uniforms per sender, for
every sender j = 0..N−1 in order (the receiver's own slot is drawn and ignored, so the draws do
not depend on who is the receiver): ``rng.random((N, 2))``, column 0 decides the loss
(u < loss), column 1 the delay (d = ⌊u·(D+1)⌋).

The extra delay adds to the hop latency of the paper's multi-hop dissemination (Sec. II-B,
:mod:`planner.network`): without faults, at step k drone i holds j's record of step
ℓ = k − h_ij + 1 when 1 ≤ h_ij ≤ h_max. With faults, the record of step s is *usable* at step k
when it is not lost and

    s + (h_ij − 1) + d_ijs ≤ k,

and drone i saves the newest usable record (never replacing a newer saved one):

    ℓ_ij(k) = max(ℓ_ij(k−1), max{s : record s of j usable at k})   if 1 ≤ h_ij(k) ≤ h_max,
    ℓ_ij(k) = ℓ_ij(k−1)                                              otherwise.

With loss = 0 and D = 0 this is exactly :func:`planner.network.update_saved_steps`. Hop counts
stay the network's own (the disk graph of the drones' true positions, as without faults): a
lost record is lost by the radio link, the topology does not change (without faults too, the
position of a record not yet in the view already defines the graph when h ≥ 2).

The search is exact with a sliding window: a record older than k − W + 1, W = h + D with
h = min(h_max, N − 1), is usable whatever its delay and hop count, so only the newest non-lost
record that left the window needs remembering.

Imports: numpy and the planner core only (no zenoh).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner.network import NEVER
from planner.randomness import FAULT_STREAM, stream

IntArray = NDArray[np.int64]

#: Uniform variates per (receiver, sender, step): loss, extra delay.
FAULT_DRAWS: int = 2
#: Steps of decisions drawn from each receiver's stream at once (the same variates, in the same
#: order, as one draw per step: a generator fills an array in C order).
DRAW_BLOCK_STEPS: int = 64
#: "Ready step" of a lost record (never usable).
_NEVER_READY: int = np.iinfo(np.int64).max // 4


@dataclass(frozen=True)
class FaultModel:
    """Loss and extra delay of the peers' records at a receiver.

    Attributes:
        loss: probability that a peer's record is lost at a receiver, in [0, 1).
        max_extra_delay_steps: D, the extra delay is a uniform integer in 0..D steps.
    """

    loss: float = 0.0
    max_extra_delay_steps: int = 0

    def __post_init__(self) -> None:
        if not 0.0 <= self.loss < 1.0:
            raise ValueError(f"loss: expected a probability in [0, 1), found {self.loss!r}")
        if self.max_extra_delay_steps < 0:
            raise ValueError(f"max_extra_delay_steps: expected an integer >= 0, found {self.max_extra_delay_steps!r}")

    @property
    def enabled(self) -> bool:
        """Whether any fault is injected."""
        return self.loss > 0.0 or self.max_extra_delay_steps > 0

    def decide(self, uniforms: ArrayLike) -> tuple[NDArray[np.bool_], IntArray]:
        """Decisions from uniforms (..., 2) in [0, 1): (lost (...), extra delay in steps (...))."""
        u = np.asarray(uniforms, dtype=float)
        lost = u[..., 0] < self.loss
        d = self.max_extra_delay_steps
        delay = np.minimum(np.floor(u[..., 1] * (d + 1)).astype(np.int64), d)
        return lost, delay


class FaultBuffer:
    """The faulty memory-buffer update for a batch of receivers (pure numpy, no I/O).

    Holds, per (trial, receiver, sender), the ready step s + d of the last W records (or
    "never" if lost) and the newest non-lost record older than the window. Decisions are drawn
    in step order from each receiver's stream (module docstring).

    Args:
        model: the fault model.
        seed: the mission seed.
        trials: trial indices (the node: ``[0]``).
        receivers: receiver drone indices, 0-based (the node: ``[i]``).
        count: N, number of drones (senders).
        h_max: the mission's maximum number of hops.
    """

    def __init__(self, model: FaultModel, seed: int, trials: Sequence[int], receivers: Sequence[int], count: int, h_max: int) -> None:
        self.model = model
        self.count = count
        self.h_max = h_max
        self.window = max(1, min(h_max, max(count - 1, 1))) + model.max_extra_delay_steps
        self._rngs = [[stream(seed, m, i, FAULT_STREAM) for i in receivers] for m in trials]
        lead = (len(trials), len(receivers))
        self._ready = np.full((self.window, *lead, count), _NEVER_READY, dtype=np.int64)
        self.old_best = np.full((*lead, count), NEVER, dtype=np.int64)
        self._receivers = np.asarray(receivers, dtype=np.int64)
        # Whether each record of the window has been delivered (usable with 1 <= h <= h_max).
        self._delivered = np.zeros((self.window, *lead, count), dtype=bool)
        #: Steps of the peers' records first delivered by the last :meth:`update` that are older
        #: than the record it saved (overtaken by a newer one while late): (W, T, R, N), NEVER
        #: elsewhere, window slots oldest first. Old evidence about the source, for the
        #: estimator (:meth:`late_records`).
        self.late_steps = np.full((self.window, *lead, count), NEVER, dtype=np.int64)
        self._next = 0
        # The uniforms of steps _block_start.. (T, R, DRAW_BLOCK_STEPS, N, FAULT_DRAWS).
        self._block = np.empty((len(trials), len(receivers), 0, count, FAULT_DRAWS))
        self._block_start = 0
        #: Peer records decided so far, and how many of them were lost (own slots excluded).
        self.decided = 0
        self.lost = 0

    def _draw(self) -> None:
        """Decide the records of step ``self._next`` for every receiver and sender."""
        s = self._next
        if s - self._block_start >= self._block.shape[2]:
            shape = (DRAW_BLOCK_STEPS, self.count, FAULT_DRAWS)
            self._block = np.stack([np.stack([g.random(shape) for g in row]) for row in self._rngs])
            self._block_start = s
        u = self._block[:, :, s - self._block_start]
        lost, delay = self.model.decide(u)
        own = np.arange(self.count)[None, None, :] == self._receivers[None, :, None]
        leaving = s - self.window
        if leaving >= 0:
            kept = self._ready[0] < _NEVER_READY
            self.old_best = np.where(kept, leaving, self.old_best)
        self._ready[:-1] = self._ready[1:]
        self._ready[-1] = np.where(lost & ~own, _NEVER_READY, s + np.where(own, 0, delay))
        self._delivered[:-1] = self._delivered[1:]
        self._delivered[-1] = False
        peers = ~np.broadcast_to(own, lost.shape)
        self.decided += int(peers.sum())
        self.lost += int((lost & peers).sum())
        self._next += 1

    def update(self, saved_steps: ArrayLike, hops: ArrayLike, step: int) -> IntArray:
        """Advance the memory buffer to step k with faults (module docstring's rule).

        Args:
            saved_steps: (T, R, N) steps of the records held (:data:`NEVER` for none).
            hops: (T, R, N) hop counts h_ij from each receiver (0 for itself, −1 unreachable).
            step: k; steps are visited in increasing order (skipped steps are decided too).

        Returns:
            The new saved steps (T, R, N): own record current (ℓ = k), peers by the rule.
        """
        if step < self._next - 1:
            raise ValueError(f"fault decisions are drawn in step order: step {step} after step {self._next - 1}")
        while self._next <= step:
            self._draw()
        saved = np.asarray(saved_steps, dtype=np.int64)
        h = np.asarray(hops, dtype=np.int64)
        first = step - self.window + 1
        s_idx = (first + np.arange(self.window)).reshape((self.window,) + (1,) * h.ndim)
        usable = (self._ready <= (step - h + 1)[None]) & (s_idx >= 0)
        newest = np.maximum(np.where(usable, s_idx, NEVER).max(0), self.old_best)
        delivered = (h >= 1) & (h <= self.h_max)
        new = np.where(delivered, np.maximum(saved, newest), saved)
        own = np.arange(self.count)[None, None, :] == self._receivers[None, :, None]
        # Records delivered now for the first time; those older than the saved one were
        # overtaken while late and never enter the view, but they are still evidence.
        arrived = usable & delivered[None]
        first_arrival = arrived & ~self._delivered
        self._delivered |= arrived
        self.late_steps = np.where(first_arrival & (s_idx < new[None]) & ~own[None], s_idx, NEVER)
        return np.where(own, step, new)
