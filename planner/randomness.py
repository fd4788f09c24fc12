"""Random streams of fimnav, all derived from the mission seed (no global RNG).

Every stream is a :class:`numpy.random.Generator` seeded by a :class:`numpy.random.SeedSequence`
of ``(seed, trial, drone, purpose)``. Measurement noise is drawn as uniform variates, five per
drone and step (see :func:`planner.observation.observe_from_uniforms`), so that drawing them
one step at a time (a payload process) or all steps at once (the in-process simulator) gives
the same numbers: ``Generator.random`` consumes the stream sequentially.
"""

from __future__ import annotations

import numpy as np

from planner.sensing import measurement_draws

#: Purpose tags of the streams.
MEASUREMENT_STREAM: int = 0
CONTROL_STREAM: int = 1
#: Receiving-side loss and delay injection (:mod:`comms.faults`): drawn by the receiver.
FAULT_STREAM: int = 2

#: Uniform variates per drone and step for the measurement noise: the columns the registered
#: components draw from (:func:`planner.sensing.measurement_draws`; 5: range 0, bearing 1-4).
MEASUREMENT_DRAWS: int = measurement_draws()
#: Uniform variates per drone and step for the singular-FIM random perturbation.
CONTROL_DRAWS: int = 2


def stream(seed: int, trial: int, drone: int, purpose: int) -> np.random.Generator:
    """The generator of one drone (0-based index) in one trial for one purpose."""
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(trial), int(drone), int(purpose)]))


def measurement_rng(seed: int, trial: int, drone: int) -> np.random.Generator:
    """Measurement-noise generator of drone ``drone`` (0-based) in trial ``trial``."""
    return stream(seed, trial, drone, MEASUREMENT_STREAM)


def control_rng(seed: int, trial: int, drone: int) -> np.random.Generator:
    """Generator of the singular-FIM perturbations of drone ``drone`` in trial ``trial``."""
    return stream(seed, trial, drone, CONTROL_STREAM)


def presampled_uniforms(seed: int, trials: int, drones: int, steps: int, purpose: int, draws: int, first_trial: int = 0) -> np.ndarray:
    """Uniform variates of shape (steps, trials, drones, draws) from the per-drone streams of
    trials ``first_trial`` … ``first_trial + trials − 1``.

    Equal, element by element, to calling ``stream(seed, first_trial + m, i, purpose).random(draws)``
    once per step, in step order.
    """
    out = np.empty((steps, trials, drones, draws))
    for m in range(trials):
        for i in range(drones):
            out[:, m, i, :] = stream(seed, first_trial + m, i, purpose).random((steps, draws))
    return out
