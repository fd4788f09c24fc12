"""A partition of the swarm and its merge (issue 7), with real processes on 127.0.0.1.

Two groups of drones, each a real-time ``fimnav vehicle`` + ``fimnav plan`` per drone
(sped up), on two Zenoh routers (``fimnav router``): the planners of group A are clients of
router A, those of group B clients of router B, and a third "link" router connects to both.
Killing the link process cuts the swarm in two; starting it again joins the halves.

* Linked: every planner uses fresh records of every peer (the routers forward between
  their clients through the link router).
* Cut: both halves keep flying: every planner keeps stepping on the wall clock, the other
  half's planners leave the liveliness view, their saved records age by one step per step
  (the planners go on with them, widening the margins by the age; once the other half's
  planners have left the liveliness view each drone keeps to its side of the bisector planes
  of the last shared positions) and no record of the other half arrives; the safety
  constraints hold on the flown positions (inter-drone distance ≥ d_U* within and between
  the halves, altitude box, source distance, speed).
* Restored: the halves merge: records of the other half flow again within a few seconds and
  every planner's view is fresh again.

The figures (time to notice, ages during the cut, time to merge) are printed (pytest -s)
and reported in docs/distributed.md ("Partitions").
"""

from __future__ import annotations

import json
import math
import os
import signal
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from missions.format.loader import load_mission

from tests.distributed.partition_helpers import (
    HalfWatch,
    ages,
    min_pair_distance,
    min_pair_distance_between,
    read_steps,
    write_partition_mission,
)
from tests.support.proc import Proc, fimnav, stop_all
from tests.support.wait import wait_for
from tests.support.zenoh import start_router

pytestmark = pytest.mark.integration


@pytest.fixture
def procs() -> Iterator[list[Proc]]:
    """Every process a test starts; each process group is stopped at the end, and none may
    be left running."""
    started: list[Proc] = []
    yield started
    stop_all(started)
    assert all(p.p.poll() is not None for p in started), [p.label for p in started if p.p.poll() is None]


@dataclass(frozen=True)
class Scenario:
    """One partition run: the groups (1-based drone ids), the speed-up and the step counts
    each phase must last (steps of every planner)."""

    groups: tuple[tuple[int, ...], tuple[int, ...]]
    speedup: float
    steps: int
    linked_steps: int
    cut_steps: int
    merged_steps: int
    freeze: bool = False  # cut by SIGSTOP (a silent link: noticed by the lease) instead of SIGKILL


def starts_for(groups: tuple[tuple[int, ...], tuple[int, ...]]) -> list[list[float]]:
    """Start positions (m, ENU): the two groups interleaved on a 4 m grid, so the drones of
    one half are the nearest neighbours of the other's (the case where a stale view matters)."""
    n = sum(len(g) for g in groups)
    starts: list[list[float]] = [[0.0, 0.0, 0.0]] * n
    for row, group in enumerate(groups):
        for col, uav in enumerate(group):
            starts[uav - 1] = [10.0 + 4.0 * col + 2.0 * row, 20.0 + 4.0 * row, 8.0 + row]
    return starts


SOURCE_M = (60.0, 90.0, 2.0)
D_UAV_M = 2.0


