"""The parameter protocol of a simulated vehicle (PARAM_REQUEST_LIST / _READ, PARAM_SET,
PARAM_VALUE) and its parameter tables, one per flavour, as data: each parameter names where
its value lives and the rule that checks a new value."""

from __future__ import annotations

import difflib
import math
import struct
from collections.abc import Mapping
from dataclasses import dataclass, replace
from types import MappingProxyType
from typing import Any, Literal, Protocol

from comms.autopilot import FlavourInfo
from vehicle_sim.failsafe import Failsafes
from vehicle_sim.flight_state import FlightState
from vehicle_sim.geofence import FenceGuard
from vehicle_sim.modes import ModeMachine
from vehicle_sim.outbox import Outbox
from vehicle_sim.setpoints import GuidedSetpoints

#: The collaborator that holds a plain parameter value (:class:`ParamTargets`' attribute).
Owner = Literal["modes", "setpoints", "failsafes", "table"]


@dataclass
class ParamTargets:
    """Where parameter values live: the collaborators of one vehicle.

    Attributes:
        state: the flight state (kinematic limits in ``state.pm.limits``; home height).
        fence: the fence guard. modes, setpoints, failsafes: value holders.
        table: the parameter table itself (``sysid_param``).
    """

    state: FlightState
    fence: FenceGuard
    modes: ModeMachine
    setpoints: GuidedSetpoints
    failsafes: Failsafes
    table: Any


class Rule(Protocol):
    """How one parameter reads and checks its value (in the flavour's unit)."""

    def get(self, t: ParamTargets) -> float:
        """The value (parameter unit)."""
        ...

    def set(self, t: ParamTargets, v: float) -> str | None:
        """Adopt ``v`` (parameter unit); None, or why it is refused."""
        ...


@dataclass(frozen=True)
class LimitField:
    """A :class:`vehicle_sim.config.VehicleLimits` field: SI = value × ``to_si``, value =
    SI × ``from_si`` (e.g. cm/s: 0.01 and 100); must be finite and positive."""

    field: str
    to_si: float = 1.0
    from_si: float = 1.0

    def get(self, t: ParamTargets) -> float:
        return float(getattr(t.state.pm.limits, self.field)) * self.from_si

    def set(self, t: ParamTargets, v: float) -> str | None:
        val = v * self.to_si
        if not math.isfinite(val) or val <= 0:
            return "must be a finite positive number"
        try:
            t.state.pm.limits = replace(t.state.pm.limits, **{self.field: val})
        except ValueError as exc:
            return str(exc)
        return None


@dataclass(frozen=True)
class Scalar:
    """A float attribute of ``owner`` in [lo, hi] (SI); value = SI × ``per_si``."""

    owner: Owner
    attr: str
    lo: float
    hi: float
    per_si: float = 1.0

    def get(self, t: ParamTargets) -> float:
        value: float = getattr(getattr(t, self.owner), self.attr)
        return value * self.per_si if self.per_si != 1.0 else value

    def set(self, t: ParamTargets, v: float) -> str | None:
        u = v / self.per_si if self.per_si != 1.0 else v
        if not (math.isfinite(u) and self.lo <= u <= self.hi):
            return f"must be in [{self.lo:g}, {self.hi:g}]"
        setattr(getattr(t, self.owner), self.attr, float(u))
        return None


@dataclass(frozen=True)
class Integer:
    """An integer attribute of ``owner`` in lo..hi (stored as a float)."""

    owner: Owner
    attr: str
    lo: int
    hi: int

    def get(self, t: ParamTargets) -> float:
        value: float = getattr(getattr(t, self.owner), self.attr)
        return value

    def set(self, t: ParamTargets, v: float) -> str | None:
        if not (math.isfinite(v) and v == int(v) and self.lo <= v <= self.hi):
            return f"must be an integer in {self.lo}..{self.hi}"
        setattr(getattr(t, self.owner), self.attr, float(v))
        return None


