"""A parameter sweep: the grid of every combination of the varied mission keys, each cell a
Monte Carlo run of the same mission with the same seeds, written cell by cell and resumable.

    varies = parse_vary(["drones.count=10,50,100", "comms.h_max=1,2"])
    plan = plan_sweep("paper/joint", varies, {"drones.start.rows": {}}, criterion="both", trials=20)
    rows = run_sweep(plan, Path("results/sweep"), executor=LocalPool(2))

Layout of a sweep directory::

    OUT/
      sweep.json                the command, the varied keys and values, every cell's key
      sweep.csv                 one row per run of every finished cell, in grid order
      figures/final_peb_vs_<key>.png   final mean PEB vs each varied key, 95 % interval bands
      cells/<cell>/cell.json    a finished cell: its values, key and rows (written last)
      cells/<cell>/runs/<run>/  the run's results (as fimnav montecarlo's runs/<run>/)

A cell is finished when its ``cell.json`` is there; a rerun of the same command reads those
cells and simulates the others (an interrupted sweep loses at most the cells in flight). A
cell's key is a hash of what it runs (each run's mission as loaded, criterion, trials, steps,
first trial, the flags and the chunking): a directory holding a cell of the same name with
another key is another sweep's, and is refused.

Every cell runs its missions' trials with their own seeds, so the cells share their random
numbers (common random numbers: a difference between two cells is the parameter's, not the
noise's). A cell with injected faults is not compared with a fault-free baseline (no
``faults`` penalty in its summary): the sweep's fault-free cell is that baseline.
"""

from __future__ import annotations

import csv
import hashlib
import itertools
import json
import os
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import yaml

from comms.errors import UsageError
from missions.format.loader import MissionError
from missions.runtime.rundir import make_results_dir, writing
from missions.study.executors import MAX_CHUNKS, MIN_CHUNK_TRIALS, ChunkExecutor
from missions.study.montecarlo import expand_runs, iter_study
from missions.study.records import SAFETY_FAMILIES, RunSpec

#: Version of ``sweep.json`` and ``cell.json``.
SWEEP_FORMAT: int = 1
CELL_FILE = "cell.json"
#: Columns of ``sweep.csv`` after the varied keys (one per key, named as the key).
CSV_TAIL: tuple[str, ...] = (
    "criterion",
    "policy",
    "activation",
    "trials",
    "steps",
    "drones",
    "final_peb_mean_m",
    "final_peb_ci95_low_m",
    "final_peb_ci95_high_m",
    "final_estimate_error_median_m",
    *(f"violations_{f}" for f in SAFETY_FAMILIES),
    "runtime_s",
)


@dataclass(frozen=True)
class Vary:
    """One ``--vary KEY=V1,V2,...``: a dotted mission key and its values (YAML, as ``--set``
    reads them), with the text of each as typed (for the CSV, names and figures)."""

    key: str
    values: tuple[Any, ...]
    texts: tuple[str, ...]


def split_values(text: str) -> list[str]:
    """``V1,V2,...`` split at the commas outside brackets, braces and quotes (a value can be a
    YAML list: ``[0,150,8],[0,200,8]``)."""
    parts, depth, quote, start = [], 0, "", 0
    for n, ch in enumerate(text):
        if quote:
            quote = "" if ch == quote else quote
        elif ch in "'\"":
            quote = ch
        elif ch in "[{":
            depth += 1
        elif ch in "]}":
            depth -= 1
        elif ch == "," and depth == 0:
            parts.append(text[start:n])
            start = n + 1
    parts.append(text[start:])
    return [p.strip() for p in parts]


def parse_vary(items: Sequence[str], sets: Mapping[str, Any] | None = None) -> list[Vary]:
    """Parse ``--vary KEY=V1,V2,...`` items; the values are read as YAML (``3``, ``[1, 2]``).

    Raises:
        MissionError: an item without ``=``, a key that is not dotted, an empty or repeated
            value, a value that is not YAML, a key varied twice or also given with ``--set``.
    """
    out: list[Vary] = []
    for item in items:
        key, sep, rest = item.partition("=")
        key = key.strip()
        if not sep or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*", key):
            raise MissionError("--vary", [f"expected KEY=V1,V2,... with a dotted key such as comms.h_max=1,2,3, found {item!r}"])
        texts = split_values(rest)
        if any(not t for t in texts):
            raise MissionError("--vary", [f"{key}: expected values separated by commas, found an empty value in {rest!r}"])
        if len(set(texts)) != len(texts):
            raise MissionError("--vary", [f"{key}: expected different values, found {rest!r}"])
        values = []
        for t in texts:
            try:
                values.append(yaml.safe_load(t))
            except yaml.YAMLError:
                raise MissionError("--vary", [f"{key}: expected a YAML value, found {t!r}"]) from None
        if any(v.key == key for v in out):
            raise MissionError("--vary", [f"{key}: varied twice; give its values in one --vary"])
        if sets and key in sets:
            raise MissionError("--vary", [f"{key}: also given with --set; give it in one of them"])
        out.append(Vary(key, tuple(values), tuple(texts)))
    if not out:
        raise MissionError("--vary", ["expected at least one --vary KEY=V1,V2,..."])
    return out


