"""The live view of a swarm: a rerun recording, served to a browser from this machine.

``fimnav launch --view`` and ``fimnav montecarlo --view`` log every step of the run to a rerun
recording (rerun-sdk, the optional extra ``fimnav[view]``):

* ``world/``, mission ENU (x east, y north, z up, m): the buildings (boxes), the true source,
  each drone's position (coloured by its state: alive, stale, taken over, lost), its trail,
  its source estimate and that estimate's 1-σ uncertainty ellipsoid, the covariance J⁻¹ of
  the Fisher information of the drone's own view evaluated at its estimate (paper eqs. 10-12;
  its trace is the PEB² of eq. 18 there);
* ``peb/mean``: the mean PEB over the drones (eq. 18, at the true source, m);
* ``events``: state changes (a drone goes stale, is taken over, is lost, comes back).

The recording is written to the results directory (``view.rrd``; ``fimnav view RESULTS``
replays it) and streamed to a rerun server, a child process bound to 127.0.0.1, that hosts
rerun's web viewer: a user opens ``http://127.0.0.1:<port>`` in a browser, nothing is fetched
from the internet. See docs/in-the-field.md.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.parse
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from comms.errors import FimnavError
from missions.format.schema import Mission

FloatArray = NDArray[np.float64]

#: Drone states the view shows, with their colours (RGB).
STATE_COLOURS: dict[str, tuple[int, int, int]] = {
    "alive": (0, 200, 83),  # green
    "stale": (255, 145, 0),  # orange: the planner republishes its last record
    "taken over": (213, 0, 249),  # magenta: a pilot flies it
    "lost": (120, 120, 120),  # grey: no record this step
}
SOURCE_COLOUR = (255, 23, 68)
ESTIMATE_COLOUR = (41, 121, 255)
BUILDING_COLOUR = (150, 150, 160)
#: Steps of trail drawn behind each drone (bounded: each step re-logs the trails).
TRAIL_STEPS: int = 150
#: Ellipsoid half-axes above this (m) are not drawn (a nearly singular view).
MAX_ELLIPSOID_M: float = 1000.0
#: Seconds the rerun server may take to listen.
SERVER_START_TIMEOUT_S: float = 30.0


class ViewError(FimnavError):
    """The live view cannot start (rerun missing, its server did not come up)."""


def require_rerun() -> Any:
    """The ``rerun`` module, or a :class:`ViewError` saying how to install it."""
    try:
        import rerun
    except ImportError:
        raise ViewError(
            "the live view needs rerun-sdk: pip install 'fimnav[view]' (about 400 MB installed; the rest of fimnav runs without it)"
        ) from None
    return rerun


@dataclass(frozen=True)
class SwarmFrame:
    """What the view shows at one step. Positions in mission ENU, m.

    Attributes:
        step: step index k. time_s: mission time kΔt (s).
        positions_m: (N, 3) each drone's position at step k (NaN rows: unknown).
        states: N states, keys of :data:`STATE_COLOURS`.
        estimates_m: (N, 3) each drone's source estimate (NaN rows: none yet).
        covariances_m2: (N, 3, 3) the inverse Fisher information of each drone's view at its
            estimate (eqs. 10-12), m² (NaN: singular or unknown).
        source_m: (3,) the true source at step k.
        peb_m: the mean PEB over the drones at the true source (eq. 18), m (inf: every view singular).
    """

    step: int
    time_s: float
    positions_m: FloatArray
    states: tuple[str, ...]
    estimates_m: FloatArray
    covariances_m2: FloatArray
    source_m: FloatArray
    peb_m: float


def covariances(information: FloatArray) -> FloatArray:
    """J⁻¹ of a stack of Fisher information matrices (..., 3, 3), 1/m² → m²; NaN where J is
    singular (condition number above 1e12) or not finite."""
    J = np.asarray(information, dtype=float)
    out = np.full(J.shape, np.nan)
    finite = np.isfinite(J).all(axis=(-2, -1))
    if finite.any():
        Jf = J[finite]
        cond = np.linalg.cond(Jf)
        ok = np.isfinite(cond) & (cond < 1e12)
        inv = np.full(Jf.shape, np.nan)
        if ok.any():
            inv[ok] = np.linalg.inv(Jf[ok])
        out[finite] = inv
    return out


def ellipsoid_axes(cov: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """The 1-σ ellipsoid of a 3×3 covariance (m²): half-axes (3,) in m and the rotation as a
    quaternion (x, y, z, w) from the ellipsoid's frame to ENU; None where it cannot be drawn."""
    from scipy.spatial.transform import Rotation

    if not np.isfinite(cov).all():
        return None
    vals, vecs = np.linalg.eigh(0.5 * (cov + cov.T))
    if vals.min() <= 0.0 or np.sqrt(vals.max()) > MAX_ELLIPSOID_M:
        return None
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]
    return np.sqrt(vals), Rotation.from_matrix(vecs).as_quat()


