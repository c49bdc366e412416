"""The exact implicit tracer (``method: exact``) against an independent float64 root finder
(``implicit_reference``: dense sampling and 60 bisections, written in NumPy from Rouiller 2011,
Sec. 3) on the gallery's models, the blob slabs up to 50,000 balls, random fields, the thesis'
Fig. 7 configuration, thin necks and tangent rays.

What "agree" means: every ray that the reference decides clearly (its field stays a margin below
T before the root, or along the whole ray on a miss, and it crosses T at a slope) has the same
hit or miss, and its t within a few float32 roundings of the ray's length; every hit the exact
tracer returns lies on F = T in float64 and no earlier than the reference's first root; rays
the tracer cannot certify are flagged, never silently wrong."""

from __future__ import annotations

import numpy as np
import pytest

import implicit_reference as iref
import reference as ref
from conftest import whole_chunks
from jskel import implicit
from jskel.interface import Object, intersect
from jskel.rays import FLAG_OVERFLOW, make_rays

T = 0.5
EPS32 = float(np.finfo(np.float32).eps)


def build(raw: dict):
    cfg = implicit.ImplicitConfig.model_validate({"type": "implicit", "threshold": T, "method": "exact", **raw})
    a, b, ra, rb = implicit.primitives(implicit.expand(cfg))[:4]
    return implicit.build(cfg), (a, b, ra, rb)


def cast(built, O, D):
    """The batch intersection (``implicit.intersect_batch``: culling by (ray, leaf) pairs, the
    rounds, the compacted retraces), as renders call it."""
    rays = make_rays(np.asarray(O) - built.anchor, D)
    return whole_chunks(intersect, Object(built.params, built.static, "implicit"), rays)


def rays_through(prims, n, seed, spread=1.2):
    a, b, ra, rb = prims
    r = np.maximum(ra, rb)[:, None]
    lo, hi = np.minimum(a, b).min(0) - r.max(), np.maximum(a, b).max(0) + r.max()
    return ref.random_rays(np.random.default_rng(seed), lo, hi, n, spread=spread)


def agree(built, prims, O, D, margin_min=1e-4, slope_min=1e-2):
    """Assert the module docstring's agreement; returns (hit, t_ref, clear) for more checks.
    The reference samples every h = R_min / 128: between samples a kernel's curvature along
    the ray (at most 8 / R^2, ``_bounds.curvature``) hides at most 8 h^2 / (8 R^2) = 6e-5 of
    the field per primitive, under ``margin_min``."""
    a, b, ra, rb = prims
    R = np.maximum(ra, rb)
    t_ref, margin, slope = iref.first_root_near(O, D, a, b, ra, rb, T, h=float(R.min()) / 128)
    hit = cast(built, O, D)
    t = np.asarray(hit.t, np.float64)
    flagged = hit.flags != 0
    assert not np.any(np.isnan(t))
    clear = (margin > margin_min) & (~np.isfinite(t_ref) | (slope > slope_min)) & ~flagged
    assert clear.mean() > 0.9, clear.mean()
    same = np.isfinite(t) == np.isfinite(t_ref)
    assert np.all(same[clear]), np.nonzero(~same & clear)[0][:8]
    # depth: a few float32 roundings of the ray's extent (origin to hit, in the anchor's frame)
    scale = np.linalg.norm(O - built.anchor, axis=1) + np.where(np.isfinite(t_ref), t_ref, 0.0)
    both = clear & np.isfinite(t_ref)
    err = np.abs(t[both] - t_ref[both]) / scale[both]
    assert np.all(err < 64 * EPS32), (err.max() / EPS32, np.nonzero(both)[0][np.argmax(err)])
    # every hit is on the surface (float64 field at the float32 hit) and not past the first root
    h = np.isfinite(t) & ~flagged
    x = O[h] + t[h, None] * D[h]
    f = np.concatenate([np.zeros(0)] + [iref.field(x[i:i + 32], a, b, ra, rb) for i in range(0, len(x), 32)])
    assert np.all(np.abs(f - T) < 1e-3), np.abs(f - T).max()
    late = t[h] > np.where(np.isfinite(t_ref[h]), t_ref[h], np.inf) + 64 * EPS32 * scale[h]
    assert not np.any(late & (margin[h] > margin_min)), np.nonzero(h)[0][late][:8]
    return hit, t_ref, clear


