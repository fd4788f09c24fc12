"""The planner node's configuration: the command line's options (:class:`NodeOptions`) and the
one typed, frozen :class:`NodeConfig` the node process runs on, built once from the mission and
the options (:meth:`NodeConfig.from_mission`). Nothing downstream of it reads the mission."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from comms.autopilot import FlavourSetting, flavour_names
from comms.errors import FimnavError
from comms.faults import FaultModel
from comms.geodesy import MissionFrame
from comms.mavlink_client import AltitudeReference, Frame, read_signing_key
from comms.session import SessionSettings
from planner.config import PlannerConfig


class NodeError(FimnavError):
    """The planner cannot go on (vehicle refused, lost peers beyond the deadline, ...)."""


@dataclass(frozen=True)
class NodeOptions:
    """How one planner node runs (the ``fimnav plan`` command line).

    Attributes:
        uav: drone id, 1-based (also the vehicle's MAVLink system id unless ``sysid``).
        mavlink: pymavlink connection string to the vehicle.
        zenoh: session settings.
        lockstep: step on the lockstep clock (simulation) rather than the wall clock.
        steps: number of steps (default: the mission's).
        sysid: the vehicle's system id (default: ``uav``).
        log_path: JSON-lines log of every step.
        step_timeout_s: how long to wait for a tick, a measurement or the peers' records.
        preflight_timeout_s: how long the take-off and the flight to the start may take.
        speedup: real time only: mission seconds per wall second (1 for a real vehicle; the
            ``--speedup`` of a simulated vehicle in tests).
        flavour: ``"auto"`` (from HEARTBEAT.autopilot) or a flavour of
            :data:`comms.autopilot.FLAVOURS` (``"ardupilot"``, ``"px4"``); None:
            the mission's ``vehicles.overrides[i].flavour`` (absent: auto).
        setpoint_frame: ``"auto"``, ``"global"`` or ``"local_ned"``; None: the mission's.
        signing_key_file: MAVLink 2 signing key; None: the mission's (absent: no signing).
        stream_hz: real time: setpoint stream rate in mission-time Hz (≥ 4).
        peer_wait_fraction: real time: the peers' records of step k are awaited until
            ``t_k + peer_wait_fraction · dt``.
        measurement_max_age_s: real time: the newest payload measurement is used if it is
            at most this old (mission seconds; None: one step, dt).
        start_at_unix: real time: UNIX time of step 0 (None: the next multiple of dt/speedup
            after the planner is at its start, so planners started apart share the grid).
        end_timeout_s: real time: how long the end of mission (landing) may take (wall s).
        rejoin: lockstep: this planner replaces one that died mid-mission. It skips the
            pre-flight (the vehicle is airborne and armed), answers the clock's current step
            as skipped and flies from the next one, with a fresh estimator; its log is
            appended to, not overwritten.
        tlog_path: real time: write the MAVLink link to this .tlog (every frame in and out),
            as ``fimnav launch`` does for an external autopilot.
    """

    uav: int
    mavlink: str
    zenoh: SessionSettings = field(default_factory=SessionSettings)
    lockstep: bool = True
    steps: int | None = None
    sysid: int | None = None
    log_path: Path | None = None
    step_timeout_s: float = 30.0
    preflight_timeout_s: float = 120.0
    speedup: float = 1.0
    flavour: FlavourSetting | None = None
    setpoint_frame: Literal["auto", "global", "local_ned"] | None = None
    signing_key_file: Path | None = None
    stream_hz: float = 5.0
    peer_wait_fraction: float = 0.5
    measurement_max_age_s: float | None = None
    start_at_unix: float | None = None
    end_timeout_s: float = 120.0
    rejoin: bool = False
    tlog_path: Path | None = None

    def __post_init__(self) -> None:
        for name in ("speedup", "stream_hz", "step_timeout_s", "preflight_timeout_s", "end_timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise NodeError(f"{name}: expected a positive number, found {v!r}")
        if self.stream_hz < 4.0:
            raise NodeError(f"stream_hz: expected at least 4 Hz (the setpoint stream keeps the autopilot's timeouts away), found {self.stream_hz:g}")
        if not 0.0 < self.peer_wait_fraction < 1.0:
            raise NodeError(f"peer_wait_fraction: expected a fraction of the step in (0, 1), found {self.peer_wait_fraction!r}")
        names = flavour_names()
        if self.flavour is not None and self.flavour != "auto" and self.flavour not in names:
            raise NodeError(f"flavour: expected auto, {', '.join(names[:-1])} or {names[-1]}, found {self.flavour!r}")
        if self.setpoint_frame not in (None, "auto", "global", "local_ned"):
            raise NodeError(f"setpoint frame: expected auto, global or local_ned, found {self.setpoint_frame!r}")


@dataclass(frozen=True)
class ViewSettings:
    """What the node's delayed view (:class:`comms.latency.DelayedView`) is built with.

    Attributes:
        d_hop_m: hop distance (m). h_max: most hops. emulate: apply the hop latency.
        faults: injected loss and extra delay (None: none). seed: the mission seed.
    """

    d_hop_m: float
    h_max: int
    emulate: bool
    faults: FaultModel | None
    seed: int


@dataclass(frozen=True)
class NodeConfig:
    """Everything one planner node process runs on, resolved once from the mission and the
    options (:meth:`from_mission`).

    Attributes:
        uav: drone id, 1-based. drone_index: the same, 0-based. drone_count: N.
        sysid: the vehicle's MAVLink system id. mission_id: the Zenoh key prefix's id.
        mavlink: pymavlink connection string. zenoh: session settings.
        lockstep: the lockstep clock (True) or the wall clock (False).
        steps: steps to fly. dt_s: step length (mission s). speedup: mission s per wall s.
        seed: the mission seed (the control draws' stream).
        start_position_m: this drone's start position (m, ENU, shape (3,)).
        planner: the mission's planning parameters (:class:`planner.config.PlannerConfig`).
        view: the delayed view's settings.
        flavour_setting: ``"auto"`` or a flavour's name (``"ardupilot"``, ``"px4"``).
        setpoint_frame: ``"global"`` or ``"local_ned"`` (``auto`` resolved by the mode).
        signing_key: the MAVLink 2 signing key (read and checked), or None.
        mission_frame: the mission's ENU frame at its origin.
        origin_lat_lon_alt: the mission origin (deg, deg, m AMSL), for messages.
        altitude_reference: the mission's altitude reference (``"amsl"`` or ``"relative"``).
        end_action: ``"hold"``, ``"land"`` or ``"rtl"``.
        takeoff_alt_m: real time: the take-off altitude (m, ENU z; the start's when the
            mission gives none).
        log_path, rejoin, tlog_path, step_timeout_s, preflight_timeout_s, end_timeout_s,
        stream_hz, peer_wait_fraction, start_at_unix: as in :class:`NodeOptions`.
        measurement_max_age_s: real time: newest payload measurement used if at most this old
            (mission s; the option, else dt).
    """

    uav: int
    drone_index: int
    drone_count: int
    sysid: int
    mission_id: str
    mavlink: str
    zenoh: SessionSettings
    lockstep: bool
    steps: int
    dt_s: float
    speedup: float
    seed: int
    start_position_m: tuple[float, float, float]
    planner: PlannerConfig
    view: ViewSettings
    flavour_setting: FlavourSetting
    setpoint_frame: Frame
    signing_key: bytes | None
    mission_frame: MissionFrame
    origin_lat_lon_alt: tuple[float, float, float]
    altitude_reference: AltitudeReference
    end_action: Literal["hold", "land", "rtl"]
    takeoff_alt_m: float
    log_path: Path | None
    rejoin: bool
    tlog_path: Path | None
    step_timeout_s: float
    preflight_timeout_s: float
    end_timeout_s: float
    stream_hz: float
    peer_wait_fraction: float
    measurement_max_age_s: float
    start_at_unix: float | None

    @property
    def dt_wall_s(self) -> float:
        """Step length in wall seconds (dt / speedup)."""
        return self.dt_s / self.speedup

    @property
    def start_m(self) -> np.ndarray:
        """:attr:`start_position_m` as a float array (m, ENU, shape (3,))."""
        return np.array(self.start_position_m, dtype=float)

    @classmethod
    def from_mission(cls, mission: Any, options: NodeOptions) -> NodeConfig:
        """Resolve the options against the mission (``missions.schema.Mission``, duck-typed):
        the drone's vehicle settings, the setpoint frame, the signing key (read and
        permission-checked here: a refused key starts nothing). NodeError for a drone id
        outside the mission."""
        n = mission.drones.count
        if not 1 <= options.uav <= n:
            raise NodeError(f"--uav {options.uav}: the mission has drones 1..{n}")
        index = options.uav - 1
        resolved = mission.vehicles.for_drone(index)
        frame = options.setpoint_frame or resolved.setpoint_frame
        key_file = options.signing_key_file or resolved.signing_key_file
        start = mission.drones.start_positions_m()[index]
        start_position = (float(start[0]), float(start[1]), float(start[2]))
        return cls(
            uav=options.uav,
            drone_index=index,
            drone_count=n,
            sysid=options.sysid or options.uav,
            mission_id=mission.id,
            mavlink=options.mavlink,
            zenoh=options.zenoh,
            lockstep=options.lockstep,
            steps=options.steps or mission.steps,
            dt_s=mission.dt_s,
            speedup=options.speedup,
            seed=mission.seed,
            start_position_m=start_position,
            planner=mission.planner_config(),
            view=ViewSettings(
                d_hop_m=mission.comms.d_hop_m,
                h_max=mission.comms.h_max,
                emulate=mission.comms.latency == "emulated",
                faults=mission.comms.faults.to_model(),
                seed=mission.seed,
            ),
            flavour_setting=options.flavour or resolved.autopilot,
            setpoint_frame=("local_ned" if options.lockstep else "global") if frame == "auto" else frame,
            signing_key=read_signing_key(key_file) if key_file is not None else None,
            mission_frame=MissionFrame.of_mission(mission),
            origin_lat_lon_alt=(float(mission.origin.lat_deg), float(mission.origin.lon_deg), float(mission.origin.alt_m)),
            altitude_reference=mission.altitude_reference,
            end_action=mission.end_action,
            takeoff_alt_m=float(mission.takeoff_alt_m if mission.takeoff_alt_m is not None else start[2]),
            log_path=options.log_path,
            rejoin=options.rejoin,
            tlog_path=options.tlog_path,
            step_timeout_s=options.step_timeout_s,
            preflight_timeout_s=options.preflight_timeout_s,
            end_timeout_s=options.end_timeout_s,
            stream_hz=options.stream_hz,
            peer_wait_fraction=options.peer_wait_fraction,
            measurement_max_age_s=options.measurement_max_age_s if options.measurement_max_age_s is not None else mission.dt_s,
            start_at_unix=options.start_at_unix,
        )
