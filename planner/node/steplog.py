"""The planner node's step log (JSON lines, one row per step flown): writing a row, reading a
log back, and replaying logged steps into the estimator (a rejoining planner)."""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from comms.messages import Record
from planner import estimator as est
from planner.params import Channel
from planner.sensing import SENSING, SensingTable


def replay_step_logs(
    state: Any,
    rows_by_drone: Mapping[int, Sequence[dict[str, Any]]],
    n: int,
    first: int,
    channel: Channel,
    config: est.EstimatorConfig,
    sensing: SensingTable = SENSING,
    update: Callable[[Any, est.Measurements], Any] | None = None,
) -> tuple[Any, dict[int, list[tuple[int, np.ndarray, float, bool]]]]:
    """Feed the records of the steps before ``first`` found in step logs to the estimator, step
    by step in order (eqs. 3-5 measurements at the logged positions, m, ENU): a rejoining
    planner's own log (its predecessor's), and its peers' logs when they are at hand (a launch
    keeps every planner's log in one results directory). A step logged twice (an earlier
    rejoin) counts once; a torn line is skipped (:func:`read_step_log`).

    Args:
        rows_by_drone: drone index (0-based) → that drone's logged rows.
        n: drones in the mission. first: the first step not to replay.
        sensing: the table of the values beyond range and bearing a row's measurement may
            carry (``extra_values``) and of the components the estimator takes them for.
        update: the estimator's call (state, records) -> state; None:
            :func:`planner.estimator.update` with ``channel``, ``config`` and ``sensing``.

    Returns:
        The updated state and, per drone index, its replayed steps as (step, position m,
        range m or NaN, LOS).
    """
    nan = np.nan
    table: dict[int, dict[int, dict[str, Any]]] = {}
    for j, rows in rows_by_drone.items():
        for r in rows:
            if 0 <= r["step"] < first:
                table.setdefault(int(r["step"]), {}).setdefault(j, r)
    done: dict[int, list[tuple[int, np.ndarray, float, bool]]] = {j: [] for j in rows_by_drone}
    for step in sorted(table):
        pos = np.full((n, 3), nan)
        rng, az, el = np.full(n, nan), np.full(n, nan), np.full(n, nan)
        los = np.zeros(n, dtype=bool)
        extra = {name: np.full(n, nan) for name in sensing.extra_value_names}
        for j, r in table[step].items():
            m = r["measurement"]
            pos[j] = r["position_m"]
            rng[j] = nan if m.get("range_m") is None else m["range_m"]
            az[j] = nan if m.get("azimuth_rad") is None else m["azimuth_rad"]
            el[j] = nan if m.get("elevation_rad") is None else m["elevation_rad"]
            los[j] = bool(m.get("los"))
            for name, value in (m.get("extra_values") or {}).items():
                if name in extra:
                    extra[name][j] = nan if value is None else value
            done[j].append((step, pos[j].copy(), float(rng[j]), bool(los[j])))
        meas = est.Measurements(positions_m=pos, range_m=rng, azimuth_rad=az, elevation_rad=el, los=los, extra_values=extra)
        state = est.update(state, meas, channel, config, sensing.components) if update is None else update(state, meas)
    return state, done


def read_step_log(path: Path) -> list[dict[str, Any]]:
    """The rows of a planner's step log (JSON lines with a ``step``); a missing file or a
    torn last line (the planner was killed while writing it) gives what could be read."""
    rows: list[dict[str, Any]] = []
    try:
        text = path.read_text()
    except OSError:
        return rows
    for line in text.splitlines():
        try:
            row = json.loads(line)
        except ValueError:
            continue
        if isinstance(row, dict) and isinstance(row.get("step"), int) and "position_m" in row and "measurement" in row:
            rows.append(row)
    return rows


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


class StepLog:
    """The JSON-lines step log of one planner (None path: nothing written).

    Args:
        path: the log file, or None. append: append (a rejoining planner continues its
            predecessor's log) rather than overwrite.
    """

    def __init__(self, path: Path | None, append: bool) -> None:
        self._file: TextIO | None = None
        if path is not None:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._file = path.open("a" if append else "w")

    def write_step(
        self, k: int, t_s: float, own_m: np.ndarray, record: Record, view: Any, state: Any, result: Any, rows: int, timing: dict[str, float]
    ) -> None:
        """One row: step ``k`` at time ``t_s`` (mission s in lockstep, UNIX s in real time), the
        own position (m, ENU), the own measurement, the view, the estimate, the plan and the
        step's timing (wall s)."""
        if self._file is None:
            return
        step = result.step
        entry: dict[str, Any] = {
            "step": k,
            "t_s": t_s,
            "position_m": [float(v) for v in own_m],
            "measurement": {
                "range_m": _num(record.range_m),
                "azimuth_rad": _num(record.azimuth_rad),
                "elevation_rad": _num(record.elevation_rad),
                "los": record.los,
            },
            "saved_steps": [int(s) for s in view.saved_steps],
            "hops": [int(h) for h in view.hops],
            "new_records": rows,
            "estimate_m": [float(v) for v in state.estimate_m],
            "observable": bool(state.observable),
            "cost": _num(float(result.cost.value)),
            "next_position_m": [float(v) for v in step.next_position],
            "active": {name: bool(a) for name, a in zip(("uav", "source", "obstacle", "altitude"), np.asarray(step.active))},
            "singular": bool(step.singular),
            "filtered": bool(step.filtered),
            "loiter": bool(np.asarray(result.loiter)),
            "timing": {name: round(v, 6) for name, v in timing.items()},
        }
        offset_db = getattr(state, "offset_db", None)  # the source's power unknown (planner.radio.power_estimator)
        if offset_db is not None:
            entry["power_offset_db"] = _num(float(offset_db))
        if record.extra_values:  # the values of components beyond range and bearing, if any
            entry["measurement"]["extra_values"] = {name: _num(v) for name, v in record.extra_values.items()}
        self._file.write(json.dumps(entry) + "\n")
        self._file.flush()  # the step log is the record of what was flown: it must survive a kill

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._file is not None:
            self._file.close()
            self._file = None
