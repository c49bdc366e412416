"""The fit's term from the surface back to the points (``solver.cover``, issue 53): its samples lie
on each segment's cone where the docstring puts them, its nearest-point search finds what brute
force finds, and its residuals are the distance from a swollen tube's surface to the points of
the true one (closed form). That the sparse normal equations carry its rows as the dense
Jacobian does is asserted in ``test_fit_normal``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jskel.fit import segments_of
from jskel.fit._config import SolverConfig
from jskel.fit._cover import AROUND, AXIAL, SAMPLES, nearest_points, point_index, samples
from jskel.fit._distance import geometry
from jskel.fit._fit import data_of, on_device
from jskel.fit._problem import problem_of, residuals


def test_samples_lie_on_each_cone_at_their_rings():
    """Three segments of a bent, tapering chain: every sample's axial coordinate is u h and its
    distance from the axis r1 + u (r2 - r1) (float64 NumPy), and each ring's samples are evenly
    spread around the axis, the second ring turned half a step."""
    j = np.array([[0.0, 0.0, 0.0], [0.3, 1.0, 0.1], [1.2, 1.5, -0.4], [1.4, 1.6, 0.9]])
    r = np.array([0.3, 0.2, 0.25, 0.05])
    p = np.array([-1, 0, 1, 2])
    g = geometry(jnp.asarray(j, jnp.float32), jnp.asarray(r, jnp.float32), segments_of(j, r, p))
    xs = np.asarray(jax.jit(samples)(g), np.float64)
    assert xs.shape == (3, SAMPLES, 3)
    for s in range(3):
        a, b = j[s], j[s + 1]
        h = np.linalg.norm(b - a)
        m = (b - a) / h
        q = xs[s] - a
        y = q @ m
        radial = q - y[:, None] * m
        rho = np.linalg.norm(radial, axis=1)
        for i, u in enumerate(AXIAL):
            ring = slice(i * AROUND, (i + 1) * AROUND)
            np.testing.assert_allclose(y[ring], u * h, atol=1e-5)
            np.testing.assert_allclose(rho[ring], r[s] + u * (r[s + 1] - r[s]), atol=1e-5)
        unit = radial / rho[:, None]
        step = np.cos(2 * np.pi / AROUND)
        for i in range(len(AXIAL)):
            ring = unit[i * AROUND : (i + 1) * AROUND]
            np.testing.assert_allclose(np.sum(ring * np.roll(ring, -1, 0), 1), step, atol=1e-5)
        np.testing.assert_allclose(unit[0] @ unit[AROUND], np.cos(np.pi / AROUND), atol=1e-5)


def test_nearest_points_match_brute_force():
    """2,000 points on a noisy torus. Queries near its surface and far from it, each a group of
    its own, and the cover samples of a chain of 23 segments around the torus' core circle with
    radius 0.3 (so on the torus, within its noise and the chords' sag), in their groups of 16
    (one segment's, sharing a list of blocks). The point found is a point of the cloud, never
    nearer than the true nearest (float64 brute force), and is the nearest for every query within
    a point spacing of the surface and for every sample."""
    rng = np.random.default_rng(4)
    u, v = rng.uniform(0, 2 * np.pi, (2, 2000))
    pts = np.stack([(1 + 0.3 * np.cos(v)) * np.cos(u), (1 + 0.3 * np.cos(v)) * np.sin(u), 0.3 * np.sin(v)], 1)
    pts += rng.normal(0, 0.005, pts.shape)
    near_q = pts[rng.choice(2000, 300)] + rng.normal(0, 0.02, (300, 3))
    far_q = rng.uniform(-1.6, 1.6, (100, 3))
    a = np.linspace(0, 2 * np.pi, 25)[:24]
    j = np.stack([np.cos(a), np.sin(a), np.zeros(24)], 1)
    g = geometry(jnp.asarray(j, jnp.float32), jnp.full(24, 0.3, jnp.float32), segments_of(j, np.full(24, 0.3), np.arange(-1, 23)))
    ring = np.asarray(jax.jit(samples)(g), np.float64)  # (23, 16, 3)
    idx = jax.tree_util.tree_map(jnp.asarray, point_index(pts.astype(np.float32)))
    find = jax.jit(nearest_points)

    def check(q, got, exact):
        got = np.asarray(got, np.float64)
        want = np.linalg.norm(q[:, None] - pts[None], axis=-1).min(1)
        d_got = np.linalg.norm(got - q, axis=1)
        assert np.all(np.min(np.linalg.norm(got[:, None] - pts[None], axis=-1), 1) < 1e-6)  # a point of the cloud
        assert np.all(d_got >= want - 1e-6)
        np.testing.assert_allclose(d_got[exact], want[exact], atol=1e-6)
        return want

    q = np.concatenate([near_q, far_q])
    want = check(q, find(idx, jnp.asarray(q[:, None], jnp.float32))[:, 0], np.arange(400) < 300)
    assert np.all(want[:300] < 0.08)  # the near queries are within a point spacing of the surface
    check(ring.reshape(-1, 3), find(idx, jnp.asarray(ring, jnp.float32)).reshape(-1, 3), np.ones(len(ring) * SAMPLES, bool))


def test_cover_rows_are_the_distance_from_a_swollen_tube_to_the_true_one():
    """Points dense on a straight tube of radius 0.3 (length 2); the skeleton on its axis, two
    segments, with radius 0.6. Each sample's residual is sqrt(w) (w = cover N / (S M), S = 2)
    times the l2 distance to its nearest point, 0.3 (its ring lies 0.3 outside the points'
    circle of the same height), less the dead zone (twice the points' median spacing, NumPy
    here), within the points' spacing; at the true radius it is within that spacing of 0."""
    rng = np.random.default_rng(5)
    n = 6000
    t, a = rng.uniform(0, 2, n), rng.uniform(0, 2 * np.pi, n)
    pts = np.stack([0.3 * np.cos(a), t, 0.3 * np.sin(a)], 1)
    j = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 2.0, 0.0]])
    p = np.array([-1, 0, 1])
    spacing = np.sqrt(2 * np.pi * 0.3 * 2 / n) * 2  # twice the mean spacing of the samples
    w = 0.7 * n / (2 * SAMPLES)  # cover 0.7, two segments
    seg = segments_of(j, np.full(3, 0.3), p)
    pr = problem_of(seg, SolverConfig(loss="l2", cover=0.7, candidates=0, validity=0.0))
    data = on_device(data_of(pts, pr, np.float32, seg))
    of = jax.jit(lambda x, d: residuals(x, d, pr))

    def rows(radius):
        # the radius parameter u gives min_radius + s softplus(u / s): radius itself for u = radius - min_radius
        x = np.concatenate([j.reshape(-1), [radius - pr.min_radius] * 3]).astype(np.float32)
        return np.asarray(of(jnp.asarray(x), data), np.float64)[n : n + 2 * SAMPLES] / np.sqrt(w)

    nn = np.sort(np.linalg.norm(pts[:1500, None] - pts[None], axis=-1), axis=1)[:, 1]  # nearest other point, 1,500 of them
    dead = 2.0 * float(np.median(nn))
    np.testing.assert_allclose(float(data.index.spacing), dead, rtol=0.1)
    np.testing.assert_allclose(rows(0.6), 0.3 - dead, atol=spacing)
    assert np.all(np.abs(rows(0.3)) < spacing)
    with pytest.raises(ValueError, match="solver.cover"):  # the points alone, without their index
        residuals(jnp.zeros(12), data._replace(index=None), pr)


