"""Ray casting against an independent float64 reference over >= 100,000 random rays per case."""

from __future__ import annotations

import numpy as np
import pytest

import reference as ref
from conftest import build_skeleton, cast

N_RAYS = 100_000


def _rot(axis, ang):
    axis = np.asarray(axis, float) / np.linalg.norm(axis)
    K = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(ang) * K + (1 - np.cos(ang)) * K @ K


def _chain(bends_deg, lengths, radii):
    """A planar-ish chain turning by each bend in turn about a tilted axis."""
    pts = [np.zeros(3)]
    d = np.array([0.0, 1.0, 0.0])
    for i, L in enumerate(lengths):
        if i > 0:
            d = _rot([0.2, 0.1, 1.0] if i % 2 else [1.0, 0.3, 0.2], np.radians(bends_deg[i - 1])) @ d
        pts.append(pts[-1] + L * d)
    return np.array(pts), np.asarray(radii, float), np.arange(len(pts)) - 1


CASES = {
    "single_cone": (np.array([[0.1, -0.2, 0.3], [0.8, 1.7, -0.2]]), [1.0, 0.4], [-1, 0]),
    "closed_tip": (np.array([[0.0, 0.0, 0.0], [0.3, 2.0, 0.1]]), [0.8, 0.0], [-1, 0]),
    "near_cylinder": (np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]]), [0.5, 0.5 + 1e-7], [-1, 0]),
    "bent_chain": _chain([35, 60, 20], [1.0, 1.3, 0.8, 1.1], [0.5, 0.45, 0.35, 0.3, 0.2]),
    "cylinder_chain": _chain([40, 25, 50], [1.0, 1.0, 1.0, 1.0], [0.3] * 5),
    "collinear": (np.array([[0, 0, 0], [0, 1, 0], [0, 2.5, 0], [0, 3.0, 0]], float), [0.5, 0.6, 0.3, 0.35], [-1, 0, 1, 2]),
    "joint_170deg": _chain([10], [1.5, 1.5], [0.4, 0.4, 0.3]),
    "branching": (
        np.array([[0, 0, 0], [0, 1.5, 0], [0.2, 3.0, 0.1], [1.0, 2.4, 0.0], [-0.8, 2.3, -0.5]], float),
        [0.5, 0.4, 0.2, 0.15, 0.15],
        [-1, 0, 1, 1, 1],
    ),
}


def _bounds(joints, radii):
    r = np.max(radii)
    return joints.min(0) - r, joints.max(0) + r


@pytest.mark.parametrize("name", sorted(CASES))
def test_random_rays_match_reference(name, rng):
    joints, radii, parents = CASES[name]
    segs = ref.segments(joints, radii, parents)
    lo, hi = _bounds(joints, np.asarray(radii))
    scale = float(np.linalg.norm(hi - lo))
    O, D = ref.random_rays(rng, lo, hi, N_RAYS)
    t_ref, id_ref = ref.intersect(segs, O, D)
    far = ref.far_from_silhouette(segs, O, D, delta=1e-3 * scale, jump=2e-2 * scale)
    hit = cast(build_skeleton(joints, radii, parents), O, D)
    assert far.mean() > 0.9, f"too many rays near silhouettes: {far.mean():.3f}"
    hit_ref = np.isfinite(t_ref)
    assert 0.05 < hit_ref.mean() < 0.95  # both hits and misses are exercised
    agree = np.isfinite(hit.t) == hit_ref
    assert np.all(agree[far]), f"{np.sum(~agree[far])} of {far.sum()} rays disagree on hit/miss"
    both = far & hit_ref
    err = np.abs(hit.t[both] - t_ref[both])
    assert err.max() <= 1e-4 * scale, f"max |t - t_ref| = {err.max():.3g} (scale {scale:.3g})"
    assert np.all(hit.prim[both] >= 0)
    # no NaN anywhere, miss sentinels as documented
    for a in (hit.t, hit.normal, hit.uv):
        assert not np.any(np.isnan(a))
    miss = ~np.isfinite(hit.t)
    assert np.all(np.isposinf(hit.t[miss])) and np.all(hit.prim[miss] == -1)
    assert np.all(hit.normal[miss] == 0) and np.all(hit.uv[miss] == 0)
    n = np.linalg.norm(hit.normal[~miss], axis=1)
    assert np.allclose(n, 1.0, atol=1e-4)
    assert np.all((hit.uv[~miss] >= 0) & (hit.uv[~miss] <= 1))
    # hit positions lie on the rays
    P = O[both] + hit.t[both, None] * D[both]
    assert np.allclose(hit.position[both], P, atol=1e-4 * scale)


@pytest.mark.parametrize("scale", [1e-3, 1e3])
def test_segment_lengths_1e_3_and_1e3(scale, rng):
    joints, radii, parents = CASES["bent_chain"]
    segs = ref.segments(joints, radii, parents)
    lo, hi = _bounds(joints, np.asarray(radii))
    O, D = ref.random_rays(rng, lo, hi, 20_000)
    t_ref, _ = ref.intersect(segs, O, D)
    far = ref.far_from_silhouette(segs, O, D, 1e-3 * np.linalg.norm(hi - lo), 2e-2 * np.linalg.norm(hi - lo))
    hit = cast(build_skeleton(joints * scale, np.asarray(radii) * scale, parents), O * scale, D)
    assert np.all(np.isfinite(hit.t[far]) == np.isfinite(t_ref[far]))
    both = far & np.isfinite(t_ref)
    rel = np.abs(hit.t[both] / scale - t_ref[both]) / np.linalg.norm(hi - lo)
    assert rel.max() <= 1e-4


def test_offset_1e4_in_float32(rng):
    """A skeleton 1e4 from the origin casts like one at the origin (rays relative to the anchor)."""
    joints, radii, parents = CASES["bent_chain"]
    segs = ref.segments(joints, radii, parents)
    lo, hi = _bounds(joints, np.asarray(radii))
    scale = float(np.linalg.norm(hi - lo))
    O, D = ref.random_rays(rng, lo, hi, 20_000)
    t_ref, _ = ref.intersect(segs, O, D)
    far = ref.far_from_silhouette(segs, O, D, 1e-3 * scale, 2e-2 * scale)
    off = np.array([1e4, -1e4, 1e4])
    built = build_skeleton(joints, radii, parents, offset=off)
    hit = cast(built, O + off, D)
    assert np.all(np.isfinite(hit.t[far]) == np.isfinite(t_ref[far]))
    both = far & np.isfinite(t_ref)
    assert np.abs(hit.t[both] - t_ref[both]).max() <= 1e-4 * scale
    assert not np.any(np.isnan(hit.normal)) and not np.any(np.isnan(hit.uv))


def test_inside_matches_reference(rng):
    import jax

    from jskel import frusta

    joints, radii, parents = CASES["branching"]
    segs = ref.segments(joints, radii, parents)
    built = build_skeleton(joints, radii, parents)
    lo, hi = _bounds(joints, np.asarray(radii))
    P = lo + rng.random((4000, 3)) * (hi - lo)
    got = np.asarray(jax.jit(jax.vmap(lambda p: frusta.inside(built.params, built.static, p)))(np.float32(P - built.anchor)))
    want = ref.inside(segs, P)
    # points within 1e-5 of a boundary may round either way in float32
    assert np.mean(got == want) > 0.999
    assert 0.05 < want.mean() < 0.95
