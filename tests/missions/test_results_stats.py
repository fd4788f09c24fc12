"""Student's t quantile of a run's PEB interval (missions/study/results.py), against closed forms
(ν = 1: Cauchy; ν = 2; the density at 0 for p near ½) and scipy's t quantile."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import stdtrit

from missions.study.results import student_t_quantile


@pytest.mark.parametrize("p", [0.5 + 1e-9, 0.51, 0.6, 0.75, 0.9, 0.975, 0.995, 0.999999])
def test_closed_forms_of_one_and_two_degrees_of_freedom(p: float) -> None:
    # ν = 1: Cauchy, t = tan(π (p − ½)) = 1 / tan(π (1 − p)) (the form without cancellation);
    # ν = 2: u = 2p − 1 = t / √(2 + t²), t = u √(2 / (1 − u²)).
    cauchy = math.tan(math.pi * (p - 0.5)) if p < 0.75 else 1.0 / math.tan(math.pi * (1.0 - p))
    assert student_t_quantile(p, 1) == pytest.approx(cauchy, rel=1e-11)
    u = 2.0 * p - 1.0
    assert student_t_quantile(p, 2) == pytest.approx(u * math.sqrt(2.0 / (1.0 - u * u)), rel=1e-11)


@pytest.mark.parametrize("dof", [3, 4, 10, 99, 1000])
def test_near_the_median_the_quantile_is_the_offset_over_the_density_at_zero(dof: int) -> None:
    # P(0 < T < t) = f(0) t + O(t³): for p − ½ = 1e-9, t = (p − ½) / f(0) to 1e-12.
    f0 = math.exp(math.lgamma((dof + 1) / 2) - math.lgamma(dof / 2)) / math.sqrt(dof * math.pi)
    assert student_t_quantile(0.5 + 1e-9, dof) == pytest.approx(1e-9 / f0, rel=1e-9)


def test_agrees_with_scipy_over_degrees_of_freedom_and_levels() -> None:
    for dof in [1, 2, 3, 5, 9, 19, 49, 99, 199, 999, 9999]:
        for p in [0.55, 0.6, 0.75, 0.8, 0.9, 0.95, 0.975, 0.99, 0.995, 0.9995, 0.999999]:
            assert student_t_quantile(p, dof) == pytest.approx(float(stdtrit(dof, p)), rel=1e-10), (dof, p)


@pytest.mark.parametrize(("p", "dof"), [(0.5, 10), (1.0, 10), (0.3, 10), (0.9, 0), (0.9, -1), (float("nan"), 3), (0.9, float("nan"))])
def test_outside_its_domain_it_says_so(p: float, dof: float) -> None:
    with pytest.raises(ValueError, match="student_t_quantile"):
        student_t_quantile(p, dof)


def test_the_run_interval_is_the_t_interval_of_the_trial_means() -> None:
    rng = np.random.default_rng(7)
    per_trial = rng.gamma(3.0, 2.0, 37)
    half = student_t_quantile(0.975, 36) * per_trial.std(ddof=1) / math.sqrt(37)
    assert half == pytest.approx(float(stdtrit(36, 0.975)) * per_trial.std(ddof=1) / math.sqrt(37), rel=1e-12)
