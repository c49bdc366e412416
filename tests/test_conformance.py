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
* derivatives of the hit distance along every float parameter, the ray origins and
  directions are finite in forward and reverse mode, reverse mode is forward mode's transpose,
  and (frusta, meshes) equals central differences of a float64 NumPy cone or plane;
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

from jskel import interface, registry
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
                  "steps_per_tile": 64, "bisection": 8, "cache": str(tmp / "cache")},  # (the default search: voxels)
        "mesh": {"type": "mesh", "path": str(sphere), "normals": "smooth"},
    }


#: variants held to the same contract: another search of a representation (name:variant -> overrides)
VARIANTS = {"cells:linear": {"search": "linear"}}


@pytest.fixture(scope="module")
def examples(tmp_path_factory):
    found = _examples(tmp_path_factory.mktemp("conformance"))
    return {**found, **{k: {**found[k.split(":")[0]], **v} for k, v in VARIANTS.items()}}


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
        self.rep = registry.get(name.split(":")[0])
        self.cfg = self.rep.Config.model_validate(raw)
        self.built = self.rep.build(self.cfg, np.float32)
        lo, hi = (np.asarray(b, np.float64) for b in self.built.bounds)
        self.o, self.d, self.t_min, self.t_max, self.away = _rays(np.random.default_rng(7), lo, hi)
        self.rays = make_rays(self.o - self.built.anchor, self.d, self.t_min, self.t_max)
        self.obj = interface.Object.of(self.rep, self.built)
        out = QUERIES(self.obj, self.rays)
        self.batch, self.one, self.pre, self.two, self.occ = jax.tree_util.tree_map(np.asarray, out)
        self.derivs = None  # (jitted jvp and vjp, primals, ...): built by the first derivative test



def _queries(obj: interface.Object, rays: Rays):
    """Every query of the interface's module-level functions on one object: the batch, ``vmap``
    of one ray, the two stages, ``occluded``."""
    pre = interface.cast(obj, rays)
    return (interface.intersect(obj, rays), interface.intersect_each(obj, rays), (pre.t, pre.prim),
            interface.surface(obj, rays, pre), interface.occluded(obj, rays))


# one jit for every representation: the Object's tree structure (representation and static
# options) keys its programs, as a user's ``jax.jit(interface.intersect)`` is keyed
QUERIES = jax.jit(_queries)


_CASES: dict = {}


@pytest.fixture(params=registry.names() + list(VARIANTS))
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
    occ = np.asarray(QUERIES(case.obj, rays)[4])
    scale = float(np.max(case.built.bounds[1] - case.built.bounds[0]))
    ahead = hit & (np.where(hit, case.batch.t, 0.0) > case.t_min + 1e-3 * scale)  # (a hit at t_min leaves no room)
    assert ahead.sum() > 20 and not np.any(occ[ahead])


def test_new_values_of_the_same_shapes_do_not_compile_again(case):
    """Every float parameter scaled by 1 + 2^-6 and the rays moved: the same program answers
    (the jit's cache does not grow), and the new values are used (the hits' t change)."""
    params = jax.tree_util.tree_map(lambda a: a * (1 + 2**-6) if jnp.issubdtype(a.dtype, jnp.floating) else a, case.built.params)
    moved = make_rays(case.o - case.built.anchor + 1e-3, case.d, case.t_min, case.t_max)
    before = QUERIES._cache_size()
    t = np.asarray(QUERIES(interface.Object(params, case.obj.static, case.obj.rep), moved)[0].t)
    assert QUERIES._cache_size() == before
    both = np.isfinite(t) & np.isfinite(case.batch.t)
    assert both.sum() > 20 and np.mean(t[both] != case.batch.t[both]) > 0.5


