"""One drone's planning step as plain data: the step's inputs (:class:`StepScene`) and what a
drone carries from one step to the next (:class:`DroneState`), both frozen values of arrays.

:func:`planner.agent.plan` takes a scene and a state and returns the next state with the step,
so the in-process simulator (every trial and drone at once, leading dimensions (M, N)) and a
planner node (one drone, no leading dimension) compute the same step from the same data by
construction; the compiled kernels (:mod:`planner.kernels`) take the arrays as they are.

Frames and units: mission ENU, metres, steps; N drones in the mission (the view has a row per
drone, the drone's own included), W = :data:`OWN_RANGE_WINDOW` own ranges, T =
:data:`OWN_TRACK_STEPS` own positions.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
IntArray = NDArray[np.int64]

#: Own ranges (the last ones, the current step's included) a ranging drone combines into a
#: lower bound on its distance to the source (:meth:`planner.agent.OwnRanges.lower_bound_m`).
OWN_RANGE_WINDOW: int = 10
#: Own positions a drone keeps by step (a ring): where it was when a peer's newest record was
#: taken (the partition planes, :func:`planner.control.lost_contact_planes`). A record that
#: arrives older than this (more than 63 consecutive losses) takes the drone's current position.
OWN_TRACK_STEPS: int = 64


@dataclass(frozen=True, eq=False)
class StepScene:
    """The inputs of one planning step (leading batch dimensions ``...``; N drones).

    Attributes:
        step_index: k, the current step (≥ 0).
        own_index: (...) int, the drone's own row i in the view.
        own_position_m: p_i^(k), (..., 3), m, ENU.
        own_range_m: (...) the drone's own range of this step (eq. 3), m; NaN: none.
        own_los: (...) bool, the LOS flag of its own measurement.
        view_positions_m: (..., N, 3) the positions of the records the drone holds, m, ENU.
        view_valid: (..., N) bool, it holds a record of that drone.
        view_los: (..., N) bool, the LOS flag of each record.
        saved_steps: (..., N) int, the step ℓ of each record (−1: none); its age is k − ℓ.
        hops: (..., N) int, hop counts from the drone (−1: unreachable).
        estimate_m: p̂0, the drone's source estimate (..., 3), m, ENU.
        information: its Fisher information (..., 3, 3), m⁻².
        observable: (...) bool, the source is locally identifiable.
        perturbation_uniforms: (..., 2) uniforms in [0, 1) for the singular fallback.
        lost_contact: (..., N) bool, the peers the drone lost contact with by a network fault (a
            partition, their planner gone from the liveliness view); None: none.
    """

    step_index: int
    own_index: IntArray
    own_position_m: FloatArray
    own_range_m: FloatArray
    own_los: BoolArray
    view_positions_m: FloatArray
    view_valid: BoolArray
    view_los: BoolArray
    saved_steps: IntArray
    hops: IntArray
    estimate_m: FloatArray
    information: FloatArray
    observable: BoolArray
    perturbation_uniforms: FloatArray
    lost_contact: BoolArray | None = None

    @property
    def batch(self) -> tuple[int, ...]:
        """The leading dimensions ``...``."""
        return np.shape(self.own_position_m)[:-1]

    @property
    def own_mask(self) -> BoolArray:
        """(..., N) bool, True at the drone's own row."""
        n = np.shape(self.view_valid)[-1]
        return np.arange(n) == np.asarray(self.own_index)[..., None]


