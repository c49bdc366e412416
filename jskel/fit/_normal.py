"""The fit's normal equations assembled from its sparsity (issue 10): J^T J and J^T r without
a dense Jacobian, so Levenberg-Marquardt and Gauss-Newton fit chains of hundreds of segments.

A point's residual is a function of one segment's frusta geometry: the signed distance is a
minimum over the point's candidate segments (``_distance._signed``), so its gradient reaches
only the segment that attains it (ties, of measure zero, go to one; :func:`point_rows`). A
segment's geometry (``Geometry``: axis start, direction, length, radii, its two cutting planes:
17 numbers) depends on at most four joints: its own two, and the far joints of the segment it
continues and of the one continuing it (the shared planes of Eq. 3-5 of Bhagvat et al. 2009,
Sec. 2.2, see ``_distance.cutting_planes``). So with ``R_i`` the residual's gradient with
respect to its segment's 17 numbers and ``G_s`` the 17 x 16 Jacobian of segment s's geometry
with respect to its joints' 16 unknowns,

    J^T J = sum_s G_s^T (sum_{i on s} R_i^T R_i) G_s,      J^T r = sum_s G_s^T sum_{i on s} R_i r_i,

(the inner sums a ``segment_sum`` over points, the outer 16 x 16 blocks scattered into the
dense (4J, 4J) matrix). The per-point gradients are one reverse pass over the point's few
candidates (as L-BFGS's gradient), the geometry Jacobian one forward pass with a handful of
tangents: joints are coloured so that no two joints of a colour touch the same segment (or the
same penalty row), and one tangent per colour and unknown (x, y, z, radius) carries all joints
of that colour at once, each output reading back only its own joints (Curtis, Powell and Reid
1974's compressed Jacobian; a chain needs 5 colours, 20 tangents, for any length). The
smoothness and plane-validity penalties (``_problem.penalty_rows``) are rows of their own
through the same forward pass.

Memory is O(points x 17 x 17 + (4J)^2) instead of the dense Jacobian's O(points x 4J), and the
work per iteration is one residual pass, its gradients and a (4J)^2 Cholesky. The dense
matrix limits this to a few thousand joints (a 5,000-segment chain's 20,004^2 float32 matrix is
1.6 GB); beyond that a banded or sparse factorisation would be next.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..accel import always, fenced
from ._distance import Geometry, Segments, Topology, _candidates, caps_of, segment_distances

FIELDS = 17  # numbers per segment in Geometry (c1 3, m 3, h, r1, r2, nb 3, db, nt 3, dt)


def flat_geometry(g: Geometry):
    """(S, 17) the per-segment numbers of ``g`` in one array."""
    one = lambda a: a[:, None]  # noqa: E731
    return jnp.concatenate([g.c1, g.m, one(g.h), one(g.r1), one(g.r2), g.nb, one(g.db), g.nt, one(g.dt)], -1)


def geometry_of_flat(f) -> Geometry:
    """:func:`flat_geometry`'s inverse (any leading shape)."""
    return Geometry(f[..., 0:3], f[..., 3:6], f[..., 6], f[..., 7], f[..., 8], f[..., 9:12], f[..., 12], f[..., 13:16], f[..., 16])


class Structure(NamedTuple):
    """Static (NumPy) sparsity of a skeleton's fit."""

    seg_joints: np.ndarray  # (S, 4) joints a segment's geometry depends on (padding: joint 0, masked)
    seg_mask: np.ndarray  # (S, 4) bool
    pen_joints: np.ndarray  # (K, Dp) joints each continuation's penalty rows depend on
    pen_mask: np.ndarray  # (K, Dp) bool
    colors: np.ndarray  # (J,) a colour per joint: no two joints of a row's set share one
    n_colors: int


#: joints a segment's geometry depends on (its own two, and the far joints of the segment it
#: continues and of the one continuing it), and a continuation's penalty rows (its two
#: segments': the first's before it, the shared joint's, the second's after it)
SEG_WIDTH, PEN_WIDTH = 4, 6


class Sparsity(NamedTuple):
    """A :class:`Structure`'s arrays padded to a problem's sizes (a pytree traced with the fit's
    data, ``_problem.Layout``): (S, 4) and (K, 6) joints and masks, (J,) colours; the count of
    colours is the problem's (static)."""

    seg_joints: np.ndarray
    seg_mask: np.ndarray
    pen_joints: np.ndarray
    pen_mask: np.ndarray
    colors: np.ndarray


def _padded(sets):
    width = max((len(s) for s in sets), default=1) or 1
    idx = np.zeros((len(sets), width), np.int64)
    mask = np.zeros((len(sets), width), bool)
    for i, s in enumerate(sets):
        idx[i, : len(s)] = s
        mask[i, : len(s)] = True
    return idx, mask