def _derivatives(case):
    """One jitted function per representation (compiled once, shared by the derivative tests):
    (t, J v, J^T u) of the hit distances t (0 where the ray missed, double ``where``) as a
    function of every float parameter, the ray origins and the ray directions, for a tangent v
    and a cotangent u: forward mode (``jax.jvp``) and reverse mode (``jax.vjp``) in one program."""
    if case.derivs is None:
        rep, static = case.rep, case.built.static
        hit = jnp.asarray(np.isfinite(case.batch.t))
        leaves, tree = jax.tree_util.tree_flatten(case.built.params)
        floats = [i for i, a in enumerate(leaves) if jnp.issubdtype(a.dtype, jnp.floating)]

        def t_of(values, origins, directions):
            mixed = list(leaves)
            for i, v in zip(floats, values):
                mixed[i] = v
            rays = case.rays._replace(origins=origins, directions=directions)
            t = rep.intersect_batch(tree.unflatten(mixed), static, rays).t
            return jnp.where(hit, jnp.where(hit, t, 0.0), 0.0)

        def both(primals, tangents, u):
            t, jv = jax.jvp(t_of, primals, tangents)
            return t, jv, jax.vjp(t_of, *primals)[1](u)

        case.derivs = (jax.jit(both), ([leaves[i] for i in floats], case.rays.origins, case.rays.directions), floats, tree, leaves)
    return case.derivs


def _random_like(rng, tree):
    return jax.tree_util.tree_map(lambda a: jnp.asarray(rng.normal(size=a.shape), a.dtype), tree)


def test_derivatives_of_the_hit_distance_are_finite(case):
    """Forward mode (``jax.jvp``) along a random direction in every float parameter and the ray
    origins and directions: finite everywhere, and not zero (t moves with the origins)."""
    fn, primals, *_ = _derivatives(case)
    rng = np.random.default_rng(3)
    _, dt, _ = fn(primals, _random_like(rng, primals), jnp.zeros(case.rays.size, case.rays.origins.dtype))
    dt = np.asarray(dt)
    assert np.all(np.isfinite(dt)), case.name
    assert np.any(dt != 0), f"{case.name}: t does not move with the parameters and origins"


def test_reverse_mode_is_finite_and_the_transpose_of_forward_mode(case):
    """Reverse mode (``jax.vjp``, what ``jax.grad`` runs) of the hit distances: finite, not zero,
    and the transpose of forward mode: <v, J^T u> = <J v, u> for random v and u. A BVH walk is a
    loop of data-dependent length that JAX cannot reverse; each representation's cast gives it
    a derivative of its own (the winning primitive's closed form, or the implicit-function
    theorem at a marched root)."""
    fn, primals, *_ = _derivatives(case)
    rng = np.random.default_rng(5)
    v = _random_like(rng, primals)
    u = jnp.asarray(rng.normal(size=case.rays.size), case.rays.origins.dtype)
    _, jv, jtu = fn(primals, v, u)
    flat = [np.asarray(g, np.float64) for g in jax.tree_util.tree_leaves(jtu)]
    assert all(np.all(np.isfinite(g)) for g in flat), case.name
    assert any(np.any(g != 0) for g in flat), f"{case.name}: the reverse-mode derivative is zero"
    assert all(np.all(np.asarray(g)[~np.isfinite(case.batch.t)] == 0) for g in jtu[1:]), f"{case.name}: a miss has a derivative"
    lhs = sum(float(np.sum(np.asarray(a, np.float64) * b)) for a, b in zip(jax.tree_util.tree_leaves(v), flat))
    rhs = float(np.sum(np.asarray(jv, np.float64) * np.asarray(u, np.float64)))
    scale = sum(float(np.sum(np.abs(np.asarray(a, np.float64) * b))) for a, b in zip(jax.tree_util.tree_leaves(v), flat))
    assert abs(lhs - rhs) <= 1e-4 * scale, (case.name, lhs, rhs, scale)


