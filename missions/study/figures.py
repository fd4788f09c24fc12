"""The figures of a results directory: the paper's Fig. 3 (PEB vs step), the estimate error, and
the paper's Fig. 2 (trajectories).

Every figure says what was run: its title names the missions, the design criterion or criteria
(A/D-optimality), the constraint activation rule when the paper's literal rule is among the runs,
the trials and the steps. Per-step curves are on a log axis labelled with plain numbers (5, 10,
20, 50, ...), each curve carries its final value at its right end, and the legend sits below
the axes with the meaning of every colour, line style, band and marker.

Each figure is built by a ``make_*`` function that returns the matplotlib figure (the tests
inspect it) and saved by the matching ``plot_*`` function. matplotlib runs headless (Agg) and
is imported only when a figure is made.
"""

from __future__ import annotations

import math
import textwrap
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from missions.study.layout import run_name
from missions.study.records import SimulationResult

CRITERION_NAMES = {"A": "A-optimality", "D": "D-optimality"}
RULE_NAMES = {"safe": "safe rule", "paper": "paper's literal rule"}
#: line style per (criterion, activation rule): the paper's Fig. 3 draws A solid and D dashed
LINESTYLES = {("A", "safe"): "-", ("D", "safe"): "--", ("A", "paper"): ":", ("D", "paper"): "-."}
ROLE_COLOURS = {"ranging": "tab:red", "bearing": "tab:purple", "joint": "tab:green"}
SOURCE_COLOUR = "tab:blue"
#: at most this many runs get their p10-p90 band drawn (more overlap into a grey wash)
MAX_BANDS = 4
#: gid of the end-value annotations (the tests find them by it)
END_VALUE_GID = "end-value"
#: mantissas of the log-axis major ticks, sparsest first; the first giving enough ticks wins
_MANTISSAS: tuple[tuple[float, ...], ...] = (
    (1.0,),
    (1.0, 2.0, 5.0),
    (1.0, 2.0, 3.0, 5.0),
    (1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 6.0, 8.0),
)
_MIN_TICKS = 4
_MAX_DECADE_TICKS = 8
_MAX_END_GAP = 0.2


