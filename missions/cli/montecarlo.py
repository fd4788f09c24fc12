"""``fimnav montecarlo``: the in-process Monte Carlo study of one or several missions."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

from missions.cli.study_args import add_executor_args, add_policy_arg, chunking, open_executor, policies, positive
from missions.runtime.rundir import make_results_dir

if TYPE_CHECKING:
    from missions.study.simulator import RunSpec, SimStep


def register(subparsers: Any) -> None:
    """Add the ``montecarlo`` subcommand."""
    p = subparsers.add_parser(
        "montecarlo",
        help="run M trials x K steps of missions in this process, write CSV, JSON and figures",
        description=(
            "Run missions in the in-process simulator (every drone with its own delayed view, "
            "estimator and control step) and write a results directory. Several missions and/or "
            "--criterion both put every run in the same figures (comparison)."
        ),
    )
    p.add_argument(
        "missions",
        nargs="+",
        metavar="MISSION",
        help="mission file(s) or names of missions shipped with fimnav, e.g. paper/joint (fimnav missions list)",
    )
    p.add_argument("--trials", type=int, help="Monte Carlo trials M (default: the mission's)")
    p.add_argument("--steps", type=int, help="steps K (default: the mission's)")
    p.add_argument("--criterion", choices=("A", "D", "both"), help="design criterion (default: the mission's)")
    p.add_argument("--activation", choices=("safe", "paper", "both"), help="constraint activation rule (default: the mission's)")
    p.add_argument(
        "--oracle-estimate", action="store_true", help="plan with the true source position (the paper's assumption) instead of each drone's estimate"
    )
    p.add_argument("--out", type=Path, default=None, help="results directory (default: results/montecarlo-<time>)")
    add_policy_arg(p)
    add_executor_args(p)
    p.add_argument("--no-figures", action="store_true", help="skip the PNG figures")
    p.add_argument(
        "--optimum",
        action="store_true",
        help="add to each run's summary the optimal placement's PEB (fimnav optimum, at the final source "
        "position, the safe rule's end-of-step distances) and the ratio final PEB / optimum",
    )
    p.add_argument(
        "--view",
        action="store_true",
        help="watch it live in a browser (rerun's web viewer on 127.0.0.1, the URL is printed): trial 1 of each run, "
        "recorded to OUT/view/<run>.rrd for fimnav view; needs pip install 'fimnav[view]'",
    )
    p.add_argument("--view-port", type=int, metavar="PORT", help="--view: the web viewer's port (default: a free one)")
    p.add_argument(
        "--baselines",
        type=Path,
        metavar="DIR",
        help="with injected faults: take each run's fault-free baseline (its PEB penalty's reference) from the results "
        "directory DIR of an earlier fimnav montecarlo of the same missions without faults, where it has the same "
        "mission, criterion, trials and steps, instead of simulating it again",
    )
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value (repeatable)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Load every mission, run every (mission, criterion, activation), write the results."""
    import functools

    from tqdm import tqdm

    from missions.format.loader import parse_overrides
    from missions.study.montecarlo import expand_runs, study_size, write_study

    positive("trials", args.trials)
    positive("steps", args.steps)
    positive("jobs", args.jobs)
    chunks = chunking(args)
    specs = expand_runs(args.missions, parse_overrides(args.overrides), args.criterion, args.activation, args.trials, args.steps, policies(args))
    t0 = time.perf_counter()
    total = study_size(specs, args.baselines, args.oracle_estimate)
    with contextlib.ExitStack() as stack:
        executor = open_executor(args, stack, lambda line: print(line, file=sys.stderr))
        out = make_results_dir(args.out or Path("results") / time.strftime("montecarlo-%Y%m%d-%H%M%S"))
        bar = stack.enter_context(tqdm(total=total, unit="trial-step", desc="montecarlo", file=sys.stderr, disable=None))
        watch = None
        if args.view:
            from missions.launch.liveview import ViewServer, require_rerun

            require_rerun()
            server = stack.enter_context(ViewServer(web_port=args.view_port))
            watch = functools.partial(_watch_run, str(server.grpc_url), str(out / "view"))
            bar.write(f"live view: {server.browser_url}", file=sys.stderr)
        # Each run's directory is written as soon as the run is done (one run in memory).
        summaries = write_study(
            specs,
            out,
            command=["fimnav", "montecarlo", *sys.argv[2:]],
            figures=not args.no_figures,
            optimum=args.optimum,
            oracle_estimate=args.oracle_estimate,
            baselines=args.baselines,
            executor=executor,
            **chunks,
            progress=bar.update,
            watch=watch,
            warn=lambda why: bar.write(f"montecarlo: --baselines: {why}", file=sys.stderr),
        )
    print_table(summaries, args.optimum)
    print(f"results: {out}  (wall {time.perf_counter() - t0:.1f} s)")
    return 0


def print_table(summaries: list[dict[str, Any]], optimum: bool) -> None:
    """The table ``fimnav montecarlo`` prints: one line per run."""
    opt_head = f" {'PEB* [m]':>9} {'PEB_K/PEB*':>10}" if optimum else ""
    print(f"{'run':<34} {'PEB0 [m]':>9} {'PEB_K [m]':>10} {'err_K [m]':>10} {'violations':>11} {'time [s]':>9}{opt_head}")
    for s in summaries:
        nviol = sum(s["violations"].values())
        opt = f" {_f(s['optimum']['peb_m']):>9} {_f(s['final_peb_over_optimum']):>10}" if optimum else ""
        print(
            f"{s['run']:<34} {_f(s['initial_peb_mean_m']):>9} {_f(s['final_peb_mean_m']):>10} "
            f"{_f(s['final_estimate_error_median_m']):>10} {nviol:>11} {s['runtime_s']:>9.1f}{opt}"
        )


def _f(x: float | None) -> str:
    return "singular" if x is None else f"{x:.3g}"


@contextlib.contextmanager
def _watch_run(grpc_url: str | None, directory: str, spec: RunSpec) -> Iterator[Callable[[SimStep], None]]:
    """The live view of a run's first trial (``--view``; :mod:`missions.launch.liveview`): a
    rerun recording ``<directory>/<mission id>_<criterion>.rrd`` streamed to ``grpc_url``.
    Runs in the process that simulates that trial (a pool worker with ``--jobs``)."""
    from missions.launch.liveview import SwarmView, swarm_frame

    mission = spec.mission
    slug = "".join(c if c.isalnum() or c in "-_" else "_" for c in f"{mission.id}_{spec.criterion}")
    sv = SwarmView(mission, Path(directory) / f"{slug}.rrd", grpc_url, name=f"{spec.label}, trial 1")
    alive = ("alive",) * mission.drones.count

    def observe(s: SimStep) -> None:
        sv.log(swarm_frame(mission, s.step, s.positions_m[0], alive, s.estimates_m[0], s.view_positions_m[0], s.view_valid[0], s.view_los[0]))

    try:
        yield observe
    finally:
        sv.close()
