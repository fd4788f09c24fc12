"""One trial of a larger in-process run replays alone (``RunSpec.first_trial``): trial m's
measurement noise, injected faults and singular-FIM perturbations come from streams of
(seed, m, drone) only (``planner.randomness.stream``), and the trials of a vectorised run do not
depend on each other. The reference is the same trial inside the larger run: bit-identical
without injected faults. With them the record ages (the faults drawn) are the same, and the
positions agree to rounding at first (some batched sums of the faulty views run over arrays of
another shape): below 1e-9 m for the first 15 steps here, after which the chaotic runs can part
(0.08 m by step 40)."""

from __future__ import annotations

import numpy as np
import pytest

from missions.format.loader import load_mission
from missions.study.results import violating_drones
from missions.study.simulator import RunSpec, simulate


@pytest.mark.parametrize(
    "overrides",
    [{}, {"comms.faults.loss": 0.2, "comms.faults.extra_delay_steps": 3}],
    ids=["no-faults", "loss-and-delay"],
)
def test_a_trial_replayed_alone_flies_as_it_did_in_the_larger_run(overrides: dict[str, float]) -> None:
    mission = load_mission("paper/heterogeneous", overrides)
    whole = simulate(RunSpec(mission, "A", 3, 40))
    alone = simulate(RunSpec(mission, "A", 1, 40, first_trial=2))
    np.testing.assert_array_equal(alone.record_ages[:, 0], whole.record_ages[:, 2])
    if overrides:
        np.testing.assert_allclose(alone.positions_m[:16, 0], whole.positions_m[:16, 2], rtol=0, atol=1e-9)
        np.testing.assert_allclose(alone.estimates_m[:15, 0], whole.estimates_m[:15, 2], rtol=0, atol=1e-9)
    else:
        np.testing.assert_array_equal(alone.positions_m[:, 0], whole.positions_m[:, 2])
        np.testing.assert_array_equal(alone.estimates_m[:, 0], whole.estimates_m[:, 2])
    # and it is not trial 0 of the run, which first_trial=0 would have flown
    assert np.abs(alone.positions_m[:, 0] - whole.positions_m[:, 0]).max() > 1.0


def test_a_replayed_trial_is_reported_under_its_own_number() -> None:
    """``violating_drones`` names the trial by its number in the run it came from."""
    mission = load_mission("paper/joint", {"constraints.activation": "paper"})
    whole = violating_drones(simulate(RunSpec(mission, "A", 3, 200)))
    alone = violating_drones(simulate(RunSpec(mission, "A", 1, 200, first_trial=2)))
    assert alone, "the paper's literal rule crosses a distance within 200 steps"
    assert {e["trial"] for entries in alone.values() for e in entries} == {2}
    compared = 0
    for family, entries in alone.items():
        mine = {e["drone"]: e for e in entries}
        for drone, entry in ((e["drone"], e) for e in whole.get(family, []) if e["trial"] == 2):
            if drone in mine:  # the larger run lists only its worst pairs
                assert mine[drone] == entry
                compared += 1
    assert compared > 0