def run_partition(tmp_path: Path, procs: list[Proc], sc: Scenario) -> dict[str, float]:
    """Fly the scenario; assert every claim of the module doc; return the measured figures."""
    a, b = sc.groups
    everyone = tuple(sorted(a + b))
    other = {u: (b if u in a else a) for u in everyone}
    same = {u: tuple(v for v in (a if u in a else b) if v != u) for u in everyone}
    peers = {u: [j for j in everyone if j != u] for u in everyone}
    far = {"A": b, "B": a}  # the other half, seen from each side's router
    path = write_partition_mission(tmp_path / "m.yaml", "partition", starts_for(sc.groups), sc.steps, SOURCE_M, D_UAV_M)
    mission = load_mission(path)
    starts = mission.drones.start_positions_m()

    ra, ea, _ = start_router(procs)
    rb, eb, _ = start_router(procs)
    link, _, _ = start_router(procs, ea, eb)
    watch = {"A": HalfWatch("partition", len(everyone), ea, a, starts, np.array(SOURCE_M)),
             "B": HalfWatch("partition", len(everyone), eb, b, starts, np.array(SOURCE_M))}
    try:
        vehicles = [Proc(fimnav("vehicle", "--mission", str(path), "--sysid", str(u), "--mavlink", "udpin:127.0.0.1:0", "--profile", "pointmass",
                                "--speedup", str(sc.speedup), "--tlog", str(tmp_path / f"v{u}.tlog"))) for u in everyone]
        procs.extend(vehicles)
        ports = {}
        for u, v in zip(everyone, vehicles):
            ready = v.ready(30.0)
            ports[u] = int(ready["vehicles"][0]["mavlink"].rsplit(":", 1)[1])
        # Step 0 of every planner at the same instant, once all are at their start positions.
        preflight_s = max(PREFLIGHT_S, PREFLIGHT_PER_DRONE_S * len(everyone))
        start_at = time.time() + preflight_s
        logs = {u: tmp_path / f"p{u}.jsonl" for u in everyone}
        planners = {}
        for u in everyone:
            zenoh = {"mode": "client", "listen": [], "connect": [ea if u in a else eb]}
            planners[u] = Proc(fimnav("plan", "--mission", str(path), "--uav", str(u), "--mavlink", f"udpout:127.0.0.1:{ports[u]}",
                                      "--speedup", str(sc.speedup), "--start-at", f"{start_at:.3f}", "--zenoh-config", json.dumps(zenoh),
                                      "--log", str(logs[u]), "--preflight-timeout", "60"))
            procs.append(planners[u])
        running = list(planners.values()) + vehicles + [ra, rb]
        t_ready = wait_for(lambda: all("ready at the start position" in p.err for p in planners.values()), preflight_s + 60.0,
                           "every planner at its start position", procs=running, interval_s=0.02)
        preflight_margin_s = start_at - (time.time() - (time.monotonic() - t_ready))

        def count(since_unix: float, oldest: Callable[[int], Sequence[int]], low: int, high: int) -> dict[int, int]:
            """Per planner: steps logged since ``since_unix`` whose ages of the peers
            ``oldest(u)`` all lie in [low, high]."""
            return {u: sum(1 for e in read_steps(logs[u]) if e["t_s"] >= since_unix and low <= min(ages(e, oldest(u)))
                           and max(ages(e, oldest(u))) <= high) for u in everyone}

        def status() -> str:
            return "\n".join(f"uav {u}: {[(e['step'], ages(e, peers[u])) for e in read_steps(logs[u])[-4:]]}" for u in everyone)

        # -- phase 1: linked -----------------------------------------------------------------
        wait_for(lambda: min(count(0.0, peers.__getitem__, 0, 1).values()) >= sc.linked_steps, 60.0 + preflight_s,
                 f"{sc.linked_steps} linked steps with every peer fresh", procs=running, detail=status, interval_s=0.02)
        for name in watch:
            assert watch[name].alive() == set(everyone), (name, watch[name].liveliness)

        # -- phase 2: cut ----------------------------------------------------------------------
        t_cut, t_cut_unix = time.monotonic(), time.time()
        # Frozen: the link's connections stay open but silent (a cable cut). Killed: the
        # kernel closes them (a crashed router machine's TCP peers see a reset).
        os.killpg(link.p.pid, signal.SIGSTOP if sc.freeze else signal.SIGKILL)
        gone = {name: wait_for(lambda n=name: watch[n].first_event(t_cut, "DELETE", far[n]) is not None, 15.0,
                               f"liveliness of the other half gone on side {name}", procs=running, interval_s=0.02)
                for name in watch}
        notice = {name: watch[name].first_event(t_cut, "DELETE", far[name]) - t_cut for name in watch}  # type: ignore[operator]
        wait_for(lambda: min(count(t_cut_unix, other.__getitem__, 2, sc.steps).values()) >= sc.cut_steps, 60.0,
                 f"{sc.cut_steps} steps of every planner with the other half stale", procs=running, detail=status,
                 interval_s=0.02)
        t_restore, t_restore_unix = time.monotonic(), time.time()
        leaked = {name: watch[name].records_between(max(gone.values()) + 0.5, t_restore, far[name]) for name in watch}
        alive_in_cut = {name: watch[name].alive() for name in watch}
        if sc.freeze:  # the frozen router is not resumed: a new link replaces it
            os.killpg(link.p.pid, signal.SIGKILL)
            link.wait(10.0)

        # -- phase 3: restored -----------------------------------------------------------------
        _, _, t_link_ready = start_router(procs, ea, eb)
        for name in watch:
            wait_for(lambda n=name: watch[n].first_record(t_restore, far[n]) is not None, 30.0,
                     f"records of the other half on side {name} after the restore", procs=running, interval_s=0.02)
        first_rec = {name: watch[name].first_record(t_restore, far[name]) - t_restore for name in watch}  # type: ignore[operator]
        wait_for(lambda: min(count(t_restore_unix, other.__getitem__, 0, 0).values()) >= sc.merged_steps, 60.0,
                 f"{sc.merged_steps} merged steps of every planner with the other half fresh", procs=running,
                 detail=status, interval_s=0.02)
        alive_back = {name: watch[name].first_event(t_restore, "PUT", far[name]) for name in watch}
        alive_merged = {name: watch[name].alive() for name in watch}
        for u, p in planners.items():
            assert p.wait(120.0) == 0, p.tail()
    finally:
        for w in watch.values():
            w.close()

    # -- what the planners flew and saw ------------------------------------------------------------
    log = {u: {e["step"]: e for e in read_steps(logs[u])} for u in everyone}
    entries = {u: sorted(log[u].values(), key=lambda e: e["step"]) for u in everyone}
    summaries = {u: json.loads(planners[u].out.strip().splitlines()[-1]) for u in everyone}
    dt_wall = mission.dt_s / sc.speedup
    # Steps from two steps after the cut (records in flight) to the restore.
    cut = {u: [e for e in entries[u] if t_cut_unix + 2 * dt_wall <= e["t_s"] <= t_restore_unix] for u in everyone}
    figures: dict[str, float] = {}
    for u in everyone:
        figures[f"max_age_uav{u}"] = max((max(ages(e, other[u])) for e in cut[u]), default=-1)
        # Merge: the first step with every record of the other half fresh.
        merged_at = [e["t_s"] for e in entries[u] if e["t_s"] >= t_restore_unix and max(ages(e, other[u])) == 0]
        figures[f"merge_s_uav{u}"] = min(merged_at) - t_restore_unix if merged_at else float("inf")

    # -- safety, from the flown positions (each planner's own position at each step) --------------
    c = mission.constraints
    common = sorted(set.intersection(*(set(log[u]) for u in everyone)))
    flown_at = {k: np.array([log[u][k]["position_m"] for u in everyone]) for k in common}
    min_d = min(min_pair_distance(p) for p in flown_at.values())
    # ... and between steps, each drone on the straight segment between its logged positions.
    min_d_between = min((min_pair_distance_between(flown_at[k], flown_at[k + 1]) for k in common if k + 1 in flown_at), default=min_d)
    # Within a half the drones always see each other: d_U* must hold there whatever happens.
    halves = [[everyone.index(u) for u in g] for g in sc.groups]
    min_d_same = min(
        min(min_pair_distance(p[h]), min_pair_distance_between(p[h], flown_at[k + 1][h]) if k + 1 in flown_at else math.inf)
        for k, p in flown_at.items() for h in halves
    )
    all_pos = np.array([e["position_m"] for u in everyone for e in log[u].values()])
    d_src = float(np.linalg.norm(all_pos - np.array(SOURCE_M), axis=1).min())
    planned = max(float(np.linalg.norm(np.subtract(e["next_position_m"], e["position_m"]))) for u in everyone for e in log[u].values())
    flown = max(float(np.linalg.norm(np.subtract(log[u][k + 1]["position_m"], log[u][k]["position_m"])))
                for u in everyone for k in log[u] if k + 1 in log[u])
    figures.update(min_distance_m=min_d, min_distance_between_steps_m=min_d_between, min_source_distance_m=d_src, max_planned_step_m=planned, max_flown_step_m=flown,
                   z_min_m=float(all_pos[:, 2].min()), z_max_m=float(all_pos[:, 2].max()))
    figures.update({f"notice_s_{n}": v for n, v in notice.items()})
    figures.update({f"first_record_s_{n}": v for n, v in first_rec.items()})
    figures.update({f"liveliness_back_s_{n}": (v - t_restore if v is not None else float("nan")) for n, v in alive_back.items()})
    figures["link_router_ready_s"] = t_link_ready - t_restore
    figures["preflight_margin_s"] = preflight_margin_s
    figures["cut_s"] = t_restore - t_cut
    linked = [e for u in everyone for e in entries[u] if e["t_s"] < t_cut_unix]
    figures["linked_steps_all_fresh"] = sum(max(ages(e, peers[u])) == 0 for u in everyone for e in entries[u] if e["t_s"] < t_cut_unix) / max(len(linked), 1)
    figures["late_steps_max"] = max(summaries[u]["late_steps"] for u in everyone)
    print("partition figures:", json.dumps({k: round(v, 3) for k, v in figures.items()}))

    for u in everyone:
        # The other half: gone from the view (no new record: the saved step stays, the age grows
        # by one per step); the own half stays fresh.
        assert len(cut[u]) >= sc.cut_steps - 2, (u, len(cut[u]))
        for j in other[u]:
            saved = {e["saved_steps"][j - 1] for e in cut[u]}
            assert len(saved) == 1, (u, j, sorted(saved))
        if same[u]:
            stale_own = sum(1 for e in cut[u] if max(ages(e, same[u])) > 1)
            assert stale_own <= len(cut[u]) // 4, (u, stale_own, [ages(e, same[u]) for e in cut[u]])
        assert all(f"planner {j} left the swarm" in planners[u].err for j in other[u]), planners[u].err[-3000:]
        # Every planner kept stepping through the cut (a step every dt of wall time).
        steps_in_cut = [e["step"] for e in entries[u] if t_cut_unix <= e["t_s"] <= t_restore_unix]
        assert steps_in_cut and max(np.diff(steps_in_cut), default=1) <= 3, (u, steps_in_cut)
        assert summaries[u]["steps"] + summaries[u]["late_steps"] + summaries[u]["stale_steps"] >= 0.8 * sc.steps, summaries[u]
        assert summaries[u]["end"]["confirmed"], summaries[u]
    assert len(common) >= 0.8 * sc.steps, len(common)
    assert leaked == {"A": 0, "B": 0}, leaked
    assert alive_in_cut == {"A": set(a), "B": set(b)}, alive_in_cut
    assert alive_merged == {"A": set(everyone), "B": set(everyone)}, alive_merged
    assert d_src >= c.d_source_m, figures
    assert c.z_min_m - POSITION_TOL_M <= figures["z_min_m"] and figures["z_max_m"] <= c.z_max_m + POSITION_TOL_M, figures
    assert planned <= c.speed_max_mps * mission.dt_s + 1e-6, figures
    assert flown <= c.speed_max_mps * mission.dt_s * 1.5 + POSITION_TOL_M, figures
    assert all(figures[f"merge_s_uav{u}"] < MERGE_WITHIN_S for u in everyone), figures
    assert all(v < MERGE_WITHIN_S for v in first_rec.values()), figures
    assert min_d_same >= c.d_uav_m - POSITION_TOL_M, (min_d_same, figures)
    # Between the halves too: each side keeps to its side of the bisector planes of the last
    # positions both halves share (planner.control.lost_contact_planes).
    assert min(min_d, min_d_between) >= c.d_uav_m - POSITION_TOL_M, figures
    return figures


