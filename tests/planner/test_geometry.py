"""Geometry against brute force: direct trigonometry, dense sampling of segments and box surfaces,
finite differences."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from planner import distance_to_boxes, distance_to_boxes_with_gradient, line_of_sight, ranges_angles
from planner.geometry import points_inside_boxes


def random_boxes(rng: np.random.Generator, b: int, lo: float = -20.0, hi: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    bmin = rng.uniform(lo, hi, (b, 3))
    return bmin, bmin + rng.uniform(1.0, 15.0, (b, 3))


def inside_any(points: np.ndarray, bmin: np.ndarray, bmax: np.ndarray) -> np.ndarray:
    """Closed-box membership by plain comparisons, (..., 3) -> (...)."""
    p = points[..., None, :]
    return ((p >= bmin) & (p <= bmax)).all(-1).any(-1)


def outside_distance(points: np.ndarray, bmin: np.ndarray, bmax: np.ndarray) -> np.ndarray:
    """Euclidean distance from points to the closed boxes (0 inside), by per-axis gaps."""
    p = points[..., None, :]
    gap = np.maximum(np.maximum(bmin - p, p - bmax), 0.0)
    return np.sqrt((gap**2).sum(-1)).min(-1)


# ---------------------------------------------------------------- ranges and angles


def test_ranges_angles_vs_direct_trig(rng):
    src = rng.uniform(-100, 100, (4, 3))
    pos = rng.uniform(-300, 300, (4, 25, 3))
    d, phi, theta = ranges_angles(src, pos)
    assert d.shape == phi.shape == theta.shape == (4, 25)
    for t in range(4):
        for j in range(25):
            rx, ry, rz = (src[t] - pos[t, j]).tolist()
            dist = math.sqrt(rx * rx + ry * ry + rz * rz)
            assert d[t, j] == pytest.approx(dist, rel=1e-14)
            # φ: the angle east->north of the horizontal projection; θ: asin of the vertical part.
            assert math.cos(phi[t, j]) * math.hypot(rx, ry) == pytest.approx(rx, abs=1e-9)
            assert math.sin(phi[t, j]) * math.hypot(rx, ry) == pytest.approx(ry, abs=1e-9)
            assert -math.pi < phi[t, j] <= math.pi
            assert theta[t, j] == pytest.approx(math.asin(rz / dist), abs=1e-12)
            # Unit vector a(φ, θ) of eq. 12 points from the drone to the source.
            a = np.array([math.cos(phi[t, j]) * math.cos(theta[t, j]), math.sin(phi[t, j]) * math.cos(theta[t, j]), math.sin(theta[t, j])])
            np.testing.assert_allclose(pos[t, j] + d[t, j] * a, src[t], atol=1e-9)


def test_ranges_angles_axes():
    d, phi, theta = ranges_angles([0.0, 0.0, 0.0], [[-1.0, 0.0, 0.0], [0.0, -2.0, 0.0], [0.0, 0.0, -3.0], [1.0, 0.0, 0.0]])
    np.testing.assert_allclose(d, [1, 2, 3, 1])
    np.testing.assert_allclose(phi[[0, 1, 3]], [0.0, math.pi / 2, math.pi])
    np.testing.assert_allclose(theta, [0.0, 0.0, math.pi / 2, 0.0])


# ---------------------------------------------------------------- line of sight


def brute_force_los(p: np.ndarray, s: np.ndarray, bmin: np.ndarray, bmax: np.ndarray, samples: int = 4001) -> tuple[bool, float]:
    """(blocked by a sample, min distance of the samples to the boxes) along the closed segment."""
    if bmin.shape[0] == 0:
        return False, math.inf
    t = np.linspace(0.0, 1.0, samples)[:, None]
    pts = p + t * (s - p)
    return bool(inside_any(pts, bmin, bmax).any()), float(outside_distance(pts, bmin, bmax).min())


@settings(max_examples=250, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), nboxes=st.integers(0, 4), n=st.integers(1, 6))
def test_line_of_sight_vs_dense_sampling(seed, nboxes, n):
    rng = np.random.default_rng(seed)
    bmin, bmax = random_boxes(rng, nboxes, -15.0, 10.0)
    src = rng.uniform(-25, 25, 3)
    pos = rng.uniform(-25, 25, (n, 3))
    # Some drones exactly on a face of a box (a drone on a roof or against a wall).
    if nboxes:
        on_face = rng.random(n) < 0.2
        k = rng.integers(0, 3, n)
        b = rng.integers(0, nboxes, n)
        corner = np.where(rng.random(n) < 0.5, bmin[b, k], bmax[b, k])
        face = rng.uniform(bmin[b], bmax[b])
        face[np.arange(n), k] = corner
        pos = np.where(on_face[:, None], face, pos)
    los = line_of_sight(pos, src, bmin, bmax)
    assert los.shape == (n,)
    for j in range(n):
        seg = np.linalg.norm(src - pos[j])
        blocked, min_dist = brute_force_los(pos[j], src, bmin, bmax)
        if blocked:
            assert not los[j]
        elif min_dist > seg / 4000.0:  # the samples are that dense: the segment misses the boxes
            assert los[j]


def test_line_of_sight_batched(rng):
    bmin, bmax = random_boxes(rng, 3)
    src = rng.uniform(-40, 40, (5, 3))
    pos = rng.uniform(-40, 40, (5, 8, 3))
    batched = line_of_sight(pos, src, bmin, bmax)
    assert batched.shape == (5, 8)
    for t in range(5):
        np.testing.assert_array_equal(batched[t], line_of_sight(pos[t], src[t], bmin, bmax))
    assert line_of_sight(pos, src, np.zeros((0, 3)), np.zeros((0, 3))).all()


BOX = (np.array([[0.0, 0.0, 0.0]]), np.array([[1.0, 1.0, 1.0]]))


@pytest.mark.parametrize(
    "p, s, expected",
    [
        # Grazing: the segment lies in the top face, in a side face, along an edge.
        ([-1.0, 0.5, 1.0], [2.0, 0.5, 1.0], False),
        ([0.5, -1.0, 0.0], [0.5, 3.0, 0.0], False),
        ([-1.0, 0.0, 0.0], [2.0, 0.0, 0.0], False),
        # Touching one edge point / one corner only.
        ([-1.0, 1.0, 0.5], [1.0, -1.0, 0.5], False),
        ([-1.0, -1.0, -1.0], [0.0, 0.0, 0.0], False),
        # An endpoint on the surface (a drone sitting on a roof), or inside.
        ([0.5, 0.5, 1.0], [0.5, 0.5, 5.0], False),
        ([0.5, 0.5, 0.5], [5.0, 5.0, 5.0], False),
        # Just clear of a face, of an edge, of a corner; ending just short of a face.
        ([-1.0, 0.5, 1.0 + 1e-9], [2.0, 0.5, 1.0 + 1e-9], True),
        ([-1.0, 1.0 - 1e-9, 0.5], [1.0 - 1e-9, -1.0, 0.5], True),
        ([-1.0, -1.0, -1.0], [-1e-9, -1e-9, -1e-9], True),
        ([0.5, 0.5, 5.0], [0.5, 0.5, 1.0 + 1e-9], True),
        # Axis-parallel segments outside the slab, passing beside the box.
        ([-1.0, 2.0, 0.5], [3.0, 2.0, 0.5], True),
        ([0.5, 0.5, 3.0], [0.5, 0.5, 2.0], True),
        # Through the middle.
        ([-5.0, 0.5, 0.5], [5.0, 0.5, 0.5], False),
    ],
)
def test_line_of_sight_touching_cases(p, s, expected):
    assert bool(line_of_sight(np.array([p]), np.array(s), *BOX)[0]) is expected
    # The segment is symmetric: swapping drone and source gives the same answer.
    assert bool(line_of_sight(np.array([s]), np.array(p), *BOX)[0]) is expected


# ---------------------------------------------------------------- distance to boxes


def surface_samples(bmin: np.ndarray, bmax: np.ndarray, spacing: float) -> np.ndarray:
    """Points on the six faces of every box, on a grid of at most ``spacing``."""
    pts = []
    for lo, hi in zip(bmin, bmax):
        axes = [np.linspace(lo[k], hi[k], max(2, int(math.ceil((hi[k] - lo[k]) / spacing)) + 1)) for k in range(3)]
        for k in range(3):
            a, b = [axes[m] for m in range(3) if m != k]
            A, B = np.meshgrid(a, b, indexing="ij")
            for v in (lo[k], hi[k]):
                face = np.empty(A.shape + (3,))
                others = [m for m in range(3) if m != k]
                face[..., others[0]] = A
                face[..., others[1]] = B
                face[..., k] = v
                pts.append(face.reshape(-1, 3))
    return np.concatenate(pts)


def test_distance_to_boxes_vs_surface_sampling(rng):
    spacing = 0.25
    for _ in range(6):
        bmin, bmax = random_boxes(rng, int(rng.integers(1, 4)))
        surf = surface_samples(bmin, bmax, spacing)
        pts = rng.uniform(-30, 40, (300, 3))
        sd = distance_to_boxes(pts, bmin, bmax)
        assert sd.shape == (300,)
        inside = inside_any(pts, bmin, bmax)
        nearest = np.sqrt(((pts[:, None, :] - surf[None]) ** 2).sum(-1)).min(-1)
        # |sd| is the distance to the nearest surface: the samples overestimate it by at most
        # half a grid diagonal, never underestimate it.
        half_diag = spacing * math.sqrt(2.0) / 2.0
        assert (np.abs(sd) <= nearest + 1e-9).all()
        assert (np.abs(sd) >= nearest - half_diag - 1e-9).all()
        # Sign: negative strictly inside, positive outside.
        assert (sd[inside] <= 0.0).all() and (sd[~inside] > 0.0).all()
        np.testing.assert_array_equal(points_inside_boxes(pts, bmin, bmax), inside)
        # Outside, it is the exact Euclidean distance to the union of boxes.
        np.testing.assert_allclose(sd[~inside], outside_distance(pts[~inside], bmin, bmax), rtol=1e-12)


def test_distance_to_boxes_no_obstacle_and_batched(rng):
    pts = rng.uniform(-10, 10, (4, 5, 3))
    assert (distance_to_boxes(pts, np.zeros((0, 3)), np.zeros((0, 3))) == np.inf).all()
    d, g = distance_to_boxes_with_gradient(pts, np.zeros((0, 3)), np.zeros((0, 3)))
    assert (d == np.inf).all() and not g.any()
    bmin, bmax = random_boxes(rng, 2, -5, 5)
    d, g = distance_to_boxes_with_gradient(pts, bmin, bmax)
    assert d.shape == (4, 5) and g.shape == (4, 5, 3)
    np.testing.assert_allclose(d, distance_to_boxes(pts, bmin, bmax))
    np.testing.assert_allclose(d[2, 3], distance_to_boxes(pts[2, 3], bmin, bmax))


@settings(max_examples=250, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), nboxes=st.integers(1, 3))
def test_distance_gradient_vs_finite_differences(seed, nboxes):
    rng = np.random.default_rng(seed)
    bmin, bmax = random_boxes(rng, nboxes, -10, 10)
    p = rng.uniform(-20, 30, 3)
    d, g = distance_to_boxes_with_gradient(p, bmin, bmax)
    # Away from the non-smooth set: equidistant from two boxes, or (inside) from two faces.
    per_box_out = np.sqrt((np.maximum(np.maximum(bmin - p, p - bmax), 0.0) ** 2).sum(-1))
    faces = np.concatenate([p - bmin, bmax - p], axis=-1)  # (B, 6), all > 0 inside a box
    per_box = np.where(per_box_out > 0, per_box_out, -faces.min(-1))
    order = np.sort(per_box)
    assume(nboxes == 1 or order[1] - order[0] > 1e-3)
    assume(abs(d) > 1e-3)
    if d < 0:
        f = np.sort(faces[per_box.argmin()])
        assume(f[1] - f[0] > 1e-3)
    h = 1e-6
    fd = np.array([(distance_to_boxes(p + h * e, bmin, bmax) - distance_to_boxes(p - h * e, bmin, bmax)) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(g, fd, atol=1e-6)
    assert np.linalg.norm(g) == pytest.approx(1.0, abs=1e-12)
