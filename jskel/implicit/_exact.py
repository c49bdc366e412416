"""The exact first-hit tracer of skeletal implicit surfaces (``method: exact``).

Along a ray o + t d, Rouiller's kernel (2011, Sec. 3) f = (1 - r^2/R^2)^2 of a point primitive is
a polynomial of degree four in t inside its sphere of influence: r^2 is quadratic in t. So is a
segment primitive's of constant radius, piece by piece: the squared distance to a segment is the
squared distance to its end a where the projection parameter s(t) <= 0, to its axis line where
0 < s < 1, to its end b where s >= 1 (s is linear in t), each quadratic in t. Between consecutive
*breakpoints* (entries into and exits from each piece's support, and the t where s crosses 0
and 1) the field F is one quartic, and its first root of F - T on each interval is found in order
along the ray (Nishita and Nakamae 1994 and Kanamori, Szego and Nishita 2008 do the same with
Bezier clipping; here the critical points are isolated recursively, Yuksel 2022, "High-Performance
Polynomial Root Finding for Graphics", Proc. ACM Comput. Graph. Interact. Tech. 5(3): every
derivative of the polynomial is monotone between the roots of the next, so each root lies in a
bracket with a sign change and is found by Newton steps safeguarded by bisection; no root can be
missed but within rounding of a double root, a tangent ray, at the silhouette).

A tube whose radius tapers (Sec. 3: R linear along the segment) has, on its axis piece,
f = N^2 / R^4 with N = R^2 - r^2 quadratic and R linear in t: where that piece is the only
tapered one on an interval, F - T has the sign of (S - T) R^4 + N^2 (R > 0 inside the support;
S the other pieces' quartic), a polynomial of degree eight, isolated the same way. An interval
with two or more tapered axis pieces cannot be written so; the ray is marked ``uncertified``
and ``intersect_batch`` traces it again by the guaranteed Lipschitz march (its flags then
apply).

CSG and displacement are not sums of such pieces, but both stay below a sum of them: every CSG
operation on non-negative group fields (sum, max, min, min(F_l, 2T - F_r)) is at most the sum of
all kernels S, and a displacement scales the field by 1 + amp n(x) <= 1 + amp (Sec. 6.2). So the
shaped field is below T wherever S < T / (1 + amp), and the first root of S - T / (1 + amp), found
exactly as above (:func:`lowered`), is a certified start: before it the ray is outside. From there
the guaranteed Lipschitz march (``_trace.lipschitz_from``) finds the shaped surface with its
documented tolerance (``eps``, then bisection); a ray whose sum never reaches the lowered
threshold is a certain miss and marches nothing.

Each interval's polynomial is formed in a local variable u in [-1, 1] about the interval's
midpoint, from each piece's distance written about that point: its coefficients are O(1) per
primitive whatever the interval's length or the model's size (the midpoint o + m d itself is
rounded at the ray's distance, as every tracer's sample point is). Tubes need both radii > 0
(the build says so by name): a tapering piece's R^4 at a zero end leaves the product no digits.

Every function here is one ray's, vmapped by the caller; loops are ``lax`` loops of static or
traced length.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..numerics import dot3, safe_div, stable_quadratic
from ..numerics import differentiable_root
from ..rays import FLAG_OVERFLOW
from ._bounds import _kernel_bounds, _supports
from ._field import Prims, shaped_field

NEWTON = 12  # Newton-bisection steps per bracket, no stopping test: Newton converges in float32 in a few
# steps once near; a bracket where every step leaves it ends 2^-12 of its width wide


def breakpoints(sub: Prims, o, d, tubes: bool):
    """(C, K) values of t where some candidate's kernel changes its piece: entry into and exit from
    the support of the ball at a (radius ra), and, with ``tubes``, of the axis piece
    (r_axis^2 = R(s)^2, quadratic in t) and the ball at b, and the t where s = 0 and s = 1. Each is
    a root of a quadratic written about the foot of a on the ray (no cancellation for a far
    origin); missing ones are +inf. Extra breakpoints only split an interval more."""
    dd = dot3(d, d)
    tca = safe_div(dot3(sub.a - o, d), dd, 0.0)
    pa = o + tca[:, None] * d - sub.a  # the foot of a, relative to a
    out = [_sphere_roots(pa, d, sub.ra, tca)]
    if tubes:
        ab = sub.b - sub.a
        l2 = dot3(ab, ab)
        s0 = safe_div(dot3(pa, ab), l2, 0.0)  # s at tca
        s1 = safe_div(dot3(d, ab), l2, 0.0)  # ds / dt
        out.append(_sphere_roots(pa - ab, d, sub.rb, tca))
        w = pa - s0[:, None] * ab
        z = d - s1[:, None] * ab
        kappa = (sub.rb - sub.ra) * s1
        rho = sub.ra + (sub.rb - sub.ra) * s0
        lo, hi = stable_quadratic(dot3(z, z) - kappa * kappa, dot3(w, z) - rho * kappa, dot3(w, w) - rho * rho)
        out.append(jnp.stack([lo, hi], -1) + tca[:, None])
        cuts = jnp.stack([safe_div(-s0, s1, jnp.inf), safe_div(1.0 - s0, s1, jnp.inf)], -1) + tca[:, None]
        out.append(cuts)
    bp = jnp.concatenate(out, -1)
    return jnp.where(sub.valid[:, None] & jnp.isfinite(bp), bp, jnp.inf)


def _sphere_roots(p, d, R, t0):
    """(C, 2) t where |p + (t - t0) d| = R: the sphere of radius R about -p + (foot at t0)."""
    lo, hi = stable_quadratic(dot3(d, d), dot3(p, d), dot3(p, p) - R * R)
    return jnp.stack([lo, hi], -1) + t0[:, None]


def _square(w):
    """Coefficients (..., 5) of (w0 + w1 u + w2 u^2)^2 from w (..., 3), ascending."""
    w0, w1, w2 = w[..., 0], w[..., 1], w[..., 2]
    return jnp.stack([w0 * w0, 2 * w0 * w1, w1 * w1 + 2 * w0 * w2, 2 * w1 * w2, w2 * w2], -1)


def _mul(p, q):
    """Product of two ascending coefficient vectors (static lengths)."""
    out = [0.0] * (p.shape[-1] + q.shape[-1] - 1)
    for i in range(p.shape[-1]):
        for j in range(q.shape[-1]):
            out[i + j] = out[i + j] + p[..., i] * q[..., j]
    return jnp.stack(out, -1)


def interval_poly(sub: Prims, o, d, ta, tb, threshold, degree: int):
    """Coefficients (degree + 1,) in u in [-1, 1] (t = m + h u, m and h the midpoint and half
    width of [ta, tb]) of a polynomial with the sign of F(t) - T on the interval, and whether it
    is uncertified: two or more tapered axis pieces live on it (``degree`` 8), or one (``degree``
    4, chosen by the build for a model without tapering tubes). Each candidate's piece is the
    one its projection parameter s selects at the midpoint; it is live where r^2 < R^2 there
    (the breakpoints make both constant on the interval, up to rounding at an end where the
    kernel is 0 with its derivative)."""
    m, h = 0.5 * (ta + tb), 0.5 * (tb - ta)
    P, V = o + m * d, h * d
    ab = sub.b - sub.a
    l2 = dot3(ab, ab)
    pa = P - sub.a
    s = safe_div(dot3(pa, ab), l2, 0.0)
    sv = safe_div(dot3(V, ab), l2, 0.0)
    axis = (s > 0) & (s < 1)
    e0 = jnp.where(axis[:, None], pa - s[:, None] * ab, jnp.where((s >= 1)[:, None], P - sub.b, pa))
    ev = jnp.where(axis[:, None], V - sv[:, None] * ab, V)
    R0 = jnp.where(axis, sub.ra + (sub.rb - sub.ra) * s, jnp.where(s >= 1, sub.rb, sub.ra))
    R1 = jnp.where(axis, (sub.rb - sub.ra) * sv, 0.0)
    r2 = jnp.stack([dot3(e0, e0), 2 * dot3(e0, ev), dot3(ev, ev)], -1)  # (C, 3)
    live = sub.valid & (R0 > 0) & (r2[:, 0] < R0 * R0)
    tapered = live & axis & (sub.ra != sub.rb)
    R02 = jnp.where(live, R0 * R0, 1.0)
    # N / R0^2 = (R^2 - r^2) / R0^2 with R = R0 + R1 u: 1 - q for constant R
    n = jnp.stack([R02 - r2[:, 0], 2 * R0 * R1 - r2[:, 1], R1 * R1 - r2[:, 2]], -1) / R02[:, None]
    quart = jnp.sum(jnp.where((live & ~tapered)[:, None], _square(n), 0.0), 0)
    quart = quart.at[0].add(-threshold)
    if degree == 4:
        return quart, jnp.any(tapered)
    one = tapered.astype(n.dtype)[:, None]
    nt = jnp.sum(one * n, 0)  # the single tapered piece, if any
    rt = jnp.stack([jnp.ones_like(m), jnp.sum(one[:, 0] * safe_div(R1, R0, 0.0))])  # R / R0
    r4 = _mul(_mul(rt, rt), _mul(rt, rt))
    g = _mul(quart, r4) + jnp.pad(_square(nt), (0, 4))
    return g, jnp.sum(tapered.astype(jnp.int32)) > 1


def _horner(c, u):
    acc = c[..., -1]
    for k in range(c.shape[-1] - 2, -1, -1):
        acc = acc * u + c[..., k]
    return acc


def _deriv(c):
    return c[..., 1:] * jnp.arange(1, c.shape[-1], dtype=c.dtype)


def _newton_bisect(c, lo, hi):
    """The root of the polynomial c in [lo, hi] (vectorised over brackets), where c is monotone
    and changes sign: Newton steps, a bisection wherever Newton leaves the bracket."""
    dc = _deriv(c)
    neg_lo = _horner(c, lo) < 0

    def body(_, st):
        lo, hi, x = st
        fx = _horner(c, x)
        below = (fx < 0) == neg_lo
        lo, hi = jnp.where(below, x, lo), jnp.where(below, hi, x)
        xn = x - safe_div(fx, _horner(dc, x), jnp.inf)
        # inclusive: a converged step lands on the end the last sample just moved there
        xn = jnp.where((xn >= lo) & (xn <= hi), xn, 0.5 * (lo + hi))
        return lo, hi, jnp.where(fx == 0, x, xn)

    return jax.lax.fori_loop(0, NEWTON, body, (lo, hi, 0.5 * (lo + hi)))[2]


def first_root(c):
    """The first u in [-1, 1] where the polynomial c (ascending, c(-1) < 0) reaches 0, or +inf.
    Critical points from the bottom up (Yuksel 2022): the quadratic derivative's roots in closed
    form (``numerics.stable_quadratic``), then each higher derivative's one root per monotone
    bracket with a sign change (a bracket without one adds its end: extra splits keep every
    piece monotone); at the top, the first bracket whose end is >= 0."""
    n = c.shape[-1] - 1
    ders = [c]
    for _ in range(n - 2):
        ders.append(_deriv(ders[-1]))
    q = ders[-1]
    one = jnp.ones((), c.dtype)
    r0, r1 = stable_quadratic(q[2], 0.5 * q[1], q[0])
    r0, r1 = (jnp.where((r > -1) & (r < 1), r, one) for r in (r0, r1))
    pts = jnp.stack([jnp.minimum(r0, r1), jnp.maximum(r0, r1)])
    for p in ders[-2:0:-1]:  # the derivatives of degree 3 .. n - 1: all their roots
        e = jnp.concatenate([-one[None], pts, one[None]])
        lo, hi = e[:-1], e[1:]
        change = (_horner(p, lo) < 0) != (_horner(p, hi) < 0)
        pts = jnp.where(change, _newton_bisect(p, lo, hi), hi)
    e = jnp.concatenate([-one[None], pts, one[None]])
    up = _horner(c, e[1:]) >= 0
    k = jnp.argmax(up)
    u = _newton_bisect(c, e[k], e[k + 1])
    return jnp.where(jnp.any(up), u, jnp.inf)


class Ray(NamedTuple):
    """What one ray's intervals need, computed once (:func:`prepare`): its candidates, the
    breakpoints (flattened), each candidate's sphere of influence on the ray and its kernel's
    bound on the whole line (``_bounds``), the window's end and the threshold."""

    sub: Prims
    o: jnp.ndarray
    d: jnp.ndarray
    bp: jnp.ndarray
    enter: jnp.ndarray
    leave: jnp.ndarray
    kb: jnp.ndarray
    t_hi: jnp.ndarray
    T: jnp.ndarray


