"""Results directories: CSV curves and trajectories, summary JSON, and the paper's figures.

Layout of one results directory (``fimnav montecarlo`` and ``fimnav launch``)::

    OUT/
      summary.json              every run's summary (list), plus the command and versions
      figures/peb.png           mean PEB vs step, every run, log scale (Fig. 3; missions.study.figures)
      figures/estimate_error.png   median source estimate error vs step, every run, log scale
      figures/trajectories_<run>.png   trial 0: 3-D and top view, obstacles, source, start/end (Fig. 2)
      figures/policies_<run>.png   a mission run under several policies (--policy): mean PEB
                                vs step per policy, the optimum's as a line (missions.study.comparison)
      runs/<run>/mission.yaml   the mission as run (defaults filled, overrides applied)
      runs/<run>/peb.csv        per step: mean PEB, p10, p90, singular fraction, estimate error
      runs/<run>/trajectories.csv   trial 0: every drone's position, estimate and PEB per step
      runs/<run>/summary.json   final PEB, estimate error, violations per constraint, run time
                                (with injected comms faults: "faults", the PEB penalty against
                                the same mission without faults; with ``fimnav montecarlo
                                --optimum``: "optimum", the optimal placement's PEB, and
                                "final_peb_over_optimum")
      runs/<run>/penalty_reference.npz   a run without faults: what the PEB penalty of the same
                                run with faults needs from it (``fimnav montecarlo --baselines
                                OUT``; missions.study.simulator.PenaltyReference)

``<run>`` is ``<mission id>_<criterion>`` (with ``_paper`` when the paper's activation rule
was used, and ``_<policy>`` under a baseline policy).
"""

from __future__ import annotations

import csv
import dataclasses
import io
import json
import math
import platform
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from missions.format.loader import mission_to_yaml
from missions.runtime.rundir import make_results_dir, writing
from missions.study.layout import PENALTY_REFERENCE, run_name, spec_name
from missions.study.records import SAFETY_FAMILIES, PenaltyReference, SimulationResult

__all__ = [
    "PENALTY_REFERENCE",
    "ResultsWriter",
    "figure_view",
    "run_name",
    "spec_name",
    "summarize",
    "violating_drones",
    "write_results",
    "write_run",
]


def summarize(result: SimulationResult, penalty: dict[str, Any] | None = None, with_penalty: bool = True) -> dict[str, Any]:
    """The summary of one run (JSON-ready): final PEB (mean, its 95 % interval over trials,
    percentiles) and estimate error, safety counts, time.

    A run with injected comms faults (``comms.faults``) also gets ``"faults"``: the PEB penalty
    against the same mission without faults (:func:`missions.study.simulator.fault_penalty`), given
    as ``penalty`` or else computed here (a fault-free simulation of the same trials and steps);
    not with ``with_penalty=False`` (``fimnav sweep``: its cells compare with each other).
    """
    spec = result.spec
    stats = result.peb_stats()
    final_err = result.estimate_error_m[-1]
    m = spec.mission
    drone_steps = spec.trials * spec.steps * m.drones.count
    return (
        {
            "run": run_name(result),
            "mission_id": m.id,
            "criterion": spec.criterion,
            "policy": m.policy,
            "activation": m.constraints.activation,
            "trials": spec.trials,
            "steps": spec.steps,
            "drones": m.drones.count,
            "seed": m.seed,
            "oracle_estimate": bool(result.extra.get("oracle_estimate", 0.0)),
            "final_peb_mean_m": _num(stats["mean"][-1]),
            "final_peb_ci95_m": final_peb_interval(result),
            "final_peb_p10_m": _num(stats["p10"][-1]),
            "final_peb_p90_m": _num(stats["p90"][-1]),
            "final_singular_fraction": _num(stats["singular_fraction"][-1]),
            "initial_peb_mean_m": _num(stats["mean"][0]),
            "final_estimate_error_mean_m": _num(final_err.mean()),
            "final_estimate_error_median_m": _num(np.median(final_err)),
            "violations": result.violations(),
            "violation_families": list(SAFETY_FAMILIES),
            "violating_drones": violating_drones(result),
            "worst_margins_m": {k: _num(v.min()) for k, v in result.margins_m.items()},
            "singular_fallback_steps": int(result.singular_fallback.sum()),
            "safety_filter_steps": int(result.filtered.sum()),
            "loiter_steps": int(result.loiter.sum()),
            "runtime_s": round(result.runtime_s, 3),
            "drone_steps_per_s": round(drone_steps / max(result.runtime_s, 1e-9), 1),
        }
        | (_faults(result, penalty) if with_penalty else {})
        | _source_power(result)
    )


