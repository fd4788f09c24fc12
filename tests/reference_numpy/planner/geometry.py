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


def _box_distances(p: FloatArray, bmin: FloatArray, bmax: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Per-box signed distances (..., B), outside offsets p - clip(p) (..., B, 3) and face gaps."""
    q = p[..., None, :]
    offset = q - np.minimum(np.maximum(q, bmin), bmax)
    outside = np.sqrt((offset * offset).sum(-1))
    gaps = np.minimum(q - bmin, bmax - q)  # > 0 inside, per axis
    depth = gaps.min(-1)
    return np.where(outside > 0.0, outside, -np.maximum(depth, 0.0)), offset, gaps


def distance_to_boxes(points: ArrayLike, boxes_min: ArrayLike, boxes_max: ArrayLike) -> FloatArray:
    """Signed distance from each point to the nearest obstacle surface (negative inside).

    Used by the obstacle constraint g3 = d_O - d_O* (paper eq. 17).

    Args:
        points: shape (..., 3), metres, ENU.
        boxes_min, boxes_max: shape (B, 3), metres, ENU.

    Returns:
        Shape (...): metres; ``+inf`` when there is no obstacle.
    """
    p = np.asarray(points, dtype=float)
    bmin = np.asarray(boxes_min, dtype=float).reshape(-1, 3)
    bmax = np.asarray(boxes_max, dtype=float).reshape(-1, 3)
    if bmin.shape[0] == 0:
        return np.full(p.shape[:-1], np.inf)
    return _box_distances(p, bmin, bmax)[0].min(-1)


def distance_to_boxes_with_gradient(points: ArrayLike, boxes_min: ArrayLike, boxes_max: ArrayLike) -> tuple[FloatArray, FloatArray]:
    """Signed distance to the nearest box and its gradient with respect to the point.

    Outside a box the distance is ``|p - clip(p, min, max)|`` and its gradient the unit vector
    from the closest surface point to p; inside, it is minus the distance to the nearest face
    and the gradient is that face's outward normal.

    Args:
        points: shape (..., 3), metres, ENU.
        boxes_min, boxes_max: shape (B, 3), metres, ENU.

    Returns:
        ``(distance, gradient)`` with shapes (...) and (..., 3). With no obstacle: ``+inf`` and
        zeros.
    """
    p = np.asarray(points, dtype=float)
    bmin = np.asarray(boxes_min, dtype=float).reshape(-1, 3)
    bmax = np.asarray(boxes_max, dtype=float).reshape(-1, 3)
    if bmin.shape[0] == 0:
        return np.full(p.shape[:-1], np.inf), np.zeros(p.shape)
    q = p[..., None, :]
    offset = q - np.minimum(np.maximum(q, bmin), bmax)
    outside = np.sqrt((offset * offset).sum(-1))
    if (outside > 0.0).all():  # the usual case, outside every box: unit vector from the surface
        batch = outside.shape[:-1]
        nb = outside.shape[-1]
        nearest = outside.reshape(-1, nb).argmin(-1)
        off = offset.reshape(-1, nb, 3)[np.arange(nearest.shape[0]), nearest].reshape(batch + (3,))
        d = outside.min(-1)
        return d, off / d[..., None]
    below = q - bmin
    above = bmax - q
    gaps = np.minimum(below, above)  # > 0 inside, per axis
    sd = np.where(outside > 0.0, outside, -np.maximum(gaps.min(-1), 0.0))  # per box, as _box_distances
    nearest = sd.argmin(-1)[..., None]  # (..., 1)
    d = np.take_along_axis(sd, nearest, -1)[..., 0]
    off = np.take_along_axis(offset, nearest[..., None], -2)[..., 0, :]
    out = d > 0.0
    # Inside: outward normal of the nearest face (sign: nearer to max -> +, to min -> -).
    gap = np.take_along_axis(gaps, nearest[..., None], -2)[..., 0, :]
    axis = gap.argmin(-1)[..., None]
    lower = np.take_along_axis(np.take_along_axis(below, nearest[..., None], -2)[..., 0, :], axis, -1) < np.take_along_axis(
        np.take_along_axis(above, nearest[..., None], -2)[..., 0, :], axis, -1
    )
    grad = np.zeros(p.shape)
    np.put_along_axis(grad, axis, np.where(lower, -1.0, 1.0), -1)
    grad = np.where(out[..., None], off / np.where(out, d, 1.0)[..., None], grad)
    return d, grad


def points_inside_boxes(points: ArrayLike, boxes_min: ArrayLike, boxes_max: ArrayLike) -> BoolArray:
    """Whether each point lies inside (or on) any box. Shape (...)."""
    return distance_to_boxes(points, boxes_min, boxes_max) <= 0.0


#: Points sampled along a link by :func:`link_clearance_with_gradient`.
LINK_SAMPLES: int = 16


#: How far (m) a box is extended past a face a link cannot pass (:func:`link_clearance_with_gradient`).
_NO_EXIT_M: float = 1.0e4


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
    otherwise a link low across a building was sent to the ground, under it.

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
    p = np.asarray(positions, dtype=float)
    s = np.asarray(source, dtype=float)
    shape = np.broadcast_shapes(p.shape, s.shape)
    bmin = np.asarray(boxes_min, dtype=float).reshape(-1, 3)
    bmax = np.asarray(boxes_max, dtype=float).reshape(-1, 3)
    nb = bmin.shape[0]
    if nb == 0:
        return np.zeros(shape[:-1] + (0,)), np.zeros(shape[:-1] + (0, 3))
    p, s = np.broadcast_to(p, shape).reshape(-1, 3), np.broadcast_to(s, shape).reshape(-1, 3)
    if cutoff_m is None:
        near = np.ones((p.shape[0], nb), dtype=bool)
        c = np.zeros(near.shape)
    else:
        # Distance between the link's bounding box and each box: a lower bound on the clearance.
        hi_ps, lo_ps = np.maximum(p, s), np.minimum(p, s)
        c2 = np.zeros((p.shape[0], nb))
        for a in range(3):  # per axis: reductions over a length-3 last axis are slow in numpy
            gap = np.maximum(np.maximum(bmin[:, a] - hi_ps[:, a, None], lo_ps[:, a, None] - bmax[:, a]), 0.0)
            c2 += gap * gap
        c = np.sqrt(c2)  # (n, B)
        near = c < cutoff_m
    g = np.zeros(c.shape + (3,))
    r, b = np.nonzero(near)
    if r.size:
        # A box's bottom at or below both ends of the link (a building on the ground), or its top
        # at or above both, is no way out for this link: the box is extended past it.
        lo_b, hi_b = bmin[b], bmax[b]
        z_lo, z_hi = np.minimum(p[r, 2], s[r, 2]), np.maximum(p[r, 2], s[r, 2])
        lo_b = np.concatenate((lo_b[:, :2], np.where(lo_b[:, 2] <= z_lo, z_lo - _NO_EXIT_M, lo_b[:, 2])[:, None]), axis=1)
        hi_b = np.concatenate((hi_b[:, :2], np.where(hi_b[:, 2] >= z_hi, z_hi + _NO_EXIT_M, hi_b[:, 2])[:, None]), axis=1)
        c[r, b], g[r, b] = _link_sdf_pairs(p[r], s[r], lo_b, hi_b, samples)
    return c.reshape(shape[:-1] + (nb,)), g.reshape(shape[:-1] + (nb, 3))


def _link_sdf_pairs(p: FloatArray, s: FloatArray, bmin: FloatArray, bmax: FloatArray, samples: int) -> tuple[FloatArray, FloatArray]:
    """Sampled clearance (K,) and its gradient (K, 3) of links s → p from one box each, all (K, 3).

    The signed distance and its gradient are :func:`distance_to_boxes_with_gradient`'s, written
    for one box per link and axis by axis: called on the simulator's 1000 links × 16 points a
    step, that function took 6 ms, this form 0.5 ms (with the cutoff of the caller)."""
    t = np.arange(1, samples + 1, dtype=float) / samples
    # One (K, samples) array per axis: reductions over a length-3 last axis are slow in numpy.
    below, above, e = [], [], []
    for a in range(3):
        x = s[:, a, None] + t * (p[:, a] - s[:, a])[:, None]  # (K, S)
        lo, hi = bmin[:, a, None] - x, x - bmax[:, a, None]  # > 0: below / above the box on this axis
        below.append(lo)
        above.append(hi)
        e.append(np.maximum(lo, hi))  # > 0 outside by e, ≤ 0 inside by |e|
    ep = [np.maximum(ea, 0.0) for ea in e]
    out = np.sqrt(ep[0] * ep[0] + ep[1] * ep[1] + ep[2] * ep[2])
    sdf = out + np.minimum(np.maximum(np.maximum(e[0], e[1]), e[2]), 0.0)  # signed distance to a box
    k = sdf.argmin(1)  # the sample nearest the box
    rows = np.arange(p.shape[0])
    clearance = sdf[rows, k]
    e_sel = np.stack([ea[rows, k] for ea in e], -1)  # (K, 3)
    # Nearer the lower face on an axis: that axis's outward direction is −.
    sign = np.stack([np.where(below[a][rows, k] >= above[a][rows, k], -1.0, 1.0) for a in range(3)], -1)
    out_sel = out[rows, k]
    inside = out_sel <= 0.0
    unit_out = np.maximum(e_sel, 0.0) / np.where(inside, 1.0, out_sel)[:, None]
    grad = sign * unit_out
    if inside.any():
        grad[inside] = _crossing_exit(p[inside], s[inside], bmin[inside], bmax[inside])
    return clearance, grad * t[k][:, None]


def _crossing_exit(p: FloatArray, s: FloatArray, bmin: FloatArray, bmax: FloatArray) -> FloatArray:
    """Unit direction (K, 3) in which drones p move links s → p that cross one box each out of it.

    For each face, the drone's displacement along the face's normal that takes the part of the
    segment inside the box, x(t) = s + t (p − s) for t in [t_in, t_out] (slab test), past that
    face: max over t of (face − x(t))/t, found at t_in or t_out as it is monotone in t. The face
    with the smallest displacement is the way out. (The deepest point's nearest face, the
    sdf's gradient, can be a face the link runs through, the building's back, which no lateral
    move clears.)"""
    d = p - s
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (bmin - s) / d, (bmax - s) / d
    inside_slab = (s >= bmin) & (s <= bmax)
    t_lo = np.where(d == 0.0, np.where(inside_slab, -np.inf, np.inf), np.minimum(t1, t2))
    t_hi = np.where(d == 0.0, np.where(inside_slab, np.inf, -np.inf), np.maximum(t1, t2))
    t_in = np.clip(t_lo.max(-1), 1e-6, 1.0)
    t_out = np.clip(t_hi.min(-1), t_in, 1.0)
    ends = np.stack((t_in, t_out), -1)[:, None, :]  # (K, 1, 2)
    x = s[:, :, None] + ends * d[:, :, None]  # (K, 3, 2)
    up = ((bmax[:, :, None] - x) / ends).max(-1)  # (K, 3): displacement past the upper face
    down = ((x - bmin[:, :, None]) / ends).max(-1)  # past the lower face
    move = np.concatenate((up, down), -1)  # (K, 6)
    best = move.argmin(-1)
    out = np.zeros(p.shape)
    out[np.arange(p.shape[0]), best % 3] = np.where(best < 3, 1.0, -1.0)
    return out
