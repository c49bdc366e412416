"""Tracing the rays of one level against a scene's objects (the integrator's first stage, see
``_scene``): the nearest hit over all objects and the any-hit test of shadow rays. Each object
is reached through the representation interface in its own frame (``XForm``), and traces only
the rays that cross its world bounding box, compacted into dense sub-batches
(``wavefront.compact_map``); an object placed exactly at its anchor skips its identity transform."""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import registry
from ..accel import always, fenced
from ..rays import Rays
from ..wavefront import compact_map
from ._build import SceneParams, SceneStatic, XForm


class SceneHit(NamedTuple):
    """Nearest hit of a ray over all objects, in the eye-relative world frame (leading axis N).

    t (+inf on a miss), position (3), normal (3, unit, outward), uv (2), prim (-1 on a miss),
    obj (index of the object, -1 on a miss), base (3, the representation's colour at the hit:
    skeleton colour or texture), flags (int32 diagnostics of the representation)."""

    t: jnp.ndarray
    position: jnp.ndarray
    normal: jnp.ndarray
    uv: jnp.ndarray
    prim: jnp.ndarray
    obj: jnp.ndarray
    base: jnp.ndarray
    flags: jnp.ndarray


def _apply(m, v):
    """``m @ v`` for each row of v (..., 3), written out per component: exact for the identity,
    and free of the reduced-precision matrix units some accelerators use for float32 dots."""
    return v[..., 0:1] * m[:, 0] + v[..., 1:2] * m[:, 1] + v[..., 2:3] * m[:, 2]


def _box_entry(rays: Rays, lo, hi):
    """Slab test: (crossed, near), each (N,): does the ray's interval (t_min, t_max] meet the box
    [lo, hi], and at which t does the ray's line enter it."""
    inv = 1.0 / rays.directions  # +-inf for zero components: the slab then holds or fails whole
    t0 = (lo - rays.origins) * inv
    t1 = (hi - rays.origins) * inv
    near = jnp.max(jnp.where(jnp.isnan(t0), -jnp.inf, jnp.minimum(t0, t1)), axis=-1)
    far = jnp.min(jnp.where(jnp.isnan(t1), jnp.inf, jnp.maximum(t0, t1)), axis=-1)
    return (near <= far) & (far >= rays.t_min) & (near <= rays.t_max), near


def _box_crossed(rays: Rays, lo, hi):
    """Does the ray's interval (t_min, t_max] meet the box [lo, hi]? (N,) bool."""
    return _box_entry(rays, lo, hi)[0]


def front_to_back(rays: Rays, live, lo, hi):
    """(K,) int32: the order in which to trace K objects of boxes ``lo``/``hi`` (K, 3) for these
    rays, nearest first: by the mean t at which the live rays that cross a box enter it (a box no
    live ray crosses goes last). One order for the whole batch, computed in the program from the
    rays' values, so a moved camera reorders without compiling again; an order only saves work
    (:func:`nearest` merges with ties to the lower index, so any order gives the same hits)."""
    crossed, near = jax.vmap(lambda a, b: _box_entry(rays, a, b))(lo, hi)  # (K, N)
    use = crossed & live[None, :]
    count = jnp.sum(use, axis=1)
    mean = jnp.sum(jnp.where(use, jnp.maximum(near, rays.t_min[None, :]), 0.0), axis=1) / jnp.maximum(count, 1)
    return jnp.argsort(jnp.where(count > 0, mean, jnp.inf), stable=True).astype(jnp.int32)


def _to_object(x: XForm, rays: Rays) -> Rays:
    return Rays(_apply(x.rt, rays.origins) / x.s + x.c, _apply(x.rt, rays.directions), rays.t_min / x.s, rays.t_max / x.s)


def _object_hits(rep_name: str, static, p, x: XForm, k: int, rays: Rays, identity: bool = False) -> SceneHit:
    """Object k's hits of ``rays`` in the rays' frame. ``identity``: the transform is the
    identity (``SceneStatic.identity``: a scene of one at its anchor), so the rays and hits skip it (the same floats: ``_apply`` is
    exact for the identity and its offsets are zero)."""
    rep = registry.get(rep_name)
    local = rays if identity else _to_object(x, rays)
    h = rep.intersect_batch(p, static, local)
    base = jax.vmap(lambda hh: rep.albedo(p, static, hh))(h)
    hit = jnp.isfinite(h.t)
    t = h.t if identity else h.t * x.s
    pos = jnp.where(hit[:, None], h.position if identity else _apply(x.r, jnp.where(hit[:, None], h.position, 0.0)) * x.s + x.g, jnp.inf)
    flags = jnp.zeros_like(h.prim) if h.flags is None else h.flags
    obj = jnp.where(hit, k, -1).astype(jnp.int32)
    nrm = h.normal if identity else _apply(x.r, h.normal)
    return SceneHit(t, pos, nrm, h.uv, h.prim, obj, base.astype(t.dtype), flags.astype(jnp.int32))


def _miss(n: int, dtype) -> SceneHit:
    z3 = jnp.zeros((n, 3), dtype)
    return SceneHit(jnp.full((n,), jnp.inf, dtype), jnp.full((n, 3), jnp.inf, dtype), z3, jnp.zeros((n, 2), dtype),
                    jnp.full((n,), -1, jnp.int32), jnp.full((n,), -1, jnp.int32), z3, jnp.zeros((n,), jnp.int32))


