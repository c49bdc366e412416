"""Candidate lists for packets of coherent rays: culling by interval arithmetic, then dense tests
of (packet, primitive) pairs (issue 6).

Bhagvat et al. (2009, Sec. 2.6) never walk a hierarchy per ray: each frustum's bounding pyramid
is rasterised and the fragment shader casts only the rays under it. ``nearest_binned`` is that
idea for any batch of rays, in the order ``jskel.camera.tile_order`` gives them (consecutive rays
close on screen):

1. the batch is cut into packets of ``packet`` consecutive rays; each packet is bounded by the
   box of its origins, the box of its directions and its t range (interval arithmetic, as in
   packet tracers of the 2000s: a box is kept when *some* ray of those boxes could meet it,
   ``packet_meets``, a superset of the rays' own hits);
2. the primitive boxes that the whole batch may meet are compacted into a list (``nonzero``,
   O(primitives) per batch);
3. that list is taken ``candidates`` at a time, nearest the batch first (sorted by where the
   batch's bound enters each box), each block tested against every packet; the (packet,
   primitive) pairs that pass are compacted, ``pairs`` at a time and in that near-to-far order,
   into dense tests of every ray of the packet against the pair's primitive, and a
   ``segment_min`` over the packet keeps each ray's nearest t, a second its primitive. Before
   each step, the pairs left are pruned: a box that every ray of its packet enters beyond its
   best hit so far cannot hold a nearer one (``packet_entry``), the front-to-back cut-off a BVH
   walk makes. The pairs left are a bit mask (:func:`pack_bits`) and a cursor: each step takes
   the first ``pairs`` set bits (:func:`first_set`), so every pair before the cursor is done or
   pruned for good (best t only falls). On the cacti at 1024 x 768 that halved the segment tests per ray (7.5 -> 4.0,
   ``experiments/bench_scale.yaml``'s stats); the sparse oasis (9 % of the pixels hit, few
   packets ever resolved) prunes 1 % and pays for the compaction per step. Nothing else
   rides through the loop: the caller recomputes what it needs of the hit (surface parameter,
   code) from the winning primitive, one test per ray (two scatters per step where (t, index,
   parameter, code) took four).

The loops run as many times as the lists are long (compaction; nothing is tested that no
packet may meet or that pruning has ruled out, and no static capacity can overflow). The result
equals brute force: every primitive a ray hits is in its packet's list (the test is
conservative), pruning drops only boxes that lie beyond a nearer hit, and ties in t go to the
lowest primitive index, as ``frusta._intersect.nearest_one`` does.

Why on the CPU: XLA runs dense elementwise work at full width, while a per-ray walk is a
vmapped while loop that runs until its slowest ray ends. On the 2,158-segment cacti at
1024 x 768 (packets of 64, 8 x 8 pixels) a packet's list held 7.5 segments per ray on average,
4.0 tested after pruning, against the 14 segments per ray that the BVH walk tests (docs/performance.md).
Incoherent rays still get the right answer, only with long lists: the BVH traversals remain for
them.
"""

from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp


def _products(t0, t1, dlo, dhi):
    """Bounds of t * d for t in [t0, t1], d in [dlo, dhi] (0 where d is 0, even at t = inf)."""
    ps = []
    for t in (t0, t1):
        for d in (dlo, dhi):
            ps.append(jnp.where(d == 0, 0.0, t * d))
    return jnp.minimum(jnp.minimum(ps[0], ps[1]), jnp.minimum(ps[2], ps[3])), jnp.maximum(jnp.maximum(ps[0], ps[1]), jnp.maximum(ps[2], ps[3]))


def packet_meets(olo, ohi, dlo, dhi, tlo, thi, lo, hi):
    """:func:`packet_entry`'s first result: whether the packet may meet each box."""
    return packet_entry(olo, ohi, dlo, dhi, tlo, thi, lo, hi)[0]


