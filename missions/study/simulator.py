"""In-process Monte Carlo simulator: M trials × K steps of an N-drone mission, vectorised.

Every drone of every trial runs the same chain as a planner process (docs/distributed.md, "The
planner node"): its own measurement (eq. 3, noise from its own seeded stream), its delayed view
of the peers (hop latency and memory buffer, :mod:`planner.network`), its own source estimate
(:mod:`planner.estimator`), its own control step (:func:`planner.control.control_step`). The
arrays carry the trial and drone axes together, so one numpy call serves all M·N drones.

Step k of a trial, for every drone i (all drones in parallel):

1. record: true position p_i^(k), LOS of its link, measurement from p_i^(k) (eq. 3);
2. hop counts on the disk graph of the current positions; memory buffer update (ℓ = k − h + 1;
   with injected loss and delay, ``comms.faults``, the newest usable record, :mod:`comms.faults`);
3. the records new to drone i feed its estimator; p̂_0,i^(k) and its information;
4. J(p̂_0,i; q_i^(k)) over the records it holds, cost gradient (eq. 6, 13), control step (eq. 14);
5. PEB (eq. 18) at the true source with the positions known to drone i, estimate error, and
   the margin of every constraint with the true positions.

The noise of drone i in trial m comes from ``planner.randomness.measurement_rng(seed, m, i)``,
five uniforms per step, the same stream a vehicle payload process draws from, so a distributed
run of trial 0 sees the same measurements as trial 0 here.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from comms.faults import FaultBuffer
from missions.format.schema import Mission
from missions.study.records import KINEMATIC_TOL as KINEMATIC_TOL
from missions.study.records import MAVLINK_KINEMATIC_TOL as MAVLINK_KINEMATIC_TOL
from missions.study.records import SAFETY_FAMILIES as SAFETY_FAMILIES
from missions.study.records import PenaltyReference as PenaltyReference
from missions.study.records import RunSpec as RunSpec
from missions.study.records import SimulationResult as SimulationResult
from missions.study.records import fault_penalty_against
from missions.study.records import mean_record_age as mean_record_age
from missions.study.records import without_faults as without_faults
from planner import estimator as est
from planner import kernels as K
from planner import sim_kernels
from planner.control import StepResult
from planner.fim import fisher_information, position_error_bound
from planner.geometry import as_boxes, distance_to_boxes
from planner.observation import observe_from_uniforms
from planner.params import Limits
from planner.policies import RANDOM_WALK_DRAWS, RANDOM_WALK_STREAM, policy_planner
from planner.radio import power_estimator as power
from planner.radio.unknown_power import fisher_information_unknown_power, position_error_bound_unknown_power
from planner.randomness import CONTROL_DRAWS, CONTROL_STREAM, MEASUREMENT_STREAM, presampled_uniforms
from planner.sensing import SENSING, SensingTable
from planner.step import DroneState, StepScene

FloatArray = NDArray[np.float64]


def _gather(history: NDArray, saved: NDArray[np.int64]) -> NDArray:
    """history[saved[m,i,j], m, j] for history (K, M, N, ...) and saved (M, N, N) (the values of
    the components beyond range and bearing; :func:`planner.sim_kernels.gather_view` gathers
    the rest)."""
    m_idx = np.arange(saved.shape[0])[:, None, None]
    j_idx = np.arange(saved.shape[2])[None, None, :]
    return history[np.maximum(saved, 0), m_idx, j_idx]


def _contiguous(a: FloatArray) -> FloatArray:
    """``a`` as a C-contiguous, writeable float array (the form the kernels are compiled for)."""
    if a.dtype == np.float64 and a.flags.c_contiguous and a.flags.writeable:
        return a
    return np.array(a, dtype=np.float64, order="C")


def _position_error_bound(fim: FloatArray) -> FloatArray:
    """PEB (eq. 18, m) of FIMs (..., 3, 3), +inf where singular: from the cofactors where J is
    provably well conditioned (:func:`planner.sim_kernels.position_error_bounds`), elsewhere
    :func:`planner.fim.position_error_bound` (its eigenvalue check decides singular views)."""
    J = _contiguous(fim).reshape(-1, 3, 3)
    peb, checked = np.empty(J.shape[0]), np.empty(J.shape[0], dtype=bool)
    sim_kernels.position_error_bounds(J, peb, checked)
    if checked.any():
        idx = np.flatnonzero(checked)
        peb[idx] = position_error_bound(J[idx])[0]
    return peb.reshape(fim.shape[:-2])


def _with_late_records(
    meas: est.Measurements,
    late_steps: NDArray[np.int64],
    positions: FloatArray,
    rec_range: FloatArray,
    rec_az: FloatArray,
    rec_el: FloatArray,
    rec_los: NDArray[np.bool_],
    rec_extra: Mapping[str, FloatArray],
) -> est.Measurements:
    """The view's new records plus the peers' records delivered late, after a newer one
    (:attr:`comms.faults.FaultBuffer.late_steps`, (W, M, N, N)): old evidence about the source
    is still evidence. They follow the view's N rows, oldest window slot first, then by sender
    (the order of a planner node's rows); rows empty in every batch element are left out.
    ``rec_extra``: the records' values of the components other than range and bearing, by
    value name, each (K, M, N)."""
    W, M, N, _ = late_steps.shape
    steps = np.moveaxis(late_steps, 0, 2).reshape(M, N, W * N)  # (m, i, slot·N + j)
    have = steps >= 0
    if not have.any():
        return meas
    order = np.argsort(~have, axis=-1, kind="stable")[..., : int(have.sum(-1).max())]
    steps = np.take_along_axis(steps, order, -1)
    have = np.take_along_axis(have, order, -1)
    j = np.broadcast_to(np.arange(N), (W, N)).reshape(-1)[order]
    idx = (np.maximum(steps, 0), np.arange(M)[:, None, None], j)
    nan = np.nan
    return est.Measurements(
        positions_m=np.concatenate([meas.positions_m, np.where(have[..., None], positions[idx], nan)], axis=-2),
        range_m=np.concatenate([meas.range_m, np.where(have, rec_range[idx], nan)], axis=-1),
        azimuth_rad=np.concatenate([meas.azimuth_rad, np.where(have, rec_az[idx], nan)], axis=-1),
        elevation_rad=np.concatenate([meas.elevation_rad, np.where(have, rec_el[idx], nan)], axis=-1),
        los=np.concatenate([meas.los, have & rec_los[idx]], axis=-1),
        extra_values={
            name: np.concatenate([meas.extra_values[name], np.where(have, values[idx], nan)], axis=-1) for name, values in rec_extra.items()
        },
    )


@dataclass(frozen=True)
class SimStep:
    """What :func:`simulate` shows an observer at step k (every trial; mission ENU, m).

    Attributes:
        step: k. positions_m: (M, N, 3) where the drones took their records of step k.
        estimates_m: (M, N, 3) each drone's source estimate after step k's records.
        view_positions_m: (M, N, N, 3) drone i's record of drone j's position.
        view_valid: (M, N, N) drone i holds a record of drone j. view_los: (M, N, N) it was LOS.
    """

    step: int
    positions_m: FloatArray
    estimates_m: FloatArray
    view_positions_m: FloatArray
    view_valid: NDArray[np.bool_]
    view_los: NDArray[np.bool_]


@dataclass(frozen=True)
class _View:
    """Every drone's delayed view at one step (M trials, N drones).

    Attributes:
        cut: (N, N) links cut by a partition at this step, or None.
        hops: (M, N, N) hop counts on the disk graph of the current positions.
        saved: (M, N, N) step of drone i's record of drone j (−1: none).
        have: (M, N, N) drone i holds a record of drone j.
        positions_m: (M, N, N, 3) the positions of those records (m, ENU). los: (M, N, N).
    """

    cut: NDArray[np.bool_] | None
    hops: NDArray[np.int64]
    saved: NDArray[np.int64]
    have: NDArray[np.bool_]
    positions_m: FloatArray
    los: NDArray[np.bool_]


class _Simulation:
    """The state of :func:`simulate` between steps: the drones' positions, records, views,
    estimators, and the arrays of the result (see :func:`simulate` for the arguments)."""

    def __init__(
        self, spec: RunSpec, estimator_config: est.EstimatorConfig | None, oracle_estimate: bool, float32_positions: bool, sensing: SensingTable
    ) -> None:
        mission = spec.mission
        M, K = spec.trials, spec.steps
        N = mission.drones.count
        self.spec = spec
        self.config = config = mission.planner_config(spec.criterion, sensing)
        self.channel = config.channel
        self.bmin, self.bmax = as_boxes(config.boxes_min_m, config.boxes_max_m)
        self.ranging, self.bearing = config.ranging, config.bearing
        self.extra_masks = config.extra_masks
        self.components = sensing.components
        self.comms = comms = mission.comms
        self.estimator_config = config.estimator if estimator_config is None else estimator_config
        self.oracle_estimate = oracle_estimate
        self.float32_positions = float32_positions

        first = spec.first_trial
        self.meas_u = presampled_uniforms(mission.seed, M, N, K, MEASUREMENT_STREAM, sensing.measurement_draws(), first)
        self.ctrl_u = presampled_uniforms(mission.seed, M, N, K, CONTROL_STREAM, CONTROL_DRAWS, first)

        # Every drone's start position (the mission's; the planning step keeps clear of a peer not
        # heard of yet there, planner.agent.plan).
        pos = np.broadcast_to(mission.drones.start_positions_m(), (M, N, 3)).copy()
        if float32_positions:
            pos = pos.astype(np.float32).astype(np.float64)
        self.pos = pos
        self.positions = np.empty((K + 1, M, N, 3))
        self.positions[0] = pos
        self.rec_range = np.full((K, M, N), np.nan)
        self.rec_az = np.full((K, M, N), np.nan)
        self.rec_el = np.full((K, M, N), np.nan)
        self.rec_los = np.zeros((K, M, N), dtype=bool)
        # The values of the components other than range and bearing, by value name.
        self.rec_extra = {name: np.full((K, M, N), np.nan) for name in sensing.extra_value_names}
        self.saved = np.full((M, N, N), -1, dtype=np.int64)
        fault_model = comms.faults.to_model()
        # A partition: drones 1..ceil(N/2) and the rest exchange nothing while it lasts; each drone
        # knows it has lost them (as a planner node sees their planners leave the liveliness view).
        self.partition = comms.faults.partition
        half = np.arange(N) < (N + 1) // 2
        self.partition_links = half[:, None] != half[None, :]
        # Injected faults: receiver i of trial m draws from its own stream, as a planner node does.
        self.faults = FaultBuffer(fault_model, mission.seed, range(first, first + M), range(N), N, comms.h_max) if fault_model is not None else None
        self.used = np.full((M, N, N), -1, dtype=np.int64)
        unknown = self.unknown_power = config.unknown_power
        self.state: power.SourceEstimatorState = (
            est.initial_state((M, N), self.estimator_config) if unknown is None else power.initial_state((M, N), self.estimator_config, unknown)
        )
        #: The true source's power offset b (planner.radio.power_estimator; 0: the nominal power).
        self.true_offset = power.offset_of_power_db(mission.source.power_offset_db, self.channel.gamma)
        self.offsets_db = np.full((K, M, N), np.nan) if config.unknown_power is not None else None
        # What does not change from step to step: the sensing roles as every drone's view sees
        # them, the links a partition cuts (the kernels' form), whether the source is slow.
        self.rng_view = np.broadcast_to(self.ranging, (M, N, N))
        self.brg_view = np.broadcast_to(self.bearing, (M, N, N))
        self.no_cut = np.zeros((N, N), dtype=bool)
        self.source_slow = mission.source_is_slow()

        self.estimates = np.empty((K, M, N, 3))
        self.est_err = np.empty((K, M, N))
        self.observable = np.empty((K, M, N), dtype=bool)
        self.peb = np.empty((K, M, N))
        self.sources = np.array([mission.source.position_at(k * mission.dt_s) for k in range(K + 1)])
        self.active_counts = np.zeros((K, 4), dtype=np.int64)
        self.fallback = np.empty((K, M, N), dtype=bool)
        self.filtered = np.empty((K, M, N), dtype=bool)
        self.loiter = np.empty((K, M, N), dtype=bool)
        #: What every drone carries from one planning step to the next (planner.step.DroneState).
        self.drone = DroneState.initial((M, N), N)
        self.own_index = np.broadcast_to(np.arange(N), (M, N))
        self.ages = np.empty((K, M, N, N), dtype=np.int16)
        # The mission's navigation policy (planner.policies): its planning step (the planner's
        # for 'fim' and 'centralized') and, for 'centralized', every record at once (_view).
        self.policy = mission.policy
        walk = presampled_uniforms(mission.seed, M, N, K, RANDOM_WALK_STREAM, RANDOM_WALK_DRAWS, first) if self.policy == "random" else None
        self.plan_step = policy_planner(self.policy, walk)

    def step(self, k: int, observer: Callable[[SimStep], None] | None) -> None:
        """Step k of every drone of every trial, in the order of the module doc."""
        src = self.sources[k]
        self._record(k, src)
        view = self._delayed_view(k) if self.policy != "centralized" else self._instant_view(k)
        self._estimate(k, src, view)
        step = self._plan(k, src, view)
        self._accuracy(k, src, view, observer)
        self._move(k, step)

    def _record(self, k: int, src: FloatArray) -> None:
        """1. Own record: position, LOS and measurement at step k."""
        self.pos = pos = _contiguous(self.pos)
        los = self.rec_los[k]
        sim_kernels.line_of_sight(pos.reshape(-1, 3), _contiguous(src), self.bmin, self.bmax, los.reshape(-1))
        obs = observe_from_uniforms(src, pos, self.ranging, self.bearing, los, self.channel, self.meas_u[k], self.extra_masks, self.components)
        rng = obs.range_m
        if self.true_offset != 0.0:
            rng = power.offset_ranges(rng, np.linalg.norm(src - pos, axis=-1), self.true_offset, self.channel.gamma)
        self.rec_range[k], self.rec_az[k], self.rec_el[k] = rng, obs.azimuth_rad, obs.elevation_rad
        for name, values in self.rec_extra.items():
            values[k] = obs.values[name]

    def _delayed_view(self, k: int) -> _View:
        """2. Delayed view (hop latency, memory buffer)."""
        comms, partition = self.comms, self.partition
        cut = self.partition_links if partition is not None and partition[0] <= k < partition[1] else None
        hops = np.empty(self.saved.shape, dtype=np.int64)
        sim_kernels.hop_counts(self.pos, comms.d_hop_m, comms.h_max + 1, self.no_cut if cut is None else cut, cut is not None, hops)
        if self.faults is None:
            saved = self.saved.copy()
            sim_kernels.update_saved_steps(saved, hops, k, comms.h_max)
        else:
            saved = self.faults.update(self.saved, hops, k)
        self.saved = saved
        return self._view(k, cut, hops, saved)

    def _view(self, k: int, cut: NDArray[np.bool_] | None, hops: NDArray[np.int64], saved: NDArray[np.int64]) -> _View:
        """The view of the records held at step k (``saved``), and their ages."""
        have = np.empty(saved.shape, dtype=bool)
        view_pos, view_los = np.empty(saved.shape + (3,)), np.empty(saved.shape, dtype=bool)
        sim_kernels.gather_view(self.positions, self.rec_los, saved, k, view_pos, view_los, have, self.ages[k])
        return _View(cut, hops, saved, have, view_pos, view_los)

    def _instant_view(self, k: int) -> _View:
        """2'. The centralized policy's view: every drone's record of step k, at once (no hop
        latency, no hop limit, no comms fault), every peer a neighbour."""
        M, N = self.pos.shape[:2]
        saved = np.full((M, N, N), k, dtype=np.int64)
        self.saved = saved
        hops = np.broadcast_to(1 - np.eye(N, dtype=np.int64), (M, N, N)).copy()
        return self._view(k, None, hops, saved)

    def _estimate(self, k: int, src: FloatArray, view: _View) -> None:
        """3. Estimator: records new to each drone."""
        saved = view.saved
        new = saved > self.used
        extra = {name: np.where(new, _gather(rec, saved), np.nan) for name, rec in self.rec_extra.items()}
        shape = saved.shape
        positions, values, los = np.empty(shape + (3,)), np.empty((3,) + shape), np.empty(shape, dtype=bool)
        sim_kernels.gather_new_records(
            saved, self.used, view.positions_m, view.los, self.rec_range, self.rec_az, self.rec_el, positions, values[0], values[1], values[2], los
        )
        meas = est.Measurements(
            positions_m=positions,
            range_m=values[0],
            azimuth_rad=values[1],
            elevation_rad=values[2],
            los=los,
            extra_values=extra,
        )
        if self.faults is not None and self.rec_extra:
            late = self.faults.late_steps
            meas = _with_late_records(meas, late, self.positions, self.rec_range, self.rec_az, self.rec_el, self.rec_los, self.rec_extra)
        elif self.faults is not None:
            meas = self._with_late_records(meas)
        if not isinstance(self.state, power.PowerEstimatorState):
            self.state = est.update(self.state, meas, self.channel, self.estimator_config, self.components, overwrite=True)
        elif self.unknown_power is not None:  # the source's power unknown (planner.radio)
            joint = power.update(self.state, meas, self.channel, self.estimator_config, self.unknown_power, self.components)
            self.state = joint
            if self.offsets_db is not None:
                self.offsets_db[k] = joint.offset_db
        self.estimates[k] = self.state.estimate_m
        err = self.state.estimate_m - src
        self.est_err[k] = np.sqrt((err * err).sum(-1))
        self.observable[k] = self.state.observable

    def _with_late_records(self, meas: est.Measurements) -> est.Measurements:
        """:func:`_with_late_records` with range and bearing only, in compiled loops."""
        late = self.faults.late_steps if self.faults is not None else None
        width = 0 if late is None else sim_kernels.late_record_count(late)
        if late is None or width == 0:
            return meas
        M, N = late.shape[1:3]
        positions, values, los = np.empty((M, N, width, 3)), np.empty((3, M, N, width)), np.empty((M, N, width), dtype=bool)
        rec = (self.positions, self.rec_range, self.rec_az, self.rec_el, self.rec_los)
        sim_kernels.gather_late_records(late, *rec, positions, values[0], values[1], values[2], los)
        return est.Measurements(
            positions_m=np.concatenate([meas.positions_m, positions], axis=-2),
            range_m=np.concatenate([meas.range_m, values[0]], axis=-1),
            azimuth_rad=np.concatenate([meas.azimuth_rad, values[1]], axis=-1),
            elevation_rad=np.concatenate([meas.elevation_rad, values[2]], axis=-1),
            los=np.concatenate([meas.los, los], axis=-1),
            extra_values=meas.extra_values,
        )

    def _plan(self, k: int, src: FloatArray, view: _View) -> StepResult:
        """4. Planning step from the view and each drone's carried state (shared with the planner
        node, planner.agent.plan): every trial and drone in one call of each kernel."""
        M, N = self.pos.shape[:2]
        scene = StepScene(
            step_index=k,
            own_index=self.own_index,
            own_position_m=self.pos,
            own_range_m=self.rec_range[k],
            own_los=self.rec_los[k],
            view_positions_m=view.positions_m,
            view_valid=view.have,
            view_los=view.los,
            saved_steps=view.saved,
            hops=view.hops,
            estimate_m=self.state.estimate_m,
            information=self.state.information,
            observable=self.state.observable,
            perturbation_uniforms=self.ctrl_u[k],
            lost_contact=None if view.cut is None else np.broadcast_to(view.cut, (M, N, N)),
        )
        oracle = src if self.oracle_estimate else None
        offset = power.planning_offset(self.state)  # None with the power known
        planned = self.plan_step(self.config, scene, self.drone, oracle_source=oracle, oracle_slow=self.source_slow, power_offset=offset)
        self.drone = planned.state
        step = planned.step
        self.fallback[k] = step.singular
        self.filtered[k] = step.filtered
        self.loiter[k] = planned.loiter
        self.active_counts[k] = step.active.reshape(-1, 4).sum(0)
        return step

    def _accuracy(self, k: int, src: FloatArray, view: _View, observer: Callable[[SimStep], None] | None) -> None:
        """5. Accuracy at the true source with the positions known to each drone (eq. 18)."""
        extra_view = {name: mask & view.have for name, mask in self.extra_masks.items()}
        rng, brg = self.rng_view & view.have, self.brg_view & view.have
        if self.offsets_db is None and self.true_offset == 0.0 and not extra_view:
            self.peb[k] = self._view_pebs(src, view, rng, brg)
        elif self.offsets_db is None and self.true_offset == 0.0:
            J_true = fisher_information(src, view.positions_m, rng, brg, view.los, self.channel, extra_view, self.components)
            self.peb[k] = _position_error_bound(J_true)
        else:
            # The true channel's information (offset b); with the power unknown, its Schur complement.
            J4 = fisher_information_unknown_power(
                src, view.positions_m, rng, brg, view.los, self.channel, self.true_offset, extra_view, self.components
            )
            self.peb[k] = position_error_bound_unknown_power(J4)[0] if self.offsets_db is not None else _position_error_bound(J4[..., :3, :3])
        if observer is not None:
            observer(SimStep(k, self.positions[k], self.state.estimate_m, view.positions_m, view.have, view.los))

    def _view_pebs(self, src: FloatArray, view: _View, rng: NDArray[np.bool_], brg: NDArray[np.bool_]) -> FloatArray:
        """PEB (eq. 18, m) of every drone's view with range and bearing only, (M, N): the FIM
        kernel of :func:`planner.fim.fisher_information` once per distinct view (the drones of a
        trial holding the same records share it, :func:`planner.sim_kernels.same_views`)."""
        M, N = rng.shape[:2]
        first = np.empty((M, N), dtype=np.int64)
        sim_kernels.same_views(view.saved, first)
        flat = (first + (np.arange(M) * N)[:, None]).reshape(-1)
        distinct = np.flatnonzero(flat == np.arange(M * N))
        J = np.zeros((distinct.size, 3, 3))
        src_b = np.empty((distinct.size, 3))
        src_b[:] = src
        rows = (view.positions_m.reshape(M * N, N, 3)[distinct], rng.reshape(M * N, N)[distinct], brg.reshape(M * N, N)[distinct])
        K.fim_batch(src_b, *rows, view.los.reshape(M * N, N)[distinct].astype(float), self.channel.kernel_array, J)
        return _position_error_bound(J)[np.searchsorted(distinct, flat)].reshape(M, N)

    def _move(self, k: int, step: StepResult) -> None:
        """The drones fly their steps: positions at step k + 1."""
        pos = step.next_position
        if self.float32_positions:
            # The vehicle lands on the float32 setpoint; the drone keeps its planned step as
            # its previous direction (its carried state), as the planner node does.
            pos = pos.astype(np.float32).astype(np.float64)
        self.pos = pos
        self.positions[k + 1] = pos

    def result(self, t0: float) -> SimulationResult:
        """The :class:`SimulationResult` of the steps run (``t0``: ``time.perf_counter()`` at
        the start, for the runtime)."""
        margins = safety_margins(self.positions, self.sources, self.config.limits, self.bmin, self.bmax)
        return SimulationResult(
            spec=self.spec,
            positions_m=self.positions,
            estimates_m=self.estimates,
            estimate_error_m=self.est_err,
            observable=self.observable,
            peb_m=self.peb,
            source_m=self.sources,
            margins_m=margins,
            active=self.active_counts,
            singular_fallback=self.fallback,
            filtered=self.filtered,
            loiter=self.loiter,
            record_ages=self.ages,
            runtime_s=time.perf_counter() - t0,
            extra=_extra(self.oracle_estimate, self.float32_positions, self.faults),
            power_offset_db=self.offsets_db,
        )


def simulate(
    spec: RunSpec,
    progress: Callable[[int], None] | None = None,
    estimator_config: est.EstimatorConfig | None = None,
    oracle_estimate: bool = False,
    float32_positions: bool = False,
    observer: Callable[[SimStep], None] | None = None,
    sensing: SensingTable = SENSING,
) -> SimulationResult:
    """Run ``spec.trials`` trials of ``spec.steps`` steps of a mission in this process.

    Args:
        spec: the mission and run overrides (criterion, trials, steps).
        progress: called with the number of steps just completed (for a progress bar).
        estimator_config: estimator tuning; default: static source, all measurements; a moving
            source gets a forgetting factor.
        oracle_estimate: plan with the true source instead of each drone's estimate (the
            paper's assumption that the estimate is given); the estimator still runs and its
            error is still recorded.
        float32_positions: round every new position to float32, as a MAVLink position setpoint
            is (the ideal simulated vehicle lands exactly on it): a lockstep distributed run
            then computes the same numbers (docs/distributed.md).
        observer: called at every step with a :class:`SimStep` (the live view); it must not
            change the arrays.
        sensing: the role table and component registry the mission's roles refer to
            (:data:`planner.sensing.SENSING`; a larger table flies a component registered
            outside it, e.g. in a test).

    Returns:
        The :class:`SimulationResult`.
    """
    t0 = time.perf_counter()
    sim = _Simulation(spec, estimator_config, oracle_estimate, float32_positions, sensing)
    for k in range(spec.steps):
        sim.step(k, observer)
        if progress is not None:
            progress(1)
    return sim.result(t0)


def _extra(oracle_estimate: bool, float32_positions: bool, faults: FaultBuffer | None) -> dict[str, float]:
    """The run's flags and, with injected faults, the fraction of peer records lost."""
    extra = {"oracle_estimate": float(oracle_estimate), "float32_positions": float(float32_positions)}
    if faults is not None:
        extra["fault_lost_fraction"] = faults.lost / max(faults.decided, 1)
        extra["fault_lost"], extra["fault_decided"] = float(faults.lost), float(faults.decided)  # chunks of a run add up
    return extra


