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

from ..numerics import dot3, safe_div, safe_sqrt


class Prims(NamedTuple):
    """P primitives (leading axis P). a, b: (P,3) ends (a == b for a metaball); ra, rb: (P,)
    effective radii at a and b (> 0 for balls; a tube may have one zero end); valid: (P,)
    False for padding."""

    a: jnp.ndarray
    b: jnp.ndarray
    ra: jnp.ndarray
    rb: jnp.ndarray
    valid: jnp.ndarray
    group: jnp.ndarray  # (P,) int32 CSG group of each primitive (0 without CSG)


class Shape(NamedTuple):
    """Static description of how primitive fields combine (hashable).

    tree: a CSG tree of tuples: ("group", k) a leaf (the sum of group k's kernels, Sec. 3), or
      (op, left, right) with op "sum" (blend), "max" (union), "min" (intersection) or "diff"
      (left minus right: min(F_l, 2T - F_r), inside iff inside left and outside right).
    groups: number of groups. displace: "none" or "noise" (Sec. 6.2, a 3D value noise).
    """

    tree: tuple = ("group", 0)
    groups: int = 1
    displace: str = "none"  # none | noise | image


class Displace(NamedTuple):
    """Traced displacement parameters (Sec. 6.2). ``noise``: amplitude and frequency of the 3D
    value noise. ``image``: a height map (H, W) in [0, 1] through a planar projector (origin,
    unit side and up axes, scale), and ``grad``, a bound on |grad (h o uv)| (per world unit)."""

    amp: jnp.ndarray
    freq: jnp.ndarray
    height: jnp.ndarray
    origin: jnp.ndarray
    side: jnp.ndarray
    up: jnp.ndarray
    scale: jnp.ndarray
    grad: jnp.ndarray


def closest(prims: Prims, x):
    """(squared distance, effective radius R) from x (3,) to every primitive (P,)."""
    ab = prims.b - prims.a
    ax = x - prims.a
    s = jnp.clip(safe_div(dot3(ax, ab), dot3(ab, ab), 0.0), 0.0, 1.0)
    d = ax - s[..., None] * ab
    r = prims.ra + (prims.rb - prims.ra) * s
    return dot3(d, d), r


def kernel(r2, R):
    """f = (1 - r^2/R^2)^2 inside R, 0 outside (and 0 where R == 0). Gradient-safe: the squared
    distance is used directly (no sqrt), and R == 0 is excluded by a double where."""
    ok = R > 0
    q = safe_div(r2, jnp.where(ok, R * R, 1.0), 1.0)
    inside = ok & (q < 1.0)
    return jnp.where(inside, (1.0 - q) ** 2, 0.0)


def field(prims: Prims, x):
    """F(x): the sum of every primitive's kernel at x (3,) (Sec. 3), ignoring CSG groups."""
    r2, R = closest(prims, x)
    return jnp.sum(jnp.where(prims.valid, kernel(r2, R), 0.0))


def _hash3(i, j, k):
    """A value in [-1, 1] per integer lattice point (32-bit integer hash, no float tricks)."""
    h = (i.astype(jnp.uint32) * jnp.uint32(73856093)) ^ (j.astype(jnp.uint32) * jnp.uint32(19349663)) ^ (k.astype(jnp.uint32) * jnp.uint32(83492791))
    h = h ^ (h >> 13)
    h = h * jnp.uint32(0x5BD1E995)
    h = h ^ (h >> 15)
    return (h & jnp.uint32(0xFFFF)).astype(jnp.float32) / 32767.5 - 1.0


def value_noise(x, freq):
    """Smooth 3D value noise in [-1, 1]: lattice values trilinearly blended with smoothstep
    weights. |grad| <= sqrt(3) * 1.5 * 2 * freq (smoothstep' <= 1.5, lattice range 2)."""
    p = x * freq
    p0 = jnp.floor(p)
    f = p - p0
    w = f * f * (3.0 - 2.0 * f)
    i0 = p0.astype(jnp.int32)
    acc = 0.0
    for dx in (0, 1):  # 8 corners: a static unrolled loop, not over rays
        for dy in (0, 1):
            for dz in (0, 1):
                v = _hash3(i0[0] + dx, i0[1] + dy, i0[2] + dz).astype(x.dtype)
                wx = w[0] if dx else 1.0 - w[0]
                wy = w[1] if dy else 1.0 - w[1]
                wz = w[2] if dz else 1.0 - w[2]
                acc = acc + v * wx * wy * wz
    return acc


