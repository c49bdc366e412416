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
from ..interface import Preliminary
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


def _box_crossed(rays: Rays, lo, hi):
    """Slab test: does the ray's interval (t_min, t_max] meet the box [lo, hi]? (N,) bool."""
    inv = 1.0 / rays.directions  # +-inf for zero components: the slab then holds or fails whole
    t0 = (lo - rays.origins) * inv
    t1 = (hi - rays.origins) * inv
    near = jnp.max(jnp.where(jnp.isnan(t0), -jnp.inf, jnp.minimum(t0, t1)), axis=-1)
    far = jnp.min(jnp.where(jnp.isnan(t1), jnp.inf, jnp.maximum(t0, t1)), axis=-1)
    return (near <= far) & (far >= rays.t_min) & (near <= rays.t_max)


def _to_object(x: XForm, rays: Rays) -> Rays:
    return Rays(_apply(x.rt, rays.origins) / x.s + x.c, _apply(x.rt, rays.directions), rays.t_min / x.s, rays.t_max / x.s)


def _object_hits(rep_name: str, static, p, x: XForm, k: int, rays: Rays, identity: bool = False) -> SceneHit:
    """Object k's hits of ``rays`` in the rays' frame, both stages at once (a scene of
    one's camera rays). ``identity``: the transform is the identity (``SceneStatic.identity``: a scene of one at its anchor), so the rays and
    hits skip it (the same floats: ``_apply`` is exact for the identity and its offsets are zero)."""
    rep = registry.get(rep_name)
    local = rays if identity else _to_object(x, rays)
    return _to_scene(rep, static, p, x, k, rep.intersect_batch(p, static, local), identity)


def _to_scene(rep, static, p, x: XForm, k: int, h, identity: bool) -> SceneHit:
    """Object k's finished hits ``h`` (its own frame) as a :class:`SceneHit` in the rays' frame,
    with the representation's colour at each (``albedo``)."""
    base = jax.vmap(lambda hh: rep.albedo(p, static, hh))(h)
    hit = jnp.isfinite(h.t)
    t = h.t if identity else h.t * x.s
    pos = jnp.where(hit[:, None], h.position if identity else _apply(x.r, jnp.where(hit[:, None], h.position, 0.0)) * x.s + x.g, jnp.inf)
    flags = jnp.zeros_like(h.prim) if h.flags is None else h.flags
    obj = jnp.where(hit, k, -1).astype(jnp.int32)
    nrm = h.normal if identity else _apply(x.r, h.normal)
    return SceneHit(t, pos, nrm, h.uv, h.prim, obj, base.astype(t.dtype), flags.astype(jnp.int32))


class _Cast(NamedTuple):
    """Object k's preliminary hits (``Representation.cast``) of N rays: t in the rays' frame
    (what the nearest is chosen by), the object's own t, primitive and payload (what its
    ``surface`` finishes the winners from), and its flags (int32, 0 where it has none)."""

    t: jnp.ndarray
    obj: jnp.ndarray
    flags: jnp.ndarray
    pre: Preliminary


def _object_cast(rep_name: str, static, p, x: XForm, k: int, rays: Rays, identity: bool = False) -> _Cast:
    rep = registry.get(rep_name)
    pre = rep.cast(p, static, rays if identity else _to_object(x, rays))
    flags = jnp.zeros_like(pre.prim) if pre.flags is None else pre.flags
    pre = pre._replace(flags=None)
    return _Cast(pre.t if identity else pre.t * x.s, jnp.where(jnp.isfinite(pre.t), k, -1).astype(jnp.int32), flags.astype(jnp.int32), pre)


def _object_surface(rep_name: str, static, p, x: XForm, k: int, sub, identity: bool = False) -> SceneHit:
    """Object k's ``surface`` of the rays it won (``sub``: (rays, their :class:`_Cast` rows))."""
    rays, c = sub
    rep = registry.get(rep_name)
    local = rays if identity else _to_object(x, rays)
    return _to_scene(rep, static, p, x, k, rep.surface(p, static, local, c.pre), identity)


def _miss(n: int, dtype) -> SceneHit:
    z3 = jnp.zeros((n, 3), dtype)
    return SceneHit(jnp.full((n,), jnp.inf, dtype), jnp.full((n, 3), jnp.inf, dtype), z3, jnp.zeros((n, 2), dtype),
                    jnp.full((n,), -1, jnp.int32), jnp.full((n,), -1, jnp.int32), z3, jnp.zeros((n,), jnp.int32))