def fault_penalty(mission: Mission, result: SimulationResult, baseline: SimulationResult | PenaltyReference | None = None) -> dict[str, float | None]:
    """PEB penalty of the injected loss and delay: ``result`` (run with ``mission.comms.faults``)
    against the same mission without faults (:func:`missions.study.records.fault_penalty_against`,
    which says what it returns).

    The baseline, unless given (a fault-free result or its :class:`PenaltyReference`), is
    simulated in this process with the same criterion, trials, steps and flags as ``result``; a
    distributed run (``result.extra['distributed']``) is compared with the float32-position
    simulation, which equals a fault-free distributed run to 1e-7 m (docs/distributed.md).
    """
    if baseline is None:
        flags = result.extra
        baseline = simulate(
            dataclasses.replace(result.spec, mission=without_faults(mission)),
            oracle_estimate=bool(flags.get("oracle_estimate", 0.0)),
            float32_positions=bool(flags.get("float32_positions", 0.0) or flags.get("distributed", 0.0)),
        )
    return fault_penalty_against(mission, result, baseline)


def safety_margins(
    positions: FloatArray,
    sources: FloatArray,
    limits: Limits,
    boxes_min: FloatArray,
    boxes_max: FloatArray,
    kinematic_tol: float = KINEMATIC_TOL,
) -> dict[str, FloatArray]:
    """Margins of every safety constraint after each step, from the true trajectories.

    Args:
        positions: (K+1, M, N, 3) true positions, m, ENU. sources: (K+1, 3) true source.
        limits, boxes_min, boxes_max: the mission's.
        kinematic_tol: tolerance of the speed and turn-rate accounting (m, rad): float64
            round-off here; positions reported over MAVLink are float32
            (:data:`MAVLINK_KINEMATIC_TOL`).

    Returns:
        Per family of :data:`SAFETY_FAMILIES`, (K, M, N): the margin of the position after
        step k (distance minus its safety distance for uav/source/obstacle, distance inside the
        altitude box) and of step k itself (slack to the speed bounds and to the heading and
        tilt change limits). Negative is a violation.
    """
    nxt = positions[1:]
    u = np.diff(positions, axis=0)
    out = {name: np.empty(nxt.shape[:-1]) for name in SAFETY_FAMILIES}
    nearest = np.empty(nxt.shape[:-1])
    sim_kernels.nearest_peer_distance(_contiguous(nxt), nearest)
    out["uav"] = nearest - limits.d_uav_m
    out["source"] = np.linalg.norm(nxt - sources[1:, None, None, :], axis=-1) - limits.d_source_m
    out["obstacle"] = distance_to_boxes(nxt, boxes_min, boxes_max) - limits.d_obstacle_m
    out["altitude"] = np.minimum(nxt[..., 2] - limits.z_min_m, limits.z_max_m - nxt[..., 2])
    speed = np.sqrt((u * u).sum(-1))
    out["speed"] = np.minimum(speed - limits.step_min_m, limits.step_max_m - speed) + kinematic_tol
    out["turn_rate"] = _turn_margin(u, speed, limits, kinematic_tol) + KINEMATIC_TOL
    return out


