"""``fimnav launch``: fly a mission as a swarm of processes (vehicles, planners, clock)."""

from __future__ import annotations

import argparse
import math
import sys
import time
from pathlib import Path
from typing import Any

from comms.errors import UsageError


def register(subparsers: Any) -> None:
    """Add the ``launch`` subcommand."""
    p = subparsers.add_parser(
        "launch",
        help="fly a mission distributed: one planner process per drone, simulated vehicles (10 per process), lockstep clock",
        description="Validate the mission, start N simulated vehicles and N planner processes talking "
        "over Zenoh (loopback) and MAVLink, step them in lockstep, show progress and write the results.",
    )
    _add_run_options(p)
    _add_realtime_options(p)
    _add_process_options(p)
    p.set_defaults(func=run)


def _add_run_options(p: argparse.ArgumentParser) -> None:
    """The mission, the results directory, the run's overrides and its failure policy."""
    p.add_argument("mission", type=Path, metavar="MISSION", help="a mission file, or the name of a shipped mission (fimnav missions list)")
    p.add_argument(
        "--out",
        type=Path,
        help="results directory (default: results/<mission id>-<date>-<time>, with -2, -3, ... "
        "if taken); one holding a previous run is refused unless --overwrite",
    )
    p.add_argument(
        "--overwrite",
        action="store_true",
        help="--out holds a previous run: remove its files (mission.yaml, "
        "summary.json, logs/, tlogs/, runs/, figures/; nothing else) before starting",
    )
    p.add_argument("--steps", type=int, help="steps K (default: the mission's)")
    p.add_argument("--seed", type=int, help="root seed (default: the mission's)")
    p.add_argument("--criterion", choices=("A", "D"), help="design criterion (default: the mission's)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE", help="override a mission value (repeatable)")
    p.add_argument("--step-timeout", type=float, default=30.0, help="seconds a step may take before the run fails (default 30)")
    p.add_argument(
        "--no-figures",
        dest="figures",
        action="store_false",
        help="skip the PNG figures (about 2-3 s of CPU at the end of a run; the CSV and JSON results are the same)",
    )
    p.add_argument(
        "--on-failure",
        choices=("continue", "abort", "restart"),
        default="continue",
        help="when a vehicle or planner fails mid-mission: fly on without that drone (default), stop the run, "
        "or also restart a failed planner, which rejoins at the current step; the summary lists every failure "
        "and the exit status is then 3",
    )


def _add_realtime_options(p: argparse.ArgumentParser) -> None:
    """Real time: the wall clock, a mixed fleet, the ground station."""
    rt = p.add_argument_group("real time (a mixed fleet: drones with vehicles.overrides[i].connection fly that autopilot)")
    rt.add_argument(
        "--realtime",
        action="store_true",
        help="step on the wall clock instead of the lockstep clock; simulated "
        "vehicles run in real time; drones with a connection in the mission get no simulated vehicle",
    )
    rt.add_argument(
        "--speedup",
        type=float,
        default=1.0,
        help="real time: mission seconds per wall second (default 1; "
        "more only when every vehicle is simulated, or an external SITL runs at the same speed-up)",
    )
    rt.add_argument(
        "--gcs",
        metavar="ENDPOINT",
        help="real time: one ground-station port for every simulated vehicle, "
        "e.g. udpout:127.0.0.1:14550 (QGroundControl, MAVProxy) or tcpin:127.0.0.1:5760; its commands go to the "
        "vehicle they target (docs/in-the-field.md)",
    )
    rt.add_argument(
        "--start-delay",
        type=float,
        metavar="S",
        help="real time: wall seconds from the launch to step 0 "
        "(default 30 s + 1 s per drone); a drone not at its start by then joins at the current step",
    )


def _add_process_options(p: argparse.ArgumentParser) -> None:
    """The live view and how the processes are started."""
    p.add_argument(
        "--view",
        action="store_true",
        help="watch the swarm live in a browser: rerun's web viewer on 127.0.0.1 "
        "(the address is printed), recorded to OUT/view.rrd for fimnav view; needs pip install 'fimnav[view]'",
    )
    p.add_argument("--view-port", type=int, metavar="PORT", help="--view: the web viewer's port (default: a free one)")
    p.add_argument(
        "--vehicles-per-process",
        type=int,
        default=10,
        help="simulated vehicles hosted by one process (default 10: "
        "fewer interpreters share the cores better; 1 gives every vehicle its own process, e.g. to kill one)",
    )
    p.add_argument(
        "--no-fork-server",
        dest="fork_server",
        action="store_false",
        help="start every planner as a fresh interpreter (about 0.45 s of CPU each to import) instead of forking it "
        "from a fork server that imported them once; each planner is its own process either way",
    )


def _sig(x: float | None, unit: str = " m") -> str:
    """``x`` rounded to three significant digits (29.0, 7.46, 0.351; whole from 100 on), with
    its unit; "undefined" for a missing or infinite value (e.g. every view singular)."""
    if x is None or not math.isfinite(x):
        return "undefined"
    text = f"{x:#.3g}"
    return (f"{x:.0f}" if abs(x) >= 100 or text.endswith(".") else text) + unit


