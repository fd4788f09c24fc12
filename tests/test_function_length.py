"""At most :data:`MAX_LONG` functions of the packages are longer than :data:`LONG_LINES` lines
(an AST count, docstrings included): a long function is split where it reads better."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("planner", "comms", "vehicle_sim", "missions")
LONG_LINES = 80
MAX_LONG = 3


def long_functions(root: Path = ROOT) -> dict[str, int]:
    """``path:function`` → lines, for every function (or method) longer than LONG_LINES."""
    found = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and node.end_lineno is not None:
                    lines = node.end_lineno - node.lineno + 1
                    if lines > LONG_LINES:
                        found[f"{path.relative_to(root).as_posix()}:{node.name}"] = lines
    return found


def test_at_most_three_long_functions() -> None:
    found = long_functions()
    assert len(found) <= MAX_LONG, found


def test_the_count_sees_a_long_function(tmp_path: Path) -> None:
    (tmp_path / "missions").mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(LONG_LINES))
    (tmp_path / "missions" / "m.py").write_text(f"def long():\n{body}\n\n\ndef short():\n    return 1\n")
    for package in PACKAGES[:-1]:
        (tmp_path / package).mkdir()
    assert long_functions(tmp_path) == {"missions/m.py:long": LONG_LINES + 1}
