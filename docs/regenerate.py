"""Regenerate every result table and figure of the documentation from scratch.

    python docs/regenerate.py                 # the full size the docs quote (8 minutes on a 2-core Zen 5 machine)
    python docs/regenerate.py --trials 5 --steps 100 --out /tmp/quick --no-docs   # a quick look

It runs the studies that the docs name, as ``fimnav montecarlo`` commands, through the same
library call (:func:`missions.study.montecarlo.write_study`, in this process, one study after the
other), then rewrites the tables between the markers

    <!-- BEGIN regenerate.py: NAME -->
    ...
    <!-- END regenerate.py: NAME -->

in ``docs/case-study.md`` (``case-study``; ``policies``: the navigation policies compared;
``power``: the cost of not knowing the transmit power),
``docs/distributed.md`` (``fault-table``) and ``docs/reliability.md`` (``fault-grid``), and
copies the figures into ``docs/figures/``.
``--only NAME`` (repeatable) runs and rewrites just those blocks. Each table states the command, the commit it was
measured at and the package versions. The runs are deterministic for a given mission seed, so
the same commit gives the same tables; a tree with uncommitted changes is stamped as such.
They run with pinned numerics (:mod:`missions.runtime.numerics`, the commands shown as
``FIMNAV_NUMERICS=portable fimnav ...``), so that any x86-64 machine with AVX2 and FMA gives the
same tables bit for bit: with each machine's own choices the ranging runs' trajectories part
with the last bits (their statistics agree, a rare event such as a keep-out crossing may come or
go). On a machine that cannot run them, or with ``FIMNAV_NUMERICS=host``, the script runs with
the host's and says so in the stamp.

The per-command results directories are kept under ``--out`` (default ``results/docs``): each
has the ``summary.json`` the tables are read from, the per-step CSVs and the figures.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import shutil
import subprocess
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

DOCS = Path(__file__).resolve().parent
REPO = DOCS.parent
if str(REPO) not in sys.path[:1]:
    sys.path.insert(0, str(REPO))  # this clone's code, whatever else is installed

from missions.runtime.numerics import NUMERICS_VARIABLE, pin_unless_host  # noqa: E402

#: Pinned before numpy loads (``None``), else why not: this machine cannot run the pinned
#: numerics, or ``FIMNAV_NUMERICS=host`` asks for its own.
UNPINNED = pin_unless_host(os.environ)

import numpy as np  # noqa: E402

#: Paper missions in the order of the case-study table, with the label the table uses.
CASE_STUDY_RUNS: tuple[tuple[str, str], ...] = (
    ("paper_ranging_los", "ranging, LOS"),
    ("paper_ranging_nlos", "ranging, buildings"),
    ("paper_dynamic_source", "ranging, moving source"),
    ("paper_bearing", "bearing, buildings"),
    ("paper_joint", "joint, buildings"),
    ("paper_heterogeneous", "heterogeneous, buildings"),
)
PAPER_NAMES = ("ranging_los", "ranging_nlos", "dynamic_source", "bearing", "joint", "heterogeneous")
FIG3_NAMES = ("ranging_nlos", "bearing", "joint", "heterogeneous")
TRAJECTORY_RUNS = ("paper_heterogeneous_A", "paper_ranging_nlos_A", "paper_joint_A", "paper_bearing_A")

#: (record loss probability, extra delay in steps) of the fault table, first row without faults.
FAULT_SETTINGS: tuple[tuple[float, int], ...] = ((0.0, 0), (0.1, 0), (0.2, 0), (0.4, 0), (0.0, 3), (0.2, 3))
FAULT_TRIALS = 20

#: The fault grid of docs/reliability.md: every paper mission, A and D, 100 trials, under each
#: of these settings (label, --set overrides).
GRID_SETTINGS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("no faults", ()),
    ("20 % loss", ("comms.faults.loss=0.2",)),
    ("3 steps delay", ("comms.faults.extra_delay_steps=3",)),
    ("loss and delay", ("comms.faults.loss=0.2", "comms.faults.extra_delay_steps=3")),
    ("partition, 50 steps", ("comms.faults.partition_start_step=100", "comms.faults.partition_steps=50")),
)
GRID_TRIALS = 100

#: The policy comparison of docs/case-study.md: Fig. 3's missions under every navigation policy
#: (planner/policies.py), each mission's criterion, with the optimum; trials per run.
POLICY_TRIALS = 20

#: The cost of not knowing the transmit power (docs/case-study.md): the paper missions whose
#: drones range (bearings do not depend on the power), A and D, with the power known and with
#: it unknown (``source.power=unknown``), the same trials; trials per run.
POWER_NAMES = ("ranging_los", "ranging_nlos", "joint", "heterogeneous")
POWER_TRIALS = 20

FAMILIES = ("uav", "source", "obstacle", "altitude", "speed", "turn_rate")


@dataclass(frozen=True)
class Command:
    """One study the docs name, as the ``fimnav montecarlo`` command that runs it and the
    results directory it writes."""

    name: str
    missions: tuple[str, ...]
    out: Path
    criterion: str | None = None
    activation: str | None = None
    trials: int | None = None
    steps: int | None = None
    #: worker processes (``--jobs``; None: the command's default, one)
    jobs: int | None = None
    figures: bool = True
    #: ``--set KEY=VALUE`` overrides
    sets: tuple[str, ...] = ()
    #: The results directory of the same runs without faults, whose baselines this command
    #: reads instead of simulating them again (``--baselines``; the same numbers).
    baselines: Path | None = None
    #: ``--policy`` (None: each mission's)
    policy: str | None = None
    #: ``--optimum``
    optimum: bool = False

    @property
    def args(self) -> tuple[str, ...]:
        """The command's arguments after ``fimnav montecarlo`` (without ``--out``, ``--baselines``)."""
        return (
            *self.missions,
            *(["--criterion", self.criterion] if self.criterion else []),
            *(["--activation", self.activation] if self.activation else []),
            *(["--trials", str(self.trials)] if self.trials else []),
            *(["--steps", str(self.steps)] if self.steps else []),
            *(["--jobs", str(self.jobs)] if self.jobs is not None else []),
            *([] if self.figures else ["--no-figures"]),
            *(a for kv in self.sets for a in ("--set", kv)),
            *(["--policy", self.policy] if self.policy else []),
            *(["--optimum"] if self.optimum else []),
        )

    def argv(self) -> list[str]:
        reuse = ["--baselines", str(self.baselines)] if self.baselines is not None else []
        return ["montecarlo", *self.args, "--out", str(self.out), *reuse]

    def shown(self) -> str:
        """The command as a user types it (results directory left to its default), with the
        numerics it ran with."""
        pinned = f"{NUMERICS_VARIABLE}=portable " if UNPINNED is None else ""
        return pinned + "fimnav " + " ".join(["montecarlo", *self.args])