def packet_entry(olo, ohi, dlo, dhi, tlo, thi, lo, hi):
    """Whether some ray ``o + t d`` with o in [olo, ohi], d in [dlo, dhi] (3,) and t in
    [tlo, thi] may meet the boxes [lo, hi] (N, 3); conservative (never False for a box that one
    of the packet's rays meets). Empty boxes (lo = +inf) are never met.

    Per axis with d of one sign, the union over the packet of each ray's slab interval lies in
    [min (lo - o) / d, max (hi - o) / d], whose ends interval arithmetic gives; the intersection
    over axes of those unions contains every ray's hit interval. An axis whose d interval holds
    0 gives no such bound; it is checked afterwards: over the t range left by the other axes,
    o + t d stays in [olo + min(t d), ohi + max(t d)], which must overlap the box's slab.

    Returns (met, t0): t0 is at most every packet ray's entry t into the box, so a box whose t0
    lies beyond every ray's best hit so far cannot hold a nearer hit."""
    neg = dhi < 0
    mono = neg | (dlo > 0)
    # mirror the axes where d < 0 so that d > 0 on every monotone axis
    o_lo, o_hi = jnp.where(neg, -ohi, olo), jnp.where(neg, -olo, ohi)
    d_lo, d_hi = jnp.where(neg, -dhi, dlo), jnp.where(neg, -dlo, dhi)
    b_lo, b_hi = jnp.where(neg, -hi, lo), jnp.where(neg, -lo, hi)
    d_lo_safe = jnp.where(mono, d_lo, 1.0)
    d_hi_safe = jnp.where(mono, d_hi, 1.0)
    n_lo, n_hi = b_lo - o_hi, b_hi - o_lo
    enter = jnp.where(n_lo < 0, n_lo / d_lo_safe, n_lo / d_hi_safe)
    leave = jnp.where(n_hi > 0, n_hi / d_lo_safe, n_hi / d_hi_safe)
    inf = jnp.asarray(jnp.inf, lo.dtype)
    t0 = jnp.maximum(jnp.max(jnp.where(mono, enter, -inf), axis=-1), tlo)
    t1 = jnp.minimum(jnp.min(jnp.where(mono, leave, inf), axis=-1), thi)
    p_lo, p_hi = _products(t0[:, None], t1[:, None], dlo, dhi)
    reach = (olo + p_lo <= hi) & (ohi + p_hi >= lo)
    return (t0 <= t1) & jnp.all(mono | reach, axis=-1) & jnp.all(lo <= hi, axis=-1), t0


def packet_bounds(origins, directions, t_min, t_max):
    """(olo, ohi, dlo, dhi, tlo, thi) of rays over their second-to-last axis (...,  G, 3)."""
    return (_tree(jnp.minimum, origins, -2), _tree(jnp.maximum, origins, -2), _tree(jnp.minimum, directions, -2),
            _tree(jnp.maximum, directions, -2), _tree(jnp.minimum, t_min, -1), _tree(jnp.maximum, t_max, -1))


def _tree(op, x, axis: int):
    """``op``-reduction of x over ``axis`` by halving: elementwise ops that XLA fuses into one
    loop. XLA on the CPU sent ``x.min(-2)`` over a packet's (64, 64, 3) rays to a library
    reduction call; the eight packet bounds of a 4,096-ray chunk were most of an empty chunk's
    cost (development profile, docs/choices.md#packet-bounds-tree). Not for reductions whose
    result feeds a big elementwise consumer: XLA then fuses the tree into it and recomputes it
    per element (the packets' reach in the pair loop ran slower so)."""
    x = jnp.moveaxis(x, axis, 0)
    while x.shape[0] > 1:
        h = x.shape[0] // 2
        y = op(x[:h], x[h : 2 * h])
        x = jnp.concatenate([y, x[2 * h :]]) if x.shape[0] % 2 else y
    return x[0]


def _pad_rows(x, n: int):
    pad = n - x.shape[0]
    return jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])]) if pad else x


