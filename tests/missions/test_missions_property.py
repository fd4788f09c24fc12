"""Property tests: any valid mission survives mission_to_yaml -> load unchanged and satisfies
the JSON Schema; breaking one ordered pair (v_min/v_max, z_min/z_max) is always refused."""

from __future__ import annotations

from typing import Any

import jsonschema
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from missions.format.loader import MissionError, loads_mission, mission_to_yaml
from missions.format.schema import mission_json_schema

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@st.composite
def missions(draw: st.DrawFn) -> dict[str, Any]:
    count = draw(st.integers(1, 12))
    roles: Any = draw(st.one_of(st.sampled_from(["ranging", "bearing", "joint"]),
                                st.lists(st.sampled_from(["ranging", "bearing", "joint"]), min_size=count, max_size=count)))
    v_min = draw(st.floats(0.0, 5.0))
    v_max = draw(st.floats(max(v_min, 1e-3), 10.0))
    z_min = draw(st.floats(-10.0, 50.0))
    z_max = draw(st.floats(z_min + 30.0, z_min + 100.0))
    rx = draw(st.floats(5.0 * count, 100.0 * count))
    return {
        "id": draw(st.from_regex(r"[A-Za-z0-9_-]{1,20}", fullmatch=True)),
        "description": draw(st.text(max_size=30)),
        "seed": draw(st.integers(0, 2**64 - 1)),
        "dt_s": draw(st.floats(1e-3, 10.0)),
        "steps": draw(st.integers(1, 10_000)),
        "trials": draw(st.integers(1, 1000)),
        "criterion": draw(st.sampled_from(["A", "D"])),
        "origin": {"lat_deg": draw(st.floats(-90, 90)), "lon_deg": draw(st.floats(-180, 180)), "alt_m": draw(finite)},
        "drones": {
            "count": count,
            "roles": roles,
            "start": {"ellipse": {"center_m": [0.0, 0.0, z_min + 15.0], "radius_x_m": rx, "radius_z_m": 10.0,
                                  "phase_deg": draw(st.floats(-360, 360))}},
        },
        "source": {"position_m": [0.0, -(rx + 600.0), 0.0], "velocity_mps": [draw(st.floats(-0.1, 0.1)), 0.0, 0.0]},
        "constraints": {"speed_min_mps": v_min, "speed_max_mps": v_max, "z_min_m": z_min, "z_max_m": z_max,
                        "d_uav_m": 1.0, "activation": draw(st.sampled_from(["safe", "paper"]))},
        "fence": {"x_min_m": -2e6, "x_max_m": 2e6,  # the source may drift 10 km
                  "y_min_m": -(rx + 2000.0), "y_max_m": 5000.0},
        "controller": {"xi": draw(st.one_of(st.none(), st.floats(1e-3, 10.0)))},
    }


@pytest.fixture(scope="module")
def validator() -> Any:
    return jsonschema.Draft202012Validator(mission_json_schema())


@settings(max_examples=30, deadline=None)
@given(missions())
def test_round_trip_and_schema(validator: Any, doc: dict[str, Any]) -> None:
    m = loads_mission(yaml.safe_dump(doc))
    text = mission_to_yaml(m)
    assert loads_mission(text) == m
    assert validator.is_valid(yaml.safe_load(text))
    assert validator.is_valid(doc)


@settings(max_examples=30, deadline=None)
@given(missions(), st.sampled_from([("speed_min_mps", "speed_max_mps"), ("z_min_m", "z_max_m")]), st.floats(0.1, 10.0))
def test_swapped_bounds_are_refused(doc: dict[str, Any], pair: tuple[str, str], gap: float) -> None:
    lo, hi = pair
    doc["constraints"][lo] = doc["constraints"][hi] + gap
    with pytest.raises(MissionError, match=rf"constraints\.{lo}: expected {lo} <= {hi}"):
        loads_mission(yaml.safe_dump(doc))
