"""The comparison of navigation policies (:mod:`planner.policies`) in one study: the mean PEB
vs step of each policy of a mission (same seeds), with the optimal placement's PEB as a
horizontal line when the study computed it (``fimnav montecarlo --optimum``), and the table of
final PEBs with their 95 % intervals. Written into a results directory by
:func:`missions.study.results.write_results` when a mission ran under several policies.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from missions.study.figures import _pyplot, _save, _set_log_axis, format_value
from missions.study.layout import run_name
from missions.study.records import SimulationResult

#: Colour of each policy (the planner's first).
POLICY_COLOURS = {"fim": "tab:blue", "centralized": "tab:green", "orbit": "tab:orange", "random": "tab:purple", "static": "tab:gray"}
POLICY_LABELS = {
    "fim": "fim (the paper's planner)",
    "centralized": "centralized (every record at once)",
    "orbit": "orbit (circle the estimate)",
    "random": "random walk at v_max",
    "static": "static (hold the start)",
}


def _group(result: SimulationResult) -> tuple[str, str, str]:
    m = result.spec.mission
    return m.id, result.spec.criterion, m.constraints.activation


def policy_groups(results: Sequence[SimulationResult]) -> dict[tuple[str, str, str], list[int]]:
    """Indices of the runs of each (mission, criterion, activation rule) flown under more than
    one policy, in the order of ``results``."""
    groups: dict[tuple[str, str, str], list[int]] = {}
    for n, r in enumerate(results):
        groups.setdefault(_group(r), []).append(n)
    return {g: idx for g, idx in groups.items() if len({results[i].spec.mission.policy for i in idx}) > 1}


def make_policy_figure(results: Sequence[SimulationResult], optimum_m: float | None = None) -> Any:
    """Mean PEB (eq. 18) vs step of the runs of one mission under each policy (log axis), with
    the optimal placement's PEB (:mod:`missions.study.optimum`) as a horizontal line."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(8.5, 5.4), constrained_layout=True)
    finite: list[float] = []
    for r in results:
        mean = r.peb_stats()["mean"]
        policy = r.spec.mission.policy
        style = "--" if policy == "centralized" else "-"  # over the planner's curve where they agree
        ax.plot(np.arange(mean.size), mean, style, color=POLICY_COLOURS.get(policy, "black"), lw=1.6, label=POLICY_LABELS.get(policy, policy))
        ok = mean[np.isfinite(mean)]
        finite += [float(ok.min()), float(ok.max())] if ok.size else []
        if ok.size:
            ax.annotate(format_value(ok[-1]), (mean.size - 1, ok[-1]), xytext=(4, 0), textcoords="offset points", fontsize=8, va="center")
    if optimum_m is not None:
        ax.axhline(optimum_m, color="black", ls=":", lw=1.2, label=f"optimal placement (fimnav optimum): {format_value(optimum_m)} m")
        finite.append(optimum_m)
    _set_log_axis(ax, min(finite, default=1.0), max(finite, default=10.0))
    first = results[0].spec
    m = first.mission
    rule = "" if m.constraints.activation == "safe" else ", paper's literal rule"
    ax.set_title(
        f"{m.id}, {first.criterion}-optimality{rule}: mean PEB vs step per policy\n{first.trials} trials × {first.steps} steps, same seeds",
        fontsize=10,
    )
    ax.set_xlabel("step k")
    ax.set_ylabel(r"$\overline{\mathrm{PEB}}^{(k)}$ [m]")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.13), ncol=2, fontsize=8, frameon=False)
    return fig


def write_policy_figures(results: Sequence[SimulationResult], extras: Sequence[Mapping[str, Any] | None], figures_dir: Path) -> list[Path]:
    """``policies_<run>.png`` for every mission (criterion, rule) run under several policies,
    named after its ``fim`` run (or its first); the optimum line where ``extras`` hold one."""
    paths = []
    for idx in policy_groups(results).values():
        group = [results[i] for i in idx]
        optimum = next((e["optimum"]["peb_m"] for i in idx if (e := extras[i]) and e.get("optimum")), None)
        named = next((r for r in group if r.spec.mission.policy == "fim"), group[0])
        path = figures_dir / f"policies_{run_name(named)}.png"
        _save(make_policy_figure(group, optimum), path, dpi=130)
        paths.append(path)
    return paths


def policy_table(summaries: Sequence[Mapping[str, Any]], labels: Mapping[str, str] | None = None) -> list[str]:
    """Markdown: per mission and criterion, the final mean PEB of each policy with its 95 %
    interval over trials, its ratio to the ``fim`` policy's, and the violating drone-steps
    (every family; the speed family apart: holding still is below v_min)."""
    lines = [
        "| run | policy | final mean PEB [m] | 95 % interval [m] | × fim | violating drone-steps (speed apart) | of which speed |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    by: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for s in summaries:
        by.setdefault((s["mission_id"], s["criterion"]), []).append(s)
    for (mission, crit), runs in by.items():
        fim = next((s for s in runs if s.get("policy", "fim") == "fim"), None)
        for s in runs:
            peb, ci = s["final_peb_mean_m"], s.get("final_peb_ci95_m")
            ratio = f"{peb / fim['final_peb_mean_m']:.2f}" if fim and peb and fim["final_peb_mean_m"] else "—"
            viol = s["violations"]
            other = sum(v for k, v in viol.items() if k != "speed")
            name = (labels or {}).get(mission, mission)
            lines.append(
                f"| {name}, {crit} | {s.get('policy', 'fim')} | {format_value(peb) if peb else '—'} | "
                f"{f'{format_value(ci[0])}–{format_value(ci[1])}' if ci else '—'} | {ratio} | {other} | {viol.get('speed', 0)} |"
            )
    return lines
