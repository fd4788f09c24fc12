"""Benchmarks of the distributed run (issue 5), not timed tests.

Measures, with real processes on this machine:

1. wall time of ``fimnav launch missions/paper/heterogeneous.yaml`` (10 drones, 550 steps),
   start-up included, over ``--repeats`` runs (median); target ≤ 30 s;
2. the per-step latency from the payload measurement to the setpoint on the wire, from the
   planners' step logs (median and 99th percentile);
3. 100 drones × 100 steps (a generated mission: the paper's scenario with 100 drones on a wider
   start ellipse), target ≤ 120 s.

Baseline in the same run: the in-process simulator on the same missions (one trial), to show
what the distribution costs.

Usage::

    python benchmarks/bench_distributed.py [--repeats 3] [--skip-100]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def launch(mission: Path, out: Path, *args: str) -> float:
    """Run ``fimnav launch`` and return its wall time (s); raise if it fails."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "missions", "launch", str(mission), "--out", str(out), *args],
        cwd=ROOT, capture_output=True, text=True, env=dict(os.environ, TQDM_DISABLE="1"),
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"launch failed ({proc.returncode}):\n{proc.stderr[-3000:]}")
    return wall


def step_latencies(out: Path) -> np.ndarray:
    """measurement_to_setpoint_s of every planner step in a results directory."""
    values = []
    for path in sorted((out / "logs").glob("planner_*.jsonl")):
        for line in path.open():
            values.append(json.loads(line)["timing"]["measurement_to_setpoint_s"])
    return np.asarray(values)


def swarm_mission(path: Path, drones: int) -> Path:
    """The paper's heterogeneous scenario with ``drones`` drones (at most 100) on a start grid."""
    import yaml

    m = yaml.safe_load((ROOT / "missions" / "paper" / "heterogeneous.yaml").read_text())
    roles = ["ranging", "bearing", "joint"]
    m["id"] = f"swarm{drones}"
    m["drones"] = {
        "count": drones,
        "roles": [roles[i % 3] for i in range(drones)],
        # A 20 x 5 grid 10 m x 4 m apart, 170 m north of the source (an ellipse this wide would
        # bunch its ends closer than d_U*).
        "start": {"positions_m": [[-95.0 + 10.0 * (i % 20), 170.0, 4.0 + 4.0 * (i // 20)] for i in range(drones)]},
    }
    path.write_text(yaml.safe_dump(m, sort_keys=False))
    return path


def simulator_time(mission_path: Path, steps: int) -> float:
    from missions.format.loader import load_mission
    from missions.study.simulator import RunSpec, simulate

    m = load_mission(mission_path)
    t0 = time.perf_counter()
    simulate(RunSpec(m, m.criterion, 1, steps))
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--skip-100", action="store_true")
    args = ap.parse_args()
    print(f"load average at start: {os.getloadavg()}")
    het = ROOT / "missions" / "paper" / "heterogeneous.yaml"
    with tempfile.TemporaryDirectory() as tmp:
        walls = []
        walls_one = []  # same-run baseline: one vehicle per process (the default before)
        lat = np.array([])
        for r in range(args.repeats):
            out = Path(tmp) / f"het{r}"
            walls.append(launch(het, out))
            lat = np.concatenate([lat, step_latencies(out)])
            walls_one.append(launch(het, Path(tmp) / f"het1_{r}", "--vehicles-per-process", "1"))
            print(f"  run {r}: {walls[-1]:.1f} s (default: 10 vehicles per process); {walls_one[-1]:.1f} s (1 per process)")
        sim = simulator_time(het, 550)
        print(f"10 drones x 550 steps, launch (start-up included): median {statistics.median(walls):.1f} s "
              f"(runs {', '.join(f'{w:.1f}' for w in walls)}); with 1 vehicle per process: median "
              f"{statistics.median(walls_one):.1f} s; in-process simulator, 1 trial: {sim:.2f} s")
        print(f"measurement -> setpoint on the wire, per planner step ({lat.size} steps): "
              f"median {np.median(lat) * 1e3:.1f} ms, p99 {np.percentile(lat, 99) * 1e3:.1f} ms")
        if not args.skip_100:
            mission = swarm_mission(Path(tmp) / "swarm100.yaml", 100)
            out = Path(tmp) / "s100"
            wall = launch(mission, out, "--steps", "100", "--vehicles-per-process", "10", "--step-timeout", "120")
            lat100 = step_latencies(out)
            sim100 = simulator_time(mission, 100)
            print(f"100 drones x 100 steps (10 vehicles per process): {wall:.1f} s; "
                  f"latency median {np.median(lat100) * 1e3:.1f} ms, p99 {np.percentile(lat100, 99) * 1e3:.1f} ms; "
                  f"in-process simulator: {sim100:.2f} s")
    print(f"load average at end: {os.getloadavg()}")


if __name__ == "__main__":
    main()
