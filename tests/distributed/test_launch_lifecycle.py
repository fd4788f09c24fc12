"""How a ``fimnav launch`` ends, with real processes on 127.0.0.1: every way leaves no process
of the swarm behind, with the conventional exit status; a results directory holds one run;
children run the launcher's own code; a real-time launch says what its start delay waits for.

- SIGINT (Ctrl-C, to the launcher's process group as a terminal sends it), SIGTERM (to the
  launcher), SIGHUP (the terminal closed: to the process group) and SIGKILL (to the launcher):
  every descendant of the launcher, recorded from /proc while the mission flies, is gone within
  a few seconds; exit 130, 143, 129 (128 + signal) and a line naming the partial logs.
- Started with SIGHUP ignored (``nohup fimnav launch``), a SIGHUP to the group changes nothing:
  the mission ends normally.
- A second launch into the same ``--out`` is refused at once (exit 2) and ``--overwrite``
  replaces the previous run, whose stale vehicle log no longer misleads the launcher.
- Started from a directory holding another ``missions`` package, the children import the
  launcher's (they report it: the vehicles in their ready line, the planners in their log).
- ``fimnav plan`` started by hand exits 143 on SIGTERM and 129 on SIGHUP; ``fimnav vehicle``
  started by hand outlives the process that started it (no launcher watchdog).
"""

from __future__ import annotations

import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import NamedTuple

import pytest

from comms.errors import UsageError
from missions.launch.supervisor import ready_line
from missions.runtime.rundir import claim_results_dir, previous_run, unique_results_dir
from tests.support.launch import PAPER, ROOT, Launch, processes_with_environment
from tests.support.net import free_port
from tests.support.proc import Proc, fimnav, with_hangup
from tests.support.wait import wait_for

pytestmark = pytest.mark.integration

#: Seconds every process of the swarm has to disappear once the launcher has exited (SIGINT,
#: SIGTERM, SIGHUP: the launcher stopped its children itself) or was killed (SIGKILL: each child
#: notices on its own; the measured time is below 1 s).
GONE_WITHIN_S = 6.0

MISSIONS_DIR = str(ROOT / "missions")


class ProcInfo(NamedTuple):
    """One process as /proc shows it."""

    ppid: int
    state: str
    start: int  # clock ticks after boot: with the pid, names the process (pids are reused)
    cmdline: str


