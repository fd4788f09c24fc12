"""The broken-mission corpus, each file through the real CLI in a subprocess (issue 7).

Every case must exit with status 2 and print exactly one error message that names the file,
the key path, what was expected and what was found (as declared in the file's
``# expect-*`` header), and never a traceback. Nothing else is printed on stdout.
"""

from __future__ import annotations

import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import pytest

from tests.support.shared import once_per_run

HERE = Path(__file__).resolve().parent
BROKEN = HERE / "broken"
CASES = sorted(BROKEN.glob("*.yaml"))
REPO = HERE.parents[1]


def _expectations(path: Path) -> dict[str, str]:
    out: dict[str, str] = {}
    for raw in path.read_bytes().splitlines()[:6]:
        line = raw.decode("ascii", errors="replace")
        for key in ("path", "expected", "found"):
            prefix = f"# expect-{key}:"
            if line.startswith(prefix):
                out[key] = line[len(prefix):].strip()
    return out


def run_check(target: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run(
        [sys.executable, "-m", "missions", "check", target],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=str(REPO),
        env=env,
    )


def run_check_in_process(target: str) -> subprocess.CompletedProcess[str]:
    """The same ``fimnav check`` entry point (``missions.cli.main.main``), in this process."""
    import contextlib
    import io

    from missions.cli.main import main

    out, err = io.StringIO(), io.StringIO()
    cwd = os.getcwd()
    os.chdir(REPO)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            code = main(["check", target])
    finally:
        os.chdir(cwd)
    return subprocess.CompletedProcess(["fimnav", "check", target], code, out.getvalue(), err.getvalue())


#: Every sixth corpus file also goes through a real ``python -m missions check`` subprocess
#: (the process boundary: exit status, no traceback); all go through the CLI entry point.
SUBPROCESS_SAMPLE = frozenset(str(c.relative_to(REPO)) for c in CASES[::6])


def _corpus_runs() -> dict[str, list[Any]]:
    """``fimnav check`` on every corpus file: in process, and for a sample as a subprocess too
    (the two must agree); per file [argv, exit status, stdout, stderr]."""
    rels = [str(c.relative_to(REPO)) for c in CASES]
    runs = {rel: run_check_in_process(rel) for rel in rels}
    with ThreadPoolExecutor(max_workers=2) as pool:
        sample = sorted(SUBPROCESS_SAMPLE)
        for rel, proc in zip(sample, pool.map(run_check, sample)):
            assert (proc.returncode, proc.stderr) == (runs[rel].returncode, runs[rel].stderr), rel
            runs[rel] = proc
    return {rel: [list(p.args), p.returncode, p.stdout, p.stderr] for rel, p in runs.items()}


@pytest.fixture(scope="module")
def corpus_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, subprocess.CompletedProcess[str]]:
    """:func:`_corpus_runs`, once per test run (shared by the workers: :mod:`tests.support.shared`)."""
    runs = once_per_run(tmp_path_factory, "broken-missions-corpus", _corpus_runs)
    return {rel: subprocess.CompletedProcess(args, code, out, err) for rel, (args, code, out, err) in runs.items()}


def assert_one_clear_error(proc: subprocess.CompletedProcess[str], file_label: str) -> str:
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert "Traceback" not in proc.stderr
    assert proc.stdout == ""
    error_lines = [ln for ln in proc.stderr.splitlines() if "error:" in ln]
    assert len(error_lines) == 1, proc.stderr
    message = proc.stderr.strip()
    assert message.startswith("fimnav check: error: "), message
    assert "\n" not in message, f"expected a one-line message, found:\n{message}"
    assert file_label in message
    return message


def test_corpus_is_large_enough() -> None:
    assert len(CASES) >= 40


@pytest.mark.parametrize("case", CASES, ids=[c.stem for c in CASES])
def test_broken_mission_is_refused_with_one_clear_message(
    case: Path, corpus_runs: dict[str, subprocess.CompletedProcess[str]]
) -> None:
    expect = _expectations(case)
    assert set(expect) == {"path", "expected", "found"}, f"{case.name}: incomplete # expect-* header"
    rel = str(case.relative_to(REPO))
    message = assert_one_clear_error(corpus_runs[rel], rel)
    body = message.split(rel, 1)[1]
    if expect["path"]:
        assert f" {expect['path']}" in body, (expect["path"], message)
    assert "expected" in body and "found" in body, message
    before_found = body.rsplit("found", 1)[0]
    assert expect["expected"] in before_found, (expect["expected"], message)
    after_expected = body.split("expected", 1)[1]
    assert expect["found"] in after_expected, (expect["found"], message)


def test_typo_suggests_the_nearest_key(corpus_runs: dict[str, subprocess.CompletedProcess[str]]) -> None:
    rel = str((BROKEN / "typo_nested_key.yaml").relative_to(REPO))
    message = assert_one_clear_error(corpus_runs[rel], rel)
    assert "did you mean 'activation'?" in message


def test_nonexistent_file() -> None:
    target = str(BROKEN / "does_not_exist.yaml")
    message = assert_one_clear_error(run_check(target), target)
    assert "not found" in message and "expected an existing YAML file" in message


def test_directory_instead_of_file() -> None:
    target = str(BROKEN)
    message = assert_one_clear_error(run_check(target), target)
    assert "expected a mission YAML file" in message and "found a directory" in message


def test_valid_paper_mission_passes_the_same_cli() -> None:
    proc = run_check("missions/paper/heterogeneous.yaml")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert "missions/paper/heterogeneous.yaml: OK" in proc.stdout
    assert "ranging {1, 4, 7, 10}; bearing {2, 5, 8}; joint {3, 6, 9}" in proc.stdout