def _incomplete_beta(x: float, a: float, b: float) -> float:
    """The regularized incomplete beta function I_x(a, b), 0 ≤ x ≤ 1, a, b > 0: Lentz's
    continued fraction (Numerical Recipes §6.4), on the side of the symmetry
    I_x(a, b) = 1 − I_(1−x)(b, a) where it converges fast."""
    if x <= 0.0 or x >= 1.0:
        return 0.0 if x <= 0.0 else 1.0
    if x > (a + 1.0) / (a + b + 2.0):
        return 1.0 - _incomplete_beta(1.0 - x, b, a)
    front = math.exp(math.lgamma(a + b) - math.lgamma(a) - math.lgamma(b) + a * math.log(x) + b * math.log1p(-x)) / a
    tiny = 1e-300
    c, d = 1.0, 1.0 - (a + b) * x / (a + 1.0)
    d = 1.0 / (d if abs(d) > tiny else tiny)
    f = d
    for m in range(1, 100_000):
        for numerator in (m * (b - m) * x / ((a + 2 * m - 1) * (a + 2 * m)), -(a + m) * (a + b + m) * x / ((a + 2 * m) * (a + 2 * m + 1))):
            d = 1.0 + numerator * d
            d = 1.0 / (d if abs(d) > tiny else tiny)
            c = 1.0 + numerator / c
            c = c if abs(c) > tiny else tiny
            f *= c * d
        if abs(c * d - 1.0) < 1e-16:
            break
    return front * f


def student_t_quantile(p: float, dof: float) -> float:
    """The ``p`` quantile of Student's t with ``dof`` degrees of freedom (0.5 < p < 1), as
    ``scipy.stats.t.ppf`` (tests/missions/test_results_stats.py checks it against scipy: 1e-10
    relative up to 10⁴ degrees of freedom, trials of a run). t solves P(0 < T < t) = ½ I_(t²/(ν+t²))(½, ν/2) =
    p − ½ for p ≤ 0.75, and P(T > t) = ½ I_(ν/(ν+t²))(ν/2, ½) = 1 − p above (each side where
    its right-hand side is exact), by bisection on a bracket then Newton steps with the t
    density. No scipy: importing it costs a study more than writing its results."""
    if not (0.5 < p < 1.0) or not dof > 0:
        raise ValueError(f"student_t_quantile: expected 0.5 < p < 1 and dof > 0, found p={p}, dof={dof}")
    nu = float(dof)
    central = p <= 0.75
    target = p - 0.5 if central else 1.0 - p

    def excess(t: float) -> float:  # > 0: t too small
        if central:
            return target - 0.5 * _incomplete_beta(t * t / (nu + t * t), 0.5, nu / 2.0)
        return 0.5 * _incomplete_beta(nu / (nu + t * t), nu / 2.0, 0.5) - target

    log_norm = math.lgamma((nu + 1.0) / 2.0) - math.lgamma(nu / 2.0) - 0.5 * math.log(nu * math.pi)
    lo, hi = 0.0, 1.0
    while excess(hi) > 0.0:
        lo, hi = hi, 2.0 * hi
    t = 0.5 * (lo + hi)
    for _ in range(200):
        e = excess(t)
        lo, hi = (t, hi) if e > 0.0 else (lo, t)
        density = math.exp(log_norm - (nu + 1.0) / 2.0 * math.log1p(t * t / nu))
        step = t + e / density
        new = step if lo < step < hi else 0.5 * (lo + hi)
        if abs(new - t) <= 1e-15 * abs(t) or hi - lo <= 1e-15 * hi:
            return new
        t = new
    return t