def _pyplot() -> ModuleType:
    """matplotlib.pyplot on the Agg backend (headless), imported only when a figure is made."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def write_figures(results: Sequence[SimulationResult], figures_dir: Path) -> list[Path]:
    """Write every figure of a results directory into ``figures_dir``; return their paths."""
    paths = [figures_dir / "peb.png", figures_dir / "estimate_error.png"]
    plot_peb(results, paths[0])
    plot_estimate_error(results, paths[1])
    for r in results:
        paths.append(figures_dir / f"trajectories_{run_name(r)}.png")
        plot_trajectories(r, paths[-1])
    return paths


# ---------------------------------------------------------------------------------------------
# What was run, in words


def _rule(result: SimulationResult) -> str:
    return result.spec.mission.constraints.activation


def _distributed(result: SimulationResult) -> bool:
    return bool(result.extra.get("distributed", 0.0))


def _count(values: Sequence[int], noun: str) -> str:
    lo, hi = min(values), max(values)
    if lo == hi:
        return f"{lo} {noun}{'' if lo == 1 else 's'}"
    return f"{lo}-{hi} {noun}s"


def _criteria_text(criteria: Sequence[str]) -> str:
    crit = sorted(set(criteria))
    return CRITERION_NAMES[crit[0]] if len(crit) == 1 else "A- and D-optimality"


def _rules_text(rules: Sequence[str]) -> str:
    """The activation rule(s) in words; empty when every run used the default safe rule."""
    rs = sorted(set(rules), key=["safe", "paper"].index)
    if rs == ["safe"]:
        return ""
    if rs == ["paper"]:
        return "paper's literal constraint rule"
    return "safe and paper's literal constraint rules"


def describe_runs(results: Sequence[SimulationResult]) -> str:
    """One line saying what was run: missions, criteria, rule(s), trials × steps, mode."""
    return ", ".join(_run_parts(results))


def _run_parts(results: Sequence[SimulationResult]) -> list[str]:
    ids = list(dict.fromkeys(r.spec.mission.id for r in results))
    missions = ids[0] if len(ids) == 1 else f"{len(ids)} missions ({', '.join(ids)})"
    parts = [missions, _criteria_text([r.spec.criterion for r in results])]
    rules = _rules_text([_rule(r) for r in results])
    if rules:
        parts.append(rules)
    size = f"{_count([r.spec.trials for r in results], 'trial')} × {_count([r.spec.steps for r in results], 'step')}"
    parts.append(f"{size} × {_count([r.spec.mission.drones.count for r in results], 'drone')}")
    if any(_distributed(r) for r in results):
        parts.append("distributed run (fimnav launch)")
    if any(r.extra.get("oracle_estimate", 0.0) for r in results):
        parts.append("planned with the true source")
    if any(r.spec.mission.comms.faults.enabled for r in results):
        parts.append("with injected comms faults")
    return parts


def _title(what: str, results: Sequence[SimulationResult], width: int = 95) -> str:
    """``what: <what was run>``, wrapped between its comma-separated parts (and between the
    missions of a long list), never inside a part such as "10 drones"."""
    nbsp = "\u00a0"  # textwrap does not break at a no-break space
    parts = [p.replace(" ", nbsp).replace("," + nbsp, ", ") for p in _run_parts(results)]
    text = f"{what.replace(' ', nbsp)}: " + ", ".join(parts)
    return "\n".join(textwrap.wrap(text, width=width, break_long_words=False, break_on_hyphens=False)).replace(nbsp, " ")


def _roles_text(result: SimulationResult) -> str:
    roles = list(result.spec.mission.drones.roles)
    counts = {role: roles.count(role) for role in ROLE_COLOURS if role in roles}
    return ", ".join(f"{n} {role}" for role, n in counts.items())


# ---------------------------------------------------------------------------------------------
# Log axis with plain-number ticks


def log_ticks(lo: float, hi: float) -> list[float]:
    """Major tick values for a log axis from ``lo`` to ``hi`` (> 0): round numbers, at least
    four inside when the range allows it (1-2-5 per decade and denser for narrow ranges, evenly
    spaced round numbers when even 1-1.5-2-3-4-5-6-8 leaves fewer than four inside)."""
    if not (0.0 < lo < hi and math.isfinite(hi)):
        raise ValueError(f"log_ticks: need 0 < lo < hi < inf, found {lo!r}, {hi!r}")
    e0, e1 = math.floor(math.log10(lo)) - 1, math.ceil(math.log10(hi)) + 1
    span = math.log10(hi / lo)
    for mantissas in _MANTISSAS:
        ticks = [float(f"{m * 10.0**e:.6g}") for e in range(e0, e1 + 1) for m in mantissas]
        inside = [t for t in ticks if lo <= t <= hi]
        if len(inside) > _MAX_DECADE_TICKS and len(mantissas) == 1:
            step = math.ceil(len(inside) / _MAX_DECADE_TICKS)
            return inside[::step]
        # enough ticks, and neither end unlabelled over more than a fifth of the span
        if len(inside) >= _MIN_TICKS and max(math.log10(inside[0] / lo), math.log10(hi / inside[-1])) <= _MAX_END_GAP * span:
            return inside
    from matplotlib.ticker import MaxNLocator

    for nbins in range(5, 13):
        ticks = [float(f"{t:.6g}") for t in MaxNLocator(nbins=nbins, steps=[1, 2, 5, 10]).tick_values(lo, hi)]
        inside = [t for t in ticks if lo <= t <= hi]
        if len(inside) >= _MIN_TICKS - 1:
            break
    return inside


def format_tick(value: float) -> str:
    """A tick label as a plain number: 0.5, 5, 10, 150, 2000."""
    return f"{value:.6g}"


def format_value(value: float) -> str:
    """A value with three significant digits as a plain number: 0.402, 7.34, 20.7, 136."""
    value = float(f"{value:.3g}")  # 9.996 -> 10.0, not 10.00
    a = abs(value)
    if a >= 100:
        return f"{value:.0f}"
    if a >= 10:
        return f"{value:.1f}"
    if a >= 1:
        return f"{value:.2f}"
    return f"{value:.3g}"


def _set_log_axis(ax: Any, lo: float, hi: float) -> None:
    """Log y axis over the data range [lo, hi] (padded), plain-number major ticks, 1..9 minor."""
    from matplotlib.ticker import FixedFormatter, FixedLocator, LogLocator, NullFormatter

    if not (np.isfinite(lo) and np.isfinite(hi) and lo > 0):
        lo, hi = 1.0, 10.0
    if hi <= lo * 1.001:
        lo, hi = lo / 1.05, hi * 1.05
    pad = max((hi / lo) ** 0.04, 1.01)
    lo, hi = lo / pad, hi * pad
    ax.set_yscale("log")
    ax.set_ylim(lo, hi)
    ticks = log_ticks(lo, hi)
    ax.yaxis.set_major_locator(FixedLocator(ticks))
    ax.yaxis.set_major_formatter(FixedFormatter([format_tick(t) for t in ticks]))
    if len(ticks) >= 2 and ticks[1] / ticks[0] < 1.5 and _evenly_spaced(ticks):
        step = ticks[1] - ticks[0]  # narrow range: round numbers evenly spaced, minor at halves
        minor = np.arange(ticks[0] - step, ticks[-1] + step, step / 2.0)
        ax.yaxis.set_minor_locator(FixedLocator([t for t in minor if lo <= t <= hi]))
    else:
        ax.yaxis.set_minor_locator(LogLocator(base=10.0, subs=[float(m) for m in range(1, 10)], numticks=100))
    ax.yaxis.set_minor_formatter(NullFormatter())


def _evenly_spaced(ticks: Sequence[float]) -> bool:
    d = np.diff(ticks)
    return bool(np.allclose(d, d[0], rtol=1e-6))


# ---------------------------------------------------------------------------------------------
# Per-step figures (PEB, estimate error)


class _Curve:
    """One run's per-step curve: centre line, optional p10-p90 band, its style."""

    def __init__(self, result: SimulationResult, centre: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
        self.result = result
        self.centre = np.where(np.isfinite(centre) & (centre > 0), centre, np.nan)
        self.lo = np.where(np.isfinite(lo) & (lo > 0), lo, np.nan)
        self.hi = np.where(np.isfinite(hi) & (hi > 0), hi, np.nan)
        self.steps = np.arange(len(centre))

    @property
    def criterion(self) -> str:
        return self.result.spec.criterion

    @property
    def rule(self) -> str:
        return _rule(self.result)

    @property
    def linestyle(self) -> str:
        return LINESTYLES[(self.criterion, self.rule)]

    def last(self) -> tuple[int, float] | None:
        """(step, value) of the last finite point, None if there is none."""
        finite = np.flatnonzero(np.isfinite(self.centre))
        if finite.size == 0:
            return None
        k = int(finite[-1])
        return k, float(self.centre[k])


def _peb_curves(results: Sequence[SimulationResult]) -> list[_Curve]:
    out = []
    for r in results:
        stats = r.peb_stats()
        out.append(_Curve(r, stats["mean"], stats["p10"], stats["p90"]))
    return out


def _error_curves(results: Sequence[SimulationResult]) -> list[_Curve]:
    out = []
    for r in results:
        err = r.estimate_error_m.reshape(r.estimate_error_m.shape[0], -1)
        out.append(_Curve(r, np.median(err, axis=-1), np.percentile(err, 10, axis=-1), np.percentile(err, 90, axis=-1)))
    return out


def make_peb_figure(results: Sequence[SimulationResult]) -> Any:
    """Mean PEB (eq. 18) vs step of every run on a log axis: the paper's Fig. 3."""
    curves = _peb_curves(results)
    singular = any(np.isnan(c.centre).any() for c in curves)
    note = "Gaps: every drone's view singular at that step (mean undefined)." if singular else ""
    return _step_figure(
        curves,
        title=_title("Mean PEB vs step", results),
        ylabel=r"$\overline{\mathrm{PEB}}^{(k)}$ [m]",
        centre_name="mean PEB",
        band_of="PEB",
        note=note,
        band_csv=" (each run's are in runs/<run>/peb.csv)",
    )


def make_estimate_error_figure(results: Sequence[SimulationResult]) -> Any:
    """Median source estimate error |p̂0 − p0| vs step of every run on a log axis."""
    return _step_figure(
        _error_curves(results),
        title=_title("Source estimate error vs step", results),
        ylabel=r"median estimate error $\|\hat{\mathbf{p}}_0-\mathbf{p}_0\|$ [m]",
        centre_name="median estimate error",
        band_of="estimate error",
        note="",
    )


def plot_peb(results: Sequence[SimulationResult], path: Path) -> None:
    """Save :func:`make_peb_figure` to ``path``."""
    _save(make_peb_figure(results), path, dpi=130)


def plot_estimate_error(results: Sequence[SimulationResult], path: Path) -> None:
    """Save :func:`make_estimate_error_figure` to ``path``."""
    _save(make_estimate_error_figure(results), path, dpi=130)


def _save(fig: Any, path: Path, dpi: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    _pyplot().close(fig)


def _mission_colours(results: Sequence[SimulationResult]) -> dict[str, Any]:
    ids = list(dict.fromkeys(r.spec.mission.id for r in results))
    cmap = _pyplot().get_cmap("tab10")
    return {mid: cmap(i % 10) for i, mid in enumerate(ids)}


def _step_figure(curves: list[_Curve], title: str, ylabel: str, centre_name: str, band_of: str, note: str, band_csv: str = "") -> Any:
    """Per-step log figure: curves, bands, end values at the right, legend and caption below."""
    plt = _pyplot()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    results = [c.result for c in curves]
    colours = _mission_colours(results)
    styles = list(dict.fromkeys((c.criterion, c.rule) for c in curves))
    spread = any(np.nanmax(c.hi / c.lo, initial=1.0) > 1.0005 for c in curves if np.isfinite(c.hi / c.lo).any())
    bands = len(curves) <= MAX_BANDS and spread
    # tall enough for one end-value label per curve at the right of the axes
    height = max(5.6, 0.17 * len(curves) + 3.6)
    fig, ax = plt.subplots(figsize=(9.0, height), layout="constrained")
    fig.get_layout_engine().set(w_pad=0.08)
    for c in curves:
        colour = colours[c.result.spec.mission.id]
        ax.plot(c.steps, c.centre, c.linestyle, color=colour, lw=1.6)
        if bands:
            ax.fill_between(c.steps, c.lo, c.hi, color=colour, alpha=0.13, lw=0)
    data = [c.centre for c in curves] + ([x for c in curves for x in (c.lo, c.hi)] if bands else [])
    finite = np.concatenate([d[np.isfinite(d)] for d in data]) if data else np.array([])
    lo, hi = (float(finite.min()), float(finite.max())) if finite.size else (1.0, 10.0)
    _set_log_axis(ax, lo, hi)
    n_steps = max(len(c.steps) for c in curves)
    ax.set_xlim(0, max(n_steps - 1, 1))
    ax.set_xlabel("step k")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=10.5)
    ax.grid(True, which="major", alpha=0.45)
    ax.grid(True, which="minor", alpha=0.15)

    # legend: one colour per mission (first column), one line style per (criterion, rule)
    # (second column, when there are several), the band
    one_style = LINESTYLES[styles[0]] if len(styles) == 1 else "-"
    missions: list[Any] = [
        Line2D([], [], color=colours[r.spec.mission.id], ls=one_style, lw=2.0, label=f"{r.spec.mission.id} ({_roles_text(r)})")
        for r in {r.spec.mission.id: r for r in results}.values()
    ]
    who = f"{_count([r.spec.trials for r in results], 'trial')} × {_count([r.spec.mission.drones.count for r in results], 'drone')}"
    if bands:
        shade = next(iter(colours.values())) if len(colours) == 1 else "0.5"
        missions.append(Patch(facecolor=shade, alpha=0.3, label=f"p10–p90 of the {band_of} over {who}"))
    line_styles: list[Any] = []
    if len(styles) > 1:
        rules = {rule for _, rule in styles}
        for crit, rule in sorted(styles, key=lambda s: (s[1] != "safe", s[0])):
            label = CRITERION_NAMES[crit] if rules == {"safe"} else f"{CRITERION_NAMES[crit]}, {RULE_NAMES[rule]}"
            line_styles.append(Line2D([], [], color="0.2", ls=LINESTYLES[(crit, rule)], lw=1.6, label=label))
    caption = [f"{centre_name} over {who} per step; at the right end of each curve: its value at the last step."]
    if not spread:
        caption.append(f"No p10–p90 band: the drones' {band_of} values coincide at every step (p10 = p90).")
    elif not bands:
        caption.append(f"p10–p90 bands not drawn for more than {MAX_BANDS} runs{band_csv}.")
    if note:
        caption.append(note)
    rows = max(len(missions), len(line_styles))
    blank = Line2D([], [], ls="", label=" ")
    handles = missions + [blank] * (rows - len(missions))
    if line_styles:
        handles += line_styles + [blank] * (rows - len(line_styles))
    fig.legend(
        handles=handles,
        loc="outside lower center",
        ncol=2 if line_styles else 1,
        fontsize=8.5,
        frameon=True,
        title="\n".join(line for sentence in caption for line in textwrap.wrap(sentence, 120)),
        title_fontsize=8,
    )

    _annotate_ends(fig, ax, curves, colours)
    return fig


def _end_tag(curve: _Curve, curves: Sequence[_Curve]) -> str:
    """What distinguishes a curve from others of the same colour: criterion and/or rule."""
    same = [c for c in curves if c.result.spec.mission.id == curve.result.spec.mission.id]
    tags = []
    if len({c.criterion for c in same}) > 1:
        tags.append(curve.criterion)
    if len({c.rule for c in same}) > 1:
        tags.append("literal" if curve.rule == "paper" else "safe")
    return f" ({', '.join(tags)})" if tags else ""


def _annotate_ends(fig: Any, ax: Any, curves: Sequence[_Curve], colours: dict[str, Any]) -> None:
    """Each curve's last value as text right of the axes, joined to the curve's end by a line;
    labels are spread vertically so that they do not overlap."""
    ends = [(c, e) for c in curves if (e := c.last()) is not None]
    if not ends:
        return
    fig.canvas.draw()  # the layout fixes the axes height, which sets the labels' spacing
    height_px = ax.get_window_extent().height
    gap = 1.35 * 8.5 * fig.dpi / 72.0 / max(height_px, 1.0)
    lo, hi = (math.log10(v) for v in ax.get_ylim())
    want = [(math.log10(e[1]) - lo) / (hi - lo) for _, e in ends]
    order = np.argsort(want, kind="stable")
    pos = np.array(want, dtype=float)[order]
    for i in range(1, len(pos)):
        pos[i] = max(pos[i], pos[i - 1] + gap)
    overflow = pos[-1] - 1.0
    if overflow > 0:
        pos -= overflow
        for i in range(len(pos) - 2, -1, -1):
            pos[i] = min(pos[i], pos[i + 1] - gap)
    placed = np.empty_like(pos)
    placed[order] = pos
    n_last = max(len(c.steps) for c in curves) - 1
    for (c, (k, value)), y in zip(ends, placed):
        colour = colours[c.result.spec.mission.id]
        at = "" if k == n_last else f" at k={k}"
        ax.annotate(
            f"{format_value(value)} m{at}{_end_tag(c, curves)}",
            xy=(k, value),
            xycoords="data",
            xytext=(1.06, y),
            textcoords="axes fraction",
            va="center",
            ha="left",
            fontsize=8.5,
            color=colour,
            annotation_clip=False,
            arrowprops={"arrowstyle": "-", "color": colour, "lw": 0.9, "ls": c.linestyle, "shrinkA": 0, "shrinkB": 2, "relpos": (0.0, 0.5)},
            gid=END_VALUE_GID,
        )


# ---------------------------------------------------------------------------------------------
# Trajectories: the paper's Fig. 2


def _trajectories_legend(m: Any, last_k: int, moving: bool, d_s: float) -> list[Any]:
    """The legend of :func:`make_trajectories_figure`: a line per sensing role flown, start and
    end markers (``last_k``: the last step), the source (a track when ``moving``), its keep-out
    circle (radius ``d_s`` m, if any) and the buildings."""
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    roles = list(m.drones.roles)
    handles: list[Any] = [
        Line2D([], [], ls="--", marker="s", color=ROLE_COLOURS[role], label=f"{role} drones ({roles.count(role)}), path dashed")
        for role in ROLE_COLOURS
        if role in roles
    ]
    handles += [
        Line2D([], [], ls="", marker="s", markersize=6, markerfacecolor="white", markeredgecolor="0.2", label="start, k = 0"),
        Line2D([], [], ls="", marker="s", markersize=6, color="0.5", markeredgecolor="k", label=f"end, k = {last_k}"),
        Line2D(
            [],
            [],
            ls="-" if moving else "",
            marker="^",
            markersize=8,
            color=SOURCE_COLOUR,
            label="source (track; triangle: last position)" if moving else "source (true position)",
        ),
    ]
    if d_s > 0:
        handles.append(Line2D([], [], ls=":", color=SOURCE_COLOUR, label=f"source keep-out $d_S^*$ = {d_s:g} m (top view)"))
    if m.obstacles:
        handles.append(Patch(facecolor="0.6", edgecolor="0.35", alpha=0.5, label=f"building ({len(m.obstacles)})"))
    return handles


def make_trajectories_figure(result: SimulationResult, trial: int = 0) -> Any:
    """3-D trajectories of one trial (the paper's Fig. 2) beside a top view with the source's
    keep-out circle: buildings grey, the source a blue triangle, each drone's path dashed in its
    sensing role's colour, an open square at k = 0 and a filled square at the last step."""
    plt = _pyplot()
    from matplotlib.patches import Circle, Rectangle
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    m = result.spec.mission
    pos = result.positions_m[:, trial]
    n_pos = pos.shape[0]
    src = result.source_m
    moving = bool(np.ptp(src, axis=0).max() > 1e-9)
    fig = plt.figure(figsize=(12.0, 6.4), layout="constrained")
    ax3 = fig.add_subplot(1, 2, 1, projection="3d")
    ax2 = fig.add_subplot(1, 2, 2)

    for box in m.obstacles:
        lo, hi = np.asarray(box.min_m), np.asarray(box.max_m)
        ax3.add_collection3d(Poly3DCollection(_box_faces(lo, hi), facecolor="0.6", edgecolor="0.35", alpha=0.3))
        ax2.add_patch(Rectangle((lo[0], lo[1]), hi[0] - lo[0], hi[1] - lo[1], facecolor="0.6", edgecolor="0.35", alpha=0.5))
    for i, role in enumerate(m.drones.roles):
        c = ROLE_COLOURS[role]
        track = pos[:, i]
        ok = np.flatnonzero(np.isfinite(track).all(-1))
        if ok.size == 0:
            continue
        first, last = track[ok[0]], track[ok[-1]]
        ax3.plot(track[:, 0], track[:, 1], track[:, 2], "--", color=c, lw=0.9)
        ax3.scatter(*first, marker="s", s=26, facecolor="white", edgecolor=c, linewidths=1.2, depthshade=False)
        ax3.scatter(*last, marker="s", s=34, color=c, edgecolor="k", linewidths=0.8, depthshade=False)
        ax2.plot(track[:, 0], track[:, 1], "--", color=c, lw=0.9)
        ax2.scatter(first[0], first[1], marker="s", s=26, facecolor="white", edgecolor=c, linewidths=1.2, zorder=3)
        ax2.scatter(last[0], last[1], marker="s", s=34, color=c, edgecolor="k", linewidths=0.8, zorder=3)
    if moving:
        ax3.plot(src[:, 0], src[:, 1], src[:, 2], "-", color=SOURCE_COLOUR, lw=1.2)
        ax2.plot(src[:, 0], src[:, 1], "-", color=SOURCE_COLOUR, lw=1.2)
    ax3.scatter(*src[-1], marker="^", color=SOURCE_COLOUR, s=70, depthshade=False)
    ax2.scatter(src[-1, 0], src[-1, 1], marker="^", color=SOURCE_COLOUR, s=70, zorder=4)
    d_s = m.constraints.d_source_m
    if d_s > 0:
        ax2.add_patch(Circle((src[-1, 0], src[-1, 1]), d_s, fill=False, ls=":", color=SOURCE_COLOUR, lw=1.0))

    ax3.set_xlabel("x east [m]")
    ax3.set_ylabel("y north [m]")
    ax3.set_zlabel("z up [m]")
    ax3.set_title("3-D view", fontsize=10)
    ax2.set_xlabel("x east [m]")
    ax2.set_ylabel("y north [m]")
    ax2.set_title("top view", fontsize=10)
    ax2.set_aspect("equal", adjustable="datalim")
    ax2.grid(True, alpha=0.3)

    last_k = n_pos - 1
    crit = CRITERION_NAMES[result.spec.criterion]
    rule = "safe constraint rule" if _rule(result) == "safe" else "paper's literal constraint rule"
    mode = "distributed run (fimnav launch)" if _distributed(result) else f"trial {trial} of {result.spec.trials}"
    fig.suptitle(f"Trajectories: {m.id} ({_roles_text(result)}), {crit}, {rule}\n{mode}, steps k = 0…{last_k}", fontsize=11)

    handles = _trajectories_legend(m, last_k, moving, d_s)
    fig.legend(handles=handles, loc="outside lower center", ncol=min(4, len(handles)), fontsize=8.5)
    return fig


def plot_trajectories(result: SimulationResult, path: Path, trial: int = 0) -> None:
    """Save :func:`make_trajectories_figure` to ``path``."""
    _save(make_trajectories_figure(result, trial), path, dpi=120)


def _box_faces(lo: np.ndarray, hi: np.ndarray) -> list[list[np.ndarray]]:
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0], [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]])
    idx = [[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4], [2, 3, 7, 6], [1, 2, 6, 5], [0, 3, 7, 4]]
    return [[v[j] for j in face] for face in idx]