@functools.lru_cache(maxsize=8)
def structure(seg: Segments, n_joints: int) -> Structure:
    """Which joints each segment's geometry and each continuation's penalty rows depend on,
    and a greedy colouring of the joints that keeps every such set's joints apart (kept for the
    last few topologies: a fit asks for it for its sizes and again for its layout; callers
    never write into it)."""
    start, end = np.asarray(seg.start, np.int64), np.asarray(seg.end, np.int64)
    deps = [[int(start[s]), int(end[s])] for s in range(len(start))]
    for a, b in zip(np.asarray(seg.cont_a), np.asarray(seg.cont_b)):
        deps[b].insert(0, int(start[a]))  # the continued segment's far joint (its plane with b)
        deps[a].append(int(end[b]))  # the continuing segment's far joint
    deps = [list(dict.fromkeys(d)) for d in deps]
    pen = [list(dict.fromkeys(deps[a] + deps[b])) for a, b in zip(np.asarray(seg.cont_a), np.asarray(seg.cont_b))]
    neighbours = [set() for _ in range(n_joints)]
    for group in deps + pen:
        for j in group:
            neighbours[j].update(group)
    colors = -np.ones(n_joints, np.int64)
    for j in range(n_joints):  # host loop over joints, once per problem (static topology)
        used = {int(colors[k]) for k in neighbours[j] if k != j and colors[k] >= 0}
        c = 0
        while c in used:
            c += 1
        colors[j] = c
    sj, sm = _padded(deps)
    pj, pm = _padded(pen) if pen else (np.zeros((0, 1), np.int64), np.zeros((0, 1), bool))
    return Structure(sj, sm, pj, pm, colors, int(colors.max()) + 1 if n_joints else 0)


def sparsity_of(st: Structure, joints: int, segments: int, conts: int) -> Sparsity:
    """``st``'s arrays padded to ``joints``, ``segments`` and ``conts`` rows (int32; padding
    rows joint 0, masked; padding joints colour 0, in no row)."""

    def rows(a, n, width, dtype):
        out = np.zeros((n, width), dtype)
        out[: a.shape[0], : a.shape[1]] = a
        return out

    colors = np.zeros(joints, np.int32)
    colors[: len(st.colors)] = st.colors
    return Sparsity(rows(st.seg_joints, segments, SEG_WIDTH, np.int32), rows(st.seg_mask, segments, SEG_WIDTH, bool),
                    rows(st.pen_joints, conts, PEN_WIDTH, np.int32), rows(st.pen_mask, conts, PEN_WIDTH, bool), colors)


def _param_index(joints, n_joints: int):
    """(..., 4) flat parameter indices of joints (x, y, z, radius) in ``_problem.unpack``'s layout."""
    j = jnp.asarray(joints)[..., None]
    return jnp.concatenate([3 * j + jnp.arange(3, dtype=j.dtype), 3 * n_joints + j], -1)


def _seeds(colors, n_colors: int, dtype):
    """(4C, 4J) tangents: for colour c and unknown p, 1 on unknown p of every joint of colour c
    (``colors`` (J,) traced)."""
    nj = colors.shape[0]
    oh = (colors[None, :] == jnp.arange(n_colors, dtype=colors.dtype)[:, None]).astype(dtype)  # (C, J)
    xyz = (oh[:, None, :, None] * jnp.eye(3, dtype=dtype)[None, :, None, :]).reshape(n_colors, 3, 3 * nj)
    xyz = jnp.concatenate([xyz, jnp.zeros((n_colors, 3, nj), dtype)], -1)
    rad = jnp.concatenate([jnp.zeros((n_colors, 1, 3 * nj), dtype), oh[:, None, :]], -1)
    return jnp.concatenate([xyz, rad], 1).reshape(4 * n_colors, 4 * nj)


def _decode(out, colors, joints, mask):
    """Read back, for each row of ``out`` (4C, R, F) and each of its joints (R, D), the
    derivative with respect to that joint's 4 unknowns: (R, F, D, 4), zero where masked."""
    c = colors[joints]  # (R, D)
    col = c[..., None] * 4 + jnp.arange(4, dtype=c.dtype)  # (R, D, 4)
    o = jnp.moveaxis(out, 0, -1)  # (R, F, 4C)
    rows = jnp.arange(joints.shape[0])[:, None, None]
    vals = o[rows, :, col]  # (R, D, 4, F)
    vals = jnp.moveaxis(vals, -1, 1) * jnp.asarray(mask, out.dtype)[:, None, :, None]
    return vals