MODELS = {
    "gecko": ({"procedural": "gecko"}, 1500, 1),
    "spider": ({"procedural": "spider", "frame": 10.0}, 1200, 2),  # tapered bone tubes: degree 8
    "blobs_500": ({"procedural": "blob_grid", "options": {"n": 500}, "capacity": 64}, 1200, 3),
    "blobs_5000": ({"procedural": "blob_grid", "options": {"n": 5000}, "capacity": 64}, 800, 4),
    "blobs_50000": ({"procedural": "blob_grid", "options": {"n": 50000}, "capacity": 64}, 500, 5),
}


@pytest.mark.parametrize("name", list(MODELS))
def test_models_against_the_float64_reference(name):
    raw, n, seed = MODELS[name]
    built, prims = build(raw)
    O, D = rays_through(prims, n, seed)
    hit, t_ref, clear = agree(built, prims, O, D)
    assert 0.05 < np.isfinite(t_ref).mean() < 0.95
    assert np.mean((hit.flags & FLAG_OVERFLOW) != 0) < 0.05  # random rays along the slab meet > 64 balls


def test_random_fields_of_balls_and_tubes_tapered_and_overlapping():
    """Random balls, constant and tapering tubes, overlapping: intervals of degree 8 (one
    tapering tube) and rays through two tapering tubes' axis pieces at once (left to the
    Lipschitz march, ``_exact`` docstring)."""
    rng = np.random.default_rng(8)
    balls = [{"center": rng.uniform(-1, 1, 3).tolist(), "radius": float(rng.uniform(0.3, 0.8))} for _ in range(6)]
    tubes = []
    for _ in range(6):
        a = rng.uniform(-1, 1, 3)
        b = a + rng.normal(size=3) * 0.8
        ra, rb = rng.uniform(0.2, 0.6, 2)
        tubes.append({"a": a.tolist(), "b": b.tolist(), "radius_a": float(ra), "radius_b": float(rb if _ % 3 else ra)})
    built, prims = build({"balls": balls, "tubes": tubes})
    assert built.static.quality.degree == 8
    O, D = rays_through(prims, 1500, 9)
    agree(built, prims, O, D)


