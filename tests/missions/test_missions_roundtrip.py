"""mission_to_yaml -> load gives an equal Mission; the Mission is frozen; overrides and
relative paths behave as documented; in-process errors are MissionError (a UsageError)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pydantic
import pytest

from missions.format.loader import MissionError, load_mission, loads_mission, mission_to_yaml, parse_overrides
from missions.format.schema import Mission
from comms.errors import UsageError

PAPER = Path(__file__).resolve().parents[2] / "missions" / "paper"

RICH = """\
id: rich-mission_1
description: every section set
seed: 18446744073709551615
dt_s: 0.5
steps: 40
trials: 3
criterion: D
origin: {lat_deg: 44.4949, lon_deg: 11.3426, alt_m: 54.0}
drones:
  count: 3
  roles: [joint, bearing, ranging]
  start:
    positions_m: [[0, 100, 5], [10, 100, 6], [20, 100, 7]]
source: {position_m: [0, 0, 1], velocity_mps: [0.1, -0.2, 0]}
obstacles:
  - {name: hall, min_m: [-30, 40, 0], max_m: [-10, 60, 40]}
channel: {path_loss_exponent: 3.0, sigma_ratio_los: 2, sigma_ratio_nlos: 4, sigma_bearing_deg: 5}
constraints: {d_uav_m: 2, d_source_m: 20, d_obstacle_m: 3, speed_min_mps: 0, speed_max_mps: 5,
              heading_change_max_deg: 30, tilt_change_max_deg: 20, z_min_m: 1, z_max_m: 50, activation: paper}
comms: {d_hop_m: 60, h_max: 3, latency: real}
controller: {xi: 0.25, random_perturbation_deg: 10}
fence: {x_min_m: -200, x_max_m: 200, y_min_m: -100, y_max_m: 300}
zenoh:
  mode: client
  listen: []
  connect: ["tls/192.0.2.1:7447"]
  multicast_scouting: false
  tls: {root_ca_certificate: certs/ca.pem, certificate: certs/node.pem, private_key: certs/node.key}
  auth: {user: swarm, password_file: secrets/zenoh.pw}
vehicles:
  flavour: px4
  profile: pointmass
  overrides:
    - {connection: "udpin:127.0.0.1:14550", signing_key_file: keys/d1.key}
    - {flavour: ardupilot}
    - {connection: "/dev/ttyUSB0,57600"}