@dataclass(frozen=True)
class FenceEnable:
    """The fence on (1) or off (0)."""

    def get(self, t: ParamTargets) -> float:
        return float(t.fence.fence.enabled)

    def set(self, t: ParamTargets, v: float) -> str | None:
        if v not in (0.0, 1.0):
            return "must be 0 or 1"
        t.fence.fence = replace(t.fence.fence, enabled=v == 1.0)
        return None


@dataclass(frozen=True)
class FenceHeight:
    """The fence's floor or ceiling (``z_min_m`` / ``z_max_m``) as a height above home (m)."""

    field: Literal["z_min_m", "z_max_m"]

    def get(self, t: ParamTargets) -> float:
        return float(getattr(t.fence.fence, self.field)) - float(t.state.home[2])

    def set(self, t: ParamTargets, v: float) -> str | None:
        if not math.isfinite(v):
            return "must be finite"
        z = v + float(t.state.home[2])
        try:
            t.fence.fence = replace(t.fence.fence, z_min_m=z) if self.field == "z_min_m" else replace(t.fence.fence, z_max_m=z)
        except ValueError as exc:
            return str(exc)
        return None


@dataclass(frozen=True)
class FenceRadius:
    """The fence radius about home (m; 0 = none)."""

    def get(self, t: ParamTargets) -> float:
        return 0.0 if t.fence.fence.radius_m is None else t.fence.fence.radius_m

    def set(self, t: ParamTargets, v: float) -> str | None:
        if not (math.isfinite(v) and v >= 0):
            return "must be >= 0 (0 = off)"
        t.fence.fence = replace(t.fence.fence, radius_m=None if v == 0 else float(v))
        return None


@dataclass(frozen=True)
class FenceBox:
    """A bound of the mission's horizontal fence box (ENU m; read-only; NaN if none)."""

    field: str

    def get(self, t: ParamTargets) -> float:
        val = getattr(t.fence.fence, self.field)
        return float("nan") if val is None else float(val)

    def set(self, t: ParamTargets, v: float) -> str | None:
        return "read-only"


@dataclass(frozen=True)
class SystemId:
    """The system id the vehicle takes at its next boot (1..255), as on ArduPilot."""

    def get(self, t: ParamTargets) -> float:
        value: float = t.table.sysid_param
        return value

    def set(self, t: ParamTargets, v: float) -> str | None:
        if not (v == int(v) and 1 <= v <= 255):
            return "must be an integer in 1..255"
        t.table.sysid_param = float(v)
        return None


@dataclass(frozen=True)
class Constant:
    """A read-only constant."""

    value: float

    def get(self, t: ParamTargets) -> float:
        return self.value

    def set(self, t: ParamTargets, v: float) -> str | None:
        return "read-only"


@dataclass(frozen=True)
class ParamSpec:
    """One parameter: its name, whether it is an integer (MAV_PARAM_TYPE_INT32), its rule."""

    name: str
    integer: bool
    rule: Rule


PX4_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("MAV_SYS_ID", True, SystemId()),
    ParamSpec("MPC_XY_VEL_MAX", False, LimitField("speed_max_h_mps")),
    ParamSpec("MPC_Z_VEL_MAX_UP", False, LimitField("speed_max_up_mps")),
    ParamSpec("MPC_Z_VEL_MAX_DN", False, LimitField("speed_max_down_mps")),
    ParamSpec("MPC_ACC_HOR_MAX", False, LimitField("accel_max_mps2")),
    ParamSpec("MPC_LAND_SPEED", False, LimitField("land_speed_mps")),
    ParamSpec("MPC_TKO_SPEED", False, LimitField("takeoff_speed_mps")),
    ParamSpec("COM_OF_LOSS_T", False, Scalar("setpoints", "offboard_loss_s", 0.1, 60.0)),
    ParamSpec("COM_OBL_RC_ACT", True, Integer("failsafes", "offboard_loss_action", 0, 7)),
    ParamSpec("MIS_TAKEOFF_ALT", False, Scalar("modes", "takeoff_alt_m", 0.5, 1000.0)),
    ParamSpec("RTL_RETURN_ALT", False, Scalar("modes", "rtl_alt_m", 0.0, 1000.0)),
    ParamSpec("GF_MAX_VER_DIST", False, FenceHeight("z_max_m")),
    ParamSpec("GF_MAX_HOR_DIST", False, FenceRadius()),
    ParamSpec("FIMNAV_FENCE_ZMIN", False, FenceHeight("z_min_m")),
)

