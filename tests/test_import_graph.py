"""The planner's math core (``planner`` and its subpackages except the node process,
``planner/node/``) imports neither the node package, zenoh, pymavlink, comms, vehicle_sim nor
missions.

Two independent checks: (1) in a fresh interpreter, importing ``planner`` and every core module
leaves none of the forbidden packages (nor ``planner.node``) in ``sys.modules``; (2) an AST scan
of every core module's import statements (including imports inside functions) finds none of
them, and finds only the standard library, numpy, scipy, numba (the compiled kernels) and planner
itself. (3) A process that never plans (a simulated vehicle) does not import numba.
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
ALLOWED_THIRD_PARTY = ("numpy", "scipy", "numba")


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


def test_a_process_that_never_plans_does_not_import_numba():
    """A simulated vehicle (its MAVLink side, payload and mission file) measures with the core's
    observation model and line of sight but never plans: importing numba would cost it ~0.3-0.5 s
    of start-up and memory. Checked in a fresh interpreter, after a measurement."""
    code = (
        "import json, sys\n"
        "import numpy as np\n"
        "import vehicle_sim.vehicle, vehicle_sim.payload, comms.messages, comms.latency\n"
        "from planner.observation import observe\n"
        "from planner.params import Channel\n"
        "from planner.geometry import line_of_sight\n"
        "boxes = np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 1.0, 1.0]])\n"
        "observe(np.zeros(3), np.ones((2, 3)) * 5, [True, False], [False, True], *boxes, Channel(), np.random.default_rng(0))\n"
        "line_of_sight(np.ones((2, 3)) * 5, np.zeros(3), *boxes)\n"
        "print(json.dumps(sorted(k for k in sys.modules if k.split('.')[0] in ('numba', 'llvmlite'))))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert json.loads(out.stdout.strip().splitlines()[-1]) == []


# --------------------------------------------------------------------------- import cycles

#: Every package of the project whose modules the cycle check reads.
PACKAGES = ("planner", "comms", "vehicle_sim", "missions")


def project_modules() -> dict[str, Path]:
    """Module name → file of every module of :data:`PACKAGES` (a package by its ``__init__``)."""
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            found[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return found


def import_edges(path: Path, module: str, modules: set[str]) -> set[str]:
    """The project modules ``module`` (at ``path``) imports: every import statement, at the top
    or inside a function (relative ones resolved), every ``importlib.import_module`` or
    ``__import__`` of a constant, and, in a module that imports by a computed name, every
    string constant that names a project module (e.g. a table of subcommand modules).
    ``from a import b`` imports ``a.b`` when that is a module, else ``a``. Starting the program
    by name (``python -m missions``, ``runpy``) is not an import."""
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    named: set[str] = set()
    dynamic = False
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            named.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                base = ".".join([*anchor, *([base] if base else [])])
            named.update(f"{base}.{alias.name}" if f"{base}.{alias.name}" in modules else base for alias in node.names)
        elif isinstance(node, ast.Call) and getattr(node.func, "attr", getattr(node.func, "id", "")) in ("import_module", "__import__"):
            if node.args and isinstance(node.args[0], ast.Constant) and isinstance(node.args[0].value, str):
                named.add(node.args[0].value)
            else:
                dynamic = True
    if dynamic:
        named.update(n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str) and n.value in modules)
    return {n for n in named if n in modules and n != module}


def import_cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan), each sorted: every
    set of modules that import each other, directly or through others."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(edges.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                cycles.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return cycles


def test_no_import_cycles_anywhere() -> None:
    modules = project_modules()
    edges = {m: import_edges(p, m, set(modules)) for m, p in modules.items()}
    assert sum(len(e) for e in edges.values()) > 200  # the scan sees the imports
    assert import_cycles(edges) == []


def test_the_cycle_check_finds_a_cycle_through_a_function_level_import(tmp_path: Path) -> None:
    """Two modules that import each other, one inside a function (as the figures and the
    results once did), and one of them by a computed name: a cycle, found."""
    (tmp_path / "pkg").mkdir()
    a = tmp_path / "pkg" / "a.py"
    b = tmp_path / "pkg" / "b.py"
    c = tmp_path / "pkg" / "c.py"
    a.write_text("from pkg.b import f\n")
    b.write_text("def g():\n    from . import a\n")
    c.write_text("import importlib\nNAMES = ('pkg.a',)\ndef h(n):\n    return importlib.import_module(n)\n")
    names = {"pkg", "pkg.a", "pkg.b", "pkg.c"}
    edges = {m: import_edges(tmp_path.joinpath(*m.split(".")).with_suffix(".py"), m, names) for m in ("pkg.a", "pkg.b", "pkg.c")}
    assert edges == {"pkg.a": {"pkg.b"}, "pkg.b": {"pkg.a"}, "pkg.c": {"pkg.a"}}
    assert import_cycles(edges) == [["pkg.a", "pkg.b"]]
    assert import_cycles({"x": {"y"}, "y": {"z"}, "z": set()}) == []
