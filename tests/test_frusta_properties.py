"""Consistency (jit/eager, vmap/loop, chunked/whole, culled/brute force) and surface properties."""

from __future__ import annotations

import jax
import numpy as np

import reference as ref
from conftest import build_skeleton, cast
from jskel import frusta
from jskel.rays import make_rays
from jskel.executor import map_chunks
from test_frusta_random import CASES, _bounds


def _rays(name, n, seed=0):
    joints, radii, parents = CASES[name]
    lo, hi = _bounds(joints, np.asarray(radii))
    return ref.random_rays(np.random.default_rng(seed), lo, hi, n)


def test_jit_vmap_chunked_and_culled_agree():
    joints, radii, parents = CASES["branching"]
    b = build_skeleton(joints, radii, parents)
    O, D = _rays("branching", 20_000)
    whole = cast(b, O, D)  # vmap(intersect_one), chunks of 8192
    culled = cast(b, O, D, culled=True)  # block-skipping batch path
    for a, c in zip(whole, culled):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(c))
    # one call on all rays (no chunking) equals the chunked result
    rays = make_rays(O - b.anchor, D)
    one = jax.jit(lambda p, r: frusta.intersect(p, b.static, r))(b.params, rays)
    np.testing.assert_array_equal(np.asarray(one.prim), whole.prim)
    np.testing.assert_allclose(np.asarray(one.t), whole.t, rtol=1e-6)
    # eager single rays and a Python loop equal the vmapped batch
    for i in range(5):
        h = frusta.intersect_one(b.params, b.static, rays.origins[i], rays.directions[i], rays.t_min[i], rays.t_max[i])
        assert int(h.prim) == whole.prim[i]
        np.testing.assert_allclose(float(h.t), whole.t[i], rtol=1e-6)
        np.testing.assert_allclose(np.asarray(h.normal), whole.normal[i], atol=1e-5)


def test_no_recompile_when_values_change():
    joints, radii, parents = CASES["bent_chain"]
    b1 = build_skeleton(joints, radii, parents)
    b2 = build_skeleton(joints * 1.1, np.asarray(radii) * 0.9, parents)
    O, D = _rays("bent_chain", 100)
    from conftest import batch_fn, frusta_object

    fn = batch_fn(False)
    map_chunks(fn, frusta_object(b1), make_rays(O, D), chunk=8192)
    r2 = map_chunks(fn, frusta_object(b2), make_rays(O + 1.0, D), chunk=8192)
    assert r2.compile_s == 0.0


def test_u_aligned_and_normals_continuous_across_joints():
    """Sec. 2.3-2.4 across every joint of a bent chain, with and without a twist.

    Rays hit just below and just above each cutting plane along generators of the upper
    frustum. At the angle of the lower frustum's u = 0 generator (the paper aligns exactly that
    point) u agrees; elsewhere the two parametrizations of the seam differ by a bounded amount.
    The interpolated normals (Eq. 8) agree at every angle (C0 continuity).
    """
    joints, radii, parents = CASES["bent_chain"]
    n_ang = 12
    for twist in (0.0, 90.0):
        b = build_skeleton(joints, radii, parents, twist_deg=twist)
        arr, topo, _ = frusta.frusta_from_skeleton(joints, radii, parents, twist_deg=twist)
        O, D = [], []
        for s in np.nonzero(topo.parent_seg >= 0)[0]:
            k = (arr.r2[s] - arr.r1[s]) / arr.h[s]
            for ang in np.linspace(0, 2 * np.pi, n_ang, endpoint=False):
                radial = np.sin(ang) * arr.u[s] + np.cos(ang) * arr.w[s]
                base = arr.c1[s] + arr.r1[s] * radial
                dirn = arr.m[s] + k * radial
                y0 = (arr.db[s] - arr.nb[s] @ (base - arr.c1[s])) / (arr.nb[s] @ dirn)
                for eps in (-2e-3, 2e-3):
                    target = base + (y0 + eps) * dirn
                    O.append(target + radial * 2.0)
                    D.append(-radial)
        O, D = np.array(O), np.array(D)
        hit = cast(b, O, D)
        assert np.all(np.isfinite(hit.t))
        assert np.all(hit.prim[0::2] != hit.prim[1::2])  # each pair straddles the seam
        du = np.abs(hit.uv[0::2, 0] - hit.uv[1::2, 0])
        du = np.minimum(du, 1 - du).reshape(-1, n_ang)
        assert du[:, 0].max() < 2e-3, du[:, 0]
        assert du.max() < 0.05
        cosang = np.sum(hit.normal[0::2] * hit.normal[1::2], 1)
        assert cosang.min() > 0.99


