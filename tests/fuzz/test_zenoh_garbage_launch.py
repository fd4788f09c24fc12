"""Hostile Zenoh traffic into a live ``fimnav launch`` (real processes, real Zenoh on
127.0.0.1): while the swarm flies, a test peer on the same Zenoh network publishes garbage on
``fimnav/<id>/record/*``, ``measurement/*`` and ``clock/tick``: random bytes, truncated
records, unknown schema versions and kinds, NaN and infinite values, spoofed sender ids
(sender field ≠ key), records of another mission, out-of-range sender ids.

The run must complete, compute exactly what the in-process simulator computes (so the garbage
changed nothing: positions within 1 cm, as tests/distributed/test_launch.py requires of a
clean run), and the planners' logs must say they dropped messages (counted in the summary).
"""

from __future__ import annotations

import json
import math
import struct
import threading
from pathlib import Path

import numpy as np
import pytest

from comms.messages import Record, Tick, encode
from missions.format.loader import load_mission
from missions.study.simulator import RunSpec, simulate

from tests.support.launch import PAPER, Launch, read_trajectories
from tests.support.net import free_port
from tests.support.zenoh import raw_session

pytestmark = [pytest.mark.integration, pytest.mark.slow]

MISSION_ID = "hostile"


def garbage(rng: np.random.Generator, count: int) -> list[tuple[str, bytes]]:
    """(key tail, payload) pairs that a correct receiver must all drop."""
    obs = Record(2, 1, 0.5, (1.0, 2.0, 3.0), True, False, True, 10.0, math.nan, math.nan)
    rec = encode(obs, MISSION_ID, 1)
    items: list[tuple[str, bytes]] = []
    for j in range(1, count + 1):
        bad_version = bytearray(rec)
        bad_version[2] = 2
        bad_kind = bytearray(rec)
        bad_kind[3] = 9
        nan_pos = bytearray(rec)
        struct.pack_into("<d", nan_pos, 26, math.nan)
        inf_range = bytearray(rec)
        struct.pack_into("<d", inf_range, 52, math.inf)
        spoof = encode(Record(j % count + 1, 1, 0.5, (900.0, 900.0, 900.0), True, False, True, 1.0, math.nan, math.nan), MISSION_ID, 2)
        other = encode(Record(j, 1, 0.5, (900.0, 900.0, 900.0), True, False, True, 1.0, math.nan, math.nan), "another-mission", 3)
        big_sender = bytearray(rec)
        struct.pack_into("<H", big_sender, 8, count + 7)
        for kind in ("record", "measurement"):
            items += [
                (f"{kind}/{j}", rng.integers(0, 256, int(rng.integers(0, 120)), dtype=np.uint8).tobytes()),
                (f"{kind}/{j}", rec[: int(rng.integers(1, len(rec)))]),
                (f"{kind}/{j}", bytes(bad_version)),
                (f"{kind}/{j}", bytes(bad_kind)),
                (f"{kind}/{j}", bytes(nan_pos)),
                (f"{kind}/{j}", bytes(inf_range)),
                (f"{kind}/{j}", spoof),  # sender j%N+1 on drone j's key
                (f"{kind}/{j}", other),
                (f"{kind}/{j}", bytes(big_sender)),
            ]
    tick = bytearray(encode(Tick(3, 0.3), MISSION_ID, 1))
    struct.pack_into("<d", tick, 18, math.nan)
    items += [("clock/tick", bytes(tick)), ("clock/tick", b"\x00"), ("clock/tick", encode(Tick(9999, 1.0), "another-mission", 1))]
    return items


def test_garbage_on_the_swarm_keys_changes_nothing(tmp_path: Path, launches: list[Launch]) -> None:
    port = free_port()
    hub = raw_session(listen=[f"tcp/127.0.0.1:{port}"])
    stop = threading.Event()
    sent = [0]
    items = garbage(np.random.default_rng(77), 10)

    def attack() -> None:
        pubs: dict[str, object] = {}
        i = 0
        while not stop.wait(0.01):
            tail, payload = items[i % len(items)]
            key = f"fimnav/{MISSION_ID}/{tail}"
            if key not in pubs:
                pubs[key] = hub.declare_publisher(key)
            pubs[key].put(payload)  # type: ignore[attr-defined]
            sent[0] += 1
            i += 1

    attacker = threading.Thread(target=attack, daemon=True)
    out = tmp_path / "hostile"
    try:
        run = Launch(PAPER / "ranging_los.yaml", out, "--steps", "15", "--set", f"id={MISSION_ID}",
                     "--set", f'zenoh.connect=["tcp/127.0.0.1:{port}"]')
        launches.append(run)
        attacker.start()
        code, _, stderr = run.wait(400.0)
        assert code == 0, stderr[-3000:]
    finally:
        stop.set()
        attacker.join(5)
        hub.close()
    assert sent[0] > len(items), f"only {sent[0]} garbage messages published"
    mission = load_mission(out / "mission.yaml")
    pos, _ = read_trajectories(out, mission)
    sim = simulate(RunSpec(mission, mission.criterion, 1, mission.steps), float32_positions=True)
    # Every step the planners computed: as the simulator to 1e-4 m (a clean run agrees to
    # ~5e-8 m; one forged or garbled record in an estimate moves the next step by far more).
    # The last row (the position after the last setpoint) is left out: it is sampled at the
    # end of the mission and on a loaded machine the vehicle may still be on its way there
    # (measured up to 0.28 m, also in runs where no message reached the swarm at all).
    np.testing.assert_allclose(pos[:-1], sim.positions_m[:-1, 0], atol=1e-4, rtol=0)
    summary = json.loads((out / "summary.json").read_text())["runs"][0]
    assert summary["violations"] == {k: 0 for k in summary["violations"]}
    assert summary["dropped_messages"] > 0  # the launcher's own record collector dropped garbage too
    dropped_logged = 0
    for i in range(1, mission.drones.count + 1):
        text = (out / "logs" / f"planner_{i}.log").read_text()
        dropped_logged += text.count("dropped message")
        assert "Traceback" not in text
    assert dropped_logged > 0
    print({"garbage_published": sent[0], "planner_drop_warnings": dropped_logged, "launcher_dropped": summary["dropped_messages"]})