def commands(out: Path, trials: int | None, steps: int | None, jobs: int, figures: bool) -> dict[str, Command]:
    """Every command the docs' tables and figures come from."""
    paper = tuple(f"paper/{n}" for n in PAPER_NAMES)
    cmds = {
        "case-study": Command("case-study", paper, out / "case-study", "both", "both", trials, steps, jobs, figures),
        "fig3": Command("fig3", tuple(f"paper/{n}" for n in FIG3_NAMES), out / "fig3", "both", None, trials, steps, jobs, figures),
    }
    first = out / "faults-loss{:g}-delay{}".format(*FAULT_SETTINGS[0])
    for loss, delay in FAULT_SETTINGS:
        name = f"faults-loss{loss:g}-delay{delay}"
        sets = (f"comms.faults.loss={loss:g}", f"comms.faults.extra_delay_steps={delay}")
        cmds[name] = Command(name, ("paper/heterogeneous",), out / name, trials=trials or FAULT_TRIALS, steps=steps, figures=False, sets=sets,
                             baselines=first if loss or delay else None)  # fmt: skip
    cmds["policies"] = Command("policies", tuple(f"paper/{n}" for n in FIG3_NAMES), out / "policies", trials=trials or POLICY_TRIALS, steps=steps,
                               jobs=jobs, policy="all", optimum=True)  # fmt: skip
    power = tuple(f"paper/{n}" for n in POWER_NAMES)
    cmds["power-known"] = Command("power-known", power, out / "power-known", "both", None, trials or POWER_TRIALS, steps, jobs, False)
    cmds["power-unknown"] = Command("power-unknown", power, out / "power-unknown", "both", None, trials or POWER_TRIALS, steps, jobs, False,
                                    ("source.power=unknown",))  # fmt: skip
    for g, (_, sets) in enumerate(GRID_SETTINGS):
        cmds[f"grid-{g}"] = Command(f"grid-{g}", paper, out / f"grid-{g}", "both", None, trials or GRID_TRIALS, steps, jobs, False, sets,
                                    out / "grid-0" if sets else None)  # fmt: skip
    return cmds