#: ArduPilot's speeds and accelerations are in cm/s and cm/s².
ARDUPILOT_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("SYSID_THISMAV", True, SystemId()),
    ParamSpec("FRAME_CLASS", True, Constant(1.0)),
    ParamSpec("WPNAV_SPEED", False, LimitField("speed_max_h_mps", to_si=0.01, from_si=100.0)),
    ParamSpec("WPNAV_SPEED_UP", False, LimitField("speed_max_up_mps", to_si=0.01, from_si=100.0)),
    ParamSpec("WPNAV_SPEED_DN", False, LimitField("speed_max_down_mps", to_si=0.01, from_si=100.0)),
    ParamSpec("WPNAV_ACCEL", False, LimitField("accel_max_mps2", to_si=0.01, from_si=100.0)),
    ParamSpec("LAND_SPEED", False, LimitField("land_speed_mps", to_si=0.01, from_si=100.0)),
    ParamSpec("PILOT_SPEED_UP", False, LimitField("takeoff_speed_mps", to_si=0.01, from_si=100.0)),
    ParamSpec("GUID_TIMEOUT", False, Scalar("setpoints", "guided_timeout_s", 0.1, 5.0)),
    ParamSpec("FS_GCS_ENABLE", True, Integer("failsafes", "fs_gcs_enable", 0, 6)),
    ParamSpec("FS_GCS_TIMEOUT", False, Scalar("failsafes", "fs_gcs_timeout_s", 2.0, 120.0)),
    ParamSpec("SYSID_MYGCS", True, Integer("failsafes", "sysid_mygcs", 1, 255)),
    ParamSpec("RTL_ALT", False, Scalar("modes", "rtl_alt_m", 0.0, 1000.0, per_si=100.0)),
    ParamSpec("FENCE_ALT_MAX", False, FenceHeight("z_max_m")),
    ParamSpec("FENCE_ALT_MIN", False, FenceHeight("z_min_m")),
    ParamSpec("FENCE_RADIUS", False, FenceRadius()),
)

#: The flavours' parameter tables by name (:attr:`comms.autopilot.FlavourInfo.param_table`).
PARAM_TABLES: Mapping[str, tuple[ParamSpec, ...]] = MappingProxyType({"ardupilot": ARDUPILOT_PARAMS, "px4": PX4_PARAMS})


def param_table(name: str) -> tuple[ParamSpec, ...]:
    """The parameter table ``name`` of :data:`PARAM_TABLES`.

    Raises:
        ValueError: no such table.
    """
    table = PARAM_TABLES.get(name)
    if table is None:
        raise ValueError(f"parameter table {name!r}: expected one of {', '.join(repr(n) for n in PARAM_TABLES)}")
    return table


#: Parameters of both flavours, after the flavour's own.
COMMON_PARAMS: tuple[ParamSpec, ...] = (ParamSpec("FENCE_ENABLE", True, FenceEnable()),)
#: The mission's horizontal fence box, read-only, present when the fence has one.
FENCE_BOX_PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("FIMNAV_FENCE_XMIN", False, FenceBox("x_min_m")),
    ParamSpec("FIMNAV_FENCE_XMAX", False, FenceBox("x_max_m")),
    ParamSpec("FIMNAV_FENCE_YMIN", False, FenceBox("y_min_m")),
    ParamSpec("FIMNAV_FENCE_YMAX", False, FenceBox("y_max_m")),
)


class Param:
    """One parameter bound to its vehicle: :meth:`get` and :meth:`set` in the flavour's unit."""

    def __init__(self, spec: ParamSpec, targets: ParamTargets) -> None:
        self.spec = spec
        self.name = spec.name
        self.integer = spec.integer
        self._targets = targets

    def get(self) -> float:
        """The current value."""
        return self.spec.rule.get(self._targets)

    def set(self, v: float) -> str | None:
        """Adopt ``v``; None, or why it is refused."""
        return self.spec.rule.set(self._targets, v)


