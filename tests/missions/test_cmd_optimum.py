"""``fimnav optimum``: the command as a user runs it (a subprocess), with one start."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "missions", "optimum", *args], cwd=ROOT, capture_output=True, text=True, timeout=120)


def test_optimum_prints_the_peb_the_placement_and_its_parameters() -> None:
    out = _run("paper/joint", "--starts", "1", "--seed", "2")
    assert out.returncode == 0, out.stderr
    text = out.stdout
    peb = float(re.search(r"optimal PEB\s+([0-9.]+) m", text).group(1))
    # The best joint placement at d_S* + 1.5 m + b (52.14 m) in the 2..25 m box, all LOS.
    assert peb == pytest.approx(5.46, abs=0.01)
    for word in ("paper_joint", "criterion A", "source >= 52.14 m", "drones >= 3.29 m", "buildings >= 6.14 m",
                 "z 2.00..25.00 m", "sigma_sh/gamma 1.7 LOS / 3.2 NLOS", "seed 2", "10/10 links LOS"):
        assert word in text, word
    rows = [ln.split() for ln in text.splitlines() if re.match(r"\s+\d+ (ranging|bearing|joint) ", ln)]
    assert len(rows) == 10
    for row in rows:
        assert float(row[2]) >= 52.14 - 1e-2 and 2.0 <= float(row[4]) <= 25.0 and row[5] == "yes"


def test_optimum_bad_starts_exits_2() -> None:
    out = _run("paper/joint", "--starts", "0")
    assert out.returncode == 2
    assert "--starts" in out.stderr


def test_montecarlo_optimum_adds_the_ratio_to_each_summary(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    import json

    import missions.study.optimum
    from missions.cli.main import main

    monkeypatch.setattr(missions.study.optimum, "DEFAULT_STARTS", 1)
    out = tmp_path / "mc"
    assert main(["montecarlo", "paper/joint", "--trials", "1", "--steps", "3", "--no-figures", "--optimum", "--oracle-estimate", "--out", str(out)]) == 0
    assert "PEB_K/PEB*" in capsys.readouterr().out
    s = json.loads((out / "runs" / "paper_joint_A" / "summary.json").read_text())
    opt = s["optimum"]
    assert opt["oracle_estimate"] is True and opt["margins"] == "filter" and opt["starts"] == 1
    assert opt["source_distance_min_m"] == pytest.approx(50.0 + 0.6428, abs=1e-3)  # no inflation about the true source
    assert s["final_peb_over_optimum"] == pytest.approx(s["final_peb_mean_m"] / opt["peb_m"])
    assert json.loads((out / "summary.json").read_text())["runs"][0]["optimum"]["peb_m"] == opt["peb_m"]
