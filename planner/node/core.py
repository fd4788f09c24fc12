"""One step of one planner, the same for both clocks (docs/distributed.md, "The planner node"): own record (position and
measurement) → publish it → collect the peers' records → delayed view → source estimate →
control step (:func:`planner.agent.plan`, the function the in-process simulator runs) →
setpoint → status and ``Done``. The drivers (:mod:`planner.node.lockstep`,
:mod:`planner.node.realtime`) say when a step starts, where the drone is, what it measured, how
long the peers are awaited and how the setpoint goes out."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from comms.latency import DelayedView
from comms.messages import Record, Status
from planner import estimator as est
from planner.agent import measurements_from_records, plan, records_as_arrays
from planner.geometry import vec3
from planner.node.config import NodeConfig
from planner.node.steplog import StepLog, replay_step_logs
from planner.node.swarm import Swarm
from planner.radio import power_estimator as power
from planner.randomness import CONTROL_DRAWS, control_rng
from planner.step import OWN_TRACK_STEPS as OWN_TRACK_STEPS  # re-exported by planner.node
from planner.step import DroneState, StepScene


def build_view(config: NodeConfig) -> DelayedView:
    """The node's delayed view of its peers' records (hop latency, injected faults)."""
    v = config.view
    return DelayedView(config.drone_index, config.drone_count, v.d_hop_m, v.h_max, emulate=v.emulate, faults=v.faults, seed=v.seed)


@dataclass(frozen=True)
class OwnMeasurement:
    """This drone's measurement of a step, as its record carries it.

    Attributes:
        los: line of sight. range_m: range (m; NaN: none). azimuth_rad, elevation_rad:
            bearing (rad, ENU; NaN: none).
        extra_values: the values of the components beyond range and bearing, by value name
            (NaN or absent: none; only the drone's own components' are recorded).
    """

    los: bool
    range_m: float
    azimuth_rad: float
    elevation_rad: float
    extra_values: Mapping[str, float] = field(default_factory=lambda: MappingProxyType({}))


@dataclass(frozen=True)
class StepOutcome:
    """What one step did.

    Attributes:
        record: this drone's record of the step.
        view: the delayed view the step planned on. rows: records fed to the estimator.
        result: the plan (:func:`planner.agent.plan`).
        sent: whether the setpoint went out (False: the drone was taken over meanwhile).
        published_s, peers_in_s, sent_s: the driver's clock after the own record was
            published, after the peers' records were collected, after the setpoint was sent.
    """

    record: Record
    view: Any
    rows: int
    result: Any
    sent: bool
    published_s: float
    peers_in_s: float
    sent_s: float


class StepCore:
    """The planning state of one drone and its step (see the module doc).

    Args:
        config: the node's configuration. view: its delayed view (shared with the swarm's
        record handler). swarm: where records, status and ``Done`` go. step_log: the step log.
    """

    def __init__(self, config: NodeConfig, view: DelayedView, swarm: Swarm, step_log: StepLog | None = None) -> None:
        import planner.node.warm  # noqa: F401  # the compiled planning step, loaded before the first step (not during it)

        self.config = config
        self.view = view
        self.swarm = swarm
        self.step_log = step_log
        self.planner = config.planner
        self.index = config.drone_index
        self.count = config.drone_count
        self.ctrl_rng = control_rng(config.seed, 0, self.index)
        #: The source estimator's state (the joint one of planner.radio with the power unknown).
        self.state: power.SourceEstimatorState = power.initial_source_state((), self.planner)
        est.warm_up(self.planner.estimator)  # the compiled estimator loaded before the first step
        #: Per drone, the newest step fed to the estimator.
        self.used_steps = np.full(self.count, -1, dtype=np.int64)
        #: What this drone carries from one planning step to the next (its last displacement, own
        #: range window, loiter, keep-out, peers' drift, own track): planner.step.DroneState, the
        #: same value the in-process simulator carries for each of its drones.
        self.drone = DroneState.initial((), self.count)
        #: This drone's last own record.
        self.last_record: Record | None = None
        #: The value names of this drone's components beyond range and bearing (its record's
        #: extension, comms.messages).
        self.own_extra_value_names = tuple(
            name for c in self.planner.sensing.extra_components if self.planner.component_masks[c.name][self.index] for name in c.value_names
        )

    def step(
        self,
        k: int,
        t_s: float,
        own_m: np.ndarray,
        measurement: OwnMeasurement,
        now: Callable[[], float],
        collect_peers: Callable[[int], None],
        send_setpoint: Callable[[np.ndarray, Any], bool],
    ) -> StepOutcome:
        """Step ``k`` at time ``t_s`` (lockstep: mission s; real time: UNIX s) from own
        position ``own_m`` (m, ENU): record, publish, ``collect_peers(k)``, view, estimate,
        plan, ``send_setpoint(own_m, plan)`` (False: not sent, the step ends without status),
        then status and ``Done(k)``. ``now`` stamps the stages (the driver's clock)."""
        record = self.own_record(k, t_s, own_m, measurement)
        self.swarm.publish_record(record)
        published_s = now()
        collect_peers(k)
        peers_in_s = now()
        view, rows, result = self.view_estimate_plan(k, own_m)
        if not send_setpoint(own_m, result):
            self.drone = self.drone.without_step()
            return StepOutcome(record, view, rows, result, False, published_s, peers_in_s, now())
        sent_s = now()
        step = result.step
        active_mask = int(sum(1 << b for b, a in enumerate(np.asarray(step.active)) if a))
        state = self.state
        status = Status(
            self.config.uav,
            k,
            t_s,
            vec3(state.estimate_m),
            bool(state.observable),
            bool(step.singular),
            active_mask,
            tuple(int(s) for s in view.saved_steps),
        )
        self.swarm.publish_status(status)
        self.swarm.publish_done(k)
        return StepOutcome(record, view, rows, result, True, published_s, peers_in_s, sent_s)

    def log_step(self, k: int, t_s: float, own_m: np.ndarray, outcome: StepOutcome, timing: dict[str, float]) -> None:
        """Write step ``k`` to the step log with the driver's ``timing`` (wall s)."""
        if self.step_log is not None:
            self.step_log.write_step(k, t_s, own_m, outcome.record, outcome.view, self.state, outcome.result, outcome.rows, timing)

    @property
    def prev_step_m(self) -> np.ndarray:
        """The last step's displacement (m, ENU); zero after a step without a command."""
        return self.drone.previous_step_m

    @prev_step_m.setter
    def prev_step_m(self, value: np.ndarray) -> None:
        if np.any(np.asarray(value) != 0.0):
            raise ValueError("prev_step_m: only a step without a command (zeros) is set from outside the planning step")
        self.drone = self.drone.without_step()

    def own_record(self, k: int, t_s: float, own_m: np.ndarray, measurement: OwnMeasurement) -> Record:
        """This drone's record of step ``k``, entered in its own view (the planning step enters it
        in the drone's range window and track)."""
        record = Record(
            self.config.uav,
            k,
            t_s,
            vec3(own_m),
            bool(self.planner.ranging[self.index]),
            bool(self.planner.bearing[self.index]),
            measurement.los,
            measurement.range_m,
            measurement.azimuth_rad,
            measurement.elevation_rad,
            extra_values=self._own_extra(measurement.extra_values),
        )
        self.last_record = record
        self.view.add(record)
        return record

    def taken_over_record(self, k: int, t_s: float, position_m: np.ndarray) -> Record:
        """The record of step k while a pilot flies the drone: its position (m, ENU) at time
        ``t_s``, flagged taken over, without a measurement (the pilot's flight is no planned
        sensing)."""
        nan = float("nan")
        return Record(
            self.config.uav,
            k,
            t_s,
            vec3(position_m),
            bool(self.planner.ranging[self.index]),
            bool(self.planner.bearing[self.index]),
            True,
            nan,
            nan,
            nan,
            taken_over=True,
            extra_values=self._own_extra({}),
        )

    def _own_extra(self, values: Mapping[str, float]) -> Mapping[str, float]:
        """This drone's values of its components beyond range and bearing from ``values`` (NaN
        where absent), read-only; empty for a drone of range and bearing only."""
        nan = float("nan")
        return MappingProxyType({name: float(values.get(name, nan)) for name in self.own_extra_value_names})

    def track(self, k: int, own_m: np.ndarray) -> None:
        """Remember the own position (m, ENU) of a step k this drone does not plan (a pilot flies it)."""
        self.drone = self.drone.tracked(k, np.asarray(own_m, dtype=float))

    def skip_control_draws(self, steps: int) -> None:
        """Advance the control stream past ``steps`` steps not planned (taken over, rejoined
        later), so the draws of a later step stay those of its step. The last planned step's
        keep-out is forgotten: the first step planned again is not rate-limited against it."""
        self.ctrl_rng.random(steps * CONTROL_DRAWS)
        self.drone = self.drone.without_keepout()

    def view_estimate_plan(self, k: int, own_m: np.ndarray) -> tuple[Any, int, Any]:
        """Step k after the records are in: delayed view, source estimate (with the records
        not used before), control step. Returns (view, new rows, plan)."""
        view = self.view.advance(k)
        self.state, rows = self._estimate(view)
        self.used_steps = np.maximum(self.used_steps, view.saved_steps)
        result = self._plan(k, own_m, view)
        self.drone = result.state
        return view, rows, result

    def _estimate(self, view: Any) -> tuple[power.SourceEstimatorState, int]:
        """Feed the estimator the view's records new since :attr:`used_steps` (one row per
        drone, in drone order) and then the peers' records that arrived late, after a newer one
        (``view.late_records``: old evidence about the source is still evidence), in the
        order of the in-process simulator. Returns the state and the number of rows fed."""
        new = view.saved_steps > self.used_steps
        late = view.late_records
        fed = [rec if rec is not None and new[j] else None for j, rec in enumerate(view.records)] + list(late)
        sensing = self.planner.sensing
        meas = measurements_from_records(fed, sensing.extra_value_names)
        return power.update_source(self.state, meas, self.planner), int(new.sum()) + len(late)

    def _plan(self, k: int, own_m: np.ndarray, view: Any) -> Any:
        """The planning step (planner.agent.plan) of step k from the view, the own record of the step
        and the drone's carried state."""
        positions, valid, los = records_as_arrays(view.records)
        # Peers whose planner left the liveliness view (a partition, not distance): kept apart
        # by the bisector planes of the step of their last record (planner.agent.plan).
        left = self.swarm.left
        lost = np.array([j + 1 in left and valid[j] for j in range(self.count)], dtype=bool)
        record = self.last_record
        if record is None:
            raise RuntimeError("StepCore._plan: no own record of the step")
        state = self.state
        scene = StepScene(
            step_index=k,
            own_index=np.array(self.index),
            own_position_m=np.asarray(own_m, dtype=float),
            own_range_m=np.array(record.range_m, dtype=float),
            own_los=np.array(record.los),
            view_positions_m=positions,
            view_valid=valid,
            view_los=los,
            saved_steps=np.where(valid, np.asarray(view.saved_steps), -1),
            hops=np.asarray(view.hops),
            estimate_m=np.asarray(state.estimate_m, dtype=float),
            information=np.asarray(state.information, dtype=float),
            observable=np.asarray(state.observable),
            perturbation_uniforms=self.ctrl_rng.random(CONTROL_DRAWS),
            lost_contact=lost,
        )
        return plan(self.planner, scene, self.drone, power_offset=power.planning_offset(state))

    def rebuild(self, first: int, rows_by_drone: Mapping[int, Sequence[dict[str, Any]]]) -> dict[int, list[tuple[int, np.ndarray, float, bool]]]:
        """A rejoining planner's estimator, own-range window, own track and used steps, from
        its predecessor's step log and its peers' logs (drone index → rows) for the steps
        before ``first`` (:func:`~planner.node.steplog.replay_step_logs`). Returns the replayed
        steps per drone index."""
        self.state, done = replay_step_logs(
            self.state,
            rows_by_drone,
            self.count,
            first,
            self.planner.channel,
            self.planner.estimator,
            self.planner.sensing,
            lambda state, meas: power.update_source(state, meas, self.planner),
        )
        self.drone = self.drone.replayed(done.get(self.index, []))
        for j, steps in done.items():
            if steps:
                self.used_steps[j] = steps[-1][0]
        return done