def final_peb_interval(result: SimulationResult, level: float = 0.95) -> list[float] | None:
    """The ``level`` confidence interval (m) of the final mean PEB (eq. 18, last step): per
    trial the mean over its drones' finite views, then Student's t over the trials,
    mean ± t_(1+level)/2, M−1 · s / √M. None below two trials with a finite mean (a trial
    whose every final view is singular is left out, as in the mean)."""

    peb = result.peb_m[-1]  # (M, N)
    finite = np.isfinite(peb)
    count = finite.sum(-1)
    per_trial = np.where(finite, peb, 0.0).sum(-1)[count > 0] / count[count > 0]
    if per_trial.size < 2:
        return None
    mean = float(per_trial.mean())
    half = float(student_t_quantile(0.5 + level / 2.0, per_trial.size - 1) * per_trial.std(ddof=1) / np.sqrt(per_trial.size))
    return [mean - half, mean + half]


#: At most this many violating (trial, drone) pairs are listed per family in a summary.
MAX_VIOLATING_DRONES: int = 10


def violating_drones(result: SimulationResult) -> dict[str, list[dict[str, Any]]]:
    """Per safety family with violations, the (trial, drone) pairs that crossed it: their first
    and last violating step, how many steps, the worst margin (m, negative) and, for the source
    family, the range of the drone's own source-estimate error (m) over those steps (a keep-out
    is held about the estimate). At most :data:`MAX_VIOLATING_DRONES` pairs per family, worst
    first; trials and steps count from 0, drones from 1."""
    out: dict[str, list[dict[str, Any]]] = {}
    err = result.estimate_error_m  # (K, M, N)
    for family, margins in result.margins_m.items():
        bad = margins < 0.0  # (K, M, N) or (K+1, M, N)
        if not bad.any():
            continue
        pairs = []
        for t, i in sorted({(int(t), int(i)) for _, t, i in np.argwhere(bad)}):
            steps = np.flatnonzero(bad[:, t, i])
            entry: dict[str, Any] = {
                "trial": t + result.spec.first_trial,
                "drone": i + 1,
                "first_step": int(steps[0]),
                "last_step": int(steps[-1]),
                "steps": int(steps.size),
                "worst_margin_m": round(float(margins[steps, t, i].min()), 3),
            }
            if family == "source":
                e = err[steps[steps < err.shape[0]], t, i]
                if e.size:
                    entry["estimate_error_m"] = [round(float(e.min()), 1), round(float(e.max()), 1)]
            pairs.append(entry)
        out[family] = sorted(pairs, key=lambda d: d["worst_margin_m"])[:MAX_VIOLATING_DRONES]
    return out


def _source_power(result: SimulationResult) -> dict[str, Any]:
    """``{"source_power": ...}`` for a run with the power unknown or a true power offset: the
    model, the true offset (dB above the nominal power) and, with the power unknown, the drones'
    final estimates of it (mean, RMSE about the truth, dB; the fraction of drones with one)."""
    source = result.spec.mission.source
    if source.power == "known" and source.power_offset_db == 0.0:
        return {}
    out: dict[str, Any] = {"model": source.power, "true_offset_db": source.power_offset_db}
    if result.power_offset_db is not None:
        final = result.power_offset_db[-1]
        have = np.isfinite(final)
        out["final_offset_estimated_fraction"] = _num(have.mean())
        out["final_offset_mean_db"] = _num(final[have].mean()) if have.any() else None
        out["final_offset_rmse_db"] = _num(np.sqrt(((final[have] - source.power_offset_db) ** 2).mean())) if have.any() else None
    return {"source_power": out}


