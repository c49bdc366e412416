"""Gradient-safe numerics shared by every representation.

Every function here is branch-free and safe under ``jax.grad``: the double-``where`` pattern
(jax-md ``safe_mask``, MJX ``math.norm``) keeps NaN out of the backward pass, because a single
``where`` around ``sqrt`` or a division still differentiates the discarded branch.

Tolerances are looked up from the dtype of the data (``jnp.finfo(x.dtype).eps``), never from a
float32 constant, so the same code is right in float32 (the default) and float64 (references).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def eps_of(x) -> jnp.ndarray:
    """Machine epsilon of ``x``'s floating dtype, as a scalar of that dtype."""
    return jnp.asarray(jnp.finfo(jnp.result_type(x)).eps, dtype=jnp.result_type(x))


def safe_sqrt(x):
    """``sqrt(max(x, 0))`` with a zero (not NaN/inf) gradient at and below 0."""
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def safe_div(num, den, fallback=0.0):
    """``num / den`` where ``den != 0``, else ``fallback``; gradients finite everywhere."""
    ok = den != 0
    return jnp.where(ok, num / jnp.where(ok, den, 1.0), fallback)


def dot3(a, b):
    """Dot product over a last axis of 3, written out per component. Two reasons, both measured
    on XLA CPU: under vmap ``jnp.sum(a * b, -1)`` became a library reduction that cost more than
    the shading around it (docs/choices.md#dot3-unrolled), and in the
    jitted distance of a 50-segment chain it came out wrong past the 655th point of a batch
    while the same ops run one by one were right."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


def norm3(v):
    """|v| over a last axis of 3 (:func:`dot3`), zero gradient at 0."""
    return safe_sqrt(dot3(v, v))


def safe_norm(v, axis=-1, keepdims=False):
    """Euclidean norm with gradient 0 (not NaN) at the zero vector."""
    return safe_sqrt(jnp.sum(v * v, axis=axis, keepdims=keepdims))


def safe_normalize(v, axis=-1):
    """``v / |v|``; the zero vector maps to the zero vector (finite gradient)."""
    n = safe_norm(v, axis=axis, keepdims=True)
    return safe_div(v, n, 0.0)


def stable_quadratic(a, half_b, c):
    """Both roots of ``a t^2 + 2 half_b t + c = 0`` without catastrophic cancellation.

    Uses ``q = -(half_b + sign(half_b) sqrt(half_b^2 - a c))`` and the roots ``q / a``, ``c / q``
    (Press et al., Numerical Recipes 5.6), so the root of small magnitude is not formed as the
    difference of two nearly equal numbers. Handles the linear case ``a == 0`` (one root
    ``-c / (2 half_b)``, returned as ``c / q``) and returns ``+inf`` for every root that does not
    exist (negative discriminant, ``a == half_b == 0``).

    Args:
      a, half_b, c: arrays of one shape and floating dtype.

    Returns:
      ``(t_lo, t_hi)`` with ``t_lo <= t_hi`` where both exist; missing roots are ``+inf``.
    """
    disc = half_b * half_b - a * c
    has = disc >= 0
    sq = safe_sqrt(disc)
    sgn = jnp.where(half_b >= 0, 1.0, -1.0)
    q = -(half_b + sgn * sq)
    inf = jnp.inf
    r1 = safe_div(q, a, inf)
    r2 = safe_div(c, q, inf)
    r1 = jnp.where(has, r1, inf)
    r2 = jnp.where(has, r2, inf)
    lo = jnp.minimum(r1, r2)
    hi = jnp.maximum(r1, r2)
    # a missing root is inf; keep it last so lo is the existing one
    lo_f = jnp.isfinite(lo)
    t_lo = jnp.where(lo_f, lo, hi)
    t_hi = jnp.where(lo_f, hi, inf)
    return t_lo, t_hi


def line_dist2(oc, d, tc):
    """Squared distance from a point to the line through the origin along ``d``, given the
    point relative to the ray origin ``oc`` (..., 3) and its projection parameter ``tc``
    (``oc . d / d . d``). Formed as |oc - tc d|^2, not |oc|^2 - tc^2 |d|^2: the difference form
    cancels catastrophically for a far origin (in float32, a sphere 70 units away was misjudged
    by 1 % of its radius)."""
    e = oc - tc[..., None] * d
    return dot3(e, e)


def differentiable_root(g, t):
    """``t`` (a root of the scalar function ``g`` found by a march or a bisection) unchanged, with
    derivatives by the implicit-function theorem (issue 9): g(t(p), p) = 0 gives
    dt = -(dg/dp . dp) / (dg/dt) for whatever ``g`` closes over (primitive ends and radii, the
    threshold, a shell's radii and thickness, the ray). Without it the derivative of a bisection
    loop's output is exactly zero, with no error. ``lax.custom_root`` with an identity solve: the
    forward value is ``t`` bit for bit and the loop that found it is not differentiated. Where
    dg/dt is 0 (a grazing hit, where t itself jumps) the derivative is reported as 0."""
    return jax.lax.custom_root(g, jax.lax.stop_gradient(t), lambda f, x0: x0,
                               lambda gt, y: safe_div(y, gt(jnp.ones_like(y)), 0.0))


def frozen(tree):
    """``tree`` with the derivative of every floating leaf cut (``lax.stop_gradient``); other
    leaves (ints, bools, Python constants) as they are. The input of a loop that only *finds* a
    root: under ``jax.jvp`` or ``jax.linearize`` JAX would otherwise carry tangents through
    every iteration (doubling the loop in the derivative's program) only for
    :func:`differentiable_root` to drop them."""

    def one(a):
        if isinstance(a, jax.Array | np.ndarray) and jnp.issubdtype(a.dtype, jnp.floating):
            return jax.lax.stop_gradient(a)
        return a

    return jax.tree_util.tree_map(one, tree)


def euler_xyz(deg) -> np.ndarray:
    """Rotation matrix (3,3) float64 for XYZ Euler angles in degrees, X applied first:
    ``R = Rz @ Ry @ Rx`` (host; the convention of bones' keyframes and scene transforms)."""
    x, y, z = np.radians(np.asarray(deg, np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(x), np.sin(x), np.cos(y), np.sin(y), np.cos(z), np.sin(z)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx



def on_device(x, dtype=None) -> jax.Array:
    """Host data as a device array of ``dtype`` (default: its own, 64-bit types narrowed as JAX
    narrows them without x64), cast by NumPy on the host and copied with ``jax.device_put``.
    ``jnp.asarray(x, dtype)`` on host data hands XLA a small program per shape and dtype (a
    ``convert_element_type`` or copy): a render's build made thirteen of them, each compiled in
    a cold process and loaded from the cache in a warm one."""
    return jax.device_put(np.asarray(x) if dtype is None else np.asarray(x, dtype))
