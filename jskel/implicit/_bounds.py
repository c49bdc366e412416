"""Bounds of the implicit field on a ray or a piece of it (Rouiller 2011, Sec. 3's kernel
(1 - r^2/R^2)^2), and the thesis' bisection (Alg. 2, Sec. 4.2) watched by them: what lets the
``bisection`` method say when a miss (Fig. 7) or a hit (Sec. 4.2.2's later crossing) is not
decided. Flags are set by ``_trace``; every bit is defined in ``jskel.rays``."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..numerics import dot3, safe_div, safe_sqrt
from ._field import Displace, Prims, Shape, closest, kernel, lipschitz, lipschitz_total


def field_bound(sub: Prims, o, d, shape: Shape, disp: Displace):
    """An upper bound of the shaped field anywhere on the line o + t d: each candidate's kernel
    at its smallest distance to the line (:func:`_kernel_bounds`). The sum bounds the CSG tree
    too (every group field is >= 0, and sum, max, min and min(F_l, 2T - F_r) are each <= the
    sum of their children), and a displacement multiplies it by 1 + |amp| (Sec. 6.2). Below T,
    no point of the ray is inside: a certain miss."""
    return _displaced(jnp.sum(_kernel_bounds(sub, o, d)[0]), shape, disp)


def _displaced(bound, shape: Shape, disp: Displace):
    """A bound of the undisplaced field made one of the displaced field (Sec. 6.2: F (1 + amp n))."""
    return bound * (1.0 + jnp.abs(disp.amp)) if shape.displace != "none" else bound


def _kernel_bounds(sub: Prims, o, d, t0=None, t1=None, R=None):
    """Each candidate's kernel (C,) at its smallest distance to the line o + t d, or to its
    piece t0 <= t <= t1 (:func:`_reach`; shortened by a few ulps of the coordinates), with its
    largest radius (or ``R`` (C,), a bound of R on the piece): a kernel falls with distance and
    grows with R, so no point of the line (or piece) has more of that primitive's field. Also (C,) ints: where the piece's closest point
    to the primitive is its end t0 (-1) or t1 (1), else 0."""
    p = sub.a - o
    ab = sub.b - sub.a
    slack = 8 * jnp.finfo(o.dtype).eps * (safe_sqrt(dot3(p, p)) + safe_sqrt(dot3(ab, ab)))
    r2, end = _reach(p, ab, d, t0, t1)
    r = jnp.maximum(safe_sqrt(r2) - slack, 0.0)
    R = jnp.maximum(sub.ra, sub.rb) if R is None else R
    return jnp.where(sub.valid, kernel(r * r, R), 0.0), end


def _reach(p, ab, d, t0=None, t1=None):
    """(squared distance (C,), end (C,)) from each segment a + s ab (s in [0, 1], p = a - o)
    to the line o + t d, or to its piece t0 <= t <= t1: the closest points of two segments (Ericson,
    *Real-Time Collision Detection*, Sec. 5.1.9: s for the lines clamped, t for that s clamped,
    s again for that t), written with the parts of p and ab across d (pp, qq) and t relative to
    p's foot tc, so that a ray from far away loses no digits to cancellation. ``end``: -1 or 1
    where the closest point is the piece's end t0 or t1, else 0 (always 0 on the line)."""
    dd = dot3(d, d)
    tc = safe_div(dot3(p, d), dd, 0.0)
    k = safe_div(dot3(ab, d), dd, 0.0)  # t of the foot moves by k per unit of s
    pp = p - tc[:, None] * d  # the parts across the ray
    qq = ab - k[:, None] * d
    s = jnp.clip(safe_div(-dot3(pp, qq), dot3(qq, qq), 0.0), 0.0, 1.0)
    if t0 is None:
        e = pp + s[:, None] * qq
        return dot3(e, e), jnp.zeros(s.shape, jnp.int32)
    w0, w1 = t0 - tc, t1 - tc
    w = jnp.clip(k * s, w0, w1)  # t - tc at the closest point of the piece
    s = jnp.clip(safe_div(w * dot3(d, ab) - dot3(pp, ab), dot3(ab, ab), 0.0), 0.0, 1.0)
    e = pp + s[:, None] * ab - w[:, None] * d
    return dot3(e, e), jnp.where(k * s <= w0, -1, jnp.where(k * s >= w1, 1, 0))


def watched_bisect(sub: Prims, g, threshold, eps, shape: Shape, disp: Displace, o, d, lo, hi, n: int):
    """``n`` halvings of [lo, hi] (g(lo) <= 0 < g(hi)), and whether [lo, final lo] may hold a
    crossing: the bisection converges on *a* crossing of its bracket, not the first (Sec.
    4.2.2). The outside ends it keeps rise, lo_0 < lo_1 < ...; on a piece [a, b] between two of
    them the field is at most the sum over the candidates of the smaller of two bounds of each
    kernel f_i: its value at its distance to the piece (:func:`_kernel_bounds`; where the
    closest point is an end of the piece, at the distance sampled there, as the field's own
    samples round it: the distance is convex along the ray) with the larger R of the piece's
    ends (R is linear in the closest point's parameter on the primitive, which is monotone
    along the ray) and
    the tent (f_i(a) + f_i(b) + L_i (b - a)) / 2 of its Lipschitz constant
    (``_field.lipschitz``); that sum bounds the CSG tree as in :func:`field_bound`. Where it
    reaches T on a piece, and neither does (T - F(a)) + (T - F(b)) > L (b - a) exclude a
    crossing (the whole field's Lipschitz test of ``_trace._march``), and that piece starts
    more than ``eps`` (world units) before the final outside end (a crossing closer to the hit
    than that is the hit, within the tolerance of the other methods), the result is
    ``earlier``."""
    speed = safe_sqrt(dot3(d, d))
    L = lipschitz_total(sub, shape, disp) * speed
    Li = lipschitz(sub) * speed
    T = threshold * (1 - 8 * jnp.finfo(o.dtype).eps)

    def kernels(t):  # (f_i, r_i^2, R_i) at o + t d
        r2, R = closest(sub, o + t * d)
        return jnp.where(sub.valid, kernel(r2, R), 0.0), r2, R

    def body(_, st):
        lo, glo, klo, hi, open_from = st
        mid = 0.5 * (lo + hi)
        gm, km = g(mid), kernels(mid)
        (flo, r2lo, Rlo), (fm, r2m, Rm) = klo, km
        inside = gm > 0
        tent = 0.5 * (flo + fm + Li * (mid - lo))
        R = jnp.maximum(Rlo, Rm)  # R is linear in the closest point's s, monotone in t
        near, end = _kernel_bounds(sub, o, d, lo, mid, R)
        near = jnp.where(end < 0, kernel(r2lo, R), jnp.where(end > 0, kernel(r2m, R), near))
        near = jnp.where(sub.valid, near, 0.0)
        piece = _displaced(jnp.sum(jnp.minimum(near, tent)), shape, disp)
        excluded = (-glo - gm > L * (mid - lo)) | (piece < T)
        open_from = jnp.where(~inside & ~excluded, jnp.minimum(open_from, lo), open_from)  # the earliest piece left open
        keep = lambda a, b: jnp.where(inside, a, b)  # noqa: E731
        return keep(lo, mid), keep(glo, gm), jax.tree_util.tree_map(keep, klo, km), keep(mid, hi), open_from

    st = (lo, g(lo), kernels(lo), hi, jnp.asarray(jnp.inf, o.dtype))
    if n > 0:
        st = jax.lax.fori_loop(0, n, body, st)
    return st[0], st[3], st[0] - st[4] > safe_div(eps, speed, 0.0)
