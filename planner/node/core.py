"""One step of one planner, the same for both clocks (docs/distributed.md, "The planner node"): own record (position and
measurement) → publish it → collect the peers' records → delayed view → source estimate →
control step (:func:`planner.agent.plan`, the function the in-process simulator runs) →
setpoint → status and ``Done``. The drivers (:mod:`planner.node.lockstep`,
:mod:`planner.node.realtime`) say when a step starts, where the drone is, what it measured, how
long the peers are awaited and how the setpoint goes out."""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from types import MappingProxyType
from typing import Any

import numpy as np

from comms.latency import DelayedView
from comms.messages import Record, Status
from planner import estimator as est
from planner.agent import OWN_RANGE_WINDOW, PeerDrift, PlanView, measurements_from_records, own_ranges, plan
from planner.geometry import vec3
from planner.node.config import NodeConfig
from planner.node.steplog import StepLog, replay_step_logs
from planner.node.swarm import Swarm
from planner.randomness import CONTROL_DRAWS, control_rng

#: Steps of own positions a planner keeps (the partition planes need the step of a peer's
#: last record; for a peer silent for longer the plane is drawn from the current position).
OWN_TRACK_STEPS = 5000


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
        self.config = config
        self.view = view
        self.swarm = swarm
        self.step_log = step_log
        self.planner = config.planner
        self.index = config.drone_index
        self.count = config.drone_count
        self.ctrl_rng = control_rng(config.seed, 0, self.index)
        self.state = est.initial_state((), self.planner.estimator)
        est.warm_up(self.planner.estimator)  # the compiled estimator loaded before the first step
        #: Per drone, the newest step fed to the estimator.
        self.used_steps = np.full(self.count, -1, dtype=np.int64)
        #: The last step's displacement (m, ENU); zero after a step without a command.
        self.prev_step_m = np.zeros(3)
        #: This drone's own last ranges and LOS flags (the second source keep-out, planner.agent).
        self.own_ranges: deque[tuple[float, bool]] = deque(maxlen=OWN_RANGE_WINDOW)
        #: This drone loitered at its last planned step (planner.agent.must_loiter).
        self.loitering = False
        #: This drone's keep-out of its last planned step (centre, radius), planner.agent.plan.
        self.last_keepout: tuple[np.ndarray, np.ndarray] | None = None
        #: Each peer's last step from this drone's records of it (planner.agent.PeerDrift).
        self.peer_drift = PeerDrift.empty((self.count,))
        #: This drone's own positions by step (m, ENU), the last OWN_TRACK_STEPS: where it was
        #: when each peer's last record was taken (the partition planes, planner.agent.plan).
        self.own_track: dict[int, np.ndarray] = {}
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
            self.prev_step_m = np.zeros(3)
            return StepOutcome(record, view, rows, result, False, published_s, peers_in_s, now())
        sent_s = now()
        step = result.step
        self.prev_step_m = np.asarray(step.displacement, dtype=float)
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

    def own_record(self, k: int, t_s: float, own_m: np.ndarray, measurement: OwnMeasurement) -> Record:
        """This drone's record of step ``k``, entered in its own view, range window and track."""
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
        self.own_ranges.append((record.range_m, record.los))
        self.track(k, own_m)
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
        """Remember the own position of step k (the last OWN_TRACK_STEPS steps)."""
        self.own_track[k] = np.array(own_m, dtype=float)
        self.own_track.pop(k - OWN_TRACK_STEPS, None)

    def skip_control_draws(self, steps: int) -> None:
        """Advance the control stream past ``steps`` steps not planned (taken over, rejoined
        later), so the draws of a later step stay those of its step. The last planned step's
        keep-out is forgotten: the first step planned again is not rate-limited against it."""
        self.ctrl_rng.random(steps * CONTROL_DRAWS)
        self.last_keepout = None

    def view_estimate_plan(self, k: int, own_m: np.ndarray) -> tuple[Any, int, Any]:
        """Step k after the records are in: delayed view, source estimate (with the records
        not used before), control step. Returns (view, new rows, plan)."""
        view = self.view.advance(k)
        self.state, rows = self._estimate(view)
        self.used_steps = np.maximum(self.used_steps, view.saved_steps)
        result = self._plan(k, own_m, view)
        self.loitering = bool(np.asarray(result.loiter))
        self.last_keepout = (result.keepout_centre_m, result.keepout_m)
        return view, rows, result

    def _estimate(self, view: Any) -> tuple[est.EstimatorState, int]:
        """Feed the estimator the view's records new since :attr:`used_steps` (one row per
        drone, in drone order) and then the peers' records that arrived late, after a newer one
        (``view.late_records``: old evidence about the source is still evidence), in the
        order of the in-process simulator. Returns the state and the number of rows fed."""
        new = view.saved_steps > self.used_steps
        late = view.late_records
        fed = [rec if rec is not None and new[j] else None for j, rec in enumerate(view.records)] + list(late)
        sensing = self.planner.sensing
        meas = measurements_from_records(fed, sensing.extra_value_names)
        return est.update(self.state, meas, self.planner.channel, self.planner.estimator, sensing.components), int(new.sum()) + len(late)

    def _plan(self, k: int, own_m: np.ndarray, view: Any) -> Any:
        plan_view = PlanView.from_records(self.index, view.records, view.saved_steps, k, view.hops)
        self.peer_drift = self.peer_drift.update(plan_view.positions_m, view.saved_steps, plan_view.valid)
        plan_view = replace(plan_view, drift_m=self.peer_drift.drift_m)
        # Peers whose planner left the liveliness view (a partition, not distance): kept apart
        # by the bisector planes of the step of their last record (planner.agent.plan).
        left = self.swarm.left
        lost = np.array([j + 1 in left and plan_view.valid[j] for j in range(self.count)], dtype=bool)
        own_then = None
        if lost.any():
            own_then = np.array([self.own_track.get(int(view.saved_steps[j]), own_m) for j in range(self.count)], dtype=float)
        uniforms = self.ctrl_rng.random(CONTROL_DRAWS)
        own = own_ranges(
            np.array([r for r, _ in self.own_ranges], dtype=float), np.array([los for _, los in self.own_ranges], dtype=bool), self.planner.channel
        )
        return plan(
            self.planner,
            own_m,
            self.prev_step_m,
            plan_view,
            self.state,
            uniforms,
            step_index=k,
            own_ranges=own,
            loitering=self.loitering,
            last_keepout=self.last_keepout,
            lost_contact=lost if own_then is not None else None,
            own_then_m=own_then,
        )

    def rebuild(self, first: int, rows_by_drone: Mapping[int, Sequence[dict[str, Any]]]) -> dict[int, list[tuple[int, np.ndarray, float, bool]]]:
        """A rejoining planner's estimator, own-range window, own track and used steps, from
        its predecessor's step log and its peers' logs (drone index → rows) for the steps
        before ``first`` (:func:`~planner.node.steplog.replay_step_logs`). Returns the replayed
        steps per drone index."""
        self.state, done = replay_step_logs(
            self.state, rows_by_drone, self.count, first, self.planner.channel, self.planner.estimator, self.planner.sensing
        )
        for step, pos, rng, los in done.get(self.index, []):
            self.own_ranges.append((rng, los))
            self.track(step, pos)
        for j, steps in done.items():
            if steps:
                self.used_steps[j] = steps[-1][0]
        return done