#: Wall seconds from starting the planners to the shared step 0 (pre-flight: heartbeat,
#: streams, readiness, arm, take-off, flight to the start; all planners at once on 2 cores).
PREFLIGHT_S = 10.0
#: ... and at least this much per drone (measured under load: 4.2-6.3 s for 4 planners, 5.3-7.7 s for 6).
PREFLIGHT_PER_DRONE_S = 2.5
#: Tolerance on flown positions (m): tracking of the sped-up point-mass vehicle between samples.
POSITION_TOL_M = 0.2
#: The halves merge (every planner's view fresh) within this many wall seconds of the restart
#: of the link process (which itself takes about a second to start).
MERGE_WITHIN_S = 6.0


@pytest.mark.slow  # 25 s of real time; the router-level cut and merge stays in the default run
def test_a_partitioned_swarm_keeps_flying_safely_and_merges_again(tmp_path: Path, procs: list[Proc]) -> None:
    """2 + 2 drones at ×4: linked, cut (the link router killed), restored (restarted)."""
    run_partition(tmp_path, procs, Scenario(groups=((1, 2), (3, 4)), speedup=4.0, steps=45, linked_steps=6, cut_steps=10, merged_steps=6))


@pytest.mark.slow
def test_a_silent_cut_between_two_groups_of_three(tmp_path: Path, procs: list[Proc]) -> None:
    """3 + 3 drones at ×4, the link router frozen (SIGSTOP: no connection closes, the cut is
    noticed by the Zenoh lease), then replaced by a new one."""
    run_partition(tmp_path, procs, Scenario(groups=((1, 2, 3), (4, 5, 6)), speedup=4.0, steps=110, linked_steps=10, cut_steps=30,
                                            merged_steps=10, freeze=True))