def _faults(result: SimulationResult, penalty: dict[str, Any] | None) -> dict[str, Any]:
    """``{"faults": penalty}`` for a run with injected comms faults, else nothing."""
    mission = result.spec.mission
    if not mission.comms.faults.enabled:
        return {}
    if penalty is None:  # a result without its penalty (a launch's): the baseline simulated here
        from missions.study.simulator import fault_penalty

        penalty = fault_penalty(mission, result)
    return {"faults": penalty}


def _num(x: float) -> float | None:
    """JSON has no inf/NaN: None stands for 'undefined' (e.g. every view singular)."""
    x = float(x)
    return x if np.isfinite(x) else None


def write_run(
    result: SimulationResult, out: Path, penalty: dict[str, Any] | None = None, extra: dict[str, Any] | None = None, with_penalty: bool = True
) -> dict[str, Any]:
    """Write ``runs/<run>/`` for one run; return its summary (``penalty``, ``with_penalty``: see
    :func:`summarize`; ``extra``: entries added to the summary, e.g. the optimum of ``fimnav
    montecarlo --optimum``)."""
    run_dir = out / "runs" / run_name(result)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "mission.yaml").write_text(mission_to_yaml(result.spec.mission))
    stats = result.peb_stats()
    err = result.estimate_error_m.reshape(result.estimate_error_m.shape[0], -1)
    with (run_dir / "peb.csv").open("w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["step", "peb_mean_m", "peb_p10_m", "peb_p90_m", "singular_fraction", "estimate_error_mean_m", "estimate_error_median_m"])
        err_mean, err_median = err.mean(axis=1), np.median(err, axis=1)
        for k in range(len(stats["mean"])):
            w.writerow(
                [
                    k,
                    _fmt(stats["mean"][k]),
                    _fmt(stats["p10"][k]),
                    _fmt(stats["p90"][k]),
                    _fmt(stats["singular_fraction"][k]),
                    _fmt(err_mean[k]),
                    _fmt(err_median[k]),
                ]
            )
    with (run_dir / "trajectories.csv").open("w", newline="") as fh:
        csv.writer(fh).writerow(["trial", "step", "drone", "role", "x_m", "y_m", "z_m", "estimate_x_m", "estimate_y_m", "estimate_z_m", "peb_m"])
        fh.write(_trajectory_rows(result))
    from missions.study.exports import write_exports

    write_exports(result, run_dir)  # trajectories.kml, trajectories.geojson (first trial)
    if not result.spec.mission.comms.faults.enabled:
        PenaltyReference.of(result).save(run_dir / PENALTY_REFERENCE)
    summary = summarize(result, penalty, with_penalty) | (extra or {})
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def _fmt(x: float) -> str:
    return f"{float(x):.10g}"


#: One row of trajectories.csv (trial 0, step, drone, role, numbers as :func:`_fmt` writes them).
_TRAJECTORY_ROW = "0,%d,%d,%s" + ",%.10g" * 7 + "\r\n"


def _csv_cell(text: str) -> str:
    """``text`` as ``csv.writer`` writes one cell (quoted only where it must be)."""
    buf = io.StringIO()
    csv.writer(buf).writerow([text])  # its line terminator decides the quoting too: kept, then cut
    return buf.getvalue()[: -len("\r\n")]


def _trajectory_rows(result: SimulationResult) -> str:
    """The rows of trajectories.csv (the first trial: every step's position of each drone, m,
    ENU, with its estimate and PEB of that step, the last step's for the final position), as
    ``csv.writer`` writes them with :func:`_fmt`'s numbers: one format per row."""
    roles = [_csv_cell(r) for r in result.spec.mission.drones.roles]
    pos, est, peb = result.positions_m[:, 0].tolist(), result.estimates_m[:, 0].tolist(), result.peb_m[:, 0].tolist()
    K = len(est)
    rows = []
    for k, at_k in enumerate(pos):
        e_k, peb_k = est[min(k, K - 1)], peb[min(k, K - 1)]
        for i, p in enumerate(at_k):
            e = e_k[i]
            rows.append(_TRAJECTORY_ROW % (k, i + 1, roles[i], p[0], p[1], p[2], e[0], e[1], e[2], peb_k[i]))
    return "".join(rows)


def figure_view(result: SimulationResult) -> SimulationResult:
    """What a run's figures read, for a writer that keeps every run of a study until its
    figures: every trial's PEB and estimate error (the per-step curves) and the first trial of
    everything else (its trajectories); the other trials' positions, estimates, margins and
    record ages (most of a run's memory) are left out. Not for summaries: its margins are empty
    and its other per-trial arrays hold the first trial only."""
    first = slice(0, 1)
    return dataclasses.replace(
        result,
        positions_m=result.positions_m[:, first].copy(),
        estimates_m=result.estimates_m[:, first].copy(),
        observable=result.observable[:, first].copy(),
        margins_m={},
        singular_fallback=result.singular_fallback[:, first].copy(),
        filtered=result.filtered[:, first].copy(),
        loiter=result.loiter[:, first].copy(),
        record_ages=result.record_ages[:, first].copy(),
    )


class ResultsWriter:
    """Writes a results directory run by run, so a study holds one run in memory at a time:
    :meth:`add` writes ``runs/<run>/`` as soon as a run is done (and keeps its summary and, for
    the figures, its :func:`figure_view`); :meth:`close` writes ``summary.json`` and the figures.
    The only writer of ``summary.json`` (and of ``runs/<run>/summary.json``).

    Raises:
        UsageError: ``out`` cannot be made or written (:mod:`missions.runtime.rundir`).
    """

    def __init__(self, out: Path, command: Sequence[str] = (), figures: bool = True) -> None:
        self.out = make_results_dir(out)
        self.command = list(command)
        self.figures = figures
        self.summaries: list[dict[str, Any]] = []
        self.kept: list[SimulationResult] = []
        self.extras: list[dict[str, Any] | None] = []

    def add(self, result: SimulationResult, penalty: dict[str, Any] | None = None, extra: dict[str, Any] | None = None) -> dict[str, Any]:
        """Write one run (``penalty``, ``extra``: see :func:`write_run`); return its summary."""
        with writing(self.out):
            summary = write_run(result, self.out, penalty, extra)
        self.summaries.append(summary)
        self.extras.append(extra)
        if self.figures:
            self.kept.append(figure_view(result))
        return summary

    def close(self) -> list[dict[str, Any]]:
        """Write ``summary.json`` (every run added, in order) and the figures; return the summaries."""
        with writing(self.out):
            doc = {
                "command": self.command,
                "python": platform.python_version(),
                "numpy": np.__version__,
                "runs": self.summaries,
            }
            (self.out / "summary.json").write_text(json.dumps(doc, indent=2) + "\n")
            if self.figures:
                from missions.study.figures import write_figures  # matplotlib only when figures are wanted

                write_figures(self.kept, self.out / "figures")
                from missions.study.comparison import write_policy_figures

                write_policy_figures(self.kept, self.extras, self.out / "figures")
        return self.summaries


def write_results(
    results: Sequence[SimulationResult],
    out: Path,
    command: Sequence[str] = (),
    figures: bool = True,
    penalties: Sequence[dict[str, Any] | None] | None = None,
    extras: Sequence[dict[str, Any] | None] | None = None,
) -> list[dict[str, Any]]:
    """Write the whole results directory for one or several runs (:class:`ResultsWriter`);
    return the summaries.

    ``penalties``: per run, its fault penalty if already computed (see :func:`summarize`).
    ``extras``: per run, entries added to its summary (see :func:`write_run`).

    Raises:
        UsageError: ``out`` cannot be made or written (:mod:`missions.runtime.rundir`).
    """
    pens = list(penalties) if penalties is not None else [None] * len(results)
    exs = list(extras) if extras is not None else [None] * len(results)
    writer = ResultsWriter(out, command, figures)
    for r, p, e in zip(results, pens, exs, strict=True):
        writer.add(r, p, e)
    return writer.close()
