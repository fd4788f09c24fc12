"""The compiled estimator kernels (planner/estimator/kernels) against independent references:
numpy's own sums, the memory's likelihood minimised by scipy, the candidates' likelihood
evaluated point by point, a component's error raised through the compiled refinement, the
import cost of the estimator package, and determinism."""

from __future__ import annotations

import json
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
from scipy.optimize import minimize

from planner import estimator as est
from planner.estimator import memory as rmem
from planner.estimator.kernels.linalg import dot, pairwise_sum
from planner.params import Channel
from planner.sensing import COMPONENTS, LinkGeometry, SensingComponent

ROOT = Path(__file__).resolve().parents[2]
GAMMA = 2.0
BOX = (np.array([-1000.0, -1000.0, 0.0]), np.array([1000.0, 1000.0, 30.0]))


def test_sums_are_numpys_sums_to_the_bit() -> None:
    """dot is numpy.einsum('k,k->') and pairwise_sum numpy.sum, bit for bit (the PL systems
    are summed this way: a tie between mirror roots is decided by their last bits)."""
    rng = np.random.default_rng(1)
    for n in (*range(0, 20), 31, 64, 127, 128, 129, 300, 1000):
        a = rng.standard_normal(n) * 10.0 ** rng.integers(-8, 8, n)
        b = rng.standard_normal(n)
        assert dot(a, b, n) == np.einsum("k,k->", a, b), n
        assert pairwise_sum(a, 0, n) == a.sum(), n


def _memory(rng: np.random.Generator, cells: int = 64) -> rmem.RangeMemory:
    src = np.array([0.0, 0.0, 2.0])
    mem = rmem.empty_memory((), cells)
    for _ in range(12):
        pos = np.column_stack((rng.uniform(-60, 60, 10), rng.uniform(-60, 60, 10), rng.uniform(2, 25, 10)))
        d = np.linalg.norm(pos - src, axis=1)
        mem = rmem.insert(mem, pos, d + 0.39 * d * rng.standard_normal(10), np.ones(10), np.full(10, 0.39), 0.05)
    return mem


def test_polish_reaches_the_likelihoods_minimum() -> None:
    """From two starts, the likelier polished point is the minimum that scipy finds in the
    search box (L-BFGS-B on rmem.nll, from that point): the same cost within 1e-3 (the polish
    stops once its step is shorter than 1 mm, slow along the flat directions of a ranging
    likelihood)."""
    mem = _memory(np.random.default_rng(2))
    starts = np.array([[5.0, -3.0, 10.0], [-20.0, 15.0, 25.0]])
    x, cost = rmem.polish(mem, starts, GAMMA, BOX)
    np.testing.assert_allclose(cost, rmem.nll(mem, x, GAMMA), rtol=1e-12)
    best = int(np.argmin(cost))
    ref = minimize(
        lambda y: float(rmem.nll(mem, y, GAMMA)),
        x[best],
        method="L-BFGS-B",
        bounds=list(zip(*BOX, strict=True)),
        options={"ftol": 1e-15, "gtol": 1e-10},
    )
    assert abs(cost[best] - ref.fun) < 1e-3


def test_best_start_is_the_likeliest_candidate() -> None:
    """best_start returns the point of lowest likelihood among the candidate and the points on
    the least-informed line (reconstructed here from the memory's Fisher information)."""
    mem = _memory(np.random.default_rng(3))
    x, cand = np.array([3.0, 4.0, 12.0]), np.array([-10.0, 8.0, 1.0])
    got = rmem.best_start(mem, x, cand, GAMMA, BOX, points=16)
    _, F = rmem.gradient_fisher(mem, x, GAMMA, False)
    v = np.linalg.eigh(F)[1][:, 0]
    cells = rmem.Cells.of(mem)
    reach = np.linalg.norm(x - cells.centre[cells.n > 0], axis=1).mean()
    pts = np.clip(x + (np.linspace(-1.0, 1.0, 16) * reach)[:, None] * v, *BOX)
    pts = np.vstack((pts, cand))
    costs = rmem.nll(mem, pts, GAMMA)
    assert rmem.nll(mem, got, GAMMA) <= costs.min() + 1e-9


@dataclass(frozen=True)
class _Broken(SensingComponent):
    """A component whose estimator terms fail."""

    name: ClassVar[str] = "broken"
    wire_bit: ClassVar[int] = 8
    value_names: ClassVar[tuple[str, ...]] = ("broken_value",)

    def estimator_terms(self, values: tuple[np.ndarray, ...], geom: LinkGeometry, channel: Channel) -> tuple[np.ndarray, np.ndarray]:
        raise RuntimeError("broken component: no terms")


def test_an_error_of_a_component_reaches_the_caller() -> None:
    """A component outside the compiled kernel is called back from compiled code; its error is
    raised by the update, not lost in the callback."""
    rng = np.random.default_rng(4)
    pos = rng.uniform(-50, 50, (6, 3))
    d = np.linalg.norm(pos, axis=1)
    nan = np.full(6, np.nan)
    meas = est.Measurements(pos, d, nan, nan, np.ones(6, bool), {"broken_value": d * d})
    with pytest.raises(RuntimeError, match="broken component"):
        est.update(est.initial_state(()), meas, Channel(), est.EstimatorConfig(), (*COMPONENTS, _Broken()))


def test_updates_are_deterministic() -> None:
    """The same records give the same state, bit for bit, in the same process and across
    batch layouts (a batch element computes what the same records give alone)."""
    rng = np.random.default_rng(5)
    config = est.EstimatorConfig(range_memory_cells=32, bounds_min_m=BOX[0], bounds_max_m=BOX[1])
    pos = rng.uniform(-60, 60, (12, 3, 10, 3))
    rec = [np.linalg.norm(p - np.array([0.0, 0.0, 2.0]), axis=-1) * (1 + 0.3 * rng.standard_normal((3, 10))) for p in pos]
    nan = np.full((3, 10), np.nan)

    def run(sel: slice) -> est.EstimatorState:
        state = est.initial_state((pos[0][sel].shape[0],), config)
        for p, r in zip(pos, rec, strict=True):
            state = est.update(state, est.Measurements(p[sel], r[sel], nan[sel], nan[sel], np.ones_like(r[sel], bool)), Channel(), config)
        return state

    a, b = run(slice(None)), run(slice(None))
    np.testing.assert_array_equal(a.estimate_m, b.estimate_m)
    np.testing.assert_array_equal(a.information, b.information)
    alone = run(slice(1, 2))
    np.testing.assert_array_equal(alone.estimate_m[0], a.estimate_m[1])


def test_importing_the_estimator_does_not_load_the_compiler() -> None:
    """planner.estimator (its types, a mission's settings) imports without numba; the first
    update loads it."""
    code = (
        "import json, sys\n"
        "import planner.estimator as est, missions.format.schema\n"
        "before = 'numba' in sys.modules\n"
        "import numpy as np\n"
        "from planner.params import Channel\n"
        "nan = np.full(1, np.nan)\n"
        "est.update(est.initial_state(()), est.Measurements(np.zeros((1, 3)), nan, nan, nan, np.ones(1, bool)), Channel())\n"
        "print(json.dumps([before, 'numba' in sys.modules]))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == [False, True]