def read_proc(pid: int) -> ProcInfo | None:
    """/proc/PID/stat and cmdline, or None if there is no such process."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        cmd = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return None
    fields = stat.rsplit(")", 1)[1].split()
    return ProcInfo(int(fields[1]), fields[0], int(fields[19]), cmd)


def descendants(root: int) -> dict[int, ProcInfo]:
    """Every live (non-zombie) descendant of ``root``, from /proc."""
    table = {int(e.name): read_proc(int(e.name)) for e in Path("/proc").iterdir() if e.name.isdigit()}
    children: dict[int, list[int]] = {}
    for pid, p in table.items():
        if p is not None:
            children.setdefault(p.ppid, []).append(pid)
    found: dict[int, ProcInfo] = {}
    stack = [root]
    while stack:
        for c in children.get(stack.pop(), []):
            p = table[c]
            if p is not None and p.state != "Z":
                found[c] = p
                stack.append(c)
    return found


def still_alive(procs: dict[int, ProcInfo]) -> dict[int, str]:
    """The processes of ``procs`` still running (same pid and start time, not a zombie)."""
    alive = {}
    for pid, p in procs.items():
        now = read_proc(pid)
        if now is not None and now.start == p.start and now.state != "Z":
            alive[pid] = now.cmdline[:160]
    return alive


def steps_logged(out: Path, uav: int = 1) -> int:
    path = out / "logs" / f"planner_{uav}.jsonl"
    return path.read_text().count("\n") if path.exists() else 0


def swarm_of(run: Launch, planners: int) -> dict[int, ProcInfo]:
    """The launcher's descendants once the mission flies: ``planners`` planners, the vehicles'
    process and the planners' fork server (and multiprocessing's resource tracker)."""
    wait_for(lambda: steps_logged(run.out) >= 2, 90.0, "the mission to fly two steps")

    seen: dict[int, ProcInfo] = {}

    def planners_up() -> bool:  # a forked planner shows its own command line a moment after the fork
        # Every snapshot is kept (by pid): a short mission may end before one snapshot shows
        # every planner with its command line (a loaded machine flew 40 steps in under 2 s and
        # never showed all four at once).
        seen.update(descendants(run.proc.pid))
        return sum(" plan " in p.cmdline for p in seen.values()) >= planners

    wait_for(planners_up, 30.0, f"{planners} planner processes")
    tree = seen
    kinds = [p.cmdline for p in tree.values()]
    assert sum(" plan " in c for c in kinds) == planners, kinds
    assert sum(" vehicle " in c for c in kinds) == 1, kinds
    assert sum("multiprocessing.forkserver" in c for c in kinds) == 1, kinds
    return tree


@pytest.mark.parametrize(
    ("signum", "to_group"),
    [(signal.SIGINT, True), (signal.SIGTERM, False), (signal.SIGHUP, True)],
    ids=["SIGINT-ctrl-c", "SIGTERM-kill", "SIGHUP-terminal-closed"],
)
def test_a_signal_stops_every_process_with_status_128_plus_signal(tmp_path: Path, launches: list[Launch], signum: int,
                                                                  to_group: bool) -> None:
    out = tmp_path / "run"
    run = Launch(PAPER / "joint.yaml", out, "--steps", "400", "--step-timeout", "20", "--set", "drones.count=4")
    launches.append(run)
    tree = swarm_of(run, 4)
    if to_group:
        os.killpg(run.proc.pid, signum)  # the launcher's group: it, the fork server, the tracker
    else:
        run.proc.send_signal(signum)
    code, stdout, stderr = run.wait(30.0)
    exited = time.monotonic()
    name = signal.Signals(signum).name
    assert code == 128 + signum, stderr[-2000:]
    assert f"fimnav launch: interrupted by {name}: every process was stopped; partial logs in {out / 'logs'}" in stderr, stderr[-2000:]
    assert "Traceback" not in stderr and "results:" not in stdout
    wait_for(lambda: not still_alive(tree), GONE_WITHIN_S, f"every process of the swarm to end after the launcher's exit: {still_alive(tree)}")
    assert time.monotonic() - exited <= GONE_WITHIN_S
    # The forked planners ran the launcher's code.
    assert f"fimnav code from {MISSIONS_DIR}" in (out / "logs" / "planner_1.log").read_text()


def test_a_finished_launch_has_stopped_its_fork_server_when_it_returns(tmp_path: Path, launches: list[Launch]) -> None:
    """A launch that ends normally has ended every process it started by the time it exits,
    its planners' fork server and multiprocessing's resource tracker included (they used to
    end on their own a moment after the launcher, reading the end of file of their pipes)."""
    out = tmp_path / "run"
    # 100 steps (about 4 s): the planners must still be flying when swarm_of counts them (with
    # 12, and once with 40, a loaded machine saw the launch end between its two-step wait and its count).
    run = Launch(PAPER / "joint.yaml", out, "--steps", "100", "--set", "drones.count=4")
    launches.append(run)
    tree = swarm_of(run, 4)
    run.proc.wait(60.0)  # the launcher's exit (its output is read by threads meanwhile)
    left = still_alive(tree)
    code, _, stderr = run.wait(60.0)
    assert code == 0, stderr[-2000:]
    assert not left, left


def test_a_launch_started_with_hangups_ignored_flies_on_through_a_hangup(tmp_path: Path, launches: list[Launch]) -> None:
    """``nohup fimnav launch``: a SIGHUP inherited ignored stays ignored (missions.runtime.signals),
    so the run outlives its terminal. SIGHUP to the launcher's group (the terminal closing) while
    the mission flies: the launch ends the mission normally (exit 0, its results line, a summary)
    and leaves no process behind."""
    out = tmp_path / "run"
    argv = with_hangup(fimnav("launch", str(PAPER / "joint.yaml"), "--out", str(out), "--steps", "60", "--set", "drones.count=4", "--no-figures"), "SIG_IGN")
    run = Launch.command(argv, out, ROOT)
    launches.append(run)
    tree = swarm_of(run, 4)
    os.killpg(run.proc.pid, signal.SIGHUP)
    code, stdout, stderr = run.wait(120.0)
    assert code == 0, stderr[-2000:]
    assert "interrupted" not in stderr and "results:" in stdout, (stdout[-1000:], stderr[-1000:])
    assert steps_logged(out) == 60
    assert (out / "summary.json").exists()
    wait_for(lambda: not still_alive(tree), GONE_WITHIN_S, f"every process of the swarm to end: {still_alive(tree)}")


@pytest.mark.parametrize("fork_server", [True, pytest.param(False, marks=pytest.mark.slow)], ids=["forked-planners", "fresh-interpreters"])
def test_a_killed_launcher_leaves_no_process(tmp_path: Path, launches: list[Launch], fork_server: bool) -> None:
    """SIGKILL to the launcher: nothing stops the children for it; each notices by itself
    (the watchdog pipe reads end of file) and stops."""
    out = tmp_path / "run"
    run = Launch(PAPER / "joint.yaml", out, "--steps", "400", "--step-timeout", "20", "--set", "drones.count=4",
                 *([] if fork_server else ["--no-fork-server"]))
    launches.append(run)
    if fork_server:
        tree = swarm_of(run, 4)
    else:
        wait_for(lambda: steps_logged(out) >= 2, 90.0, "the mission to fly two steps")
        tree = descendants(run.proc.pid)
        assert sum(" plan " in p.cmdline for p in tree.values()) == 4
    killed = time.monotonic()
    run.proc.kill()
    assert run.proc.wait(10.0) == -signal.SIGKILL
    wait_for(lambda: not still_alive(tree), GONE_WITHIN_S, f"every process of the swarm to end after the launcher was killed: {still_alive(tree)}")
    assert time.monotonic() - killed <= GONE_WITHIN_S


SUMMARY = re.compile(
    r"^paper_joint_A: mean PEB \d+(\.\d+)? m → \d+(\.\d+)? m \(step 0 → 2\), median estimate error \d+(\.\d+)? m \(step 2\), "
    r"safety violations \d+, \d+\.\d s\nresults: (?P<out>.+)$",
    re.M,
)


@pytest.mark.slow  # two launches (4 s); the results-directory rules stay in the default run (test_results_directory_rules below)
def test_a_results_directory_holding_a_run_is_refused_or_overwritten(tmp_path: Path, launches: list[Launch]) -> None:
    """A previous run's files in ``--out`` (here: a summary and a vehicle log whose ready line
    names a port nobody listens on, which made a second launch wait 120 s for a heartbeat):
    refused at once, exit 2, nothing touched; ``--overwrite`` removes them (only them) and the
    run flies."""
    out = tmp_path / "het"
    (out / "logs").mkdir(parents=True)
    stale = json.dumps({"event": "ready", "pid": 1, "vehicles": [{"sysid": i, "mavlink": "udpin:127.0.0.1:9"} for i in range(1, 5)]}) + "\n"
    (out / "logs" / "vehicles_1-4.log").write_text(stale)
    (out / "summary.json").write_text("{}\n")
    (out / "notes.txt").write_text("mine\n")

    refused = Launch(PAPER / "joint.yaml", out, "--steps", "3", "--set", "drones.count=4")
    launches.append(refused)
    code, stdout, stderr = refused.wait(60.0)
    assert code == 2, stderr[-2000:]
    assert stderr.strip().splitlines()[-1] == (f"fimnav launch: error: results directory {out} already holds a run "
                                               "(summary.json, logs/); choose another --out or pass --overwrite")
    assert sorted(p.name for p in out.iterdir()) == ["logs", "notes.txt", "summary.json"]
    assert (out / "logs" / "vehicles_1-4.log").read_text() == stale

    run = Launch(PAPER / "joint.yaml", out, "--steps", "3", "--set", "drones.count=4", "--overwrite")
    launches.append(run)
    code, stdout, stderr = run.wait(90.0)
    assert code == 0, stderr[-3000:]
    m = SUMMARY.search(stdout)
    assert m is not None and m.group("out") == str(out), stdout
    assert (out / "notes.txt").read_text() == "mine\n"
    ready = [json.loads(line) for line in (out / "logs" / "vehicles_1-4.log").read_text().splitlines() if line.startswith('{"event": "ready"')]
    assert len(ready) == 1 and ready[0]["pid"] != 1 and ready[0]["code"] == MISSIONS_DIR, ready
    assert json.loads((out / "summary.json").read_text())["runs"][0]["steps"] == 3


def test_results_directory_rules(tmp_path: Path) -> None:
    """The rules behind ``--out``/``--overwrite`` and the default directory, without processes."""
    a = unique_results_dir(tmp_path / "results", "m-20250101-120000")
    b = unique_results_dir(tmp_path / "results", "m-20250101-120000")
    assert (a.name, b.name) == ("m-20250101-120000", "m-20250101-120000-2") and a.is_dir() and b.is_dir()
    claim_results_dir(a)
    assert previous_run(a) == ["logs/", "tlogs/"]
    with pytest.raises(UsageError, match="already holds a run"):
        claim_results_dir(a)
    (a / "keep.txt").write_text("x")
    claim_results_dir(a, overwrite=True)
    assert sorted(p.name for p in a.iterdir()) == ["keep.txt", "logs", "tlogs"]
    with pytest.raises(UsageError, match="expected a directory, found a file"):
        claim_results_dir(a / "keep.txt")
    # A vehicle's ready line is its own: a line of another process (an older run) is skipped.
    log = tmp_path / "vehicles.log"
    log.write_text('{"event": "ready", "pid": 11, "vehicles": []}\nnoise\n{"event": "ready", "pid": 22, "vehicles": [{"sysid": 1}]}\n')
    assert ready_line(log, 22) == {"event": "ready", "pid": 22, "vehicles": [{"sysid": 1}]}
    assert ready_line(log, 33) is None


@pytest.mark.parametrize("fork_server", [True, pytest.param(False, marks=pytest.mark.slow)], ids=["forked-planners", "fresh-interpreters"])
def test_children_run_the_launchers_code(tmp_path: Path, launches: list[Launch], fork_server: bool) -> None:
    """The launcher started like the console script of an installed copy (its code found on its
    ``sys.path``, not in the working directory), from a directory that holds another
    ``missions`` package, as a clone does: the vehicles and the planners (forked from the fork
    server, or fresh interpreters) import the launcher's package, not the working directory's."""
    decoy = tmp_path / "clone"
    (decoy / "missions").mkdir(parents=True)
    marker = tmp_path / "decoy-imported"
    (decoy / "missions" / "__init__.py").write_text(f"import pathlib\npathlib.Path({str(marker)!r}).write_text(__file__)\n")
    (decoy / "missions" / "__main__.py").write_text("raise SystemExit(7)\n")
    bindir = tmp_path / "bin"
    bindir.mkdir()
    script = bindir / "fimnav"
    # (as pip writes a console script: multiprocessing imports it again in a forked child)
    script.write_text(f"import sys\nsys.path.insert(0, {str(ROOT)!r})\nfrom missions.cli.main import main\nif __name__ == '__main__':\n    sys.exit(main())\n")
    out = tmp_path / "run"
    run = Launch.command([sys.executable, str(script), "launch", str(PAPER / "joint.yaml"), "--steps", "2", "--set", "drones.count=2",
                          *([] if fork_server else ["--no-fork-server"]), "--out", str(out)], out, cwd=decoy)
    launches.append(run)
    code, _, stderr = run.wait(90.0)
    assert code == 0, stderr[-3000:]
    assert not marker.exists(), f"a child imported {marker.read_text()}"
    ready = json.loads((out / "logs" / "vehicles_1-2.log").read_text().splitlines()[0])
    assert ready["code"] == MISSIONS_DIR
    for i in (1, 2):
        assert f"fimnav code from {MISSIONS_DIR}" in (out / "logs" / f"planner_{i}.log").read_text()


@pytest.mark.slow  # a real-time launch that waits (4 s); the lockstep lifecycle tests stay in the default run
def test_realtime_launch_says_what_its_start_delay_waits_for(tmp_path: Path) -> None:
    """``--realtime``: one line with what the start delay waits for and when step 0 is, then the
    drones ready at their starts as they report; Ctrl-C during the delay stops everything."""
    out = tmp_path / "rt"
    run = Proc(fimnav("launch", str(PAPER / "joint.yaml"), "--out", str(out), "--realtime",
                      "--speedup", "5", "--start-delay", "60", "--steps", "5", "--set", "drones.count=2"), cwd=ROOT)
    try:
        wait_for(lambda: "drones ready at their starts" in run.err or run.p.poll() is not None, 60.0, "a drone ready at its start")
        text = run.err
        assert re.search(r"^waiting for 2 drones to be ready and at their starts: step 0 at \d\d:\d\d:\d\d \(in \d+ s\)$", text, re.M), text
        assert re.search(r"^[12]/2 drones ready at their starts \(step 0 in \d+ s\)$", text, re.M), text
        tree = descendants(run.p.pid)
        os.killpg(run.p.pid, signal.SIGINT)
        assert run.wait(30.0) == 130
        assert f"interrupted by SIGINT: every process was stopped; partial logs in {out / 'logs'}" in run.err
        wait_for(lambda: not still_alive(tree), GONE_WITHIN_S, f"every process to end: {still_alive(tree)}")
    finally:
        run.stop(signal.SIGKILL)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGHUP], ids=["SIGTERM", "SIGHUP"])
def test_a_planner_started_by_hand_exits_128_plus_signal(signum: int) -> None:
    """``fimnav plan`` by hand (no launcher; its vehicle never answers): SIGTERM ends it with
    143, SIGHUP with 129, after its clean-up and with one line saying so."""
    run = Proc(fimnav("plan", "--mission", str(PAPER / "joint.yaml"), "--uav", "1",
                      "--mavlink", f"udpout:127.0.0.1:{free_port(socket.SOCK_DGRAM)}"), cwd=ROOT)
    try:
        wait_for(lambda: "fimnav code from" in run.err or run.p.poll() is not None, 60.0, "the planner to start")
        assert "launcher" not in run.err
        run.p.send_signal(signum)
        assert run.wait(20.0) == 128 + signum, run.err[-2000:]
        # (on a loaded machine the clean-up can be cut short after its 5 s grace: the line says so)
        assert run.err.strip().splitlines()[-1].startswith(f"fimnav plan: stopped by {signal.Signals(signum).name}"), run.err[-2000:]
        assert "Traceback" not in run.err
    finally:
        run.stop(signal.SIGKILL)


def test_a_vehicle_started_by_hand_outlives_its_parent(tmp_path: Path) -> None:
    """No launcher, no watchdog: a ``fimnav vehicle`` whose parent process has exited keeps
    flying (its heartbeats keep coming)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as gcs:
        gcs.bind(("127.0.0.1", 0))
        gcs.settimeout(1.0)
        port = gcs.getsockname()[1]
        starter = (
            "import subprocess, sys\n"
            f"p = subprocess.Popen([sys.executable, '-m', 'missions', 'vehicle', '--mavlink', 'udpout:127.0.0.1:{port}'],"
            " stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)\n"
            "print(p.pid)\n"
        )
        parent = subprocess.run([sys.executable, "-c", starter], cwd=ROOT, capture_output=True, text=True, timeout=60)
        pid = int(parent.stdout)
        try:
            received = 0
            deadline = time.monotonic() + 30.0
            while received < 3:
                assert time.monotonic() < deadline, "no heartbeats from the vehicle after its parent exited"
                try:
                    gcs.recvfrom(4096)
                    received += 1
                except TimeoutError:
                    continue
            assert read_proc(pid) is not None and read_proc(pid).state != "Z"  # type: ignore[union-attr]
        finally:
            os.kill(pid, signal.SIGTERM)
            wait_for(lambda: read_proc(pid) is None or read_proc(pid).state == "Z", 10.0, "the vehicle to stop")  # type: ignore[union-attr]