def batch_list(whole, lo, hi, groups=None):
    """(list (S + extra,) int32, count): the primitives whose boxes a batch of rays bounded by
    ``whole`` may meet, first ``count`` entries valid.

    ``groups = (g_lo, g_hi, slots)``: boxes (NG, 3) over groups of primitives and each group's
    primitives (NG, per) (-1 for padding), e.g. one level of a BVH. The groups are tested
    first and only the primitives of met groups, ``per * 8`` at a time in a while loop; a
    batch that sees a small part of the scene then tests far fewer boxes than S."""
    s = lo.shape[0]
    if groups is None:
        m1 = packet_meets(*whole, lo, hi)
        return jnp.nonzero(m1, size=s, fill_value=0)[0].astype(jnp.int32), jnp.sum(m1, dtype=jnp.int32)
    g_lo, g_hi, slots = groups
    ng_all, per = slots.shape
    b = min(8, ng_all)
    mg = packet_meets(*whole, g_lo, g_hi)
    ng = jnp.sum(mg, dtype=jnp.int32)
    glist = jnp.concatenate([jnp.nonzero(mg, size=ng_all, fill_value=0)[0].astype(jnp.int32), jnp.zeros((b,), jnp.int32)])
    out = jnp.zeros((s + b * per,), jnp.int32)

    def body(st):
        j, out, n1 = st
        gi = jax.lax.dynamic_slice_in_dim(glist, j * b, b)
        rows = slots[gi]
        ids = rows.reshape(-1)
        ok = ((j * b + jnp.arange(b) < ng)[:, None] & (rows >= 0)).reshape(-1)
        safe = jnp.maximum(ids, 0)
        m = packet_meets(*whole, lo[safe], hi[safe]) & ok
        found = jnp.nonzero(m, size=b * per, fill_value=0)[0]
        out = jax.lax.dynamic_update_slice_in_dim(out, safe[found], n1, 0)
        return j + 1, out, n1 + jnp.sum(m, dtype=jnp.int32)

    _, out, n1 = jax.lax.while_loop(lambda st: st[0] * b < ng, body, (jnp.int32(0), out, jnp.int32(0)))
    return out, n1


def _order(e):
    """``jnp.argsort(e)`` (stable: ties by index) of a short vector, from each entry's rank
    among all pairwise comparisons, one fusion and a scatter. XLA on the CPU ran the sort of a
    bin block's 128 entry distances as a library call costing about as much as the block's
    box tests (``jax.profiler`` trace of the oasis' densest chunks); K^2 compares
    of K = 128 run at full vector width (docs/choices.md#bins-order)."""
    k = e.shape[0]
    i = jnp.arange(k)
    before = (e[None, :] < e[:, None]) | ((e[None, :] == e[:, None]) & (i[None, :] < i[:, None]))
    rank = jnp.sum(before, axis=1, dtype=jnp.int32)
    return jnp.zeros((k,), jnp.int32).at[rank].set(i.astype(jnp.int32), unique_indices=True)


