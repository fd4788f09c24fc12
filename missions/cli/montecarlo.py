"""``fimnav montecarlo``: the in-process Monte Carlo study of one or several missions."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import os
import signal
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from types import FrameType
from typing import TYPE_CHECKING, Any

from comms.errors import UsageError

if TYPE_CHECKING:
    from missions.study.simulator import PenaltyReference, RunSpec
    from planner.params import Criterion


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
    p.add_argument("--jobs", type=int, default=1, help="worker processes, one run each (default 1)")
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


def _positive(name: str, value: int | None) -> None:
    if value is not None and value < 1:
        raise UsageError(f"--{name}: expected a positive integer, found {value}")


def run(args: argparse.Namespace) -> int:
    """Load every mission, run every (mission, criterion, activation), write the results."""
    import functools
    import multiprocessing

    from tqdm import tqdm

    from missions.format.loader import load_mission, parse_overrides
    from missions.study.results import write_results
    from missions.study.simulator import RunSpec, fault_penalty, without_faults

    _positive("trials", args.trials)
    _positive("steps", args.steps)
    _positive("jobs", args.jobs)
    overrides = parse_overrides(args.overrides)
    specs: list[RunSpec] = []
    for path in args.missions:
        activations = ("safe", "paper") if args.activation == "both" else (args.activation,)
        for activation in activations:
            ov = dict(overrides)
            if activation is not None:
                ov["constraints.activation"] = activation
            mission = load_mission(path, ov)
            criteria: tuple[Criterion, ...] = ("A", "D") if args.criterion == "both" else (args.criterion or mission.criterion,)
            for crit in criteria:
                m = mission if crit == mission.criterion else load_mission(path, {**ov, "criterion": crit})
                specs.append(RunSpec(m, crit, args.trials or m.trials, args.steps or m.steps))
    out = args.out or Path("results") / time.strftime("montecarlo-%Y%m%d-%H%M%S")
    # A run with injected faults is summarised with its PEB penalty against the same run without
    # them: those baselines run here, with the runs (in the pool when --jobs > 1), not one after
    # another while the summaries are written.
    # With --baselines, a baseline found in an earlier run's results is read, not simulated.
    known = {i: _known_baseline(args.baselines, s, args.oracle_estimate) for i, s in enumerate(specs) if s.mission.comms.faults.enabled}
    baselines = [dataclasses.replace(specs[i], mission=without_faults(specs[i].mission)) for i, ref in known.items() if ref is None]
    jobs = [(s, False) for s in specs] + [(b, True) for b in baselines]
    total = sum(s.steps for s, _ in jobs)
    t0 = time.perf_counter()
    outcomes = []
    with contextlib.ExitStack() as stack, tqdm(total=total, unit="step", desc="montecarlo", file=sys.stderr, disable=None) as bar:
        view = None
        if args.view:
            from missions.launch.liveview import ViewServer, require_rerun

            require_rerun()
            server = stack.enter_context(ViewServer(web_port=args.view_port))
            view = (str(server.grpc_url), str(out / "view"))
            bar.write(f"live view: {server.browser_url}", file=sys.stderr)
        if args.jobs == 1 or len(jobs) == 1:
            for spec, baseline in jobs:
                bar.set_postfix_str(spec.label + (" without faults" if baseline else ""))
                outcomes.append(_simulate(spec, args.oracle_estimate, bar.update, None if baseline else view))
        else:
            # A Pool, not a ProcessPoolExecutor: leaving the block on an error, a signal or
            # Ctrl-C terminates the workers instead of waiting for the queued runs. After the
            # last result the workers are told to finish and joined (close, join): terminating
            # them then could find one blocked on the task queue's lock, which the terminating
            # pool holds, and wait for it forever.
            # The pool starts with Ctrl-C, SIGTERM and SIGHUP held back (_signals_deferred), and
            # is entered in the exit stack before they are let through: interrupted while
            # multiprocessing forked its workers, the command lost the signal (raised in a fork
            # hook, where Python ignores it) or left a worker it had not yet recorded running.
            with _signals_deferred():
                pool = stack.enter_context(multiprocessing.Pool(min(args.jobs, len(jobs)), initializer=_worker_signals))
            sim = functools.partial(_simulate_job, oracle=args.oracle_estimate, view=view)
            for (spec, _), result in zip(jobs, pool.imap(sim, jobs)):
                outcomes.append(result)
                bar.update(spec.steps)
            pool.close()
            pool.join()
    results = outcomes[: len(specs)]
    clean = iter(outcomes[len(specs) :])
    penalties = [
        fault_penalty(r.spec.mission, r, next(clean) if known[i] is None else known[i]) if r.spec.mission.comms.faults.enabled else None
        for i, r in enumerate(results)
    ]
    extras = None
    if args.optimum:
        from missions.cli.optimum import run_optimum_summary

        extras = [run_optimum_summary(r) for r in results]
    summaries = write_results(
        results, out, command=["fimnav", "montecarlo", *sys.argv[2:]], figures=not args.no_figures, penalties=penalties, extras=extras
    )
    wall = time.perf_counter() - t0
    opt_head = f" {'PEB* [m]':>9} {'PEB_K/PEB*':>10}" if args.optimum else ""
    print(f"{'run':<34} {'PEB0 [m]':>9} {'PEB_K [m]':>10} {'err_K [m]':>10} {'violations':>11} {'time [s]':>9}{opt_head}")
    for s in summaries:
        nviol = sum(s["violations"].values())
        opt = f" {_f(s['optimum']['peb_m']):>9} {_f(s['final_peb_over_optimum']):>10}" if args.optimum else ""
        print(
            f"{s['run']:<34} {_f(s['initial_peb_mean_m']):>9} {_f(s['final_peb_mean_m']):>10} "
            f"{_f(s['final_estimate_error_median_m']):>10} {nviol:>11} {s['runtime_s']:>9.1f}{opt}"
        )
    print(f"results: {out}  (wall {wall:.1f} s)")
    return 0


#: Signals held back while the worker pool starts (:func:`_signals_deferred`).
DEFERRED_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@contextlib.contextmanager
def _signals_deferred() -> Iterator[None]:
    """Inside: :data:`DEFERRED_SIGNALS` are recorded, not handled; on leaving, the previous
    handlers are back and each recorded signal is raised again. In a process forked inside
    (a pool worker before its initializer) such a signal has its default effect at once:
    KeyboardInterrupt for SIGINT, the end of the process for SIGTERM and SIGHUP. A signal
    ignored (or handled outside Python) is left as it is."""
    owner = os.getpid()
    got: list[int] = []

    def record(signum: int, frame: FrameType | None) -> None:
        if os.getpid() == owner:
            got.append(signum)
        elif signum == signal.SIGINT:
            raise KeyboardInterrupt
        else:
            signal.signal(signum, signal.SIG_DFL)
            os.kill(os.getpid(), signum)

    previous = {}
    for signum in DEFERRED_SIGNALS:
        handler = signal.getsignal(signum)
        if handler is not None and handler != signal.SIG_IGN:
            previous[signum] = signal.signal(signum, record)
    try:
        yield
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        for held in dict.fromkeys(got):
            signal.raise_signal(held)


def _worker_signals() -> None:
    """In a pool worker: SIGTERM and SIGHUP end the process at once (the default action), so
    the pool's ``terminate`` ends it wherever it waits; the command's own handlers belong to
    the parent. Ctrl-C raises KeyboardInterrupt, as in any Python process (the worker was
    forked while the parent held it back, :func:`_signals_deferred`)."""
    for signum in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(signum) != signal.SIG_IGN:
            signal.signal(signum, signal.SIG_DFL)
    if signal.getsignal(signal.SIGINT) != signal.SIG_IGN:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _known_baseline(directory: Path | None, spec: RunSpec, oracle: bool) -> PenaltyReference | None:
    """The :class:`missions.study.simulator.PenaltyReference` of ``spec`` (a run with faults) in the
    results ``directory`` (``--baselines``), or None when there is none to use there: then
    the baseline is simulated, and a line on stderr says why."""
    if directory is None:
        return None
    from missions.study.results import PENALTY_REFERENCE, spec_name
    from missions.study.simulator import PenaltyReference

    path = directory / "runs" / spec_name(spec) / PENALTY_REFERENCE
    if not path.is_file():
        why = f"no {path}"
    else:
        try:
            ref = PenaltyReference.load(path)
        except ValueError as exc:
            why = str(exc)
        else:
            if ref.matches(spec, oracle):
                return ref
            why = f"{path} is another run (mission, criterion, trials, steps or flags differ)"
    print(f"montecarlo: --baselines: {why}; simulating {spec.label} without faults", file=sys.stderr)
    return None


def _f(x: float | None) -> str:
    return "singular" if x is None else f"{x:.3g}"


def _simulate_job(job: tuple[Any, bool], oracle: bool, view: tuple[str, str] | None) -> Any:
    """One pool job: a run (logged live to ``view`` if given) or, ``job[1]``, the fault-free
    baseline of a run with faults (never logged)."""
    spec, baseline = job
    return _simulate(spec, oracle, None, None if baseline else view)


def _simulate(spec: Any, oracle: bool, progress: Any, view: tuple[str, str] | None = None) -> Any:
    """One run; ``view``: (the rerun server's stream, the directory of the recordings), to log
    trial 1 of the run live (:mod:`missions.launch.liveview`)."""
    from missions.study.simulator import simulate

    if view is None:
        return simulate(spec, progress=progress, oracle_estimate=oracle)
    from missions.launch.liveview import SwarmView, swarm_frame

    mission = spec.mission
    slug = "".join(c if c.isalnum() or c in "-_" else "_" for c in f"{mission.id}_{spec.criterion}")
    sv = SwarmView(mission, Path(view[1]) / f"{slug}.rrd", view[0], name=f"{spec.label}, trial 1")
    alive = ("alive",) * mission.drones.count

    def observe(s: Any) -> None:
        sv.log(swarm_frame(mission, s.step, s.positions_m[0], alive, s.estimates_m[0], s.view_positions_m[0], s.view_valid[0], s.view_los[0]))

    try:
        return simulate(spec, progress=progress, oracle_estimate=oracle, observer=observe)
    finally:
        sv.close()