class ParameterTable:
    """The flavour's parameters and the parameter protocol.

    Args:
        flavour: ``"ardupilot"`` or ``"px4"``. info: the autopilot profile (integer
            encoding). sysid: the system id at boot. outbox: the sending side.
        state, fence, modes, setpoints, failsafes: where the values live.
    """

    def __init__(
        self,
        flavour: str,
        info: FlavourInfo,
        sysid: int,
        outbox: Outbox,
        state: FlightState,
        fence: FenceGuard,
        modes: ModeMachine,
        setpoints: GuidedSetpoints,
        failsafes: Failsafes,
    ) -> None:
        self.flavour = flavour
        self.info = info
        self.outbox = outbox
        self.mavlink = outbox.mavlink
        self.sysid_param = float(sysid)
        targets = ParamTargets(state, fence, modes, setpoints, failsafes, self)
        specs = param_table(info.param_table) + COMMON_PARAMS
        if fence.fence.has_box:
            specs += FENCE_BOX_PARAMS
        self.params: dict[str, Param] = {s.name: Param(s, targets) for s in specs}

    def boot_param(self, name: str, value: float) -> None:
        """Set parameter ``name`` at boot (``VehicleConfig.params``).

        Raises:
            ValueError: unknown name (with the closest known names) or a refused value.
        """
        p = self.params.get(name)
        if p is None:
            close = difflib.get_close_matches(name, list(self.params), n=3)
            hint = f"; did you mean {', '.join(close)}?" if close else f"; known: {', '.join(sorted(self.params))}"
            raise ValueError(f"parameter {name!r} is not a parameter of the simulated {self.flavour} vehicle{hint}")
        err = p.set(float(value))
        if err:
            raise ValueError(f"parameter {name} = {value:g}: {err}")

    def _encode(self, p: Param) -> tuple[float, int]:
        m = self.mavlink
        value = p.get()
        if not p.integer:
            return value, m.MAV_PARAM_TYPE_REAL32
        if self.info.param_bytewise:
            return struct.unpack("<f", struct.pack("<i", int(value)))[0], m.MAV_PARAM_TYPE_INT32
        return float(int(value)), m.MAV_PARAM_TYPE_INT32

    def _decode(self, p: Param, raw: float) -> float:
        if p.integer and self.info.param_bytewise:
            return float(struct.unpack("<i", struct.pack("<f", raw))[0])
        return float(raw)

    def _send(self, p: Param) -> None:
        names = list(self.params)
        value, ptype = self._encode(p)
        self.outbox.send(self.mavlink.MAVLink_param_value_message(p.name.encode(), value, ptype, len(names), names.index(p.name)))

    @staticmethod
    def _param_id(raw: Any) -> str:
        if isinstance(raw, bytes):
            raw = raw.decode("utf-8", errors="replace")
        return str(raw).split("\x00")[0].strip()

    def on_param_request_list(self, msg: Any) -> None:
        """PARAM_REQUEST_LIST: every PARAM_VALUE in table order."""
        for p in self.params.values():
            self._send(p)

    def on_param_request_read(self, msg: Any) -> None:
        """PARAM_REQUEST_READ by index (>= 0) or name; nothing for an unknown one."""
        names = list(self.params)
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send(self.params[names[msg.param_index]])
            return
        p = self.params.get(self._param_id(msg.param_id))
        if p is not None:
            self._send(p)

    def on_param_set(self, msg: Any) -> None:
        """PARAM_SET: adopt the value (or say why not), then report the value in force."""
        name = self._param_id(msg.param_id)
        p = self.params.get(name)
        if p is None:
            self.outbox.statustext(4, f"Param {name[:16]} not found")
            return
        value = self._decode(p, msg.param_value)
        err = p.set(value)
        if err:
            self.outbox.statustext(4, f"Param {name}: {err}"[:50])
        self._send(p)
