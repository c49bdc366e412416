"""Secondary rays that leave a surface without hitting it again (``jskel.spawn``).

A hit's position is computed in floating point (``o + t d``, a bisection's last bracket, a
voxel's face), so it lies on either side of the true surface; a ray started there hits the
surface it leaves on a large share of rays ("surface acne"), more so the farther the object is
from the rays' origin. pbrt-v4 (Pharr, Jakob, Humphreys, Sec. 6.8.6 "Robust spawned ray
origins") bounds the error of the position with gamma(n) = n u / (1 - n u) (Sec. 6.8.1) and moves
the origin along the normal, to the side of the new direction, by that bound projected on the
normal, then one float further. Here the bound is the error of ``o + t d`` (every tracer reports
its position that way, or nearer) plus the representation's own tolerance, a fact of its
``Built`` (:func:`surface_offset`), so no representation is named. :func:`refine` recomputes
hits from near (one more cast through the object), for rays from far away whose positions' error
would otherwise set the offset. The renderer's integrator
(``render/_scene.py``) spawns every shadow, reflection and refraction ray through
:func:`spawn_rays`; docs/numerics.md states the bound and its test (``tests/test_spawn.py``).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from . import checks
from .interface import Built
from .rays import FLAG_BAD_DIRECTION, Hit, Rays

#: the n of gamma(n) bounding a hit position's error per unit of |o| + |t d| + |p|, per
#: component. pbrt-v4 bounds ``o + t d`` by gamma(3) for an exact t (Sec. 6.8.4); the tracers'
#: t comes from longer chains (the frusta's recentred quadratic, a triangle's barycentrics, a
#: march's sample positions). ``tests/test_spawn.py``'s hits lie at most about 2 u x that sum
#: (projected on the normal) off the closed-form surface, so 16 leaves a margin of about 8
#: (docs/choices.md#spawn-gamma)
SPAWN_GAMMA_N = 16


def gamma(n: int, dtype) -> float:
    """pbrt-v4's gamma(n) = n u / (1 - n u) (Sec. 6.8.1) for ``dtype``'s unit roundoff u =
    eps / 2: a bound on the relative error of a chain of n floating-point operations."""
    u = float(np.finfo(dtype).eps) / 2.0
    return n * u / (1.0 - n * u)


def surface_offset(source) -> float:
    """The part of a spawn offset a representation states about its own surface, in its units:
    ``Built.secondary_offset`` where it sets one (a cell object's voxel: Nürnberg 2011 Alg. 3.2
    starts secondary rays one voxel out), else four times ``Built.surface_tolerance`` (how far a
    hit may lie from the true surface: a marching tracer's last bisection bracket; 0 for
    analytic intersections). ``source``: a ``Built``, or a number (returned as it is)."""
    if isinstance(source, Built):
        off = source.secondary_offset
        return float(4.0 * source.surface_tolerance if off is None else off)
    return source


def spawn(source, rays: Rays, hit: Hit, directions, t_max=np.inf) -> Rays:
    """Secondary rays leaving the surface at ``hit`` along ``directions``, one per ray.

    source: the ``Built`` the hit came from (``rep.build(cfg)``), or a number, the surface part
      of the offset in the rays' units (:func:`surface_offset`).
    rays: the rays that made ``hit``; hit: what a public intersect returned for them
      (``frusta.intersect``, ``implicit.intersect_batch``, ``mesh.intersect_batch``,
      ``interface.intersect``, ...), in the same frame (relative to the object's anchor).
    directions: (N, 3) the new directions, any non-zero length.
    t_max: () or (N,) the new rays' far end (a shadow ray's distance to its light).

    Each origin is the hit's position moved along its normal, to the side ``directions`` points
    to, by ``gamma(SPAWN_GAMMA_N)`` x (|o| + |t d| + |p|) per component projected on |n|, plus
    :func:`surface_offset`, then rounded one float further (pbrt-v4 Sec. 6.8.6). A ray that leaves
    a convex piece of surface outward from there cannot meet it again, at any translation or
    scale, and a surface farther than the offset is still found (``tests/test_spawn.py``).
    The offset grows with the rays' distance (|o| + |t d|): for rays from 1e5 object sizes
    away it is about 0.2 of the size in float32 (the positions there are good to ~1e-2 of it).
    pbrt's own term, gamma(n) |p|, bounds a point recomputed on the surface; ``o + t d``'s
    error follows |o| + |t d|, and such hits lie far beyond gamma(16) |p| off the surface
    (docs/numerics.md, ``tests/test_spawn.py``), so the term stays; :func:`refine` recomputes
    the hits from near first, and the offset from its near rays is about 1e-3 of the size there.
    Rays of misses are empty (origin 0, t_min = 0 > t_max = -1) and hit nothing; so are rays
    whose direction is zero or not finite (direction +z instead), which :func:`spawn_flags`
    marks with ``FLAG_BAD_DIRECTION`` and :func:`checked_spawn` reports. Pure, jit- and
    grad-friendly: the origins differentiate as the hit positions do."""
    return spawn_rays(rays, hit.t, hit.position, hit.normal, jnp.asarray(directions), surface_offset(source), t_max)


#: the cosine below which :func:`refine` treats a ray as grazing: its step back (four times
#: the position's error along the ray) stops growing there, so a grazing hit may keep its own
#: position (no refined hit in the window)
REFINE_COS_FLOOR = 1.0 / 64.0


def refine(source, obj, rays: Rays, hit: Hit) -> tuple[Rays, Hit]:
    """The hits recomputed from near, so that their positions' error follows the object's size
    instead of the rays' distance: (near rays, refined hits), to hand to :func:`spawn`.

    pbrt-v4 recomputes a hit on the surface in the object's frame (a sphere's reprojection, a
    triangle's barycentric sum: Sec. 6.8.2-6.8.5), so its spawn offset bounds gamma(n) |p|. Here
    every representation's hit is ``o + t d``, good to about gamma (|o| + |t d|): for rays from
    1e5 object sizes away, a tenth of the size, which :func:`spawn`'s offset must cover. This
    casts each hit's ray again through ``obj`` (an ``interface.Object``, the one the hits came
    from; ``source`` its ``Built`` or a number, as :func:`spawn` takes) from the point 4 e
    before the hit along it, e its position's error along the ray (the bound :func:`spawn`
    uses, with the surface's own part, over the cosine between ray and normal, floored at
    :data:`REFINE_COS_FLOOR`); the new hit is kept where it lies within 2 e of that distance and
    its normal is on the same side as the old one. Its position is then good to about gamma
    (|p| + 8 e) plus the tracer's own tolerance, and so is the offset :func:`spawn` computes from
    the near rays (``tests/test_spawn.py``: at 1e5 sizes, below 1e-3 of the size). Elsewhere
    (misses, grazing rays, a recast that found another part of the object first) the hit and
    ray stay as they were. The recast stays within the ray's own window (t_min, t_max), and a
    kept hit carries the first cast's flags as well as its own. One more cast per ray; the renderer does not call it (its rays start
    at the camera, near the scene, or at a spawned origin). Pure and jit-friendly."""
    from .interface import intersect

    got = jnp.isfinite(hit.t)
    dn = jnp.linalg.norm(rays.directions, axis=-1)
    u = rays.directions / jnp.where(dn > 0, dn, 1.0)[:, None]
    p = jnp.where(got[:, None], hit.position, 0.0)
    tt = jnp.where(got, hit.t, 0.0)[:, None]
    err_n = _offset_bound(rays, tt, p, hit.normal, surface_offset(source))
    cos = jnp.abs(jnp.sum(u * hit.normal, axis=-1))
    e = err_n / jnp.maximum(cos, REFINE_COS_FLOOR)
    # within the ray's own window: never back past its start (a surface t_min excluded) nor on past its end
    back = jnp.minimum(4.0 * e, jnp.maximum(tt[:, 0] - rays.t_min, 0.0) * dn)
    end = back + jnp.minimum(2.0 * e, jnp.maximum(rays.t_max - tt[:, 0], 0.0) * dn)
    near = Rays(p - back[:, None] * u, u, jnp.zeros_like(back), jnp.where(got, end, -1.0))
    again = intersect(obj, near)
    keep = got & (jnp.abs(again.t - back) <= 2.0 * e) & (jnp.sum(again.normal * hit.normal, axis=-1) > 0)
    pick = lambda a, b: jnp.where(keep.reshape(keep.shape + (1,) * (a.ndim - 1)), a, b)  # noqa: E731
    # a kept hit carries what the first cast could not decide as well as its own flags
    flags = None if hit.flags is None and again.flags is None else (
        (0 if hit.flags is None else hit.flags) | (0 if again.flags is None else jnp.where(keep, again.flags, 0)))
    out = Hit(*(pick(a, b) for a, b in zip(again[:5], hit[:5])), flags)
    return Rays(*(pick(a, b) for a, b in zip(near, rays))), out


def bad_directions(directions):
    """(N,) bool: the directions (N, 3) no ray can follow, zero or with a NaN or an infinity."""
    return ~jnp.all(jnp.isfinite(directions), axis=-1) | jnp.all(directions == 0, axis=-1)


def spawn_flags(directions):
    """(N,) int32 ``Hit.flags`` bits of the rays :func:`spawn` makes along ``directions``:
    ``FLAG_BAD_DIRECTION`` where the direction is zero or not finite (that ray is empty: a
    lost ray, never a silent one), 0 elsewhere. OR it into the flags of what the rays hit."""
    return jnp.where(bad_directions(directions), FLAG_BAD_DIRECTION, 0).astype(jnp.int32)


def _offset_bound(rays: Rays, tt, p, normal, surface):
    """(N,) the bound on a hit position's error projected on its normal, plus the surface's own
    part: gamma(SPAWN_GAMMA_N) x sum_i |n_i| (|o_i| + |t d_i| + |p_i|) + ``surface`` (t (N, 1)
    and p (N, 3) zero on misses; non-finite origins count as 0)."""
    o = jnp.where(jnp.isfinite(rays.origins), rays.origins, 0.0)
    err = gamma(SPAWN_GAMMA_N, p.dtype) * (jnp.abs(o) + jnp.abs(tt * rays.directions) + jnp.abs(p))
    return jnp.sum(jnp.abs(normal) * err, axis=-1) + jnp.asarray(surface, p.dtype)


def spawn_rays(rays: Rays, t, position, normal, directions, surface, t_max=np.inf) -> Rays:
    """:func:`spawn` from a hit's fields t (N,), position and normal (N, 3); ``surface`` () or
    (N,) the surface part of the offset in the rays' units (a scene's per-object value)."""
    dtype = position.dtype
    bad = bad_directions(directions)
    hit = jnp.isfinite(t) & ~bad
    p = jnp.where(hit[:, None], position, 0.0)
    tt = jnp.where(hit, t, 0.0)[:, None]
    off = _offset_bound(rays, tt, p, normal, surface)
    side = jnp.where(jnp.sum(normal * directions, axis=-1) < 0, -1.0, 1.0).astype(dtype)
    push = side[:, None] * normal
    q = p + off[:, None] * push
    # one float further along the push: the sum above rounds to nearest (a constant step for
    # derivatives: nextafter has none)
    qs = jax.lax.stop_gradient(q)
    away = jnp.where(push > 0, jnp.nextafter(qs, jnp.asarray(jnp.inf, dtype)),
                     jnp.where(push < 0, jnp.nextafter(qs, jnp.asarray(-jnp.inf, dtype)), qs))
    q = q + (away - qs)
    zero = jnp.zeros_like(tt[:, 0])
    far = jnp.broadcast_to(jnp.asarray(t_max, dtype), zero.shape)
    d = jnp.where(bad[:, None], jnp.asarray([0.0, 0.0, 1.0], dtype), directions.astype(dtype))
    return Rays(jnp.where(hit[:, None], q, 0.0), d, zero, jnp.where(hit, far, -1.0))


def _spawn_problems(rays, t, position, normal, directions, *_):
    return checks.traced("directions", directions, "nonzero")


_checked_spawn_rays = checks.checked(spawn_rays, _spawn_problems)


def checked_spawn(source, rays: Rays, hit: Hit, directions, t_max=np.inf) -> Rays:
    """:func:`spawn` with its directions checked inside the compiled function
    (``jskel.checks.checked``): zero or non-finite directions raise one ValueError naming every
    such ray by index and value (``directions[5]: is the zero vector (got [0, 0, 0]); 1 of 64
    entries``) instead of coming back as empty rays. One module-level jit: new values of the
    same shapes compile nothing."""
    return _checked_spawn_rays(rays, hit.t, hit.position, hit.normal, jnp.asarray(directions), surface_offset(source), t_max)


__all__ = ["REFINE_COS_FLOOR", "SPAWN_GAMMA_N", "bad_directions", "checked_spawn", "gamma", "refine", "spawn", "spawn_flags", "spawn_rays", "surface_offset"]
