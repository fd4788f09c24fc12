"""Missions shipped in the package, by name from any directory: ``fimnav check paper/joint``,
``fimnav missions list|show``, ``fimnav --version``.

The command-line tests run ``python -m missions`` in a subprocess whose working directory is
an empty temporary directory, so a relative ``missions/paper/...`` path does not exist there.
"""

from __future__ import annotations

import importlib.metadata
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from missions.cli.main import build_parser
from missions.format.loader import MissionError, bundled_missions, load_mission, loads_mission, resolve_mission

REPO = Path(__file__).resolve().parents[2]
PAPER = REPO / "missions" / "paper"
NAMES = sorted(f"paper/{p.stem}" for p in PAPER.glob("*.yaml"))


def fimnav(*argv: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``python -m missions ARGV`` (the ``fimnav`` command) run in ``cwd``."""
    env = {**os.environ, "PYTHONPATH": str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", "")}
    return subprocess.run(
        [sys.executable, "-m", "missions", *argv], capture_output=True, text=True, timeout=120, cwd=str(cwd), env=env
    )


def one_line_error(proc: subprocess.CompletedProcess[str], command: str) -> str:
    """The single stderr line of a command that failed with exit status 2."""
    assert proc.returncode == 2, (proc.returncode, proc.stdout, proc.stderr)
    assert proc.stdout == "" and "Traceback" not in proc.stderr, proc.stderr
    message = proc.stderr.strip()
    assert "\n" not in message and message.startswith(f"fimnav {command}: error: "), message
    return message


# --- the loader ------------------------------------------------------------------------------


def test_bundled_missions_are_the_paper_missions() -> None:
    found = bundled_missions()
    assert sorted(found) == NAMES and len(NAMES) == 6
    for name, path in found.items():
        assert path.is_file()
        assert path.read_bytes() == (PAPER / f"{name.split('/')[1]}.yaml").read_bytes()


@pytest.mark.parametrize(
    "given", ["paper/joint", "paper/joint.yaml", "paper/joint.yml", "missions/paper/joint.yaml", "./missions/paper/joint.yaml"]
)
def test_a_name_or_the_source_path_resolves_to_the_bundled_file_from_anywhere(
    given: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    assert resolve_mission(given) == bundled_missions()["paper/joint"]
    assert load_mission(given).id == "paper_joint"


def test_an_existing_file_wins_over_a_bundled_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    (tmp_path / "paper").mkdir()
    text = (PAPER / "joint.yaml").read_text(encoding="utf-8").replace("id: paper_joint", "id: my_joint")
    (tmp_path / "paper" / "joint.yaml").write_text(text, encoding="utf-8")
    assert load_mission("paper/joint.yaml").id == "my_joint"
    assert load_mission("paper/joint").id == "paper_joint"  # no file "paper/joint": the bundled one


def test_the_message_names_the_mission_as_given(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(MissionError) as info:
        load_mission("paper/joint", {"steps": 0})
    assert str(info.value).startswith("paper/joint: (override) steps: expected")


@pytest.mark.parametrize(
    ("given", "suggested"),
    [
        ("paper/jiont", "did you mean paper/joint?"),
        ("paper/heterogenous.yaml", "did you mean paper/heterogeneous?"),
        ("heterogeneous", "did you mean paper/heterogeneous?"),
        ("missions/paper/ranging.yaml", "did you mean paper/ranging_los or paper/ranging_nlos?"),
        ("examples/joint", "did you mean paper/joint?"),
    ],
)
def test_an_unknown_name_suggests_the_nearest(given: str, suggested: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(MissionError) as info:
        load_mission(given)
    message = str(info.value)
    assert message.startswith(f"{given}: mission not found: expected an existing YAML file or the name of a bundled mission")
    assert message.endswith(suggested) and "\n" not in message


def test_no_suggestion_for_a_path_nothing_resembles(tmp_path: Path) -> None:
    with pytest.raises(MissionError) as info:
        load_mission(tmp_path / "nowhere" / "x.yaml")
    assert str(info.value).endswith("found neither")


@pytest.mark.parametrize(
    "argv",
    [
        ["launch", "paper/heterogeneous"],
        ["plan", "--mission", "paper/heterogeneous", "--uav", "1"],
        ["montecarlo", "paper/heterogeneous"],
        ["check", "paper/heterogeneous"],
        ["vehicle", "--mission", "paper/heterogeneous", "--sysid", "1", "--mavlink", "udpout:127.0.0.1:14550"],
    ],
    ids=lambda argv: argv[0],
)
def test_every_mission_argument_takes_a_name(argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The parsed argument of each command is what its ``run`` hands to ``load_mission``."""
    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args(argv)
    given = args.missions[0] if argv[0] == "montecarlo" else args.mission
    assert load_mission(given).id == "paper_heterogeneous"


# --- the command line, from a directory without the missions --------------------------------


def test_check_by_name_and_by_the_readme_path_from_another_directory(tmp_path: Path) -> None:
    for given in ("paper/heterogeneous", "missions/paper/heterogeneous.yaml"):
        proc = fimnav("check", given, cwd=tmp_path)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.startswith(f"{given}: OK\nmission    paper_heterogeneous")


def test_check_unknown_name_is_one_line_with_a_suggestion(tmp_path: Path) -> None:
    message = one_line_error(fimnav("check", "paper/heterogenous", cwd=tmp_path), "check")
    assert message == (
        "fimnav check: error: paper/heterogenous: mission not found: expected an existing YAML file or the name of a "
        "bundled mission (fimnav missions list), found neither; did you mean paper/heterogeneous?"
    )


def test_launch_unknown_name_exits_2_before_starting_anything(tmp_path: Path) -> None:
    message = one_line_error(fimnav("launch", "paper/jiont", "--out", str(tmp_path / "out"), cwd=tmp_path), "launch")
    assert "did you mean paper/joint?" in message
    assert not (tmp_path / "out").exists() and not (tmp_path / "results").exists()


def test_missions_list_is_a_table_of_the_bundled_missions(tmp_path: Path) -> None:
    proc = fimnav("missions", "list", cwd=tmp_path)
    assert proc.returncode == 0 and proc.stderr == "", proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0].split() == ["name", "drones", "roles", "steps", "criterion", "description"]
    rows = {line.split()[0]: line for line in lines[1:1 + len(NAMES)]}
    assert sorted(rows) == NAMES
    het = rows["paper/heterogeneous"].split()
    assert het[1:9] == ["10", "ranging", "4,", "bearing", "3,", "joint", "3", "550"] and het[9] == "A"
    assert "Heterogeneous swarm with buildings" in rows["paper/heterogeneous"]
    assert rows["paper/bearing"].split()[1:5] == ["10", "bearing", "10", "550"]
    assert max(len(line) for line in lines) <= 140
    assert "fimnav missions show NAME" in proc.stdout
    assert fimnav("missions", cwd=tmp_path).stdout == proc.stdout  # no action: list


