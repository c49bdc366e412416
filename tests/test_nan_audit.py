"""NaN audit (issue 9): for every representation, a batch that mixes misses, tangent and
grazing rays, rays along axes, through an apex and a seam, from inside, with a zero direction,
and (cells) total internal reflection, runs under ``jax_debug_nans``: values, forward- and
reverse-mode derivatives of t raise nothing (a NaN anywhere in a jitted output would raise
FloatingPointError), and every value is finite or the documented miss sentinel."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jskel import cells, frusta, implicit
from jskel.rays import Rays


@pytest.fixture
def debug_nans():
    jax.config.update("jax_debug_nans", True)
    yield
    jax.config.update("jax_debug_nans", False)


def _rays(anchor, pairs):
    """float32 rays on [0, inf) as the intersectors meet them under jit, zero directions
    included (``make_rays``, the API's entry, rejects those: issue 29)."""
    O = np.array([o for o, _ in pairs], float) - anchor
    D = np.array([d for _, d in pairs], float)
    n = len(pairs)
    return Rays(jnp.asarray(O, jnp.float32), jnp.asarray(D, jnp.float32), jnp.zeros(n, jnp.float32), jnp.full(n, jnp.inf, jnp.float32))


def _check_hit(hit):
    t = np.asarray(hit.t)
    hitm = np.isfinite(t)
    assert not np.any(np.isnan(t)) and np.all(np.isposinf(t[~hitm]))
    for f in (hit.normal, hit.uv):
        f = np.asarray(f)
        assert np.all(np.isfinite(f)) and np.all(f[~hitm] == 0)
    assert np.all(np.isfinite(np.asarray(hit.position)[hitm]))
    assert np.all(np.asarray(hit.prim)[~hitm] == -1)
    return hitm


def _check_derivatives(t_of, rays, hitm):
    """Forward (jacfwd) and reverse (grad of t where finite, else 0) derivatives in the ray, in
    one compiled program (two programs compiled the tracer twice)."""

    def finite_t(o, d):
        t = t_of(o, d)
        return jnp.where(jnp.isfinite(t), t, 0.0)

    def both(o, d):
        return jax.vmap(jax.jacfwd(t_of, argnums=(0, 1)))(o, d), jax.vmap(jax.grad(finite_t, argnums=(0, 1)))(o, d)

    jf, jr = jax.jit(both)(rays.origins, rays.directions)
    for j in jf:
        assert np.all(np.isfinite(np.asarray(j)[hitm]))
    for j in jr:
        assert np.all(np.isfinite(np.asarray(j)))


def test_frusta_hard_rays_raise_no_nan(debug_nans):
    cfg = frusta.FrustaConfig.model_validate({"type": "frusta", "skeleton": {
        "joints": [[0, 0, 0], [0, 1, 0], [0, 2, 0], [0.5, 2.8, 0]], "radii": [0.3, 0.3, 0.2, 0.0], "parents": [-1, 0, 1, 2]}})
    b = frusta.build(cfg)
    rays = _rays(b.anchor, [
        ([0, -1, 0], [0, 1, 0]),         # along the axis, through both caps
        ([0.3, -1, 0], [0, 1, 0]),       # along a generator of the cylinder
        ([0.3, 0.5, 5], [0, 0, -1]),     # tangent to the side
        ([5, 1.0, 0], [-1, 0, 0]),       # in the seam plane y = 1
        ([0.5, 2.8, 5], [0, 0, -1]),     # at the closed tip's apex
        ([5, 5, 5], [1, 0, 0]),          # a miss
        ([0, 0.5, 0], [1, 0, 0]),        # from inside
        ([0, 0.5, 0], [0, 0, 0]),        # zero direction
    ])
    for fn in (frusta.intersect, frusta.intersect_batch):
        hit = jax.jit(lambda p, r, fn=fn: fn(p, b.static, r))(b.params, rays)
        hitm = _check_hit(hit)
    assert hitm.sum() >= 4

    def t_of(o, d):
        return frusta.intersect_one(b.params, b.static, o, d, 0.0, jnp.inf).t

    _check_derivatives(t_of, rays, hitm)


def test_relief_hard_rays_raise_no_nan(debug_nans):
    cfg = frusta.FrustaConfig.model_validate({"type": "frusta", "skeleton": {
        "joints": [[0, 0, 0], [0, 1, 0], [0.3, 2, 0]], "radii": [0.4, 0.35, 0.0], "parents": [-1, 0, 1]},
        "relief": {"map": "brick", "thickness": 0.08, "steps": 16, "bisection": 4, "uv": "exact"}})
    b = frusta.build(cfg)
    rays = _rays(b.anchor, [
        ([0, -1, 0], [0, 1, 0]),         # along the axis
        ([0.48, 0.5, 5], [0, 0, -1]),    # grazing the shell's outside
        ([5, 1.0, 0], [-1, 0, 0]),       # in the seam plane
        ([0.3, 2.0, 5], [0, 0, -1]),     # at the apex
        ([0, 0.5, 0], [1, 0, 0]),        # from inside the inner cone
        ([0.37, 0.5, 0], [0, 1, 0]),     # inside the shell, along it
        ([5, 5, 5], [1, 0, 0]),          # a miss
        ([0, 0.5, 3], [0, 0, 0]),        # zero direction
    ])
    hit = jax.jit(lambda p, r: frusta.intersect_batch(p, b.static, r))(b.params, rays)
    hitm = _check_hit(hit)
    assert hitm.sum() >= 3

    def t_of(o, d):
        return frusta.intersect_one(b.params, b.static, o, d, 0.0, jnp.inf).t

    _check_derivatives(t_of, rays, hitm)


def _shaped(method: str) -> dict:
    """``exact+displace``: ``exact`` on a displaced field (its certified start, then the march)."""
    return {"method": "exact", "displace": {"type": "noise", "amplitude": 0.2}} if method == "exact+displace" else {"method": method}


@pytest.mark.parametrize("method", ["lipschitz", "bisection", "naive", "exact"])  # exact+displace: op by op below
def test_implicit_hard_rays_raise_no_nan(debug_nans, method):
    cfg = implicit.ImplicitConfig.model_validate({
        "type": "implicit", "threshold": 0.5, **_shaped(method), "step": 0.02, "eps": 1e-3, "capacity": 8,
        "balls": [{"center": [0, 0, 0], "radius": 1.0}],
        "tubes": [{"a": [1, 0, 0], "b": [2, 1, 0], "radius_a": 0.5, "radius_b": 0.05}]})
    b = implicit.build(cfg)
    r_surf = float(np.sqrt(1 - np.sqrt(0.5)))  # a lone ball's iso-surface radius (F = T)
    rays = _rays(b.anchor, [
        ([0, 0, 5], [0, 0, -1]),             # through the ball's centre (grad F = 0 there)
        ([0, r_surf, 5], [0, 0, -1]),        # grazing the lone ball's silhouette
        ([2, 1, 5], [0, 0, -1]),             # at the tube's thin end
        ([0, 0, 0], [1, 0, 0]),              # from inside, along an axis
        ([5, 5, 5], [1, 0, 0]),              # a miss
        ([0, 0, 5], [0, 0, 0]),              # zero direction
    ])
    hit = jax.jit(lambda p, r: implicit.intersect_batch(p, b.static, r))(b.params, rays)
    hitm = _check_hit(hit)
    assert hitm[0]

    def t_of(o, d):
        return implicit.intersect_one(b.params, b.static, o, d, 0.0, jnp.inf).t

    _check_derivatives(t_of, rays, hitm)


@pytest.mark.parametrize("mode", ["refraction"])  # the two-sided cast: rays from inside get their exit
def test_cells_hard_rays_raise_no_nan(debug_nans, tmp_path, mode):
    """Values only: a cell's boundary is a discrete choice, so t has no derivative to check;
    the shading of both modes is the next test's."""
    cfg = cells.CellsConfig.model_validate({
        "type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45},
        "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "tiles": 6,
        "search": "linear", "steps_per_tile": 32, "bisection": 6, "mode": mode, "bounces": 2, "ior": 2.4, "cache": str(tmp_path / "c")})
    b = cells.build(cfg)
    rays = _rays(b.anchor, [
        ([0, 0, 5], [0, 0, -1]),          # through the hole
        ([1.0, 0, 5], [0, 0, -1]),        # through the tube's core
        ([1.45, 0, 5], [0, 0, -1]),       # grazing the outer rim
        ([5, 0, 0], [-1, 0, 0]),          # along an axis, through both sides
        ([1.0, 0, 0], [0, 1, 0]),         # from inside
        ([5, 5, 5], [1, 0, 0]),           # a miss
        ([1.0, 0, 5], [0, 0, 0]),         # zero direction
    ])
    from jskel.interface import Object, intersect

    hit = jax.jit(intersect)(Object(b.params, b.static, "cells"), rays)
    hitm = _check_hit(hit)
    assert hitm[1] and hitm[4] and not hitm[5]  # through the core; from inside it finds its exit; the miss


@pytest.mark.parametrize("mode", ["reflection", "refraction"])
def test_cells_modes_through_the_integrator_raise_no_nan(debug_nans, tmp_path, mode):
    """Both modes are the shared integrator's materials (two bounces; refraction at ior 2.4,
    where total internal reflection is common): rays from outside, from inside the tube and
    along an axis through both sides raise no NaN."""
    from jskel.config import validate
    from jskel.render import render

    obj = {"type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45},
           "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "tiles": 6,
           "search": "linear", "steps_per_tile": 32, "bisection": 6, "mode": mode, "bounces": 2, "ior": 2.4, "cache": str(tmp_path / "c")}
    for eye, target in (([0, 0, 5], [1.0, 0, 0]), ([1.0, 0, 0], [1.0, 0.3, -1.0]), ([5, 0, 0], [-1, 0, 0])):
        raw = {"object": obj, "camera": {"eye": eye, "target": target, "up": [0, 1, 0], "width": 16, "height": 12},
               "render": {"progress": False}}
        res = render(validate(raw))
        assert np.all(np.isfinite(res.rgb)) and res.run["effects"]["bounces"] == 2


@pytest.mark.parametrize("method", ["lipschitz", "bisection", "naive", "exact", "exact+displace"])
def test_implicit_tracers_compute_no_masked_nan(debug_nans, method):
    """Op by op (``jax.disable_jit``), ``jax_debug_nans`` checks every operation, not only a
    jitted program's outputs: a NaN masked by a ``where`` raises too. Two balls that pinch off
    (at +-sqrt(1/2), R = 1, T = 1/2), a ray past the pinch (0, 3, 0.3) down -y and a ray that
    meets no candidate: the cast, and the gradient of t in the centres, radii and threshold.
    (The marches once formed L (t_hi - t) with t_hi = -inf and L = 0 for a ray without
    candidates, and sampled the field at t = inf; the bisection formed its inside points'
    positions at t = inf.)"""
    cfg = implicit.ImplicitConfig.model_validate({
        "type": "implicit", "threshold": 0.5, **_shaped(method), "eps": 1e-2, "step": 0.05, "bisection": 2, "steps": 256,
        "balls": [{"center": [float(np.sqrt(0.5)), 0, 0], "radius": 1.0}, {"center": [-float(np.sqrt(0.5)), 0, 0], "radius": 1.0}]})
    b = implicit.build(cfg)
    p0 = b.params

    def t_of(a, ra, T, o, d):
        sc = p0._replace(prims=p0.prims._replace(a=a, b=a, ra=ra, rb=ra), tune=p0.tune._replace(threshold=T))
        t = implicit.intersect_one(sc, b.static, o, d, 0.0, jnp.inf).t
        return jnp.where(jnp.isfinite(t), t, 0.0)

    args = (p0.prims.a, p0.prims.ra, p0.tune.threshold)
    for o, d in (([0, 3, 0.3], [0, -1, 0]), ([5, 5, 5], [1, 0, 0])):
        o = jnp.asarray(np.array(o, float) - b.anchor, jnp.float32)
        d = jnp.asarray(d, jnp.float32)
        # op by op, JAX checks an operation's output when it first compiles it (jax 0.10.2:
        # a second ray through the same operations raised nothing): clear its caches first.
        # jax.grad evaluates the cast's own operations too (its forward pass), so one pass
        # checks both
        jax.clear_caches()
        with jax.disable_jit():
            t, g = jax.value_and_grad(t_of, argnums=(0, 1, 2))(*args, o, d)
        assert t == 0.0 or method == "exact+displace"  # both miss: the pinch is F = T at one point only
        assert all(np.all(np.isfinite(np.asarray(x))) for x in g)
