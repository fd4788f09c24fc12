"""The packages read top-down (docs/architecture.md, "Packages and what they may import"): every
import statement of a package (including imports inside functions) names only packages of its
own layer or below, so no arrow runs back up.

    missions.cli        the fimnav command line: one module per subcommand
    missions.launch     a swarm flown as processes: launcher, supervisor, clock, live view
    missions.study      the in-process simulator, results directories, figures, exports
    missions.format     the mission file: schema and loader
    missions.runtime    what every command's process shares: stop signals, results directory
    vehicle_sim         the simulated vehicle        planner.node   the planner process
    comms               Zenoh, MAVLink, wire format, geodesy, autopilot profiles
    planner (core)      numpy, scipy and numba only (tests/test_import_graph.py)
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]

#: Package (folder) → our packages it must never import.
FORBIDDEN: dict[str, tuple[str, ...]] = {
    "comms": ("vehicle_sim", "missions", "planner.node"),
    "vehicle_sim": ("missions", "planner.node"),
    "planner/node": ("vehicle_sim", "missions"),
    "missions/runtime": ("missions.format", "missions.study", "missions.launch", "missions.cli"),
    "missions/format": ("missions.study", "missions.launch", "missions.cli"),
    "missions/study": ("missions.launch", "missions.cli"),
    "missions/launch": ("missions.cli",),
}

#: The subpackages of ``missions``, top-down.
MISSIONS_SUBPACKAGES: tuple[str, ...] = ("cli", "launch", "study", "format", "runtime")


def imported_modules(source: str) -> set[str]:
    """Absolute module names of every import statement in ``source``."""
    names: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names.add(node.module)
            names.update(f"{node.module}.{alias.name}" for alias in node.names)
    return names


def upward_imports(folder: str) -> list[str]:
    """``path: module`` for every import in ``folder`` of a package above its layer."""
    bad = FORBIDDEN[folder]
    found = []
    for path in sorted((ROOT / folder).rglob("*.py")):
        for module in sorted(imported_modules(path.read_text())):
            if any(module == b or module.startswith(b + ".") for b in bad):
                found.append(f"{path.relative_to(ROOT)}: {module}")
    return found


@pytest.mark.parametrize("folder", sorted(FORBIDDEN))
def test_no_import_runs_back_up(folder: str) -> None:
    assert (ROOT / folder).is_dir()
    assert upward_imports(folder) == []


def test_the_scan_sees_an_upward_import_inside_a_function() -> None:
    source = "def f():\n    from missions.format.schema import Mission\n    import planner.node.core\n"
    assert {"missions.format.schema", "missions.format.schema.Mission", "planner.node.core"} <= imported_modules(source)


def test_the_scan_sees_from_planner_import_node() -> None:
    assert "planner.node" in imported_modules("from planner import node\n")


def test_every_missions_module_lives_in_a_subpackage() -> None:
    """Only the package's ``__init__`` and ``__main__`` (``python -m missions``) sit at the top
    of ``missions``; every other module is in one of :data:`MISSIONS_SUBPACKAGES`."""
    loose = sorted(p.name for p in (ROOT / "missions").glob("*.py") if p.name not in ("__init__.py", "__main__.py"))
    assert loose == []
    folders = sorted(p.name for p in (ROOT / "missions").iterdir() if p.is_dir() and (p / "__init__.py").is_file())
    assert folders == sorted(MISSIONS_SUBPACKAGES)


def test_the_missions_subpackages_forbid_every_layer_above_them() -> None:
    """The table above follows the order of :data:`MISSIONS_SUBPACKAGES`: a subpackage may import
    the ones below it only."""
    for i, name in enumerate(MISSIONS_SUBPACKAGES[1:], start=1):
        above = {f"missions.{a}" for a in MISSIONS_SUBPACKAGES[:i]}
        assert set(FORBIDDEN[f"missions/{name}"]) == above, name
