"""Hard cases: each gives no NaN/inf in t (on hits), normal or uv, and the right hit or miss."""

from __future__ import annotations

import numpy as np
import pytest

from conftest import build_skeleton, cast

from jskel import frusta


def _finite(hit):
    h = np.isfinite(hit.t)
    assert not np.any(np.isnan(hit.t))
    assert np.all(np.isfinite(hit.normal)) and np.all(np.isfinite(hit.uv))
    assert np.allclose(np.linalg.norm(hit.normal[h], axis=1), 1.0, atol=1e-4)
    return h


CYL = ([[0, 0, 0], [0, 2, 0]], [0.5, 0.5], [-1, 0])


@pytest.mark.parametrize("radii", [(0.5, 0.5), (0.5, 0.3), (0.5, 0.5 + 1e-7)])
def test_ray_along_axis_through_both_caps(radii):
    b = build_skeleton(CYL[0], radii, CYL[2])
    O = np.array([[0, -3.0, 0], [0, 5.0, 0], [0, 1.0, 0]])  # below, above, inside
    D = np.array([[0, 1.0, 0], [0, -1.0, 0], [0, 1.0, 0]])
    hit = cast(b, O, D)
    _finite(hit)
    np.testing.assert_allclose(hit.t[:2], [3.0, 3.0], atol=1e-5)  # bottom cap at y=0, top cap at y=2
    np.testing.assert_allclose(hit.normal[0], [0, -1, 0], atol=1e-6)
    np.testing.assert_allclose(hit.normal[1], [0, 1, 0], atol=1e-6)
    np.testing.assert_allclose(hit.t[2], 1.0, atol=1e-5)  # from inside: the top cap from below
    assert np.all(hit.prim == 0)


