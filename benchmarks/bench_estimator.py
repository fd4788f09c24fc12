"""Benchmark of one :func:`planner.estimator.update` call (not a test).

Prints the median wall time of one update for the Monte Carlo shape, batch (trials, drones) =
(100, 10) with 10 new records per element, and for one planner (batch ``()``, 10 records), in
the steady state (every element initialised, gate active, warm start) and for the first call
(pseudo-linear initialisation). Also prints the same for a few configurations, and one planner's
ranging-only estimator over 550 calls without and with the range memory.

    python benchmarks/bench_estimator.py [--repeat 50]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Sequence

import numpy as np

from planner.estimator import EstimatorConfig, EstimatorState, Measurements, initial_state, update
from planner.params import Channel


def _records(rng: np.random.Generator, batch: tuple[int, ...], m: int, source: np.ndarray, channel: Channel) -> Measurements:
    """Joint range/bearing records from drones 50-200 m around the source, LOS, noisy."""
    shape = batch + (m,)
    az = rng.uniform(-np.pi, np.pi, shape)
    rad = rng.uniform(50.0, 200.0, shape)
    pos = np.stack((source[0] + rad * np.cos(az), source[1] + rad * np.sin(az), rng.uniform(2.0, 25.0, shape)), axis=-1)
    r = source - pos
    d = np.linalg.norm(r, axis=-1)
    sb = channel.sigma_bearing_rad
    return Measurements(
        positions_m=pos,
        range_m=d + rng.normal(size=shape) * channel.sigma_r0_los * d ** (channel.gamma / 2),
        azimuth_rad=np.arctan2(r[..., 1], r[..., 0]) + sb * rng.normal(size=shape),
        elevation_rad=np.arctan2(r[..., 2], np.hypot(r[..., 0], r[..., 1])) + sb * rng.normal(size=shape),
        los=np.ones(shape, dtype=bool),
    )


def _median_ms(state: EstimatorState, meas: Sequence[Measurements], channel: Channel, config: EstimatorConfig, repeat: int) -> float:
    times = []
    for i in range(repeat):
        m = meas[i % len(meas)]
        t0 = time.perf_counter()
        update(state, m, channel, config)
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeat", type=int, default=50, help="timed calls per case (default 50)")
    parser.add_argument("--skip-large-window", action="store_true", help="skip window_rows=50 for batch (100, 10)")
    args = parser.parse_args(argv)
    channel = Channel()
    rng = np.random.default_rng(np.random.SeedSequence(2026))
    source = np.array([20.0, -10.0, 0.0])
    configs = {
        "default": EstimatorConfig(),
        "iterations=2": EstimatorConfig(iterations=2),
        "window_rows=10": EstimatorConfig(window_rows=10),
        "window_rows=50": EstimatorConfig(window_rows=50),
        "huber+gate": EstimatorConfig(loss="huber", gate_sigma=5.0),
    }
    print(f"numpy {np.__version__}; median of {args.repeat} calls; 10 new records per element")
    for batch in ((100, 10), ()):
        meas = [_records(rng, batch, 10, source, channel) for _ in range(8)]
        for name, config in configs.items():
            if batch and args.skip_large_window and config.window_rows >= 50:
                continue
            first = initial_state(batch, config)
            warm = first
            for m in meas[:6]:
                warm = update(warm, m, channel, config)
            t_first = _median_ms(first, meas, channel, config, max(args.repeat // 5, 3))
            t_warm = _median_ms(warm, meas, channel, config, args.repeat)
            print(f"batch {str(batch):9s} {name:15s} steady {t_warm:8.3f} ms   first call {t_first:8.3f} ms")
    _range_memory(rng, channel)
    return 0


def _range_memory(rng: np.random.Generator, channel: Channel, calls: int = 550, cells: int = 256) -> None:
    """One planner's estimator (batch ``()``) over a mission's worth of calls, ten LOS ranging
    records each (drones 40-120 m around a source 2 m up, 2-25 m high), without and with the
    range memory: the median of every call and of the re-check calls (every
    ``recheck_every``-th), back to back, twice."""
    source = np.array([0.0, 0.0, 2.0])
    meas = []
    nan = np.full(10, np.nan)
    for _ in range(calls):
        az, rad = rng.uniform(-np.pi, np.pi, 10), rng.uniform(40.0, 120.0, 10)
        pos = np.column_stack((rad * np.cos(az), rad * np.sin(az), rng.uniform(2.0, 25.0, 10)))
        r = np.linalg.norm(pos - source, axis=-1)
        noisy = r + rng.normal(size=10) * channel.sigma_r0_los * r ** (channel.gamma / 2)
        meas.append(Measurements(positions_m=pos, range_m=noisy, azimuth_rad=nan, elevation_rad=nan, los=np.ones(10, dtype=bool)))
    for _ in range(2):
        for n in (0, cells):
            config = EstimatorConfig(bounds_min_m=(-1000.0, -1000.0, 0.0), bounds_max_m=(1000.0, 1000.0, 30.0), range_memory_cells=n)
            state = initial_state((), config)
            times = []
            for m in meas:
                t0 = time.perf_counter()
                state = update(state, m, channel, config)
                times.append(time.perf_counter() - t0)
            every = config.recheck_every
            print(
                f"batch ()        ranging, range_memory_cells={n:<4d} {calls} calls: median {1e3 * statistics.median(times):7.3f} ms, "
                f"re-check calls {1e3 * statistics.median(times[every - 1 :: every]):7.3f} ms, total {sum(times):6.2f} s"
            )


if __name__ == "__main__":
    raise SystemExit(main())
