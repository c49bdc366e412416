"""Skeleton -> frusta geometry, written once in JAX (Bhagvat et al. 2009, Sec. 2.1-2.3).

One set of functions from joints, radii and a fixed topology to every frame-dependent field of
the frusta: the axes, the cutting planes at the joints, the caps, and the u-aligned frames with
their twist offsets. Three callers share it:

* the host build (``_build.build_frusta``) has NumPy evaluate its jaxpr in float64
  (``jskel.compile.host_eval``), traced under a scoped ``jax.enable_x64(True)`` (no global switch), on
  the topology padded to a power of two so skeletons of similar size share one trace;
* the device rebuild (``_device.rebuilder``) runs it in the working dtype on every animation
  frame;
* the fit's signed distance (``jskel.fit``) takes the axes and cutting planes
  (:func:`segment_axes`, :func:`joint_planes`) and differentiates through them.

Each segment is a frustum in a local frame ``(U, M, W)`` at its base joint ``C1``: ``M`` the
unit medial axis (the paper's y), ``U`` and ``W`` the paper's x and z. The cone of Eq. 1-2 is
written without the apex height h' = r1 h / (r1 - r2):

    x^2 + z^2 = (r1 + k y)^2,   k = (r2 - r1) / h,

which is Eq. 1 multiplied by (r1 / h')^2 = k^2, so the cylinder r1 == r2 (h' infinite, k = 0)
and the closed tip r2 == 0 are the same formula, with no division by r1 - r2.

Each segment is clipped by two planes ``n . (P - C1) >= d`` (bottom) and ``n . (P - C1) <= d``
(top), both normals pointing along ``M``. The plane shared by a segment and its continuation is
the medial-plane construction of Eq. 3-5 (:func:`cutting_planes`); free ends and the bases of
side branches (``_skeleton``) are cut perpendicular to the axis and closed by flat caps.

The frames align u across joints as in Sec. 2.3 (:func:`frames`): the u = 0 generator of the
lower frustum meets the cutting plane at a point Q; the upper frustum's ``W`` is chosen through
Q, which is the paper's "subtract u_t" built into the frame. A twist theta per segment adds
v * theta to u (Sec. 2.3), and the offsets accumulate along a chain so a twisted texture stays
continuous. Frames go one depth level per step of a ``fori_loop`` (a static count), so the
whole function is differentiable in the joints.

Every division and norm goes through ``numerics.safe_*``: gradients stay finite at collinear
joints and on padding rows.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics import dot3, safe_div, safe_norm, safe_sqrt

_COLLINEAR_SIN = 1e-7
ELLIPSE_MARGIN = 0.05  # |n . m| must exceed sin(half-angle) by this much


class SegmentTopology(NamedTuple):
    """A skeleton's topology as int arrays, padded to ``N`` rows (``padded_topology``)."""

    start: jnp.ndarray  # (N,) base joint of each segment row (0 for padding)
    end: jnp.ndarray  # (N,) top joint (1 for padding)
    parent: jnp.ndarray  # (N,) row this one continues, -1 (root or side branch, or padding)
    branch: jnp.ndarray  # (N,) row ending at the base joint, -1 at roots
    depth: jnp.ndarray  # (N,) depth level (-1 for padding)
    valid: jnp.ndarray  # (N,) bool
    by_level: jnp.ndarray  # (L, W) the rows at each depth level, padded with N (L, W powers of two)


def padded_topology(topo, n: int, xp=jnp) -> SegmentTopology:
    """The host ``Topology`` (``_skeleton.topology``) as arrays of ``n >= S`` rows; ``xp`` is
    ``jnp`` for device arrays or ``np`` for host arrays handed to a jitted call."""
    s = topo.seg_start.shape[0]

    def pad(a, fill):
        return xp.asarray(np.concatenate([np.asarray(a, np.int32), np.full(n - s, fill, np.int32)]))

    return SegmentTopology(pad(topo.seg_start, 0), pad(topo.seg_end, 1), pad(topo.parent_seg, -1),
                           pad(topo.branch_parent, -1), pad(topo.depth, -1), xp.asarray(np.arange(n) < s),
                           xp.asarray(rows_by_level(topo.depth, n)))


def _pow2(k: int) -> int:
    return 1 << max(int(k) - 1, 0).bit_length()