def rerun_binary() -> list[str]:
    """The command of rerun's viewer/server binary shipped by rerun-sdk (``rerun_cli``), run
    directly (not through its Python wrapper) so that signals reach it."""
    require_rerun()
    override = os.environ.get("RERUN_CLI_PATH")
    if override:
        return [override]
    import rerun_cli

    exe = Path(rerun_cli.__file__).parent / ("rerun.exe" if sys.platform.startswith("win") else "rerun")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "rerun_cli"]


class ViewServer:
    """rerun's web viewer and gRPC proxy (``rerun --serve-web``) as a child process, both bound
    to 127.0.0.1 (free ports unless given). A recording logs to :attr:`grpc_url`; a browser
    opens :attr:`browser_url`. ``rrds``: recordings the server loads and serves (a replay).

    The child is in its own session and gets SIGTERM from the kernel if this process dies
    (Linux); :meth:`close` stops it. Its output goes to ``log_path`` (default: discarded)."""

    def __init__(self, web_port: int | None = None, grpc_port: int | None = None, rrds: Sequence[Path] = (), log_path: Path | None = None) -> None:
        from missions.launch.supervisor import free_port

        self.web_port = web_port or free_port()
        self.grpc_port = grpc_port or free_port()
        self.rrds = tuple(rrds)
        self.log_path = log_path
        self.proc: subprocess.Popen[bytes] | None = None

    @property
    def grpc_url(self) -> str:
        """Where a recording streams to: ``rerun+http://127.0.0.1:<port>/proxy``."""
        return f"rerun+http://127.0.0.1:{self.grpc_port}/proxy"

    @property
    def browser_url(self) -> str:
        """The page to open: the web viewer, connected to the server's stream."""
        return f"http://127.0.0.1:{self.web_port}/?url={urllib.parse.quote(self.grpc_url, safe='')}"

    def start(self) -> ViewServer:
        """Start the server and wait (up to :data:`SERVER_START_TIMEOUT_S`) until both ports listen."""
        from missions.launch.forkspawn import set_parent_death_signal

        args = [
            *rerun_binary(),
            "--serve-web",
            "--bind",
            "127.0.0.1",
            "--port",
            str(self.grpc_port),
            "--web-viewer-port",
            str(self.web_port),
            "--server-memory-limit",
            "25%",
        ]
        args.extend(str(r) for r in self.rrds)
        env = dict(os.environ, RERUN_ANALYTICS="0", TELEMETRY_ENABLED="false")  # nothing leaves this machine
        out: Any = open(self.log_path, "ab") if self.log_path is not None else subprocess.DEVNULL  # noqa: SIM115 (closed below)
        try:
            self.proc = subprocess.Popen(
                args,
                stdin=subprocess.DEVNULL,
                stdout=out,
                stderr=subprocess.STDOUT,
                env=env,
                start_new_session=True,
                preexec_fn=set_parent_death_signal,
            )
        except OSError as exc:
            raise ViewError(f"cannot start rerun's viewer ({args[0]}): {exc}") from None
        finally:
            if out is not subprocess.DEVNULL:
                out.close()
        deadline = time.monotonic() + SERVER_START_TIMEOUT_S
        pending = {self.web_port, self.grpc_port}
        while pending:
            if self.proc.poll() is not None:
                raise ViewError(
                    f"rerun's viewer exited with status {self.proc.returncode} while starting" + (f" (see {self.log_path})" if self.log_path else "")
                )
            if time.monotonic() > deadline:
                self.close()
                raise ViewError(f"rerun's viewer did not listen on 127.0.0.1:{min(pending)} within {SERVER_START_TIMEOUT_S:g} s")
            for port in list(pending):  # noqa: PERF101 - the loop discards from pending: it iterates a copy
                with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), timeout=0.2):
                    pending.discard(port)
            if pending:
                time.sleep(0.05)  # polling the ports, with the deadline above
        return self

    def wait(self) -> int:
        """Wait until the server exits; its exit status (RuntimeError if it was not started)."""
        if self.proc is None:
            raise RuntimeError("rerun's viewer was not started (ViewServer.start)")
        return self.proc.wait()

    def close(self) -> None:
        """Stop the server (SIGTERM, then SIGKILL after 3 s)."""
        p = self.proc
        if p is None or p.poll() is not None:
            return
        with contextlib.suppress(ProcessLookupError):
            os.killpg(p.pid, signal.SIGTERM)
        try:
            p.wait(3.0)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()

    def __enter__(self) -> ViewServer:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()