#: Which commands each docs block is made from.
BLOCKS = {
    "case-study": ("case-study", "fig3"),
    "fault-table": ("faults-",),
    "fault-grid": ("grid-",),
    "policies": ("policies",),
    "power": ("power-",),
}


def stamp() -> str:
    """Commit, dirty flag and versions, for the tables' provenance line."""
    from importlib.metadata import version

    import numpy
    import scipy

    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", *args], cwd=REPO, capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return ""

    commit = git("rev-parse", "--short=7", "HEAD") or "unknown"
    dirty = " with uncommitted changes" if git("status", "--porcelain", "--untracked-files=no") else ""
    numerics = "pinned numerics" if UNPINNED is None else f"the host's numerics ({UNPINNED})"
    return (f"commit {commit}{dirty}, fimnav {version('fimnav')}, Python {sys.version.split()[0]}, "
            f"numpy {numpy.__version__}, scipy {scipy.__version__}, {numerics}")


STAMP_FILE = "regenerate-stamp.txt"


def run_command(cmd: Command, when: str) -> list[dict[str, Any]]:
    """Run one study in this process (the library call ``fimnav montecarlo`` makes,
    :func:`missions.study.montecarlo.write_study`), write its results directory; return its run
    summaries (the directory also records ``when``, the commit and versions it ran at)."""
    from tqdm import tqdm

    from comms.errors import FimnavError
    from missions.format.loader import parse_overrides
    from missions.study.executors import local_executor
    from missions.study.montecarlo import expand_runs, study_size, write_study
    from planner.policies import POLICIES

    print(f"$ {cmd.shown()} --out {cmd.out}", flush=True)
    if cmd.out.exists():
        shutil.rmtree(cmd.out)
    try:
        policies = None if cmd.policy is None else (list(POLICIES) if cmd.policy == "all" else cmd.policy.split(","))
        specs = expand_runs(cmd.missions, parse_overrides(list(cmd.sets)), cmd.criterion, cmd.activation, cmd.trials, cmd.steps, policies)
        with tqdm(total=study_size(specs, cmd.baselines), unit="trial-step", desc=cmd.name, file=sys.stderr, disable=None) as bar:
            summaries = write_study(specs, cmd.out, command=["fimnav", *cmd.argv()], figures=cmd.figures, optimum=cmd.optimum,
                                    baselines=cmd.baselines, executor=local_executor(cmd.jobs or 1), progress=bar.update,
                                    warn=lambda why: bar.write(f"regenerate: --baselines: {why}", file=sys.stderr))  # fmt: skip
    except FimnavError as exc:
        raise SystemExit(f"regenerate: {cmd.shown()}: {exc}") from None
    (cmd.out / STAMP_FILE).write_text(when + "\n")
    return summaries


def reuse_command(cmd: Command) -> tuple[list[dict[str, Any]], str]:
    """The summaries and stamp of an earlier run of ``cmd`` (``--reuse``)."""
    try:
        return json.loads((cmd.out / "summary.json").read_text())["runs"], (cmd.out / STAMP_FILE).read_text().strip()
    except OSError as exc:
        raise SystemExit(f"regenerate: --reuse: {cmd.out} holds no complete earlier run ({exc.strerror}); run without --reuse") from None


# --------------------------------------------------------------------------- formatting