def summary_line(summary: dict[str, Any], out: Path, stream: Any = None) -> str:
    """The two lines ``fimnav launch`` prints at the end: what the run achieved, each value
    named by its statistic and rounded, then where the results are. E.g.::

        paper_heterogeneous_A: mean PEB 29.0 m → 7.46 m (step 0 → 99), median estimate error 0.350 m (step 99), safety violations 0, 17.8 s
        results: results/het

    ``stream``: where it will be printed (an arrow it cannot encode is written ``->``)."""
    last = int(summary["steps"]) - 1
    viol = sum(summary["violations"].values())
    text = (
        f"{summary['run']}: mean PEB {_sig(summary['initial_peb_mean_m'])} → {_sig(summary['final_peb_mean_m'])} (step 0 → {last}), "
        f"median estimate error {_sig(summary['final_estimate_error_median_m'])} (step {last}), safety violations {viol}, "
        f"{summary['runtime_s']:.1f} s\nresults: {out}"
    )
    encoding = getattr(stream, "encoding", None) or "utf-8"
    try:
        text.encode(encoding)
    except (UnicodeEncodeError, LookupError):
        text = text.replace("→", "->")
    return text


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The mission overrides of ``--set``, ``--steps``, ``--seed`` and ``--criterion``.

    Raises:
        UsageError: a malformed ``--set``, or ``--steps``/``--seed`` out of range.
    """
    from missions.format.loader import parse_overrides

    overrides = parse_overrides(args.overrides)
    for name in ("steps", "seed"):
        value = getattr(args, name)
        if value is not None:
            if value < (1 if name == "steps" else 0):
                raise UsageError(f"--{name}: expected {'a positive' if name == 'steps' else 'a non-negative'} integer, found {value}")
            overrides[name] = value
    if args.criterion:
        overrides["criterion"] = args.criterion
    return overrides


def _check_options(args: argparse.Namespace) -> None:
    """Refuse options that do not go together or are out of range (before anything starts).

    Raises:
        UsageError: naming the option and why.
    """
    for name in ("speedup", "start_delay"):
        v = getattr(args, name)
        if v is not None and not (math.isfinite(v) and v > 0):
            raise UsageError(f"--{name.replace('_', '-')}: expected a positive number of seconds, found {v}")
    if not args.realtime and (args.speedup != 1.0 or args.start_delay is not None):
        raise UsageError("--speedup and --start-delay: only with --realtime (lockstep runs as fast as the machine allows)")
    if args.gcs is not None:
        if not args.realtime:
            raise UsageError("--gcs: only with --realtime (a ground station runs on the wall clock)")
        from missions.launch.gcs import check_endpoint

        check_endpoint(args.gcs)
    if args.vehicles_per_process < 1:
        raise UsageError(f"--vehicles-per-process: expected a positive integer, found {args.vehicles_per_process}")
    if args.view:
        from missions.launch.liveview import require_rerun

        require_rerun()
    elif args.view_port is not None:
        raise UsageError("--view-port: only with --view")


def _results_dir(args: argparse.Namespace, mission_id: str) -> Path:
    """``--out`` (checked: no previous run unless ``--overwrite``), or a new
    ``results/<mission id>-<date>-<time>``."""
    from missions.runtime.rundir import check_results_dir, unique_results_dir

    if args.out is None:
        return unique_results_dir(Path("results"), f"{mission_id}-{time.strftime('%Y%m%d-%H%M%S')}")
    check_results_dir(args.out, args.overwrite)  # before anything shows; the launcher claims (makes) it
    return Path(args.out)


def _report(summary: dict[str, Any], out: Path) -> int:
    """Print the summary and the failures; the exit status (3: completed with failures)."""
    print(summary_line(summary, out, sys.stdout))
    for f in summary["failures"]:
        print(
            f"failure: {f['process']} (drones {f['drones']}) at step {f['step']}, status {f['status']}: {f['reason']} -> {f['action']}",
            file=sys.stderr,
        )
    if summary["failures"]:
        print(f"the mission completed with {len(summary['failures'])} failure(s): see {out / 'summary.json'}", file=sys.stderr)
        return 3
    return 0


def run(args: argparse.Namespace) -> int:
    """Validate, launch, report."""
    from tqdm import tqdm

    from missions.format.loader import load_mission
    from missions.launch.launcher import launch

    overrides = _overrides(args)
    _check_options(args)
    mission = load_mission(args.mission, overrides)
    out = _results_dir(args, mission.id)
    bar = tqdm(total=mission.steps, unit="step", desc=f"launch {mission.id}", file=sys.stderr, disable=None)

    def progress(k: int, peb: float, err: float, alive: int) -> None:
        bar.set_postfix_str(f"PEB {peb:.3g} m, err {err:.3g} m, alive {alive}/{mission.drones.count}")
        bar.update(1)

    def notice(text: str) -> None:
        bar.write(text, file=sys.stderr)

    try:
        summary = launch(
            mission,
            out,
            progress=progress,
            step_timeout_s=args.step_timeout,
            vehicles_per_process=args.vehicles_per_process,
            on_failure=args.on_failure,
            realtime=args.realtime,
            speedup=args.speedup,
            start_delay_s=args.start_delay,
            fork_server=args.fork_server,
            overwrite=args.overwrite,
            notice=notice,
            gcs=args.gcs,
            view=args.view,
            view_port=args.view_port,
            figures=args.figures,
        )
    finally:
        bar.close()
    return _report(summary, out)
