"""The results figures (missions/study/figures.py) say what was run and can be read.

Tiny runs of the paper's missions (2 trials × 25 steps) are drawn and the figures inspected:
the log axis is labelled with plain numbers spanning the data, every curve's final value is
written at its end and equals the data's, titles name the criterion actually run (no D on an
A-only run) and the constraint rule when the paper's literal rule is shown, line styles match
the legend's key, the legend sits outside the axes, the p10-p90 band and the start/end markers
are explained, and write_results writes every figure.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from matplotlib.text import Text

from missions.study import figures as F
from missions.format.loader import load_mission
from missions.study.results import run_name, write_results
from missions.study.simulator import RunSpec, SimulationResult, simulate

PAPER = Path(__file__).resolve().parents[2] / "missions" / "paper"
TRIALS, STEPS = 2, 25
PLAIN_NUMBER = re.compile(r"^\d+(\.\d+)?$")


def _run(name: str, criterion: str = "A", activation: str = "safe") -> SimulationResult:
    mission = load_mission(PAPER / f"{name}.yaml", {"criterion": criterion, "constraints.activation": activation})
    return simulate(RunSpec(mission, criterion, TRIALS, STEPS))


@pytest.fixture(scope="module")
def a_only() -> list[SimulationResult]:
    """One mission, A-optimality, safe rule: what ``fimnav montecarlo heterogeneous.yaml`` runs."""
    return [_run("heterogeneous")]


@pytest.fixture(scope="module")
def comparison() -> list[SimulationResult]:
    """Two missions × A, D × safe, paper rule (``--criterion both --activation both``)."""
    return [_run(name, crit, act) for name in ("joint", "heterogeneous") for act in ("safe", "paper") for crit in ("A", "D")]


@pytest.fixture(scope="module", autouse=True)
def _close_figures() -> Any:
    yield
    F._pyplot().close("all")


@pytest.fixture(scope="module")
def step_figures(a_only: list[SimulationResult], comparison: list[SimulationResult]) -> dict[str, Any]:
    """Per run set: [(figure, per-run centre curve)] of the PEB and estimate-error figures, drawn."""
    out = {"a_only": _step_figures(a_only), "comparison": _step_figures(comparison)}
    for figs in out.values():
        for fig, _ in figs:
            _drawn(fig)
    return out


def _drawn(fig: Any) -> Any:
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def _all_text(fig: Any) -> str:
    return "\n".join(t.get_text() for t in fig.findobj(lambda a: hasattr(a, "get_text") and callable(a.get_text)))


def _step_figures(results: list[SimulationResult]) -> list[tuple[Any, list[np.ndarray]]]:
    """(figure, per-run centre curve) for the PEB and the estimate-error figures."""
    peb = [r.peb_stats()["mean"] for r in results]
    err = [np.median(r.estimate_error_m.reshape(r.estimate_error_m.shape[0], -1), axis=-1) for r in results]
    return [(F.make_peb_figure(results), peb), (F.make_estimate_error_figure(results), err)]


@pytest.mark.parametrize("which", ["a_only", "comparison"])
def test_log_axis_has_plain_number_ticks_spanning_the_data(which: str, step_figures: dict[str, Any]) -> None:
    for fig, curves in step_figures[which]:
        ax = fig.axes[0]
        assert ax.get_yscale() == "log"
        lo, hi = ax.get_ylim()
        data = np.concatenate([c[np.isfinite(c)] for c in curves])
        assert lo <= data.min() and data.max() <= hi, "a curve leaves the axes"
        labels = [(t.get_position()[1], t.get_text()) for t in ax.get_yticklabels() if lo <= t.get_position()[1] <= hi]
        assert len(labels) >= 3, labels
        for value, text in labels:
            assert PLAIN_NUMBER.match(text), f"tick label {text!r} is not a plain number"
            assert math.isclose(float(text), value, rel_tol=1e-6)
        assert all(t.get_text() == "" for t in ax.get_yticklabels(minor=True)), "minor ticks are labelled"
        # no more than a fifth of the axis (log) unlabelled at either end
        span = math.log10(hi / lo)
        assert math.log10(labels[0][0] / lo) <= 0.2 * span + 1e-9
        assert math.log10(hi / labels[-1][0]) <= 0.2 * span + 1e-9


@pytest.mark.parametrize("which", ["a_only", "comparison"])
def test_end_values_are_the_final_values(which: str, step_figures: dict[str, Any]) -> None:
    for fig, curves in step_figures[which]:
        renderer = fig.canvas.get_renderer()
        ax = fig.axes[0]
        notes = [t for t in ax.texts if t.get_gid() == F.END_VALUE_GID]
        assert len(notes) == len(curves)
        for curve in curves:
            k = len(curve) - 1
            match = [n for n in notes if n.xy[0] == k and math.isclose(n.xy[1], curve[-1], rel_tol=1e-12)]
            assert len(match) == 1, "no annotation at the curve's end"
            text = match[0].get_text()
            number = re.match(r"^(\d+(?:\.\d+)?) m\b", text)
            assert number, text
            assert math.isclose(float(number.group(1)), curve[-1], rel_tol=5e-3), (text, curve[-1])
        boxes = [Text.get_window_extent(n, renderer) for n in notes]  # the text, not its leader line
        axes_box = ax.get_window_extent(renderer)
        for i, b in enumerate(boxes):
            assert b.x0 >= axes_box.x1, "an end value is written over the curves"
            assert b.x1 <= fig.bbox.x1, "an end value is cut off by the figure's edge"
            for other in boxes[i + 1 :]:
                assert not b.overlaps(other), "two end values overlap"


def test_titles_name_what_was_run_a_only(a_only: list[SimulationResult], step_figures: dict[str, Any]) -> None:
    for fig, _ in step_figures["a_only"]:
        title = fig.axes[0].get_title()
        assert "paper_heterogeneous" in title and "A-optimality" in title
        assert f"{TRIALS} trials" in title and f"{STEPS} steps" in title
        text = _all_text(fig)
        for wrong in ("D-optimality", "D solid", "D dashed", "dashed", "literal"):
            assert wrong not in text, f"{wrong!r} on an A-only, safe-rule figure"
    fig = F.make_trajectories_figure(a_only[0])
    title = fig._suptitle.get_text()
    assert "paper_heterogeneous" in title and "A-optimality" in title and f"trial 0 of {TRIALS}" in title
    assert f"k = 0…{STEPS}" in title
    assert "D-optimality" not in _all_text(fig)


def test_titles_and_legend_explain_the_comparison(comparison: list[SimulationResult], step_figures: dict[str, Any]) -> None:
    for fig, _ in step_figures["comparison"]:
        title = fig.axes[0].get_title()
        assert "A- and D-optimality" in title
        assert "paper's literal constraint rule" in title
        assert "paper_joint" in title and "paper_heterogeneous" in title
        legend = fig.legends[0]
        key = {t.get_text(): h for t, h in zip(legend.get_texts(), legend.legend_handles)}
        for (crit, rule), ls in F.LINESTYLES.items():
            label = f"{F.CRITERION_NAMES[crit]}, {F.RULE_NAMES[rule]}"
            assert label in key, f"no legend entry {label!r}"
            assert key[label].get_linestyle() == ls
        # every curve is drawn as the key says: its run's line style, its mission's colour
        colour_of = {t.get_text().split(" ")[0]: h.get_color() for t, h in zip(legend.get_texts(), legend.legend_handles) if t.get_text().startswith("paper_")}
        curves = fig.axes[0].lines
        assert len(curves) == len(comparison)
        for line, r in zip(curves, comparison):
            assert line.get_linestyle() == F.LINESTYLES[(r.spec.criterion, r.spec.mission.constraints.activation)]
            assert line.get_color() == colour_of[r.spec.mission.id]
    fig = F.make_trajectories_figure(comparison[3])  # joint, D, paper rule
    title = fig._suptitle.get_text()
    assert "D-optimality" in title and "paper's literal constraint rule" in title and "A-optimality" not in title


@pytest.mark.parametrize("which", ["a_only", "comparison"])
def test_legends_are_outside_the_axes(which: str, request: pytest.FixtureRequest, step_figures: dict[str, Any]) -> None:
    results = request.getfixturevalue(which)
    figs = [f for f, _ in step_figures[which]] + [F.make_trajectories_figure(results[0])]
    for fig in figs:
        renderer = _drawn(fig)
        assert len(fig.legends) == 1 and all(ax.get_legend() is None for ax in fig.axes)
        box = fig.legends[0].get_window_extent(renderer)
        assert fig.bbox.x0 <= box.x0 and box.x1 <= fig.bbox.x1 and fig.bbox.y0 <= box.y0, "legend cut off"
        for ax in fig.axes:
            assert not box.overlaps(ax.get_window_extent(renderer)), "the legend covers an axes"
        for text in fig.axes[0].texts:
            assert not box.overlaps(Text.get_window_extent(text, renderer)), "the legend covers an end value"


def test_band_is_drawn_and_explained(step_figures: dict[str, Any]) -> None:
    fig = step_figures["a_only"][0][0]
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    assert any("p10–p90" in t and f"{TRIALS} trials × 10 drones" in t for t in labels), labels
    assert len(fig.axes[0].collections) == 1  # the band
    assert "at the right end of each curve" in fig.legends[0].get_title().get_text()
    fig = step_figures["comparison"][0][0]  # 8 runs: no bands, and the caption says so
    assert len(fig.axes[0].collections) == 0
    assert "bands not drawn" in fig.legends[0].get_title().get_text()


def test_no_band_when_every_drone_has_the_same_value(a_only: list[SimulationResult]) -> None:
    r = a_only[0]
    one = dataclasses.replace(r, peb_m=np.broadcast_to(r.peb_m[:, :1, :1], r.peb_m.shape).copy())
    fig = F.make_peb_figure([one])
    assert len(fig.axes[0].collections) == 0
    assert not any("p10–p90 of" in t.get_text() for t in fig.legends[0].get_texts())
    assert "No p10–p90 band" in fig.legends[0].get_title().get_text()


def test_singular_last_steps_end_value_at_the_last_finite_step(a_only: list[SimulationResult]) -> None:
    r = a_only[0]
    peb = r.peb_m.copy()
    peb[-3:] = np.inf  # every view singular at the last three steps
    fig = F.make_peb_figure([dataclasses.replace(r, peb_m=peb)])
    (note,) = [t for t in fig.axes[0].texts if t.get_gid() == F.END_VALUE_GID]
    k = STEPS - 4
    assert note.xy[0] == k and f"at k={k}" in note.get_text()
    assert "Gaps" in fig.legends[0].get_title().get_text()


def test_distributed_run_says_so(a_only: list[SimulationResult]) -> None:
    r = dataclasses.replace(a_only[0], extra={"distributed": 1.0})
    assert "distributed run" in F.make_peb_figure([r]).axes[0].get_title()
    assert "distributed run" in F.make_trajectories_figure(r)._suptitle.get_text()


def test_estimate_error_axes_are_labelled(a_only: list[SimulationResult]) -> None:
    ax = F.make_estimate_error_figure(a_only).axes[0]
    assert ax.get_title().startswith("Source estimate error vs step: paper_heterogeneous, A-optimality")
    assert ax.get_xlabel() == "step k"
    assert "estimate error" in ax.get_ylabel() and ax.get_ylabel().endswith("[m]")


def test_trajectories_explain_markers_and_mark_the_ends(a_only: list[SimulationResult]) -> None:
    r = a_only[0]
    fig = F.make_trajectories_figure(r)
    labels = [t.get_text() for t in fig.legends[0].get_texts()]
    for want in ("start, k = 0", f"end, k = {STEPS}", "source (true position)", "building (3)"):
        assert want in labels, labels
    assert any(t.startswith("ranging drones (4)") for t in labels)
    top = fig.axes[1]
    points = np.concatenate([c.get_offsets() for c in top.collections if len(c.get_offsets())])
    pos = r.positions_m[:, 0]
    for i in range(pos.shape[1]):
        for k in (0, STEPS):
            assert np.isclose(points, pos[k, i, :2]).all(-1).any(), f"drone {i + 1} has no marker at k={k}"


@pytest.mark.parametrize(
    ("lo", "hi"),
    [(5.1, 840.0), (6.6, 31.0), (20.4, 29.4), (5.69, 5.78), (0.3, 40.0), (1e-3, 1e3), (0.9, 1.1)],
)
def test_log_ticks_are_round_numbers_inside(lo: float, hi: float) -> None:
    ticks = F.log_ticks(lo, hi)
    assert len(ticks) >= 3, ticks
    assert all(lo <= t <= hi for t in ticks)
    assert all(PLAIN_NUMBER.match(F.format_tick(t)) for t in ticks if t >= 1e-3)
    assert ticks == sorted(set(ticks))


@pytest.mark.parametrize(("value", "text"), [(7.3449, "7.34"), (20.72, "20.7"), (136.4, "136"), (0.40213, "0.402"), (9.996, "10.0"), (999.7, "1000")])
def test_format_value_three_significant_digits(value: float, text: str) -> None:
    assert F.format_value(value) == text


def test_write_results_writes_every_figure(a_only: list[SimulationResult], tmp_path: Path) -> None:
    write_results(a_only, tmp_path)
    names = sorted(p.name for p in (tmp_path / "figures").iterdir())
    assert names == sorted(["peb.png", "estimate_error.png", f"trajectories_{run_name(a_only[0])}.png"])
    for p in (tmp_path / "figures").iterdir():
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_degenerate_runs_still_draw(a_only: list[SimulationResult], tmp_path: Path) -> None:
    """Every view singular at every step, and a drone lost half-way (NaN positions, as a
    distributed run records them): the figures are still written, without end values."""
    r = a_only[0]
    pos = r.positions_m.copy()
    pos[STEPS // 2 :, :, 3] = np.nan
    broken = dataclasses.replace(r, peb_m=np.full_like(r.peb_m, np.inf), positions_m=pos)
    F.write_figures([broken], tmp_path)
    assert not [t for t in F.make_peb_figure([broken]).axes[0].texts if t.get_gid() == F.END_VALUE_GID]
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["peb.png", "estimate_error.png", f"trajectories_{run_name(r)}.png"])