def num(x: float | None, digits: int = 3) -> str:
    """A value to ``digits`` significant figures, thousands grouped ('—' for undefined)."""
    if x is None:
        return "—"
    if abs(x) >= 10 ** digits:
        return f"{x:,.0f}".replace(",", " ")
    return f"{x:.{digits}g}"


def violations(s: dict[str, Any]) -> str:
    """Per family, inter-drone / source / obstacle / altitude / speed / turn rate."""
    v = s["violations"]
    text = " / ".join(f"{int(v[f]):,}".replace(",", " ") for f in FAMILIES)
    if v["source"]:
        text += f" (worst source margin {s['worst_margins_m']['source']:+.2f} m)".replace("-", "−")
    return text


def case_study_table(runs: Sequence[dict[str, Any]]) -> list[str]:
    """The case study's table: the default rule beside the paper's literal rule."""
    by = {r["run"]: r for r in runs}
    head = runs[0]
    k_last = head["steps"] - 1
    lines = [
        f"| run | PEB k=0 [m] | PEB k={k_last} mean [m] | p10–p90 [m] | estimate error k={k_last}, median [m] | "
        "violations, safe rule (default) | violations, paper's literal rule | PEB k={k}, literal rule [m] |".replace("{k}", str(k_last)),
        "|---|---:|---:|---:|---:|---|---|---:|",
    ]
    for mission_id, label in CASE_STUDY_RUNS:
        for crit in ("A", "D"):
            s, p = by.get(f"{mission_id}_{crit}"), by.get(f"{mission_id}_{crit}_paper")
            if s is None:
                continue
            lines.append(
                f"| {label}, {crit} | {num(s['initial_peb_mean_m'])} | {num(s['final_peb_mean_m'])} | "
                f"{num(s['final_peb_p10_m'])}–{num(s['final_peb_p90_m'])} | {s['final_estimate_error_median_m']:.2f} | "
                f"{violations(s)} | {violations(p) if p else '—'} | {num(p['final_peb_mean_m']) if p else '—'} |"
            )
    safe = [r for r in runs if r["activation"] == "safe"]
    total = sum(sum(r["violations"].values()) for r in safe)
    drone_steps = sum(r["trials"] * r["steps"] * r["drones"] for r in safe)
    lines += ["", f"Default (`safe`) rule: **{total} violating drone-steps** of {drone_steps:,}".replace(",", " ")
              + (" in every family." if total == 0 else ", per run and family as above.")]
    het = {c: by.get(f"paper_heterogeneous_{c}") for c in "AD"}
    joint = {c: by.get(f"paper_joint_{c}") for c in "AD"}
    ratios = [f"{c}: {het[c]['final_peb_mean_m'] / joint[c]['final_peb_mean_m']:.3f}" for c in "AD"
              if het[c] and joint[c] and het[c]["final_peb_mean_m"] and joint[c]["final_peb_mean_m"]]
    if ratios:
        lines.append(f"Heterogeneous / joint final mean PEB: {', '.join(ratios)}.")
    return lines


def peb_curve(out: Path, run: str) -> list[tuple[float | None, float]]:
    """A run's per-step (mean PEB in m or None if every view is singular, singular fraction)."""
    with (out / "runs" / run / "peb.csv").open() as fh:
        return [(float(r["peb_mean_m"]) if r["peb_mean_m"] not in ("inf", "nan") else None, float(r["singular_fraction"]))
                for r in csv.DictReader(fh)]