def rows_by_level(depth, n: int) -> np.ndarray:
    """(L, W) int32: row ``i`` of the table lists the segment rows at depth ``i``, padded with
    ``n`` (out of range); L and W are the depth count and the widest level rounded up to powers
    of two (at least 8), so skeletons of similar shape share an executable (rows past the depth
    count are never visited). :func:`frames` visits only these
    rows per level: a neuron 430 levels deep costs 430 small steps, not 430 passes over every
    segment (most of its host build before: docs/choices.md#depth-table)."""
    depth = np.asarray(depth, np.int64)
    levels = int(depth.max()) + 1 if depth.size else 1
    order = np.argsort(depth, kind="stable")
    counts = np.bincount(depth, minlength=levels) if depth.size else np.zeros(1, np.int64)
    table = np.full((_pow2(max(levels, 8)), _pow2(max(int(counts.max()), 8))), n, np.int32)
    col = np.arange(depth.size) - np.repeat(np.cumsum(counts) - counts, counts)
    table[depth[order], col] = order
    return table


def _unit(v):
    return safe_div(v, safe_norm(v, keepdims=True), 0.0)


def _any_perp(m):
    """A unit vector perpendicular to each row of m (coordinate-axis substitution of Sec. 2.2)."""
    ax = jnp.eye(3, dtype=m.dtype)[jnp.argmin(jnp.abs(m), axis=-1)]
    return _unit(ax - dot3(ax, m)[..., None] * m)


def _cross2(a, b):
    return a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]


def cone_sin(r0, r1, h):
    """Sine of the half-angle of the cone with radii ``r0 -> r1`` over length ``h``."""
    k = safe_div(r1 - r0, h, 0.0)
    return jnp.abs(k) / jnp.sqrt(1.0 + k * k)


def cuts_ellipse(n, m, r0, r1, h):
    """Whether planes of normal n cut the cones (axis m, radii r0 -> r1 over h) in ellipses."""
    return jnp.abs(dot3(n, m)) > cone_sin(r0, r1, h) + ELLIPSE_MARGIN


def _meet(ca2, cb2, sa, sb, ra0, ra1, rb0, rb1, sign):
    """Eq. 4 in the 2D medial plane: where the side line of a (``C - r (M x Nm)``, left for
    sign = +1, right for -1) meets the side line of b; ``ok`` where the lines are not parallel."""
    zero = jnp.zeros_like(ca2)
    l1 = ca2 - sign * ra0[:, None] * sa
    l2 = zero - sign * ra1[:, None] * sa
    l3 = zero - sign * rb0[:, None] * sb
    l4 = cb2 - sign * rb1[:, None] * sb
    d1, d2 = l2 - l1, l4 - l3
    den = _cross2(d1, d2)
    ok = jnp.abs(den) > 1e-9 * safe_norm(d1) * safe_norm(d2)
    s = safe_div(_cross2(l3 - l1, d2), jnp.where(ok, den, 0.0), 0.0)
    return l1 + s[:, None] * d1, ok


def medial_normal(ma, mb):
    """``(nm, collinear)``: the unit normal ``ma x mb`` of the medial plane of Eq. 3 at K joints,
    and where the axes are collinear (then any unit vector perpendicular to ``ma``)."""
    cr = jnp.cross(ma, mb)
    sin = safe_norm(cr)
    collinear = sin < _COLLINEAR_SIN
    return jnp.where(collinear[:, None], _any_perp(ma), safe_div(cr, sin[:, None], 0.0)), collinear


#: every frustum piece lies within ``PIECE_REACH * max(r1, r2)`` of its own segment (the capsule
#: of that radius around C1-C2): a shared cutting plane that would let a piece reach farther is
#: replaced (:func:`cutting_planes`). 6 keeps the bisector of two equal cylinders up to a bend of
#: 2 atan(sqrt(35)) = 161 degrees (its ellipse reaches r tan(bend / 2) past the joint)
PIECE_REACH = 6.0

#: how a joint's planes were chosen (:func:`cutting_planes`' ``kind``)
PLANE_EQ35, PLANE_COLLINEAR, PLANE_BISECTOR, PLANE_SPLIT = 0, 1, 2, 3
PLANE_KINDS = ("eq_3_5", "collinear", "bisector", "perpendicular_caps")


