"""Geometry in the mission ENU frame: ranges and angles, line of sight, distance to obstacles.

Frame: ENU, metres (x east, y north, z up), about the mission origin. Angles in radians.
Obstacles are axis-aligned boxes (the paper's parallelepipeds) given by their lower and upper
corners, ``boxes_min`` and ``boxes_max`` of shape (B, 3); B may be 0.

Every function broadcasts over leading dimensions (trials, drones, ...).
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Horizontal distances below this are treated as this (m): the azimuth is undefined
#: straight above or below the source.
RHO_FLOOR_M: float = 1e-9


def vec3(values: Iterable[float]) -> tuple[float, float, float]:
    """One point or vector, e.g. a (3,) array, as three Python floats ``(x, y, z)`` (the form
    messages and settings hold); ValueError for another number of values."""
    out = tuple(float(v) for v in values)
    if len(out) != 3:
        raise ValueError(f"expected 3 coordinates (x, y, z), found {len(out)}")
    return out[0], out[1], out[2]


def ranges_angles(source: ArrayLike, positions: ArrayLike) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Distance, azimuth and elevation from each drone to the source (paper Fig. 1, eq. 3).

    .. math::
        \\mathbf r = \\mathbf p_0 - \\mathbf p_j,\\quad d = \\lVert \\mathbf r\\rVert,\\quad
        \\phi = \\operatorname{atan2}(r_y, r_x),\\quad
        \\theta = \\operatorname{atan2}(r_z, \\sqrt{r_x^2 + r_y^2})

    Args:
        source: source position p0, shape (..., 3), metres, mission ENU frame.
        positions: drone positions p_j, shape (..., N, 3), metres, mission ENU frame.

    Returns:
        ``(d, phi, theta)``, each of shape (..., N): distance (m), azimuth (rad, from east
        towards north, in (-π, π]) and elevation (rad, in [-π/2, π/2]) of the source seen from
        each drone.
    """
    r = np.asarray(source, dtype=float)[..., None, :] - np.asarray(positions, dtype=float)
    rho = np.hypot(r[..., 0], r[..., 1])
    d = np.sqrt(rho * rho + r[..., 2] ** 2)
    return d, np.arctan2(r[..., 1], r[..., 0]), np.arctan2(r[..., 2], rho)


