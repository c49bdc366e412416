"""The integrator of every render: a scene of objects with materials, lights and effects
(issue 7); a file's single ``object:`` is a scene of one (``config.ExperimentFile.experiment``).

A scene (``objects:`` in an experiment) holds objects of any representation, each with a
transform (uniform scale, XYZ Euler rotation, translation; plus a rigid ``motion`` per frame),
a material, and lights (directional or point, each casting shadows or not). The renderer talks
to every object through the representation interface only (``intersect_batch`` or
``intersect_one``, ``albedo``), so it never branches on a representation's type inside a kernel.
A scene of one is the same program with one object; without reflection or refraction its camera
rays are traced as one batch (no box test: the representation culls), and an object at its own
anchor skips its transform (``SceneStatic.identity``).

Frame. Rays are expressed relative to the camera's eye ("camera-relative rendering"): the
host computes, in float64, each object's offsets between that frame and the frame its params
are stored in (its build anchor), so float32 keeps full precision near the camera wherever the
scene sits in the world; with an identity transform a primary ray reaches an object as the
very floats the representation's own cast gives it (the two-object test relies on it).

Effects only where the scene calls for them, in both senses:

* statically (:func:`effects_of`): shadow code exists only if a light casts shadows, reflection
  code only if a material has ``reflectivity > 0``, refraction only if one has
  ``transparency > 0``, and bounce levels only if either exists. Which effects exist is part of
  the static key, so a scene without them compiles a program without their work (a test reads
  the jaxpr and XLA's cost analysis);
* per ray (wavefront style): every level of the ray tree is a fixed-capacity queue of rays.
  Each object traces only the queued rays that are live *and* cross its world bounding box
  before the nearest hit the objects traced before it found (a ray stopped in front of the box
  cannot be won by the object),
  gathered into dense sub-batches of ``lanes`` rays (``jskel.wavefront.compact_map``), each
  object's full hit merged into the nearest (casting every object and finishing only the
  winner was measured and not kept: docs/choices.md#surface-once); shadow rays
  are gathered the same way per light, and an object tests only the shadow rays that no earlier
  object has already blocked (early out across objects). In a scene (not a scene of one) a
  level's shadow rays travel in the next step's batch, behind the next level's rays, as
  any-hit rows of the same ``nearest`` (``_piped``), so each object's traversal appears once in
  the program instead of twice; objects of one representation, options and param shapes (a
  floor, a mirror and a glass rod of one segment each) share one traced copy, run over them in
  a ``scan`` (``_hits.groups``). Reflection and refraction rays are
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
An object alone in its scene may state a material of its own (``Representation.own_material``): a cell
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
from ..rays import FLAG_BAD_DIRECTION, FLAG_OVERFLOW, FLAG_TIR, Hit, Rays, or_flags_at
from ..wavefront import compact_map
from ..shading import facing, light_at, shade_local
from ._build import Effects as Effects
from ._build import Materials, SceneParams, SceneStatic
from ._hits import SceneHit as SceneHit
from ._hits import _miss, nearest, occluded
from ._queue import Queue as Queue
from ._queue import _camera_queue, _tir, _transmitted
from ._queue import spawn as spawn
from ._queue import spawned as spawned
from ._build import build_scene as build_scene
from ._build import effects_of as effects_of


SHADE_LANES = 1024  # hits per sub-batch of the local shading (cheap per ray: wide batches)


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


def shadow_rays(params: SceneParams, static: SceneStatic, hit: SceneHit, q_rays: Rays, live):
    """(rays, need), both of N*L rows (ray i's light l at row i*L + l): a shadow ray from each
    hit towards each light, needed only from live hits facing a light that casts shadows."""
    n, nl = hit.t.shape[0], params.lights.radiance.shape[0]
    got = live & jnp.isfinite(hit.t)
    nf = jax.vmap(facing)(hit.normal, q_rays.directions)
    p0 = jnp.where(got[:, None], hit.position, 0.0)
    ldir, _, dist = jax.vmap(lambda p: light_at(params.lights, p))(p0)  # (N,L,3), (N,L)
    facing_light = jnp.sum(ldir * nf[:, None, :], axis=-1) > 0
    need = got[:, None] & params.shadows[None, :] & facing_light
    each = jax.tree_util.tree_map(lambda a: jnp.repeat(a, nl, axis=0), (q_rays, hit))
    rays = spawned(each[0], each[1], params.mat, ldir.reshape(n * nl, 3), dist.reshape(n * nl))
    return rays, need.reshape(n * nl)


def _lit(blocked, n: int, nl: int, dtype):
    """(N, L) visibility from the shadow rays' (N*L,) ``blocked``: 0 where blocked, else 1."""
    return jnp.where(blocked.reshape(n, nl), 0.0, 1.0).astype(dtype)


def _visibility(params: SceneParams, static: SceneStatic, hit: SceneHit, q_rays: Rays, live):
    """(N, L) visibility of each light from each live hit: 1, or 0 where a shadow ray is
    blocked (its own any-hit pass, :func:`occluded`; a scene casts them with the next level's
    rays instead, ``_levels``)."""
    rays, need = shadow_rays(params, static, hit, q_rays, live)
    with jax.named_scope("shadow_rays"):
        blocked = occluded(params, static, rays, need)
    return _lit(blocked, hit.t.shape[0], params.lights.radiance.shape[0], hit.position.dtype)


def weights(m: Materials, hits: SceneHit, got, level):
    """(kr, kt) (N,) of each hit: the share of its light that comes by reflection and by
    refraction; past the first level a ``local_once`` material passes its light on whole."""
    k = jnp.maximum(hits.obj, 0)
    later = (level > 0) & (m.local_once[k] > 0)
    kr = jnp.where(got & ~later, m.reflect[k], 0.0)
    kt = jnp.where(got, jnp.where(later, 1.0, m.transmit[k]), 0.0)
    return kr, kt


def shade_level(params: SceneParams, static: SceneStatic, q: Queue, rgb, hits: SceneHit, vis, level=0):
    """``rgb`` (N,3) with one level's light added, each light seen as ``vis`` (Q, L) says. On
    the last level (``level == bounces``) a material with ``last_local`` keeps its local light
    whole (Nürnberg 2011, Alg. 3.2: the last bounce's hit is shaded, not weighted by 1 - k), and
    one with ``last_env`` adds the environment its refracted ray would see (Alg. 3.3's end)."""
    n_pix = rgb.shape[0]
    d = q.rays.directions
    got = q.live & jnp.isfinite(hits.t)
    m = params.mat
    k = jnp.maximum(hits.obj, 0)
    kd = hits.base * m.color[k]
    pos0 = jnp.where(got[:, None], hits.position, 0.0)

    def shade(args):
        return jax.vmap(lambda p, nn, dd, b, sp, sh, v: shade_local(p, nn, dd, b, params.lights, params.ambient, sp, sh, v))(*args)

    # local light only where a ray hit, in dense sub-batches (the misses take the environment)
    local = compact_map(shade, got, (pos0, hits.normal, d, kd, m.specular[k], m.shininess[k], vis), jnp.zeros_like(kd), SHADE_LANES)
    kr, kt = weights(m, hits, got, level)
    last = level == static.effects.bounces
    w_local = jnp.where(last & (m.last_local[k] > 0), 1.0, 1.0 - kr - kt)
    col = jnp.where(got[:, None], w_local[:, None] * local, _escaped(params, static, d))
    if static.effects.refraction:
        t, _, factor = _transmitted(m, hits, safe_normalize(d), kd)
        ends = got & last & (m.last_env[k] > 0)
        col = col + jnp.where(ends[:, None], kt[:, None] * factor * _escaped(params, static, t), 0.0)
    if static.effects.bounces == 0:  # the camera rays alone: slot i is pixel i, no scatter
        return rgb + q.weight * col
    dst = jnp.where(q.live, q.pixel, n_pix)
    return rgb.at[dst].add(q.weight * col, mode="drop")


class Records(NamedTuple):
    """What a chunk's pixels gather over the levels: colour, flags, where the first reflection /
    refraction path ends (N, 2), secondary rays, the camera rays' hits and their visibility."""

    rgb: jnp.ndarray
    flags: jnp.ndarray
    first_obj: jnp.ndarray
    secondary: jnp.ndarray
    aov: SceneHit
    vis0: jnp.ndarray


def _advance(params: SceneParams, static: SceneStatic, level, q: Queue, hits: SceneHit, rec: Records):
    """Level ``level``'s hits recorded (flags, the camera rays' AOVs, secondary rays, where paths
    end) and its reflection and refraction rays spawned: (next queue, records)."""
    n = rec.rgb.shape[0]
    levels = 1 + static.effects.bounces
    kr, kt = weights(params.mat, hits, q.live & jnp.isfinite(hits.t), level)
    flags = rec.flags
    if static.effects.refraction:  # the pixels whose refracted ray turned back (total internal reflection)
        tir = jnp.where(_tir(params, q, hits, kt), q.pixel, n)
        flags = flags | jnp.zeros_like(flags).at[tir].max(FLAG_TIR, mode="drop")  # one bit: a max is its or
    first = level == 0
    aov = hits if first is True else jax.tree_util.tree_map(lambda a, b: jnp.where(first, a[:n], b), hits, rec.aov)
    if levels == 1:  # the camera rays alone: slot i is pixel i, no scatter, no later level
        return q, rec._replace(flags=flags | jnp.where(q.live, hits.flags, 0), aov=aov)
    flags = or_flags_at(flags, jnp.where(q.live, q.pixel, n), hits.flags)  # a miss's flags too: a lost ray is one
    secondary = rec.secondary.at[jnp.where(q.live & ~first, q.pixel, n)].add(1, mode="drop")
    col = jnp.clip(q.kind - 1, 0, 1)
    # where the path of the first reflection / refraction ray ends: later levels overwrite
    first_obj = rec.first_obj.at[jnp.where(q.live & (level >= 1), q.pixel, n), col].set(hits.obj, mode="drop")
    q, pix, dropped, bad = spawn(params, static, q, hits, kr, kt, level)
    lost = jnp.where(dropped, FLAG_OVERFLOW, 0) | jnp.where(bad, FLAG_BAD_DIRECTION, 0)
    flags = or_flags_at(flags, jnp.where(lost != 0, pix, n), lost)
    return q, rec._replace(flags=flags, aov=aov, secondary=secondary, first_obj=first_obj)


def _levels(params: SceneParams, static: SceneStatic, q: Queue, rec: Records) -> Records:
    """The ray tree level by level, each level's shadow rays cast on their own (a scene of one;
    any render without shadows). ``level`` is traced, so every level runs one copy of the
    tracing code (unrolling them multiplied the compile time by the depth), and the loop ends at
    the first level with no live ray."""
    n, levels, eff = rec.rgb.shape[0], 1 + static.effects.bounces, static.effects

    def level_fn(level, q, rec):
        hits = nearest(params, static, q.rays, q.live)
        if eff.shadows:
            vis = _visibility(params, static, hits, q.rays, q.live)
        else:
            vis = jnp.ones((hits.t.shape[0], params.lights.radiance.shape[0]), rec.rgb.dtype)
        rgb = shade_level(params, static, q, rec.rgb, hits, vis, level)
        vis0 = vis if levels == 1 else jnp.where(level == 0, vis[:n], rec.vis0)
        return _advance(params, static, level, q, hits, rec._replace(rgb=rgb, vis0=vis0))

    if levels == 1:
        return level_fn(0, q, rec)[1]
    # stops early once a level spawns no ray (a scalar loop condition: a real branch)
    return jax.lax.while_loop(lambda c: (c[0] < levels) & jnp.any(c[1].live),
                              lambda c: (c[0] + 1, *level_fn(c[0], c[1], c[2])), (jnp.int32(0), q, rec))[2]


def _piped(params: SceneParams, static: SceneStatic, q: Queue, rec: Records) -> Records:
    """The ray tree of a scene with shadows, wavefront style: step i casts one batch, level i's
    rays followed by level i - 1's shadow rays (``nearest``'s any-hit rows), through each
    object once, then shades level i - 1 and spawns level i + 1. So each object's traversal is
    traced once in the program instead of once for hits and once for shadows. ``1 + bounces``
    levels take one step more than levels (the last casts shadow rays only); the loop ends
    once no level is left to cast or shade."""
    n, levels, dtype = rec.rgb.shape[0], 1 + static.effects.bounces, rec.rgb.dtype
    cap, nl = q.live.shape[0], params.lights.radiance.shape[0]
    any_hit = jnp.arange(cap * (1 + nl)) >= cap

    def step(c):
        i, q, prev, prev_hits, rec = c
        srays, sneed = shadow_rays(params, static, prev_hits, prev.rays, prev.live)
        both = jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b], axis=0), q.rays, srays)
        with jax.named_scope("rays_and_shadow_rays"):
            h = nearest(params, static, both, jnp.concatenate([q.live, sneed]), any_hit)
        hits = jax.tree_util.tree_map(lambda a: a[:cap], h)
        vis = _lit(jnp.isfinite(h.t[cap:]), cap, nl, dtype)
        rgb = shade_level(params, static, prev, rec.rgb, prev_hits, vis, i - 1)
        rec = rec._replace(rgb=jnp.where(i > 0, rgb, rec.rgb), vis0=jnp.where(i == 1, vis[:n], rec.vis0))
        q_next, rec = _advance(params, static, i, q, hits, rec)
        return i + 1, q_next._replace(live=q_next.live & (i + 1 < levels)), q, hits, rec

    dead = q._replace(live=jnp.zeros_like(q.live))
    init = (jnp.int32(0), q, dead, _miss(cap, dtype), rec)
    return jax.lax.while_loop(lambda c: jnp.any(c[1].live) | jnp.any(c[2].live), step, init)[4]


