"""Ray batches and the ``Hit`` record shared by every representation.

A representation's ``intersect_one`` maps one ray to one ``Hit``; ``jax.vmap`` makes it a batch
function. Cameras that make rays live in :mod:`jskel.camera`, the gather/scatter of the rays
that need an effect in :mod:`jskel.wavefront`, and the chunked, compiled evaluation of a batch
function in :mod:`jskel.executor`.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from . import checks


class Rays(NamedTuple):
    """A batch of rays ``x(t) = origins + t * directions`` for ``t`` in ``(t_min, t_max]``.

    origins: (N, 3); directions: (N, 3) (unit length from cameras; any non-zero length is
    accepted by intersectors, and ``t`` is measured in units of that length); t_min, t_max: (N,).
    """

    origins: jnp.ndarray
    directions: jnp.ndarray
    t_min: jnp.ndarray
    t_max: jnp.ndarray

    @property
    def size(self) -> int:
        return int(self.origins.shape[0])


#: Hit.flags bits: every way a tracer can fail to decide a ray gets its own bit, so no ray is
#: lost silently. Defined here once; ``FLAG_NAMES`` names them for ``run.json``'s counts and
#: docs/numerics.md's table lists them (``tests/test_lost_rays.py`` checks the two agree).
FLAG_OVERFLOW = 1  # a static-capacity list (e.g. candidate primitives) overflowed: result not trusted
FLAG_STEP_CAP = 2  # an iterative search stopped at its step cap before finishing
FLAG_NO_BRACKET = 4  # no start point inside was found, but a bound says the field may still cross (Rouiller Fig. 7)
FLAG_FLOAT_SPACING = 8  # the tolerance was below a few ulps of t there: the march stepped by those ulps instead
FLAG_GRAZE = 16  # the field came within the tolerance of the threshold and left again without crossing
FLAG_TIR = 32  # not a lost ray: the refracted ray underwent total internal reflection (jskel.optics.refract), set by the integrator
FLAG_BAD_DIRECTION = 64  # a secondary ray asked for a zero or non-finite direction: spawned empty (jskel.spawning.spawn_flags)

#: the name of every bit, in bit order (``run.json``'s ``flags`` counts are keyed by these)
FLAG_NAMES = {
    FLAG_OVERFLOW: "overflow",
    FLAG_STEP_CAP: "step_cap",
    FLAG_NO_BRACKET: "no_bracket",
    FLAG_FLOAT_SPACING: "float_spacing",
    FLAG_GRAZE: "graze",
    FLAG_TIR: "tir",
    FLAG_BAD_DIRECTION: "bad_direction",
}


def flag_counts(flags) -> dict:
    """{name: number of rays carrying that bit} over an int array of ``Hit.flags`` (host)."""
    f = np.asarray(flags)
    return {name: int(np.sum((f & bit) != 0)) for bit, name in FLAG_NAMES.items()}


def or_flags_at(flags, index, values):
    """``flags`` (N,) with ``values`` OR-ed in at ``index`` (out-of-range indices dropped; several
    values at one index all kept): one scatter-max a bit, since a scatter has no bitwise or and
    the max of two bit sets loses bits."""
    values = jnp.broadcast_to(jnp.asarray(values, flags.dtype), jnp.shape(index))
    for bit in FLAG_NAMES:  # a static loop over the few bits, not over rays
        flags = flags | jnp.zeros_like(flags).at[index].max(values & bit, mode="drop")
    return flags


def ulp_floor(t, scale):
    """A few ulps (4 eps) of ``|t| + scale``: the smallest step a march along a ray may take at
    ``t`` in float type of ``t`` (``scale``: the origin's magnitude in units of t), so that
    ``t + step > t`` and the sample point moves. Tolerances below it are raised to it and the
    ray flagged ``FLAG_FLOAT_SPACING``."""
    return 4 * jnp.finfo(jnp.result_type(t)).eps * (jnp.abs(t) + scale)


class Hit(NamedTuple):
    """The nearest intersection of one ray (or a batch: every field gains a leading axis).

    t: () ray parameter, ``+inf`` on a miss.
    position: (3,) hit point in the frame of the rays (``+inf`` on a miss).
    normal: (3,) unit shading normal, zero on a miss.
    uv: (2,) surface parametrization, zero on a miss.
    prim: () int32 primitive id (segment id for frusta), -1 on a miss.
    flags: () int32 bit set of the ``FLAG_*`` bits above (how a tracer could not decide the ray:
      on a miss as on a hit), or None where a representation has none.
    """

    t: jnp.ndarray
    position: jnp.ndarray
    normal: jnp.ndarray
    uv: jnp.ndarray
    prim: jnp.ndarray
    flags: jnp.ndarray | None = None


def masked_hit(t, position, normal, uv, prim, flags=None) -> Hit:
    """A ``Hit`` with the miss sentinels applied wherever ``t`` is not finite: position +inf,
    normal and uv 0, prim -1. Shared by every representation's finishing step."""
    hit = jnp.isfinite(t)
    inf = jnp.asarray(jnp.inf, t.dtype)
    return Hit(
        t=t,
        position=jnp.where(hit, position, inf),
        normal=jnp.where(hit, normal, 0.0),
        uv=jnp.where(hit, uv, 0.0),
        prim=jnp.where(hit, prim, -1).astype(jnp.int32),
        flags=None if flags is None else flags.astype(jnp.int32),
    )


def make_rays(origins, directions, t_min=0.0, t_max=np.inf, dtype=np.float32) -> Rays:
    """Build a ``Rays`` batch from array-likes, broadcasting ``t_min``/``t_max`` to (N,).

    Raises one ValueError listing every bad ray by index and value (``jskel.checks``): origins
    or directions not finite, zero directions, a NaN ``t_min`` or ``t_max`` (``t_max = inf``
    is the unbounded ray; an empty window ``t_min >= t_max`` is a valid ray that hits nothing);
    a shape that is not (N, 3), or a window that is neither one value nor N, names its field."""
    o, d = np.asarray(origins, dtype=np.float64), np.asarray(directions, dtype=np.float64)
    for name, a in (("rays.origins", o), ("rays.directions", d)):
        if a.ndim == 0 or a.shape[-1] != 3:
            raise ValueError(f"{name}: expected (N, 3) values, got shape {a.shape}")
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    if o.shape != d.shape:
        raise ValueError(f"rays: origins {o.shape} and directions {d.shape} differ in shape")
    n = o.shape[0]
    tmin, tmax = np.asarray(t_min, dtype=np.float64), np.asarray(t_max, dtype=np.float64)
    for name, t in (("rays.t_min", tmin), ("rays.t_max", tmax)):
        if t.ndim > 1 or t.size not in (1, n):
            raise ValueError(f"{name}: expected one value or {n} (one a ray), got shape {t.shape}")
    tmin, tmax = np.broadcast_to(tmin.reshape(-1), (n,)), np.broadcast_to(tmax.reshape(-1), (n,))
    checks.raise_all(_bad_rays(o, d, tmin, tmax))
    # cast on the host: jnp.asarray's own float64 -> float32 conversion compiled a program per batch size
    return Rays(*(jnp.asarray(np.asarray(a, dtype), dtype) for a in (o, d, tmin, tmax)))


def _bad_rays(o: np.ndarray, d: np.ndarray, tmin: np.ndarray, tmax: np.ndarray) -> list[str]:
    """Every bad ray of a batch, one line per kind (``jskel.checks``)."""
    lines = checks.nonfinite("rays.origins", o, "rays") + checks.nonfinite("rays.directions", d, "rays")
    lines += checks.zero_vectors("rays.directions", d, "rays")
    for name, t in (("rays.t_min", tmin), ("rays.t_max", tmax)):
        nan = np.nonzero(np.isnan(t))[0]
        lines += checks.at(name, "is not a number", nan, t[nan], "rays")
    return lines
