"""A study on a real Dask cluster on loopback (``dask scheduler`` and two ``dask worker``
processes, tests/support/dask.py): its results are the local run's, bit for bit, also when a
worker is killed in the middle of the study (its chunks run again on the other), and its
progress counts every trial-step once. The reference is the same study in this process."""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from distributed import Client

from comms.errors import FimnavError, UsageError
from missions.cli.main import main
from missions.runtime.numerics import numerics_identity
from missions.study import cluster as cluster_mod
from missions.study.cluster import DaskCluster, connect, environment
from missions.study.executors import Chunk
from missions.study.montecarlo import expand_runs, run_study, study_size
from missions.study.results import summarize
from missions.study.simulator import RunSpec
from tests import UNPINNED
from tests.missions.test_study import LOSS, _assert_same, _untimed
from tests.simulator.conftest import paper_mission
from tests.support.dask import LoopbackCluster, start_cluster, worker_addresses
from tests.support.net import free_port
from tests.support.proc import Proc
from tests.support.wait import wait_for

pytestmark = pytest.mark.integration

#: every chunk one trial: six chunks for two workers
ONE_TRIAL = {"chunk_trials": 1, "max_chunks": 1 << 30}


@pytest.fixture(scope="module")
def shared() -> Iterator[LoopbackCluster]:
    """One cluster of two workers for the tests that kill none (stopped at the end)."""
    started: list[Proc] = []
    try:
        yield start_cluster(started)
    finally:
        for p in reversed(started):
            p.stop()


def test_montecarlo_on_the_cluster_is_the_local_run(shared: LoopbackCluster, tmp_path: Path) -> None:
    """``fimnav montecarlo --cluster`` and the same command on this machine: the same
    summary.json (but wall times) and the same per-step CSVs, byte for byte; a run with
    injected faults has its fault-free baseline simulated on the cluster too."""
    cluster = shared
    args = ["montecarlo", "paper/joint", "paper/heterogeneous", "--trials", "3", "--steps", "6", "--chunk-trials", "1", "--no-figures"]
    args += ["--set", "comms.faults.loss=0.2"]
    assert main([*args, "--out", str(tmp_path / "local")]) == 0
    assert main([*args, "--cluster", cluster.address, "--out", str(tmp_path / "cluster")]) == 0
    local, remote = (json.loads((tmp_path / d / "summary.json").read_text())["runs"] for d in ("local", "cluster"))
    assert [_untimed(s) for s in remote] == [_untimed(s) for s in local]
    assert all(s["faults"]["lost_fraction"] > 0 for s in local)
    for run in ("paper_joint_A", "paper_heterogeneous_A"):
        for name in ("peb.csv", "trajectories.csv"):
            assert (tmp_path / "cluster" / "runs" / run / name).read_bytes() == (tmp_path / "local" / "runs" / run / name).read_bytes()


