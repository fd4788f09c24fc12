"""How often the 95 % region of ``fimnav localize`` covers the truth, on synthetic logs (not a test).

    python benchmarks/radio_coverage.py [--samples 240 360 960] [--reps 300] [--grid 12]

A survey flight (six east-west legs over ±120 m at 40 m), an emitter on the ground drawn
uniformly in ±60 m, the log-distance model with γ = 3, σ = 6 dB and a reference power drawn in
[−20, 40] dB and unknown to the estimate; three scenarios: no censoring; 40 % of the samples
censored below a threshold; a vertical dipole's zenith null with 25 % censored. Per scenario
and sample count: the share of repetitions whose profile-likelihood region (deviance ≤ χ²₂,
0.95 = 5.99) holds the truth, the mean deviance at the truth (2 for an exact χ²₂) and the
seconds per repetition. The default test run checks 360 samples, 200 repetitions
(``tests/planner/test_radio_localize.py``).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
from scipy.stats import chi2

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path[:1]:
    sys.path.insert(0, str(REPO))

from planner.radio.localize import LocalizeOptions, RadioLog, maximum_likelihood, profile_loglik  # noqa: E402
from planner.radio.pathloss import Pattern, link_terms  # noqa: E402

SCENARIOS = (
    ("unknown power", 1, "isotropic", 0.0),
    ("unknown power, 40 % censored", 2, "isotropic", 0.4),
    ("zenith null, 25 % censored", 3, "dipole", 0.25),
)


def survey(samples: int) -> np.ndarray:
    """Six legs over ±120 m at 40 m, ``samples`` positions (m, ENU)."""
    per = samples // 6
    x = np.linspace(-120.0, 120.0, per)
    return np.concatenate(
        [np.column_stack([x[:: 1 - 2 * (i % 2)], np.full(per, y), np.full(per, 40.0)]) for i, y in enumerate(np.linspace(-120.0, 120.0, 6))]
    )


def deviance_at_truth(rng: np.random.Generator, pos: np.ndarray, pattern: str, share: float, options: LocalizeOptions) -> float:
    """One repetition: draw the emitter and a log, return 2(ℓ̂ − ℓ_p(truth))."""
    src = np.array([rng.uniform(-60, 60), rng.uniform(-60, 60), 1.0])
    terms = link_terms(src, pos, Pattern(pattern), derivatives=False)
    p0 = rng.uniform(-20.0, 40.0)
    y = p0 - 3.0 * terms.log_d + terms.gain + 6.0 * rng.standard_normal(len(pos))
    thr = float(np.quantile(p0 - 3.0 * terms.log_d, share)) if share > 0 else np.nan
    cens = y < thr if share > 0 else np.zeros(len(y), dtype=bool)
    log = RadioLog(pos, np.where(cens, np.nan, y), cens, np.full(len(y), thr))
    return 2.0 * (maximum_likelihood(log, options).loglik - float(profile_loglik(log, options, src)))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, nargs="+", default=[240, 360, 960])
    ap.add_argument("--reps", type=int, default=300)
    ap.add_argument("--grid", type=int, default=12)
    args = ap.parse_args(argv)
    level = chi2.ppf(0.95, 2)
    print("| scenario | samples | repetitions | coverage | mean deviance | s per repetition |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, seed, pattern, share in SCENARIOS:
        options = LocalizeOptions(
            area_min_m=(-200.0, -200.0), area_max_m=(200.0, 200.0), emitter_z_m=1.0, gamma=3.0, pattern=Pattern(pattern), grid=args.grid
        )
        for n in args.samples:
            pos = survey(n)
            t0 = time.perf_counter()
            dev = np.array([deviance_at_truth(np.random.default_rng([seed, r]), pos, pattern, share, options) for r in range(args.reps)])
            per = (time.perf_counter() - t0) / args.reps
            print(f"| {name} | {n} | {args.reps} | {100 * np.mean(dev <= level):.1f} % | {dev.mean():.2f} | {per:.3f} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