def point_rows(flat, seg: Segments | Topology, points, candidates: int, robust, block: int = 0, per_block: int = 0):
    """Each point's robust residual (N,), its gradient with respect to the 17 numbers of the
    one segment it depends on (N, 17), and that segment (N,).

    The signed distance (``_distance._signed``) is the minimum over the point's candidates of
    one of two per-segment distances (to the pieces bounded by all their planes, or capped at
    free ends only, chosen by the candidates together), so its value and gradient are those of
    the winning segment's distance alone: the candidates are measured forward only, and the
    reverse pass runs on the winner's 17 numbers (it ran on all candidates' before, their
    gradients zero but the winner's; ties, of measure zero, go to the first)."""
    s = flat.shape[0]
    cap_b, cap_t = (jnp.asarray(c) for c in caps_of(seg))
    if 0 < candidates < s:
        idx, _ = _candidates(geometry_of_flat(flat), points, candidates, block, per_block)
    else:
        idx = jnp.broadcast_to(jnp.arange(s), (points.shape[0], s))

    def one(p, i):
        sub = geometry_of_flat(jax.lax.stop_gradient(flat[i]))
        cb, ct = cap_b[i], cap_t[i]
        d_cap, within = segment_distances(sub, p, cb, ct)
        d_all = segment_distances(sub, p)[0]
        use_all = (jnp.min(d_all) > 0) | ~jnp.any(within)  # as _signed chooses
        a = jnp.where(use_all, jnp.argmin(d_all), jnp.argmin(jnp.where(within, d_cap, jnp.inf)))

        def f(row):
            g1 = geometry_of_flat(row[None])
            v = jnp.where(use_all, segment_distances(g1, p)[0][0], segment_distances(g1, p, cb[a][None], ct[a][None])[0][0])
            return robust(v)

        r, grow = jax.value_and_grad(f)(flat[i[a]])
        return r, grow, i[a]

    return jax.vmap(one)(points, idx)


def normal_equations(x, points, model_fn, seg: Topology, sp: Sparsity, n_colors: int, candidates: int, robust, block: int = 0,
                     per_block: int = 0, cover=None):
    """(r, J^T J, J^T r) of the fit's residuals at ``x`` (4J,): ``r`` in ``_problem.residuals``'s
    order (points, cover rows, then penalty rows).

    ``model_fn(x) -> (Geometry, (K, E))``: the frusta, and ``E`` penalty rows per continuation
    (each depending only on its two segments' joints). ``seg`` and ``sp`` (:func:`sparsity_of`,
    with ``n_colors`` colours) are the topology and its sparsity as data, so one program serves
    every topology of the same sizes. ``cover(flat) -> (r (S, M), dr/dflat (S, M, 17))``: rows
    that each depend on one segment's 17 numbers (``_problem.cover_segment_rows``)."""
    n_joints = x.shape[-1] // 4
    nseg = seg.start.shape[0]
    seeds = _seeds(sp.colors, n_colors, x.dtype)

    def both(x):
        g, pen = model_fn(x)
        return flat_geometry(g), pen

    (flat, pen), lin = jax.linearize(both, x)
    dflat, dpen = jax.vmap(lin)(seeds)  # (4C, S, 17), (4C, K, E)
    gj = _decode(dflat, sp.colors, sp.seg_joints, sp.seg_mask).reshape(nseg, FIELDS, -1)  # (S, 17, 4D)
    sidx = _param_index(sp.seg_joints, n_joints).reshape(nseg, -1)  # (S, 4D)

    # fenced: compiled in one program with the segment_sum of their outer products below, XLA on
    # the CPU (jax 0.10.2) computed the points' rows with the gradient in their segment's first
    # number (c1.x) zero for the points of segment 0 (10 of 1,200 points of
    # tests/test_fit_normal.py's branching chain; J^T J wrong by 0.6 in entries of up to 54, while
    # the same program run op by op, or point_rows compiled alone, was right)
    r, rows, which = fenced(always(flat), lambda: point_rows(flat, seg, points, candidates, robust, block, per_block))
    m = jax.ops.segment_sum(rows[:, :, None] * rows[:, None, :], which, nseg)  # (S, 17, 17)
    v = jax.ops.segment_sum(rows * r[:, None], which, nseg)  # (S, 17)
    if cover is not None:
        rc, jc = cover(flat)
        m = m + jnp.einsum("smf,smg->sfg", jc, jc)
        v = v + jnp.einsum("smf,sm->sf", jc, rc)
        r = jnp.concatenate([r, rc.reshape(-1)])
    h = jnp.einsum("sfa,sfg,sgb->sab", gj, m, gj)
    p = 4 * n_joints
    jtj = jnp.zeros((p, p), x.dtype).at[sidx[:, :, None], sidx[:, None, :]].add(h)
    jtr = jnp.zeros((p,), x.dtype).at[sidx].add(jnp.einsum("sfa,sf->sa", gj, v))
    if pen.shape[0] and pen.shape[1]:
        k, e = pen.shape
        pv = _decode(dpen, sp.colors, sp.pen_joints, sp.pen_mask)  # (K, E, Dp, 4)
        pv = pv.reshape(k, e, -1)
        pidx = _param_index(sp.pen_joints, n_joints).reshape(k, -1)
        jtj = jtj.at[pidx[:, :, None], pidx[:, None, :]].add(jnp.einsum("kea,keb->kab", pv, pv))
        jtr = jtr.at[pidx].add(jnp.einsum("kea,ke->ka", pv, pen))
        r = jnp.concatenate([r, pen.reshape(-1)])
    return r, jtj, jtr