def test_samples_of_a_segment_of_no_length_stay_finite_with_their_derivatives():
    """Two coincident joints (a fit can pass through one before an edit merges it): the samples
    sit on the ring's centre and their forward derivatives are finite, not NaN."""
    from jskel.fit._normal import geometry_of_flat

    row = jnp.asarray([0.5, 0.5, 0.5, 0.0, 0.0, 0.0, 0.0, 0.2, 0.1, 0, 0, 1, 0.0, 0, 0, 1, 0.0], jnp.float32)
    f = jax.jit(lambda r: samples(geometry_of_flat(r[None]))[0])
    xs, jac = f(row), jax.jit(jax.jacfwd(lambda r: samples(geometry_of_flat(r[None]))[0]))(row)
    np.testing.assert_array_equal(np.asarray(xs), np.full((SAMPLES, 3), 0.5, np.float32))
    assert np.all(np.isfinite(np.asarray(jac)))


def test_a_fit_with_cover_draws_a_tip_back_to_where_the_points_end():
    """Points on a tube of radius 0.3 from y = 0 to 1.5 only; the start, two segments on its
    axis, runs to y = 2. The points' own residuals leave the part beyond 1.5 where it is (no
    point is near it, nothing pulls it); with cover, its rings are pulled to the tube's last
    points, so the tip comes back towards y = 1.5 (each ring no further than its nearest points
    at equilibrium: the outer one, at three quarters of the second segment, ends near the rim
    at 1.5 give or take the dead zone of a few hundredths, so the tip lies near 1.5 + (2 - 1.5)
    / 3, well below 2). Through ``fit_points``, data built by ``data_of``; the radius stays the
    tube's."""
    from jskel.fit import fit_points

    rng = np.random.default_rng(6)
    n = 3000
    t, a = rng.uniform(0, 1.5, n), rng.uniform(0, 2 * np.pi, n)
    pts = np.stack([0.3 * np.cos(a), t, 0.3 * np.sin(a)], 1) + rng.normal(0, 0.005, (n, 3))
    j0 = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 2.0, 0.0]])
    res = fit_points(pts, j0, np.full(3, 0.3), np.array([-1, 0, 1]),
                     SolverConfig(name="lm", loss="huber", scale=0.005, maxiter=40, cover=1.0, validity=0.0))
    assert res.joints[2, 1] < 1.75
    np.testing.assert_allclose(res.radii[:2], 0.3, rtol=0.05)


