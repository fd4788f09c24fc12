"""``fimnav check`` options in process (the subprocess runs are in test_missions_broken.py)."""

from __future__ import annotations

from pathlib import Path

import pytest

from missions.cli.main import main
from missions.format.loader import load_mission, loads_mission

PAPER = Path(__file__).resolve().parents[2] / "missions" / "paper"


def test_check_summary_fits_one_screen(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(PAPER / "ranging_nlos.yaml")]) == 0
    out = capsys.readouterr().out
    lines = out.splitlines()
    assert len(lines) <= 24 and max(len(ln) for ln in lines) <= 120
    for word in ("paper_ranging_nlos", "ranging 1-10", "ellipse in XZ", "source", "B1:", "B3:",
                 "sigma_sh/gamma 1.7 LOS / 3.2 NLOS", "d_U* 1 m, d_S* 50 m, d_O* 5 m", "d_hop 100 m, h_max 1"):
        assert word in out, word


def test_check_overrides(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(PAPER / "joint.yaml"), "--criterion", "D", "--set", "constraints.activation=paper"]) == 0
    out = capsys.readouterr().out
    assert "criterion D-optimal, activation paper" in out


def test_check_yaml_is_the_mission_as_run(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(PAPER / "dynamic_source.yaml"), "--yaml", "--set", "trials=7"]) == 0
    text = capsys.readouterr().out
    again = loads_mission(text)
    assert again == load_mission(PAPER / "dynamic_source.yaml", {"trials": 7})


def test_check_bad_override_exits_2(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["check", str(PAPER / "joint.yaml"), "--set", "steps=-3"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("fimnav check: error: ") and "(override) steps: expected a number greater than or equal to 1, found -3" in err
    assert main(["check", str(PAPER / "joint.yaml"), "--set", "nonsense"]) == 2
    assert "expected KEY=VALUE" in capsys.readouterr().err
