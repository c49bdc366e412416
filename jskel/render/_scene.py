"""The integrator of every render: scenes of several objects with materials, lights and
effects (issue 7), and a single object as a scene of one (``_build.build_single``).

A scene (``objects:`` in an experiment) holds objects of any representation, each with a
transform (uniform scale, XYZ Euler rotation, translation; plus a rigid ``motion`` per frame),
a material, and lights (directional or point, each casting shadows or not). The renderer talks
to every object through the representation interface only (``intersect_batch`` or
``intersect_one``, ``albedo``), so it never branches on a representation's type inside a kernel.
A single object is the same program with one object, the identity transform and the default
material; its camera rays are traced as one batch (``SceneStatic.single``: no box test, the
representation culls) and it returns a single-object render's outputs.

Frame. Rays are expressed relative to the camera's eye ("camera-relative rendering"): the
host computes, in float64, each object's offsets between that frame and the frame its params
are stored in (its build anchor), so float32 keeps full precision near the camera wherever the
scene sits in the world; with an identity transform a primary ray reaches an object as the
very floats a single-object render gives it (the two-object test relies on it).

Effects only where the scene calls for them, in both senses:

* statically (:func:`effects_of`): shadow code exists only if a light casts shadows, reflection
  code only if a material has ``reflectivity > 0``, refraction only if one has
  ``transparency > 0``, and bounce levels only if either exists. Which effects exist is part of
  the static key, so a scene without them compiles a program without their work (a test reads
  the jaxpr and XLA's cost analysis);
* per ray (wavefront style): every level of the ray tree is a fixed-capacity queue of rays.
  Each object traces only the queued rays that are live *and* cross its world bounding box,
  gathered into dense sub-batches of ``lanes`` rays (``jskel.wavefront.compact_map``); shadow rays
  are gathered the same way per light, and an object tests only the shadow rays that no earlier
  object has already blocked (early out across objects). Reflection and refraction rays are
  compacted into the next level's queue (``jnp.nonzero`` with a static size). Under ``vmap`` a
  ``lax.cond`` would run both branches for every ray; here the work follows the number of rays
  that need it (the ``bench_effects`` benchmark measures 10/50/100 % reflective coverage).

The queue holds ``N`` rays (the chunk) when each hit spawns at most one secondary ray, and
``2N`` when materials both reflect and refract; a level whose rays do not fit drops the excess
and flags their pixels with ``FLAG_OVERFLOW`` (counted in ``run.json``, never silent).

Shading (Whitted 1980): a hit's colour is ``(1 - kr - kt) * local + kr * L(reflected) + kt *
L(refracted)``, where ``local`` is ambient + Lambert + Blinn-Phong with each light's
visibility; total internal reflection turns the refracted ray into a reflected one (``jskel.optics``;
the pixel gains the ``FLAG_TIR`` bit); rays beyond
``render.bounces`` contribute nothing; rays that escape take the environment's colour. Secondary
rays (shadow, reflection, refraction) are spawned as ``jskel.spawn`` spawns them
(``spawning.spawn_rays``): offset along the normal, to the side of their direction, by a float
rounding bound on the hit's position (pbrt-v4 Sec. 6.8.6) plus the object's own surface offset
(``Built.secondary_offset`` or four times ``Built.surface_tolerance``, scaled by its placement):
a fixed epsilon fails once the scene is scaled or moved.

Transparent objects must report the exit of a ray from inside (``exits_from_inside(cfg)`` in
the interface: frusta without relief, whose intersection is analytic, and a cell object in
refraction mode); the implicit tracer searches for the first entry only (a ValueError says so).
A single object may state a material of its own (``Representation.own_material``): a cell
object's reflection and refraction modes (Nürnberg 2011, Alg. 3.2-3.3) are such materials, with
``Materials.last_local``, ``last_env``, ``local_once`` and ``tint`` saying how their paths end.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import checks, registry
from ..numerics import safe_normalize
from ..optics import reflect, refract_surface
from ..rays import FLAG_BAD_DIRECTION, FLAG_OVERFLOW, FLAG_TIR, Hit, Rays, or_flags_at
from ..spawning import bad_directions, spawn_rays
from ..wavefront import compact_map
from ..shading import facing, light_at, shade_local
from ._build import Effects as Effects
from ._build import Materials, SceneParams, SceneStatic
from ._hits import SceneHit as SceneHit
from ._hits import _miss, nearest, occluded
from ._build import build_scene as build_scene
from ._build import build_single as build_single
from ._build import effects_of as effects_of


SHADE_LANES = 1024  # hits per sub-batch of the local shading (cheap per ray: wide batches)


def spawned(q_rays: Rays, hit: SceneHit, mat: Materials, directions, t_max=jnp.inf) -> Rays:
    """Secondary rays from each hit along ``directions`` (``spawning.spawn_rays``, as
    ``jskel.spawn``): offset along the normal, to the directions' side, by a float rounding bound
    on the hit's position (pbrt-v4 Sec. 6.8.6) plus the object's own surface offset
    (``Materials.offset``: ``Built.secondary_offset`` or four times its surface tolerance,
    scaled by its placement)."""
    surface = mat.offset[jnp.maximum(hit.obj, 0)]
    return spawn_rays(q_rays, hit.t, hit.position, hit.normal, directions, surface, t_max)


def environment(env, d):
    """Sky gradient over world y: horizon -> zenith upwards, horizon -> ground downwards."""
    y = safe_normalize(d)[..., 1:2]
    up = env[1] + (env[0] - env[1]) * jnp.maximum(y, 0.0)
    down = env[1] + (env[2] - env[1]) * jnp.maximum(-y, 0.0)
    return jnp.where(y >= 0, up, down)


def _escaped(params: SceneParams, static: SceneStatic, d):
    """(N, 3) what rays that escape see: the experiment's environment, or a scene of one's own
    (``Representation.environment``, e.g. a cell object's sky; its frame is the world's)."""
    if static.sky:
        rep = registry.get(static.reps[0])
        return jax.vmap(lambda dd: rep.environment(params.objects[0], static.statics[0], dd))(d).astype(d.dtype)
    return environment(params.env, d)


def _visibility(params: SceneParams, static: SceneStatic, hit: SceneHit, q_rays: Rays, live):
    """(N, L) visibility of each light from each live hit: 1, or 0 where a shadow ray is
    blocked. Shadow rays exist only for hits facing the light, of lights casting shadows."""
    n, nl = hit.t.shape[0], params.lights.radiance.shape[0]
    got = live & jnp.isfinite(hit.t)
    nf = jax.vmap(facing)(hit.normal, q_rays.directions)
    p0 = jnp.where(got[:, None], hit.position, 0.0)
    ldir, _, dist = jax.vmap(lambda p: light_at(params.lights, p))(p0)  # (N,L,3), (N,L)
    facing_light = jnp.sum(ldir * nf[:, None, :], axis=-1) > 0
    need = got[:, None] & params.shadows[None, :] & facing_light
    each = jax.tree_util.tree_map(lambda a: jnp.repeat(a, nl, axis=0), (q_rays, hit))
    rays = spawned(each[0], each[1], params.mat, ldir.reshape(n * nl, 3), dist.reshape(n * nl))
    with jax.named_scope("shadow_rays"):
        blocked = occluded(params, static, rays, need.reshape(n * nl))
    return jnp.where(blocked.reshape(n, nl), 0.0, 1.0).astype(p0.dtype)


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


def shade_level(params: SceneParams, static: SceneStatic, q: Queue, rgb, hits: SceneHit, level=0):
    """Add one level's light to ``rgb`` (N,3) and return (rgb, visibility, kr, kt). On the last
    level (``level == bounces``) a material with ``last_local`` keeps its local light whole
    (Nürnberg 2011, Alg. 3.2: the last bounce's hit is shaded, not weighted by 1 - k), and one
    with ``last_env`` adds the environment its refracted ray would see (Alg. 3.3's end)."""
    n_pix = rgb.shape[0]
    d = q.rays.directions
    got = q.live & jnp.isfinite(hits.t)
    if static.effects.shadows:
        vis = _visibility(params, static, hits, q.rays, q.live)
    else:
        vis = jnp.ones((hits.t.shape[0], params.lights.radiance.shape[0]), d.dtype)
    m = params.mat
    k = jnp.maximum(hits.obj, 0)
    kd = hits.base * m.color[k]
    pos0 = jnp.where(got[:, None], hits.position, 0.0)

    def shade(args):
        return jax.vmap(lambda p, nn, dd, b, sp, sh, v: shade_local(p, nn, dd, b, params.lights, params.ambient, sp, sh, v))(*args)

    # local light only where a ray hit, in dense sub-batches (the misses take the environment)
    local = compact_map(shade, got, (pos0, hits.normal, d, kd, m.specular[k], m.shininess[k], vis), jnp.zeros_like(kd), SHADE_LANES)
    later = (level > 0) & (m.local_once[k] > 0)  # past the first level: light passed on whole
    kr = jnp.where(got & ~later, m.reflect[k], 0.0)
    kt = jnp.where(got, jnp.where(later, 1.0, m.transmit[k]), 0.0)
    last = level == static.effects.bounces
    w_local = jnp.where(last & (m.last_local[k] > 0), 1.0, 1.0 - kr - kt)
    col = jnp.where(got[:, None], w_local[:, None] * local, _escaped(params, static, d))
    if static.effects.refraction:
        t, _, factor = _transmitted(m, hits, safe_normalize(d), kd)
        ends = got & last & (m.last_env[k] > 0)
        col = col + jnp.where(ends[:, None], kt[:, None] * factor * _escaped(params, static, t), 0.0)
    if static.effects.bounces == 0:  # the camera rays alone: slot i is pixel i, no scatter
        return rgb + q.weight * col, vis, kr, kt
    dst = jnp.where(q.live, q.pixel, n_pix)
    rgb = rgb.at[dst].add(q.weight * col, mode="drop")
    return rgb, vis, kr, kt


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


def scene_batch(static: SceneStatic):
    """The per-chunk function ``(params, rays) -> dict of per-ray outputs`` for a scene."""
    eff = static.effects
    levels = 1 + eff.bounces
    cap_factor = 2 if (eff.reflection and eff.refraction and levels > 1) else 1  # no level after the camera's: N

    def batch(params: SceneParams, rays: Rays):
        n, dtype = rays.size, rays.origins.dtype
        q = _camera_queue(rays, cap_factor * n)
        rgb = jnp.zeros((n, 3), dtype)
        flags = jnp.zeros((n,), jnp.int32)
        first_obj = jnp.full((n, 2), -1, jnp.int32)  # where the reflection / refraction path ends
        secondary = jnp.zeros((n,), jnp.int32)

        def level_fn(level, carry):
            """One level of the ray tree; ``level`` is traced, so every level runs one copy of
            the tracing code (unrolling them multiplied the compile time by the depth), and the
            loop ends at the first level with no live ray."""
            q, rgb, flags, first_obj, secondary, aov, vis0 = carry
            hits = nearest(params, static, q.rays, q.live)
            rgb, vis, kr, kt = shade_level(params, static, q, rgb, hits, level)
            first = level == 0
            if static.effects.refraction:  # the pixels whose refracted ray turned back (total internal reflection)
                tir = jnp.where(_tir(params, q, hits, kt), q.pixel, n)
                flags = flags | jnp.zeros_like(flags).at[tir].max(FLAG_TIR, mode="drop")  # one bit: a max is its or
            if levels == 1:  # the camera rays alone: slot i is pixel i, no scatter, no later level
                return q, rgb, flags | jnp.where(q.live, hits.flags, 0), first_obj, secondary, hits, vis
            flags = or_flags_at(flags, jnp.where(q.live, q.pixel, n), hits.flags)  # a miss's flags too: a lost ray is one
            aov = jax.tree_util.tree_map(lambda a, b: jnp.where(first, a[:n], b), hits, aov)
            vis0 = jnp.where(first, vis[:n], vis0)
            secondary = secondary.at[jnp.where(q.live & ~first, q.pixel, n)].add(1, mode="drop")
            col = jnp.clip(q.kind - 1, 0, 1)
            # where the path of the first reflection / refraction ray ends: later levels overwrite
            first_obj = first_obj.at[jnp.where(q.live & (level >= 1), q.pixel, n), col].set(hits.obj, mode="drop")
            if levels > 1:
                q, pix, dropped, bad = spawn(params, static, q, hits, kr, kt, level)
                lost = jnp.where(dropped, FLAG_OVERFLOW, 0) | jnp.where(bad, FLAG_BAD_DIRECTION, 0)
                flags = or_flags_at(flags, jnp.where(lost != 0, pix, n), lost)
            return q, rgb, flags, first_obj, secondary, aov, vis0

        aov = _miss(n, dtype)
        vis0 = jnp.ones((n, params.lights.radiance.shape[0]), dtype)
        carry = (q, rgb, flags, first_obj, secondary, aov, vis0)
        if levels == 1:
            carry = level_fn(0, carry)
        else:  # stops early once a level spawns no ray (a scalar loop condition: a real branch)
            carry = jax.lax.while_loop(lambda c: (c[0] < levels) & jnp.any(c[1][0].live),
                                       lambda c: (c[0] + 1, level_fn(c[0], c[1])), (jnp.int32(0), carry))[1]
        _, rgb, flags, first_obj, secondary, aov, vis0 = carry
        if static.single:  # a single object's outputs: its hit, the colour, the shadows it asked for
            out = {"hit": Hit(aov.t, aov.position, aov.normal, aov.uv, aov.prim, flags), "rgb": rgb}
            return {**out, "visibility": vis0} if eff.shadows else out
        return {"hit": aov, "rgb": rgb, "visibility": vis0, "flags": flags, "first_obj": first_obj, "secondary": secondary}

    return batch


@jax.tree_util.register_pytree_node_class
@dataclass(frozen=True)
class Scene:
    """A built scene as one pytree: ``params`` (:class:`SceneParams`) its children, ``static``
    (:class:`SceneStatic`, hashable) its aux data, so the tree structure carries the static key
    (STYLE.md item 4) and :func:`scene_call`, one module-level function, compiles once per
    static key in JAX's and the executor's caches."""

    params: SceneParams
    static: SceneStatic

    def tree_flatten(self):
        return (self.params,), self.static

    @classmethod
    def tree_unflatten(cls, static, children):
        return cls(children[0], static)


def scene_call(scene: Scene, rays: Rays) -> dict:
    """``scene_batch(scene.static)(scene.params, rays)``: the executor's batch function of
    every render (a second render of the same shapes compiles nothing)."""
    return scene_batch(scene.static)(scene.params, rays)


def _scene_problems(scene: Scene, rays: Rays):
    """``jskel.checks.traced`` on the camera rays, every object's ``traced_fields`` (under
    ``object.`` for a single object, ``objects[i].`` in a scene), its placement (``xform``: scale
    positive, rotation and offsets finite) and the lights' directions and radiance (finite)."""
    found = checks.traced("rays.origins", rays.origins) + checks.traced("rays.directions", rays.directions, "nonzero")
    p, single = scene.params, scene.static.single
    for i, (rep, obj, x) in enumerate(zip(scene.static.reps, p.objects, p.xforms)):
        at = "object." if single else f"objects[{i}]."
        for name, (a, kind, valid, ids) in registry.get(rep).traced_fields(obj).items():
            found += checks.traced(at + name, a, kind, valid, ids)
        if not single:  # its placement (``SceneParams.xforms[i]``), by the field's name
            found += checks.traced(at + "xform.s", jnp.reshape(x.s, (1,)), "positive")
            for name in ("r", "c", "g"):
                found += checks.traced(f"{at}xform.{name}", jnp.reshape(getattr(x, name), (1, -1)))
    return found + checks.traced("lights.direction", p.lights.direction) + checks.traced("lights.radiance", p.lights.radiance)


#: :func:`scene_call` with its traced inputs checked inside the compiled function
#: (``jskel.checks.checked``): a ray, an object's params (a device rebuild's, an optimiser's),
#: a placement or a light that turned bad raises one ValueError with a line per failing field
#: (``objects[1].segments.r1[3]: not finite (got nan); 1 of 12 entries``) instead of a silent
#: image. One module-level jit, cached per static key as :func:`scene_call` is.
checked_scene_call = checks.checked(scene_call, _scene_problems)


__all__ = ["Effects", "Queue", "Scene", "SceneHit", "build_scene", "build_single", "effects_of", "nearest", "occluded",
           "checked_scene_call", "scene_batch", "scene_call", "shade_level", "spawn", "spawned"]