def test_samples_inside_another_segment_do_not_count():
    """A T: a trunk of radius 0.5 along y (two segments, joint at y = 1) and a branch leaving
    that joint along x, 1 long, its cone from the joint's 0.5 down to 0.1. A sample counts where
    it is not inside the other part (NumPy: the trunk's cylinder for the branch's samples, the
    branch's cone for the trunk's, each by its perpendicular depth) by more than the scale:
    the branch's ring at a quarter of its length (radius 0.4, at most 0.47 from the trunk's
    axis) lies inside the trunk, as does the trunk's sample facing the branch beside the joint."""
    from jskel.fit._problem import _near_and_kept, layout_of

    j = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 2.0, 0.0], [1.0, 1.0, 0.0]])
    r = np.array([0.5, 0.5, 0.5, 0.1])
    p = np.array([-1, 0, 1, 1])
    seg = segments_of(j, r, p)
    scale = 0.01
    pr = problem_of(seg, SolverConfig(loss="l2", cover=1.0, candidates=0, scale=scale))
    pts = np.random.default_rng(0).normal(size=(64, 3))
    idx = jax.tree_util.tree_map(jnp.asarray, point_index(pts.astype(np.float32)))
    g = geometry(jnp.asarray(j, jnp.float32), jnp.asarray(r, jnp.float32), seg)
    lay = layout_of(seg, pr)
    xs, kept = jax.jit(lambda g, i, lay: (samples(g), _near_and_kept(g, i, pr, lay)[1]))(g, idx, lay)
    xs, kept = np.asarray(xs, np.float64), np.asarray(kept)
    branch = int(np.nonzero(np.asarray(seg.end) == 3)[0][0])
    depth = np.empty(kept.shape)
    for s in range(3):
        x = xs[s]
        if s == branch:  # inside the trunk's cylinder by
            depth[s] = 0.5 - np.hypot(x[:, 0], x[:, 2])
        else:  # inside the branch's cone by (its radius 0.5 - 0.4 x between x = 0 and 1)
            radius = 0.5 - 0.4 * x[:, 0]
            depth[s] = np.where((x[:, 0] > 0) & (x[:, 0] < 1), (radius - np.hypot(x[:, 1] - 1, x[:, 2])) / np.hypot(1, 0.4), -1.0)
    clear = np.abs(depth - scale) > scale  # not within a scale of the threshold
    assert clear.sum() > 40
    np.testing.assert_array_equal(kept[clear], (depth <= scale)[clear])
    assert not kept[branch, :AROUND].any() and kept[branch, AROUND:].all()
    assert (~kept[np.arange(3) != branch]).sum() >= 1  # the trunk's sample beside the joint
