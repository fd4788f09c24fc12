"""``fimnav montecarlo --baselines``: a run with faults compared with the fault-free run of an
earlier results directory gives the same PEB penalty as when it simulates that run again."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from missions.cli.main import main
from missions.study.results import PENALTY_REFERENCE
from missions.study.simulator import PenaltyReference, RunSpec, fault_penalty, simulate
from tests.simulator.conftest import paper_mission

SIZE = ["--trials", "2", "--steps", "12", "--no-figures"]
LOSS = ["--set", "comms.faults.loss=0.2"]


def _faults(out: Path) -> dict[str, dict]:
    """Per run, its summary's PEB penalty without the baseline's own run time (wall clock)."""
    runs = json.loads((out / "summary.json").read_text())["runs"]
    return {r["run"]: {k: v for k, v in r["faults"].items() if k != "baseline_runtime_s"} for r in runs}


def test_a_saved_reference_gives_the_same_penalty(tmp_path: Path) -> None:
    """The reference saved and read back is exact, and the penalty from it equals the one from
    the fault-free result itself, whose final mean PEB it quotes unchanged."""
    faulty = paper_mission("heterogeneous", **{"comms.faults.loss": 0.2, "comms.faults.extra_delay_steps": 2})
    res = simulate(RunSpec(faulty, "A", 3, 15))
    base = simulate(RunSpec(paper_mission("heterogeneous"), "A", 3, 15))
    PenaltyReference.of(base).save(tmp_path / "ref.npz")
    ref = PenaltyReference.load(tmp_path / "ref.npz")
    np.testing.assert_array_equal(ref.peb_mean_m, base.peb_stats()["mean"])
    assert fault_penalty(faulty, res, ref) == fault_penalty(faulty, res, base)
    assert fault_penalty(faulty, res, ref)["baseline_final_peb_mean_m"] == float(base.peb_stats()["mean"][-1])
    assert ref.matches(res.spec, oracle_estimate=False)
    assert not ref.matches(res.spec, oracle_estimate=True)
    assert not ref.matches(RunSpec(faulty, "A", 3, 14), oracle_estimate=False)
    assert not ref.matches(RunSpec(faulty, "D", 3, 15), oracle_estimate=False)
    other = paper_mission("heterogeneous", **{"comms.faults.loss": 0.2, "comms.d_hop_m": 90.0})
    assert not ref.matches(RunSpec(other, "A", 3, 15), oracle_estimate=False)
    (tmp_path / "bad.npz").write_text("not numpy")
    with pytest.raises(ValueError, match=r"bad\.npz: not a fault-free run's PEB reference"):
        PenaltyReference.load(tmp_path / "bad.npz")


def test_baselines_from_an_earlier_run(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """With ``--baselines`` the command reads every baseline it finds and simulates the rest,
    saying why on stderr; the summaries equal those of the command that simulates them all."""
    clean = tmp_path / "clean"
    assert main(["montecarlo", "paper/joint", "--criterion", "both", *SIZE, "--out", str(clean)]) == 0
    assert (clean / "runs" / "paper_joint_A" / PENALTY_REFERENCE).is_file()
    assert main(["montecarlo", "paper/joint", "--criterion", "both", *SIZE, *LOSS, "--out", str(tmp_path / "fresh")]) == 0
    (clean / "runs" / "paper_joint_D" / PENALTY_REFERENCE).unlink()
    capsys.readouterr()
    assert main(["montecarlo", "paper/joint", "--criterion", "both", *SIZE, *LOSS, "--baselines", str(clean), "--out", str(tmp_path / "reused")]) == 0
    err = capsys.readouterr().err
    assert "paper_joint_A" not in err
    assert f"--baselines: no {clean / 'runs' / 'paper_joint_D' / PENALTY_REFERENCE}; simulating paper_joint (D) without faults" in err
    assert _faults(tmp_path / "reused") == _faults(tmp_path / "fresh")
    # Another size is another run: simulated, with the reason.
    assert main(["montecarlo", "paper/joint", "--criterion", "A", "--trials", "3", "--steps", "12", "--no-figures", *LOSS,
                 "--baselines", str(clean), "--out", str(tmp_path / "other")]) == 0  # fmt: skip
    assert "paper_joint_A/penalty_reference.npz is another run" in capsys.readouterr().err
    assert json.loads((tmp_path / "other" / "summary.json").read_text())["runs"][0]["faults"]["baseline_final_peb_mean_m"] > 0


def test_regenerate_reads_the_fault_free_runs_it_has_just_made(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """docs/regenerate.py: every command with faults reads its baselines from the first
    command of its block (run before it), and the command the docs show leaves that out."""
    import importlib.util

    spec = importlib.util.spec_from_file_location("regenerate", Path(__file__).resolve().parents[2] / "docs" / "regenerate.py")
    assert spec is not None and spec.loader is not None
    regenerate = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "regenerate", regenerate)  # its dataclasses look their module up
    spec.loader.exec_module(regenerate)
    cmds = regenerate.commands(tmp_path, None, None, 2, figures=False)
    names = list(cmds)
    for name, cmd in cmds.items():
        faults = any(a.startswith("comms.faults.") and not a.endswith(("=0", "=0.0")) for a in cmd.args)
        first = "grid-0" if name.startswith("grid-") else "faults-loss0-delay0"
        if faults:
            assert cmd.argv()[-2:] == ["--baselines", str(tmp_path / first)], name
            assert names.index(first) < names.index(name)
        else:
            assert "--baselines" not in cmd.argv(), name
        assert "--baselines" not in cmd.shown()
    assert sum(c.baselines is not None for c in cmds.values()) == 4 + len(regenerate.FAULT_SETTINGS) - 1