def _cone_candidates(seg, o, d):
    """(N, 4) float64 ray parameters of each ray against its own frustum (fields (N, ...)): the
    two roots of the cone |p - (p.m) m|^2 = (r1 + (r2 - r1)/h p.m)^2, p = o + t d - c1 (the
    perpendicular distance to the axis, not the code's frame components), and the two cutting
    planes nb.p = db, nt.p = dt (Bhagvat et al. 2009, Sec. 2.3-2.5); NaN where none."""
    q = o - seg["c1"]
    m = seg["m"]
    k = (seg["r2"] - seg["r1"]) / seg["h"]
    qm, dm = np.sum(q * m, 1), np.sum(d * m, 1)
    P, D = q - qm[:, None] * m, d - dm[:, None] * m
    re = seg["r1"] + k * qm
    a = np.sum(D * D, 1) - k * k * dm * dm
    b = 2.0 * (np.sum(P * D, 1) - k * dm * re)
    c = np.sum(P * P, 1) - re * re
    disc = b * b - 4 * a * c
    sq = np.sqrt(np.where(disc >= 0, disc, np.nan))
    with np.errstate(divide="ignore", invalid="ignore"):
        roots = [(-b - sq) / (2 * a), (-b + sq) / (2 * a)]
        planes = [(seg[dist] - np.sum(seg[n] * q, 1)) / np.sum(seg[n] * d, 1) for n, dist in (("nb", "db"), ("nt", "dt"))]
    return np.stack(roots + planes, 1)


def _plane_t(v0, v1, v2, o, d):
    """Float64 ray parameter of each ray on its triangle's plane, and the plane's normal."""
    n = np.cross(v1 - v0, v2 - v0)
    return np.sum(n * (v0 - o), 1) / np.sum(n * d, 1), n


def _reverse_against_central_differences(case, fields, row, t_ref, u, holder):
    """Reverse mode's J^T u against float64 central differences of ``t_ref`` (the hit rays'
    t from their primitives' fields and their rays, a closed form written here).

    fields: name -> (K, ...) float64 primitive array (as the params hold it); row: (n,) the
    primitive of each hit ray (the cast's choice; the value is the reference's); u: (N,)
    cotangent, 0 on misses and ill-posed rays; holder: the params' node holding the fields. The
    derivative of a primitive's field is summed over the rays that hit it."""
    fn, primals, floats, tree, leaves = _derivatives(case)
    _, _, (gv, go, gd) = fn(primals, _random_like(np.random.default_rng(0), primals), jnp.asarray(u, case.rays.origins.dtype))
    grads = list(leaves)
    for i, g in zip(floats, gv):
        grads[i] = g
    grads = holder(tree.unflatten(grads))
    hit = np.isfinite(case.batch.t)
    x = {name: a[row] for name, a in fields.items()} | {"o": case.o[hit] - case.built.anchor, "d": case.d[hit]}
    x = {name: a.reshape(a.shape[0], -1) for name, a in x.items()}
    shapes = {name: a.shape for name, a in fields.items()}
    h = 1e-6
    ok = 0
    for name, a in x.items():
        fd = np.zeros(a.shape)
        for j in range(a.shape[1]):
            plus, minus = dict(x), dict(x)
            plus[name], minus[name] = a.copy(), a.copy()
            plus[name][:, j] += h
            minus[name][:, j] -= h
            fd[:, j] = (t_ref(**plus) - t_ref(**minus)) / (2 * h)
        want = u[hit][:, None] * fd
        if name in fields:  # summed per primitive
            per = np.zeros((shapes[name][0], a.shape[1]))
            np.add.at(per, row, want)
            want, got = per.reshape(shapes[name]), np.asarray(getattr(grads, name), np.float64)
        else:
            full = np.zeros((hit.size, 3))
            full[hit] = want
            want, got = full, np.asarray(go if name == "o" else gd, np.float64)
        np.testing.assert_allclose(got, want, rtol=2e-3, atol=2e-3 * np.max(np.abs(want)), err_msg=f"{case.name}: d t / d {name}")
        ok += int(np.sum(want != 0))
    assert ok > 500, f"{case.name}: only {ok} derivatives compared"


