"""Estimator accuracy against the bound in a paper mission's final geometry (by default the ranging one).

    python benchmarks/estimator_final_geometry.py [--mission paper/ranging_los] [--trials 400] [--snapshots 1 10 50] [--memory-cells 64]
        [--geometry final|optimum] [--z-max METRES]

The drones are held fixed at ``--geometry`` ``final`` (default): the final positions of the
mission's first trial (the in-process simulator, seeded), or ``optimum``: the mission's optimal
placement for criterion A about the true source (``fimnav optimum MISSION --oracle-estimate``:
the safe rule's end-of-step distances, 8 starts, seed 0), the placement with the smallest PEB
that keeps the drones d_S* plus the turn buffer from the source and inside the altitude box.
``--z-max`` replaces the ceiling of that box (as ``--set constraints.z_max_m=METRES``; for
``final`` the simulated trial flies under it too); the first line printed then also names the
box. Each trial draws ``K`` snapshots of the ten drones' records there (their roles' ranges
and bearings, the paper's channel, seeded noise) and gives them to (a) fimnav's estimator with the mission's settings but without the
range memory, one call per snapshot as a planner would, (b) the same with the range memory of
``--memory-cells`` cells (``range_memory_cells``; a mission's default for a static source is
256, and held still the drones' ranges fill a few cells, so 64 act as 256 would), and
(c) the exact maximum-likelihood estimate of the same ranges (d̂ ~ N(d, σ_r0² d^γ), minimised by
Nelder-Mead from the true source and from the estimator's answer, the better kept), unbounded
and (d) in the mission's search box (L-BFGS-B from (c), clipped); (c) and (d) for a ranging-only
swarm, "—" for a swarm with bearings. Printed per K: the PEB of the
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

from missions.study.optimum import mission_optimum  # noqa: E402
from missions.format.loader import load_mission  # noqa: E402
from missions.format.schema import Mission  # noqa: E402
from missions.study.simulator import RunSpec, simulate  # noqa: E402
from planner import estimator as est  # noqa: E402
from planner.fim import fisher_information, position_error_bound  # noqa: E402
from planner.geometry import line_of_sight  # noqa: E402
from planner.observation import observe_from_uniforms  # noqa: E402

#: Random starts and seed of the optimal placement (``fimnav optimum``'s defaults).
OPTIMUM_STARTS: int = 8
OPTIMUM_SEED: int = 0


def drone_positions(mission: Mission, geometry: str) -> tuple[np.ndarray, str]:
    """The drones' fixed positions (N, 3), m, ENU, for ``geometry`` (``"final"``: where the
    mission's seeded trial 0 ends; ``"optimum"``: its optimal placement, criterion A, about the
    true source) and a few words naming them."""
    if geometry == "final":
        return simulate(RunSpec(mission, "A", 1, mission.steps)).positions_m[-1, 0], "final geometry of trial 0"
    p = mission_optimum(mission, "A", OPTIMUM_STARTS, OPTIMUM_SEED, "filter", oracle_estimate=True)
    b = p.bounds
    return p.positions_m, (
        f"optimal placement (criterion A, PEB {p.peb_m:.2f} m per snapshot; source >= {b.source_m:.2f} m, "
        f"{OPTIMUM_STARTS} starts, seed {OPTIMUM_SEED})"
    )


def range_nll(x: np.ndarray, positions: np.ndarray, d_hat: np.ndarray, s0sq: np.ndarray, gamma: float) -> float:
    """Negative log-likelihood (up to a constant) of the ranges ``d_hat`` (K, N), m, of drones at
    ``positions`` (N, 3), m, ENU, for a source at ``x`` (3,): d̂ ~ N(d, σ_r0² d^γ), ``s0sq`` the
    σ_r0² of each link (N,), m^(2−γ)."""
    d = np.linalg.norm(positions - x, axis=1)
    var = s0sq * d**gamma
    return float(0.5 * (((d_hat - d) ** 2) / var + np.log(var)).sum())


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mission", default="paper/ranging_los")
    ap.add_argument("--trials", type=int, default=400)
    ap.add_argument("--memory-cells", type=int, default=64)
    ap.add_argument("--snapshots", type=int, nargs="+", default=[1, 10, 50])
    ap.add_argument("--seed", type=int, default=7)
    ap.add_argument("--geometry", choices=("final", "optimum"), default="final", help="where the drones are held (default final)")
    ap.add_argument("--z-max", type=float, default=None, metavar="METRES", help="ceiling of the altitude box (default: the mission's)")
    args = ap.parse_args(argv)
    m = load_mission(args.mission, None if args.z_max is None else {"constraints.z_max_m": args.z_max})
    ch = m.channel.to_planner()
    cfg = dataclasses.replace(m.estimator_config(), range_memory_cells=0)  # (a): without the memory
    src = np.array(m.source.position_m, dtype=float)
    final, what = drone_positions(m, args.geometry)  # (N, 3), m, ENU
    n = final.shape[0]
    bmin = np.array([o.min_m for o in m.obstacles], dtype=float).reshape(-1, 3)
    bmax = np.array([o.max_m for o in m.obstacles], dtype=float).reshape(-1, 3)
    los = line_of_sight(final, src, bmin, bmax)  # (N,)
    roles = m.drones.roles
    ranging = np.array([r in ("ranging", "joint") for r in roles])
    bearing = np.array([r in ("bearing", "joint") for r in roles])
    ranges_only = not bearing.any()  # the exact ML (c, d) is of ranges only
    if args.geometry != "final" or args.z_max is not None:
        what += f", altitude box z in [{m.constraints.z_min_m:g}, {m.constraints.z_max_m:g}] m"
    print(
        f"{args.mission}: {what}, drone heights {np.round(final[:, 2], 1).tolist()} m, "
        f"distances {np.round(np.linalg.norm(final - src, axis=1), 1).tolist()} m"
    )
    print(
        "| K | PEB (m) | without range memory ×PEB | height bias (m) | > 10 m above | with range memory ×PEB | height bias (m) | > 10 m above "
        "| exact ML ×PEB | exact ML in the search box ×PEB |"
    )
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
            obs = observe_from_uniforms(
                src, np.broadcast_to(final, (T, n, 3)), ranging, bearing, np.broadcast_to(los, (T, n)), ch, g.random((T, n, 5))
            )
            ranges.append(obs.range_m)
            meas = est.Measurements(
                positions_m=np.broadcast_to(final, (T, n, 3)).copy(),
                range_m=obs.range_m,
                azimuth_rad=obs.azimuth_rad,
                elevation_rad=obs.elevation_rad,
                los=np.broadcast_to(los, (T, n)).copy(),
            )
            state = est.update(state, meas, ch, cfg)
            state_m = est.update(state_m, meas, ch, cfg_memory)
        d_hat = np.stack(ranges, 1)  # (T, K, N)
        s0sq = np.where(los, ch.sigma_r0_los**2, ch.sigma_r0_nlos**2)

        ml, ml_box = np.full((T, 3), np.nan), np.full((T, 3), np.nan)
        bounds = list(zip(np.maximum(lo, -1e4), np.minimum(hi, 1e4), strict=True))
        for t in range(T if ranges_only else 0):
            data = (final, d_hat[t], s0sq, ch.gamma)
            fits = [
                minimize(range_nll, x0, args=data, method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-7, "maxiter": 4000})
                for x0 in (src, state.estimate_m[t])
            ]
            ml[t] = min(fits, key=lambda r: r.fun).x
            ml_box[t] = minimize(range_nll, np.clip(ml[t], lo, hi), args=data, method="L-BFGS-B", bounds=bounds).x

        def ratio(x: np.ndarray, peb: float = peb) -> str:
            return "—" if np.isnan(x).all() else f"{math.sqrt(float(((x - src) ** 2).sum(1).mean())) / peb:.2f}"

        def up(x: np.ndarray) -> str:
            return f"{float((x[:, 2] - src[2]).mean()):.2f} | {100 * float((x[:, 2] - src[2] > 10).mean()):.0f} %"

        print(
            f"| {K} | {peb:.2f} | {ratio(state.estimate_m)} | {up(state.estimate_m)} | {ratio(state_m.estimate_m)} | {up(state_m.estimate_m)} "
            f"| {ratio(ml)} | {ratio(ml_box)} |"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
