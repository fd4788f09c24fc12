"""Point-mass dynamics of the simulated vehicle (pure numpy, no I/O).

State: true position ``p`` and velocity ``v`` in the mission ENU frame (m, m/s), advanced at a
fixed physics step ``h`` (s). Commands (:class:`Command`) come from the vehicle's mode logic.

Two profiles:

``ideal``
    The commanded motion is integrated exactly, with no acceleration limit and no lag,
    in closed form from the time the command was received (no accumulated rounding):

    * velocity ``u``: ``p(t) = p0 + u (t - t0)``;
    * position ``q`` with speed ``s`` (``|v_ff|`` for a fixed position+velocity target, else
      the speed limit): straight line from ``p0`` to ``q`` at speed ``s``; on arrival the
      position is set to ``q`` *exactly* and held. Hence a fixed position+velocity setpoint
      ``(p + v dt, v)`` received at ``t0`` puts the vehicle at exactly ``p + v dt`` at
      ``t0 + dt``. "Arrival" tolerates the float32 rounding of MAVLink fields (see
      :meth:`PointMass._arrival_tol`);
    * a moving target ``(q, v)`` (``Command.moving``): see below.

``pointmass``
    A velocity loop saturated at the acceleration limit tracks a desired velocity: the
    velocity command itself, or for position targets ``dir · min(s, sqrt(2 a_max d), k_p d)``
    (``d`` distance to go, ``k_p`` = 1/s), capped by the horizontal/vertical speed limits,
    optionally low-passed with a first-order lag ``tau`` and disturbed by wind as the
    acceleration ``drag · wind``. Semi-implicit Euler integration.

A position+velocity target is a *fixed* point (PX4 OFFBOARD: the velocity is a feed-forward)
or, with ``Command.moving`` (ArduPilot GUIDED), a point that moves with the velocity from the
time it was received, ``q(t) = q + v (t - t0)``, as ArduPilot's position controller advances its
target between setpoints. The ideal profile then closes its initial offset from ``q`` at the
speed limit along it and follows ``q(t)`` exactly; see docs/vehicle_sim.md.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from vehicle_sim.config import Profile, VehicleLimits

FloatArray = NDArray[np.float64]
CommandKind = Literal["idle", "hold", "position", "velocity", "posvel"]

#: Gravity (m/s²) for the attitude of the ATTITUDE message.
GRAVITY_MPS2 = 9.80665
#: Proportional gain of the position loop of the pointmass profile (1/s).
POSITION_GAIN_PER_S = 1.0


@dataclass(frozen=True)
class Command:
    """What the mode logic asks of the point mass.

    Attributes:
        kind: ``idle`` (on the ground, motors off), ``hold`` (stop and hold ``position``),
            ``position`` (go to ``position``), ``velocity`` (fly ``velocity``), ``posvel``
            (go to ``position`` at speed ``|velocity|``).
        position: target (3,) ENU m, or None.
        velocity: velocity command or feed-forward (3,) ENU m/s, or None.
        speed_mps: speed cap of position moves (m/s), None for the limits.
        fence: maps a position into the allowed region (ENU m) or None (no fence).
        moving: for ``posvel``: the target moves with ``velocity`` from the time the command
            was received (ArduPilot GUIDED); False: a fixed point reached at ``|velocity|``.
    """

    kind: CommandKind
    position: FloatArray | None = None
    velocity: FloatArray | None = None
    speed_mps: float | None = None
    fence: Callable[[FloatArray], FloatArray] | None = None
    moving: bool = False


def limit_velocity(v: FloatArray, limits: VehicleLimits) -> FloatArray:
    """Scale ``v`` (ENU m/s) uniformly so its horizontal norm and vertical rate are within
    the limits; direction is kept."""
    scale = 1.0
    h = math.hypot(float(v[0]), float(v[1]))
    if h > limits.speed_max_h_mps:
        scale = min(scale, limits.speed_max_h_mps / h)
    vz = float(v[2])
    if vz > limits.speed_max_up_mps:
        scale = min(scale, limits.speed_max_up_mps / vz)
    elif vz < -limits.speed_max_down_mps:
        scale = min(scale, limits.speed_max_down_mps / -vz)
    return v if scale >= 1.0 else v * scale


def max_speed_along(direction: FloatArray, limits: VehicleLimits) -> float:
    """Largest speed (m/s) along the unit vector ``direction`` within the limits."""
    return float(np.linalg.norm(limit_velocity(direction * 1e6, limits)))


class PointMass:
    """The true kinematic state of one vehicle.

    Args:
        position: initial position (3,), ENU m.
        limits: kinematic limits. profile: ``ideal`` or ``pointmass``.
        lag_s: first-order lag on the velocity command (s, pointmass only, 0 = none).
        wind_enu_mps: constant wind (3,), ENU m/s (pointmass only). drag_per_s: 1/s.
        ground_z_m: ENU altitude of the ground (m); the mass never goes below it.
    """

    def __init__(
        self,
        position: FloatArray,
        limits: VehicleLimits,
        profile: Profile,
        *,
        lag_s: float = 0.0,
        wind_enu_mps: FloatArray | None = None,
        drag_per_s: float = 0.5,
        ground_z_m: float = 0.0,
    ) -> None:
        self.position = np.array(position, dtype=float)
        self.velocity = np.zeros(3)
        self.accel = np.zeros(3)
        self.limits = limits
        self.profile = profile
        self.lag_s = float(lag_s)
        self.wind = np.zeros(3) if wind_enu_mps is None else np.array(wind_enu_mps, dtype=float)
        self.drag_per_s = float(drag_per_s)
        self.ground_z_m = float(ground_z_m)
        self.command = Command("idle")
        self._t = 0.0
        self._t0 = 0.0
        self._p0 = self.position.copy()
        self._vcmd = np.zeros(3)
        self.fenced = False

    def set_command(self, command: Command, t_s: float) -> None:
        """Adopt ``command`` from sim time ``t_s`` (s), the current time of the mass."""
        self.command = command
        self._t0 = t_s
        self._t = t_s
        self._p0 = self.position.copy()

    def step(self, h: float, t_s: float | None = None) -> None:
        """Advance the state by ``h`` seconds (0 < h, normally the physics step) to sim time
        ``t_s`` (s; default: the previous time + h). Passing ``t_s`` avoids accumulating
        rounding in the ideal profile's closed form."""
        self._t = self._t + h if t_s is None else float(t_s)
        self.fenced = False
        before = self.position.copy()
        if self.profile == "ideal":
            self._step_ideal()
        else:
            self._step_pointmass(h)
        cmd = self.command
        if cmd.fence is not None and cmd.kind != "idle":
            fenced = cmd.fence(self.position)
            if not np.array_equal(fenced, self.position):
                self.fenced = True
                self.position = fenced
                self.velocity = (fenced - before) / h
        if self.position[2] < self.ground_z_m:
            self.position[2] = self.ground_z_m
            self.velocity[2] = max(0.0, float(self.velocity[2]))

    # -- profiles ---------------------------------------------------------------------------

    def _travel_speed(self, direction: FloatArray) -> float:
        cmd = self.command
        cap = max_speed_along(direction, self.limits)
        if cmd.kind == "posvel" and cmd.velocity is not None:
            s = float(np.linalg.norm(cmd.velocity))
            if s > 0.0:
                cap = min(cap, s)
        if cmd.speed_mps is not None:
            cap = min(cap, cmd.speed_mps)
        return cap

    def _step_ideal(self) -> None:
        cmd = self.command
        elapsed = self._t - self._t0
        self.accel = np.zeros(3)
        if cmd.kind == "idle" or (cmd.kind == "hold" and cmd.position is None):
            self.velocity = np.zeros(3)
            return
        if cmd.kind == "velocity":
            u = limit_velocity(np.asarray(cmd.velocity, dtype=float), self.limits)
            self.position = self._p0 + u * elapsed
            self.velocity = u.copy()
            return
        if cmd.kind == "posvel" and cmd.moving and cmd.velocity is not None:
            self._step_ideal_moving(elapsed)
            return
        target = np.asarray(cmd.position, dtype=float)
        delta = target - self._p0
        dist = float(np.linalg.norm(delta))
        if dist == 0.0:
            self.position = target.copy()
            self.velocity = np.zeros(3)
            return
        direction = delta / dist
        speed = self._travel_speed(direction)
        travelled = speed * elapsed
        if travelled >= dist - self._arrival_tol(target, dist):
            self.position = target.copy()
            self.velocity = np.zeros(3)
        else:
            self.position = self._p0 + direction * travelled
            self.velocity = direction * speed

    def _step_ideal_moving(self, elapsed: float) -> None:
        """Ideal tracking of a moving target ``q(t) = q + v (t - t0)`` (ArduPilot GUIDED
        position+velocity): the offset ``e0 = p0 - q`` shrinks along itself at the speed limit
        in that direction, on top of the target's motion; once closed the vehicle is at ``q(t)``.
        ``v`` is scaled within the limits first."""
        cmd = self.command
        v = limit_velocity(np.asarray(cmd.velocity, dtype=float), self.limits)
        q_t = np.asarray(cmd.position, dtype=float) + v * elapsed
        e0 = self._p0 - np.asarray(cmd.position, dtype=float)
        d0 = float(np.linalg.norm(e0))
        if d0 > 0.0:
            back = -e0 / d0
            closing = max_speed_along(back, self.limits)
            left = d0 - closing * elapsed
            if left > 0.0:
                self.position = q_t - back * left
                self.velocity = v + back * closing
                return
        self.position = q_t
        self.velocity = v

    def _arrival_tol(self, target: FloatArray, dist: float) -> float:
        """Distance (m) below which the ideal profile snaps onto its target: covers the float32
        rounding of MAVLink setpoints (a target ``p + v dt`` and a velocity ``v`` rounded
        separately disagree by ~1e-7 relative), i.e. 1e-5 of the leg plus 4e-7 of the largest
        coordinate."""
        scale = max(1.0, float(np.max(np.abs(target))), float(np.max(np.abs(self._p0))))
        return 1e-5 * dist + 4e-7 * scale

    def _step_pointmass(self, h: float) -> None:
        cmd = self.command
        lim = self.limits
        if cmd.kind == "idle":
            self.velocity = np.zeros(3)
            self.accel = np.zeros(3)
            self._vcmd = np.zeros(3)
            return
        if cmd.kind == "velocity":
            v_des = limit_velocity(np.asarray(cmd.velocity, dtype=float), lim)
        elif cmd.kind == "posvel" and cmd.velocity is not None and cmd.position is not None:
            # Position + velocity (ArduPilot GUIDED, PX4 OFFBOARD): the velocity is a
            # feed-forward and the position error is corrected on top of it, so a setpoint
            # moving along a path is tracked without a lag that grows with the speed.
            # ArduPilot (``moving``) advances the target with the velocity between setpoints.
            target = np.asarray(cmd.position, dtype=float)
            if cmd.moving:
                target = target + np.asarray(cmd.velocity, dtype=float) * (self._t - self._t0)
            delta = target - self.position
            v_des = limit_velocity(np.asarray(cmd.velocity, dtype=float) + POSITION_GAIN_PER_S * delta, lim)
        else:
            target = np.asarray(cmd.position if cmd.position is not None else self.position, dtype=float)
            delta = target - self.position
            dist = float(np.linalg.norm(delta))
            if dist < 1e-9:
                v_des = np.zeros(3)
            else:
                direction = delta / dist
                speed = min(
                    self._travel_speed(direction),
                    math.sqrt(2.0 * lim.accel_max_mps2 * dist),
                    POSITION_GAIN_PER_S * dist,
                )
                v_des = direction * speed
        if self.lag_s > 0.0:
            alpha = 1.0 - math.exp(-h / self.lag_s)
            self._vcmd = self._vcmd + alpha * (v_des - self._vcmd)
        else:
            self._vcmd = v_des
        a = (self._vcmd - self.velocity) / h
        na = float(np.linalg.norm(a))
        if na > lim.accel_max_mps2:
            a = a * (lim.accel_max_mps2 / na)
        a = a + self.drag_per_s * self.wind
        self.accel = a
        self.velocity = self.velocity + a * h
        self.position = self.position + self.velocity * h

    def attitude(self, yaw_rad: float) -> tuple[float, float]:
        """(roll, pitch) in radians (NED body convention) that produce the current horizontal
        acceleration at heading ``yaw_rad`` (from north, clockwise)."""
        a_n, a_e = float(self.accel[1]), float(self.accel[0])
        fwd = a_n * math.cos(yaw_rad) + a_e * math.sin(yaw_rad)
        right = -a_n * math.sin(yaw_rad) + a_e * math.cos(yaw_rad)
        return math.atan2(right, GRAVITY_MPS2), -math.atan2(fwd, GRAVITY_MPS2)