class SwarmView:
    """A rerun recording of one run: the scene of ``mission`` (buildings, altitude box) once,
    then :meth:`log` each step. Written to ``rrd_path``; also streamed to ``grpc_url`` (a
    :class:`ViewServer`) when given.

    Args:
        mission: the mission flown (its buildings, source and drone roles).
        rrd_path: the recording file written (replay with ``fimnav view``).
        grpc_url: a rerun server's stream to log to live (None: the file only).
        name: the recording's name (the run's label).
    """

    def __init__(self, mission: Mission, rrd_path: Path, grpc_url: str | None = None, name: str | None = None) -> None:
        rr = require_rerun()
        self._rr = rr
        self.n = mission.drones.count
        self.rec = rr.RecordingStream("fimnav", recording_id=f"{name or mission.id}-{time.time_ns()}", send_properties=False)
        rrd_path.parent.mkdir(parents=True, exist_ok=True)
        sinks = [rr.FileSink(str(rrd_path))]
        if grpc_url is not None:
            sinks.append(rr.GrpcSink(grpc_url))
        self.rec.set_sinks(*sinks, default_blueprint=self._blueprint())
        self.rec.send_recording_name(name or mission.id)
        self._trails: list[list[FloatArray]] = [[] for _ in range(self.n)]
        self._states: list[str | None] = [None] * self.n
        self._scene(mission)

    def _blueprint(self) -> Any:
        rrb = self._rr.blueprint
        return rrb.Blueprint(
            rrb.Horizontal(
                rrb.Spatial3DView(origin="/world", name="swarm (mission ENU, m)"),
                rrb.Vertical(rrb.TimeSeriesView(origin="/peb", name="mean PEB (m)"), rrb.TextLogView(origin="/events", name="events")),
                column_shares=[3, 2],
            ),
            rrb.TimePanel(state="collapsed"),
            collapse_panels=True,
        )

    def _scene(self, mission: Mission) -> None:
        rr = self._rr
        rec = self.rec
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        bmin, bmax = mission.obstacle_bounds()
        if len(bmin):
            lo, hi = np.asarray(bmin, dtype=float), np.asarray(bmax, dtype=float)
            rec.log(
                "world/buildings",
                rr.Boxes3D(centers=0.5 * (lo + hi), half_sizes=0.5 * (hi - lo), colors=[BUILDING_COLOUR], fill_mode="solid"),
                static=True,
            )
        starts = mission.drones.start_positions_m()
        rec.log("world/starts", rr.Points3D(starts, radii=0.6, colors=[(200, 200, 200)]), static=True)

    def log(self, frame: SwarmFrame) -> None:
        """Log one step (timelines ``step`` and ``mission_time``)."""
        rr = self._rr
        rec = self.rec
        rec.set_time("step", sequence=frame.step)
        rec.set_time("mission_time", duration=frame.time_s)
        rec.log("world/source", rr.Points3D([frame.source_m], radii=1.5, colors=[SOURCE_COLOUR], labels=["source"]))
        known = np.all(np.isfinite(frame.positions_m), axis=1)
        ids = [i for i in range(self.n) if known[i]]
        for i in ids:
            trail = self._trails[i]
            trail.append(np.asarray(frame.positions_m[i], dtype=float))
            del trail[:-TRAIL_STEPS]
        labels = [f"UAV {i + 1}" + ("" if frame.states[i] == "alive" else f" ({frame.states[i]})") for i in ids]
        rec.log("world/drones", rr.Points3D(frame.positions_m[ids], radii=2.0, colors=[STATE_COLOURS[frame.states[i]] for i in ids], labels=labels))
        strips = [np.asarray(t) for t in self._trails if len(t) >= 2]
        if strips:
            rec.log("world/trails", rr.LineStrips3D(strips, radii=0.3, colors=[(0, 150, 70)]))
        has_est = np.all(np.isfinite(frame.estimates_m), axis=1)
        est_ids = [i for i in range(self.n) if has_est[i]]
        rec.log(
            "world/estimates",
            rr.Points3D(
                frame.estimates_m[est_ids], radii=0.8, colors=[ESTIMATE_COLOUR], labels=[f"estimate {i + 1}" for i in est_ids], show_labels=False
            ),
        )
        centres, halves, quats = [], [], []
        for i in est_ids:
            axes = ellipsoid_axes(frame.covariances_m2[i])
            if axes is not None:
                centres.append(frame.estimates_m[i])
                halves.append(axes[0])
                quats.append(axes[1])
        rec.log(
            "world/uncertainty",
            rr.Ellipsoids3D(
                centers=centres,
                half_sizes=halves,
                quaternions=[rr.Quaternion(xyzw=q) for q in quats],
                colors=[ESTIMATE_COLOUR],
                fill_mode="majorwireframe",
            ),
        )
        if np.isfinite(frame.peb_m):
            rec.log("peb/mean", rr.Scalars(frame.peb_m))
        for i, state in enumerate(frame.states):
            if state != self._states[i] and (self._states[i] is not None or state != "alive"):
                level = "INFO" if state == "alive" else "WARN"
                rec.log("events", rr.TextLog(f"step {frame.step}: UAV {i + 1} {state}", level=level))
            self._states[i] = state

    def close(self) -> None:
        """Flush and close the recording (the file is complete after this)."""
        self.rec.flush()
        self.rec.disconnect()