NOISE_SLOPE = 3.0 * 1.7320508075688772  # sqrt(3) * 1.5 * 2, per unit frequency


def combine(tree, groups_f, threshold):
    """Evaluate a static CSG tree over per-group fields (G,)."""
    op = tree[0]
    if op == "group":
        return groups_f[tree[1]]
    left = combine(tree[1], groups_f, threshold)
    right = combine(tree[2], groups_f, threshold)
    if op == "sum":
        return left + right
    if op == "max":
        return jnp.maximum(left, right)
    if op == "min":
        return jnp.minimum(left, right)
    if op == "diff":
        return jnp.minimum(left, 2.0 * threshold - right)
    raise ValueError(f"object.csg: unknown operation {op!r}")  # pragma: no cover - validated


def _bilinear1(img, uu, vv):
    h, w = img.shape
    x = uu * w - 0.5
    y = vv * h - 0.5
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = x - x0, y - y0
    i, j = x0.astype(jnp.int32), y0.astype(jnp.int32)
    g = lambda yy, xx: img[jnp.mod(yy, h), jnp.mod(xx, w)]  # noqa: E731
    return (1 - fx) * (1 - fy) * g(j, i) + fx * (1 - fy) * g(j, i + 1) + (1 - fx) * fy * g(j + 1, i) + fx * fy * g(j + 1, i + 1)


def displacement(x, shape: Shape, disp: Displace):
    """The signed perturbation in [-1, 1] at x: the noise, or 2 h(uv) - 1 of a planar-projected
    height map (both wrap)."""
    if shape.displace == "noise":
        return value_noise(x, disp.freq)
    p = x - disp.origin
    return 2.0 * _bilinear1(disp.height, dot3(p, disp.side) * disp.scale[0], dot3(p, disp.up) * disp.scale[1]) - 1.0


def shaped_field(prims: Prims, x, shape: Shape, threshold, disp: Displace):
    """The model's field at x: kernels summed per group, the CSG tree, then the displacement
    F (1 + amp * n(x)) with n in [-1, 1] (Sec. 6.2; it vanishes wherever F does, so supports are
    unchanged, and amp < 1 keeps the sign of F)."""
    r2, R = closest(prims, x)
    vals = jnp.where(prims.valid, kernel(r2, R), 0.0)
    if shape.groups == 1 and shape.tree == ("group", 0):
        f = jnp.sum(vals)
    else:
        g = jnp.zeros((shape.groups,), x.dtype).at[prims.group].add(vals)
        f = combine(shape.tree, g, threshold)
    if shape.displace != "none":
        f = f * (1.0 + disp.amp * displacement(x, shape, disp))
    return f


def gradient(prims: Prims, x):
    """dF/dx by ``jax.grad`` (Sec. 4: normals from the derivative of the field)."""
    return jax.grad(field, argnums=1)(prims, x)


def lipschitz_total(prims: Prims, shape: Shape, disp: Displace):
    """A bound on |grad| of :func:`shaped_field` over the primitives given: the sum of the
    per-primitive bounds holds for sum, max, min and 2T - F; a displacement multiplies it by
    (1 + amp) and adds amp * |grad n| * max|F| with max|F| <= the number of primitives and
    |grad n| <= NOISE_SLOPE * freq (noise) or 2 * ``disp.grad`` (image)."""
    base = jnp.sum(lipschitz(prims))
    if shape.displace == "none":
        return base
    n = jnp.sum(prims.valid.astype(base.dtype))
    slope = NOISE_SLOPE * disp.freq if shape.displace == "noise" else 2.0 * disp.grad
    return base * (1.0 + disp.amp) + disp.amp * slope * n


def lipschitz(prims: Prims):
    """Per-primitive bound on |grad f_i| (P,): the kernel's steepest slope 8 / (3 sqrt(3) R) at
    r = R / sqrt(3), plus, for tubes whose radius varies, |df/dR| <= 1/R times |dR/dx| <=
    |rb - ra| / |b - a|; R is taken at its smallest over the primitive."""
    rmin = jnp.minimum(prims.ra, prims.rb)
    ok = rmin > 0
    rs = jnp.where(ok, rmin, 1.0)
    ab = prims.b - prims.a
    length = safe_sqrt(dot3(ab, ab))  # a ball's a == b: finite derivative
    slope = safe_div(jnp.abs(prims.rb - prims.ra), length, 0.0)
    bound = 8.0 / (3.0 * jnp.sqrt(3.0) * rs) + slope / rs
    return jnp.where(prims.valid, jnp.where(ok, bound, jnp.inf), 0.0)
