"""The results of a ``fimnav launch`` run: the run as a one-trial :class:`SimulationResult`, with
the same accounting as the in-process simulator, from the planners' step logs completed by what
the launcher heard over Zenoh; and the take-overs the planners report.

The planners' step logs (``OUT/logs/planner_<i>.jsonl``) are the authoritative record of what
each planner saw and did (a Zenoh message published just before a planner exits can be lost; its
own log cannot).
"""

from __future__ import annotations

import contextlib
import json
from pathlib import Path
from typing import Any

import numpy as np

from comms.messages import Record, Status
from missions.format.schema import Mission
from missions.launch.collect import Collected
from missions.launch.view_peb import peb_of_view
from missions.study.simulator import MAVLINK_KINEMATIC_TOL, RunSpec, SimulationResult, safety_margins
from planner.config import PlannerConfig
from planner.radio.power_offset import offset_of_power_db

#: Step logs by (step, drone id): each a planner's JSON step log entry.
StepLogs = dict[tuple[int, int], dict[str, Any]]
#: A planner's step by (step, drone id): (estimate m ENU, observable, singular, filtered,
#: saved steps of its view, active constraints [uav, source, obstacle, altitude], loiter).
PlannerSteps = dict[tuple[int, int], tuple[Any, ...]]

#: The active-constraint names of a step log, in the order of SimulationResult.active.
ACTIVE_NAMES: tuple[str, ...] = ("uav", "source", "obstacle", "altitude")


def step_logs_of(out: Path, j: int) -> StepLogs:
    """Planner ``j``'s step log entries by (step, j), from ``out/logs/planner_<j>.jsonl`` (a
    line cut by a killed planner is skipped; no file: none)."""
    found: StepLogs = {}
    path = out / "logs" / f"planner_{j}.jsonl"
    with contextlib.suppress(OSError):
        for line in path.read_text().splitlines():
            try:
                entry = json.loads(line)
                found[(int(entry["step"]), j)] = entry
            except (ValueError, KeyError, TypeError):
                continue  # a line cut by a killed planner
    return found


def step_logs(out: Path, n: int) -> StepLogs:
    """Every planner's step log entries by (step, drone id), drones 1..n."""
    found: StepLogs = {}
    for j in range(1, n + 1):
        found.update(step_logs_of(out, j))
    return found


def taken_over(out: Path, n: int) -> dict[str, list[dict[str, Any]]]:
    """Drone id → its planner's take-overs (``{"step", "mode", "handed_back_step"?}``), from
    the summary line that ends each planner's log (a pilot or ground station switched its
    vehicle out of GUIDED/OFFBOARD; docs/in-the-field.md)."""
    found: dict[str, list[dict[str, Any]]] = {}
    for i in range(1, n + 1):
        try:
            lines = (out / "logs" / f"planner_{i}.log").read_text().strip().splitlines()
            last = json.loads(lines[-1]) if lines else None
        except (OSError, ValueError):
            continue
        if isinstance(last, dict) and last.get("taken_over"):
            found[str(i)] = last["taken_over"]
    return found


def _records(mission: Mission, heard: dict[tuple[int, int], Record], logs: StepLogs) -> dict[tuple[int, int], Record]:
    """Records (position where measured, LOS) of every drone and step: those heard, replaced by
    the step logs' where a planner logged the step."""
    recs: dict[tuple[int, int], Record] = dict(heard)
    nan = float("nan")
    ranging, bearing = mission.drones.ranging_mask(), mission.drones.bearing_mask()
    for (k, j), e in logs.items():
        recs[(k, j)] = Record(
            j,
            k,
            float(e.get("t_s", nan)),
            tuple(e["position_m"]),
            bool(ranging[j - 1]),
            bool(bearing[j - 1]),
            bool(e["measurement"]["los"]),
            nan,
            nan,
            nan,
        )
    return recs


def _positions(recs: dict[tuple[int, int], Record], logs: StepLogs, n: int, K: int) -> np.ndarray:
    """Positions, shape (K + 1, 1, n, 3), m ENU: each step's record, and after the last step
    the position each planner commanded (nan: not known)."""
    positions = np.full((K + 1, 1, n, 3), np.nan)
    for (k, j), r in recs.items():
        if 0 <= k < K:
            positions[k, 0, j - 1] = r.position_m
    for j in range(1, n + 1):
        last = logs.get((K - 1, j))
        if last is not None:
            positions[K, 0, j - 1] = last["next_position_m"]
    return positions