def nearest(params: SceneParams, static: SceneStatic, rays: Rays, live, any_hit=None) -> SceneHit:
    """Nearest hit over all objects of the ``live`` rays (others: misses). Each object traces
    only the live rays that cross its bounding box before the nearest hit found so far,
    compacted into sub-batches of ``lanes``. The objects of a group (:func:`groups`) are traced
    nearest box first for the batch (:func:`front_to_back`), so that where boxes do not overlap
    along a ray, only its nearest object finishes a hit for it; groups go in a fixed order.

    ``any_hit`` (N,) bool, optional, marks rows that only ask whether they meet some object in
    (t_min, t_max] (shadow rays cast in the same batch as the rays they light, so that each
    object's traversal is traced once in the program, not once per query): an object skips such
    a row once an earlier object hit it (early out, as :func:`occluded`), and of such a row only
    ``jnp.isfinite(t)`` means anything (what the interface's default ``occluded`` asks)."""
    n, dtype = rays.size, rays.origins.dtype
    eff = static.effects
    if len(static.reps) == 1 and not (eff.reflection or eff.refraction):  # a scene of one, camera rays only: one batch (the representation culls)
        fn = functools.partial(_object_hits, static.reps[0], static.statics[0], params.objects[0], params.xforms[0], 0,
                               identity=static.identity[0])
        return fenced(always(rays.t_min), lambda: fn(rays))
    best = _miss(n, dtype)
    for ks in groups(params, static):
        def merge(best, p, x, k, rep=static.reps[ks[0]], st=static.statics[ks[0]], identity=static.identity[ks[0]]):
            # a ray whose nearest hit so far lies before the object's box cannot be won by it: it is
            # not traced (the rays traced keep their own t_max, so each object's hits are as before)
            ahead = rays._replace(t_max=jnp.minimum(rays.t_max, best.t))
            need = (live & _box_crossed(ahead, x.lo, x.hi)) if static.compaction else jnp.ones_like(live)
            if any_hit is not None and static.compaction:
                need = need & ~(any_hit & jnp.isfinite(best.t))
            fn = functools.partial(_object_hits, rep, st, p, x, k, identity=identity)
            return _closer(compact_map(fn, need, rays, _miss(n, dtype), static.lanes), best)

        if len(ks) == 1:
            best = merge(best, params.objects[ks[0]], params.xforms[ks[0]], ks[0])
        else:  # one traced copy of the object's tracing for the whole group, run nearest box first
            stack = functools.partial(jax.tree_util.tree_map, lambda *a: jnp.stack(a))
            each = (stack(*[params.objects[k] for k in ks]), stack(*[params.xforms[k] for k in ks]), jnp.asarray(ks, jnp.int32))
            if static.compaction:
                seek = live if any_hit is None else live & ~any_hit  # the order serves the rows that seek the nearest
                order = front_to_back(rays, seek, each[1].lo, each[1].hi)
                each = jax.tree_util.tree_map(lambda a: a[order], each)
            best = jax.lax.scan(lambda b, item: (merge(b, *item), None), best, each)[0]
    return best


def groups(params: SceneParams, static: SceneStatic) -> list:
    """The scene's object indices grouped by representation, static options and the shapes of
    their params, in order of each group's first object: :func:`nearest` traces one copy of the
    hit code per group and runs it over the group's objects in a ``scan`` (a scene's floor,
    mirror and glass rod of one segment each share a shape bucket, so their traversal is
    compiled once, not three times)."""
    found: dict = {}
    for k, (rep, st, obj, ident) in enumerate(zip(static.reps, static.statics, params.objects, static.identity)):
        leaves, tree = jax.tree_util.tree_flatten(obj)
        found.setdefault((rep, st, ident, tree, tuple((jnp.shape(a), jnp.result_type(a)) for a in leaves)), []).append(k)
    return list(found.values())


def _closer(hk: SceneHit, best: SceneHit) -> SceneHit:
    """``best`` with the rows where object hits ``hk`` are nearer replaced, ties going to the
    lower object index (so the order in which groups are traced changes nothing), and every
    object's flags kept: a ray lost by one object is not decided."""
    closer = (hk.t < best.t) | ((hk.t == best.t) & (hk.obj >= 0) & (hk.obj < best.obj))
    best = jax.tree_util.tree_map(lambda a, b: jnp.where(closer.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), hk, best)
    return best._replace(flags=best.flags | hk.flags)


def occluded(params: SceneParams, static: SceneStatic, rays: Rays, need):
    """Any-hit: (N,) True where a ``need``-ed ray meets some object in (t_min, t_max]. Objects
    are tested in turn and each only on the rays no earlier object blocked (early out)."""
    blocked = jnp.zeros_like(need)
    for k, (rep, st) in enumerate(zip(static.reps, static.statics)):
        x = params.xforms[k]
        todo = (need & ~blocked & _box_crossed(rays, x.lo, x.hi)) if static.compaction else jnp.ones_like(need)

        def fn(sub, rep=rep, st=st, k=k, x=x):
            return registry.get(rep).occluded(params.objects[k], st, _to_object(x, sub))

        if static.compaction:
            blocked = compact_map(fn, todo, rays, blocked, static.lanes)
        else:  # masking: every ray traced, the result kept where needed
            blocked = blocked | (need & compact_map(fn, todo, rays, jnp.zeros_like(blocked), static.lanes))
    return blocked
