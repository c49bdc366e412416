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


#: Hit.flags bits shared by every representation that reports diagnostics
FLAG_OVERFLOW = 1  # a static-capacity list (e.g. candidate primitives) overflowed: result not trusted
FLAG_STEP_CAP = 2  # an iterative search stopped at its step cap before finishing


class Hit(NamedTuple):
    """The nearest intersection of one ray (or a batch: every field gains a leading axis).

    t: () ray parameter, ``+inf`` on a miss.
    position: (3,) hit point in the frame of the rays (``+inf`` on a miss).
    normal: (3,) unit shading normal, zero on a miss.
    uv: (2,) surface parametrization, zero on a miss.
    prim: () int32 primitive id (segment id for frusta), -1 on a miss.
    flags: () int32 bit set of diagnostics (representation-specific, e.g. the implicit tracer's
      candidate overflow and step cap), or None where a representation has none.
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
    """Build a ``Rays`` batch from array-likes, broadcasting ``t_min``/``t_max`` to (N,)."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if o.shape != d.shape:
        raise ValueError(f"rays: origins {o.shape} and directions {d.shape} differ in shape")
    n = o.shape[0]
    tmin = np.broadcast_to(np.asarray(t_min, dtype=np.float64), (n,))
    tmax = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (n,))
    return Rays(
        jnp.asarray(o, dtype), jnp.asarray(d, dtype), jnp.asarray(tmin, dtype), jnp.asarray(tmax, dtype)
    )