def test_closed_tip_hit_at_apex_and_no_nan():
    b = build_skeleton([[0, 0, 0], [0, 2, 0]], [0.5, 0.0], [-1, 0])
    O = np.array([[0, 5.0, 0], [1.0, 2.0, 0.0], [0.0, 1.0, 3.0]])
    D = np.array([[0, -1.0, 0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
    hit = cast(b, O, D)
    h = _finite(hit)
    # along the axis from above: the apex at y = 2 (t = 3); sideways at the apex height grazes the tip
    np.testing.assert_allclose(hit.t[0], 3.0, atol=1e-4)
    # at y = 1 the radius is 0.25: enters at z = 0.25
    np.testing.assert_allclose(hit.t[2], 3.0 - 0.25, atol=1e-5)
    assert h[0] and h[2]


@pytest.mark.parametrize("radii", [(0.5, 0.5), (0.6, 0.3)])
def test_rays_tangent_to_the_side(radii):
    """Rays along x at the silhouette distance, just inside it and just outside it."""
    b = build_skeleton(CYL[0], radii, CYL[2])
    y = 1.0
    r = radii[0] + (radii[1] - radii[0]) * y / 2.0
    zs = np.array([r, r * (1 - 1e-3), r * (1 + 1e-3)])
    O = np.stack([np.full(3, -4.0), np.full(3, y), zs], 1)
    D = np.tile([1.0, 0, 0], (3, 1))
    hit = cast(b, O, D)
    h = _finite(hit)
    assert h[1] and not h[2]
    x_in = np.sqrt(r * r - zs[1] ** 2)
    np.testing.assert_allclose(hit.t[1], 4.0 - x_in, atol=1e-3)
    if h[0]:  # the exact tangent may round either way, but if hit, at the tangent point
        np.testing.assert_allclose(hit.t[0], 4.0, atol=2e-3)


def test_rays_parallel_to_a_cutting_plane():
    """Rays in and next to the plane of a cap and of an oblique joint plane."""
    joints = np.array([[0, 0, 0], [0, 1, 0], [1, 2, 0]], float)
    b = build_skeleton(joints, [0.4, 0.4, 0.4], [-1, 0, 1])
    O = np.array([[-3, 1e-4, 0.1], [-3, -1e-4, 0.1], [-3, 0.0, 0.1]])
    D = np.tile([1.0, 0, 0], (3, 1))
    hit = cast(b, O, D)
    h = _finite(hit)
    assert h[0] and not h[1]
    np.testing.assert_allclose(hit.t[0], 3.0 - np.sqrt(0.4**2 - 0.1**2), atol=1e-4)
    # the joint plane at (0,1,0) between the two segments: its in-plane direction and normal
    n = (np.array([0, 1.0, 0]) + np.array([1.0, 1.0, 0]) / np.sqrt(2))
    n /= np.linalg.norm(n)
    along = np.cross(n, [0, 0, 1.0])
    O2 = np.array([[0, 1.0, 0] - 3 * along + [0, 0, 0.05]])
    hit2 = cast(b, O2, along[None, :])
    h2 = _finite(hit2)
    assert h2[0]  # a ray inside the joint plane through the solid hits the side
    np.testing.assert_allclose(np.linalg.norm(O2[0] + hit2.t[0] * along - [0, 1, 0] - [0, 0, 0.05]), 3.0 - hit2.t[0], atol=1e-5)


def test_bend_of_170_degrees_is_finite():
    """A joint that folds back by 170 degrees still yields finite hits on both segments."""
    a = np.radians(170)
    joints = np.array([[0, 0, 0], [0, 2, 0], [2 * np.sin(a), 2 + 2 * np.cos(a), 0]])
    b = build_skeleton(joints, [0.2, 0.2, 0.2], [-1, 0, 1])
    rng = np.random.default_rng(0)
    O = np.stack([rng.uniform(-1, 1, 4000), rng.uniform(-0.5, 2.5, 4000), np.full(4000, 5.0)], 1)
    D = np.tile([0, 0, -1.0], (4000, 1))
    hit = cast(b, O, D)
    h = _finite(hit)
    assert set(np.unique(hit.prim[h])) == {0, 1}
    assert np.all(hit.t[h] > 4.0) & np.all(hit.t[h] < 5.2)


def test_fold_back_beyond_limit_is_rejected():
    a = np.radians(179.5)
    joints = np.array([[0, 0, 0], [0, 2, 0], [2 * np.sin(a), 2 + 2 * np.cos(a), 0]])
    with pytest.raises(ValueError, match=r"joints\[1\]: folds back by more than 179 degrees \(got 179\.5 degrees"):  # at validation
        build_skeleton(joints, [0.2, 0.2, 0.2], [-1, 0, 1])


def test_t_min_t_max_interval_is_half_open():
    b = build_skeleton(CYL[0], (0.5, 0.5), CYL[2])
    O = np.tile([-3.0, 1.0, 0.0], (4, 1))
    D = np.tile([1.0, 0, 0], (4, 1))
    # entry at t = 2.5, exit at t = 3.5
    hit = cast(b, O, D, t_min=np.array([0.0, 2.5, 3.0, 0.0]), t_max=np.array([np.inf, np.inf, np.inf, 2.5]))
    np.testing.assert_allclose(hit.t[:3], [2.5, 3.5, 3.5], atol=1e-5)
    np.testing.assert_allclose(hit.t[3], 2.5, atol=1e-5)  # t == t_max is included


def test_closed_tip_normals_are_the_cone_normal_whatever_the_program():
    """On a cone closed at its top (r2 = 0) Eq. 8's N_u = P_u - C2 is zero up to rounding at
    every point; normalising that noise once gave normals in any direction, of length up to
    1.7, that changed between the jitted and eager programs (test_frusta_random's closed tip
    passed by luck). Every side hit's normal must be the cone's own unit normal, computed here
    in float64, in one chunk and one ray at a time alike."""
    c1, c2, r1 = np.array([0.0, 0.0, 0.0]), np.array([0.3, 2.0, 0.1]), 0.8
    b = build_skeleton([c1, c2], [r1, 0.0], [-1, 0])
    rng = np.random.default_rng(3)
    O = rng.uniform(-3, 3, (4000, 3)) + np.array([0.0, 1.0, 0.0])
    O *= 3.0 / np.linalg.norm(O - [0.15, 1.0, 0.05], axis=1, keepdims=True)
    D = np.array([0.15, 1.0, 0.05]) + rng.uniform(-0.4, 0.4, (4000, 3)) - O
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    hit = cast(b, O, D)
    h = np.isfinite(hit.t)
    P = hit.position[h]
    h_len = np.linalg.norm(c2 - c1)
    m = (c2 - c1) / h_len
    y = (P - c1) @ m
    side = (y > 1e-3) & (y < h_len - 1e-3)  # not the bottom cap, not the apex itself
    assert side.sum() > 500
    radial = (P - c1) - y[:, None] * m
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    k = -r1 / h_len  # dr/dy
    true_n = radial - k * m
    true_n /= np.linalg.norm(true_n, axis=1, keepdims=True)
    n = hit.normal[h][side]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert np.degrees(np.arccos(np.clip(np.sum(n * true_n[side], 1), -1, 1))).max() < 0.05
    # three rays op by op, outside jit: other rounding of the zero N_u, the same normals
    from jskel.rays import make_rays

    idx = np.nonzero(h)[0][side][:3]
    eager = frusta.intersect(b.params, b.static, make_rays(O[idx] - b.anchor, D[idx]))
    np.testing.assert_allclose(np.asarray(eager.normal), hit.normal[idx], atol=1e-5)
