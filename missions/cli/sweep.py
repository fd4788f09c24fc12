"""``fimnav sweep``: a parameter sweep of one mission, each cell a Monte Carlo run, resumable."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path
from typing import Any

from missions.cli.study_args import add_executor_args, add_policy_arg, chunking, open_executor, policies, positive


def register(subparsers: Any) -> None:
    """Add the ``sweep`` subcommand."""
    p = subparsers.add_parser(
        "sweep",
        help="run a mission over the grid of every combination of --vary values (a Monte Carlo run each, same seeds): CSV and figures",
        description=(
            "Run MISSION once per combination of the --vary values (the grid), each cell a Monte Carlo run with the same "
            "seeds, and write one CSV row per run of a cell (the values, final mean PEB and its 95 % interval, median "
            "estimate error, violations per family, time) and a figure per varied key. Run the same command again to "
            "resume: finished cells are read, not simulated again."
        ),
    )
    p.add_argument("mission", metavar="MISSION", help="mission file or name of a mission shipped with fimnav, e.g. paper/joint")
    p.add_argument(
        "--vary",
        action="append",
        default=[],
        required=True,
        metavar="KEY=V1,V2,...",
        help="a mission key and its values, read as --set reads a value (repeatable: the grid of every combination; "
        "values holding commas in brackets, e.g. [0,150,8],[0,200,8], are kept whole)",
    )
    p.add_argument(
        "--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value in every cell (repeatable)"
    )
    p.add_argument("--trials", type=int, help="Monte Carlo trials M per cell (default: the mission's)")
    p.add_argument("--steps", type=int, help="steps K (default: the mission's)")
    p.add_argument("--criterion", choices=("A", "D", "both"), help="design criterion (default: the mission's)")
    p.add_argument("--oracle-estimate", action="store_true", help="plan with the true source position instead of each drone's estimate")
    p.add_argument(
        "--out",
        type=Path,
        default=None,
        help="sweep directory (default: results/sweep-<mission id>-<hash of the sweep>, so the same command finds it again)",
    )
    add_policy_arg(p)
    add_executor_args(p)
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Plan every cell (each mission checked first), resume from the directory, run the rest."""
    from tqdm import tqdm

    from missions.format.loader import parse_overrides
    from missions.study.sweep import default_out, parse_vary, plan_sweep, read_finished, run_sweep, sweep_size

    positive("trials", args.trials)
    positive("steps", args.steps)
    chunks = chunking(args)
    sets = parse_overrides(args.overrides)
    plan = plan_sweep(
        args.mission,
        parse_vary(args.vary, sets),
        sets,
        args.criterion,
        args.trials,
        args.steps,
        args.oracle_estimate,
        policies=policies(args),
        **chunks,
    )
    out = args.out or default_out(plan)
    finished = read_finished(plan, out)
    t0 = time.perf_counter()
    with contextlib.ExitStack() as stack:
        executor = open_executor(args, stack, lambda line: print(line, file=sys.stderr))
        if finished:
            print(f"sweep: {len(finished)} of {len(plan.cells)} cells already in {out}, read", file=sys.stderr)
        bar = stack.enter_context(tqdm(total=sweep_size(plan, finished), unit="trial-step", desc="sweep", file=sys.stderr, disable=None))
        done = run_sweep(
            plan,
            out,
            executor,
            command=["fimnav", "sweep", *sys.argv[2:]],
            progress=bar.update,
            on_cell=lambda cell, rows: bar.write(f"cell {cell.index + 1}/{len(plan.cells)} done: {cell.name}", file=sys.stderr),
            figures=not args.no_figures,
        )
    print_table(plan.varies, done)
    print(f"results: {out}  (wall {time.perf_counter() - t0:.1f} s; the same command resumes it)")
    return 0


def print_table(varies: Any, done: dict[int, list[dict[str, Any]]]) -> None:
    """One line per run of each cell: the values, criterion, final PEB with its interval,
    median estimate error, violations, time."""
    keys = [v.key for v in varies]
    width = [max(len(k), *(len(str(r[k])) for rows in done.values() for r in rows)) for k in keys]
    head = " ".join(f"{k:<{w}}" for k, w in zip(keys, width))
    print(f"{head} crit {'policy':<11} {'PEB_K [m]':>10} {'95 % interval [m]':>19} {'err_K [m]':>10} {'violations':>11} {'time [s]':>9}")
    for index in sorted(done):
        for r in done[index]:
            ci = "-" if r["final_peb_ci95_low_m"] is None else f"{r['final_peb_ci95_low_m']:.3g}-{r['final_peb_ci95_high_m']:.3g}"
            peb = "singular" if r["final_peb_mean_m"] is None else f"{r['final_peb_mean_m']:.3g}"
            nviol = sum(v for k, v in r.items() if k.startswith("violations_"))
            vals = " ".join(f"{r[k]!s:<{w}}" for k, w in zip(keys, width))
            print(
                f"{vals} {r['criterion']:<4} {r['policy']:<11} {peb:>10} {ci:>19} {r['final_estimate_error_median_m']:>10.3g} {nviol:>11} {r['runtime_s']:>9.1f}"
            )