@dataclass(frozen=True)
class Cell:
    """One combination of the varied values: its runs and its place in the sweep.

    Attributes:
        index: its place in the grid (the first key varies slowest), from 0.
        values: ``(key, value as typed)`` of every varied key, in ``--vary`` order.
        specs: its runs (:func:`missions.study.montecarlo.expand_runs`: each criterion).
        key: the hash of what it runs (see the module doc).
    """

    index: int
    values: tuple[tuple[str, str], ...]
    specs: tuple[RunSpec, ...]
    key: str

    @property
    def name(self) -> str:
        """Its directory under ``cells/``: ``c<index>_<key>=<value>_...`` (file-name safe)."""
        text = "_".join(f"{k.rsplit('.', 1)[-1]}={v}" for k, v in self.values)
        return f"c{self.index:03d}_" + re.sub(r"[^A-Za-z0-9_.=+-]+", "-", text)[:80]


@dataclass(frozen=True)
class SweepPlan:
    """Every cell of a sweep, and what a results directory needs to say what it is."""

    mission: str
    varies: tuple[Vary, ...]
    cells: tuple[Cell, ...]
    oracle_estimate: bool
    chunk_trials: int
    max_chunks: int

    @property
    def key(self) -> str:
        """A hash of every cell's key: the same sweep (same missions as loaded, values, runs)."""
        return hashlib.sha256("".join(c.key for c in self.cells).encode()).hexdigest()[:10]


def _cell_key(specs: Sequence[RunSpec], oracle: bool, chunk_trials: int, max_chunks: int) -> str:
    text = json.dumps(
        {
            "runs": [[s.mission.model_dump_json(), s.criterion, s.trials, s.steps, s.first_trial] for s in specs],
            "oracle_estimate": oracle,
            "chunks": [chunk_trials, max_chunks],
        }
    )
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def plan_sweep(
    mission: str | os.PathLike[str],
    varies: Sequence[Vary],
    overrides: Mapping[str, Any] | None = None,
    criterion: Literal["A", "D", "both"] | None = None,
    trials: int | None = None,
    steps: int | None = None,
    oracle_estimate: bool = False,
    chunk_trials: int = MIN_CHUNK_TRIALS,
    max_chunks: int = MAX_CHUNKS,
    policies: Sequence[str] | None = None,
) -> SweepPlan:
    """Every cell of the grid of ``varies`` over ``mission`` (with ``overrides``, ``--set``),
    each loaded and checked before anything runs; a cell runs each criterion (``criterion``)
    and policy (``policies``, :data:`planner.policies.POLICIES`; None: the mission's).

    Raises:
        UsageError: a cell's mission is invalid (the message names the key and value).
    """
    cells = []
    for index, combo in enumerate(itertools.product(*(range(len(v.values)) for v in varies))):
        cell_overrides = dict(overrides or {})
        for v, n in zip(varies, combo):
            cell_overrides[v.key] = v.values[n]
        values = tuple((v.key, v.texts[n]) for v, n in zip(varies, combo))
        try:
            specs = expand_runs([mission], cell_overrides, criterion, None, trials, steps, policies)
        except MissionError as exc:
            where = ", ".join(f"{k}={t}" for k, t in values)
            raise UsageError(f"--vary {where}: {exc}") from None
        cells.append(Cell(index, values, tuple(specs), _cell_key(specs, oracle_estimate, chunk_trials, max_chunks)))
    return SweepPlan(str(mission), tuple(varies), tuple(cells), oracle_estimate, chunk_trials, max_chunks)


def default_out(plan: SweepPlan) -> Path:
    """``results/sweep-<mission id>-<plan key>``: the same command finds its directory again."""
    return Path("results") / f"sweep-{plan.cells[0].specs[0].mission.id}-{plan.key}"