@pytest.mark.slow  # three routers in real time (5 s)
def test_router_links_forward_between_clients_and_it_stops_cleanly(procs: list[Proc]) -> None:
    """``fimnav router``: the ready line gives the OS-chosen endpoint; a client of router A
    receives what a client of router B publishes once a third router links A and B (and not
    before); SIGINT, SIGTERM and SIGHUP stop a router (its session closed) with exit 130, 143,
    129, one line naming the signal and no traceback; a bad endpoint is a one-line error (exit 2)."""
    from comms.session import SessionSettings, open_session

    _, ea, _ = start_router(procs)
    _, eb, _ = start_router(procs)
    assert ea != eb and ea.startswith("tcp/127.0.0.1:") and not ea.endswith(":0")
    got: list[float] = []
    sa = open_session(SessionSettings(mode="client", listen=(), connect=(ea,)))
    sb = open_session(SessionSettings(mode="client", listen=(), connect=(eb,)))
    try:
        sub = sa.declare_subscriber("partition-test/**", lambda _s: got.append(time.monotonic()))
        pub = sb.declare_publisher("partition-test/x")
        t_end = time.monotonic() + 1.0
        while time.monotonic() < t_end:  # a second of traffic that must not cross (not linked)
            pub.put(b"x")
            time.sleep(0.05)
        assert got == []
        link, _, t_link = start_router(procs, ea, eb)

        def crossed() -> bool:
            pub.put(b"x")
            return bool(got)

        wait_for(crossed, 10.0, "a message from a client of B at a client of A through the link router", procs=[link], interval_s=0.02)
        print(f"routers linked: first message across {got[0] - t_link:.3f} s after the link router's ready line")
        sub.undeclare()
    finally:
        sa.close()
        sb.close()
    # Started together (each is a Python start-up on a shared machine), then checked.
    bad = {args: Proc(fimnav("router", *args)) for args in (("--listen", "tcp/127.0.0.1"), ("--listen", "7447"), ("--connect", "tcp 127.0.0.1:7447"),
                                                       ("--auth-user", "swarm"), ("--duration", "nan"))}
    procs.extend(bad.values())
    stopped = {signum: start_router(procs)[0] for signum in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    for signum, r in stopped.items():
        os.kill(r.p.pid, signum)
    for signum, r in stopped.items():
        assert r.wait(15.0) == 128 + signum and "Traceback" not in r.err, r.tail()
        assert f"fimnav router: stopped by {signal.Signals(signum).name}" in r.err, r.tail()
    for args, p in bad.items():
        assert p.wait(30.0) == 2 and "fimnav router: error:" in p.err and "Traceback" not in p.err, (args, p.tail())
    assert "cannot open the router" in bad[("--listen", "tcp/127.0.0.1")].err


def test_min_pair_distance_between_steps_against_dense_sampling() -> None:
    """The closed-form closest approach of two straight moves (used for the safety check)
    against a dense sampling of the moves, and a crossing whose end points are far apart."""
    crossing = min_pair_distance_between(np.array([[0.0, 0.0, 0.0], [10.0, 1.0, 0.0]]), np.array([[10.0, 0.0, 0.0], [0.0, 1.0, 0.0]]))
    assert crossing == pytest.approx(1.0)
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 1.0, 20001)[:, None, None]
    for _ in range(50):
        start = rng.normal(size=(4, 3)) * 3.0
        end = start + rng.normal(size=(4, 3))
        path = start + t * (end - start)  # (T, 4, 3)
        i, j = np.triu_indices(4, 1)
        gaps = np.linalg.norm(path[:, i, :] - path[:, j, :], axis=-1)
        assert min_pair_distance_between(start, end) == pytest.approx(float(gaps.min()), abs=1e-5)


