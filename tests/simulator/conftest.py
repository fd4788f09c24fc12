"""Shared fixtures: the paper missions and cached reduced runs (each run once per session)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import pytest

from missions.format.loader import load_mission
from missions.format.schema import Mission
from missions.study.simulator import RunSpec, SimulationResult, simulate

PAPER = Path(__file__).resolve().parents[2] / "missions" / "paper"


def paper_mission(name: str, **overrides: object) -> Mission:
    """A paper mission from missions/paper/<name>.yaml with dotted-key overrides."""
    return load_mission(PAPER / f"{name}.yaml", dict(overrides) if overrides else None)


@pytest.fixture(scope="session")
def reduced_run() -> Callable[..., SimulationResult]:
    """``reduced_run(name, criterion, trials, steps, **overrides)``, memoised for the session."""
    cache: dict[tuple, SimulationResult] = {}

    def run(name: str, criterion: str = "A", trials: int = 3, steps: int = 200, **overrides: object) -> SimulationResult:
        key = (name, criterion, trials, steps, tuple(sorted(overrides.items())))
        if key not in cache:
            cache[key] = simulate(RunSpec(paper_mission(name, **overrides), criterion, trials, steps))
        return cache[key]

    return run
