"""Analytic ray casting of conical frusta (Bhagvat et al. 2009, Sec. 2.3-2.5), in JAX.

``nearest_one`` takes one ray and a group of frusta and returns the nearest (t, s, code, index);
``_finish`` turns it into a ``Hit``. Both are branch-free (a miss is ``t = inf``) and batched with
``jax.vmap`` at the call site; ``nearest_batch`` is the batch-level variant that skips blocks.

Numerical form (why it differs from Eq. 9-10 as printed):

* the cone is ``x^2 + z^2 = (r1 + k y)^2`` (see ``_build``), so a = D_x^2 + D_z^2 - k^2 D_y^2,
  b/2 = E_x D_x + E_z D_z - k D_y (r1 + k E_y), c = E_x^2 + E_z^2 - (r1 + k E_y)^2: Eq. 10 with
  r1/h' replaced by -k, exact for cylinders and closed tips;
* the ray origin is first moved along the ray to the point nearest the segment's midpoint
  (t0), so E is small and c does not cancel for far origins; the hit is t = t0 + s and the local
  parameter s is kept for the hit position;
* the roots come from :func:`jskel.numerics.stable_quadratic` (no cancellation in -b +- sqrt);
* a == 0 (ray parallel to a generator, or along a cylinder's axis) is the linear case; a == b == 0
  gives no side hit, and then only the caps can be hit.

Segments are visited in blocks of ``block`` with ``lax.scan`` (a vmap over the block inside), so
memory is O(block) per ray whatever the number of segments; padding segments never hit. Two
one-off CPU measurements on 65,536 rays shaped this (docs/choices.md#segment-blocks): dot
products written out per component instead of ``jnp.sum(a * b, -1)`` made one segment's test
about nine times faster; and a vmap over a block of 64 with a min/select reduction took less
than half the time of a scan over single segments. The nearest candidate is therefore found by
min and selects, not argmin.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from ..numerics import dot3, eps_of, line_dist2, safe_div, safe_normalize, safe_sqrt, stable_quadratic
from ..rays import Hit, masked_hit

_TWO_PI = 2.0 * jnp.pi


class FrustaParams(NamedTuple):
    """Per-segment arrays (leading axis S, padded to a multiple of the block size).

    The fields mirror ``_build.FrustaArrays`` in the working dtype, plus ``valid`` (S,) marking
    real (non-padding) segments. Positions are relative to the scene anchor.
    """

    c1: jnp.ndarray
    m: jnp.ndarray
    u: jnp.ndarray
    w: jnp.ndarray
    h: jnp.ndarray
    r1: jnp.ndarray
    r2: jnp.ndarray
    nb: jnp.ndarray
    db: jnp.ndarray
    nt: jnp.ndarray
    dt: jnp.ndarray
    cap_b: jnp.ndarray
    cap_t: jnp.ndarray
    u_off: jnp.ndarray
    twist: jnp.ndarray
    valid: jnp.ndarray
    sid: jnp.ndarray  # (S,) int32 segment id in the skeleton (-1 for padding)
    shell: jnp.ndarray  # (S,) relief shell thickness (0 where the segment has no relief)
    v_off: jnp.ndarray  # (S,) v of the segment's base along its chain (a texture spans segments)


class Quality(NamedTuple):
    """Static options (hashable): changing one recompiles."""

    normals: str = "interpolated"  # "interpolated" (Eq. 8) or "geometric" (cone gradient)
    block: int = 64  # segments per scan step (padded to a multiple of it)


# codes of the surface that was hit
SIDE, CAP_BOTTOM, CAP_TOP = 0, 1, 2


def recentre(seg: FrustaParams, o, d):
    """(t0, e): the ray origin moved to the point nearest the segment's midpoint, relative to C1.

    Hits are then found as local parameters s with t = t0 + s, so the quadratic's constant term
    does not cancel for far origins.
    """
    dd = dot3(d, d)
    cm = seg.c1 + 0.5 * seg.h * seg.m
    t0 = safe_div(dot3(cm - o, d), dd, 0.0)
    return t0, o + t0 * d - seg.c1


def side_roots(seg: FrustaParams, e, d, dr=0.0):
    """Roots (s_lo, s_hi) of the ray e + s d with the cone of radii (r1 + dr, r2 + dr)."""
    k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
    return _cone_roots(k, seg.r1 + dr, dot3(e, seg.u), dot3(e, seg.m), dot3(e, seg.w), dot3(d, seg.u), dot3(d, seg.m), dot3(d, seg.w))


def _cone_roots(k, r1, ex, ey, ez, dx, dy, dz):
    """Roots of the ray (ex, ey, ez) + s (dx, dy, dz), in the frame (u, m, w), with the cone
    x^2 + z^2 = (r1 + k y)^2."""
    re = r1 + k * ey
    a = dx * dx + dz * dz - k * k * dy * dy
    hb = ex * dx + ez * dz - k * dy * re
    c = ex * ex + ez * ez - re * re
    return stable_quadratic(a, hb, c)


def _segment_t(seg: FrustaParams, o, d, t_min, t_max):
    """Nearest hit of one ray with one frustum: (t, s, code); t = inf on a miss.

    The ray is projected once on the frame (u, m, w) and on the two cutting-plane normals (ten
    dot products); every candidate point e + s d is then tested through those projections
    (x = ex + s dx, ...), not re-projected: fewer operations per (ray, segment) test, the
    innermost work of every traversal."""
    inf = jnp.asarray(jnp.inf, o.dtype)
    t0, e = recentre(seg, o, d)
    ex, ey, ez = dot3(e, seg.u), dot3(e, seg.m), dot3(e, seg.w)
    dx, dy, dz = dot3(d, seg.u), dot3(d, seg.m), dot3(d, seg.w)
    be, bd = dot3(seg.nb, e), dot3(seg.nb, d)
    te, td = dot3(seg.nt, e), dot3(seg.nt, d)
    k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
    # a, hb, c are all zero only for a ray along a cylinder's axis: no side hit then
    s_lo, s_hi = _cone_roots(k, seg.r1, ex, ey, ez, dx, dy, dz)

    tol = 32.0 * eps_of(o) * (seg.h + seg.r1 + seg.r2)

    def in_slab(s):
        return (be + s * bd >= seg.db - tol) & (te + s * td <= seg.dt + tol)

    def accept(s, ok):
        t = t0 + s
        good = ok & jnp.isfinite(s) & (t > t_min) & (t <= t_max) & seg.valid
        return jnp.where(good, t, inf), s

    def side(s):
        y = ey + s * dy
        return accept(s, in_slab(s) & (seg.r1 + k * y >= 0))

    def cap(ne, nd, dist, flag):
        s = safe_div(dist - ne, nd, inf)
        x, y, z = ex + s * dx, ey + s * dy, ez + s * dz
        ry = seg.r1 + k * y
        inside = (x * x + z * z <= ry * ry) & (ry >= 0) & in_slab(s)
        return accept(s, inside & flag)

    # nearest of the four candidates by a chain of selects (an argmin over a stacked axis is a
    # variadic reduce, which XLA on CPU runs several times slower)
    best_t, best_s = side(s_lo)
    best_c = jnp.int32(SIDE)
    for (tc, sc), code in (
        (side(s_hi), SIDE),
        (cap(be, bd, seg.db, seg.cap_b), CAP_BOTTOM),
        (cap(te, td, seg.dt, seg.cap_t), CAP_TOP),
    ):
        better = tc < best_t
        best_t = jnp.where(better, tc, best_t)
        best_s = jnp.where(better, sc, best_s)
        best_c = jnp.where(better, jnp.int32(code), best_c)
    return best_t, best_s, best_c


def _surface(seg: FrustaParams, o, d, s, code, normals: str):
    """Position, normal and (u, v) at local ray parameter ``s`` on segment ``seg``.

    (u, v): Eq. 6-7 with the frame alignment and twist of ``_build``; v is the ratio of the
    distances to the cutting planes along the generator through P (the line through P and the
    apex, written as direction M + k * radial so cylinders need no apex).
    Interpolated normals: Eq. 8, N = (1 - v) N_l + v N_u with N_l = P_l - C1, N_u = P_u - C2.
    """
    t0, e = recentre(seg, o, d)
    p = e + s * d  # relative to C1
    x, z = dot3(p, seg.u), dot3(p, seg.w)
    rho = safe_sqrt(x * x + z * z)
    radial = safe_div(x * seg.u + z * seg.w, rho, 0.0)
    k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
    g = seg.m + k * radial  # generator direction through P
    s_l = safe_div(seg.db - dot3(seg.nb, p), dot3(seg.nb, g), 0.0)
    s_u = safe_div(seg.dt - dot3(seg.nt, p), dot3(seg.nt, g), 0.0)
    v = jnp.clip(safe_div(-s_l, s_u - s_l, 0.0), 0.0, 1.0)
    v = jnp.where(code == CAP_BOTTOM, 0.0, jnp.where(code == CAP_TOP, 1.0, v))
    on_axis = rho <= 0
    ang = jnp.arctan2(jnp.where(on_axis, 0.0, x), jnp.where(on_axis, 1.0, z))
    u = jnp.mod(ang / _TWO_PI + seg.u_off + v * seg.twist, 1.0)

    true_n = safe_normalize(radial - k * seg.m)
    if normals == "interpolated":
        nl_raw = p + s_l * g  # P_l - C1
        nu_raw = p + s_u * g - seg.h * seg.m  # P_u - C2
        # at a closed end (r = 0) every generator meets the joint, so N_l or N_u is zero up to
        # rounding and its direction is noise: a normalised noise vector gave normals of any
        # direction (and, with denormals, not of unit length) that changed with the compiled
        # program. Where either is within rounding of zero the cone's own normal is used.
        tiny = (1024 * eps_of(p) * (seg.h + seg.r1 + seg.r2)) ** 2
        closed = (dot3(nl_raw, nl_raw) <= tiny) | (dot3(nu_raw, nu_raw) <= tiny)
        n_side = safe_normalize((1.0 - v) * safe_normalize(nl_raw) + v * safe_normalize(nu_raw))
        # where the blend itself vanishes (opposite N_l and N_u), the cone normal as well
        n_side = jnp.where((dot3(n_side, n_side) > 0.5) & ~closed, n_side, true_n)
    elif normals == "geometric":
        n_side = true_n
    else:  # pragma: no cover - validated in config
        raise ValueError(f"object.normals: unknown mode {normals!r}")
    normal = jnp.where(
        code == CAP_BOTTOM, -seg.nb, jnp.where(code == CAP_TOP, seg.nt, n_side)
    )
    return seg.c1 + p, normal, jnp.stack([u, v])


def _finish(params: FrustaParams, origin, direction, t, s, code, idx, normals: str) -> Hit:
    """Hit attributes for the winning segment of one ray (gathered once, not per segment)."""
    hit = jnp.isfinite(t)
    seg = jax.tree_util.tree_map(lambda a: a[jnp.maximum(idx, 0)], params)
    pos, normal, uv = _surface(seg, origin, direction, jnp.where(hit, s, 0.0), code, normals)
    return masked_hit(t, pos, normal, uv, seg.sid)


def _blocks(params, b: int):
    n = params.h.shape[0]
    return jax.tree_util.tree_map(lambda a: a.reshape((n // b, b) + a.shape[1:]), params)


def _reduce_block(ts, ss, cs, base, carry):
    """Fold the nearest of a block (last axis) into the running best, without argmin."""
    bt, bs, bc, bi = carry
    b = ts.shape[-1]
    tm = jnp.min(ts, axis=-1)
    idx = jnp.arange(b, dtype=jnp.int32)
    i = jnp.min(jnp.where(ts == tm[..., None], idx, b), axis=-1)
    sel = idx == i[..., None]
    sm = jnp.sum(jnp.where(sel, ss, 0.0), axis=-1)
    cm = jnp.sum(jnp.where(sel, cs, 0), axis=-1)
    better = tm < bt
    return (
        jnp.where(better, tm, bt),
        jnp.where(better, sm, bs).astype(bs.dtype),
        jnp.where(better, cm, bc).astype(bc.dtype),
        jnp.where(better, base + i, bi).astype(bi.dtype),
    )


def nearest_one(params: FrustaParams, seg_fn, origin, direction, t_min, t_max, block: int, undecided: bool = False):
    """Brute-force nearest of ``seg_fn(seg, o, d, t_min, t_max) -> (t, s, code)`` over segments.

    Returns (t, s, code, idx) with idx the position in ``params`` (-1 on a miss). ``undecided``
    (static; the relief's test): seg_fn returns a fourth value, the t where it could not decide
    (inf where it could), and its least over every segment is returned fifth.
    """
    vfn = jax.vmap(seg_fn, in_axes=(0, None, None, None, None))
    inf = jnp.asarray(jnp.inf, origin.dtype)

    def step(carry, xs):
        blk, base = xs
        out = vfn(blk, origin, direction, t_min, t_max)
        best = _reduce_block(*out[:3], base, carry[:4])
        if undecided:
            best = best + (jnp.minimum(carry[4], jnp.min(out[3])),)
        return best, None

    init = (inf, jnp.zeros((), origin.dtype), jnp.int32(SIDE), jnp.int32(-1)) + ((inf,) if undecided else ())
    nblk = params.h.shape[0] // block
    bases = jnp.arange(nblk, dtype=jnp.int32) * block
    out, _ = jax.lax.scan(step, init, (_blocks(params, block), bases))
    return out


def _rays_touch_sphere(origins, directions, dd, t_min, t_max, c, r):
    """(N,) whether each ray's (t_min, t_max] passes within r of c (a bounding-sphere test); a
    padding block's sphere (r < 0) is met by none (r * r alone would let rays within 1 of c in)."""
    oc = c[None, :] - origins
    tc = safe_div(dot3(oc, directions), dd, 0.0)
    dist2 = line_dist2(oc, directions, tc)
    rt = safe_div(r, safe_sqrt(dd), 0.0)  # d = 0: no NaN
    return (dist2 <= r * r) & (tc + rt > t_min) & (tc - rt <= t_max) & (r >= 0)


def _no_hits(n: int, dtype):
    """Running best (t, s, code, index) of n rays before any segment is tested."""
    return (
        jnp.full((n,), jnp.inf, dtype),
        jnp.zeros((n,), dtype),
        jnp.full((n,), SIDE, jnp.int32),
        jnp.full((n,), -1, jnp.int32),
    )


def _scan_blocks(step, params, block: int, block_c, block_r, init):
    """Run ``step(carry, (block params, base index, sphere centre, radius))`` over the blocks."""
    nblk = params.h.shape[0] // block
    bases = jnp.arange(nblk, dtype=jnp.int32) * block
    out, _ = jax.lax.scan(step, init, (_blocks(params, block), bases, block_c, block_r))
    return out


def nearest_batch(params: FrustaParams, block_c, block_r, seg_fn, origins, directions, t_min, t_max, block: int):
    """Batched :func:`nearest_one` that skips whole blocks no ray of the batch can reach.

    block_c (B,3), block_r (B,): a bounding sphere per block of ``block`` segments. For each
    block the rays of the batch are tested against its sphere; if none touches it, the block is
    skipped by a ``lax.cond`` on that *scalar* (batch-wide) predicate, which, unlike a per-ray
    ``cond`` under vmap, really skips the work. Rays should be spatially coherent (the renderer
    orders them in screen tiles). Equal to ``vmap(nearest_one)`` hit for hit.
    """
    vfn = jax.vmap(jax.vmap(seg_fn, in_axes=(0, None, None, None, None)), in_axes=(None, 0, 0, 0, 0))
    dtype = origins.dtype
    n = origins.shape[0]
    dd = dot3(directions, directions)

    def touches(c, r):
        return _rays_touch_sphere(origins, directions, dd, t_min, t_max, c, r)

    def step(carry, xs):
        blk, base, c, r = xs

        def work(carry):
            ts, ss, cs = vfn(blk, origins, directions, t_min, t_max)
            return _reduce_block(ts, ss, cs, base, carry)

        return jax.lax.cond(jnp.any(touches(c, r)), work, lambda c_: c_, carry), None

    return _scan_blocks(step, params, block, block_c, block_r, _no_hits(n, dtype))


def nearest_batch_compact(params: FrustaParams, block_c, block_r, pre_fn, seg_fn, origins, directions, t_min, t_max, block: int, cap: int,
                          undecided: bool = False, seg_c=None, seg_r=None, lanes=None):
    """Like :func:`nearest_batch`, but ``seg_fn`` runs only on the (ray, segment) pairs that
    ``pre_fn(seg, o, d, t_min, t_max) -> bool`` admits: compaction, not masking.

    For each block the cheap ``pre_fn`` (e.g. "the ray enters this segment's relief shell") is
    evaluated for every pair; the admitted pairs are gathered into dense sub-batches of ``cap``
    lanes and a ``while_loop`` runs only as many sub-batches as there are admitted pairs. Under
    vmap a per-pair ``cond`` would run the expensive branch for every pair. Results are merged
    with scatter-min, so they equal the masked version up to ties in t. ``undecided``: as in
    :func:`nearest_one` (the least over the marched pairs, fifth).

    ``seg_c``, ``seg_r`` (S,3), (S,): a bounding sphere per segment. Then ``pre_fn`` runs only on
    the pairs whose ray meets the segment's sphere, gathered the same way (``wavefront.compact_map``):
    on every pair it was most of a relief cast's time when the march took one step
    (docs/choices.md#relief-pairs).

    ``lanes``: (begin, advance, done, finish, steps) for a ``seg_fn`` of many uneven iterations
    (``_relief_exact``): ``begin(seg, o, d, t_min, t_max) -> (ctx, state)``, ``advance(ctx,
    state) -> state``, ``done(state)``, ``finish(ctx, state) -> (t, s, code, *undecided)``. Then
    the admitted pairs are traced by ``cap`` persistent lanes, each refilled with the next pair
    as its own finishes, ``steps`` iterations between refills (``wavefront.refill_loop``),
    instead of sub-batches that each wait for their slowest pair.
    """
    n = origins.shape[0]
    dtype = origins.dtype
    rays = (origins, directions, t_min, t_max)
    dd = dot3(directions, directions)
    vpre = jax.vmap(jax.vmap(pre_fn, in_axes=(0, None, None, None, None)), in_axes=(None, 0, 0, 0, 0))

    def touches(c, r):
        return _rays_touch_sphere(origins, directions, dd, t_min, t_max, c, r)

    def step(carry, xs):
        blk, base, c, r, sc, sr = xs

        def seg_of(pair):
            return base + pair % block

        def work(carry):
            if sc is None:
                ok = vpre(blk, origins, directions, t_min, t_max).reshape(-1)  # (n * block,), ray-major
            else:
                near = jax.vmap(touches, out_axes=1)(sc, sr).reshape(-1)  # (n, block): the segment's sphere
                ok = _admitted(params, pre_fn, rays, near, seg_of, block, cap)
            return _cast_pairs(params, seg_fn, rays, *_set_pairs(ok, cap), lambda p: p // block, seg_of, cap, lanes, carry)

        return jax.lax.cond(jnp.any(touches(c, r)), work, lambda c_: c_, carry), None

    init = _no_hits(n, dtype) + ((jnp.full((n,), jnp.inf, dtype),) if undecided else ())
    nblk = params.h.shape[0] // block
    bases = jnp.arange(nblk, dtype=jnp.int32) * block
    spheres = (None, None) if seg_c is None else (seg_c.reshape(nblk, block, 3), seg_r.reshape(nblk, block))
    out, _ = jax.lax.scan(step, init, (_blocks(params, block), bases, block_c, block_r, *spheres))
    return out


def nearest_leaves_compact(params: FrustaParams, order, leaf: int, first, after, pre_fn, seg_fn, origins, directions, t_min, t_max, cap: int,
                           seg_c, seg_r, undecided: bool = False, lanes=None):
    """:func:`nearest_batch_compact` over each ray's own candidates instead of every block: the
    segments of the BVH leaves the ray meets. ``first() -> (leaves (N, C) leaf indices, -1 in
    unused slots, overflow (N,))`` lists them (``wavefront.leaves_of``); ``after(need, r) ->
    (leaves, overflow)`` lists the next ones of the rays ``need`` whose list overflowed in
    round r - 1 (``wavefront.leaves_after``); ``order``: the tree's (L * leaf,) segment row of
    each leaf slot, -1 for padding.

    Each round numbers the (ray, listed leaf slot) candidates by a prefix sum of the rays' list
    lengths, so its work follows the candidates listed, not N x C x ``leaf`` (a mask of every
    slot and its compaction cost 5x the march on the relief column's 4,096 camera rays):
    ``cap`` candidates at a time are tested against their segment's sphere (``seg_c``,
    ``seg_r``) and ``pre_fn``, the admitted appended to a list, which ``seg_fn`` casts in
    sub-batches of ``cap`` (or the persistent ``lanes``), merged by scatter-min (a pair listed
    twice merges to the same result). Rounds run while a ray's list overflows, in one
    ``while_loop``, so ``seg_fn`` is compiled once. The same pairs as the blocks wherever a
    leaf's box bounds its segments' shells."""
    n = origins.shape[0]
    rays = (origins, directions, t_min, t_max)
    rays_ = jax.lax.stop_gradient(rays)  # the admission is a decision: nothing to differentiate
    params_ = jax.lax.stop_gradient(params)
    init = _no_hits(n, origins.dtype) + ((jnp.full((n,), jnp.inf, origins.dtype),) if undecided else ())

    def one_round(r, need, acc):
        leaves, over = jax.lax.cond(r == 0, lambda _: first(), lambda nd: after(nd, r), need)
        c = leaves.shape[1]
        per = jnp.sum(leaves >= 0, axis=1, dtype=jnp.int32) * leaf  # candidates per ray
        end = jnp.cumsum(per)
        total = end[-1]
        size = n * c * leaf + cap  # every slot admitted, at most

        def admit(st):
            j, m, buf_r, buf_s = st
            k = j * cap + jnp.arange(cap, dtype=jnp.int32)
            ray = jnp.minimum(jnp.searchsorted(end, k, side="right").astype(jnp.int32), n - 1)
            local = k - (end[ray] - per[ray])
            lf = leaves[ray, jnp.minimum(local // leaf, c - 1)]
            seg = jnp.where((k < total) & (lf >= 0), order[jnp.maximum(lf, 0) * leaf + local % leaf], -1)
            row = jnp.maximum(seg, 0)
            o, d, a, b = (x[ray] for x in rays_)
            near = _rays_touch_sphere(o, d, dot3(d, d), a, b, seg_c[row], seg_r[row]) & (seg >= 0)
            sg = jax.tree_util.tree_map(lambda x: x[row], params_)
            ok = near & jax.vmap(pre_fn)(sg, o, d, a, b)
            at = jnp.where(ok, m + jnp.cumsum(ok.astype(jnp.int32)) - 1, size)  # appended in order; size: dropped
            return j + 1, m + jnp.sum(ok, dtype=jnp.int32), buf_r.at[at].set(ray, mode="drop"), buf_s.at[at].set(row, mode="drop")

        zeros = jnp.zeros((size,), jnp.int32)
        _, m, buf_r, buf_s = jax.lax.while_loop(lambda st: st[0] * cap < total, admit, (jnp.int32(0), jnp.int32(0), zeros, zeros))
        acc = _cast_pairs(params, seg_fn, rays, jnp.arange(size, dtype=jnp.int32), m, lambda p: buf_r[p], lambda p: buf_s[p], cap, lanes, acc)
        return acc, need & over

    def body(st):
        r, need, acc = st
        acc, need = one_round(r, need, acc)
        return r + 1, need, acc

    _, _, out = jax.lax.while_loop(lambda st: jnp.any(st[1]), body, (jnp.int32(0), jnp.ones((n,), bool), init))
    return out


def _admitted(params: FrustaParams, pre_fn, rays, near, seg_of, per_ray: int, cap: int):
    """(pairs,) bool: the pairs ``near`` marks that ``pre_fn`` admits, ``pre_fn`` run only on
    those (``wavefront.compact_map``). Pair p is ray p // ``per_ray`` and segment row
    ``seg_of(p)``."""
    from ..wavefront import compact_map

    rays_ = jax.lax.stop_gradient(rays)  # a decision: nothing to differentiate

    def test(idx):
        seg = jax.tree_util.tree_map(lambda a: jax.lax.stop_gradient(a)[seg_of(idx)], params)
        return jax.vmap(pre_fn)(seg, *(a[idx // per_ray] for a in rays_))

    return compact_map(test, near, jnp.arange(near.shape[0], dtype=jnp.int32), jnp.zeros_like(near), cap)


def _cast_pairs(params: FrustaParams, seg_fn, rays, order, count, ray_of, seg_of, cap: int, lanes, carry):
    """``carry`` (the running best (t, s, code, index, *undecided) of every ray) with the pairs
    ``order[:count]`` (int32 codes, padded with at least ``cap`` entries; code p is ray
    ``ray_of(p)`` and segment row ``seg_of(p)``) cast by ``seg_fn`` and merged by scatter-min:
    in sub-batches of ``cap``, or through the persistent ``lanes``
    (:func:`nearest_batch_compact`)."""
    from ..wavefront import refill_loop

    origins, directions, t_min, t_max = rays
    n = origins.shape[0]
    vseg = jax.vmap(seg_fn, in_axes=(0, 0, 0, 0, 0))

    def merge(acc, pair, live, t, s_, code, und):
        bt, bs, bc, bi, *bu = acc
        ray = jnp.where(live, ray_of(pair), n)  # n: dropped by the scatters
        rc = jnp.minimum(ray, n - 1)
        t = jnp.where(live, t, jnp.inf)
        bu = [b_.at[ray].min(u_, mode="drop") for b_, u_ in zip(bu, und)]  # (dropped where not live)
        new_t = bt.at[ray].min(t, mode="drop")
        win = live & (t == new_t[rc]) & (t < bt[rc])
        wr = jnp.where(win, ray, n)
        bs = bs.at[wr].set(s_, mode="drop")
        bc = bc.at[wr].set(code, mode="drop")
        bi = bi.at[wr].set(seg_of(pair), mode="drop")
        return (new_t, bs, bc, bi, *bu)

    def gathered(pair):
        rc = jnp.minimum(ray_of(pair), n - 1)
        seg = jax.tree_util.tree_map(lambda a: a[seg_of(pair)], params)
        return seg, origins[rc], directions[rc], t_min[rc], t_max[rc]

    if lanes is not None:
        begin, advance, done, finish, steps = lanes
        return refill_loop(lambda p: jax.vmap(begin)(*gathered(p)), jax.vmap(advance), jax.vmap(done),
                           lambda acc, p, ctx, st, fin: merge(acc, p, fin, *jax.vmap(finish)(ctx, st)),
                           order, count, cap, steps, carry)

    def sub(state):
        j, acc = state
        lane = j * cap + jnp.arange(cap, dtype=jnp.int32)
        pair = jax.lax.dynamic_slice(order, (j * cap,), (cap,))
        t, s_, code, *und = vseg(*gathered(pair))
        return j + 1, merge(acc, pair, lane < count, t, s_, code, und)

    _, out = jax.lax.while_loop(lambda st: st[0] * cap < count, sub, (jnp.int32(0), carry))
    return out


def _set_pairs(ok, cap: int):
    """(order, count): the indices of ``ok``'s set entries (``accel.first_set``), padded with
    ``cap`` entries, as :func:`_cast_pairs` takes them."""
    from ..accel import first_set, pack_bits

    order, count = first_set(pack_bits(ok), ok.shape[0])
    return jnp.concatenate([jnp.minimum(order, ok.shape[0] - 1), jnp.zeros((cap,), jnp.int32)]), count


def inside_one(params: FrustaParams, point) -> jnp.ndarray:
    """True when ``point`` (3,) lies inside (or on) any frustum between its cutting planes."""
    def one(seg):
        p = point - seg.c1
        x, y, z = dot3(p, seg.u), dot3(p, seg.m), dot3(p, seg.w)
        k = safe_div(seg.r2 - seg.r1, seg.h, 0.0)
        ry = seg.r1 + k * y
        return (
            seg.valid
            & (ry >= 0)
            & (x * x + z * z <= ry * ry)
            & (dot3(seg.nb, p) >= seg.db)
            & (dot3(seg.nt, p) <= seg.dt)
        )

    return jnp.any(jax.vmap(one)(params))