class State(NamedTuple):
    """Where one ray is: the start of its next interval, its root (inf: none yet), whether it is
    still searching and whether it met an interval it cannot certify."""

    ta: jnp.ndarray
    t: jnp.ndarray
    live: jnp.ndarray
    unc: jnp.ndarray


def prepare(cand, tune, o, d, q) -> Ray:
    """The :class:`Ray` of one ray over its culled candidates (``_cull.Candidates``)."""
    sub = cand.sub
    enter, leave = _supports(sub, o, d)
    bp = breakpoints(sub, o, d, q.tubes).reshape(-1)
    return Ray(sub, o, d, bp, enter, leave, _kernel_bounds(sub, o, d)[0], cand.t_hi, tune.threshold)


def start(cand) -> State:
    """The first :class:`State` of one ray: searching from its window's start if it has candidates."""
    inf = jnp.full(cand.t_lo.shape, jnp.inf, cand.t_lo.dtype)
    return State(jnp.where(cand.any, cand.t_lo, cand.t_hi), inf, cand.any, jnp.zeros(cand.any.shape, bool))


def step(ray: Ray, st: State, degree: int) -> State:
    """One interval of one ray: skip every interval on which the candidates live there (their
    spheres of influence cover it) cannot sum to T (each at most its bound on the line), then
    solve the first one that may (:func:`interval_poly`, :func:`first_root`). The ray stays live
    until it has a root or reaches the window's end."""
    inf = jnp.asarray(jnp.inf, ray.o.dtype)
    lowT = ray.T * (1 - 8 * jnp.finfo(ray.o.dtype).eps)

    def nxt(ta):
        tb = jnp.minimum(jnp.min(jnp.where(ray.bp > ta, ray.bp, inf)), ray.t_hi)
        bound = jnp.sum(jnp.where((ray.enter < tb) & (ray.leave > ta), ray.kb, 0.0))
        return tb, bound

    def skip(c):
        ta, tb, bound = c
        return (ta < ray.t_hi) & (bound < lowT)

    def advance(c):
        tb = c[1]
        return (tb, *nxt(tb))

    ta, tb, _ = jax.lax.while_loop(skip, advance, (st.ta, *nxt(st.ta)))
    # the candidates' bounds on the whole line below T: a certain miss (``_bounds.field_bound``)
    go = st.live & (ta < ray.t_hi) & (jnp.sum(ray.kb) >= lowT)
    # a lane that is done (a padded sub-batch's copy of a ray without candidates: ta = inf) solves
    # [0, 1] instead: its interval's midpoint and width would be NaN, even masked after
    c, unc = interval_poly(ray.sub, ray.o, ray.d, jnp.where(go, ta, 0.0), jnp.where(go, tb, 1.0), ray.T, degree)
    start_in = _horner(c, -jnp.ones_like(ta)) >= 0  # the ray starts inside, or the last interval ended at a root
    u = jnp.where(start_in, -1.0, first_root(c))
    t = jnp.where(go & jnp.isfinite(u), 0.5 * (ta + tb) + 0.5 * (tb - ta) * jnp.where(jnp.isfinite(u), u, 0.0), inf)
    t = jnp.where(st.live, t, st.t)
    unc = st.unc | (go & unc)
    return State(jnp.where(go, tb, st.ta), t, go & ~jnp.isfinite(t) & ~unc & (tb < ray.t_hi), unc)


