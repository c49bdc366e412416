"""Frusta through the linear BVH of ``jskel.accel`` (issue 6).

Bounds (Sec. 2.6 bounds each frustum by a pyramid): a clipped frustum is the convex hull of its
two elliptical cuts (every generator runs straight from one cut to the other), so the box of
``n_ang`` points on each cut, grown by the chord sag of the polygon, bounds it. Computed in JAX
from the segment parameters, so the tree is rebuilt from the frame's own frusta.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..accel import BVH, Best, bin_groups, build, hold, map_groups, nearest, nearest_binned, nearest_packet
from ..numerics import dot3, safe_div
from ._intersect import CAP_BOTTOM, SIDE, FrustaParams, _cone_roots, _segment_t, recentre


def segment_boxes(f: FrustaParams, n_ang: int = 32):
    """(lo, hi) (S,3) boxes of each frustum (relative to the anchor)."""
    ang = jnp.linspace(0.0, 2 * math.pi, n_ang, endpoint=False).astype(f.h.dtype)
    rad = jnp.cos(ang)[None, :, None] * f.u[:, None, :] + jnp.sin(ang)[None, :, None] * f.w[:, None, :]
    k = jnp.where(f.h > 0, (f.r2 - f.r1) / jnp.where(f.h > 0, f.h, 1.0), 0.0)
    base = f.c1[:, None, :] + f.r1[:, None, None] * rad
    dirn = f.m[:, None, :] + k[:, None, None] * rad
    pts = []
    # dot products written out (``_intersect._dot``): as jnp.sum over the last axis of 3, XLA on
    # the CPU ran them as library reductions, a quarter of the cacti's device rebuild
    for n, dist in ((f.nb, f.db), (f.nt, f.dt)):
        den = dot3(n[:, None, :], dirn)
        y = (dist[:, None] - dot3(n[:, None, :], base - f.c1[:, None, :])) / jnp.where(den == 0, 1.0, den)
        pts.append(base + y[..., None] * dirn)
    pts = jnp.concatenate(pts, axis=1)
    lo, hi = pts.min(1), pts.max(1)
    # the polygon of n_ang points inside a convex cut misses at most its sag; grow by twice the
    # sag of the widest cut, plus float rounding of the coordinates
    size = _max3(hi - lo)
    grow = 2.0 * (1.0 - math.cos(2 * math.pi / n_ang)) * size + 64 * jnp.finfo(f.h.dtype).eps * (jnp.max(jnp.abs(pts), axis=(1, 2)) + size)
    return lo - grow[:, None], hi + grow[:, None]


def _max3(x):
    return jnp.maximum(jnp.maximum(x[..., 0], x[..., 1]), x[..., 2])


_PACKED = ("c1", "m", "u", "w", "h", "r1", "r2", "nb", "db", "nt", "dt", "cap_b", "cap_t", "valid")


class FrustaBVH(NamedTuple):
    """The tree and the segments' ray-test fields packed in leaf order: one row per leaf slot,
    so a leaf's segments arrive in one gather instead of one per field."""

    tree: BVH
    rows: jnp.ndarray  # (L * leaf, 30) packed _PACKED fields, padding slots invalid
    box_lo: jnp.ndarray  # (S, 3) each segment's box, in ``f``'s order (empty for padding)
    box_hi: jnp.ndarray  # (S, 3)


def _pack(f: FrustaParams, order):
    cols = []
    for name in _PACKED:
        a = getattr(f, name).astype(f.h.dtype)
        cols.append(a[jnp.maximum(order, 0)].reshape(order.shape[0], -1))
    rows = jnp.concatenate(cols, axis=1)
    return rows.at[:, -1].set(jnp.where(order >= 0, rows[:, -1], 0.0))


def packed_widths(f: FrustaParams) -> tuple[int, ...]:
    """Columns of each ``_PACKED`` field in a packed row (1 for scalars, 3 for vectors)."""
    return tuple(1 if getattr(f, name).ndim == 1 else 3 for name in _PACKED)


def _unpack(rows, f: FrustaParams) -> FrustaParams:
    out, i = {}, 0
    for name, w in zip(_PACKED, packed_widths(f)):
        col = rows[..., i : i + w]
        out[name] = col[..., 0] if w == 1 else col
        i += w
    out["cap_b"] = out["cap_b"] > 0.5
    out["cap_t"] = out["cap_t"] > 0.5
    out["valid"] = out["valid"] > 0.5
    z = jnp.zeros(rows.shape[:-1], rows.dtype)
    return FrustaParams(**out, u_off=z, twist=z, sid=z.astype(jnp.int32), shell=z, v_off=z)


def build_bvh(f: FrustaParams, leaf: int) -> FrustaBVH:
    lo, hi = segment_boxes(f)
    tree = build(lo, hi, f.valid, leaf)
    inf = jnp.asarray(jnp.inf, lo.dtype)
    return FrustaBVH(tree, _pack(f, tree.order), jnp.where(f.valid[:, None], lo, inf), jnp.where(f.valid[:, None], hi, -inf))