def scene_batch(static: SceneStatic):
    """The per-chunk function ``(params, rays) -> dict of per-ray outputs`` for a scene: only
    what the render writes (``render.aovs_of``): the camera ray's ``hit`` with its pixel's flags
    and ``rgb``; ``visibility`` and ``secondary`` where shadows and bounces exist or objects
    are several; ``obj`` and ``first_obj`` (where reflected / refracted paths end) with several."""
    eff = static.effects
    levels = 1 + eff.bounces
    cap_factor = 2 if (eff.reflection and eff.refraction and levels > 1) else 1  # no level after the camera's: N

    def batch(params: SceneParams, rays: Rays):
        n, dtype = rays.size, rays.origins.dtype
        q = _camera_queue(rays, cap_factor * n)
        rec = Records(jnp.zeros((n, 3), dtype), jnp.zeros((n,), jnp.int32), jnp.full((n, 2), -1, jnp.int32),
                      jnp.zeros((n,), jnp.int32), _miss(n, dtype), jnp.ones((n, params.lights.radiance.shape[0]), dtype))
        several = len(static.reps) > 1
        rec = (_piped if eff.shadows and several else _levels)(params, static, q, rec)
        a = rec.aov
        out = {"hit": Hit(a.t, a.position, a.normal, a.uv, a.prim, rec.flags), "rgb": rec.rgb}  # the pixel's flags
        if eff.shadows or several:
            out["visibility"] = rec.vis0
        if eff.bounces or several:
            out["secondary"] = rec.secondary
        if several:  # what only names one object among several
            out["obj"] = a.obj
            if eff.reflection or eff.refraction:
                out["first_obj"] = rec.first_obj
        return out

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

    def compiler_options(self) -> dict:
        """The XLA options its program compiles with on the CPU: those its objects'
        representations agree on (``interface.agreed_options``)."""
        from ..interface import agreed_options

        return agreed_options(self.static.reps, self.static.statics)


