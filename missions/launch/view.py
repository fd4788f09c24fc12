"""The live view of a ``fimnav launch`` run (``--view``): rerun's web viewer on 127.0.0.1 and the
run's recording (``OUT/view.rrd``), fed each step from what the launcher heard
(:mod:`missions.launch.liveview`)."""

from __future__ import annotations

import contextlib
import json
import logging
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from missions.format.schema import Mission
from missions.launch.collect import Heard

log = logging.getLogger("fimnav.launch")


class LaunchView:
    """The live view of one run, while it flies.

    Args:
        mission: the mission as run.
        out: the results directory (the viewer's log in ``out/logs/viewer.log``).
        view_port: the web viewer's port on 127.0.0.1 (None: a free one).
        notice: called with the viewer's address.
    """

    def __init__(self, mission: Mission, out: Path, view_port: int | None, notice: Callable[[str], None]) -> None:
        self.mission = mission
        self.out = out
        self._abs_out = out.absolute()
        self.view_port = view_port
        self.notice = notice
        self._server: Any = None
        self._swarm_view: Any = None
        self._last_position: dict[int, tuple[float, float, float]] = {}

    @property
    def running(self) -> bool:
        """The recording is open (between :meth:`start` and :meth:`stop`)."""
        return self._swarm_view is not None

    def start(self) -> None:
        """Start rerun's web viewer (a child bound to 127.0.0.1) and the run's recording."""
        from missions.launch.liveview import SwarmView, ViewServer

        server = ViewServer(web_port=self.view_port, log_path=self.out / "logs" / "viewer.log")
        self._server = server.start()
        self._swarm_view = SwarmView(self.mission, self._abs_out / "view.rrd", server.grpc_url, name=self.mission.id)
        # Where tools and tests find the view while the swarm flies.
        (self._abs_out / "logs" / "view.json").write_text(json.dumps({"url": server.browser_url, "grpc": server.grpc_url}) + "\n")
        self.notice(f"live view: {server.browser_url}")

    def stop(self) -> None:
        """Close the recording (complete whatever ended the run) and stop the viewer."""
        if self._swarm_view is not None:
            with contextlib.suppress(Exception):
                self._swarm_view.close()  # the recording is complete whatever ended the run
            self._swarm_view = None
        if self._server is not None:
            self._server.close()
            self._server = None

    def step(self, k: int, heard: Heard) -> None:
        """Log step k from what the launcher heard of it (:meth:`SwarmListener.heard_at`):
        each drone's record (its position and state), its status (estimate and view)."""
        from missions.launch.liveview import swarm_frame

        n = self.mission.drones.count
        own, stat, recs = heard
        positions = np.full((n, 3), np.nan)
        states = []
        estimates = np.full((n, 3), np.nan)
        view_pos = np.zeros((n, n, 3))
        valid = np.zeros((n, n), dtype=bool)
        los = np.zeros((n, n), dtype=bool)
        for j in range(1, n + 1):
            r = own[j]
            if r is not None:
                self._last_position[j] = r.position_m
                states.append("taken over" if r.taken_over else "stale" if r.stale else "alive")
            else:
                states.append("lost")
            if j in self._last_position:
                positions[j - 1] = self._last_position[j]
            st = stat[j]
            if st is not None:
                estimates[j - 1] = st.estimate_m
                for i, s in enumerate(st.saved_steps):
                    rec = recs.get((s, i + 1)) if s >= 0 else None
                    if rec is not None:
                        view_pos[j - 1, i], valid[j - 1, i], los[j - 1, i] = rec.position_m, True, rec.los
        try:
            self._swarm_view.log(swarm_frame(self.mission, k, positions, states, estimates, view_pos, valid, los))
        except Exception as exc:  # the view must never end a flight
            log.warning("live view: step %d not logged (%s)", k, exc)