def shell_bvh(f: FrustaParams, leaf: int) -> BVH:
    """``accel.BVH`` over the outer solids of relief segments' shells (radii grown by each row's
    ``shell``), for culling their (ray, segment) pairs by the leaves each ray meets
    (``_intersect.nearest_leaves_compact``)."""
    lo, hi = segment_boxes(f._replace(r1=f.r1 + f.shell, r2=f.r2 + f.shell))
    return build(lo, hi, f.valid, leaf)


def _leaf_best(f: FrustaParams, fb: FrustaBVH, leaf: int, slots, o, d, t_min, t_hi):
    """Best of one ray against one leaf's segments (their rows arrive in one gather)."""
    seg = _unpack(jax.lax.dynamic_slice_in_dim(fb.rows, slots[0], leaf), f)
    ids = jax.lax.dynamic_slice_in_dim(fb.tree.order, slots[0], leaf)
    ts, ss, cs = jax.vmap(_segment_t, in_axes=(0, None, None, None, None))(seg, o, d, t_min, t_hi)
    tm = jnp.min(ts)
    i = jnp.min(jnp.where(ts == tm, jnp.arange(leaf), leaf))
    sel = jnp.arange(leaf) == i
    return Best(tm, jnp.sum(jnp.where(sel, ss, 0.0)), jnp.sum(jnp.where(sel, cs, 0)).astype(jnp.int32),
                jnp.where(jnp.isfinite(tm), jnp.sum(jnp.where(sel, ids, 0)), -1).astype(jnp.int32))


def _init(dtype):
    return Best(jnp.asarray(jnp.inf, dtype), jnp.zeros((), dtype), jnp.int32(SIDE), jnp.int32(-1))


def miss_is_inf(t, idx):
    """t where a segment was hit, else +inf: the walks start their best t at the ray's t_max, so a
    ray with a finite window that meets nothing would otherwise come back with t = t_max."""
    return jnp.where(idx >= 0, t, jnp.asarray(jnp.inf, t.dtype))


def nearest_bvh(f: FrustaParams, fb: FrustaBVH, leaf: int, o, d, t_min, t_max, any_hit: bool = False):
    """(t, s, code, idx, visits, leaves) of one ray through the tree; idx indexes ``f``; with
    ``any_hit`` the first hit the walk finds (``accel.nearest``)."""

    def leaf_fn(slots, o, d, t_min, t_hi):
        return _leaf_best(f, fb, leaf, slots, o, d, t_min, t_hi)

    best, visits, leaves = nearest(fb.tree, leaf_fn, leaf, o, d, t_min, t_max, _init(o.dtype), any_hit)
    return miss_is_inf(best.t, best.idx), best.s, best.code, best.idx, visits, leaves


def nearest_packets(f: FrustaParams, fb: FrustaBVH, leaf: int, packet: int, origins, directions, t_min, t_max):
    """(t, s, code, idx, iterations) of a batch in packets of ``packet`` consecutive rays, each
    packet one traversal (``accel.nearest_packet``; ``lax.map`` over packets). Consecutive rays
    should be close on screen (``camera.tile_order``: a packet of 256 is a 16 x 16 square); the
    results equal :func:`nearest_groups`' whatever the order, only the time depends on it."""
    n = origins.shape[0]
    g = min(packet, n)
    leaf_fn = jax.vmap(lambda slots, o, d, a, b: _leaf_best(f, fb, leaf, slots, o, d, a, b), in_axes=(None, 0, 0, 0, 0))

    def one(xs):
        best, it = nearest_packet(fb.tree, leaf_fn, leaf, *xs, _init(origins.dtype))
        return miss_is_inf(best.t, best.idx), best.s, best.code, best.idx, jnp.broadcast_to(it, best.t.shape)

    return map_groups(lambda *xs: one(xs), g, origins, directions, t_min, t_max)


def nearest_groups(f: FrustaParams, bvh, leaf: int, group: int, origins, directions, t_min, t_max, any_hit: bool = False):
    """:func:`nearest_bvh` over a batch in groups of ``group`` rays (``lax.map`` over groups,
    vmap within one): a vmapped while loop runs until its slowest ray ends, so small groups of
    coherent rays waste the fewest lanes."""
    one = jax.vmap(lambda o, d, a, b: nearest_bvh(f, bvh, leaf, o, d, a, b, any_hit))
    return map_groups(one, group, origins, directions, t_min, t_max)


# up to this many segments (the plain group's size bucket, so no new program) ``nearest_bins``
# compiles its pair test for one lane count, not two (``accel._bins._lane_test``): a smaller
# program at no cost in render time on small objects; above it the two are kept (a long list's
# part-full steps run on fewer lanes; docs/choices.md#bins-one-lane)
BINS_ONE_LANE = 32