def march(ray: Ray, st: State, degree: int) -> State:
    """Every interval of one ray in order until a root (a ``while_loop``)."""
    return jax.lax.while_loop(lambda s: s.live, lambda s: step(ray, s, degree), st)


def finish(sub: Prims, o, d, t, tune, q):
    """The hit's t, differentiable by the implicit-function theorem (``numerics.differentiable_root``
    of the shaped field), as the marches' are."""
    found = jnp.isfinite(t)

    def g(t):
        return shaped_field(sub, o + t * d, q.shape, tune.threshold, tune.disp) - tune.threshold

    return jnp.where(found, differentiable_root(g, jnp.where(found, t, 0.0)), t)


def plain(shape) -> bool:
    """The shaped field is the sum of kernels itself (no CSG tree, no displacement)."""
    return shape.groups == 1 and shape.tree == ("group", 0) and shape.displace == "none"


def lowered(tune, q):
    """``tune`` with the threshold the sum of kernels must reach for the shaped field to reach T
    (the module's docstring): T itself for a plain sum, T / (1 + amp) under a displacement."""
    if plain(q.shape):
        return tune
    amp = tune.disp.amp if q.shape.displace != "none" else 0.0
    return tune._replace(threshold=tune.threshold / (1.0 + amp))


def march_start(cand, st: State):
    """Where the Lipschitz march of a shaped field (or of an uncertified ray) starts: a few ulps
    before the sum's first root at the lowered threshold (its rounding must not start the march
    past the surface), or the window's start for an uncertified ray."""
    eps = jnp.finfo(cand.t_lo.dtype).eps
    t = jnp.where(jnp.isfinite(st.t), st.t, cand.t_lo)
    span = jnp.where(cand.any, cand.t_hi - cand.t_lo, 0.0)
    return jnp.where(st.unc | ~jnp.isfinite(st.t), cand.t_lo, jnp.maximum(cand.t_lo, t - 64 * eps * (jnp.abs(t) + span)))