end_action: rtl
altitude_reference: amsl
takeoff_alt_m: 10
"""


@pytest.mark.parametrize("path", sorted(PAPER.glob("*.yaml")), ids=lambda p: p.stem)
def test_round_trip_paper(path: Path) -> None:
    m = load_mission(path)
    text = mission_to_yaml(m)
    again = loads_mission(text)
    assert again == m
    assert mission_to_yaml(again) == text


def test_round_trip_rich(tmp_path: Path) -> None:
    f = tmp_path / "rich.yaml"
    f.write_text(RICH)
    m = load_mission(f)
    again = loads_mission(mission_to_yaml(m))
    assert again == m
    # relative paths were resolved against the mission file's directory
    assert m.zenoh.tls is not None and m.zenoh.tls.root_ca_certificate == tmp_path / "certs" / "ca.pem"
    assert m.zenoh.auth is not None and m.zenoh.auth.password_file == tmp_path / "secrets" / "zenoh.pw"
    v0, v1, v2 = (m.vehicles.for_drone(i) for i in range(3))
    assert (v0.connection, v0.flavour, v0.signing_key_file) == ("udpin:127.0.0.1:14550", "px4", tmp_path / "keys" / "d1.key")
    assert (v1.connection, v1.flavour, v1.profile) == (None, "ardupilot", "pointmass")
    assert v2.connection == "/dev/ttyUSB0,57600"
    assert m.seed == 2**64 - 1 and m.controller.xi == 0.25 and m.takeoff_alt_m == 10.0
    limits = m.limits()
    assert (limits.step_min_m, limits.step_max_m, limits.activation) == (0.0, 2.5, "paper")
    np.testing.assert_allclose(m.source.position_at(10.0), [1.0, -2.0, 1.0])


@pytest.mark.parametrize("text", ["\x85", "a\x85b", "\u2028", "x\u2029y", "tab\tand\nnewline", "café ✓"])
def test_round_trip_text_with_unicode_line_breaks(text: str) -> None:
    """NEL, LS and PS are YAML line breaks: the mission as run escapes them, so the text reads back unchanged."""
    mission = load_mission(PAPER / "joint.yaml", {"description": text})
    again = loads_mission(mission_to_yaml(mission))
    assert again.description == text and again == mission


def test_mission_is_frozen() -> None:
    m = load_mission(PAPER / "joint.yaml")
    with pytest.raises(pydantic.ValidationError):
        m.steps = 3  # type: ignore[misc]
    with pytest.raises(pydantic.ValidationError):
        m.constraints.z_max_m = 3.0  # type: ignore[misc]
    assert isinstance(m.drones.roles, tuple) and isinstance(m.obstacles, tuple)
    assert hash(m.constraints) == hash(load_mission(PAPER / "joint.yaml").constraints)


def test_defaults_documented_values() -> None:
    m = loads_mission("id: x\ndrones: {count: 2, roles: ranging, start: {ellipse: {}}}\nsource: {position_m: [0, 0, 2]}\n")
    assert (m.origin.lat_deg, m.origin.lon_deg, m.origin.alt_m) == (-35.363261, 149.16523, 584.0)
    assert (m.seed, m.dt_s, m.steps, m.trials, m.criterion) == (0, 1.0, 550, 100, "A")
    assert m.zenoh.listen == ("tcp/127.0.0.1:0",) and m.zenoh.multicast_scouting is False
    assert (m.vehicles.flavour, m.vehicles.profile, m.end_action, m.altitude_reference) == ("ardupilot", "ideal", "hold", "relative")
    assert (m.comms.latency, m.controller.xi, m.controller.random_perturbation_deg) == ("emulated", None, 20.0)
    assert (m.fence.x_min_m, m.fence.y_max_m) == (-1000.0, 1000.0)
    assert m.drones.roles == ("ranging", "ranging")


def test_overrides_dotted_and_nested() -> None:
    m = load_mission(PAPER / "joint.yaml", {"constraints.activation": "paper", "comms": {"h_max": 2}, "trials": 4})
    assert (m.constraints.activation, m.comms.h_max, m.trials) == ("paper", 2, 4)
    assert m.constraints.z_max_m == 25.0 and m.comms.d_hop_m == 100.0  # untouched siblings
    m = load_mission(PAPER / "joint.yaml", {"drones.count": 4})  # a role string follows the count
    assert m.drones.roles == ("joint",) * 4 and m.drones.start_positions_m().shape == (4, 3)


def test_estimator_range_memory_reaches_the_planner() -> None:
    """``estimator.range_memory_cells`` is the planner's estimator setting; by default 256 for a
    static source and 0 (off) for a moving one, where an explicit memory is refused."""
    assert load_mission(PAPER / "ranging_los.yaml").planner_config().estimator.range_memory_cells == 256
    assert load_mission(PAPER / "dynamic_source.yaml").planner_config().estimator.range_memory_cells == 0
    off = load_mission(PAPER / "ranging_los.yaml", {"estimator.range_memory_cells": 0})
    assert off.planner_config().estimator.range_memory_cells == 0
    with pytest.raises(MissionError, match=r"estimator.range_memory_cells: expected 0 or null for a moving source.*found 64"):
        load_mission(PAPER / "dynamic_source.yaml", {"estimator.range_memory_cells": 64})
    m = load_mission(PAPER / "ranging_los.yaml", {"estimator.range_memory_cells": 64})
    config = m.planner_config().estimator
    assert config.range_memory_cells == 64
    assert config.forgetting == 1.0 and config.bounds_max_m == m.estimator_config().bounds_max_m  # the rest as before
    with pytest.raises(MissionError, match=r"\(override\) estimator.range_memory_cells: .*0.*found -1"):
        load_mission(PAPER / "ranging_los.yaml", {"estimator.range_memory_cells": -1})


def test_override_errors_say_so() -> None:
    with pytest.raises(MissionError) as info:
        load_mission(PAPER / "joint.yaml", {"constraints.activtion": "paper"})
    text = str(info.value)
    assert "(override) constraints.activtion" in text and "did you mean 'activation'" in text
    with pytest.raises(MissionError, match=r"\(override\) criterion: expected 'A' or 'D', found 'E'"):
        load_mission(PAPER / "joint.yaml", {"criterion": "E"})


def test_parse_overrides() -> None:
    assert parse_overrides(["criterion=D", "trials=5", "constraints.z_max_m=30.5", "zenoh.connect=[a, b]"]) == {
        "criterion": "D",
        "trials": 5,
        "constraints.z_max_m": 30.5,
        "zenoh.connect": ["a", "b"],
    }
    for bad in ("criterion", "=3", "a..b=1", "x=[1,"):
        with pytest.raises(MissionError):
            parse_overrides([bad])


def test_mission_error_is_a_usage_error_with_line_and_path(tmp_path: Path) -> None:
    f = tmp_path / "m.yaml"
    f.write_text("id: x\ndrones:\n  count: 3\n  roles: [ranging, joint, radar]\n  start: {ellipse: {}}\nsource: {position_m: [0, 0, 2]}\n")
    with pytest.raises(UsageError) as info:
        load_mission(f)
    assert isinstance(info.value, MissionError) and info.value.exit_code == 2
    assert str(info.value) == (
        f"{f}: line 4: drones.roles[2]: expected 'ranging', 'bearing' or 'joint', found 'radar' (text)"
    )


def test_several_problems_in_one_message() -> None:
    text = "id: x\nsteps: -1\ntrials: 0\ndrones: {count: 2, roles: joint, start: {ellipse: {}}}\nsource: {position_m: [0, 0, 2]}\n"
    with pytest.raises(MissionError) as info:
        loads_mission(text, file="two.yaml")
    assert str(info.value).startswith("two.yaml: 2 problems in the mission:\n  - line 2: steps:")
    assert len(info.value.problems) == 2


def test_starts_near_obstacle_are_errors_not_warnings() -> None:
    base = (
        "id: x\ndrones: {count: 1, roles: joint, start: {positions_m: [[0, 100, 5]]}}\n"
        "source: {position_m: [0, 0, 2]}\nobstacles: [{name: b, min_m: [3, 90, 0], max_m: [10, 110, 30]}]\n"
    )
    with pytest.raises(MissionError, match="at least d_obstacle_m = 5 m"):
        loads_mission(base)
    ok = loads_mission(base + "constraints: {d_obstacle_m: 2.5}\n")
    assert isinstance(ok, Mission)
