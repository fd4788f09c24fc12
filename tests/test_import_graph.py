"""The planner's math core (``planner`` and its subpackages except the node process,
``planner/node/``) imports neither the node package, zenoh, pymavlink, comms, vehicle_sim nor
missions.

Two independent checks: (1) in a fresh interpreter, importing ``planner`` and every core module
leaves none of the forbidden packages (nor ``planner.node``) in ``sys.modules``; (2) an AST scan
of every core module's import statements (including imports inside functions) finds none of
them, and finds only the standard library, numpy, scipy, numba (the compiled kernels) and
planner itself.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PLANNER = ROOT / "planner"
FORBIDDEN = ("zenoh", "pymavlink", "comms", "vehicle_sim", "missions")
#: The node process, at the edge of the core: the core never imports it.
NODE_PACKAGE = "planner.node"
ALLOWED_THIRD_PARTY = ("numpy", "scipy", "numba")  # numba: the compiled kernels (planner/estimator/kernels)


def core_modules() -> list[str]:
    """Every module of the planner package and its subpackages (planner/estimator/...) except
    the node edge (the planner/node/ package, cli*)."""
    names = []
    for path in sorted(PLANNER.rglob("*.py")):
        parts = path.relative_to(ROOT).with_suffix("").parts
        if parts[1] == "node" or parts[-1].startswith(("node", "cli")):
            continue
        names.append(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
    return names


def _module_path(module: str) -> Path:
    path = ROOT.joinpath(*module.split("."))
    return path / "__init__.py" if path.is_dir() else path.with_suffix(".py")


def test_core_module_list_is_not_empty():
    mods = core_modules()
    for expected in ("planner", "planner.geometry", "planner.fim", "planner.control", "planner.network", "planner.estimator", "planner.estimator.update"):
        assert expected in mods


def test_importing_the_core_loads_no_io_package():
    code = (
        "import importlib, json, sys\n"
        f"for m in {core_modules()!r}: importlib.import_module(m)\n"
        f"bad = sorted(k for k in sys.modules if k.split('.')[0] in {FORBIDDEN!r} or k == {NODE_PACKAGE!r} or k.startswith({NODE_PACKAGE + '.'!r}))\n"
        "print(json.dumps(bad))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    loaded = json.loads(out.stdout.strip().splitlines()[-1])
    assert loaded == [], f"the math core pulled in {loaded}"


def _imported_modules(path: Path) -> set[str]:
    """Every absolute module name a file imports (``from a.b import c`` gives ``a.b`` and
    ``a.b.c``: c may be a module), including imports inside functions and importlib calls."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    modules: set[str] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            modules.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            modules.add(node.module)
            modules.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in ("import_module", "__import__"):
            if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                modules.add(node.args[0].value)
    return modules


def _imported_roots(path: Path) -> set[str]:
    return {m.split(".")[0] for m in _imported_modules(path)}


def _imports_node_package(path: Path) -> bool:
    return any(m == NODE_PACKAGE or m.startswith(NODE_PACKAGE + ".") for m in _imported_modules(path))


@pytest.mark.parametrize("module", core_modules())
def test_core_module_imports_only_stdlib_numpy_scipy(module):
    path = _module_path(module)
    roots = _imported_roots(path)
    assert not roots & set(FORBIDDEN), f"{path.name} imports {sorted(roots & set(FORBIDDEN))}"
    assert not _imports_node_package(path), f"{path.name} imports the node process ({NODE_PACKAGE})"
    stdlib = set(sys.stdlib_module_names) | {"__future__"}
    other = roots - stdlib - set(ALLOWED_THIRD_PARTY) - {"planner"}
    assert not other, f"{path.name} imports third-party {sorted(other)} (core: numpy, scipy and numba only)"


def test_ast_scan_detects_a_forbidden_import(tmp_path):
    """The scanner itself can fail: it sees imports inside functions and importlib calls."""
    bad = tmp_path / "bad.py"
    bad.write_text("def f():\n    import zenoh\n    from comms.keys import x\n    importlib.import_module('pymavlink.mavutil')\n")
    assert _imported_roots(bad) >= {"zenoh", "comms", "pymavlink"}


def test_ast_scan_detects_an_import_of_the_node_package(tmp_path):
    for text in ("from planner.node import PlannerNode\n", "from planner import node\n", "def f():\n    import planner.node.core\n"):
        bad = tmp_path / "bad.py"
        bad.write_text(text)
        assert _imports_node_package(bad), text


def test_the_node_package_is_not_in_the_core_list():
    assert not [m for m in core_modules() if m == NODE_PACKAGE or m.startswith(NODE_PACKAGE + ".")]