def plane_reach(n, dist, m, r1, r2, h):
    """How far the cut of a segment's cone by the plane ``n . (P - C1) = dist`` reaches from the
    axis segment (C1 to C1 + h m), or ``inf`` where the plane does not cut the cone's first
    nappe in an ellipse facing along ``m`` (then the piece it bounds is unbounded).

    Closed form: with ``n = n_m m + n_e e`` (``e`` the unit radial direction of the tilt), a
    point of the cone ``y m + (r1 + k y) e(phi)`` lies on the plane where
    ``y = (dist - n_e r1 cos phi) / (n_m + n_e k cos phi)``, monotone in ``cos phi`` when
    ``n_m > n_e |k|`` (the ellipse condition), so the cut's axial extremes are at ``cos phi = +-1``:
    ``y = (dist -+ n_e r1) / (n_m +- n_e k)``. The distance of a cone point at ``y`` from the
    axis segment, ``sqrt((r1 + k y)^2 + overhang(y)^2)``, is convex in ``y``, so its largest
    value over the piece is at one of those extremes: the bound is exact, not sampled."""
    k = safe_div(r2 - r1, h, 0.0)
    nm = dot3(n, m)
    ne = safe_sqrt(jnp.maximum(1.0 - nm * nm, 0.0))
    ok = nm > cone_sin(r1, r2, h) + ELLIPSE_MARGIN  # cuts_ellipse, and facing along m (nm > sin implies nm > ne |k|)

    def at(y):
        over = jnp.maximum(jnp.maximum(-y, y - h), 0.0)
        rad = r1 + k * y
        return safe_sqrt(rad * rad + over * over)

    lo = safe_div(dist - ne * r1, jnp.where(ok, nm + ne * k, 1.0), 0.0)
    hi = safe_div(dist + ne * r1, jnp.where(ok, nm - ne * k, 1.0), 0.0)
    return jnp.where(ok, jnp.maximum(at(lo), at(hi)), jnp.inf)


def _within_reach(n, p, c, m, r1, r2, h):
    """Whether the plane (n, p) cuts the segment (base ``c``) in an ellipse facing along ``m``
    that stays within :data:`PIECE_REACH` times its larger radius (:func:`plane_reach`)."""
    return plane_reach(n, dot3(n, p - c), m, r1, r2, h) <= PIECE_REACH * jnp.maximum(r1, r2)


def cutting_planes(j, ma, ca, ra0, ra1, ha, mb, rb0, rb1, hb):
    """Cutting planes at joints ``j`` between segments a (ending at j) and b (starting at j).

    Bhagvat et al. 2009, Eq. 3-5, vectorised over K joints (all arrays have leading K).
    Segment a runs from ``ca`` to ``j`` with radii ``ra0 -> ra1``; b runs from ``j`` along ``mb``
    for ``hb`` with radii ``rb0 -> rb1``. The construction is done in 2D inside the medial plane
    (origin j, axes e1 = ma, e2 = Nm x ma), as the paper suggests.

    Returns ``(n, p, kind)``: unit plane normals with n . (ma + mb) > 0, a point on each plane,
    and which plane was taken (``PLANE_*``). Collinear axes (the paper's coordinate-axis
    fallback) give the plane through j perpendicular to the axis, the construction's limit.
    Every other joint takes the first plane of a chain that keeps both pieces bounded: Eq. 3-5's
    plane; where its side lines are parallel (A or B at infinity), it does not cut both cones in
    ellipses facing their segments, or a piece would reach beyond :data:`PIECE_REACH` times its
    larger radius from its segment (:func:`plane_reach`), the bisector plane through j; where
    the bisector fails the same test, no shared plane (``PLANE_SPLIT``: each segment is cut
    perpendicular to its axis at j and capped, by :func:`joint_planes`; ``n``, ``p`` are then
    the bisector's, unused). So every piece lies within ``PIECE_REACH * max(r1, r2)`` of its
    segment whatever the skeleton (a taper to zero after a sharp bend put Eq. 3-5's plane
    nearly through the axis, a piece reaching hundreds of radii; a child thicker than its
    joint after a 20 degree bend reached several segment lengths). Differentiable
    (``numerics.safe_*``; the choice is piecewise constant)."""
    nm, collinear = medial_normal(ma, mb)
    e1, e2 = ma, jnp.cross(nm, ma)
    # 2D coordinates (origin j) of the axis directions and the joints; side(d) = M x Nm in 2D
    db = jnp.stack([dot3(mb, e1), dot3(mb, e2)], -1)
    ca2 = jnp.stack([dot3(ca - j, e1), dot3(ca - j, e2)], -1)
    sa = jnp.stack([jnp.zeros_like(hb), -jnp.ones_like(hb)], -1)
    sb = jnp.stack([db[:, 1], -db[:, 0]], -1)
    a2, oka = _meet(ca2, db * hb[:, None], sa, sb, ra0, ra1, rb0, rb1, 1.0)
    b2, okb = _meet(ca2, db * hb[:, None], sa, sb, ra0, ra1, rb0, rb1, -1.0)
    ab = a2 - b2
    n = _unit(jnp.cross(ab[:, :1] * e1 + ab[:, 1:] * e2, nm))
    n = n * jnp.where(dot3(n, ma + mb) < 0, -1.0, 1.0)[:, None]
    p = j + a2[:, :1] * e1 + a2[:, 1:] * e2

    bis = _unit(ma + mb)
    # both pieces of both candidate planes (an ellipse facing their segment, within reach) in one
    # call on the four stacked cases: the program holds one copy of the test, not four
    cat = lambda *xs: jnp.concatenate(xs, 0)  # noqa: E731
    ok = _within_reach(cat(n, n, bis, bis), cat(p, p, j, j), cat(ca, j, ca, j), cat(ma, mb, ma, mb), cat(ra0, rb0, ra0, rb0),
                       cat(ra1, rb1, ra1, rb1), cat(ha, hb, ha, hb)).reshape((4,) + ha.shape)
    eq35 = ~collinear & oka & okb & ok[0] & ok[1]
    bisector = ~collinear & ~eq35 & ok[2] & ok[3]
    kind = jnp.where(collinear, PLANE_COLLINEAR, jnp.where(eq35, PLANE_EQ35, jnp.where(bisector, PLANE_BISECTOR, PLANE_SPLIT)))
    n = jnp.where(eq35[:, None], n, jnp.where(collinear[:, None], ma, bis))
    p = jnp.where(eq35[:, None], p, j)
    return n, p, kind.astype(jnp.int32)