def test_figure7_blend_is_found():
    """Two balls that only just blend (Rouiller Fig. 7): rays through the bridge whose Sec.
    4.2.1 inside points are both outside, which the thesis' bisection misses."""
    s = 0.68
    built, prims = build({"balls": [{"center": [-s, 0, 0], "radius": 1.0}, {"center": [s, 0, 0], "radius": 1.0}]})
    rng = np.random.default_rng(3)
    n = 1500
    P = np.stack([rng.uniform(-0.05, 0.05, n), rng.uniform(-0.12, 0.12, n), rng.uniform(-0.12, 0.12, n)], 1)
    D = rng.normal(size=(n, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    hit, t_ref, clear = agree(built, prims, P - 3.0 * D, D)
    assert np.isfinite(t_ref[clear]).mean() > 0.9


@pytest.mark.parametrize("s", [0.70, 0.707])
def test_thin_necks_in_closed_form(s):
    """Two balls (R = 1) at +-s on x, T = 1/2: on the mid plane F = 2 (1 - s^2 - rho^2)^2, so the
    neck is a disc of radius rho_n = sqrt(1/2 - s^2) (0.1 and 0.012; at s = sqrt(1/2) it
    pinches off). Rays down -y at height z through the mid plane hit iff |z| < rho_n, at
    t = 3 - sqrt(rho_n^2 - z^2): rays within a few ulps of the rim aside, all of them."""
    built, _ = build({"balls": [{"center": [-s, 0, 0], "radius": 1.0}, {"center": [s, 0, 0], "radius": 1.0}]})
    rho = np.sqrt(0.5 - s * s)
    z = np.concatenate([np.linspace(-1.5, 1.5, 301) * rho, [0.0]])
    O = np.stack([np.zeros_like(z), np.full_like(z, 3.0), z], 1)
    D = np.tile([0.0, -1.0, 0.0], (len(z), 1))
    hit = cast(built, O, D)
    inside = np.abs(z) < rho
    rim = np.abs(np.abs(z) - rho) < 1e-4 * rho
    assert np.all(np.isfinite(hit.t[~rim]) == inside[~rim])
    t_true = 3.0 - np.sqrt(np.maximum(rho * rho - z * z, 0.0))
    ok = inside & ~rim
    # the neck's surface crosses at a slope that falls with rho: a few ulps of t over it
    assert np.all(np.abs(hit.t[ok] - t_true[ok]) < 64 * EPS32 * 3.0 / np.sqrt(rho)), np.abs(hit.t[ok] - t_true[ok]).max()
    assert hit.flags.max() == 0


def test_tangent_rays_in_closed_form():
    """A lone ball (R = 1, T = 1/2; surface radius rho = sqrt(1 - sqrt(T))) and rays passing at
    rho - depth from its centre, depth log-uniform in [1e-5, 1e-2] on both sides: the ones
    inside, along a chord of 2 sqrt(2 rho depth) down to 0.007, all hit at the closed-form t;
    the ones outside all miss."""
    built, _ = build({"balls": [{"center": [0, 0, 0], "radius": 1.0}]})
    rng = np.random.default_rng(4)
    n = 2000
    rho = np.sqrt(1 - np.sqrt(T))
    depth = np.exp(rng.uniform(np.log(1e-5), np.log(1e-2), n)) * rng.choice([-1, 1], n)
    ang = rng.uniform(0, 2 * np.pi, n)
    radial = np.stack([np.cos(ang), np.sin(ang), rng.uniform(-1, 1, n) * 0], 1)
    D = np.stack([-np.sin(ang), np.cos(ang), np.zeros(n)], 1)
    O = radial * (rho - depth)[:, None] - 2.0 * D
    hit = cast(built, O, D)
    assert np.all(np.isfinite(hit.t) == (depth > 0))
    inside = depth > 0
    t_true = 2.0 - np.sqrt(rho**2 - (rho - depth[inside]) ** 2)
    # near tangency t is ill-conditioned: dF/dt ~ sqrt(depth), so the rounding of F moves t by
    # about eps / sqrt(depth)
    tol = 16 * EPS32 * (2.0 + 1.0 / np.sqrt(depth[inside]))
    assert np.all(np.abs(hit.t[inside] - t_true) < tol), np.max(np.abs(hit.t[inside] - t_true) / tol)


def test_rays_that_overflow_their_block_list_are_culled_again_flat():
    """200 balls in a thin slab culled in blocks of 4 with 4 kept a ray and room for 100
    candidates (more than the 16 slots a block list tests: the two lists differ in width):
    rays along the slab meet more blocks than kept, are culled again over every ball, and agree
    with the reference like the rest."""
    rng = np.random.default_rng(12)
    c = rng.uniform(-3, 3, (200, 3))
    c[:, 1] *= 0.1
    balls = [{"center": x.tolist(), "radius": 0.5} for x in c]
    built, prims = build({"balls": balls, "capacity": 100, "block_size": 4, "block_capacity": 4})
    O, D = rays_through(prims, 400, 13)
    along = np.stack([np.full(64, -10.0), rng.uniform(-0.3, 0.3, 64), rng.uniform(-3, 3, 64)], 1)
    O = np.vstack([O, along])
    D = np.vstack([D, np.tile([1.0, 0.0, 0.0], (64, 1))])
    hit, _, _ = agree(built, prims, O, D)
    assert not np.any(hit.flags[-64:])


def test_exact_needs_both_tube_radii_by_name():
    cfg = implicit.ImplicitConfig.model_validate({"type": "implicit", "method": "exact", "tubes": [
        {"a": [0, 0, 0], "b": [1, 0, 0], "radius_a": 0.5, "radius_b": 0.0}]})
    with pytest.raises(ValueError, match=r"object.tubes\[0\].radius_b: the exact method needs both tube radii > 0"):
        implicit.build(cfg)