def line_of_sight(positions: ArrayLike, source: ArrayLike, boxes_min: ArrayLike, boxes_max: ArrayLike) -> BoolArray:
    """Whether the segment drone → source crosses no obstacle (slab test).

    A link is NLOS when the closed segment from the drone to the source meets the interior
    or the surface of any box (paper: the indicator p_j of eq. 3 is 1 in LOS).

    Args:
        positions: drone positions, shape (..., N, 3), metres, ENU.
        source: source position, shape (..., 3), metres, ENU.
        boxes_min, boxes_max: box corners, shape (B, 3), metres, ENU.

    Returns:
        Boolean array of shape (..., N), True where the link is line of sight.
    """
    p = np.asarray(positions, dtype=float)
    s = np.asarray(source, dtype=float)
    bmin = np.asarray(boxes_min, dtype=float).reshape(-1, 3)
    bmax = np.asarray(boxes_max, dtype=float).reshape(-1, 3)
    if bmin.shape[0] == 0:
        return np.ones(p.shape[:-1], dtype=bool)
    direction = (s[..., None, :] - p)[..., None, :]  # (..., N, 1, 3)
    origin = p[..., None, :]  # (..., N, 1, 3)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / direction
        t1 = (bmin - origin) * inv  # (..., N, B, 3)
        t2 = (bmax - origin) * inv
    parallel = direction == 0.0
    inside_slab = (origin >= bmin) & (origin <= bmax)
    lo = np.where(parallel, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    hi = np.where(parallel, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    t_enter = np.maximum(lo.max(axis=-1), 0.0)
    t_exit = np.minimum(hi.min(axis=-1), 1.0)
    blocked = t_enter <= t_exit
    return ~blocked.any(axis=-1)


def as_boxes(boxes_min: ArrayLike, boxes_max: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Box corners (B, 3), m, ENU, as C-contiguous float arrays (the form the kernels take)."""
    return _box_array(boxes_min), _box_array(boxes_max)


def _box_array(corners: ArrayLike) -> FloatArray:
    if (
        isinstance(corners, np.ndarray)
        and corners.dtype == np.float64
        and corners.ndim == 2
        and corners.flags.c_contiguous
        and corners.flags.writeable
    ):
        return corners
    return _kernel_points(corners)


def _kernel_points(points: ArrayLike) -> FloatArray:
    """Points (..., 3) as a C-contiguous, writeable (n, 3) float array: the one array type the
    kernels are compiled for (:func:`planner.kernels.contiguous`; this module does not import
    numba at its top)."""
    arr = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
    return arr if arr.flags.writeable else arr.copy()


def distance_to_boxes(points: ArrayLike, boxes_min: ArrayLike, boxes_max: ArrayLike) -> FloatArray:
    """Signed distance from each point to the nearest obstacle surface (negative inside).

    Used by the obstacle constraint g3 = d_O - d_O* (paper eq. 17). Per box: |p − clip(p, min,
    max)| outside, minus the distance to the nearest face inside; the smallest over the boxes
    (compiled, :mod:`planner.kernels`).

    Args:
        points: shape (..., 3), metres, ENU.
        boxes_min, boxes_max: shape (B, 3), metres, ENU.

    Returns:
        Shape (...): metres; ``+inf`` when there is no obstacle.
    """
    from planner import kernels  # imported here: a vehicle process imports this module without numba

    p = np.asarray(points, dtype=float)
    d, _ = kernels.distances_batch(_kernel_points(p), *as_boxes(boxes_min, boxes_max), False)
    return d.reshape(p.shape[:-1])


def distance_to_boxes_with_gradient(points: ArrayLike, boxes_min: ArrayLike, boxes_max: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Signed distance to the nearest box and its gradient with respect to the point.

    Outside a box the distance is ``|p - clip(p, min, max)|`` and its gradient the unit vector
    from the closest surface point to p; inside, it is minus the distance to the nearest face
    and the gradient is that face's outward normal (the nearest box: the first of the smallest
    distance; compiled, :mod:`planner.kernels`).

    Args:
        points: shape (..., 3), metres, ENU.
        boxes_min, boxes_max: shape (B, 3), metres, ENU.

    Returns:
        ``(distance, gradient)`` with shapes (...) and (..., 3). With no obstacle: ``+inf`` and
        zeros.
    """
    from planner import kernels  # imported here: see distance_to_boxes

    p = np.asarray(points, dtype=float)
    d, g = kernels.distances_batch(_kernel_points(p), *as_boxes(boxes_min, boxes_max), True)
    return d.reshape(p.shape[:-1]), g.reshape(p.shape)


def points_inside_boxes(points: ArrayLike, boxes_min: ArrayLike, boxes_max: ArrayLike) -> BoolArray:
    """Whether each point lies inside (or on) any box. Shape (...)."""
    return distance_to_boxes(points, boxes_min, boxes_max) <= 0.0


#: Points sampled along a link by :func:`link_clearance_with_gradient`.
LINK_SAMPLES: int = 16


def link_clearance_with_gradient(
    positions: ArrayLike,
    source: ArrayLike,
    boxes_min: ArrayLike,
    boxes_max: ArrayLike,
    samples: int = LINK_SAMPLES,
    cutoff_m: float | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Clearance of the link drone → source from each obstacle, and its gradient w.r.t. the drone.

    The clearance from a box is c = min over t ∈ (0, 1] of the signed distance to the box
    (as :func:`distance_to_boxes`) of the point x(t) = s + t (p − s) of the segment from the
    source s to the drone p: positive when the link passes c metres from the box, negative when
    it crosses it (−c is then how deep the segment runs inside). The signed distance to a convex
    box is convex, so along the segment it has one minimum; it is located on ``samples`` points
    t_m = (m + 1)/samples (resolution |p − s|/samples). The gradient is ∇_p c = t* ∇d(x(t*)),
    t* the sampled minimiser (∂x/∂p = t I): the direction in which the drone moves its link
    away from the box (out of its shadow). A face the link cannot pass is no way out: a box whose
    bottom is at or below both ends of the link (a building standing on the ground) is taken
    to extend downwards without end for it, one whose top is at or above both ends upwards. This
    leaves the clearance of a link that passes the box unchanged (the segment's heights lie
    between its ends) and turns the gradient of one that crosses it to the nearest side face:
    otherwise a link low across a building was sent to the ground, under it. A link that
    crosses a box (the sampled minimum inside it) gets the direction that takes the part of the
    segment inside the box past a side face with the smallest move of the drone (not the deepest
    point's nearest face, which can be the building's back). Compiled (:mod:`planner.kernels`).

    Args:
        positions: drone positions p, shape (..., 3), m, ENU.
        source: source positions s (true or estimated), shape (..., 3), m, ENU.
        boxes_min, boxes_max: box corners, shape (B, 3), m, ENU.
        samples: number of points on the segment.
        cutoff_m: a link whose bounding box is farther than this from a box is not sampled for
            that box: its clearance is reported as that distance (a lower bound, ≥ cutoff_m)
            with a zero gradient. None: every link is sampled.

    Returns:
        ``(clearance, gradient)`` per box, shapes (..., B) m and (..., B, 3); the nearest box's
        clearance is ``clearance.min(-1)``.
    """
    from planner import kernels  # imported here: see distance_to_boxes

    p = np.asarray(positions, dtype=float)
    s = np.asarray(source, dtype=float)
    shape = np.broadcast_shapes(p.shape, s.shape)
    bmin, bmax = as_boxes(boxes_min, boxes_max)
    nb = bmin.shape[0]
    pf = _kernel_points(np.broadcast_to(p, shape))
    sf = _kernel_points(np.broadcast_to(s, shape))
    c, g = kernels.link_clearance_batch(pf, sf, bmin, bmax, samples, -1.0 if cutoff_m is None else float(cutoff_m))
    return c.reshape(shape[:-1] + (nb,)), g.reshape(shape[:-1] + (nb, 3))
