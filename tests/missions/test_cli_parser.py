"""The command line's parser: a command named on the command line is parsed with its own
module's parser alone (:func:`missions.cli.main.build_parser`), the same parse as with every
command registered, and without importing the other commands' modules."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from missions.cli.main import COMMAND_MODULES, COMMANDS, build_parser

ROOT = Path(__file__).resolve().parents[2]


def registered_names(module: str) -> list[str]:
    """The command names ``module``'s ``register`` adds (in a parser of its own)."""
    sub = argparse.ArgumentParser().add_subparsers()
    importlib.import_module(module).register(sub)
    return list(sub.choices)


def test_the_command_map_is_what_the_modules_register() -> None:
    assert {name: module for module in COMMAND_MODULES for name in registered_names(module)} == COMMANDS


@pytest.mark.parametrize(
    "argv",
    [
        ["check", "paper/joint"],
        ["montecarlo", "paper/joint", "--trials", "3", "--jobs", "2", "--set", "steps=5", "--no-figures"],
        ["missions", "show", "paper/joint"],
        ["schema"],
        ["launch", "paper/joint", "--steps", "4", "--realtime"],
        ["vehicle", "--mission", "m.yaml", "--sysid", "3", "--count", "2"],
    ],
    ids=lambda a: a[0],
)
def test_one_command_parses_as_with_every_command(argv: list[str]) -> None:
    alone, every = build_parser(argv).parse_args(argv), build_parser().parse_args(argv)
    assert vars(alone) == vars(every)


def test_a_command_imports_no_other_commands_module() -> None:
    code = (
        "import contextlib, io, json, sys\n"
        "from missions.cli.main import main\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    status = main(['missions', 'list'])\n"
        "print(json.dumps([status, sorted(m for m in sys.modules if m.startswith('missions.cli.'))]))\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)}, capture_output=True, text=True, timeout=120, check=True
    )
    status, loaded = json.loads(out.stdout.strip().splitlines()[-1])
    assert status == 0
    assert set(loaded) & set(COMMAND_MODULES) == {"missions.cli.missions"}, loaded


@pytest.mark.parametrize("argv", [["--help"], ["lauch", "paper/joint"]], ids=["help", "unknown-name"])
def test_help_and_an_unknown_name_see_every_command(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    from missions.cli.main import main

    with pytest.raises(SystemExit):
        main(argv)
    shown = capsys.readouterr()
    text = shown.out + shown.err
    for name in COMMANDS:
        assert name in text, (name, text)