@dataclass(frozen=True, eq=False)
class DroneState:
    """What a drone carries from one planning step to the next (leading batch dimensions ``...``).

    Attributes:
        previous_step_m: its last displacement u_i^(k), (..., 3), m; zeros before the first step
            or after a step without a command.
        own_range_m: (..., W) its own last ranges, oldest first, m; NaN: none.
        own_range_los: (..., W) bool, their LOS flags.
        loitering: (...) bool, it loitered at its last step (:func:`planner.agent.must_loiter`).
        keepout_centre_m: (..., 3) the centre of its last step's keep-out, m, ENU; NaN: none.
        keepout_m: (...) its radius, m; NaN: none (−inf: no keep-out then).
        drift_positions_m: (..., N, 3) the newest record of each peer, m, ENU (NaN: none).
        drift_saved_steps: (..., N) its step (−1: none).
        drift_m: (..., N, 3) each peer's mean step between its two newest records, m per step
            (NaN: unknown, :data:`planner.kernels.DRIFT_MAX_GAP_STEPS`).
        own_then_m: (..., N, 3) the drone's own position at the step of each peer's newest record,
            m, ENU (NaN: none).
        track_m: (..., T, 3) its own positions by step, slot k mod T, m, ENU.
        track_steps: (..., T) the step of each slot (−1: none).
    """

    previous_step_m: FloatArray
    own_range_m: FloatArray
    own_range_los: BoolArray
    loitering: BoolArray
    keepout_centre_m: FloatArray
    keepout_m: FloatArray
    drift_positions_m: FloatArray
    drift_saved_steps: IntArray
    drift_m: FloatArray
    own_then_m: FloatArray
    track_m: FloatArray
    track_steps: IntArray

    @classmethod
    def initial(cls, batch: tuple[int, ...], drones: int) -> DroneState:
        """The state before a drone's first step, for ``batch`` drones in a mission of ``drones``."""
        nan = np.nan
        return cls(
            np.zeros(batch + (3,)),
            np.full(batch + (OWN_RANGE_WINDOW,), nan),
            np.zeros(batch + (OWN_RANGE_WINDOW,), dtype=bool),
            np.zeros(batch, dtype=bool),
            np.full(batch + (3,), nan),
            np.full(batch, nan),
            np.full(batch + (drones, 3), nan),
            np.full(batch + (drones,), -1, dtype=np.int64),
            np.full(batch + (drones, 3), nan),
            np.full(batch + (drones, 3), nan),
            np.full(batch + (OWN_TRACK_STEPS, 3), nan),
            np.full(batch + (OWN_TRACK_STEPS,), -1, dtype=np.int64),
        )

    @property
    def batch(self) -> tuple[int, ...]:
        """The leading dimensions ``...``."""
        return np.shape(self.loitering)

    def kernel_arrays(self) -> tuple[np.ndarray, ...]:
        """The arrays in field order with the batch flattened to one axis (the kernels' form); a
        state the kernels made (:meth:`from_kernel_arrays`) hands back the arrays it was made of."""
        flat: tuple[np.ndarray, ...] | None = self.__dict__.get("_flat")
        if flat is not None:
            return flat
        batch = self.batch
        n = int(np.prod(batch, dtype=np.int64))
        values = (getattr(self, name) for name in _STATE_FIELDS)
        return tuple(_writeable(np.ascontiguousarray(a)).reshape((n,) + np.shape(a)[len(batch) :]) for a in values)

    @classmethod
    def from_kernel_arrays(cls, arrays: Iterable[np.ndarray], batch: tuple[int, ...]) -> DroneState:
        """The state of arrays in field order with a flat batch axis, reshaped to ``batch`` (views:
        the arrays are the state's and must not change afterwards). Each field is reshaped when
        first read (a planner reads few of them between two steps)."""
        state = cls.__new__(cls)
        state.__dict__.update(_flat=tuple(arrays), _batch=batch)  # a frozen value: no __init__
        return state

    def __getattr__(self, name: str) -> np.ndarray:
        """A field of a state made by :meth:`from_kernel_arrays`, reshaped from its flat array."""
        flat = self.__dict__.get("_flat")
        if flat is None or name not in _STATE_FIELDS:
            raise AttributeError(name)
        a = flat[_STATE_FIELDS.index(name)]
        value: np.ndarray = a.reshape(self.__dict__["_batch"] + a.shape[1:])
        self.__dict__[name] = value
        return value

    def tracked(self, step: int, position_m: FloatArray) -> DroneState:
        """The state with the own position (..., 3), m, of ``step`` in the track (a step the drone
        did not plan: a pilot flew it)."""
        track, steps = self.track_m.copy(), self.track_steps.copy()
        track[..., step % OWN_TRACK_STEPS, :] = position_m
        steps[..., step % OWN_TRACK_STEPS] = step
        return dataclasses.replace(self, track_m=track, track_steps=steps)

    def without_step(self) -> DroneState:
        """The state after a step without a command (taken over, or the setpoint not sent): no
        previous displacement."""
        return dataclasses.replace(self, previous_step_m=np.zeros_like(self.previous_step_m))

    def without_keepout(self) -> DroneState:
        """The state with the last keep-out forgotten: the next step is not rate-limited against it
        (a drone handed back after steps it did not plan)."""
        nan = np.nan
        return dataclasses.replace(self, keepout_centre_m=np.full_like(self.keepout_centre_m, nan), keepout_m=np.full_like(self.keepout_m, nan))

    def replayed(self, steps: Iterable[tuple[int, FloatArray, float, bool]]) -> DroneState:
        """A single drone's state with logged steps (step, position m, range m or NaN, LOS) in its
        range window and track, in order (a rejoining planner's own predecessor's log)."""
        state = self
        for step, position, range_m, los in steps:
            ranges = np.concatenate((state.own_range_m[..., 1:], np.full(state.batch + (1,), float(range_m))), -1)
            flags = np.concatenate((state.own_range_los[..., 1:], np.full(state.batch + (1,), bool(los))), -1)
            state = dataclasses.replace(state.tracked(step, np.asarray(position, dtype=float)), own_range_m=ranges, own_range_los=flags)
        return state


#: DroneState's field names, in order (the kernels' order of its arrays).
_STATE_FIELDS: tuple[str, ...] = tuple(f.name for f in dataclasses.fields(DroneState))


def _writeable(a: np.ndarray) -> np.ndarray:
    """``a``, copied if read-only (a read-only array is another numba type: a second compile)."""
    return a if a.flags.writeable else a.copy()