def _previous(x: FloatArray) -> FloatArray:
    """The value of the step before, along the step axis (K, ...): zero before the first."""
    return np.concatenate([np.zeros((1,) + x.shape[1:]), x[:-1]], axis=0)


def _turn_margin(u: FloatArray, length: FloatArray, limits: Limits, position_tol_m: float = 0.0) -> FloatArray:
    """Slack (rad) of the heading and tilt change limits of eq. 2 between each step u (K, ..., 3)
    and the one before (a zero step before the first); +inf on the first step. ``length``: |u|.

    ``position_tol_m`` is the position uncertainty of the recorded trajectory (float32 over
    MAVLink): it becomes an angle tolerance of tol / (length of the shorter step), horizontal
    length for the heading, whole length for the tilt. Each step's angles are computed once and
    shifted by one step for the step before.
    """
    has_prev = _previous(length) > 0.0
    psi1 = np.arctan2(u[..., 1], u[..., 0])
    rho1 = np.hypot(u[..., 0], u[..., 1])
    th1 = np.arctan2(u[..., 2], rho1)
    psi0, th0 = _previous(psi1), _previous(th1)
    dpsi = np.abs((psi1 - psi0 + np.pi) % (2.0 * np.pi) - np.pi)
    rho = np.minimum(_previous(rho1), rho1)
    length = np.minimum(_previous(length), length)
    # The heading of a vertical step is undefined: no heading limit applies across it.
    vertical = rho < max(1e-9, 100.0 * position_tol_m)
    dpsi = np.where(vertical, 0.0, dpsi)
    heading_tol = 2.0 * position_tol_m / np.maximum(rho, 1e-300)
    tilt_tol = 2.0 * position_tol_m / np.maximum(length, 1e-300)
    slack = np.minimum(limits.heading_change_max_rad - dpsi + heading_tol, limits.tilt_change_max_rad - np.abs(th1 - th0) + tilt_tol)
    return np.where(has_prev, slack, np.inf)