def scene_call(scene: Scene, rays: Rays) -> dict:
    """``scene_batch(scene.static)(scene.params, rays)``: the executor's batch function of
    every render (a second render of the same shapes compiles nothing)."""
    return scene_batch(scene.static)(scene.params, rays)


def _scene_problems(scene: Scene, rays: Rays):
    """``jskel.checks.traced`` on the camera rays, every object's ``traced_fields`` (under its key
    path as the file wrote it: ``object.``, ``objects[i].``), its placement unless it is the
    identity (``xform``: scale positive, rotation and offsets finite) and the lights' directions
    and radiance (finite)."""
    found = checks.traced("rays.origins", rays.origins) + checks.traced("rays.directions", rays.directions, "nonzero")
    p, st = scene.params, scene.static
    for rep, obj, x, path, ident in zip(st.reps, p.objects, p.xforms, st.paths, st.identity):
        at = path + "."
        for name, (a, kind, valid, ids) in registry.get(rep).traced_fields(obj).items():
            found += checks.traced(at + name, a, kind, valid, ids)
        if not ident:  # its placement (``SceneParams.xforms[i]``), by the field's name
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


__all__ = ["Effects", "Queue", "Scene", "SceneHit", "build_scene", "effects_of", "nearest", "occluded",
           "checked_scene_call", "scene_batch", "scene_call", "shade_level", "spawn", "spawned"]

