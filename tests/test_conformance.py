"""The interface's contract, checked the same way for every registered representation.

Each representation gives one small example object here (a new representation without one
fails ``test_every_representation_has_an_example``). On the same rays (aimed into the object's
bounds, plus rays aimed away from them, with random (t_min, t_max] windows) every representation
must hold, in float32:

* a miss is ``t = inf``, ``prim = -1``, position ``inf``, normal and uv 0;
* a hit's t lies in ``[t_min, t_max]``, its normal is unit, its world position lies on the ray
  at t and inside the declared bounds;
* the batch (``intersect_batch``) equals ``vmap`` of one ray (``intersect_one``);
* the two stages (``surface`` of ``cast``) give the batch's hits, and ``cast`` its t and prim;
* ``occluded`` is ``isfinite(t)``, and is false once ``t_max`` stops short of the nearest hit;
* derivatives of the hit distance along every float parameter and the ray origins (forward
  mode) are finite;
* new values of the same shapes do not compile again;
* a bad key in the object section is one ``ValueError`` line naming it.

The truths are the contract's own closed forms (a point on the ray at t, a unit vector, a box);
the batch and the single ray are independent programs (culling, compaction and packets against a
brute-force loop over every primitive).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jskel import registry
from jskel.config import ConfigError, validate
from jskel.rays import Rays, make_rays

N = 512


def _chain(n=20):
    """A bent chain of ``n`` joints with a side branch: enough segments for the BVH path."""
    a = np.linspace(0.0, 2.5, n)
    joints = np.stack([0.4 * np.sin(a), a, 0.3 * np.cos(1.3 * a)], 1)
    joints = np.vstack([joints, joints[8] + [0.6, 0.3, 0.0], joints[8] + [1.1, 0.7, 0.1]])
    parents = list(range(-1, n - 1)) + [8, n]
    radii = np.concatenate([np.linspace(0.25, 0.08, n), [0.1, 0.06]])
    return {"joints": joints.tolist(), "radii": radii.tolist(), "parents": parents}


def _examples(tmp):
    sphere = tmp / "sphere.ply"
    if not sphere.exists():
        import trimesh

        trimesh.creation.icosphere(subdivisions=2, radius=1.0).export(sphere)
    return {
        "frusta": {"type": "frusta", "skeleton": _chain()},
        "implicit": {"type": "implicit", "threshold": 0.5,
                     "balls": [{"center": [0.0, 0.0, 0.0], "radius": 1.0}, {"center": [0.9, 0.4, 0.0], "radius": 0.7}],
                     "tubes": [{"a": [-0.5, -0.6, 0.2], "b": [0.4, -1.2, 0.5], "radius_a": 0.5, "radius_b": 0.3}]},
        "cells": {"type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45},
                  "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "tiles": 4,
                  "steps_per_tile": 64, "bisection": 8, "cache": str(tmp / "cache")},
        "mesh": {"type": "mesh", "path": str(sphere), "normals": "smooth"},
    }


@pytest.fixture(scope="module")
def examples(tmp_path_factory):
    return _examples(tmp_path_factory.mktemp("conformance"))


def test_every_representation_has_an_example(tmp_path):
    assert sorted(_examples(tmp_path)) == registry.names()


def _rays(rng, lo, hi):
    """Float64 world rays: 3/4 from a sphere around the box towards points inside it, 1/4 from
    the same sphere straight away from the box (misses by construction). Random windows."""
    c, r = 0.5 * (lo + hi), 0.5 * np.linalg.norm(hi - lo)
    u = rng.normal(size=(N, 3))
    o = c + 2.0 * r * u / np.linalg.norm(u, axis=1, keepdims=True)
    aim = lo + rng.uniform(size=(N, 3)) * (hi - lo)
    d = aim - o
    away = np.arange(N) % 4 == 3
    d[away] = o[away] - c
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    t_min = np.where(rng.uniform(size=N) < 0.5, 0.0, rng.uniform(0.0, 2.0 * r, N))
    t_max = np.where(rng.uniform(size=N) < 0.5, np.inf, t_min + rng.uniform(0.5 * r, 4.0 * r, N))
    return o, d, t_min, t_max, away


class Case:
    """One representation's example, built, with its rays and every query's output (NumPy)."""

    def __init__(self, name, raw):
        self.name = name
        self.rep = registry.get(name)
        self.cfg = self.rep.Config.model_validate(raw)
        self.built = self.rep.build(self.cfg, np.float32)
        lo, hi = (np.asarray(b, np.float64) for b in self.built.bounds)
        self.o, self.d, self.t_min, self.t_max, self.away = _rays(np.random.default_rng(7), lo, hi)
        self.rays = make_rays(self.o - self.built.anchor, self.d, self.t_min, self.t_max)
        self.fn = jax.jit(self.queries(self.rep, self.built.static))
        out = self.fn(self.built.params, self.rays)
        self.batch, self.one, self.pre, self.two, self.occ = jax.tree_util.tree_map(np.asarray, out)

    @staticmethod
    def queries(rep, static):
        def fn(params, rays: Rays):
            batch = rep.intersect_batch(params, static, rays)
            one = jax.vmap(lambda o, d, a, b: rep.intersect_one(params, static, o, d, a, b))(*rays)
            pre = rep.cast(params, static, rays)
            two = rep.surface(params, static, rays, pre)
            return batch, one, (pre.t, pre.prim), two, rep.occluded(params, static, rays)

        return fn


_CASES: dict = {}


@pytest.fixture(params=registry.names())
def case(request, examples):
    name = request.param
    if name not in _CASES:
        _CASES[name] = Case(name, examples[name])
    return _CASES[name]


def test_a_miss_is_the_sentinel_and_rays_aimed_away_miss(case):
    h = case.batch
    miss = ~np.isfinite(h.t)
    assert np.all(miss[case.away]), f"{case.name}: a ray aimed away from the bounds hit"
    assert 0.1 < np.mean(~miss) < 0.75 + 1e-9, f"{case.name}: {np.mean(~miss):.2f} of the rays hit"
    assert np.all(np.isposinf(h.t[miss])) and np.all(h.prim[miss] == -1)
    assert np.all(np.isposinf(h.position[miss])) and np.all(h.normal[miss] == 0) and np.all(h.uv[miss] == 0)


def test_a_hit_lies_in_its_window_on_the_ray_inside_the_bounds_with_a_unit_normal(case):
    h = case.batch
    hit = np.isfinite(h.t)
    t = h.t[hit].astype(np.float64)
    scale = float(np.max(np.abs(case.built.bounds[1] - case.built.bounds[0])))
    slack = 1e-5 * (scale + t)
    assert np.all(t >= case.t_min[hit] - slack) and np.all(t <= case.t_max[hit] + slack)
    np.testing.assert_allclose(np.linalg.norm(h.normal[hit].astype(np.float64), axis=1), 1.0, atol=1e-5)
    world = case.built.anchor + h.position[hit].astype(np.float64)
    on_ray = case.o[hit] + t[:, None] * case.d[hit]
    tol = 1e-5 * scale + case.built.surface_tolerance
    assert np.max(np.abs(world - on_ray)) <= 4 * tol + 1e-5 * np.max(t)
    lo, hi = case.built.bounds
    assert np.all(world >= lo - tol) and np.all(world <= hi + tol)
    assert np.all((h.prim[hit] >= 0) & (h.prim[hit] < max(case.built.primitives, 1) * 64))


def test_the_batch_equals_vmap_of_one_ray(case):
    a, b = case.batch, case.one
    ha, hb = np.isfinite(a.t), np.isfinite(b.t)
    assert np.mean(ha != hb) <= 0.005, f"{case.name}: {np.sum(ha != hb)} rays hit in one program only"
    both = ha & hb
    np.testing.assert_allclose(a.t[both], b.t[both], rtol=1e-4, atol=1e-6)
    same = a.prim[both] == b.prim[both]
    assert np.mean(same) >= 0.99
    np.testing.assert_allclose(a.normal[both][same], b.normal[both][same], atol=2e-3)


def test_two_stages_give_the_batch_hits_and_cast_its_t_and_prim(case):
    t, prim = case.pre
    np.testing.assert_array_equal(t, case.batch.t)
    np.testing.assert_array_equal(prim, case.batch.prim)
    for x, y in zip(case.two, case.batch):
        if x is not None:
            np.testing.assert_allclose(x, y, rtol=1e-6, atol=1e-6)


def test_occluded_agrees_with_the_cast_and_stops_at_t_max(case):
    np.testing.assert_array_equal(case.occ, np.isfinite(case.batch.t))
    hit = np.isfinite(case.batch.t)
    short = np.where(hit, case.t_min + 0.5 * (np.where(hit, case.batch.t, 0.0) - case.t_min), case.t_max)
    rays = make_rays(case.o - case.built.anchor, case.d, case.t_min, short)
    # nothing lies nearer than the nearest hit, so no ray is blocked before it (same shapes: no compile)
    occ = np.asarray(case.fn(case.built.params, rays)[4])
    scale = float(np.max(case.built.bounds[1] - case.built.bounds[0]))
    ahead = hit & (np.where(hit, case.batch.t, 0.0) > case.t_min + 1e-3 * scale)  # (a hit at t_min leaves no room)
    assert ahead.sum() > 20 and not np.any(occ[ahead])


def test_new_values_of_the_same_shapes_do_not_compile_again(case):
    before = case.fn._cache_size()
    params = jax.tree_util.tree_map(lambda a: a * 1 if jnp.issubdtype(a.dtype, jnp.floating) else a, case.built.params)
    moved = make_rays(case.o - case.built.anchor + 1e-3, case.d, case.t_min, case.t_max)
    jax.block_until_ready(case.fn(params, moved))
    assert case.fn._cache_size() == before == 1


def test_derivatives_of_the_hit_distance_are_finite(case):
    """Forward mode (``jax.jvp``) along a random direction in every float parameter and the ray
    origins: finite everywhere, and not zero (t moves with the origins)."""
    rep, static = case.rep, case.built.static
    hit = jnp.asarray(np.isfinite(case.batch.t))
    leaves, tree = jax.tree_util.tree_flatten(case.built.params)
    floats = [i for i, a in enumerate(leaves) if jnp.issubdtype(a.dtype, jnp.floating)]

    def t_of(values, origins):
        mixed = list(leaves)
        for i, v in zip(floats, values):
            mixed[i] = v
        t = rep.intersect_batch(tree.unflatten(mixed), static, case.rays._replace(origins=origins)).t
        return jnp.where(hit, jnp.where(hit, t, 0.0), 0.0)

    rng = np.random.default_rng(3)
    primals = ([leaves[i] for i in floats], case.rays.origins)
    tangents = jax.tree_util.tree_map(lambda a: jnp.asarray(rng.normal(size=a.shape), a.dtype), primals)
    _, dt = jax.jit(lambda p, v: jax.jvp(t_of, p, v))(primals, tangents)
    dt = np.asarray(dt)
    assert np.all(np.isfinite(dt)), case.name
    assert np.any(dt != 0), f"{case.name}: t does not move with the parameters and origins"


@pytest.mark.parametrize("name", registry.names())
def test_a_bad_object_key_is_one_value_error_naming_it(name, examples):
    raw = {"camera": {"eye": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 40, "width": 8, "height": 8},
           "object": {**examples[name], "not_a_key": 1}}
    with pytest.raises(ValueError) as e:
        validate(raw)
    assert isinstance(e.value, ConfigError)
    assert len(e.value.lines) == 1 and "object.not_a_key" in e.value.lines[0], e.value.lines
