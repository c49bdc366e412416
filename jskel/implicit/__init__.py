"""Skeletal implicit surfaces, Rouiller 2011 (seeds 002 and 003): metaballs and metatubes.

Public API: :func:`build` (host: validate, pad, cast) and :func:`intersect_one` (pure, one ray)
with the tracers of ``_trace`` selected by ``object.method``; ``REPRESENTATION`` for the
registry. Animation (bones), texture projectors, displacement and CSG are not implemented yet
(issue 4 lists them); (u, v) is 0 until texture projectors exist.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..interface import Built
from ..rays import Hit
from ._config import ImplicitConfig as ImplicitConfig
from ._field import Prims as Prims
from ._field import field as field
from ._field import gradient as gradient
from ._field import lipschitz as lipschitz
from ._trace import OVERFLOW as OVERFLOW
from ._trace import STEP_CAP as STEP_CAP
from ._trace import Quality as Quality
from ._trace import Tuning as Tuning
from ._trace import cull, surface_one, trace_one


class ImplicitScene(NamedTuple):
    prims: Prims
    tune: Tuning
    color: jnp.ndarray  # (3,)


def _pad(x, n, fill=0.0):
    pad = n - x.shape[0]
    return x if pad == 0 else np.concatenate([x, np.broadcast_to(np.asarray(fill, x.dtype), (pad,) + x.shape[1:])])


def _max_field_estimate(a, b, ra, rb) -> float:
    """max F over the skeleton (host, float64): F at 9 points along every primitive."""
    s = np.linspace(0, 1, 9)
    pts = (a[:, None, :] + s[None, :, None] * (b - a)[:, None, :]).reshape(-1, 3)
    best = 0.0
    for i in range(0, pts.shape[0], 2048):
        x = pts[i : i + 2048]
        ab = b - a
        ax = x[:, None, :] - a[None]
        den = np.sum(ab * ab, -1)
        t = np.clip(np.where(den > 0, np.sum(ax * ab[None], -1) / np.where(den > 0, den, 1), 0), 0, 1)
        d = ax - t[..., None] * ab[None]
        r2 = np.sum(d * d, -1)
        R = ra[None] + (rb - ra)[None] * t
        q = np.where(R > 0, r2 / np.where(R > 0, R * R, 1), 1)
        best = max(best, float(np.max(np.sum(np.where(q < 1, (1 - q) ** 2, 0), -1))))
    return best


def primitives(cfg: ImplicitConfig):
    """Host float64 (a, b, ra, rb) in world units, after scale and offset."""
    if cfg.procedural is not None:
        from ._models import MODELS

        a, b, ra, rb = MODELS[cfg.procedural](cfg.seed, dict(cfg.options))
    else:
        a = np.array([bl.center for bl in cfg.balls] + [t.a for t in cfg.tubes], np.float64).reshape(-1, 3)
        b = np.array([bl.center for bl in cfg.balls] + [t.b for t in cfg.tubes], np.float64).reshape(-1, 3)
        ra = np.array([bl.radius for bl in cfg.balls] + [t.radius_a for t in cfg.tubes], np.float64)
        rb = np.array([bl.radius for bl in cfg.balls] + [t.radius_b for t in cfg.tubes], np.float64)
    off = np.asarray(cfg.offset, np.float64)
    return a * cfg.scale + off, b * cfg.scale + off, ra * cfg.scale, rb * cfg.scale


def build(cfg: ImplicitConfig, dtype=np.float32) -> Built:
    """Validate, pad to a power of two (>= 8) so similar models share a compile, cast."""
    a, b, ra, rb = primitives(cfg)
    nb = len(cfg.balls) if cfg.procedural is None else 0
    if cfg.method == "lipschitz":
        for i in np.nonzero(np.minimum(ra, rb) <= 0)[0]:
            which = "radius_a" if ra[i] <= 0 else "radius_b"
            raise ValueError(f"object.tubes[{i - nb}].{which}: the lipschitz method needs both tube radii > 0 (its slope bound is 8/(3 sqrt(3) R))")
    fmax = _max_field_estimate(a, b, ra, rb)
    if not cfg.threshold < fmax:
        raise ValueError(f"object.threshold: {cfg.threshold} is not below the field's maximum (about {fmax:.4g}): no surface")
    p = a.shape[0]
    n = max(8, 1 << int(np.ceil(np.log2(p))))
    prims = Prims(
        jnp.asarray(_pad(a, n), dtype), jnp.asarray(_pad(b, n), dtype),
        jnp.asarray(_pad(ra, n), dtype), jnp.asarray(_pad(rb, n), dtype),
        jnp.asarray(np.arange(n) < p),
    )
    rmax = np.maximum(ra, rb)[:, None]
    lo = np.min(np.minimum(a, b) - rmax, 0)
    hi = np.max(np.maximum(a, b) + rmax, 0)
    anchor = 0.5 * (lo + hi)
    prims = prims._replace(a=prims.a - jnp.asarray(anchor, dtype), b=prims.b - jnp.asarray(anchor, dtype))
    tune = Tuning(jnp.asarray(cfg.threshold, dtype), jnp.asarray(cfg.step, dtype), jnp.asarray(cfg.eps, dtype))
    scene = ImplicitScene(prims, tune, jnp.asarray(cfg.color, dtype))
    q = Quality(cfg.method, cfg.steps, cfg.bisection, cfg.capacity, cfg.early_exit)
    info = {"primitives": int(p), "padded_primitives": int(n), "max_field_estimate": fmax}
    return Built(scene, q, anchor, (lo, hi), info)


def intersect_one(scene: ImplicitScene, static: Quality, origin, direction, t_min, t_max) -> Hit:
    cand = cull(scene.prims, origin, direction, t_min, t_max, static.capacity)
    t, flags = trace_one(cand, scene.tune, origin, direction, t_min, t_max, static)
    pos, n, prim = surface_one(cand, origin, direction, t)
    hit = jnp.isfinite(t)
    inf = jnp.asarray(jnp.inf, origin.dtype)
    return Hit(
        t=t,
        position=jnp.where(hit, pos, inf),
        normal=jnp.where(hit, n, 0.0),
        uv=jnp.zeros((2,), origin.dtype),
        prim=jnp.where(hit, prim, -1).astype(jnp.int32),
        flags=flags.astype(jnp.int32),
    )


def albedo(scene: ImplicitScene, static: Quality, hit: Hit):
    return scene.color


def inside(scene: ImplicitScene, static: Quality, point):
    return field(scene.prims, point) > scene.tune.threshold


class _Implicit:
    name = "implicit"
    Config = ImplicitConfig
    build = staticmethod(build)
    intersect_one = staticmethod(intersect_one)
    albedo = staticmethod(albedo)
    inside = staticmethod(inside)


REPRESENTATION = _Implicit()
