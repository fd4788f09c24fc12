"""The simulated vehicle's inclusion fence (mission ENU frame), see :class:`vehicle_sim.config.Geofence`."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from vehicle_sim.config import Geofence
from vehicle_sim.dynamics import FloatArray


class FenceGuard:
    """Clamps and checks positions against the current fence (changed by FENCE_* parameters
    and MAV_CMD_DO_FENCE_ENABLE).

    Args:
        fence: the fence at boot. home: the home position (3,), ENU m, centre of the radius.
    """

    def __init__(self, fence: Geofence, home: FloatArray) -> None:
        self.fence = fence
        self.home = home

    def clamp(self, p: FloatArray, floor: FloatArray | None = None) -> FloatArray:
        """Move ``p`` (ENU m) into the fence. With ``floor`` (a reference position, normally
        the vehicle's own), the fence is widened to include it, so a vehicle already outside
        (e.g. below FENCE_ALT_MIN after take-off) is never teleported."""
        f = self.fence
        if not f.enabled:
            return p
        q = np.array(p, dtype=float)

        def lim(lo: float, hi: float, axis: int) -> tuple[float, float]:
            if floor is None:
                return lo, hi
            r = float(floor[axis])
            return min(lo, r), max(hi, r)

        zlo, zhi = lim(f.z_min_m, f.z_max_m, 2)
        q[2] = min(max(q[2], zlo), zhi)
        box = f.box
        if box is not None:
            xlo, xhi = lim(box[0], box[1], 0)
            ylo, yhi = lim(box[2], box[3], 1)
            q[0] = min(max(q[0], xlo), xhi)
            q[1] = min(max(q[1], ylo), yhi)
        if f.radius_m is not None:
            r_max = f.radius_m
            if floor is not None:
                r_max = max(r_max, math.hypot(float(floor[0] - self.home[0]), float(floor[1] - self.home[1])))
            dx, dy = q[0] - self.home[0], q[1] - self.home[1]
            r = math.hypot(dx, dy)
            if r > r_max:
                q[0] = self.home[0] + dx * r_max / r
                q[1] = self.home[1] + dy * r_max / r
        return q

    def inside(self, p: FloatArray, check_floor: bool = True) -> bool:
        """True when ``p`` (ENU m) is inside the fence; ``check_floor=False`` ignores the
        altitude floor (a vehicle on the ground)."""
        if not self.fence.enabled:
            return True
        q = np.array(p, dtype=float)
        if not check_floor and q[2] < self.fence.z_min_m:
            q[2] = self.fence.z_min_m
        return bool(np.allclose(self.clamp(q), q, atol=1e-9, rtol=0))

    def motion_fence(self, position: FloatArray) -> Callable[[FloatArray], FloatArray]:
        """The fence a guided motion starting at ``position`` (ENU m) is held in: the fence
        widened to include the start (:meth:`clamp` with ``floor``)."""
        ref = position.copy()
        return lambda p: self.clamp(p, floor=ref)
