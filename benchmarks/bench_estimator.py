"""Benchmark of one :func:`planner.estimator.update` call (not a test), the compiled estimator
against the numpy estimator it replaced, measured in the same run.

The baseline is the package ``planner/estimator`` of commit ``48f7e03`` (the last numpy
estimator), read with ``git show`` into a temporary directory and imported from there as
``estimator_baseline`` (it needs the repository's git history; ``--no-baseline`` skips it).

Prints (1) one planner's ranging estimator in the paper's final ranging geometry (the ten
drones where ``paper/ranging_los`` ends, held still, LOS ranges to a source 2 m up, range
memory of 256 cells, the mission's search box), 550 calls of ten records each: the median and
mean time of a call and of a re-check call (every ``recheck_every``-th), and per record;
(2) the median time of one update for the Monte Carlo shape, batch (trials, drones) = (100, 10)
with 10 new joint records per element, and for one planner (batch ``()``), in the steady state
and for the first call, for a few configurations.

    python benchmarks/bench_estimator.py [--repeat 50] [--calls 550] [--no-baseline]

With ``--mission``, instead: the compiled batch update
(:func:`planner.estimator.kernels.update.update_batch`) timed where the in-process simulator
calls it, in ``--rounds`` runs of each mission (criterion A, ``--trials`` × ``--steps``, one
process): per drone-step (one element of one call), split into the re-check calls (every
``recheck_every``-th) and the others, and the run's wall time; medians over the rounds.

    python benchmarks/bench_estimator.py --mission paper/ranging_los paper/bearing [--trials 20] [--steps 300] [--rounds 3]
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType

import numpy as np

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path[:1]:
    sys.path.insert(0, str(REPO))

from planner import estimator as compiled  # noqa: E402
from planner.params import Channel  # noqa: E402

#: The last numpy estimator.
BASELINE_COMMIT = "48f7e03"

#: Where ``paper/ranging_los`` ends (trial 0, seed 1): the paper's final ranging geometry, m, ENU.
FINAL_GEOMETRY_M = np.array([
    [3.1, 55.0, 22.5], [33.1, 50.0, 22.5], [26.2, 52.5, 22.4], [-44.8, -38.1, 21.4], [-49.2, -34.1, 22.4],
    [-43.7, 38.9, 4.6], [-46.9, 35.1, 4.6], [-42.5, -38.5, 23.7], [51.2, -24.8, 22.4], [-39.8, 42.0, 4.6],
])  # fmt: skip


def load_baseline(directory: Path, commit: str = BASELINE_COMMIT) -> ModuleType:
    """The package ``planner/estimator`` of ``commit``, written into ``directory`` as
    ``estimator_baseline`` (its imports of itself renamed) and imported from there."""
    package = directory / "estimator_baseline"
    package.mkdir()
    names = subprocess.run(["git", "ls-tree", "--name-only", commit, "planner/estimator/"], cwd=REPO, capture_output=True, text=True, check=True)
    for name in names.stdout.split():
        text = subprocess.run(["git", "show", f"{commit}:{name}"], cwd=REPO, capture_output=True, text=True, check=True).stdout
        (package / Path(name).name).write_text(text.replace("planner.estimator", "estimator_baseline"), encoding="utf-8")
    sys.path.insert(0, str(directory))
    return importlib.import_module("estimator_baseline")


def _records(est: ModuleType, rng: np.random.Generator, batch: tuple[int, ...], m: int, source: np.ndarray, channel: Channel) -> object:
    """Joint range/bearing records from drones 50-200 m around the source, LOS, noisy."""
    shape = batch + (m,)
    az = rng.uniform(-np.pi, np.pi, shape)
    rad = rng.uniform(50.0, 200.0, shape)
    pos = np.stack((source[0] + rad * np.cos(az), source[1] + rad * np.sin(az), rng.uniform(2.0, 25.0, shape)), axis=-1)
    r = source - pos
    d = np.linalg.norm(r, axis=-1)
    sb = channel.sigma_bearing_rad
    return est.Measurements(
        positions_m=pos,
        range_m=d + rng.normal(size=shape) * channel.sigma_r0_los * d ** (channel.gamma / 2),
        azimuth_rad=np.arctan2(r[..., 1], r[..., 0]) + sb * rng.normal(size=shape),
        elevation_rad=np.arctan2(r[..., 2], np.hypot(r[..., 0], r[..., 1])) + sb * rng.normal(size=shape),
        los=np.ones(shape, dtype=bool),
    )


def _median_ms(est: ModuleType, state: object, meas: Sequence[object], channel: Channel, config: object, repeat: int) -> float:
    times = []
    for i in range(repeat):
        m = meas[i % len(meas)]
        t0 = time.perf_counter()
        est.update(state, m, channel, config)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=50, help="timed calls per case (default 50)")
    parser.add_argument("--calls", type=int, default=550, help="calls of the final-geometry run (default 550)")
    parser.add_argument("--no-baseline", action="store_true", help="the compiled estimator only")
    parser.add_argument("--skip-large-window", action="store_true", help="skip window_rows=50 for batch (100, 10)")
    parser.add_argument("--mission", nargs="+", metavar="MISSION", help="instead: the batch update inside simulated runs of these missions")
    parser.add_argument("--trials", type=int, default=20, help="trials of a --mission run (default 20)")
    parser.add_argument("--steps", type=int, default=300, help="steps of a --mission run (default 300)")
    parser.add_argument("--rounds", type=int, default=3, help="runs of each --mission (default 3)")
    parser.add_argument("--against", metavar="COMMIT", help="with --mission: also time this commit's kernel on the same calls")
    parser.add_argument(
        "--kernels-dir", type=Path, help="with --against: where its kernels are written and compiled (default: a temporary directory)"
    )
    args = parser.parse_args(argv)
    if args.mission:
        with tempfile.TemporaryDirectory() as tmp:
            against = load_kernels(args.kernels_dir or Path(tmp), args.against) if args.against else None
            for mission in args.mission:
                _in_mission(mission, args.trials, args.steps, args.rounds, against)
        return 0
    with tempfile.TemporaryDirectory() as tmp:
        impls = {"compiled": compiled}
        if not args.no_baseline:
            impls = {f"numpy {BASELINE_COMMIT}": load_baseline(Path(tmp)), **impls}
        _warm_up(compiled)
        print(f"numpy {np.__version__}; {' vs '.join(impls)}, the same run")
        for name, est in impls.items():
            _final_geometry(name, est, args.calls)
        for name, est in impls.items():
            _configurations(name, est, args.repeat, args.skip_large_window)
    return 0


def load_kernels(directory: Path, commit: str) -> ModuleType:
    """The compiled update kernel (``planner/estimator/kernels/update.py``) of ``commit``: its
    package written into ``directory`` as ``estimator_kernels_<commit>`` (its imports of itself
    renamed; the packed layout is shared) and imported from there (numba compiles it there
    once)."""
    name = f"estimator_kernels_{commit}"
    package = directory / name
    if not package.exists():
        package.mkdir(parents=True)
        names = subprocess.run(
            ["git", "ls-tree", "--name-only", commit, "planner/estimator/kernels/"], cwd=REPO, capture_output=True, text=True, check=True
        )
        for path in names.stdout.split():
            text = subprocess.run(["git", "show", f"{commit}:{path}"], cwd=REPO, capture_output=True, text=True, check=True).stdout
            (package / Path(path).name).write_text(text.replace("planner.estimator.kernels", name), encoding="utf-8")
    if str(directory) not in sys.path:
        sys.path.insert(0, str(directory))
    return importlib.import_module(f"{name}.update")


def _in_mission(name: str, trials: int, steps: int, rounds: int, against: ModuleType | None) -> None:
    """The compiled batch update timed inside ``rounds`` simulated runs of mission ``name``
    (criterion A): CPU µs per drone-step (one element of one call), re-check calls and others,
    medians over the rounds; with ``against`` (another commit's kernel module) each call is
    also made by that kernel on a copy of the same state (the order alternating), checked to
    give the same state, and timed the same way."""
    from missions.format.loader import load_mission
    from missions.study.simulator import RunSpec, simulate
    from planner.estimator.kernels import update as kernels

    mission = load_mission(name, None)
    batch = kernels.update_batch
    impls = {"this commit": batch} if against is None else {"this commit": batch, "baseline": against.update_batch}
    times: dict[str, dict[bool, list[float]]] = {k: {True: [], False: []} for k in impls}
    sizes: list[int] = []

    def timed(state: tuple, new: tuple, cfg: np.ndarray, channel: tuple, due: bool, used: np.ndarray, cb: object, overwrite: bool) -> tuple:
        order = list(impls) if len(sizes) % 2 == 0 else list(impls)[::-1]
        outs: dict[str, tuple] = {}
        copy = tuple(a.copy() for a in state) if against is not None else state  # before either call writes into state
        for k in order:
            own = state if k == "this commit" else copy
            t0 = time.thread_time()
            outs[k] = impls[k](own, new, cfg, channel, due, used, cb, overwrite)
            times[k][bool(due)].append(time.thread_time() - t0)
        if against is not None and not all(np.array_equal(a, b, equal_nan=True) for a, b in zip(outs["this commit"], outs["baseline"], strict=True)):
            raise AssertionError(f"{name}: the baseline's state differs at call {len(sizes)}")
        sizes.append(state[0].shape[0])
        return outs["this commit"]

    results: dict[str, dict[str, list[float]]] = {k: {"all": [], "due": [], "other": []} for k in impls}
    walls = []
    kernels.update_batch = timed
    try:
        simulate(RunSpec(mission, "A", 1, 2))  # the kernels loaded, not timed
        for _ in range(rounds):
            sizes.clear()
            for k in impls:
                times[k][True].clear(), times[k][False].clear()
            t0 = time.perf_counter()
            simulate(RunSpec(mission, "A", trials, steps))
            walls.append(time.perf_counter() - t0)
            E = sizes[0]
            for k in impls:
                due, other = sum(times[k][True]), sum(times[k][False])
                results[k]["all"].append(1e6 * (due + other) / (E * len(sizes)))
                results[k]["due"].append(1e6 * due / (E * max(len(times[k][True]), 1)))
                results[k]["other"].append(1e6 * other / (E * max(len(times[k][False]), 1)))
    finally:
        kernels.update_batch = batch
    for k, r in results.items():
        print(
            f"{name} ({k}): {trials} trials x {steps} steps, batch of {E} drones, {len(sizes)} calls: update_batch "
            f"{statistics.median(r['all']):6.2f} us CPU per drone-step (re-check calls {statistics.median(r['due']):6.2f}, others "
            f"{statistics.median(r['other']):6.2f}); medians of {rounds}"
        )
    print(f"{name}: run wall {statistics.median(walls):6.2f} s (median of {rounds}; the baseline's calls included)")


def _warm_up(est: ModuleType) -> None:
    """One update of each shape, so that loading the compiled kernels is not timed."""
    for batch in ((), (2, 2)):
        config = est.EstimatorConfig(range_memory_cells=4)
        nan = np.full(batch + (1,), np.nan)
        est.update(
            est.initial_state(batch, config),
            est.Measurements(np.zeros(batch + (1, 3)), nan, nan, nan, np.ones(batch + (1,), bool)),
            Channel(),
            config,
        )


def _final_geometry(name: str, est: ModuleType, calls: int, cells: int = 256) -> None:
    """One planner's ranging estimator in the paper's final ranging geometry, range memory on."""
    channel = Channel()
    rng = np.random.default_rng(np.random.SeedSequence(2026))
    source = np.array([0.0, 0.0, 2.0])
    d = np.linalg.norm(FINAL_GEOMETRY_M - source, axis=-1)
    n = len(d)
    nan = np.full(n, np.nan)
    config = est.EstimatorConfig(bounds_min_m=(-1000.0, -1000.0, 0.0), bounds_max_m=(1000.0, 1000.0, 30.0), range_memory_cells=cells)
    state = est.initial_state((), config)
    times = []
    for _ in range(calls):
        m = est.Measurements(FINAL_GEOMETRY_M, d + rng.normal(size=n) * channel.sigma_r0_los * d ** (channel.gamma / 2), nan, nan, np.ones(n, bool))
        t0 = time.perf_counter()
        state = est.update(state, m, channel, config)
        times.append(time.perf_counter() - t0)
    every = config.recheck_every
    us = 1e6 * np.array(times)
    print(
        f"final ranging geometry, batch (), {n} records per call, range memory {cells} cells, {calls} calls, {name}: "
        f"median {statistics.median(us):8.1f} us/call ({statistics.median(us) / n:6.1f} us/record), mean {us.mean():8.1f} us/call "
        f"({us.mean() / n:6.1f} us/record); re-check calls median {statistics.median(us[every - 1 :: every]):8.1f} us; "
        f"error {np.linalg.norm(state.estimate_m - source):.2f} m"
    )


def _configurations(name: str, est: ModuleType, repeat: int, skip_large_window: bool) -> None:
    """The median update time of a few configurations, batch (100, 10) and ()."""
    channel = Channel()
    rng = np.random.default_rng(np.random.SeedSequence(2026))
    source = np.array([20.0, -10.0, 0.0])
    configs = {
        "default": est.EstimatorConfig(),
        "iterations=2": est.EstimatorConfig(iterations=2),
        "window_rows=10": est.EstimatorConfig(window_rows=10),
        "window_rows=50": est.EstimatorConfig(window_rows=50),
        "huber+gate": est.EstimatorConfig(loss="huber", gate_sigma=5.0),
    }
    for batch in ((100, 10), ()):
        meas = [_records(est, rng, batch, 10, source, channel) for _ in range(8)]
        for cname, config in configs.items():
            if batch and skip_large_window and config.window_rows >= 50:
                continue
            first = initial = est.initial_state(batch, config)
            for m in meas[:6]:
                initial = est.update(initial, m, channel, config)
            t_first = _median_ms(est, first, meas, channel, config, max(repeat // 5, 3))
            t_warm = _median_ms(est, initial, meas, channel, config, repeat)
            print(f"{name:15s} batch {batch!s:9s} {cname:15s} steady {t_warm:8.3f} ms   first call {t_first:8.3f} ms")


if __name__ == "__main__":
    raise SystemExit(main())