def test_missions_show_prints_the_yaml_to_copy_and_edit(tmp_path: Path) -> None:
    proc = fimnav("missions", "show", "paper/joint", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == (PAPER / "joint.yaml").read_text(encoding="utf-8")
    copy = tmp_path / "my.yaml"
    copy.write_text(proc.stdout.replace("steps: 550", "steps: 20"), encoding="utf-8")
    assert load_mission(copy) == load_mission(PAPER / "joint.yaml", {"steps": 20})
    assert loads_mission(proc.stdout) == load_mission(PAPER / "joint.yaml")


def test_missions_show_unknown_name(tmp_path: Path) -> None:
    message = one_line_error(fimnav("missions", "show", "paper/nope", cwd=tmp_path), "missions")
    assert message.startswith("fimnav missions: error: paper/nope: mission not found")


def test_montecarlo_by_name_from_another_directory(tmp_path: Path) -> None:
    out = tmp_path / "mc"
    proc = fimnav(
        "montecarlo", "paper/joint", "paper/heterogeneous", "--trials", "1", "--steps", "2", "--no-figures",
        "--out", str(out), cwd=tmp_path,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    text = json.dumps(summary)
    assert "paper_joint" in text and "paper_heterogeneous" in text


# --- --version ---------------------------------------------------------------------------------


def _installed_version() -> str:
    try:
        return importlib.metadata.version("fimnav")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("the fimnav distribution is not installed (python3 -m pip install -e .)")


def test_version_of_python_m_missions(tmp_path: Path) -> None:
    version = _installed_version()
    proc = fimnav("--version", cwd=tmp_path)
    assert (proc.returncode, proc.stdout, proc.stderr) == (0, f"fimnav {version}\n", "")
    assert version == "0.1.0"


def test_version_of_the_console_script(tmp_path: Path) -> None:
    version = _installed_version()
    script = shutil.which("fimnav", path=str(Path(sys.executable).parent))
    if script is None:
        pytest.skip("no fimnav console script beside this interpreter")
    proc = subprocess.run([script, "--version"], capture_output=True, text=True, timeout=60, cwd=str(tmp_path))
    assert (proc.returncode, proc.stdout, proc.stderr) == (0, f"fimnav {version}\n", "")


# --- a regular (non-editable) install -----------------------------------------------------------


@pytest.mark.slow
def test_non_editable_install_finds_the_bundled_missions(tmp_path: Path) -> None:
    """``pip install .`` (a copy of the tracked source into a target directory), then
    ``fimnav check paper/heterogeneous`` from a directory that has no missions. pip fetches the
    build backend (setuptools) in its isolated build environment."""
    tracked = subprocess.run(["git", "ls-files", "-z"], cwd=REPO, capture_output=True, check=True).stdout.split(b"\0")
    source = tmp_path / "src"
    for rel in (t.decode() for t in tracked if t):
        if (REPO / rel).is_file():
            (source / rel).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(REPO / rel, source / rel)
    target = tmp_path / "site"
    built = subprocess.run(
        [sys.executable, "-m", "pip", "install", "--quiet", "--no-deps", "--target", str(target), str(source)],
        capture_output=True, text=True, timeout=600,
    )
    if built.returncode != 0:
        pytest.skip(f"pip could not build fimnav here (no build backend available?): {built.stderr.strip()[-300:]}")
    assert (target / "missions" / "paper" / "heterogeneous.yaml").is_file()
    work = tmp_path / "elsewhere"
    work.mkdir()
    env = {**os.environ, "PYTHONPATH": str(target)}
    for given in ("paper/heterogeneous", "missions/paper/heterogeneous.yaml"):
        proc = subprocess.run([sys.executable, "-m", "missions", "check", given], capture_output=True, text=True,
                              timeout=120, cwd=str(work), env=env)
        assert proc.returncode == 0, proc.stderr
        assert proc.stdout.startswith(f"{given}: OK")
    where = subprocess.run([sys.executable, "-c", "import missions.format.loader as m; print(m.bundled_missions()['paper/joint'])"],
                           capture_output=True, text=True, timeout=60, cwd=str(work), env=env)
    assert where.stdout.strip().startswith(str(target))