def nearest_bins(f: FrustaParams, fb: FrustaBVH, packet: int, candidates: int, pairs: int, group: int, walk_ratio: float, origins, directions, t_min, t_max,
                 leaf: int = 4, walk_group: int = 512):
    """(t, s, code, idx, (n_batch, n_pairs)) of a batch through packet candidate lists
    (``accel.nearest_binned``): each packet of ``packet`` consecutive rays tests only the
    segments whose box one of its rays may meet; equal to brute force, ties included.
    ``group`` > 0: the batch's list is found through the tree's nodes of ``group`` leaf slots
    (``accel.batch_list``); in ``experiments/bench_scale_bins_knobs.yaml`` 32 beat 0 (every box)
    in most settings on the 18,557-segment oasis (docs/choices.md#bins-group).
    ``walk_ratio`` > 0: a batch whose list holds more than ``walk_ratio`` segments per ray is
    cast by per-ray walks (:func:`nearest_groups`, groups of ``walk_group``) instead: segments
    smaller than a packet's footprint (``experiments/bench_scale_size.yaml``'s wall of small
    copies: bins and walks cost the same at about 1.6 segments per ray in the list; docs/performance.md).

    The loop keeps t and the segment only; (s, code) come from one more test of each ray
    against its segment. That test is a program of its own, which XLA may round apart from the
    loop's: where it misses a hit the loop found (a graze), s is taken as t - t0 and the code
    as the side."""

    def pair_fn(ids, o, d, a, b):
        seg = jax.tree_util.tree_map(lambda x: x[ids], f)
        return jax.vmap(jax.vmap(_segment_t, in_axes=(None, 0, 0, 0, 0)))(seg, o, d, a, b)[0]

    groups = bin_groups(fb.tree, group) if group else None
    n = origins.shape[0]

    def walks(o, d, a, b):
        out = nearest_groups(f, fb, leaf, walk_group, o, d, a, b)
        return out[0], out[3]

    # (not compiled where the list cannot pass the threshold: fewer segments than that)
    fallback = walks if walk_ratio > 0 and int(walk_ratio * n) < f.h.shape[0] else None
    t, idx, counts = nearest_binned(fb.box_lo, fb.box_hi, pair_fn, packet, candidates, pairs, origins, directions, t_min, t_max, groups,
                                    fallback, int(walk_ratio * n), root=(fb.tree.lo[1], fb.tree.hi[1]),
                                    one_lane=f.h.shape[0] <= BINS_ONE_LANE)
    def again():
        seg = jax.tree_util.tree_map(lambda x: x[jnp.maximum(idx, 0)], f)
        return jax.vmap(_segment_t)(seg, origins, directions, t_min, t_max) + (jax.vmap(recentre)(seg, origins, directions)[0],)

    # in a conditional: XLA fused this test into each consumer of s and code (position,
    # normal, uv, shading) and ran it once per consumer; and a batch without a hit skips it
    zero = jnp.zeros(origins.shape[:1], origins.dtype)
    t_again, s, c, t0 = jax.lax.cond(jnp.any(idx >= 0), again, lambda: (zero, zero, jnp.zeros(zero.shape, jnp.int32), zero))
    again = jnp.isfinite(t_again)
    return t, jnp.where(again, s, t - t0), jnp.where(again, c, SIDE), idx, counts


def segment_at(seg: FrustaParams, o, d, s, code):
    """(t, s) of one ray on the surface ``code`` of one frustum, nearest the local parameter
    ``s`` that a traversal found: the closed forms of ``_segment_t`` without its window and its
    choice among candidates (the side root nearest ``s``, or a cap's plane), for the derivative
    of a hit whose value came from a loop (``accel.nearest_tangent``). Sec. 2.4-2.5: the side
    roots of the cone quadratic (Eq. 9-10 in ``_intersect``'s form), the caps on the cutting
    planes (Eq. 3-5)."""
    t0, e = recentre(seg, o, d)
    ex, ey, ez = dot3(e, seg.u), dot3(e, seg.m), dot3(e, seg.w)
    dx, dy, dz = dot3(d, seg.u), dot3(d, seg.m), dot3(d, seg.w)
    k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
    s_lo, s_hi = _cone_roots(k, seg.r1, ex, ey, ez, dx, dy, dz)
    side = jnp.where(jnp.abs(s_lo - s) <= jnp.abs(s_hi - s), s_lo, s_hi)
    s_b = safe_div(seg.db - dot3(seg.nb, e), dot3(seg.nb, d), 0.0)
    s_t = safe_div(seg.dt - dot3(seg.nt, e), dot3(seg.nt, d), 0.0)
    s_new = jnp.where(code == SIDE, side, jnp.where(code == CAP_BOTTOM, s_b, s_t))
    return t0 + s_new, s_new


def winner_ts(f: FrustaParams, rays, out):
    """(t, s, None, None) of a batch's winning segments in closed form (:func:`segment_at`)
    from a traversal's (t, s, code, idx): the ``winner`` of ``accel.nearest_tangent``. A miss
    evaluates segment 0 with its tangents held at 0, so no NaN reaches either mode."""
    t, s, code, idx = out
    hit = jnp.isfinite(t)
    seg = jax.tree_util.tree_map(lambda a: a[jnp.maximum(idx, 0)], f)
    seg, o, d = hold(hit, (seg, rays[0], rays[1]))
    tt, ss = jax.vmap(segment_at)(seg, o, d, jnp.where(hit, s, 0.0), jnp.where(hit, code, CAP_BOTTOM))
    return tt, ss, None, None