def swarm_frame(
    mission: Mission,
    step: int,
    positions_m: FloatArray,
    states: Sequence[str],
    estimates_m: FloatArray,
    view_positions_m: FloatArray,
    view_valid: NDArray[np.bool_],
    view_los: NDArray[np.bool_],
) -> SwarmFrame:
    """A step's frame from what each drone knew: its view of the swarm (the records it held).

    Args:
        positions_m: (N, 3) where the drones are at step k (NaN rows: unknown), mission ENU, m.
        states: N keys of :data:`STATE_COLOURS`.
        estimates_m: (N, 3) each drone's source estimate (NaN rows: none).
        view_positions_m: (N, N, 3) drone i's record of drone j's position.
        view_valid: (N, N) drone i holds a record of drone j. view_los: (N, N) that record was LOS.

    The covariance of drone i is the inverse of its view's Fisher information at its estimate
    (eqs. 10-12); the PEB is eq. 18 at the true source, averaged over the drones."""
    from planner.fim import fisher_information, position_error_bound

    config = mission.planner_config(mission.criterion)
    channel = config.channel
    rng = config.ranging[None, :] & view_valid
    brg = config.bearing[None, :] & view_valid
    extra = {name: mask[None, :] & view_valid for name, mask in config.extra_masks.items()}
    vp = np.where(view_valid[..., None], view_positions_m, 0.0)
    est = np.where(np.isfinite(estimates_m), estimates_m, 0.0)
    cov = covariances(fisher_information(est, vp, rng, brg, view_los, channel, extra))
    cov[~np.isfinite(estimates_m).all(axis=1)] = np.nan
    t = step * mission.dt_s
    src = np.asarray(mission.source.position_at(t), dtype=float)
    peb = position_error_bound(fisher_information(src, vp, rng, brg, view_los, channel, extra))[0]
    finite = peb[np.isfinite(peb) & view_valid.any(axis=1)]
    return SwarmFrame(
        step,
        t,
        np.asarray(positions_m, dtype=float),
        tuple(states),
        np.asarray(estimates_m, dtype=float),
        cov,
        src,
        float(finite.mean()) if finite.size else float("inf"),
    )