def trace_exact(cand, tune, o, d, q):
    """(t, flags, uncertified) of one ray over its culled candidates (``_cull.Candidates``):
    t = inf on a miss; the flags of culling (an overflow)."""
    # the march only finds where the root lies (its loop has no reverse mode): finish differentiates
    c0, tune0, o0, d0 = jax.lax.stop_gradient((cand, tune, o, d))
    st = march(prepare(c0, tune0, o0, d0, q), start(c0), q.degree)
    return finish(cand.sub, o, d, st.t, tune, q), jnp.where(cand.overflow, FLAG_OVERFLOW, 0), st.unc


def rounds(cand, tune, o, d, q, lanes: int, per_round: int = 1) -> State:
    """:func:`march` over a batch (leading axis N) without padding every ray to the batch's
    longest: in rounds, the rays still searching are gathered into dense sub-batches of
    ``lanes`` (``wavefront.compact_map``), prepared (:func:`prepare`: a ray without candidates
    never is) and take ``per_round`` more intervals each; a round costs the (ray, interval)
    pairs that remain, not the batch. Nothing here is differentiated (:func:`finish` is)."""
    from ..wavefront import compact_map

    cand, tune, o, d = jax.lax.stop_gradient((cand, tune, o, d))

    def some(sub):
        c, o1, d1, s = sub

        def one(c, o1, d1, s1):
            ray = prepare(c, tune, o1, d1, q)
            for _ in range(per_round):  # a static unroll of a few steps, not a loop over rays
                s1 = step(ray, s1, q.degree)
            return s1

        return jax.vmap(one)(c, o1, d1, s)

    def body(s):
        return compact_map(some, s.live, (cand, o, d, s), s, lanes)

    return jax.lax.while_loop(lambda s: jnp.any(s.live), body, start(cand))