def segment_axes(joints, radii, start, end, valid=None):
    """``(c1, m, h, r1, r2)`` per segment row from (J, 3) joints and (J,) radii; rows where
    ``valid`` is False (padding) get a unit axis along +y, length 1 and radius 0."""
    c1 = joints[start]
    seg = joints[end] - c1
    h = safe_sqrt(dot3(seg, seg))
    m = safe_div(seg, h[:, None], 0.0)
    r1, r2 = radii[start], radii[end]
    if valid is None:
        return c1, m, h, r1, r2
    m = jnp.where(valid[:, None], m, jnp.array([0.0, 1.0, 0.0], joints.dtype))
    return c1, m, jnp.where(valid, h, 1.0), jnp.where(valid, r1, 0.0), jnp.where(valid, r2, 0.0)


def joint_planes(c1, m, h, r1, r2, a, b, cont=None):
    """``(nb, db, nt, dt, cap_b, cap_t, kind)``: every segment's bottom and top planes. Where row
    ``b[i]`` continues row ``a[i]`` (and ``cont[i]``, default all), both share the cutting plane
    of Eq. 3-5 at their joint or its bounded fallback (:func:`cutting_planes`, whose ``kind``
    (K,) is returned); every other end, and both ends of a ``PLANE_SPLIT`` joint, is cut
    perpendicular to the axis and capped."""
    n, p, kind = cutting_planes(c1[b], m[a], c1[a], r1[a], r2[a], h[a], m[b], r1[b], r2[b], h[b])
    shared = kind != PLANE_SPLIT if cont is None else cont & (kind != PLANE_SPLIT)
    s = h.shape[0]
    ta = jnp.where(shared, a, s)  # out of range: dropped
    tb = jnp.where(shared, b, s)
    nb = m.at[tb].set(n, mode="drop")
    db = jnp.zeros_like(h).at[tb].set(dot3(n, p - c1[b]), mode="drop")
    nt = m.at[ta].set(n, mode="drop")
    dt = h.at[ta].set(dot3(n, p - c1[a]), mode="drop")
    cap_b = jnp.ones(h.shape, bool).at[tb].set(False, mode="drop")
    cap_t = jnp.ones(h.shape, bool).at[ta].set(False, mode="drop")
    return nb, db, nt, dt, cap_b, cap_t, kind