def test_the_client_of_a_cluster_study_never_loads_numba(shared: LoopbackCluster, tmp_path: Path) -> None:
    """``fimnav montecarlo --cluster`` in a fresh process (a run with injected faults, so its
    penalty is computed there too, and its figures): the study is written, and numba (the
    compiler under the kernels, which run on the workers) was never imported by the command."""
    probe = (
        "import atexit, sys\n"
        "atexit.register(lambda: print('numba imported:', 'numba' in sys.modules, flush=True))\n"
        "from missions.cli.main import main\n"
        "sys.exit(main(sys.argv[1:]))\n"
    )
    args = ["montecarlo", "paper/joint", "--trials", "2", "--steps", "4", "--set", "comms.faults.loss=0.2"]
    out = subprocess.run(
        [sys.executable, "-c", probe, *args, "--cluster", shared.address, "--out", str(tmp_path / "study")],
        cwd=Path(__file__).resolve().parents[2],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr
    assert "numba imported: False" in out.stdout, out.stdout
    summary = json.loads((tmp_path / "study" / "summary.json").read_text())["runs"]
    assert [s["run"] for s in summary] == ["paper_joint_A"] and summary[0]["faults"]["lost_fraction"] > 0
    assert list((tmp_path / "study").rglob("*.png")), "the study's figures"


def test_a_worker_killed_mid_study_loses_nothing(procs: list[Proc]) -> None:
    """SIGKILL to a worker while it simulates a chunk: the scheduler gives the chunk to the
    other worker, the study completes, every result equals the local study's bit for bit, and
    the progress adds up to the study's trial-steps exactly once."""
    cluster = start_cluster(procs)
    specs = [RunSpec(paper_mission("joint"), "A", 6, 25)]
    local = run_study(specs, **ONE_TRIAL)
    killed: dict[str, list[str]] = {}
    seen: list[int] = []
    with Client(cluster.address, set_as_default=False) as client:

        def on_progress(n: int) -> None:
            seen.append(n)
            if killed:
                return
            busy = {w: list(keys) for w, keys in client.processing().items() if keys}
            if busy:
                victim = sorted(busy)[0]
                cluster.workers[victim].send_signal(signal.SIGKILL)
                killed[victim] = busy[victim]

        study = run_study(specs, executor=DaskCluster(client=client), progress=on_progress, **ONE_TRIAL)
        (victim,) = killed
        assert killed[victim], "the killed worker had a chunk"
        assert cluster.workers[victim].wait(10) == -signal.SIGKILL
        wait_for(lambda: victim not in worker_addresses(client), 20.0, "the scheduler to drop the killed worker")
        assert len(worker_addresses(client)) == 1
    _assert_same(study.results[0], local.results[0])
    assert _untimed(summarize(study.results[0])) == _untimed(summarize(local.results[0]))
    assert sum(seen) == study_size(specs)


def test_progress_on_the_cluster_counts_every_trial_step_once(shared: LoopbackCluster) -> None:
    """Runs with and without faults (baselines included): the progress reported across the
    cluster adds up to study_size, and the results are the local ones."""
    cluster = shared
    specs = [RunSpec(paper_mission("heterogeneous"), "D", 3, 8), expand_runs(["paper/joint"], LOSS, trials=2, steps=6)[0]]
    seen: list[int] = []
    with DaskCluster(cluster.address) as executor:
        study = run_study(specs, executor=executor, progress=seen.append, **ONE_TRIAL)
    local = run_study(specs, **ONE_TRIAL)
    assert sum(seen) == study_size(specs) and all(n > 0 for n in seen)
    for a, b in zip(study.results, local.results, strict=True):
        _assert_same(a, b)
    assert [p and _untimed(p) for p in study.penalties] == [p and _untimed(p) for p in local.penalties]


def test_a_worker_with_other_code_is_refused(shared: LoopbackCluster, monkeypatch: pytest.MonkeyPatch) -> None:
    """A study submitted from a machine whose fimnav sources differ from the workers': one
    error naming the worker and what differs, nothing simulated."""
    cluster = shared
    here = environment()
    monkeypatch.setattr(cluster_mod, "environment", lambda: {**here, "fimnav sources": "0123456789abcdef"})
    with DaskCluster(cluster.address) as executor, pytest.raises(FimnavError, match=r"worker tcp://127\.0\.0\.1:\d+ runs other code: fimnav sources"):
        list(executor.map([Chunk(RunSpec(paper_mission("joint"), "A", 1, 2))]))


def test_a_worker_with_other_numerics_is_refused(shared: LoopbackCluster, monkeypatch: pytest.MonkeyPatch) -> None:
    """A study submitted from a process with the host's numerics to workers that run pinned
    ones (or the other way round, or another CPU kind): one error naming the numerics of both and
    how to mix CPU kinds, nothing simulated."""
    cluster = shared
    here = environment()
    monkeypatch.setattr(cluster_mod, "environment", lambda: {**here, "numerics": "host: Some CPU, flags 0123abcd"})
    with DaskCluster(cluster.address) as executor, pytest.raises(FimnavError) as raised:
        list(executor.map([Chunk(RunSpec(paper_mission("joint"), "A", 1, 2))]))
    message = str(raised.value)
    expected = (
        rf"worker tcp://127\.0\.0\.1:\d+ runs other code: numerics {re.escape(here['numerics'])} \(submitted from host: Some CPU, flags 0123abcd\)"
    )
    assert re.search(expected, message), message
    assert "pin the numerics" in message and "docs/studies.md" in message and "\n" not in message


def test_no_scheduler_is_one_usage_error() -> None:
    with pytest.raises(UsageError, match=r"--cluster tcp://127\.0\.0\.1:\d+: no Dask scheduler answered"):
        connect(f"tcp://127.0.0.1:{free_port()}", timeout_s=1.0)


@pytest.mark.parametrize("form", ["tcp://127.0.0.1:{port}", "127.0.0.1:{port}", "tcp://localhost:{port}"])
def test_a_port_where_nothing_listens_is_refused_as_such(form: str) -> None:
    """A refused connection is reported as refused (by the plain connection tried first), not
    after the client's retries until the timeout."""
    address = form.format(port=free_port())
    with pytest.raises(UsageError, match=r"no Dask scheduler answered \(connection refused: nothing listens on port \d+ of "):
        connect(address, timeout_s=30.0)


def test_a_listening_port_that_is_no_scheduler_is_still_one_usage_error() -> None:
    """The plain connection opens (something listens) but it is no Dask scheduler and never
    answers: one usage error after twice the timeout (Dask's client alone would wait forever)."""
    with socket.socket() as server:
        server.bind(("127.0.0.1", 0))
        server.listen()
        port = server.getsockname()[1]
        with pytest.raises(UsageError, match=rf"--cluster tcp://127\.0\.0\.1:{port}: no Dask scheduler answered"):
            connect(f"tcp://127.0.0.1:{port}", timeout_s=1.0)


def test_cluster_and_view_or_jobs_are_refused(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    base = ["montecarlo", "paper/joint", "--trials", "1", "--steps", "1", "--out", str(tmp_path / "x")]
    assert main([*base, "--cluster", "tcp://127.0.0.1:9", "--view"]) == 2
    assert "--view watches a run on this machine only" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exc:
        main([*base, "--cluster", "tcp://127.0.0.1:9", "--jobs", "2"])
    assert exc.value.code == 2 and "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_a_cluster_process_dies_with_the_test_process() -> None:
    """What stops the cluster whatever ends a test: a process started through orphan_proof by
    a parent that is then SIGKILLed (no clean-up runs) is killed by the kernel."""
    code = (
        "import subprocess, sys; from tests.support.dask import orphan_proof; "
        "p = subprocess.Popen(orphan_proof(['sleep', '60'])); print(p.pid, flush=True); sys.stdin.read()"
    )
    parent = Proc([sys.executable, "-c", code], cwd=Path(__file__).resolve().parents[2], stdin=True)
    try:
        child = int(parent.expect(r"(\d+)\n", 20).group(1))
        wait_for(lambda: _command(child).startswith("sleep"), 20, "the child to exec sleep", procs=[parent])
        parent.p.kill()
        wait_for(lambda: not _command(child).startswith("sleep"), 10, "the child to die with its parent")
    finally:
        parent.stop()


def _command(pid: int) -> str:
    """The command line of process ``pid`` ('' once it is gone or a zombie)."""
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def test_environment_names_the_code_and_libraries() -> None:
    env = environment()
    assert set(env) == {"python", "numpy", "scipy", "numba", "pydantic", "fimnav sources", "numerics"}
    assert env["numerics"] == ("pinned" if UNPINNED is None else numerics_identity(os.environ))  # tests/__init__.py
    assert env["numpy"] == np.__version__ and len(env["fimnav sources"]) == 16
    assert environment() == env