@pytest.mark.parametrize("case", ["frusta"], indirect=True)
def test_frusta_reverse_mode_equals_central_differences_of_a_float64_cone(case):
    f = case.built.params.plain.frusta
    hit = np.isfinite(case.batch.t)
    row = case.batch.prim[hit]  # the example's single plain group holds segment s in row s
    np.testing.assert_array_equal(np.asarray(f.sid)[row], row)
    seg = {name: np.asarray(getattr(f, name), np.float64) for name in ("c1", "m", "r1", "r2", "h", "nb", "db", "nt", "dt")}
    o, d, t = case.o[hit] - case.built.anchor, case.d[hit], case.batch.t[hit].astype(np.float64)
    cand = _cone_candidates({k: v[row] for k, v in seg.items()}, o, d)
    gap = np.abs(np.nan_to_num(cand - t[:, None], nan=np.inf))
    pick = np.argmin(gap, 1)
    scale = float(np.max(case.built.bounds[1] - case.built.bounds[0]))
    assert np.mean(np.min(gap, 1) <= 1e-4 * scale) > 0.99, "the float64 cone does not give the cast's t"

    def t_ref(c1, r1, r2, h, db, dt, o, d):
        fields = {"c1": c1, "m": seg["m"][row], "r1": r1[:, 0], "r2": r2[:, 0], "h": h[:, 0], "nb": seg["nb"][row], "db": db[:, 0],
                  "nt": seg["nt"][row], "dt": dt[:, 0]}
        return _cone_candidates(fields, o, d)[np.arange(row.size), pick]

    # well posed: the surface is unambiguous (no other candidate within 1e-3) and not grazed
    second = np.sort(gap, 1)[:, 1]
    p = o + t[:, None] * d - seg["c1"][row]
    y = np.sum(p * seg["m"][row], 1)
    k = (seg["r2"] - seg["r1"])[row] / seg["h"][row]
    side_n = (p - y[:, None] * seg["m"][row]) - ((seg["r1"][row] + k * y) * k)[:, None] * seg["m"][row]
    n = np.where((pick < 2)[:, None], side_n, np.where((pick == 2)[:, None], seg["nb"][row], seg["nt"][row]))
    cos = np.abs(np.sum(n * d, 1)) / np.linalg.norm(n, axis=1)
    u = np.zeros(hit.size)
    u[hit] = np.where((second > 1e-3 * scale) & (cos > 0.1) & (np.min(gap, 1) <= 1e-4 * scale), np.random.default_rng(1).normal(size=row.size), 0.0)
    fields = {name: seg[name] for name in ("c1", "r1", "r2", "h", "db", "dt")}
    _reverse_against_central_differences(case, fields, row, t_ref, u, lambda g: g.plain.frusta)


@pytest.mark.parametrize("case", ["mesh"], indirect=True)
def test_mesh_reverse_mode_equals_central_differences_of_a_float64_plane(case):
    p = case.built.params
    hit = np.isfinite(case.batch.t)
    row = case.batch.prim[hit]
    fields = {name: np.asarray(getattr(p, name), np.float64) for name in ("v0", "v1", "v2")}
    o, d = case.o[hit] - case.built.anchor, case.d[hit]
    t, n = _plane_t(fields["v0"][row], fields["v1"][row], fields["v2"][row], o, d)
    np.testing.assert_allclose(t, case.batch.t[hit], rtol=1e-4, atol=1e-5)

    def t_ref(v0, v1, v2, o, d):
        return _plane_t(v0, v1, v2, o, d)[0]

    cos = np.abs(np.sum(n * d, 1)) / np.linalg.norm(n, axis=1)
    u = np.zeros(hit.size)
    u[hit] = np.where(cos > 0.1, np.random.default_rng(1).normal(size=row.size), 0.0)
    _reverse_against_central_differences(case, fields, row, t_ref, u, lambda g: g)


@pytest.mark.parametrize("name", registry.names())
def test_a_bad_object_key_is_one_value_error_naming_it(name, examples):
    raw = {"camera": {"eye": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 40, "width": 8, "height": 8},
           "object": {**examples[name], "not_a_key": 1}}
    with pytest.raises(ValueError) as e:
        validate(raw)
    assert isinstance(e.value, ConfigError)
    assert len(e.value.lines) == 1 and "object.not_a_key" in e.value.lines[0], e.value.lines