def test_router_with_a_password_refuses_a_client_without_it(tmp_path: Path, procs: list[Proc]) -> None:
    """``fimnav router --auth-user --auth-password-file``: a client with the swarm's
    credential gets through it, a client without is refused."""
    from comms.session import SessionSettings, open_session

    password = tmp_path / "password"
    password.write_text("not-a-real-secret\n")
    password.chmod(0o600)
    r = Proc(fimnav("router", "--listen", "tcp/127.0.0.1:0", "--auth-user", "swarm", "--auth-password-file", str(password)))
    procs.append(r)
    endpoint = r.ready(30.0)["listen"][0]
    member = SessionSettings(mode="client", listen=(), connect=(endpoint,), auth_user="swarm", auth_password_file=password)
    got: list[bytes] = []
    a, b = open_session(member), open_session(member)
    try:
        b.declare_subscriber("auth-test/**", lambda s: got.append(bytes(s.payload.to_bytes())))

        def crossed() -> bool:
            a.put("auth-test/x", b"member")
            return bool(got)

        wait_for(crossed, 10.0, "a message between two clients with the password", procs=[r], interval_s=0.02)
    finally:
        a.close()
        b.close()
    with pytest.raises(Exception, match="Unable to connect"):
        open_session(SessionSettings(mode="client", listen=(), connect=(endpoint,))).close()
    assert "not-a-real-secret" not in r.out + r.err