def read_finished(plan: SweepPlan, out: Path) -> dict[int, list[dict[str, Any]]]:
    """The rows of every cell of ``plan`` already finished in ``out``, by cell index.

    Raises:
        UsageError: ``out`` holds a cell of the same name made by another sweep.
    """
    done: dict[int, list[dict[str, Any]]] = {}
    for cell in plan.cells:
        path = out / "cells" / cell.name / CELL_FILE
        if not path.is_file():
            continue
        try:
            doc = json.loads(path.read_text())
            key, rows = doc["key"], doc["rows"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise UsageError(f"{path}: not a finished cell of a sweep ({type(exc).__name__}: {exc}); use another --out") from None
        if key != cell.key:
            raise UsageError(f"{out} holds another sweep (its cell {cell.name} ran other missions, trials, steps or flags); use another --out")
        done[cell.index] = rows
    return done


def _row(cell: Cell, summary: Mapping[str, Any]) -> dict[str, Any]:
    """The ``sweep.csv`` row of one run of a cell, from the run's summary."""
    ci = summary.get("final_peb_ci95_m") or [None, None]
    row: dict[str, Any] = {"cell": cell.name, **dict(cell.values)}
    row |= {
        "criterion": summary["criterion"],
        "policy": summary["policy"],
        "activation": summary["activation"],
        "trials": summary["trials"],
        "steps": summary["steps"],
        "drones": summary["drones"],
        "final_peb_mean_m": summary["final_peb_mean_m"],
        "final_peb_ci95_low_m": ci[0],
        "final_peb_ci95_high_m": ci[1],
        "final_estimate_error_median_m": summary["final_estimate_error_median_m"],
    }
    row |= {f"violations_{f}": summary["violations"][f] for f in SAFETY_FAMILIES}
    row["runtime_s"] = summary["runtime_s"]
    return row


def _write_atomic(path: Path, text: str) -> None:
    """``text`` to ``path`` through a temporary file renamed over it (a reader never sees half)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    os.replace(tmp, path)


def write_table(plan: SweepPlan, out: Path, done: Mapping[int, Sequence[Mapping[str, Any]]]) -> Path:
    """``sweep.csv``: the rows of the finished cells, in grid order (rewritten whole)."""
    columns = ["cell", *(v.key for v in plan.varies), *CSV_TAIL]
    lines: list[list[Any]] = [columns]
    for index in sorted(done):
        lines += [[("" if r.get(c) is None else r.get(c)) for c in columns] for r in done[index]]
    path = out / "sweep.csv"
    tmp = path.with_name("sweep.csv.tmp")
    with tmp.open("w", newline="") as fh:
        csv.writer(fh).writerows(lines)
    os.replace(tmp, path)
    return path


def run_sweep(
    plan: SweepPlan,
    out: Path,
    executor: ChunkExecutor,
    command: Sequence[str] = (),
    progress: Callable[[int], object] | None = None,
    on_cell: Callable[[Cell, list[dict[str, Any]]], None] | None = None,
    figures: bool = True,
) -> dict[int, list[dict[str, Any]]]:
    """Run the cells of ``plan`` not yet finished in ``out`` on ``executor`` (all their chunks
    at once: the workers share every cell), write each cell as soon as its runs are done, then
    ``sweep.csv`` and the figures; return every cell's rows by index.

    Args:
        plan: :func:`plan_sweep`. out: the sweep directory (made if missing).
        executor: where the chunks run (:mod:`missions.study.executors`, :mod:`missions.study.cluster`).
        command: the command line, for ``sweep.json``.
        progress: trial-steps done (:func:`sweep_size` in all).
        on_cell: told each cell (and its rows) as it finishes.
        figures: draw ``figures/final_peb_vs_<key>.png``.

    Raises:
        UsageError: ``out`` cannot be made or written, or holds another sweep.
    """
    make_results_dir(out)
    done = read_finished(plan, out)
    with writing(out):
        doc = {
            "format": SWEEP_FORMAT,
            "command": list(command),
            "mission": plan.mission,
            "vary": [{"key": v.key, "values": list(v.texts)} for v in plan.varies],
            "cells": [{"name": c.name, "key": c.key, "values": dict(c.values)} for c in plan.cells],
        }
        _write_atomic(out / "sweep.json", json.dumps(doc, indent=2) + "\n")
        write_table(plan, out, done)
    pending = [c for c in plan.cells if c.index not in done]
    specs = [s for c in pending for s in c.specs]
    owner = [c for c in pending for _ in c.specs]
    rows: dict[int, list[dict[str, Any]]] = {}
    from missions.study.results import write_run

    for run in iter_study(
        specs,
        oracle_estimate=plan.oracle_estimate,
        executor=executor,
        chunk_trials=plan.chunk_trials,
        max_chunks=plan.max_chunks,
        progress=progress,
        penalties=False,
    ):
        cell = owner[run.index]
        cell_dir = out / "cells" / cell.name
        with writing(out):
            summary = write_run(run.result, cell_dir, with_penalty=False)
            rows.setdefault(cell.index, []).append(_row(cell, summary))
            if len(rows[cell.index]) == len(cell.specs):
                body = {"format": SWEEP_FORMAT, "key": cell.key, "values": dict(cell.values), "rows": rows[cell.index]}
                _write_atomic(cell_dir / CELL_FILE, json.dumps(body, indent=2) + "\n")
                done[cell.index] = rows.pop(cell.index)
                write_table(plan, out, done)
                if on_cell is not None:
                    on_cell(cell, done[cell.index])
    if figures:
        from missions.study.sweep_figures import plot_sweep

        first = plan.cells[0].specs[0]
        with writing(out):
            for vary in plan.varies:
                title = (
                    f"{first.mission.id}: final mean PEB vs {vary.key}\n{first.trials} trials × {first.steps} steps per cell, "
                    "same seeds; band: 95 % interval over trials"
                )
                others = [v.key for v in plan.varies if v.key != vary.key]
                plot_sweep(done, vary.key, vary.texts, others, title, out / "figures" / f"final_peb_vs_{vary.key}.png")
    return done


def sweep_size(plan: SweepPlan, finished: Mapping[int, object]) -> int:
    """Trial-steps :func:`run_sweep` simulates: those of the cells not in ``finished``."""
    return sum(s.trials * s.steps for c in plan.cells if c.index not in finished for s in c.specs)