def bin_groups(tree, per: int):
    """The BVH ``tree``'s nodes at the level whose subtrees hold ``per`` leaf slots: their boxes
    and slots, the ``groups`` that :func:`batch_list` tests before their primitives."""
    slots = tree.order.shape[0]
    ng = max(1, slots // max(per, 1))
    return tree.lo[ng : 2 * ng], tree.hi[ng : 2 * ng], tree.order.reshape(ng, -1)


def fenced(pred, fn: Callable):
    """``fn()``, computed in a conditional whose predicate ``pred`` is true at run time but
    unknown to the compiler: its results are materialised once, as a fusion boundary.

    XLA on the CPU fuses cheap elementwise producers into every consumer. In the pair loop that
    put the last part of the pair test, with the compaction's index arithmetic, into both
    consumers of t (the two ``segment_min``) and ran it per element in each; fenced, the bins
    cast of the cacti at 1024 x 768 took about two thirds of the time on one core (development
    A/B, same process). ``jax.lax.optimization_barrier`` did not change the fusions."""
    shapes = jax.eval_shape(fn)
    return jax.lax.cond(pred, fn, lambda: jax.tree_util.tree_map(lambda x: jnp.zeros(x.shape, x.dtype), shapes))


def always(x):
    """A boolean true at run time that the compiler cannot fold (no float exceeds +inf; a NaN
    compares false), taken from the float array ``x``: a predicate for :func:`fenced`."""
    return ~(x.reshape(-1)[0] > jnp.inf)


def pack_bits(mask):
    """(W,) uint32 words of a flat bool mask: bit b of word w is ``mask[32 w + b]`` (padded with
    False). With :func:`first_set`, the compaction of the bins' pair loop."""
    n = mask.shape[0]
    nw = -(-n // 32)
    m = jnp.pad(mask, (0, nw * 32 - n)).reshape(nw, 32).astype(jnp.uint32)
    return jax.lax.reduce(m << jnp.arange(32, dtype=jnp.uint32), jnp.uint32(0), jax.lax.bitwise_or, (1,))


def first_set(words, q: int):
    """(positions (q,) int32, count): where the first ``q`` set bits of ``words`` (:func:`pack_bits`)
    lie, in order, and how many bits are set; positions past the count are meaningless.

    ``jnp.nonzero(mask, size=q)`` does this with a prefix sum over the whole mask and a scatter
    of every element; XLA on the CPU runs that prefix sum as a long ``reduce_window``, many times
    slower than this on 8,192 elements (docs/choices.md#first-set-words). Here the prefix sum
    runs over the words' popcounts (32 times fewer), each rank finds its word by a histogram of
    those sums and its bit by a binary search on the popcount of the word's low bits."""
    nw = words.shape[0]
    pc = jax.lax.population_count(words).astype(jnp.int32)
    incl = jnp.cumsum(pc)
    r = jnp.arange(q, dtype=jnp.int32)
    # the word of rank r: how many words' inclusive counts are <= r, as a histogram of those
    # counts and its prefix sum over q (``searchsorted``'s binary search ran as a loop of 8
    # small steps, a thunk each on XLA's CPU runtime)
    wi = jnp.minimum(jnp.cumsum(jnp.zeros((q + 1,), jnp.int32).at[jnp.minimum(incl, q)].add(1))[:q], nw - 1)
    j = r - (incl[wi] - pc[wi])  # the rank within its word
    w = words[wi]
    pos = jnp.zeros_like(r)
    for sh in (16, 8, 4, 2, 1):
        cand = pos + sh
        low = jax.lax.population_count(w & ((jnp.uint32(1) << cand.astype(jnp.uint32)) - jnp.uint32(1))).astype(jnp.int32)
        pos = jnp.where(low <= j, cand, pos)
    return wi * 32 + pos, incl[-1]


class _Batch(NamedTuple):
    """What :func:`nearest_binned`'s loops read of one batch: the primitive boxes, the pair
    test, the rays cut into ``p`` packets of ``g`` (``po``, ``pd``, ``pa``, ``pb``: (P, G, ...)),
    the batch's bounds ``whole``, its ``n`` rays, the ``k`` candidates per block and ``q``
    pairs per step, and whether the pair test is compiled for ``q`` lanes alone (``one_lane``)."""

    lo: jax.Array
    hi: jax.Array
    pair_fn: Callable
    po: jax.Array
    pd: jax.Array
    pa: jax.Array
    pb: jax.Array
    whole: tuple
    n: int
    p: int
    g: int
    k: int
    q: int
    one_lane: bool = False


# every packet's bounds against one block's boxes: (P, K) met and entry t
_meets_per_packet = jax.vmap(packet_entry, in_axes=(0, 0, 0, 0, 0, 0, None, None))


def nearest_binned(lo, hi, pair_fn: Callable, packet: int, candidates: int, pairs: int, origins, directions, t_min, t_max, groups=None,
                   fallback: Callable | None = None, fallback_above: int = 0, root=None, one_lane: bool = False):
    """Nearest hit of every ray of a batch (N,) through packet candidate lists (module docstring).

    lo, hi: (S, 3) primitive boxes (empty boxes for padding). ``pair_fn(ids (Q,), o, d, t_min,
    t_max)`` with rays (Q, G, ...) returns t (Q, G) (inf on a miss). Returns ``(t, idx)`` with
    leading axis N and idx the primitive index (-1 on a miss), plus (n_batch, n_pairs): the
    batch's list length and the pairs tested, for statistics.

    ``fallback(origins, directions, t_min, t_max) -> (t, idx)``: where the batch's list holds
    more than ``fallback_above`` primitives, the batch is cast by it instead (a ``lax.cond`` on
    that batch-wide count, so one of the two runs) and n_pairs is -1. Packets share their work
    while primitives are no smaller than a packet's footprint; below that every packet's list
    holds everything under it, and a packet's cost grows with the primitives' density, not with
    log(primitives): a per-ray BVH walk is the fallback that keeps the cost per ray
    logarithmic (docs/performance.md: cost per ray against log(segments)).

    ``root = (lo (3,), hi (3,))``, a box around every primitive: a batch that cannot meet it
    (sky) skips everything but its own bounds (a ``lax.cond``).

    ``one_lane``: the pair test is compiled once, on ``pairs`` lanes, instead of once per lane
    size of :func:`_lane_test` (for few primitives: a smaller program, see its caller)."""
    n = origins.shape[0]
    g = min(packet, n)
    n_pad = -(-n // g) * g
    p = n_pad // g
    po, pd, pa, pb = (_pad_rows(x, n_pad).reshape((p, g) + x.shape[1:]) for x in (origins, directions, t_min, t_max))
    # the batch's bounds from its rays (min and max are exact: the same as over the packets')
    whole = packet_bounds(origins[None], directions[None], t_min[None], t_max[None])
    whole = tuple(b[0] for b in whole)
    s = lo.shape[0]
    k = min(candidates, s)
    q = min(pairs, p * k)
    batch = _Batch(lo, hi, pair_fn, po, pd, pa, pb, whole, n, p, g, k, q, one_lane)
    full = functools.partial(_full, batch, groups, fallback, fallback_above, origins, directions, t_min, t_max)

    def sky():
        return jnp.full((n,), jnp.inf, origins.dtype), jnp.full((n,), -1, jnp.int32), jnp.int32(0), jnp.int32(0)

    if root is None:
        t, idx, n1, tested = full()
    else:
        t, idx, n1, tested = jax.lax.cond(packet_meets(*whole, root[0][None], root[1][None])[0], full, sky)
    return t, idx, (n1, tested)


def _full(batch: _Batch, groups, fallback, fallback_above: int, origins, directions, t_min, t_max):
    """(t, idx, list length, pairs tested) of a batch that may meet the scene: its candidate
    list (:func:`batch_list`), then the binned loops or, past ``fallback_above`` candidates,
    the fallback (pairs tested -1)."""
    k, p, g = batch.k, batch.p, batch.g
    list1, n1 = batch_list(batch.whole, batch.lo, batch.hi, groups)
    list1 = jnp.concatenate([list1, jnp.zeros((k,), jnp.int32)])
    best = (jnp.full((p, g), jnp.inf, origins.dtype), jnp.full((p, g), -1, jnp.int32))
    lin = jnp.arange(k * p, dtype=jnp.int32).reshape(k, p)
    binned = functools.partial(_binned, batch, list1, n1, lin, best)
    if fallback is None:
        t, idx, tested = binned()
    else:
        t, idx, tested = jax.lax.cond(n1 > fallback_above, lambda: (*fallback(origins, directions, t_min, t_max), jnp.int32(-1)), binned)
    return t, idx, n1, tested


def _binned(batch: _Batch, list1, n1, lin, best):
    """(t (N,), idx (N,), pairs tested): the candidate list ``list1`` (``n1`` valid) taken
    ``k`` at a time (:func:`_block`), the best hits carried from block to block."""
    k = batch.k
    bounds = packet_bounds(batch.po, batch.pd, batch.pa, batch.pb)  # each (P, 3) or (P,)

    def body(st):
        best, tested = _block(batch, list1, n1, lin, bounds, st[0], st[1], st[2])
        return st[0] + 1, best, tested

    _, (t, idx), tested = jax.lax.while_loop(lambda st: st[0] * k < n1, body, (jnp.int32(0), best, jnp.int32(0)))
    n_pad = batch.p * batch.g
    return t.reshape(n_pad)[:batch.n], idx.reshape(n_pad)[:batch.n], tested


def _block(batch: _Batch, list1, n1, lin, bounds, j, best, tested):
    """(best, tested) after block ``j`` of the list: its boxes sorted nearest the batch first,
    every packet tested against them, then the (packet, primitive) pairs that pass, ``q`` per
    step (:func:`_pair_step`), until none is left alive."""
    k = batch.k
    ids = jax.lax.dynamic_slice_in_dim(list1, j * k, k)
    live = j * k + jnp.arange(k) < n1
    # the block's boxes nearest the batch first (where the batch enters each box)
    e1 = jnp.where(live, packet_entry(*batch.whole, batch.lo[ids], batch.hi[ids])[1], jnp.inf)
    perm = _order(e1)
    ids, live = ids[perm], live[perm]
    m2, e2 = fenced(n1 >= 0, lambda: _meets_per_packet(*bounds, batch.lo[ids], batch.hi[ids]))
    m2 = (m2 & live[None, :]).T  # (K, P): candidate-major, nearest candidates first
    e2 = e2.T
    step = functools.partial(_pair_step, batch, ids, m2, e2, lin)
    init = (jnp.int32(0), _alive(m2, e2, lin, jnp.int32(0), best[0]), best)
    nt, _, best = jax.lax.while_loop(lambda st: jnp.any(st[1] != 0), step, init)
    return best, tested + nt


def _alive(m2, e2, lin, cursor, bt):
    """Bit words (:func:`pack_bits`) of the block's pairs not yet taken: met (``m2``), at or
    after the cursor (taken pairs all lie before it: each step takes the first alive pairs in
    order, and a pruned pair stays pruned as best t only falls), and not entered by the packet
    beyond every one of its rays' best t (``e2``; a NaN bound keeps its pair)."""
    reach = jnp.max(bt, axis=1)  # inf while a ray of the packet has no hit
    return pack_bits((m2 & (lin >= cursor) & ~(e2 > reach[None, :])).reshape(-1))


def _pair_step(batch: _Batch, ids, m2, e2, lin, st):
    """One step of a block's pair loop: the first ``q`` alive pairs tested ray by ray, each
    packet's nearest t (and, of equal t, lowest primitive) merged into the best hits, and the
    pairs left alive after it."""
    nt, words, best = st
    bt, bi = best
    k, p, q = batch.k, batch.p, batch.q
    big = jnp.int32(jnp.iinfo(jnp.int32).max)
    at, na = first_set(words, q)
    ok = jnp.arange(q) < na
    at = jnp.minimum(at, k * p - 1)
    pk = jnp.where(ok, at % p, p)
    prim = ids[at // p]
    rows = jnp.minimum(pk, p - 1)
    t = _lane_test(batch, na, rows, prim)
    t = jnp.where(ok[:, None], t, jnp.inf)
    tm = jax.ops.segment_min(t, pk, num_segments=p)
    hit = (t == tm[rows]) & ok[:, None] & jnp.isfinite(t)
    im = jax.ops.segment_min(jnp.where(hit, prim[:, None], big), pk, num_segments=p)
    better = jnp.isfinite(tm) & ((tm < bt) | ((tm == bt) & (im < bi)))
    best = (jnp.where(better, tm, bt), jnp.where(better, im, bi))
    # every alive pair up to the last one taken is done; none is left when na <= q
    cursor = jnp.where(na > q, at[q - 1] + 1, k * p)
    return nt + jnp.minimum(na, q), _alive(m2, e2, lin, cursor, best[0]), best


def _lane_test(batch: _Batch, na, rows, prim):
    """t (Q, G) of a step's pairs (packet ``rows``, primitive ``prim``), on q/2 lanes where the
    step's ``na`` pairs fit, else q (a switch: one branch runs; a block's last step is often
    part-full, and the step's cost is its lanes). Each branch is its own program, so t is
    materialised once. ``batch.one_lane``: q lanes alone (one copy of the test). A third size,
    q/4, was dropped: its copy of the pair test lengthened the compile on Table 1's scenes and
    saved only a few percent of the cacti's cast time
    (docs/choices.md#bins-lane-counts)."""
    q = batch.q
    sizes = [m for m in (q // 2,) if m >= 16 and not batch.one_lane] + [q]
    if len(sizes) > 1:
        return jax.lax.switch(sum((na > m).astype(jnp.int32) for m in sizes[:-1]), [_lanes(batch, m, rows, prim) for m in sizes])
    return fenced(na >= 0, _lanes(batch, q, rows, prim))  # (a switch of one branch is inlined)


def _lanes(batch: _Batch, m: int, rows, prim):
    """The pair test on the first ``m`` of a step's pairs, padded with misses to ``q`` rows."""
    def test():
        r = rows[:m]
        t = batch.pair_fn(prim[:m], batch.po[r], batch.pd[r], batch.pa[r], batch.pb[r])
        return t if m == batch.q else jnp.concatenate([t, jnp.full((batch.q - m, batch.g), jnp.inf, t.dtype)])

    return test
