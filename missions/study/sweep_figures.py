"""The figures of a sweep (:mod:`missions.study.sweep`): the final mean PEB against each varied
key, one line per criterion (and per value of the other varied keys), with its 95 % interval
over the trials as a band, on a log axis with plain-number ticks (:mod:`missions.study.figures`).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from missions.study.figures import _pyplot, _save, _set_log_axis, format_value

#: Line style per criterion (as the PEB figure: A solid, D dashed).
CRITERION_STYLES = {"A": "-", "D": "--"}


def _numeric(texts: Sequence[str]) -> list[float] | None:
    """The values as numbers if every one is a number (then the x axis is numeric)."""
    try:
        return [float(t) for t in texts]
    except ValueError:
        return None


def make_sweep_figure(done: Mapping[int, Sequence[Mapping[str, Any]]], key: str, texts: Sequence[str], others: Sequence[str], title: str) -> Any:
    """Final mean PEB vs the values ``texts`` of ``key`` (x: the values, numeric if they all
    are, else in ``--vary`` order), a line per criterion and combination of the ``others``
    keys' values (and per policy), the 95 % interval over trials as a band; ``done``: the sweep's rows
    (``sweep.csv``'s, by cell); cells not finished (or every view singular) are gaps."""
    plt = _pyplot()
    numbers = _numeric(texts)
    xs = numbers if numbers is not None else list(range(len(texts)))
    lines: dict[tuple[str, ...], dict[str, tuple[float | None, float | None, float | None]]] = {}
    for rows in done.values():
        for r in rows:
            label = (str(r["criterion"]), str(r.get("policy", "fim")), *(f"{o}={r[o]}" for o in others))
            lines.setdefault(label, {})[str(r[key])] = (r["final_peb_mean_m"], r["final_peb_ci95_low_m"], r["final_peb_ci95_high_m"])
    fig, ax = plt.subplots(figsize=(8.0, 5.2), constrained_layout=True)
    cmap = plt.get_cmap("tab10")
    finite: list[float] = []
    for n, (label, points) in enumerate(sorted(lines.items())):
        y = np.array([np.nan if points.get(t, (None,))[0] is None else points[t][0] for t in texts], dtype=float)
        lo = np.array([np.nan if points.get(t, (None, None))[1] is None else points[t][1] for t in texts], dtype=float)
        hi = np.array([np.nan if points.get(t, (None, None, None))[2] is None else points[t][2] for t in texts], dtype=float)
        colour = cmap(n % 10)
        name = f"{label[0]}-optimality" + ("" if label[1] == "fim" else f", {label[1]}") + (f", {', '.join(label[2:])}" if label[2:] else "")
        ax.plot(xs, y, CRITERION_STYLES.get(label[0], "-"), marker="o", color=colour, label=name)
        ax.fill_between(xs, lo, hi, color=colour, alpha=0.18, linewidth=0)
        finite += [v for v in (*y, *lo, *hi) if np.isfinite(v) and v > 0]
    _set_log_axis(ax, min(finite, default=1.0), max(finite, default=10.0))
    if numbers is None:
        ax.set_xticks(xs, list(texts))
    else:
        ax.set_xticks(xs, [format_value(x) if len(t) > 8 else t for x, t in zip(xs, texts)])
    ax.set_xlabel(key)
    ax.set_ylabel("final mean PEB [m]")
    ax.set_title(title, fontsize=10)
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.14), ncol=2, fontsize=8, frameon=False)
    return fig


def plot_sweep(
    done: Mapping[int, Sequence[Mapping[str, Any]]], key: str, texts: Sequence[str], others: Sequence[str], title: str, path: Path
) -> None:
    """Save :func:`make_sweep_figure` to ``path``."""
    _save(make_sweep_figure(done, key, texts, others, title), path, dpi=130)
