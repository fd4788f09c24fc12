"""``fimnav schema`` prints a valid JSON Schema that every paper mission (and every mission
as run) satisfies, and that rejects unknown keys and wrong enums like the loader does."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import yaml

from missions.format.loader import load_mission, mission_to_yaml

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "missions" / "paper"


@pytest.fixture(scope="module")
def schema() -> dict[str, Any]:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    proc = subprocess.run(
        [sys.executable, "-m", "missions", "schema"], capture_output=True, text=True, timeout=60, cwd=REPO, env=env
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr == ""
    return json.loads(proc.stdout)


def _validator(schema: dict[str, Any]) -> Any:
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


def test_schema_structure(schema: dict[str, Any]) -> None:
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["type"] == "object" and schema["additionalProperties"] is False
    assert set(schema["required"]) == {"id", "drones", "source"}
    props = schema["properties"]
    for key in ("id", "seed", "dt_s", "steps", "trials", "criterion", "origin", "drones", "source", "obstacles",
                "channel", "constraints", "comms", "controller", "estimator", "fence", "zenoh", "vehicles", "end_action",
                "altitude_reference", "takeoff_alt_m", "description"):
        assert key in props, key
    for name, definition in schema["$defs"].items():
        if definition.get("type") == "object" and name != "ResolvedVehicle":
            assert definition.get("additionalProperties") is False, name


def test_schema_is_valid_json_schema(schema: dict[str, Any]) -> None:
    _validator(schema)


@pytest.mark.parametrize("path", sorted(PAPER.glob("*.yaml")), ids=lambda p: p.stem)
def test_paper_missions_validate(schema: dict[str, Any], path: Path) -> None:
    validator = _validator(schema)
    raw = yaml.safe_load(path.read_text())
    assert sorted(validator.iter_errors(raw), key=str) == []
    as_run = yaml.safe_load(mission_to_yaml(load_mission(path)))
    assert sorted(validator.iter_errors(as_run), key=str) == []


def test_schema_rejects_what_the_loader_rejects(schema: dict[str, Any]) -> None:
    validator = _validator(schema)
    good = yaml.safe_load((PAPER / "heterogeneous.yaml").read_text())
    bad_key = {**good, "constraints": {**good["constraints"], "activtion": "paper"}}
    bad_role = {**good, "drones": {**good["drones"], "roles": ["ranging", "sonar"]}}
    bad_start = {**good, "drones": {**good["drones"], "start": {}}}
    for doc in (bad_key, bad_role, bad_start):
        assert list(validator.iter_errors(doc)), doc
    assert validator.is_valid({**good, "drones": {**good["drones"], "roles": "joint"}})
