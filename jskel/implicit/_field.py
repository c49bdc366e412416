"""The skeletal implicit field of Rouiller 2011, Sec. 3 (and the poster, seed 003).

F(x) = sum_i f_i(dist(x, P_i)),  f(r) = (1 - r^2 / R^2)^2 for r < R, 0 beyond,

with point primitives (metaballs) and segment primitives (metatubes) whose effective radius R is
interpolated linearly along the segment (Sec. 3: "the effective radius is interpolated on the
segment between the two values"). The surface is F = T; inside is F > T.

Both kinds are one array of segments: a metaball is a segment with a == b (its closest-point
parameter is 0 by a safe division), so every kernel is branch-free and one code path serves
both. All functions take one point and the whole ``Prims`` pytree; batch with ``jax.vmap``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..numerics import safe_div


class Prims(NamedTuple):
    """P primitives (leading axis P). a, b: (P,3) ends (a == b for a metaball); ra, rb: (P,)
    effective radii at a and b (> 0 for balls; a tube may have one zero end); valid: (P,)
    False for padding."""

    a: jnp.ndarray
    b: jnp.ndarray
    ra: jnp.ndarray
    rb: jnp.ndarray
    valid: jnp.ndarray


def _dot(u, v):
    return u[..., 0] * v[..., 0] + u[..., 1] * v[..., 1] + u[..., 2] * v[..., 2]


def closest(prims: Prims, x):
    """(squared distance, effective radius R) from x (3,) to every primitive (P,)."""
    ab = prims.b - prims.a
    ax = x - prims.a
    s = jnp.clip(safe_div(_dot(ax, ab), _dot(ab, ab), 0.0), 0.0, 1.0)
    d = ax - s[..., None] * ab
    r = prims.ra + (prims.rb - prims.ra) * s
    return _dot(d, d), r


def kernel(r2, R):
    """f = (1 - r^2/R^2)^2 inside R, 0 outside (and 0 where R == 0). Gradient-safe: the squared
    distance is used directly (no sqrt), and R == 0 is excluded by a double where."""
    ok = R > 0
    q = safe_div(r2, jnp.where(ok, R * R, 1.0), 1.0)
    inside = ok & (q < 1.0)
    return jnp.where(inside, (1.0 - q) ** 2, 0.0)


def field(prims: Prims, x):
    """F(x): the sum of every primitive's kernel at x (3,)."""
    r2, R = closest(prims, x)
    return jnp.sum(jnp.where(prims.valid, kernel(r2, R), 0.0))


def gradient(prims: Prims, x):
    """dF/dx by ``jax.grad`` (Sec. 4: normals from the derivative of the field)."""
    return jax.grad(field, argnums=1)(prims, x)


def lipschitz(prims: Prims):
    """Per-primitive bound on |grad f_i| (P,): the kernel's steepest slope 8 / (3 sqrt(3) R) at
    r = R / sqrt(3), plus, for tubes whose radius varies, |df/dR| <= 1/R times |dR/dx| <=
    |rb - ra| / |b - a|; R is taken at its smallest over the primitive."""
    rmin = jnp.minimum(prims.ra, prims.rb)
    ok = rmin > 0
    rs = jnp.where(ok, rmin, 1.0)
    ab = prims.b - prims.a
    length = jnp.sqrt(_dot(ab, ab))
    slope = safe_div(jnp.abs(prims.rb - prims.ra), length, 0.0)
    bound = 8.0 / (3.0 * jnp.sqrt(3.0) * rs) + slope / rs
    return jnp.where(prims.valid, jnp.where(ok, bound, jnp.inf), 0.0)
