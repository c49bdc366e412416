"""Ray tracing skeletal implicit surfaces (Rouiller 2011, Sec. 4), one ray at a time.

Every method first *culls*: only primitives whose sphere of influence the ray crosses within
(t_min, t_max] are kept (Sec. 4.2), compacted into a candidate list of static capacity C; a ray
with more candidates sets the ``OVERFLOW`` flag (it is counted by the renderer, never silently
dropped) and its result is not trusted. Field evaluations along the ray then cost O(C), not
O(P): cost grows with overlap, not with model size. The ray interval is the union of the
candidates' sphere intervals.

Culling itself is two-level when the model is large (``Quality.block``): primitives are grouped
in runs of ``block`` along a Morton curve, and a ray first finds the groups it meets, keeps at
most ``block_capacity`` of them (a ray meeting more sets ``OVERFLOW`` and is retraced with flat
culling by ``intersect_batch``) and tests only their primitives. ``Quality.cull`` picks how:

* ``tree`` (default): the shared linear BVH of issue 6 (``jskel.accel.build``: Morton codes of
  the influence spheres' centres, a complete tree of their boxes, built in JAX from the traced
  primitives, so an animated or fitted model is re-bounded each call) with ``block`` primitives
  per leaf, walked per ray for every leaf whose box the ray meets (``accel.collect``: the bit
  trail walk of ``accel.nearest`` without a nearest-hit cut-off, since the field sums every
  primitive the ray passes through). Per ray: the internal nodes above its leaves, log2 of the
  model's size deep. Rouiller's Appendix A (after Gourmel et al. 2010) builds a kd-like BVH
  whose leaves do not overlap and reference every primitive influencing them (split
  primitives), walks it front to back with a stack and stops at the first leaf holding an
  inside point; it did not pay off on his GPU for his model sizes (App. A, Sec. 4.3's
  conclusion). Here the leaves overlap (each primitive is in one leaf) and every leaf met is
  kept, so the candidate list and the march are those of flat culling exactly.
* ``packets``: the tree's leaves that each ray meets, found for a batch at once by packets of
  64 consecutive rays (``accel.collect_packets``: dense box tests of each packet's bounds
  against every leaf, then of each ray against its packet's list), so the same candidates as
  ``tree`` without a per-ray loop; the rays of a packet whose list overflows are walked.
  Equal hits; on the CPU not faster than the walk on the blob slabs, and 1 s more to compile
  (docs/choices.md#cull-packets), so not the default.
* ``blocks``: every group's bounding sphere (``block_spheres``) is tested and the nearest
  ``block_capacity`` met are kept: P / block sphere tests per ray.

Chosen by measurement (``experiments/bench_implicit_cull.yaml``, docs/performance.md; the
development A/B's figures: docs/choices.md#cull-tree): on primary rays of the blob slabs,
culling through the tree (16 leaves kept) took a fraction of the blocks' time (32 kept) at
5,000 and 50,000 blobs, with identical candidate sets and hits, and whole traces were faster
too. A leaf box is tighter than a block's sphere: the camera rays met few leaves, while many of
them met more than 8 block spheres. Keeping 8 leaves was faster still on camera rays but too
many of the random rays through a slab (``tests/test_implicit_cull.py``) overflowed into flat
culling; 16 is the default.

Methods (``Quality.method``):

* ``naive``: Algorithm 1, constant steps of ``step`` (world units) until F > T, then
  ``bisection`` halvings of the last bracket (0 halvings: the first inside sample, as Alg. 1).
* ``bisection``: Algorithm 2 with the inside points of Sec. 4.2.1: the projection of each
  metaball's centre on the ray; for a metatube the projections of its ends and the intersection
  with the plane containing the segment and facing the viewer, keeping the one closest to the
  segment. The nearest candidate point with F > T is the inside end of the bracket and the entry
  into the first sphere of influence the outside end. Fast, but it misses the Figure 7 case and
  may bracket a later crossing (Sec. 4.2.2); a miss that a bound on the field along the ray
  cannot confirm (:func:`field_bound` >= T) carries ``NO_BRACKET``, a hit whose bracket a
  bound cannot clear of an earlier crossing (:func:`._bounds.watched_bisect`) ``GRAZE``.
* ``lipschitz`` (guaranteed; not in the thesis): |F(x) - F(y)| <= L |x - y| with L the sum over
  the candidates of each kernel's steepest slope (``_field.lipschitz``), which also bounds the
  CSG combinations, and grown for a displacement (``_field.lipschitz_total``). From an outside point
  with F < T no root lies closer than (T - F) / (L |d|) in t, so the march steps by that
  distance, but at least ``eps``. Guarantee: if the ray carries no flag (no candidate overflow,
  ``steps`` not exhausted, ``eps`` above the float spacing at t), the first interval of the ray
  inside the surface that is at least ``eps`` long is the one bracketed, and the returned t is
  within eps / 2^(k+1) of its start after k bisections; where two samples outside lie close
  enough to T that a crossing between them cannot be excluded, the ray carries ``GRAZE``.

Every flag bit is defined in ``jskel.rays`` and listed in docs/numerics.md.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..numerics import differentiable_root, dot3, safe_div, safe_normalize, safe_sqrt
from ..rays import FLAG_FLOAT_SPACING as FLOAT_SPACING
from ..rays import FLAG_GRAZE as GRAZE
from ..rays import FLAG_NO_BRACKET as NO_BRACKET
from ..rays import FLAG_OVERFLOW as OVERFLOW
from ..rays import FLAG_STEP_CAP as STEP_CAP
from ..rays import ulp_floor
from ._bounds import certified_reach, field_bound, watched_bisect
from ._cull import Candidates
from ._field import Displace, Prims, Shape, closest, kernel, lipschitz_total, shaped_field

CERTIFY_STEPS = 32  # most steps of the march that certifies open pieces (docs/numerics.md)


class Quality(NamedTuple):
    """Static options: changing one recompiles. (Step length, eps, the step cap and the bisection
    count are traced: see ``Tuning``.)"""

    method: str = "lipschitz"  # naive | bisection | lipschitz | exact
    capacity: int = 32  # candidate list per ray
    block: int = 16  # primitives per culling block (0: test every primitive)
    block_capacity: int = 16  # blocks kept per ray
    cull: str = "tree"  # tree: walk the shared BVH (jskel.accel) | blocks: test every block sphere
    early_exit: bool = True
    shape: Shape = Shape()
    tubes: bool = True  # exact: the model has segments (a != b): their axis pieces and s cuts break intervals
    degree: int = 4  # exact: 4 (balls and constant tubes), 8 (a tube tapers: one tapered piece per interval)


class Tuning(NamedTuple):
    """Traced knobs: threshold T, naive step length, Lipschitz minimum step (world units), the
    displacement's parameters, the marches' step cap and the bisection count (int32 values: a
    sweep over either compiles one program; their loops have traced bounds and are never
    differentiated, the root goes through ``numerics.differentiable_root``)."""

    threshold: jnp.ndarray
    step: jnp.ndarray
    eps: jnp.ndarray
    disp: Displace
    steps: jnp.ndarray
    bisection: jnp.ndarray


def _bisect(g, lo, hi, n):
    """``n`` (traced int32, 0 allowed) halvings of [lo, hi] keeping the half where g turns > 0."""
    def body(_, lh):
        lo, hi = lh
        mid = 0.5 * (lo + hi)
        inside = g(mid) > 0
        return jnp.where(inside, lo, mid), jnp.where(inside, mid, hi)

    return jax.lax.fori_loop(0, n, body, (lo, hi))


def _inside_points(sub: Prims, o, d):
    """Sec. 4.2.1 candidate t per primitive (C,)."""
    dd = dot3(d, d)
    ta = safe_div(dot3(sub.a - o, d), dd, 0.0)
    tb = safe_div(dot3(sub.b - o, d), dd, 0.0)
    ab = sub.b - sub.a
    n = jnp.cross(ab, jnp.cross(ab, jnp.broadcast_to(d, ab.shape)))
    tp = safe_div(dot3(sub.a - o, n), dot3(d, n), jnp.inf)

    def dist_to_seg(t):
        x = o + jnp.where(jnp.isfinite(t), t, 0.0)[..., None] * d  # inf * 0 is a NaN, even masked after
        s = jnp.clip(safe_div(dot3(x - sub.a, ab), dot3(ab, ab), 0.0), 0.0, 1.0)
        e = x - sub.a - s[..., None] * ab
        return jnp.where(jnp.isfinite(t), dot3(e, e), jnp.inf)

    cands = jnp.stack([ta, tb, tp])  # (3, C); a ball has ta == tb and tp = inf
    dist = jnp.stack([dist_to_seg(t) for t in (ta, tb, tp)])
    best = jnp.argmin(dist, axis=0)
    return jnp.take_along_axis(cands, best[None, :], axis=0)[0]


class Certify(NamedTuple):
    """What a ``bisection`` ray leaves to the certifying march (:func:`certify`): whether it is an
    undecided miss or a hit with an open piece before its bracket, and that piece [t0, t1]."""

    undecided: jnp.ndarray
    earlier: jnp.ndarray
    t0: jnp.ndarray
    t1: jnp.ndarray


def certify(sub: Prims, tune: Tuning, q: Quality, o, d, job: Certify):
    """``NO_BRACKET`` / ``GRAZE`` of one ``bisection`` ray: set where
    :func:`._bounds.certified_reach` does not get through ``job``'s open piece within
    ``CERTIFY_STEPS`` steps."""
    open_ = certified_reach(sub, tune.threshold, q.shape, tune.disp, o, d, job.t0, job.t1, CERTIFY_STEPS) < job.t1
    return jnp.where(job.undecided & open_, NO_BRACKET, 0) | jnp.where(job.earlier & open_, GRAZE, 0)


def trace_one(cand: Candidates, tune: Tuning, o, d, t_min, t_max, q: Quality, deferred: bool = False):
    """(t, flags) of the first hit of one ray over its culled candidates; t = inf on a miss.
    Flags (``jskel.rays``): OVERFLOW from culling; the tracer's own in :func:`_bisection_method`
    and :func:`_march`. ``deferred`` (``bisection``): (t, flags, :class:`Certify`) without
    the certifying march, for a batch to run :func:`certify` on only the rays that need it;
    (``exact``): (t, flags, uncertified) without the Lipschitz march of an uncertified ray."""
    sub, T = cand.sub, tune.threshold

    def g(t):
        return shaped_field(sub, o + t * d, q.shape, T, tune.disp) - T

    flags = jnp.where(cand.overflow, OVERFLOW, 0)
    if q.method == "bisection":
        t, job = _bisection_method(cand, g, tune, o, d, t_min, t_max, q)
        if deferred:
            return t, flags, job
        own = certify(sub, tune, q, o, d, job)
    elif q.method in ("naive", "lipschitz"):
        t, own = _march(cand, g, tune, o, d, q)
    elif q.method == "exact":
        from . import _exact

        if not _exact.plain(q.shape):  # a certified start from the sum of kernels, then the march
            c0, tune0, o0, d0 = jax.lax.stop_gradient((cand, tune, o, d))
            st = _exact.march(_exact.prepare(c0, _exact.lowered(tune0, q), o0, d0, q), _exact.start(c0), q.degree)
            go = jnp.isfinite(st.t) | st.unc
            marched = lambda: _as_flags(lipschitz_from(cand, tune, o, d, _exact.march_start(c0, st), q))  # noqa: E731
            t, own = jax.lax.cond(go, marched, lambda: (jnp.asarray(jnp.inf, o.dtype), jnp.int32(0)))
            return t, flags | own
        t, flags, unc = _exact.trace_exact(cand, tune, o, d, q)
        if deferred:
            return t, flags, unc
        if q.degree == 4:  # built without tapering tubes: none to certify, unless traced radii now taper
            return t, flags | jnp.where(unc, NO_BRACKET, 0)
        # a ray the polynomial cannot certify (two tapered axis pieces on an interval) marches
        t, own = jax.lax.cond(unc, lambda: _as_flags(lipschitz_from(cand, tune, o, d, cand.t_lo, q)), lambda: (t, jnp.int32(0)))
    else:  # pragma: no cover - validated in config
        raise ValueError(f"object.method: unknown method {q.method!r}")
    return t, flags | own


def _as_flags(tf):
    return tf[0], jnp.asarray(tf[1], jnp.int32)


def _bisection_method(cand: Candidates, g, tune: Tuning, o, d, t_min, t_max, q: Quality):
    """Alg. 2 from the Sec. 4.2.1 inside points and the window's end (t_max may cut it inside the
    surface): the nearest one with F > T is the bracket's inside end, the entry into the first
    sphere of influence its outside end.
    Where no candidate point is inside, the ray is a miss only if :func:`field_bound` is below
    T; otherwise the field may still cross (the Fig. 7 case: two primitives that just blend,
    Sec. 4.2.2) and the miss carries ``NO_BRACKET``. A hit whose bracket may hold an earlier
    crossing than the one bisected (Sec. 4.2.2: the bracket can straddle a later one) carries
    ``GRAZE`` (:func:`._bounds.watched_bisect`). Either flag is set only where
    :func:`._bounds.certified_reach` then fails to march through what the bounds left open
    (the whole [t_lo, t_hi] of a miss) within ``CERTIFY_STEPS`` steps: returns t and the
    :class:`Certify` job of that march (:func:`certify`)."""
    inf = jnp.asarray(jnp.inf, o.dtype)
    sub, t_lo, t_hi, anyc = cand.sub, cand.t_lo, cand.t_hi, cand.any
    tin = _inside_points(sub, o, d)
    ok = sub.valid & (tin > t_min) & (tin <= t_max) & (tin >= t_lo) & (tin <= t_hi)
    inside = ok & (jax.vmap(g)(jnp.where(ok, tin, 0.0)) > 0)  # not t_lo: inf without candidates, a NaN point
    end_in = anyc & jnp.isfinite(t_hi) & (g(jnp.where(jnp.isfinite(t_hi), t_hi, 0.0)) > 0)
    t_in = jnp.minimum(jnp.min(jnp.where(inside, tin, inf)), jnp.where(end_in, t_hi, inf))
    found = anyc & jnp.isfinite(t_in)
    start = jnp.where(found, t_lo, 0.0)  # a miss bisects [0, 0]: finite, masked after
    lo, hi, open_from, until = watched_bisect(sub, g, tune.threshold, tune.eps, q.shape, tune.disp, o, d, start,
                                              jnp.where(found, t_in, 0.0), tune.bisection)
    # a miss differentiates at t = 0 (g finite there; t_lo may be inf), and is masked after
    t = jnp.where(found, differentiable_root(g, jnp.where(found, 0.5 * (lo + hi), 0.0)), inf)
    T = tune.threshold
    bound = field_bound(sub, o, d, q.shape, tune.disp)
    undecided = anyc & ~found & (bound > T * (1 - 8 * jnp.finfo(o.dtype).eps))
    earlier = found & (open_from < until)
    # one march (:func:`certify`) certifies what the bounds left open: a found ray's
    # [open_from, until], a no-bracket ray's whole [t_lo, t_hi]
    t0 = jnp.where(earlier, open_from, jnp.where(undecided, t_lo, 0.0))
    t1 = jnp.where(earlier, until, jnp.where(undecided, t_hi, 0.0))
    return t, Certify(undecided, earlier, t0, t1)


def _march(cand: Candidates, g, tune: Tuning, o, d, q: Quality):
    """Alg. 1 (``naive``: steps of ``step``) or the Lipschitz march (steps of (T - F) / L, at
    least ``eps``) over [t_lo, t_hi], then bisection of the last bracket. Every step is at least
    :func:`jskel.rays.ulp_floor` of t (a smaller one would not move the sample: the march would
    stall into the step cap) and a ray whose tolerance that floor raised carries
    ``FLOAT_SPACING``. The last sample is t_hi itself (t_max may cut the window where F > 0).
    Between two samples outside, a crossing needs (T - F_k) + (T - F_k+1) <= L (t_k+1 - t_k)
    (|grad F| <= L). A miss where that held anywhere carries ``GRAZE`` (the bound cannot exclude a
    crossing shorter than the step: a graze of the surface or a chord stepped over); so does a
    hit where it held while the field was falling (a graze before the crossing found), but not
    the steps of an approach, where F rises towards T. The step cap sets ``STEP_CAP``."""
    inf = jnp.asarray(jnp.inf, o.dtype)
    sub, anyc = cand.sub, cand.any
    # a ray without candidates (t_lo = inf, t_hi = -inf) marches nothing from 0: no sample at
    # infinity, whose point is a NaN wherever d has a zero component, even masked after
    t_lo, t_hi = jnp.where(anyc, cand.t_lo, 0.0), jnp.where(anyc, cand.t_hi, -1.0)
    L = lipschitz_total(sub, q.shape, tune.disp) * safe_sqrt(dot3(d, d))
    scale = safe_div(jnp.max(jnp.abs(o)), safe_sqrt(dot3(d, d)), 0.0)  # the origin, in units of t
    # the step and the tolerance are lengths in space; t counts lengths of d (any non-zero length)
    tol = safe_div(tune.step if q.method == "naive" else tune.eps, safe_sqrt(dot3(d, d)), 0.0)

    # state: (i, t_prev, t, g(t_prev), found, near, grazed, floored); the sample at t tested each iteration
    def visit(st):
        i, tp, t, gp, found, near, grazed, floored = st
        gv = g(t)
        hit = (~found) & (gv > 0) & (t <= t_hi)
        live = ~(found | hit)
        pair = live & (t > tp) & (-gp - gv <= L * (t - tp))
        near, grazed = near | pair, grazed | (pair & (gv < gp))
        want = tol if q.method == "naive" else jnp.maximum(safe_div(-gv, L, 0.0), tol)
        floor = ulp_floor(t, scale)
        nt = jnp.where(live, jnp.minimum(t + jnp.maximum(want, floor), jnp.where(t < t_hi, t_hi, jnp.inf)), t)  # t_hi sampled
        floored = floored | (live & (floor > want)) | (live & ~(nt > t))  # raised, or no advance at all
        return i + 1, jnp.where(live, t, tp), nt, jnp.where(live, gv, gp), found | hit, near, grazed, floored

    false = jnp.asarray(False)
    init = (jnp.int32(0), t_lo, t_lo, jnp.zeros((), o.dtype), false, false, false, false)
    if q.early_exit:
        def cond(st):
            return (st[0] < tune.steps) & ~st[4] & (st[2] <= t_hi)

        i, tp, t, gp, found, near, grazed, floored = jax.lax.while_loop(cond, visit, init)
    else:
        i, tp, t, gp, found, near, grazed, floored = jax.lax.fori_loop(0, tune.steps, lambda _, st: visit(st), init)
    found = found & anyc
    capped = (~found) & anyc & (t <= t_hi)  # stopped by the step cap before leaving the interval
    # up to T and back to 0 by t_hi; (t_hi - tp) only where finite: a ray without candidates
    # has t_hi = -inf, tp = inf and L = 0, whose product was a NaN masked after
    back = (t > t_hi) & (tp <= t_hi)
    tail = back & (tune.threshold - gp <= L * jnp.where(back, t_hi - tp, 0.0))
    grazed = anyc & (grazed | (~found & (near | tail)))
    flags = jnp.where(capped, STEP_CAP, 0) | jnp.where(grazed, GRAZE, 0) | jnp.where(anyc & floored, FLOAT_SPACING, 0)
    first_sample = tp == t  # inside already at the first sample: nothing to bisect
    lo, hi = _bisect(g, tp, t, tune.bisection)
    t_hit = jnp.where(first_sample | (tune.bisection == 0), t, 0.5 * (lo + hi))
    return jnp.where(found, differentiable_root(g, jnp.where(found, t_hit, 0.0)), inf), flags


def lipschitz_from(cand: Candidates, tune: Tuning, o, d, t_start, q: Quality):
    """(t, flags) of the guaranteed Lipschitz march of one ray over its candidates from
    ``t_start`` (``exact``'s certified start of a shaped field, ``_exact.march_start``)."""
    sub, T = cand.sub, tune.threshold

    def g(t):
        return shaped_field(sub, o + t * d, q.shape, T, tune.disp) - T

    return _march(cand._replace(t_lo=t_start), g, tune, o, d, q._replace(method="lipschitz"))


def surface_one(cand: Candidates, tune: Tuning, o, d, t, q: Quality):
    """Position, outward unit normal -grad F / |grad F| (``jax.grad`` of the shaped field over
    the candidates, which are every primitive non-zero on the ray; CSG and displacement
    included), and the id of the primitive contributing most."""
    hit = jnp.isfinite(t)
    x = o + jnp.where(hit, t, 0.0) * d
    grad = jax.grad(lambda y: shaped_field(cand.sub, y, q.shape, tune.threshold, tune.disp))(x)
    n = safe_normalize(-grad)
    r2, R = closest(cand.sub, x)
    contrib = jnp.where(cand.sub.valid, kernel(r2, R), -1.0)
    prim = cand.ids[jnp.argmax(contrib)].astype(jnp.int32)
    return x, n, prim