def case_study_facts(out: Path, runs: Sequence[dict[str, Any]]) -> list[str]:
    """The derived numbers the case study's text quotes, from the same results directory."""
    by = {r["run"]: r for r in runs}
    safe = [r for r in runs if r["activation"] == "safe"]
    curves = {r["run"]: peb_curve(out, r["run"]) for r in runs}
    lines = []
    decades = [np.log10(r["initial_peb_mean_m"] / r["final_peb_mean_m"]) for r in safe if r["final_peb_mean_m"]]
    lines.append(f"- Mean PEB from step 0 to the last step, default rule: down by {min(decades):.1f} to {max(decades):.1f} "
                 "orders of magnitude.")
    lower = [1 - by[r["run"] + "_paper"]["final_peb_mean_m"] / r["final_peb_mean_m"] for r in safe
             if by.get(r["run"] + "_paper") and by[r["run"] + "_paper"]["final_peb_mean_m"] and r["final_peb_mean_m"]]
    if lower:
        lines.append(f"- Final mean PEB of the paper's literal rule against the default rule: {100 * min(lower):.0f} to "
                     f"{100 * max(lower):.0f} % lower.")
    for mission_id, label in CASE_STUDY_RUNS:
        a, d = curves.get(f"{mission_id}_A"), curves.get(f"{mission_id}_D")
        if a is None or d is None:
            continue
        both = [(x, y) for (x, _), (y, _) in zip(a, d) if x is not None and y is not None]
        share = sum(x <= y for x, y in both) / len(both)
        lines.append(f"- {label}: A ≤ D on {100 * share:.0f} % of the steps; final mean PEB A {num(by[mission_id + '_A']['final_peb_mean_m'])} m, "
                     f"D {num(by[mission_id + '_D']['final_peb_mean_m'])} m.")
    labels = dict(CASE_STUDY_RUNS)
    for r in safe:
        for family, pairs in r.get("violating_drones", {}).items():
            for v in pairs:
                est = v.get("estimate_error_m")
                lines.append(
                    f"- Default-rule violation, {labels.get(r['mission_id'], r['mission_id'])}, {r['criterion']}: {family.replace('_', ' ')}, "
                    f"trial {v['trial']}, drone {v['drone']}, steps {v['first_step']}–{v['last_step']} ({v['steps']} steps), "
                    f"at worst {-v['worst_margin_m']:.2f} m inside" + (f"; its source estimate {est[0]:g}–{est[1]:g} m off." if est else ".")
                )
    for crit in "AD":
        curve = curves.get(f"paper_bearing_{crit}")
        if curve is not None:
            singular = [f for _, f in curve if f > 0]
            lines.append(f"- bearing, buildings, {crit}: a view is singular on {len(singular)} of the {len(curve)} steps"
                         + (f" (at most {100 * max(singular):.0f} % of the views at a step)." if singular else "."))
    for crit in "AD":
        het, joint = curves.get(f"paper_heterogeneous_{crit}"), curves.get(f"paper_joint_{crit}")
        if het is None or joint is None:
            continue
        ratios = [h / j for (h, _), (j, _) in zip(het, joint) if h is not None and j]
        half = sorted(ratios[len(ratios) // 2:])
        lines.append(f"- heterogeneous / joint mean PEB, {crit}: {ratios[0]:.2f} at step 0, {ratios[-1]:.3f} at the last step, "
                     f"median {half[len(half) // 2]:.3f} over the second half of the run.")
    return lines


def fault_table(rows: Sequence[tuple[float, int, dict[str, Any]]]) -> list[str]:
    """The loss and delay table of the heterogeneous mission (PEB penalty against no faults)."""
    lines = [
        "| loss | extra delay D | lost | mean record age (steps) | PEB at k=0 (m) | final PEB (m) | final penalty (m) ± SE (ratio) "
        "| mean PEB over steps (m) | mean penalty (m) ± SE (ratio) | violations (worst source margin) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    base = next((s for loss, delay, s in rows if loss == 0 and delay == 0), None)
    # The fault-free run's record age and mean over steps: every faulty row's baseline is that
    # same run (same seeds, trials and steps), re-simulated; check that it is.
    ref = next((s["faults"] for _, _, s in rows if s.get("faults")), None)
    if base is not None and ref is not None and ref["baseline_final_peb_mean_m"] != base["final_peb_mean_m"]:
        raise SystemExit(f"regenerate: the fault-free run ({base['final_peb_mean_m']}) differs from the faulty runs' "
                         f"baseline ({ref['baseline_final_peb_mean_m']}): the simulator is not deterministic")
    for loss, delay, s in rows:
        f = s.get("faults")
        viol = s["violations"]
        fam = ", ".join(f"{viol[k]} {k.replace('_', ' ')}" for k in FAMILIES if viol[k]) or "0"
        vtext = f"{fam} ({s['worst_margins_m']['source']:+.1f} m)".replace("-", "−")
        if f is None:  # the fault-free row
            age = f"{ref['baseline_mean_record_age_steps']:.2f}" if ref else "—"
            over = f"{ref['baseline_mean_peb_over_steps_m']:.2f}" if ref else "—"
            lines.append(f"| 0 | 0 | 0 | {age} | {num(s['initial_peb_mean_m'])} | {s['final_peb_mean_m']:.2f} | — | {over} | — | {vtext} |")
            continue
        init_ratio = f["initial_peb_mean_m"] / f["baseline_initial_peb_mean_m"] if f.get("baseline_initial_peb_mean_m") else None
        lines.append(
            f"| {loss:g} | {delay} | {f.get('lost_fraction', 0.0):.2f} | {f.get('mean_record_age_steps', 0.0):.2f} | "
            f"{num(f['initial_peb_mean_m'])}{f' (×{init_ratio:.2f})' if init_ratio else ''} | {f['final_peb_mean_m']:.2f} | "
            f"{_signed(f['final_peb_penalty_m'])} ± {f['final_peb_penalty_se_m']:.2f} (×{f['final_peb_penalty_ratio']:.3f}) | "
            f"{f['mean_peb_over_steps_m']:.2f} | {_signed(f['mean_peb_penalty_m'])} ± {f['mean_peb_penalty_se_m']:.2f} "
            f"(×{f['mean_peb_penalty_ratio']:.3f}) | {vtext} |"
        )
    if base is not None:
        lines += ["", f"Violations: drone-steps of {base['trials'] * base['steps'] * base['drones']:,}.".replace(",", " ")]
    return lines


def fault_grid(per_setting: Sequence[Sequence[dict[str, Any]]]) -> list[str]:
    """Every paper mission × A/D × fault setting: violating drone-steps (all families) and the
    final mean PEB."""
    labels = dict(CASE_STUDY_RUNS)
    head = "| run | " + " | ".join(label for label, _ in GRID_SETTINGS) + " |"
    lines = [head, "|---|" + "---:|" * len(GRID_SETTINGS)]
    by = [{r["run"]: r for r in runs} for runs in per_setting]
    total = 0
    worst: dict[str, float] = {}
    for mission_id, _label in CASE_STUDY_RUNS:
        for crit in "AD":
            cells = []
            for setting in by:
                r = setting.get(f"{mission_id}_{crit}")
                if r is None:
                    cells.append("—")
                    continue
                v = sum(r["violations"].values())
                total += v
                for fam, m in r["worst_margins_m"].items():
                    if m is not None:
                        worst[fam] = min(worst.get(fam, np.inf), m)
                cells.append(f"{v} · {r['final_peb_mean_m']:.2f} m")
            lines.append(f"| {labels[mission_id]}, {crit} | " + " | ".join(cells) + " |")
    runs = [r for setting in per_setting for r in setting]
    drone_steps = sum(r["trials"] * r["steps"] * r["drones"] for r in runs)
    lines += ["", "Each cell: violating drone-steps over every family (inter-drone, source, obstacle, altitude, speed, "
              "turn rate) · final mean PEB.",
              f"Total: **{total} violating drone-steps** of {drone_steps:,}".replace(",", " ") + "; smallest margin per family: "
              + ", ".join(f"{k.replace('_', ' ')} {v:+.2f} m".replace("-", "−") for k, v in worst.items()) + "."]
    return lines


def policy_comparison(runs: Sequence[dict[str, Any]]) -> list[str]:
    """The policy table (final mean PEB, 95 % interval, ratio to the planner's, violations) and
    per mission how many times the planner's final PEB each baseline's is, and the optimum's."""
    from missions.study.comparison import policy_table

    labels = dict(CASE_STUDY_RUNS)
    lines = policy_table(runs, labels)
    head = runs[0]
    lines += ["", f"{head['trials']} trials × {head['steps']} steps × {head['drones']} drones per run; violating drone-steps "
              "over inter-drone, source, obstacle, altitude and turn-rate distances, the speed family apart (a static drone "
              "holds still, below v_min, at every step).", ""]
    by: dict[str, dict[str, dict[str, Any]]] = {}
    for r in runs:
        by.setdefault(r["mission_id"], {})[r.get("policy", "fim")] = r
    for mission, pols in by.items():
        fim = pols.get("fim")
        if not fim or not fim["final_peb_mean_m"]:
            continue
        ratios = ", ".join(f"{p} {pols[p]['final_peb_mean_m'] / fim['final_peb_mean_m']:.2f} ×" for p in ("static", "orbit", "random", "centralized")
                           if p in pols and pols[p]["final_peb_mean_m"])  # fmt: skip
        opt = fim.get("final_peb_over_optimum")
        lines.append(f"- {labels.get(mission, mission)}, {fim['criterion']}: final mean PEB of each baseline over the planner's: {ratios}"
                     + (f"; the planner ends at {opt:.2f} × the optimal placement's {num(fim['optimum']['peb_m'])} m." if opt else "."))
    return lines


def power_table(known: Sequence[dict[str, Any]], unknown: Sequence[dict[str, Any]]) -> list[str]:
    """Per mission and criterion: the final mean PEB with the power known and unknown (eq. 18 of
    J, and of its Schur complement), their ratio, violations, the median final estimate errors
    and the drones' final power-offset estimates."""
    by_known = {r["run"]: r for r in known}
    lines = [
        "| mission | criterion | final PEB, power known [m] | final PEB, power unknown [m] | ratio | violations (known / unknown) "
        "| final estimate error, known / unknown [m] (median) | final offset estimate [dB] (mean, RMSE about 0) |",
        "|---|---|---:|---:|---:|---|---|---|",
    ]
    ratios = []
    for u in unknown:
        k = by_known.get(u["run"])
        if k is None:
            continue
        ratio = u["final_peb_mean_m"] / k["final_peb_mean_m"] if u["final_peb_mean_m"] and k["final_peb_mean_m"] else None
        if ratio is not None:
            ratios.append(ratio)
        sp = u.get("source_power", {})
        offset = "—" if sp.get("final_offset_mean_db") is None else f"{sp['final_offset_mean_db']:+.2f}, {sp['final_offset_rmse_db']:.2f}"
        lines.append(
            f"| paper/{u['mission_id'].removeprefix('paper_')} | {u['criterion']} | {num(k['final_peb_mean_m'])} | {num(u['final_peb_mean_m'])} | "
            f"{'—' if ratio is None else f'{ratio:.2f}'} | {sum(k['violations'].values())} / {sum(u['violations'].values())} | "
            f"{num(k['final_estimate_error_median_m'])} / {num(u['final_estimate_error_median_m'])} | {offset} |"
        )
    head = unknown[0]
    lines += ["", f"{head['trials']} trials × {head['steps']} steps × {head['drones']} drones per run"
              + (f"; power unknown over power known, final mean PEB: {min(ratios):.2f}-{max(ratios):.2f} ×." if ratios else ".")]
    return lines


def _signed(x: float) -> str:
    return f"{x:+.2f}".replace("-", "−")


# --------------------------------------------------------------------------- docs

def replace_block(path: Path, name: str, body: Sequence[str]) -> None:
    """Replace the text between ``<!-- BEGIN regenerate.py: name -->`` and its END marker."""
    begin, end = f"<!-- BEGIN regenerate.py: {name} -->", f"<!-- END regenerate.py: {name} -->"
    text = path.read_text()
    if text.count(begin) != 1 or text.count(end) != 1:
        raise SystemExit(f"regenerate: {path.relative_to(REPO)} must hold exactly one {begin!r} and one {end!r}")
    head, rest = text.split(begin)
    _, tail = rest.split(end)
    path.write_text(head + begin + "\n" + "\n".join(body) + "\n" + end + tail)


def provenance(cmds: Sequence[Command], when: str) -> list[str]:
    lines = [f"Generated by `python docs/regenerate.py` at {when}, from:", ""]
    lines += [f"    {c.shown()}" for c in cmds]
    return [*lines, ""]


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=REPO / "results" / "docs", help="results directories (default results/docs)")
    parser.add_argument("--trials", type=int, help="trials per run (default: each mission's, 100; the fault table 20)")
    parser.add_argument("--steps", type=int, help="steps per run (default: each mission's, 550)")
    parser.add_argument("--jobs", type=int, default=2, help="worker processes per command (default 2)")
    parser.add_argument("--no-docs", action="store_true", help="run and print the tables, leave docs/ as it is")
    parser.add_argument("--reuse", action="store_true", help="rebuild the tables and figures from an earlier run's results "
                        "directories under --out (stamped with the commit that run was made at) instead of running again")
    parser.add_argument("--only", action="append", choices=sorted(BLOCKS), help="run and rewrite only this block (repeatable)")
    args = parser.parse_args(argv)
    full = args.trials is None and args.steps is None
    cmds = commands(args.out, args.trials, args.steps, args.jobs, figures=True)
    blocks = args.only or sorted(BLOCKS)
    cmds = {n: c for n, c in cmds.items() if any(n.startswith(prefix) for b in blocks for prefix in BLOCKS[b])}
    if args.reuse:
        reused = {name: reuse_command(cmd) for name, cmd in cmds.items()}
        summaries = {name: runs for name, (runs, _) in reused.items()}
        stamps = {w for _, w in reused.values()}
        if len(stamps) != 1:
            raise SystemExit(f"regenerate: --reuse: the results under {args.out} come from different commits: {sorted(stamps)}")
        when = stamps.pop()
    else:
        when = stamp()
        summaries = {name: run_command(cmd, when) for name, cmd in cmds.items()}

    out_blocks: dict[str, list[str]] = {}
    if "case-study" in blocks:
        study = case_study_table(summaries["case-study"]) + ["", *case_study_facts(cmds["case-study"].out, summaries["case-study"])]
        out_blocks["case-study"] = provenance([cmds["case-study"]], when) + study
    if "fault-table" in blocks:
        faults = fault_table([(loss, delay, summaries[f"faults-loss{loss:g}-delay{delay}"][0]) for loss, delay in FAULT_SETTINGS])
        out_blocks["fault-table"] = provenance([c for n, c in cmds.items() if n.startswith("faults-")], when) + faults
    if "policies" in blocks:
        out_blocks["policies"] = provenance([cmds["policies"]], when) + policy_comparison(summaries["policies"])
    if "power" in blocks:
        out_blocks["power"] = provenance([cmds["power-known"], cmds["power-unknown"]], when) + power_table(
            summaries["power-known"], summaries["power-unknown"]
        )
    if "fault-grid" in blocks:
        grid = fault_grid([summaries[f"grid-{g}"] for g in range(len(GRID_SETTINGS))])
        out_blocks["fault-grid"] = provenance([c for n, c in cmds.items() if n.startswith("grid-")], when) + grid
    print("\n".join(line for body in out_blocks.values() for line in ["", *body]))
    if args.no_docs:
        return 0
    if not full:
        raise SystemExit("regenerate: docs/ quote the full size; rerun without --trials/--steps, or pass --no-docs")
    files = {
        "case-study": DOCS / "case-study.md",
        "fault-table": DOCS / "distributed.md",
        "fault-grid": DOCS / "reliability.md",
        "policies": DOCS / "case-study.md",
        "power": DOCS / "case-study.md",
    }
    for name, body in out_blocks.items():
        replace_block(files[name], name, body)
    if "case-study" in blocks:
        figures = DOCS / "figures"
        shutil.copyfile(cmds["fig3"].out / "figures" / "peb.png", figures / "case-study-fig3.png")
        for run_id in TRAJECTORY_RUNS:
            shutil.copyfile(cmds["case-study"].out / "figures" / f"trajectories_{run_id}.png", figures / f"trajectories_{run_id}.png")
    if "policies" in blocks:
        for name in FIG3_NAMES:
            shutil.copyfile(cmds["policies"].out / "figures" / f"policies_paper_{name}_A.png", DOCS / "figures" / f"policies_paper_{name}_A.png")
    print(f"\nregenerate: {', '.join(str(files[b].relative_to(REPO)) for b in out_blocks)} rewritten ({when})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
