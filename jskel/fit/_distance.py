"""Differentiable signed distance from points to a skeleton's frusta (issue 10), in JAX.

The surface is the one the renderer casts rays at (Bhagvat et al. 2009, Sec. 2.1-2.2): each
segment a cone ``x^2 + z^2 = (r1 + k y)^2`` (slope form, ``k = (r2 - r1) / h``, no apex term, so
cylinders and closed tips are one formula) between two planes; a segment and its continuation
share the cutting plane of Eq. 3-5 (``jskel.frusta.joint_planes``: the very functions the host
build and the device rebuild run, same fallbacks); free ends and side-branch bases are cut
perpendicular to the axis and capped.

Per segment the signed distance combines ``cone``, the distance to the generator line in the
point's axial half-plane, ``(rho - r1 - k y) / sqrt(1 + k^2)``, with the distances beyond the
segment's real caps (free ends) as for the intersection of solids: inside, their maximum;
outside, the length of their positive parts (the distance to a rim). A shared cutting plane is
not a surface; it only decides which segment a point belongs to (:func:`signed_distance`). The
skeleton's distance is the minimum over the segments a point belongs to. Gradients are finite everywhere: the radial distance ``rho``
uses the double-``where`` norm (``numerics.safe_norm``) so a point on the axis has a zero, not a
NaN, radial gradient; divisions go through ``safe_div``; a segment of zero length is rejected on
the host (``validate_skeleton``) and guarded in JAX.

Parameters (joints, radii) are traced; the topology (which joints bound which segment, which
segment continues which) comes from ``jskel.frusta.topology`` on the host, either static
(:class:`Segments`, hashed by content: one program per topology) or as data (:class:`Topology`,
arrays traced with the points and padded to sizes chosen apart: one program for every topology
of those sizes, so a fit with topology edits between rounds compiles once for rounds whose
sizes fit, ``_problem.round_sizes``). A padding segment gets the renderer's padding axis
(``frusta.segment_axes``' ``valid``: unit length, radius 0) placed :data:`FAR` from the
normalised cloud, where no point's lower bound reaches it and no point's distance is attained;
a padding continuation shares no plane (``frusta.joint_planes``' ``cont``).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import checks
from ..accel import first_set, morton_codes, pack_bits
from ..frusta import FrustaParams, cone_sin, cutting_planes, joint_planes, segment_axes, topology, validate_skeleton
from ..numerics import dot3, norm3
from ..numerics import safe_div, safe_norm, safe_sqrt



class Segments(NamedTuple):
    """Static topology as int arrays: segment start/end joints, and the continuation pairs
    (segment ``cont_b`` continues ``cont_a`` through joint ``seg_start[cont_b]``)."""

    start: np.ndarray
    end: np.ndarray
    cont_a: np.ndarray
    cont_b: np.ndarray

    def __hash__(self):
        return hash(tuple(tuple(int(x) for x in a) for a in self))

    def __eq__(self, other):
        return all(np.array_equal(a, b) for a, b in zip(self, other))


class Topology(NamedTuple):
    """A skeleton's topology as arrays (a pytree, traced with the points): :class:`Segments`'
    four, padded with segment and continuation rows of index 0, and which rows are real
    (``live`` (S,), ``cont`` (K,))."""

    start: jax.Array
    end: jax.Array
    cont_a: jax.Array
    cont_b: jax.Array
    live: jax.Array
    cont: jax.Array


#: where a padding segment of a :class:`Topology` sits (each coordinate; the fit's coordinates
#: are normalised to the cloud's extent, so no point is within thousands of extents of it)
FAR = 1.0e4


def topology_of(seg: Segments, segments: int | None = None, conts: int | None = None) -> Topology:
    """``seg`` as a :class:`Topology` of host arrays padded to ``segments`` rows and ``conts``
    continuations (default: its own counts; ValueError where it has more)."""
    s, k = len(seg.start), len(seg.cont_b)
    ns, nk = s if segments is None else int(segments), k if conts is None else int(conts)
    if ns < s or nk < k:
        raise ValueError(f"topology: {s} segments and {k} continuations do not fit in {ns} and {nk}")

    def pad(a, n):
        return np.concatenate([np.asarray(a, np.int32), np.zeros(n - len(a), np.int32)])

    return Topology(pad(seg.start, ns), pad(seg.end, ns), pad(seg.cont_a, nk), pad(seg.cont_b, nk),
                    np.arange(ns) < s, np.arange(nk) < k)


def segments_of(joints, radii, parents, path: str = "skeleton") -> Segments:
    """Validate a skeleton on the host (naming the bad field) and return its static topology."""
    j, _, p = validate_skeleton(joints, radii, parents, path)
    topo = topology(j, p, path)
    b = np.nonzero(topo.parent_seg >= 0)[0]
    return Segments(topo.seg_start.astype(np.int32), topo.seg_end.astype(np.int32),
                    topo.parent_seg[b].astype(np.int32), b.astype(np.int32))


#: what a distance reads of a segment: its axis (base, direction, length), radii and cutting planes
DISTANCE_FIELDS = ("c1", "m", "h", "r1", "r2", "nb", "db", "nt", "dt")

# the renderer's record with only those fields, in its order and with its names and meanings, so
# the two cannot drift apart (a field renamed there makes ``geometry``'s Geometry(...) one argument too many)
Geometry = NamedTuple("Geometry", [(f, jnp.ndarray) for f in FrustaParams._fields if f in DISTANCE_FIELDS])
Geometry.__doc__ = """Per-segment arrays (S first): the fields of ``jskel.frusta.FrustaParams`` in
:data:`DISTANCE_FIELDS`, unpadded and in world (or normalised) units."""


def geometry(joints, radii, seg: Segments | Topology) -> Geometry:
    """Frusta of a skeleton from traced ``joints`` (J,3) and ``radii`` (J,): the axes and cutting
    planes of ``jskel.frusta`` (``segment_axes``, ``joint_planes``), the build's own functions
    (a :class:`Topology`'s padding rows as the module docstring says).
    A joint where no shared plane keeps both pieces within ``frusta.PIECE_REACH`` gets
    perpendicular planes there as in the renderer, but the distance still treats them as
    shared (``caps_of`` is the topology's): the renderer's caps at such a joint lie inside the
    neighbouring piece except on the outer side of the bend, and the fit's plane-validity
    penalty keeps a fitted skeleton's planes away from that fallback."""
    live, cont = (seg.live, seg.cont) if isinstance(seg, Topology) else (None, None)
    c1, m, h, r1, r2 = segment_axes(joints, radii, seg.start, seg.end, live)
    if live is not None:
        c1 = jnp.where(live[:, None], c1, jnp.asarray(FAR, c1.dtype))
    nb, db, nt, dt, _, _, _ = joint_planes(c1, m, h, r1, r2, seg.cont_a, seg.cont_b, cont)
    return Geometry(c1, m, h, r1, r2, nb, db, nt, dt)


def plane_margins(joints, radii, seg: Segments):
    """How well each shared cutting plane cuts its two cones in ellipses, facing the right
    way: (K, 2) values ``n . m - sin(half-angle)`` for the segments before and after each
    continuation, ``n`` oriented along ``ma + mb`` (the host build's ``_cuts_ellipse`` test is
    ``|n . m| > sin + ELLIPSE_MARGIN``). Below zero the plane either cuts a parabola or
    hyperbola, or faces against one of its segments (a fold past the bisector's reach): either
    way the piece between the planes is unbounded, a wedge reaching to infinity that can
    swallow far points. A fit found both on a 50-segment chain with outliers (a segment folded
    back to 0.26 of its length, its cone reaching 25 units out; a plane with n . m = -0.45
    putting an outlier 16 units behind a segment inside it), so the fit keeps these above a
    margin by a penalty (``_problem.residuals``)."""
    return margins_of(geometry(joints, radii, seg), seg)


def margins_of(g: Geometry, seg: Segments):
    """:func:`plane_margins` from an already built :class:`Geometry`."""
    if not len(seg.cont_b):
        return jnp.zeros((0, 2), g.h.dtype)
    a, b = seg.cont_a, seg.cont_b
    n = g.nt[a]

    def margin(i):
        return dot3(n, g.m[i]) - cone_sin(g.r1[i], g.r2[i], g.h[i])

    return jnp.stack([margin(a), margin(b)], -1)


def _combine(v):
    """Signed distance of the intersection of solids from their signed distances (..., K):
    inside, the maximum; outside, the length of the positive parts (the distance to a rim when a
    point is beyond the side and a cap at once; exact for a cylinder's perpendicular cap)."""
    return norm3(jnp.maximum(v, 0.0)) + jnp.minimum(jnp.max(v, axis=-1), 0.0)


def _seg2(py, pr, ay, ar, by, br):
    """Distance in the (y, rho) half-plane from point (py, pr) to the segment (a, b)."""
    dy, dr = by - ay, br - ar
    t = jnp.clip(safe_div((py - ay) * dy + (pr - ar) * dr, dy * dy + dr * dr, 0.0), 0.0, 1.0)
    ey, er = py - (ay + t * dy), pr - (ar + t * dr)
    return safe_sqrt(ey * ey + er * er)


def _section_distance(g: Geometry, q, y, rho):
    """Distance (S,) from a point outside each piece to the piece (bounded by all its planes),
    measured in the point's own axial half-plane: there the piece's section is the convex
    quadrilateral between the axis, the bottom plane's line, the generator ``rho = r1 + k y``
    and the top plane's line (``y (n . m) + rho (n . e) = dist``, ``e`` the point's radial
    direction), and the distance to it is the nearest of its three outer edges. A point of the
    section is a point of the piece, so this never reads a far point as near. The plain
    distance to the infinite cone's generator line, which it replaces for points outside,
    did: divided by sqrt(1 + k^2) and blind to where the piece ends, it put an outlier 22 units
    from a fitted chain at 7.9 (a steep cone on a segment the fit had shrunk) and a point 12.7
    units behind a segment at 2.8, and a fit bent and shrank segments to bring outliers 'near'.
    Denominators are positive when the planes cut ellipses and face their segment
    (:func:`plane_margins`, which the fit keeps positive); they are floored otherwise."""
    k = safe_div(g.r2 - g.r1, g.h, 0.0)
    e = safe_div(q - y[:, None] * g.m, rho[:, None], 0.0)
    floor = jnp.asarray(1e-3, y.dtype)

    def ends(n, dist):
        nm, ne = dot3(n, g.m), dot3(n, e)
        y_axis = dist / jnp.maximum(nm, floor)
        y_gen = (dist - g.r1 * ne) / jnp.maximum(nm + k * ne, floor)
        return y_axis, y_gen

    yb0, yb1 = ends(g.nb, g.db)
    yt0, yt1 = ends(g.nt, g.dt)
    zero = jnp.zeros_like(y)
    rb, rt = g.r1 + k * yb1, g.r1 + k * yt1
    d = jnp.minimum(_seg2(y, rho, yb0, zero, yb1, rb), _seg2(y, rho, yb1, rb, yt1, rt))
    return jnp.minimum(d, _seg2(y, rho, yt1, rt, yt0, zero))


def segment_distances(g: Geometry, x, cap_b=None, cap_t=None):
    """Signed distances of one point ``x`` (3,) to each segment (S,), and whether ``x`` lies
    between the segment's internal (shared) cutting planes (S,) bool.

    With ``cap_b``/``cap_t`` (S,) bool (which planes close a free end), the internal planes
    only select the segment and the distance combines the cone with the real caps; without
    them every plane bounds the solid."""
    q = x[None, :] - g.c1
    y = dot3(q, g.m)
    rho = norm3(q - y[:, None] * g.m)
    k = safe_div(g.r2 - g.r1, g.h, 0.0)
    cone = (rho - (g.r1 + k * y)) / jnp.sqrt(1.0 + k * k)
    below = g.db - dot3(g.nb, q)
    above = dot3(g.nt, q) - g.dt
    if cap_b is None:  # pieces bounded by all their planes: outside, the distance in the section
        d = _combine(jnp.stack([cone, below, above], -1))
        return jnp.where(d > 0, _section_distance(g, q, y, rho), d), jnp.ones_like(cone, bool)
    off = jnp.asarray(-1e30, cone.dtype)  # "no such plane": finite (see signed_distance)
    v = jnp.stack([cone, jnp.where(cap_b, below, off), jnp.where(cap_t, above, off)], -1)
    within = (cap_b | (below <= 0)) & (cap_t | (above <= 0))
    return _combine(v), within


def signed_distance(g: Geometry, x, seg: Segments | None = None):
    """Signed distance of one point (3,) to the skeleton's surface (negative inside).

    Outside every piece (each bounded by all its planes, shared ones included), the distance
    to the union's surface is the minimum of the distances to the pieces: that minimum is
    returned. Inside, a shared cutting plane is not a surface: with the topology ``seg``, each
    segment counts only for points between its shared planes and is closed only by its real
    caps, so a point inside near a joint gets its distance to the side, not to the plane (the
    plain minimum over capped pieces made interior points near joints look close to the
    surface). An inside point that no segment's shared planes enclose keeps the minimum over
    pieces."""
    if seg is None:
        return jnp.min(segment_distances(g, x)[0])
    cap_b, cap_t = caps_of(seg)
    return _signed(g, x, cap_b, cap_t)


def _signed(g: Geometry, x, cap_b, cap_t):
    """:func:`signed_distance` over the segments of ``g`` (all, or a point's candidates)."""
    d, within = segment_distances(g, x, cap_b, cap_t)
    big = jnp.asarray(1e30, d.dtype)
    d_in = jnp.min(jnp.where(within, d, big))
    d_all = jnp.min(segment_distances(g, x)[0])
    return jnp.where((d_all > 0) | ~jnp.any(within), d_all, d_in)


def caps_of(seg: Segments | Topology):
    """(cap_b, cap_t) (S,) bool (NumPy for :class:`Segments`): a plane closes a free end unless a
    continuation shares it."""
    s = len(seg.start)
    if isinstance(seg, Topology):
        ta, tb = jnp.where(seg.cont, seg.cont_a, s), jnp.where(seg.cont, seg.cont_b, s)  # s: dropped
        return jnp.ones(s, bool).at[tb].set(False, mode="drop"), jnp.ones(s, bool).at[ta].set(False, mode="drop")
    cap_b = np.ones(s, bool)
    cap_t = np.ones(s, bool)
    cap_b[np.asarray(seg.cont_b, np.int64)] = False
    cap_t[np.asarray(seg.cont_a, np.int64)] = False
    return cap_b, cap_t


def _reach(g: Geometry):
    """(S,) how far each piece reaches from its axis segment (c1 to c1 + h m): its points lie
    between the cuts' extreme axial coordinates (the ends of each ellipse's major axis, where
    the plane meets the generators ``y m +- (r1 + k y) s`` in the plane of the tilt:
    ``y = (dist -+ r1 ns) / (nm +- k ns)``) and within the largest radius there, so
    ``sqrt(radius^2 + overhang^2)`` bounds it. Used only to choose candidates (no gradient)."""
    k = safe_div(g.r2 - g.r1, g.h, 0.0)
    floor = jnp.asarray(1e-3, k.dtype)

    def ends(n, dist):
        nm = dot3(n, g.m)
        ns = safe_sqrt(jnp.maximum(1.0 - nm * nm, 0.0))
        return (dist - g.r1 * ns) / jnp.maximum(nm + k * ns, floor), (dist + g.r1 * ns) / jnp.maximum(nm - k * ns, floor)

    ys = jnp.stack([*ends(g.nb, g.db), *ends(g.nt, g.dt), jnp.zeros_like(k), g.h], -1)
    rad = jnp.max(jnp.maximum(g.r1[:, None] + k[:, None] * ys, 0.0), -1)
    over = jnp.maximum(jnp.max(jnp.maximum(-ys, ys - g.h[:, None]), -1), 0.0)
    return jnp.sqrt(rad * rad + over * over)


def _lower_bounds(g: Geometry, reach, x):
    """(S,) a lower bound on the distance from ``x`` to each piece: its distance to the axis
    segment less the piece's reach."""
    q = x[None, :] - g.c1
    t = jnp.clip(dot3(q, g.m), 0.0, g.h)
    return norm3(q - t[:, None] * g.m) - reach


#: the points unsure of their block's list choose among every segment this share of the
#: points at a time (:func:`_candidates`)
UNSURE_SHARE = 8


def _top(v, k: int):
    """``jax.lax.top_k(v, k)``'s indices, behind a barrier. XLA on the CPU runs ``top_k`` as a
    fast partial selection only where its result is read by prefix slices; an entry read alone
    (``idx[k]``) left it a full sort of every row, many times slower (docs/choices.md#top-k-prefix)."""
    return jax.lax.optimization_barrier(jax.lax.top_k(v, k)[1])


def _bound_at(g: Geometry, reach, x, i):
    """:func:`_lower_bounds`' entry ``i``, computed alone (reading it from the bounds ``top_k``
    chose from would keep all of them, points x segments, in memory)."""
    one = Geometry(*(a[i][None] for a in g))
    return _lower_bounds(one, reach[i][None], x)[0]


def _candidates(g: Geometry, points, k: int, block: int = 0, per_block: int = 0):
    """(N, k) indices of each point's k segments of smallest lower bound, and (N,) a lower
    bound on the distance to every other segment (the (k+1)-th smallest bound; inf when k
    covers every segment), all without gradient.

    ``block`` > 0 and ``per_block`` > k: the points are taken ``block`` consecutive ones at a
    time (:func:`spatial_order` puts near points together) and each block first keeps the
    ``per_block`` segments of smallest bound at its median point; each point then chooses
    among its block's list. A bound is 1-Lipschitz in the point, so a segment off the list is
    no nearer a point than its bound at the median less the point's distance from it; a point
    whose k-th bound may exceed that chooses among every segment (N / ``UNSURE_SHARE`` points
    a pass, until none is left), so every point's choice is the one it would make alone. The
    work is blocks x segments plus points x ``per_block``, plus points x segments for the
    unsure points only, instead of points x segments."""
    gs = jax.tree_util.tree_map(jax.lax.stop_gradient, g)
    pts = jax.lax.stop_gradient(points)
    reach = _reach(gs)
    s, n = g.h.shape[0], pts.shape[0]

    def one(x):
        idx = _top(-_lower_bounds(gs, reach, x), min(k + 1, s))
        return idx[:k], _bound_at(gs, reach, x, idx[k]) if k < s else jnp.asarray(jnp.inf, x.dtype)

    if not (block > 0 and k < per_block < s and n > block):
        return jax.vmap(one)(pts)
    idx, nxt, sure = _block_candidates(gs, reach, pts, k, block, per_block)
    # the points whose block list may miss one of their k (a stray point of its block, or one
    # near the list's edge) choose among every segment, ``cap`` at a time: the choice is every
    # point's own, and its cost grows with the points left unsure
    cap = min(n, max(block, n // UNSURE_SHARE))
    return redo_unsure((idx, nxt), ~sure, cap, lambda rows: jax.vmap(one)(pts[rows]))


def redo_unsure(outs: tuple, unsure, cap: int, fn):
    """``outs`` (arrays over N rows) with each row where ``unsure`` (N,) holds replaced by
    ``fn(rows)`` (rows (cap,) int, a tuple like ``outs`` of their new values), ``cap`` rows at a
    time until none is left: the fallback of a search whose cheap answer is not certain for
    every row (:func:`_candidates`, ``_cover.nearest_points``). The rows come from
    :func:`jskel.accel.first_set` (``jnp.nonzero``'s prefix sum over N cost more than the rest)."""
    n = unsure.shape[0]

    def body(st):
        outs, unsure = st
        at, count = first_set(pack_bits(unsure), cap)
        rows = jnp.where(jnp.arange(cap) < count, at, n)  # n: past the end, dropped
        new = fn(jnp.minimum(rows, n - 1))
        return tuple(o.at[rows].set(v, mode="drop") for o, v in zip(outs, new)), unsure.at[rows].set(False, mode="drop")

    return jax.lax.while_loop(lambda st: jnp.any(st[1]), body, (tuple(outs), unsure))[0]


def _block_candidates(gs: Geometry, reach, pts, k: int, block: int, per_block: int):
    """:func:`_candidates` through blocks of ``block`` consecutive points (its docstring)."""
    n = pts.shape[0]
    nb = -(-n // block)
    padded = jnp.concatenate([pts, jnp.broadcast_to(pts[-1:], (nb * block - n, 3))]).reshape(nb, block, 3)
    centre = jnp.median(padded, axis=1)  # (NB, 3): a block's stray points do not move it far
    lb_c = jax.vmap(lambda c: _lower_bounds(gs, reach, c))(centre)  # (NB, S)
    ids = _top(-lb_c, per_block + 1)
    nxt_c, ids = jnp.take_along_axis(lb_c, ids[:, per_block:], 1)[:, 0], ids[:, :per_block]  # (NB,), (NB, Kb)
    sub = Geometry(*(a[ids] for a in gs))  # each block's listed segments, gathered once per block

    def in_block(sub_b, reach_b, xs, c, nxt):
        def one(x):
            li = _top(-_lower_bounds(sub_b, reach_b, x), k + 1)
            # a bound is 1-Lipschitz in the point: a segment off the list is no nearer x than
            # its bound at the centre, less |x - c|
            rest = nxt - norm3(x - c)
            return li[:k], jnp.minimum(_bound_at(sub_b, reach_b, x, li[k]), rest), _bound_at(sub_b, reach_b, x, li[k - 1]) <= rest

        return jax.vmap(one)(xs)

    li, nxt, sure = jax.vmap(in_block)(sub, reach[ids], padded, centre, nxt_c)  # (NB, B, k), (NB, B), (NB, B)
    idx = jnp.take_along_axis(ids[:, None, :], li, axis=2)
    return idx.reshape(nb * block, k)[:n], nxt.reshape(-1)[:n], sure.reshape(-1)[:n]


def spatial_order(points) -> np.ndarray:
    """A permutation of ``points`` (N, 3) (host) along the Morton curve of the BVH build
    (``jskel.accel.morton_codes``, 10 bits an axis over the points' bounding cube): consecutive
    points lie near each other, so blocks of consecutive points are compact for
    :func:`_candidates`. Stable, so equal codes keep their order."""
    p = np.asarray(points, np.float32)
    lo = p.min(0)
    extent = max(float(np.max(p.max(0) - lo)), 1e-30)
    return np.argsort(np.asarray(morton_codes(p, lo, extent)), kind="stable")


def distances(joints, radii, seg: Segments, points, candidates: int = 0, block: int = 0, per_block: int = 0):
    """Signed distances (N,) of ``points`` (N,3) to the skeleton's surface: one vmap over the
    points, so memory is O(points x segments) (the fitting benchmark bounds that product).

    An earlier version evaluated blocks of 4,096 points under ``lax.map``; on XLA CPU (jax
    0.10.2) that path returned wrong distances for a 50-segment chain (off by up to 35 against
    the unblocked values, which match the renderer's hits), and fits above 4,096 points failed
    with it. Not yet understood, so it is gone until a test can pin it down.

    ``candidates`` > 0: each point is measured against only its ``candidates`` segments of
    smallest lower bound (distance to the axis segment less the piece's reach, chosen without
    gradient), so the work is points x candidates plus a cheap points x segments selection,
    and each residual depends on a few joints. Exact wherever :func:`culling_exact` says so.
    ``block``, ``per_block``: that selection through blocks of consecutive points
    (:func:`_candidates`; order the points by :func:`spatial_order` first)."""
    return distances_of(geometry(joints, radii, seg), seg, points, candidates, block, per_block)[0]


def distances_of(g: Geometry, seg: Segments, points, candidates: int = 0, block: int = 0, per_block: int = 0):
    """:func:`distances` from an already built :class:`Geometry`, with (N,) the lower bound on
    the segments not measured (inf without culling) for :func:`culling_exact`."""
    if candidates <= 0 or candidates >= len(seg.start):
        d = jax.vmap(lambda p: signed_distance(g, p, seg))(points)
        return d, jnp.full(d.shape, jnp.inf, d.dtype)
    cap_b, cap_t = (jnp.asarray(c) for c in caps_of(seg))
    idx, nxt = _candidates(g, points, candidates, block, per_block)

    def one(p, i):
        sub = jax.tree_util.tree_map(lambda a: a[i], g)
        return _signed(sub, p, cap_b[i], cap_t[i])

    return jax.vmap(one)(points, idx), nxt


def culling_exact(joints, radii, seg: Segments, points, candidates: int, block: int = 0, per_block: int = 0):
    """(N,) bool: whether the distance over each point's ``candidates`` nearest segments (by
    lower bound) is certainly the distance over all: outside, no other piece's lower bound is
    below the distance found; inside, no other piece can contain the point (bound > 0)."""
    d, nxt = distances_of(geometry(joints, radii, seg), seg, points, candidates, block, per_block)
    return jnp.where(d >= 0, nxt >= d, nxt > 0)


def _problems(joints, radii, seg: Segments | Topology, points):
    """``jskel.checks.traced`` of :func:`distances`' inputs: joints and points finite, radii not
    negative, every segment (a :class:`Topology`'s real ones) longer than 0 (by its end joint)."""
    h = safe_norm(joints[seg.end] - joints[seg.start])
    live = seg.live if isinstance(seg, Topology) else None
    return (checks.traced("joints", joints) + checks.traced("radii", radii, "nonnegative")
            + checks.traced("segment_length", h, "positive", valid=live, ids=seg.end if live is not None else np.asarray(seg.end))
            + checks.traced("points", points))


#: :func:`distances` with its inputs checked inside the compiled function (``jskel.checks.checked``):
#: values that only become bad under jit, a radius an optimiser drove negative, two joints that
#: met, a NaN point, raise one ValueError with a line per failing field naming the index and
#: the value (``radii[1]: negative (got -0.5); 1 of 3 entries``) instead of returning silent
#: garbage. One module-level jit with the topology ``seg`` (hashable) static: one executable
#: per topology; the checks cost a few reductions.
checked_distances = checks.checked(distances, _problems, static_argnums=2)


__all__ = ["Geometry", "Segments", "Topology", "caps_of", "checked_distances", "culling_exact", "cutting_planes", "distances", "distances_of", "geometry", "margins_of", "plane_margins",
           "segment_distances", "segments_of", "signed_distance", "topology_of"]
