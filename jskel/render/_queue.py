"""The ray tree's queues (see ``_scene``): one level's rays with their weights and pixels, the
camera's first level, and the reflection and refraction rays a level spawns, compacted into the
next level's queue of fixed capacity (those that do not fit are reported, never silent)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..numerics import safe_normalize
from ..optics import reflect, refract_surface
from ..rays import Rays
from ..shading import facing
from ..spawning import bad_directions, spawn_rays
from ._build import Materials, SceneParams, SceneStatic
from ._hits import SceneHit


def spawned(q_rays: Rays, hit: SceneHit, mat: Materials, directions, t_max=jnp.inf) -> Rays:
    """Secondary rays from each hit along ``directions`` (``spawning.spawn_rays``, as
    ``jskel.spawn``): offset along the normal, to the directions' side, by a float rounding bound
    on the hit's position (pbrt-v4 Sec. 6.8.6) plus the object's own surface offset
    (``Materials.offset``: ``Built.secondary_offset`` or four times its surface tolerance,
    scaled by its placement)."""
    surface = mat.offset[jnp.maximum(hit.obj, 0)]
    return spawn_rays(q_rays, hit.t, hit.position, hit.normal, directions, surface, t_max)


def _tir(params: SceneParams, q, hits: SceneHit, kt):
    """Which live rays of a level are refracted at their hit (``kt > 0``) beyond the critical
    angle: ``jskel.optics.refract_surface``'s mask, for the pixels' ``FLAG_TIR`` bit."""
    _, tir = refract_surface(q.rays.directions, hits.normal, params.mat.ior[jnp.maximum(hits.obj, 0)])
    return q.live & (kt > 0) & tir


class Queue(NamedTuple):
    """One level of the ray tree: Q rays with their weight, pixel (slot in the chunk), kind (0
    camera, 1 reflection, 2 refraction at the first bounce) and whether the slot is live."""

    rays: Rays
    weight: jnp.ndarray
    pixel: jnp.ndarray
    kind: jnp.ndarray
    live: jnp.ndarray


def _compact_queue(cands: Queue, cap: int):
    """The live candidates moved to the front of a queue of ``cap`` slots; (queue, dropped)
    where ``dropped`` (M,) marks live candidates that did not fit."""
    live = cands.live
    idx = jnp.nonzero(live, size=cap, fill_value=0)[0]
    count = jnp.sum(live.astype(jnp.int32))
    keep = jnp.arange(cap) < count
    q = jax.tree_util.tree_map(lambda a: a[idx], cands)
    q = q._replace(live=keep)
    rank = jnp.cumsum(live.astype(jnp.int32)) - 1
    return q, live & (rank >= cap)


def _transmitted(m: Materials, hits: SceneHit, d, kd):
    """The refracted direction at each hit (the mirrored one under total internal reflection),
    whether it is one, and the colour factor of a ``tint`` material where the ray enters:
    0.5 + 0.5 x the colour there (Nürnberg 2011, Sec. 3.2.4), 1 elsewhere."""
    k = jnp.maximum(hits.obj, 0)
    t, tir = refract_surface(d, hits.normal, m.ior[k])
    entering = (jnp.sum(d * hits.normal, axis=-1) < 0) & ~tir
    factor = jnp.where(((m.tint[k] > 0) & entering)[:, None], 0.5 + 0.5 * kd, 1.0)
    return t, tir, factor


def spawn(params: SceneParams, static: SceneStatic, q: Queue, hits: SceneHit, kr, kt, level: int):
    """Reflection and refraction rays of a level, compacted into the next level's queue.
    Returns (queue, the candidates' pixels, which candidates were dropped, which asked for a
    zero or non-finite direction, ``spawning.bad_directions``: left out of the queue)."""
    eff = static.effects
    d = safe_normalize(q.rays.directions)
    nf = jax.vmap(facing)(hits.normal, d)
    cands, dirs = [], []
    if eff.reflection:
        with jax.named_scope("reflection_rays"):
            r = reflect(d, nf)
            kind = jnp.where(level == 0, 1, q.kind).astype(jnp.int32)
            cands.append(Queue(spawned(q.rays, hits, params.mat, r), q.weight * kr[:, None], q.pixel, kind, q.live & (kr > 0)))
            dirs.append(r)
    if eff.refraction:
        with jax.named_scope("refraction_rays"):
            kd = hits.base * params.mat.color[jnp.maximum(hits.obj, 0)]
            t, _, factor = _transmitted(params.mat, hits, d, kd)  # t: through the surface, or back on the near side under TIR
            kind = jnp.where(level == 0, 2, q.kind).astype(jnp.int32)
            cands.append(Queue(spawned(q.rays, hits, params.mat, t), q.weight * kt[:, None] * factor, q.pixel, kind, q.live & (kt > 0)))
            dirs.append(t)
    allc = jax.tree_util.tree_map(lambda *xs: jnp.concatenate(xs, axis=0), *cands)
    bad = allc.live & bad_directions(jnp.concatenate(dirs, axis=0))  # (a ray spawned empty: it would see the environment)
    nq, dropped = _compact_queue(allc._replace(live=allc.live & ~bad), q.live.shape[0])
    return nq, allc.pixel, dropped, bad


def _camera_queue(rays: Rays, cap: int) -> Queue:
    """The first level's queue of ``cap`` slots: the camera rays (slot i is pixel i, weight 1,
    kind 0), then dead padding slots for the rays later levels spawn."""
    n, dtype = rays.size, rays.origins.dtype
    pad = cap - n

    def padded(a, fill):
        return jnp.concatenate([a, jnp.full((pad,) + a.shape[1:], fill, a.dtype)], axis=0) if pad else a

    return Queue(Rays(padded(rays.origins, 0.0), padded(rays.directions, 1.0), padded(rays.t_min, 0.0), padded(rays.t_max, 0.0)),
                 jnp.ones((cap, 3), dtype), jnp.arange(cap, dtype=jnp.int32) % n, jnp.zeros((cap,), jnp.int32),
                 jnp.arange(cap) < n)