def _planner_steps(status: dict[tuple[int, int], Status], logs: StepLogs) -> PlannerSteps:
    """Each planner's steps from the statuses heard, replaced by its step log's entries."""
    steps: PlannerSteps = {}
    for (k, j), st in status.items():
        steps[(k, j)] = (st.estimate_m, st.observable, st.singular, False, st.saved_steps, [bool((st.active_mask >> b) & 1) for b in range(4)], False)
    for (k, j), e in logs.items():
        act = e.get("active", {})
        steps[(k, j)] = (
            e["estimate_m"],
            e["observable"],
            e["singular"],
            e.get("filtered", False),
            e["saved_steps"],
            [bool(act.get(name, False)) for name in ACTIVE_NAMES],
            e.get("loiter", False),
        )
    return steps


class _StepArrays:
    """The per-step arrays of a one-trial result (K steps, n drones): estimates (m ENU),
    observability, singular fallback, filtering, record ages (steps; −1: none), the view's PEB
    (m) and the count of active constraints of each kind."""

    def __init__(self, n: int, K: int) -> None:
        self.estimates = np.full((K, 1, n, 3), np.nan)
        self.observable = np.zeros((K, 1, n), dtype=bool)
        self.singular = np.zeros((K, 1, n), dtype=bool)
        self.filtered = np.zeros((K, 1, n), dtype=bool)
        self.loiter = np.zeros((K, 1, n), dtype=bool)
        self.ages = np.full((K, 1, n, n), -1, dtype=np.int16)
        self.peb = np.full((K, 1, n), np.inf)
        self.active = np.zeros((K, 4), dtype=np.int64)

    def fill(
        self, steps: PlannerSteps, recs: dict[tuple[int, int], Record], sources: np.ndarray, config: PlannerConfig, true_offset: float = 0.0
    ) -> None:
        """Enter every planner step within 0..K−1 (its view's PEB at that step's source, of
        the source's power offset ``true_offset``, :func:`missions.launch.view_peb.peb_of_view`)."""
        K = self.peb.shape[0]
        for (k, j), (est_m, obs, sing, filt, saved, act, loiter) in steps.items():
            if not 0 <= k < K:
                continue
            self.estimates[k, 0, j - 1] = est_m
            self.observable[k, 0, j - 1] = obs
            self.singular[k, 0, j - 1] = sing
            self.filtered[k, 0, j - 1] = filt
            self.loiter[k, 0, j - 1] = loiter
            self.ages[k, 0, j - 1] = [k - s if s >= 0 else -1 for s in saved]
            self.peb[k, 0, j - 1] = peb_of_view(config, saved, recs, sources[k], true_offset)
            self.active[k] += np.asarray(act, dtype=np.int64)

    def hold_taken_over(self, taken: np.ndarray, steps: PlannerSteps) -> None:
        """A drone a pilot flies (taken over) has no planner step: its estimate, observability
        and view are those of its planner's last step."""
        K = self.peb.shape[0]
        for k, _, i in zip(*np.nonzero(taken[1:K]), strict=True):
            k += 1
            if (k, i + 1) not in steps and not np.isnan(self.estimates[k - 1, 0, i]).any():
                self.estimates[k, 0, i], self.observable[k, 0, i], self.peb[k, 0, i] = (
                    self.estimates[k - 1, 0, i],
                    self.observable[k - 1, 0, i],
                    self.peb[k - 1, 0, i],
                )


def _taken_over_steps(heard: dict[tuple[int, int], Record], logs: StepLogs, n: int, K: int) -> np.ndarray:
    """Shape (K + 1, 1, n): the drone was taken over at that step (a record says so and its
    planner logged no step)."""
    taken = np.zeros((K + 1, 1, n), dtype=bool)
    for (k, j), r in heard.items():
        if 0 <= k < K and r.taken_over and (k, j) not in logs:
            taken[k, 0, j - 1] = True
    return taken


def _margins(
    mission: Mission, positions: np.ndarray, sources: np.ndarray, logs: StepLogs, not_flown: np.ndarray, realtime: bool
) -> dict[str, np.ndarray]:
    """The safety margins of the recorded positions (with a float32-sized kinematic tolerance).
    A step no planner flew (``not_flown``, shape (K, 1, n)) has no speed or turn-rate bound to
    keep: its displacement is the record's gap, not a command. In real time the kinematic
    limits apply to the commanded steps (logged), not to the sampled positions."""
    K = sources.shape[0] - 1
    bmin, bmax = mission.obstacle_bounds()
    margins = safety_margins(np.nan_to_num(positions), sources, mission.limits(), bmin, bmax, MAVLINK_KINEMATIC_TOL)
    if realtime:
        # On the wall clock, positions are sampled at each step's (jittered) start: the
        # kinematic limits apply to the commanded steps, u_k = next_k − p_k (logged).
        u = np.full(positions[:K].shape, np.nan)
        for (k, j), e in logs.items():
            if 0 <= k < K:
                u[k, 0, j - 1] = np.asarray(e["next_position_m"]) - np.asarray(e["position_m"])
        not_flown = not_flown | np.isnan(u).any(-1)
        chain = np.concatenate([np.nan_to_num(positions[:1]), np.nan_to_num(positions[:1]) + np.cumsum(np.nan_to_num(u), axis=0)])
        commanded = safety_margins(chain, sources, mission.limits(), bmin, bmax, MAVLINK_KINEMATIC_TOL)
        margins["speed"], margins["turn_rate"] = commanded["speed"], commanded["turn_rate"]
    margins["speed"][not_flown] = np.inf
    margins["turn_rate"][not_flown | np.concatenate([not_flown[:1], not_flown[:-1]])] = np.inf
    return margins