def _frame_level(lvl, st, c1, m, h, r1, r2, nt, dt, topo: SegmentTopology, twist):
    """One depth level of :func:`frames`: the rows at depth ``lvl`` (``topo.by_level[lvl]``) take
    their ``W`` (and their u, v offsets) from the rows they continue or grow from."""
    w, u_off, v_off = st
    rows = topo.by_level[lvl]  # (W,), padding = N: gathered clamped, scattered dropped
    i = jnp.minimum(rows, h.shape[0] - 1)
    cont = topo.parent[i] >= 0
    a = jnp.maximum(topo.parent[i], 0)
    branch = topo.branch[i]
    mi, c1i = m[i], c1[i]
    ref = jnp.where((branch >= 0)[:, None], w[jnp.maximum(branch, 0)], jnp.array([0.0, 0.0, 1.0], c1.dtype))
    wr = ref - dot3(ref, mi)[:, None] * mi
    nrm = safe_sqrt(dot3(wr, wr))
    wr = jnp.where((nrm > 1e-6)[:, None], safe_div(wr, jnp.where(nrm > 1e-6, nrm, 1.0)[:, None], 0.0), _any_perp(mi))
    # continuations: W through Q, where the u = 0 generator of the lower frustum meets the plane
    k = safe_div(r2[a] - r1[a], h[a], 0.0)
    base = c1[a] + r1[a][:, None] * w[a]
    dirn = m[a] + k[:, None] * w[a]
    den = dot3(nt[a], dirn)
    q = base + safe_div(dt[a] - dot3(nt[a], base - c1[a]), den, 0.0)[:, None] * dirn
    wq = q - c1i
    wq = wq - dot3(wq, mi)[:, None] * mi
    nq = safe_sqrt(dot3(wq, wq))
    good = cont & (nq > 1e-9 * (h[i] + r1[i])) & (den != 0)
    w_new = jnp.where(good[:, None], safe_div(wq, nq[:, None], 0.0), wr)
    w = w.at[rows].set(w_new, mode="drop")
    u_off = u_off.at[rows].set(jnp.where(cont, u_off[a] + twist[a], u_off[i]), mode="drop")
    v_off = v_off.at[rows].set(jnp.where(cont, v_off[a] + 1.0, v_off[i]), mode="drop")
    return w, u_off, v_off


def frames(c1, m, h, r1, r2, nt, dt, topo: SegmentTopology, twist, levels: int):
    """``(u, w, u_off, v_off)`` in depth order (Sec. 2.3): roots take +z projected off the axis,
    side branches parallel-transport the frame of the segment they grow from, continuations
    pass through Q; ``levels`` is at least the deepest level plus one (a Python int for reverse
    differentiation, or traced, then the loop is a ``while_loop``)."""
    zeros = jnp.zeros(h.shape, c1.dtype)
    w0 = jnp.zeros_like(c1).at[:, 2].set(1.0)

    def level(lvl, st):
        return _frame_level(lvl, st, c1, m, h, r1, r2, nt, dt, topo, twist)

    w, u_off, v_off = jax.lax.fori_loop(0, levels, level, (w0, zeros, zeros))
    return jnp.cross(m, w), w, jnp.mod(u_off, 1.0), v_off


def frusta_fields(joints, radii, topo: SegmentTopology, twist_turns, levels: int, r1=None):
    """``(fields, kinds)``: every per-segment field of the frusta (a dict of the names of
    ``_build.FrustaArrays``) from (J, 3) joints, (J,) radii and the topology, rows in the
    topology's order, and (N,) how each row's base plane was chosen where it continues a row
    (``PLANE_*`` of :func:`cutting_planes`; -1 elsewhere); padding rows are placeholders that no
    ray hits. ``r1`` (N,), when given, replaces the base radii (the host build's minor-axis
    matching, Sec. 2.2, rescales them)."""
    c1, m, h, r1_j, r2 = segment_axes(joints, radii, topo.start, topo.end, topo.valid)
    r1 = r1_j if r1 is None else jnp.where(topo.valid, r1, 0.0)
    a = jnp.maximum(topo.parent, 0)
    cont = topo.parent >= 0
    nb, db, nt, dt, cap_b, cap_t, kind = joint_planes(c1, m, h, r1, r2, a, jnp.arange(h.shape[0]), cont)
    twist = jnp.full(h.shape, twist_turns, joints.dtype)
    u, w, u_off, v_off = frames(c1, m, h, r1, r2, nt, dt, topo, twist, levels)
    fields = dict(c1=c1, m=m, u=u, w=w, h=h, r1=r1, r2=r2, nb=nb, db=db, nt=nt, dt=dt, cap_b=cap_b, cap_t=cap_t,
                  u_off=u_off, twist=twist, v_off=v_off)
    return fields, jnp.where(cont & topo.valid, kind, -1)