def nearest(params: SceneParams, static: SceneStatic, rays: Rays, live, any_hit=None) -> SceneHit:
    """Nearest hit over all objects of the ``live`` rays (others: misses); with two objects or
    more in two stages, as Mitsuba's ``ray_intersect_preliminary`` / ``compute_surface_interaction``: every object casts
    (``Representation.cast``: t, primitive, payload) the live rays that cross its bounding box,
    compacted into sub-batches of ``lanes``; the nearest cast is kept per ray (ties to the lower
    object index); then each object finishes (``surface``, ``albedo``) only the rays it won.
    Every object's cast flags are kept: a ray lost by one object is not decided.

    ``any_hit`` (N,) bool, optional, marks rows that only ask whether they meet some object in
    (t_min, t_max] (shadow rays cast in the same batch as the rays they light, so that each
    object's traversal is traced once in the program, not once per query): an object skips such
    a row once an earlier object hit it (early out, as :func:`occluded`), no object finishes it,
    and of such a row only ``jnp.isfinite(t)`` means anything (what the interface's default
    ``occluded`` asks)."""
    n, dtype = rays.size, rays.origins.dtype
    eff = static.effects
    if len(static.reps) == 1:  # a scene of one: its hit is the nearest, so cast and finished at once
        fn = functools.partial(_object_hits, static.reps[0], static.statics[0], params.objects[0], params.xforms[0], 0,
                               identity=static.identity[0])
        if not (eff.reflection or eff.refraction):  # camera rays only: one batch (the representation culls)
            return fenced(always(rays.t_min), lambda: fn(rays))
        x = params.xforms[0]
        need = (live & _box_crossed(rays, x.lo, x.hi)) if static.compaction else jnp.ones_like(live)
        return _closer(compact_map(fn, need, rays, _miss(n, dtype), static.lanes), _miss(n, dtype))
    inf = jnp.full((n,), jnp.inf, dtype)
    best = (inf, jnp.full((n,), -1, jnp.int32), jnp.zeros((n,), jnp.int32))  # (t, obj, flags of every object)
    casts = {}  # group -> each object's _Cast rows (stacked along a leading axis for a scanned group)
    for g, ks in enumerate(groups(params, static)):
        rep, st, ident = static.reps[ks[0]], static.statics[ks[0]], static.identity[ks[0]]

        def cast(best, p, x, k, rep=rep, st=st, ident=ident):
            need = (live & _box_crossed(rays, x.lo, x.hi)) if static.compaction else jnp.ones_like(live)
            if any_hit is not None and static.compaction:
                need = need & ~(any_hit & jnp.isfinite(best[0]))
            fn = functools.partial(_object_cast, rep, st, p, x, k, identity=ident)
            c = compact_map(fn, need, rays, _no_cast, static.lanes)
            closer = (c.t < best[0]) | ((c.t == best[0]) & (c.obj >= 0) & (c.obj < best[1]))
            return (jnp.where(closer, c.t, best[0]), jnp.where(closer, c.obj, best[1]), best[2] | c.flags), c

        if len(ks) == 1:
            best, casts[g] = cast(best, params.objects[ks[0]], params.xforms[ks[0]], ks[0])
        else:  # one traced copy of the object's tracing for the whole group
            best, casts[g] = jax.lax.scan(lambda b, item: cast(b, *item), best, _stacked(params, ks))
    t, obj, flags = best
    asks = jnp.zeros_like(live) if any_hit is None else any_hit
    out = _miss(n, dtype)._replace(t=jnp.where(asks, t, jnp.inf), obj=jnp.where(asks, obj, -1))
    for g, ks in enumerate(groups(params, static)):
        rep, st, ident = static.reps[ks[0]], static.statics[ks[0]], static.identity[ks[0]]

        def finish(out, p, x, k, c, rep=rep, st=st, ident=ident):
            won = (obj == k) & ~asks
            fn = functools.partial(_object_surface, rep, st, p, x, k, identity=ident)
            if static.compaction:
                return compact_map(fn, won, (rays, c), out, static.lanes)
            every = compact_map(fn, jnp.ones_like(won), (rays, c), _miss(n, dtype), static.lanes)  # masking: every ray
            return jax.tree_util.tree_map(lambda a, b: jnp.where(won.reshape((-1,) + (1,) * (a.ndim - 1)), a, b), every, out)

        if len(ks) == 1:
            out = finish(out, params.objects[ks[0]], params.xforms[ks[0]], ks[0], casts[g])
        else:
            out = jax.lax.scan(lambda o, item: (finish(o, *item), None), out, (*_stacked(params, ks), casts[g]))[0]
    return out._replace(flags=flags | out.flags)  # every object's cast flags, and the finish's of the winner


def _stacked(params: SceneParams, ks) -> tuple:
    """The params, transforms and indices of a group's objects, stacked for a ``scan``."""
    stack = functools.partial(jax.tree_util.tree_map, lambda *a: jnp.stack(a))
    return stack(*[params.objects[k] for k in ks]), stack(*[params.xforms[k] for k in ks]), jnp.asarray(ks, jnp.int32)


def _no_cast(shapes: _Cast, n: int) -> _Cast:
    """N rows of an object's cast (``shapes``: one sub-batch's) where it casts nothing: t +inf,
    object -1, flags 0, the payload zero (never finished: such a row wins for no object)."""
    rows = jax.tree_util.tree_map(lambda s: jnp.zeros((n,) + s.shape[1:], s.dtype), shapes)
    return rows._replace(t=jnp.full((n,), jnp.inf, rows.t.dtype), obj=jnp.full((n,), -1, jnp.int32),
                         pre=rows.pre._replace(t=jnp.full((n,), jnp.inf, rows.pre.t.dtype), prim=jnp.full((n,), -1, jnp.int32)))


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
    lower object index, and every object's flags kept: a ray lost by one object is not decided."""
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