def test_a_launch_stopped_during_its_first_compile_ends_at_once_and_leaves_no_process(tmp_path: Path) -> None:
    """Ctrl-C (SIGINT to the launch's process group, as a terminal sends it) while the fork
    server compiles the kernels on a cold cache (an empty ``NUMBA_CACHE_DIR``; the compile takes
    about 35 s on two cores): the launch exits 130 within seconds, without waiting for the
    compile, and every process it started, the compiling ones included, is gone."""
    cache = f"NUMBA_CACHE_DIR={tmp_path / 'numba'}"
    env = dict(os.environ, MAVLINK20="1", PYTHONUNBUFFERED="1", NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    argv = fimnav("launch", str(PAPER / "joint.yaml"), "--out", str(tmp_path / "run"), "--set", "drones.count=4")
    run = Proc(argv, cwd=ROOT, env=env)
    try:
        wait_for(lambda: "compiling the planning and estimation kernels" in run.out + run.err, 60.0, "the launch's compiling notice", procs=[run])
        os.killpg(run.p.pid, signal.SIGINT)
        stopped_at = time.monotonic()
        run.p.wait(30.0)
        took = time.monotonic() - stopped_at
        assert run.p.returncode == 130, run.tail()
        assert took < 15.0, f"the launch took {took:.1f} s to stop during its first compile"
        assert "interrupted by SIGINT" in run.err, run.tail()
        wait_for(lambda: not processes_with_environment(cache), 10.0, "every process of the launch to end", detail=lambda: processes_with_environment(cache))
    finally:
        for pid in processes_with_environment(cache):
            os.kill(pid, signal.SIGKILL)
        run.stop()
