"""Estimator accuracy against the bound in the paper's final ranging geometry.

    python benchmarks/estimator_final_geometry.py [--mission paper/ranging_los] [--trials 400] [--snapshots 1 10 50] [--memory-cells 64]

The final positions of the mission's first trial (the in-process simulator, seeded) are held
fixed; each trial draws ``K`` snapshots of the ten ranges there (the paper's channel, seeded
noise) and gives them to (a) fimnav's estimator with the mission's settings, one call per
snapshot as a planner would, (b) the same with the range memory (``range_memory_cells``), and
(c) the exact maximum-likelihood estimate of the same ranges (d̂ ~ N(d, σ_r0² d^γ), minimised by
Nelder-Mead from the true source and from the estimator's answer, the better kept), unbounded
and (d) in the mission's search box (L-BFGS-B from (c), clipped). Printed per K: the PEB of the
K snapshots (√tr J⁻¹ at the true source, eq. 18), each estimate's RMSE/PEB, and for (a) and (b)
the mean height error (m) and the share of trials more than 10 m above the source.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path[:1]:
    sys.path.insert(0, str(REPO))

from missions.loader import load_mission  # noqa: E402
from missions.simulator import RunSpec, simulate  # noqa: E402
from planner import estimator as est  # noqa: E402
from planner.fim import fisher_information, position_error_bound  # noqa: E402
from planner.geometry import line_of_sight  # noqa: E402
from planner.observation import observe_from_uniforms  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mission", default="paper/ranging_los")
    ap.add_argument("--trials", type=int, default=400)
    ap.add_argument("--memory-cells", type=int, default=64)
    ap.add_argument("--snapshots", type=int, nargs="+", default=[1, 10, 50])
    ap.add_argument("--seed", type=int, default=7)
    args = ap.parse_args(argv)
    m = load_mission(args.mission)
    ch, cfg = m.channel.to_planner(), m.estimator_config()
    src = np.array(m.source.position_m, dtype=float)
    final = simulate(RunSpec(m, "A", 1, m.steps)).positions_m[-1, 0]  # (N, 3), m, ENU
    n = final.shape[0]
    bmin = np.array([o.min_m for o in m.obstacles], dtype=float).reshape(-1, 3)
    bmax = np.array([o.max_m for o in m.obstacles], dtype=float).reshape(-1, 3)
    los = line_of_sight(src, final, bmin, bmax)
    ranging, bearing = np.ones(n, bool), np.zeros(n, bool)
    print(f"{args.mission}: final geometry of trial 0, drone heights {np.round(final[:, 2], 1).tolist()} m, "
          f"distances {np.round(np.linalg.norm(final - src, axis=1), 1).tolist()} m")
    print("| K | PEB (m) | estimator ×PEB | height bias (m) | > 10 m above | with range memory ×PEB | height bias (m) | > 10 m above "
          "| exact ML ×PEB | exact ML in the search box ×PEB |")
    print("|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    T = args.trials
    cfg_memory = dataclasses.replace(cfg, range_memory_cells=args.memory_cells)
    lo, hi = np.array(cfg.bounds_min_m), np.array(cfg.bounds_max_m)
    for K in args.snapshots:
        peb = float(position_error_bound(K * fisher_information(src, final, ranging, bearing, los, ch))[0])
        g = np.random.default_rng(args.seed)
        state, state_m = est.initial_state((T,), cfg), est.initial_state((T,), cfg_memory)
        ranges = []
        for _ in range(K):
            obs = observe_from_uniforms(src, np.broadcast_to(final, (T, n, 3)), ranging, bearing, np.broadcast_to(los, (T, n)), ch, g.random((T, n, 5)))
            ranges.append(obs.range_m)
            meas = est.Measurements(
                positions_m=np.broadcast_to(final, (T, n, 3)).copy(), range_m=obs.range_m, azimuth_rad=np.full((T, n), np.nan),
                elevation_rad=np.full((T, n), np.nan), los=np.broadcast_to(los, (T, n)).copy())
            state = est.update(state, meas, ch, cfg)
            state_m = est.update(state_m, meas, ch, cfg_memory)
        d_hat = np.stack(ranges, 1)  # (T, K, N)
        s0sq = np.where(los, ch.sigma_r0_los**2, ch.sigma_r0_nlos**2)

        def nll(x: np.ndarray, t: int) -> float:
            d = np.linalg.norm(final - x, axis=1)
            var = s0sq * d**ch.gamma
            return float(0.5 * (((d_hat[t] - d) ** 2) / var + np.log(var)).sum())

        ml, ml_box = np.empty((T, 3)), np.empty((T, 3))
        bounds = list(zip(np.maximum(lo, -1e4), np.minimum(hi, 1e4), strict=True))
        for t in range(T):
            fits = [minimize(nll, x0, args=(t,), method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-7, "maxiter": 4000})
                    for x0 in (src, state.estimate_m[t])]
            ml[t] = min(fits, key=lambda r: r.fun).x
            ml_box[t] = minimize(nll, np.clip(ml[t], lo, hi), args=(t,), method="L-BFGS-B", bounds=bounds).x

        def ratio(x: np.ndarray) -> float:
            return math.sqrt(float(((x - src) ** 2).sum(1).mean())) / peb

        def up(x: np.ndarray) -> str:
            return f"{float((x[:, 2] - src[2]).mean()):.2f} | {100 * float((x[:, 2] - src[2] > 10).mean()):.0f} %"

        print(f"| {K} | {peb:.2f} | {ratio(state.estimate_m):.2f} | {up(state.estimate_m)} | {ratio(state_m.estimate_m):.2f} | {up(state_m.estimate_m)} "
              f"| {ratio(ml):.2f} | {ratio(ml_box):.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