def launch_result(
    mission: Mission, planner_config: PlannerConfig, collected: Collected, logs: StepLogs, realtime: bool, runtime_s: float
) -> SimulationResult:
    """The run as a one-trial :class:`SimulationResult` (same accounting as the simulator),
    from the planners' step logs, completed by what was heard over Zenoh.

    Args:
        mission: the mission as run.
        planner_config: its planner config (for the PEB of each view).
        collected: what the launcher heard (records, statuses, dropped messages).
        logs: the planners' step logs (:func:`step_logs`).
        realtime: the run flew on the wall clock (kinematic limits on the commanded steps).
        runtime_s: the run's wall time (s).
    """
    m = mission
    n, K = m.drones.count, m.steps
    recs = _records(m, collected.records, logs)
    sources = np.array([m.source.position_at(k * m.dt_s) for k in range(K + 1)])
    positions = _positions(recs, logs, n, K)
    steps = _planner_steps(collected.status, logs)
    arrays = _StepArrays(n, K)
    true_offset = offset_of_power_db(m.source.power_offset_db, planner_config.channel.gamma)
    arrays.fill(steps, recs, sources, planner_config, true_offset)
    # A drone a pilot flies (taken over) has no planner step, and its displacements are no command.
    taken = _taken_over_steps(collected.records, logs, n, K)
    arrays.hold_taken_over(taken, steps)
    missing = np.isnan(positions).any(-1)
    if missing.any():
        # Steps a drone did not fly (it died): hold its last known position for the record.
        for k in range(1, K + 1):
            positions[k] = np.where(np.isnan(positions[k]), positions[k - 1], positions[k])
    # Steps before a drone was first heard (its planner never got it flying, e.g. an external
    # autopilot nobody answered at): no position to judge; it is placed at its start, on the
    # ground there as far as the run knows, and its own margins are not counted.
    unknown = np.isnan(positions).any(-1)
    if unknown.any():
        starts = np.asarray(m.drones.start_positions_m(), dtype=float)
        positions = np.where(unknown[..., None], starts[None, None, :, :], positions)
    # A step no planner flew (its drone lost, or its planner dead until it rejoined) has no
    # speed or turn-rate bound to keep: its displacement is the record's gap, not a command.
    not_flown = missing[:K] | missing[1:] | taken[:K] | taken[1:]
    margins = _margins(m, positions, sources, logs, not_flown, realtime)
    for family in margins:
        margins[family][unknown[1:]] = np.inf
    err = np.linalg.norm(arrays.estimates - sources[:K, None, None, :], axis=-1)
    return SimulationResult(
        spec=RunSpec(m, m.criterion, 1, K),
        positions_m=positions,
        estimates_m=np.nan_to_num(arrays.estimates),
        estimate_error_m=err,
        observable=arrays.observable,
        peb_m=arrays.peb,
        source_m=sources,
        margins_m=margins,
        active=arrays.active,
        singular_fallback=arrays.singular,
        filtered=arrays.filtered,
        loiter=arrays.loiter,
        record_ages=arrays.ages,
        runtime_s=runtime_s,
        extra={"distributed": 1.0, "dropped_messages": float(collected.dropped), "missing_drone_steps": float(missing[:K].sum())},
        power_offset_db=_offsets(logs, n, K) if planner_config.unknown_power is not None else None,
    )


def _offsets(logs: StepLogs, n: int, K: int) -> np.ndarray:
    """Shape (K, 1, n): each planner's estimate of the source's power offset (dB) at each step,
    from its step log (NaN: none), with the power unknown."""
    out = np.full((K, 1, n), np.nan)
    for (k, j), e in logs.items():
        value = e.get("power_offset_db")
        if 0 <= k < K and value is not None:
            out[k, 0, j - 1] = value
    return out