def test_geometric_normals_match_cone_gradient(rng):
    joints, radii, parents = CASES["single_cone"]
    b = build_skeleton(joints, radii, parents, normals="geometric")
    O, D = _rays("single_cone", 3000)
    hit = cast(b, O, D)
    h = np.isfinite(hit.t)
    c1, c2 = np.asarray(joints[0]), np.asarray(joints[1])
    m = (c2 - c1) / np.linalg.norm(c2 - c1)
    k = (radii[1] - radii[0]) / np.linalg.norm(c2 - c1)
    L = hit.position[h] - c1
    y = L @ m
    radial = L - y[:, None] * m
    rho = np.linalg.norm(radial, axis=1)
    side = np.abs(rho - (radii[0] + k * y)) < 1e-4
    g = radial[side] / rho[side, None] - k * m  # gradient of rho - r(y), independent of jskel
    g /= np.linalg.norm(g, axis=1, keepdims=True)
    np.testing.assert_allclose(hit.normal[h][side], g, atol=1e-4)
    assert side.sum() > 300


def test_uv_follows_eq_6_7_on_a_cylinder():
    """On a straight cylinder with perpendicular caps v is the height fraction and u the angle."""
    b = build_skeleton([[0, 0, 0], [0, 2, 0]], [0.5, 0.5], [-1, 0])
    ys = np.linspace(0.1, 1.9, 7)
    angs = np.linspace(0.1, 6.0, 7)
    O = np.stack([3 * np.sin(angs), ys, 3 * np.cos(angs)], 1)
    D = -np.stack([np.sin(angs), np.zeros(7), np.cos(angs)], 1)
    hit = cast(b, O, D)
    np.testing.assert_allclose(hit.uv[:, 1], ys / 2.0, atol=1e-5)
    du = np.diff(hit.uv[:, 0])
    np.testing.assert_allclose(np.mod(du, 1.0), np.diff(angs) / (2 * np.pi), atol=1e-5)


def test_minor_axis_matching_converges():
    """Sec. 2.2: after matching, both elliptical cuts have the same minor axis (checked here by
    sampling each cone's cut independently of jskel)."""
    joints, radii, parents = CASES["bent_chain"]
    arr0, topo, info0 = frusta.frusta_from_skeleton(joints, radii, parents)
    arr, topo, info = frusta.frusta_from_skeleton(joints, radii, parents, match_minor_axes=True)
    assert info["minor_axis_mismatch"] <= 1e-10
    assert 0 < info["minor_axis_iterations"] < 100

    def minor(c1, m, r1, r2, h, n, d, nm):
        # sample the cut curve of the cone by generators, measure its width along nm
        x = np.cross(m, nm)
        angs = np.linspace(0, 2 * np.pi, 20001)
        radial = np.cos(angs)[:, None] * x + np.sin(angs)[:, None] * nm
        k = (r2 - r1) / h
        base = c1 + r1 * radial
        dirn = m + k * radial
        y = (d - (base - c1) @ n) / (dirn @ n)
        pts = base + y[:, None] * dirn
        w = pts @ nm
        return 0.5 * (w.max() - w.min())

    def mismatch(a):
        out = []
        for s in np.nonzero(topo.parent_seg >= 0)[0]:
            p = topo.parent_seg[s]
            nm = np.cross(a.m[p], a.m[s])
            nm /= np.linalg.norm(nm)
            bp = minor(a.c1[p], a.m[p], a.r1[p], a.r2[p], a.h[p], a.nt[p], a.dt[p], nm)
            bs = minor(a.c1[s], a.m[s], a.r1[s], a.r2[s], a.h[s], a.nb[s], a.db[s], nm)
            out.append(abs(bp - bs) / bp)
        return max(out)

    assert mismatch(arr0) > 1e-3  # the unmatched chain really is misaligned
    assert mismatch(arr) < 1e-6
