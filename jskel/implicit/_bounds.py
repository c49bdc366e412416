"""Bounds of the implicit field on a ray or a piece of it (Rouiller 2011, Sec. 3's kernel
(1 - r^2/R^2)^2), and the thesis' bisection (Alg. 2, Sec. 4.2) watched by them: what lets the
``bisection`` method say when a miss (Fig. 7) or a hit (Sec. 4.2.2's later crossing) is not
decided. Flags are set by ``_trace``; every bit is defined in ``jskel.rays``."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..numerics import dot3, safe_div, safe_sqrt
from ..rays import ulp_floor
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


def watched_bisect(sub: Prims, g, threshold, eps, shape: Shape, disp: Displace, o, d, lo, hi, n):
    """``n`` (traced int32, 0 allowed) halvings of [lo, hi] (g(lo) <= 0 < g(hi)), and whether
    [lo, final lo] may hold a crossing: the bisection converges on *a* crossing of its bracket, not the first (Sec.
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
    than that is the hit, within the tolerance of the other methods), the piece is open.
    Returns (lo, hi, open_from, until): the final bracket, the start of the first open piece
    (inf if none) and the end of the last one, at most the final lo less ``eps``; a crossing
    before the hit may lie in [open_from, until] only (:func:`certified_reach` looks)."""
    speed = safe_sqrt(dot3(d, d))
    L = lipschitz_total(sub, shape, disp) * speed
    Li = lipschitz(sub) * speed
    T = threshold * (1 - 8 * jnp.finfo(o.dtype).eps)

    def kernels(t):  # (f_i, r_i^2, R_i) at o + t d
        r2, R = closest(sub, o + t * d)
        return jnp.where(sub.valid, kernel(r2, R), 0.0), r2, R

    def body(_, st):
        lo, glo, klo, hi, open_from, open_to = st
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
        left = ~inside & ~excluded
        open_from = jnp.where(left, jnp.minimum(open_from, lo), open_from)  # the earliest piece left open
        open_to = jnp.where(left, mid, open_to)  # and the end of the last
        keep = lambda a, b: jnp.where(inside, a, b)  # noqa: E731
        return keep(lo, mid), keep(glo, gm), jax.tree_util.tree_map(keep, klo, km), keep(mid, hi), open_from, open_to

    inf = jnp.asarray(jnp.inf, o.dtype)
    st = (lo, g(lo), kernels(lo), hi, inf, -inf)
    st = jax.lax.fori_loop(0, n, body, st)
    return st[0], st[3], st[4], jnp.minimum(st[5], st[0] - safe_div(eps, speed, 0.0))


def _supports(sub: Prims, o, d):
    """(enter, leave) (C,): the piece of the ray inside each candidate's sphere of influence
    (centre the segment's midpoint, radius half its length plus its larger R), grown by a few
    ulps of the coordinates; a kernel is 0, with a zero derivative, outside it."""
    c = 0.5 * (sub.a + sub.b)
    ab = sub.b - sub.a
    r = 0.5 * safe_sqrt(dot3(ab, ab)) + jnp.maximum(sub.ra, sub.rb)
    oc = c - o
    dd = dot3(d, d)
    tc = safe_div(dot3(oc, d), dd, 0.0)
    e = oc - tc[:, None] * d
    r = r + 16 * jnp.finfo(o.dtype).eps * (safe_sqrt(dot3(oc, oc)) + r)
    half = safe_sqrt(jnp.maximum(safe_div(r * r - dot3(e, e), dd, 0.0), 0.0))
    met = sub.valid & (dot3(e, e) < r * r)
    inf = jnp.asarray(jnp.inf, o.dtype)
    return jnp.where(met, tc - half, inf), jnp.where(met, tc + half, -inf)


def curvature(sub: Prims, o, d):
    """Per-candidate bound (C,) of d^2 f_i / dt^2 on the ray o + t d, and whether it holds
    (constant R: balls and straight tubes). With q = r^2 / R^2, Sec. 3's kernel f = (1 - q)^2
    has f'' = 2 q'^2 - 2 (1 - q) q''. The squared distance r^2 to a convex set (a point, a
    segment) is convex and C^1 along the ray with r^2'' <= 2 |d|^2, so q'' >= 0 and, as for any
    such function, (r^2')^2 <= 4 |d|^2 (r^2 - rho^2) with rho the set's distance to the line
    (:func:`_reach`): f'' <= 8 |d|^2 (R^2 - rho^2) / R^4 wherever f > 0 (r < R). f is C^1
    (f = f' = 0 at r = R), so f(t + h) <= f(t) + f'(t) h + M h^2 / 2. A tube whose R varies
    along it has kinks where the closest point reaches an end (R(s) bends there): it keeps its
    Lipschitz constant (``_field.lipschitz``) instead."""
    p = sub.a - o
    ab = sub.b - sub.a
    slack = 8 * jnp.finfo(o.dtype).eps * (safe_sqrt(dot3(p, p)) + safe_sqrt(dot3(ab, ab)))
    rho = jnp.maximum(safe_sqrt(_reach(p, ab, d)[0]) - slack, 0.0)
    R = jnp.maximum(sub.ra, sub.rb)
    straight = sub.ra == sub.rb
    R2 = jnp.where(R > 0, R * R, 1.0)
    M = 8.0 * dot3(d, d) * jnp.maximum(R2 - rho * rho, 0.0) / (R2 * R2)
    return jnp.where(sub.valid & straight & (R > 0), M, 0.0), straight


def certified_reach(sub: Prims, threshold, shape: Shape, disp: Displace, o, d, t0, t1, steps: int):
    """How far from ``t0`` (outside) towards ``t1`` the ray is certified outside: steps each as
    long as a bound of the field on the step stays below T. On [t, t + h], every kernel
    inside its sphere of influence at t is at most f_i(t) + f_i'(t) h + M_i h^2 / 2
    (:func:`curvature`), or f_i(t) + L_i h for a tapering tube, and a kernel whose sphere
    starts later adds nothing while h stops at that sphere (:func:`_supports`); the sum bounds
    the CSG tree and the displacement as in :func:`field_bound`. h solves sum = T; a second
    solve lets each kernel whose quadratic passes its value at its distance to a trial piece
    (three such steps, :func:`_kernel_bounds`) keep that constant instead, and the longer of
    the two steps is taken (each bound holds on its own). Near a
    crossing the quadratic bound lets the step close in on it (h -> the distance to it), so
    the march stalls before a real crossing and crosses a piece where the field only comes
    near T in a few steps. At most ``steps`` steps (a ``while_loop`` that ends when every
    lane has reached ``t1`` or stalled); inputs are not differentiated."""
    o, d, t0, t1 = (jax.lax.stop_gradient(x) for x in (o, d, t0, t1))
    sub = jax.tree_util.tree_map(jax.lax.stop_gradient, sub)
    threshold = jax.lax.stop_gradient(threshold)
    speed = safe_sqrt(dot3(d, d))
    M, straight = curvature(sub, o, d)
    Li = lipschitz(sub) * speed
    enter, leave = _supports(sub, o, d)
    scale = safe_div(safe_sqrt(dot3(o, o)), speed, 0.0)
    amp = jnp.abs(disp.amp) if shape.displace != "none" else 0.0
    room_T = threshold * (1 - 64 * jnp.finfo(o.dtype).eps) / (1.0 + amp)

    def kernels(t):
        r2, R = closest(sub, o + t * d)
        return jnp.where(sub.valid, kernel(r2, R), 0.0)

    def step(t):
        f, df = jax.jvp(kernels, (t,), (jnp.ones_like(t),))
        u = ulp_floor(t, scale)
        live = (enter <= t + u) & (leave >= t - u)  # a kernel counted early or late only adds
        lin = jnp.where(straight, df, Li)  # each kernel's bound f + lin h + M h^2 / 2
        h = jnp.minimum(_solve(f, lin, M, live, room_T), jnp.maximum(t1 - t, 0.0))
        H = jnp.minimum(3 * h, jnp.maximum(t1 - t, 0.0))  # a trial piece for the kernels' own bounds
        rest = _kernel_bounds(sub, o, d, t, t + H)[0] * (1 + 16 * jnp.finfo(o.dtype).eps)
        # a kernel whose quadratic passes its bound on the rest of the ray at that step keeps the
        # bound (a constant, valid anywhere on the rest); kernels not yet live add it too
        flat = rest < f + lin * h + 0.5 * M * h * h
        quad = live & ~flat
        hm = _solve(f, lin, M, quad, room_T - jnp.sum(jnp.where(~quad & (live | flat), rest, 0.0)))
        ahead = ~live & (enter > t)  # kernels met later (the ray has left those behind)
        nxt = jnp.min(jnp.where(ahead & ~flat, enter, jnp.inf))
        nxt0 = jnp.min(jnp.where(ahead, enter, jnp.inf))
        return jnp.maximum(jnp.minimum(t + h, nxt0), jnp.minimum(t + jnp.minimum(hm, H), nxt))  # either bound holds

    def cond(st):
        i, t, moved = st
        return (i < steps) & (t < t1) & moved

    def body(st):
        i, t, _ = st
        tn = step(t)
        return i + 1, tn, tn > t + ulp_floor(t, scale)

    _, t, _ = jax.lax.while_loop(cond, body, (jnp.int32(0), t0, jnp.asarray(True)))
    return t


def _solve(f, lin, M, use, room):
    """The step h where the sum over ``use`` of f + lin h + M h^2 / 2 reaches ``room`` (inf
    where it never does, 0 where it is there already), without cancellation."""
    eps = jnp.finfo(f.dtype).eps
    F = jnp.sum(jnp.where(use, f, 0.0)) * (1 + 16 * eps)
    G = jnp.sum(jnp.where(use, lin, 0.0))
    A = 0.5 * jnp.sum(jnp.where(use, M, 0.0))
    c = room - F
    h = safe_div(2 * c, G + safe_sqrt(G * G + 4 * A * c), jnp.inf)
    return jnp.where(c > 0, h, 0.0)
