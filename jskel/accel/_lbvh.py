"""A linear BVH built in JAX every frame, traversed stacklessly under vmap (issue 6).

Build (``build``, pure and jit-able, O(P log P)): primitive boxes -> 30-bit Morton codes of their
centres over the scene box (one scale for all axes) -> sort -> groups of ``leaf`` consecutive
primitives form the leaves of a *complete* binary tree in heap order (node 1 is the root, the
children of node i are 2i and 2i + 1, the leaves are nodes L .. 2L - 1 with L a power of two);
padding leaves hold empty boxes (lo = +inf, hi = -inf) that no ray hits. Internal boxes are the
unions of their children, one level at a time (log2 L reshapes). Karras (2012) builds a radix
tree from the same Morton order; the complete tree trades a few empty nodes for an index
arithmetic that needs no child pointers and no per-node storage but the boxes.

Traversal (``nearest``): near child first with a one-int bit trail in place of a stack (see
its docstring); there is no stack, hence nothing to overflow, and the loop ends after at most
2 x nodes steps. (``escape`` is the fixed pre-order variant: strip i's trailing 1 bits and step
to the right sibling; it visited 2.4x more leaves on the L-system tree.) Why no per-ray stack
and small ray groups: a throwaway prototype (issue 6's filing) measured a per-ray stack slower
under vmap (its scatter), and groups of a few dozen rays much faster than thousands, because a
vmapped while loop runs until its slowest ray ends; ``nearest_groups`` runs ``lax.map`` over
groups of ``group`` rays inside one compiled function.

Measured on the palm (1024x768, issue 6): groups of tens to hundreds of rays beat both 8 and
4,096 (per-iteration overhead of XLA's while loop against lanes waiting on the slowest ray); a
wavefront that quarters its width as rays finish (gathering the active rays, so the tail runs at
256 then 64 lanes) was not clearly faster and compiled several times longer, so it was not kept
(the figures: docs/choices.md#lbvh-groups). Traversal work per ray grows with log2(segments)
at fixed coverage (about one more internal node per doubling; docs/performance.md,
``experiments/bench_scale_size.yaml``).

Why this structure and not a uniform grid with 3D-DDA: skeletons are long thin primitives of
very different sizes (a palm's trunk and its leaflets), which a single grid resolution bounds
poorly; a BVH adapts to them and is rebuilt in O(P log P) per frame.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp


class BVH(NamedTuple):
    """A complete binary BVH over Morton-sorted primitives (module docstring): node boxes in
    heap order, each leaf slot's primitive, and each internal node's two child boxes together."""

    lo: jnp.ndarray  # (2L, 3) node boxes in heap order (index 0 unused)
    hi: jnp.ndarray  # (2L, 3)
    order: jnp.ndarray  # (L * leaf,) primitive index of each leaf slot (-1: padding)
    children: jnp.ndarray  # (L, 12) per internal node: lo, hi of its left child, then of its right


def _expand_bits(v):
    """10-bit integers -> every third bit of 30 (the Morton interleave)."""
    v = v.astype(jnp.uint32)
    v = (v * jnp.uint32(0x00010001)) & jnp.uint32(0xFF0000FF)
    v = (v * jnp.uint32(0x00000101)) & jnp.uint32(0x0F00F00F)
    v = (v * jnp.uint32(0x00000011)) & jnp.uint32(0xC30C30C3)
    v = (v * jnp.uint32(0x00000005)) & jnp.uint32(0x49249249)
    return v


def morton_codes(points, lo, extent):
    """30-bit Morton codes (uint32) of points (N,3) in the cube [lo, lo + extent]."""
    q = jnp.clip(jnp.floor((points - lo) / extent * 1024.0), 0, 1023)
    return (_expand_bits(q[:, 0]) << 2) | (_expand_bits(q[:, 1]) << 1) | _expand_bits(q[:, 2])


def leaves_for(p: int, leaf: int) -> int:
    """Number of leaves L (a power of two, >= 1) of the complete tree for p primitives."""
    n = max(1, -(-p // leaf))
    return 1 << (n - 1).bit_length()


def build(box_lo, box_hi, valid, leaf: int) -> BVH:
    """BVH over P primitive boxes (P,3) (``valid`` (P,) marks real ones). Static shape: the leaf
    count L follows from P and ``leaf`` alone, so every frame of an animation shares a compile."""
    p = box_lo.shape[0]
    n_leaves = leaves_for(p, leaf)
    inf = jnp.asarray(jnp.inf, box_lo.dtype)
    box_lo = jnp.where(valid[:, None], box_lo, inf)
    box_hi = jnp.where(valid[:, None], box_hi, -inf)
    cent = 0.5 * (box_lo + box_hi)
    s_lo = jnp.min(jnp.where(valid[:, None], cent, inf), axis=0)
    s_hi = jnp.max(jnp.where(valid[:, None], cent, -inf), axis=0)
    extent = jnp.maximum(jnp.max(s_hi - s_lo), jnp.asarray(1e-30, box_lo.dtype))
    code = morton_codes(jnp.where(valid[:, None], cent, s_hi), s_lo, extent)
    code = jnp.where(valid, code, jnp.uint32(0xFFFFFFFF))  # padding sorts last
    order = jnp.argsort(code, stable=True).astype(jnp.int32)
    slots = n_leaves * leaf
    order = jnp.concatenate([order, jnp.full((slots - p,), -1, jnp.int32)])
    order = jnp.where(jnp.concatenate([valid, jnp.zeros((slots - p,), bool)])[jnp.maximum(order, 0)] & (order >= 0), order, -1)
    lo_s = jnp.where((order >= 0)[:, None], box_lo[jnp.maximum(order, 0)], inf).reshape(n_leaves, leaf, 3).min(1)
    hi_s = jnp.where((order >= 0)[:, None], box_hi[jnp.maximum(order, 0)], -inf).reshape(n_leaves, leaf, 3).max(1)
    los, his = [lo_s], [hi_s]
    while los[-1].shape[0] > 1:
        los.append(los[-1].reshape(-1, 2, 3).min(1))
        his.append(his[-1].reshape(-1, 2, 3).max(1))
    pad = jnp.full((1, 3), inf, box_lo.dtype)
    lo = jnp.concatenate([pad] + los[::-1])  # heap order: root at 1
    hi = jnp.concatenate([-pad] + his[::-1])
    kids = jnp.arange(n_leaves) * 2
    children = jnp.concatenate([lo[kids], hi[kids], lo[kids + 1], hi[kids + 1]], axis=1)  # row 0 unused
    return BVH(lo, hi, order, children)


def escape(i):
    """Next node of the pre-order after i's subtree (0: traversal done): strip i's trailing 1
    bits (climb while i is a right child), then step to the right sibling."""
    u = i.astype(jnp.uint32)
    ones = jax.lax.population_count((u ^ (u + 1)) >> 1)
    j = (u >> ones).astype(jnp.int32)
    return jnp.where(j == 0, 0, j + 1)


def slab(lo, hi, o, inv_d):
    """(t0, t1) of the ray against the box (t0 > t1: miss); an empty box (lo = +inf, hi = -inf,
    padding) gives t0 = -inf, t1 = inf and is tested apart by the callers."""
    ta = (lo - o) * inv_d
    tb = (hi - o) * inv_d
    return jnp.max(jnp.minimum(ta, tb)), jnp.min(jnp.maximum(ta, tb))


def ray_box(lo, hi, o, inv_d, t_min, t_max):
    """Whether the ray's (t_min, t_max] meets the box (slab test; an empty box never)."""
    t0, t1 = slab(lo, hi, o, inv_d)
    return (t0 <= t1) & (t1 >= t_min) & (t0 <= t_max) & jnp.all(lo <= hi)


class Best(NamedTuple):
    """The nearest candidate so far of a traversal (t, local parameter, surface code, primitive index)."""

    t: jnp.ndarray
    s: jnp.ndarray
    code: jnp.ndarray
    idx: jnp.ndarray


def _ctz(x):
    """Trailing zero bits of a non-zero uint32."""
    return jax.lax.population_count((x & (~x + jnp.uint32(1))) - jnp.uint32(1))


def pop(node, trail):
    """Finish the current subtree of a bit-trail walk: climb past the trail's trailing zeros to
    the nearest ancestor with a pending sibling and move to it; (next node, trail), node 0 when
    the traversal is done."""
    one = jnp.uint32(1)
    z = _ctz(jnp.where(trail == 0, one, trail))
    node = node >> z.astype(jnp.int32)
    trail = trail >> z
    done = trail == 0
    return jnp.where(done, 0, node ^ 1), jnp.where(done, trail, trail ^ one)


def _inv_d(d):
    """1 / d with signed infinities for zero components (the slab test stays exact)."""
    return jnp.where(d == 0, jnp.where(jnp.signbit(d), -jnp.inf, jnp.inf), 1.0 / jnp.where(d == 0, 1.0, d))


def descend(node, trail, row, meets: Callable, pop_fn: Callable = pop):
    """One internal-node step of a bit-trail walk: ``row`` holds the node's two child boxes
    (lo, hi of the left, then of the right) and ``meets(lo, hi) -> (hit, entry t)`` tests one;
    the walk goes to the nearer child it meets, pushing a 1 on the trail when it meets both,
    or finishes the subtree (``pop_fn``) when it meets neither. Returns (next node, trail)."""
    hl, tl = meets(row[0:3], row[3:6])
    hr, tr = meets(row[6:9], row[9:12])
    near = jnp.where(hr & (~hl | (tr < tl)), 2 * node + 1, 2 * node)
    pn, pt = pop_fn(node, trail)
    anyhit = hl | hr
    return jnp.where(anyhit, near, pn), jnp.where(anyhit, (trail << jnp.uint32(1)) | (hl & hr).astype(jnp.uint32), pt)


def nearest(bvh: BVH, leaf_fn: Callable, leaf: int, o, d, t_min, t_max, init: Best, any_hit: bool = False):
    """Nearest hit of one ray. ``leaf_fn(slot_ids (leaf,), o, d, t_min, t_max) -> Best`` of a
    leaf's primitives (slot ids index ``bvh.order``); returns (Best, nodes visited, leaves
    tested).

    At an internal node whose box the ray meets, one gather brings both children's boxes; the
    ray goes to the nearer child it meets (by slab entry), and when it meets both it pushes one
    bit on a *bit trail* (1: the far sibling is pending) instead of a node on a stack. Finishing
    a subtree pops the trail's trailing zeros (climbs to the nearest ancestor with a pending
    sibling) and moves to that sibling, whose box is already known to be met. The trail is one
    int32 (depth <= 31): nothing overflows and nothing is scattered under vmap. Near first lets
    the box tests prune against the best hit so far. While-while (Aila and Laine 2009): the inner
    loop walks internal nodes until the ray reaches a leaf, the outer loop tests that leaf, so
    under vmap the costly leaf test runs once per outer step for all lanes.

    ``any_hit`` (static): stop at the first leaf that holds a hit (shadow rays: whether the ray
    meets anything in ``(t_min, t_max]``, not where it meets it first); the Best is that hit."""
    n_leaves = bvh.lo.shape[0] // 2
    inv_d = _inv_d(d)

    def meets(lo, hi, t_hi):
        t0, t1 = slab(lo, hi, o, inv_d)
        return (t0 <= t1) & (t1 >= t_min) & (t0 <= t_hi) & jnp.all(lo <= hi), t0

    def to_leaf(node, trail, t_hi, visits):
        def body(st):
            node, trail, v = st
            nxt, ntrail = descend(node, trail, bvh.children[node], lambda lo, hi: meets(lo, hi, t_hi))
            return nxt, ntrail, v + 1

        def cond(st):
            return (st[0] > 0) & (st[0] < n_leaves)

        return jax.lax.while_loop(cond, body, (node, trail, visits))

    def outer(st):
        node, trail, best, visits, leaves = st
        node, trail, visits = to_leaf(node, trail, best.t, visits)
        found = node >= n_leaves
        slots = (jnp.maximum(node, n_leaves) - n_leaves) * leaf + jnp.arange(leaf, dtype=jnp.int32)
        cand = leaf_fn(slots, o, d, t_min, best.t)
        better = found & (cand.t < best.t)
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), cand, best)
        pn, pt = pop(node, trail)
        return jnp.where(found, pn, 0), jnp.where(found, pt, trail), best, visits, leaves + found.astype(jnp.int32)

    root = ray_box(bvh.lo[1], bvh.hi[1], o, inv_d, t_min, t_max)
    if n_leaves == 1:
        start = jnp.where(root, 1, 0)  # the root is the only leaf
    else:
        start = jnp.where(root, 1, 0)
    t0 = jnp.minimum(init.t, t_max)
    st = (start.astype(jnp.int32), jnp.uint32(0), init._replace(t=t0), jnp.int32(0), jnp.int32(0))
    go = (lambda st: (st[0] > 0) & ~(st[2].t < t0)) if any_hit else (lambda st: st[0] > 0)
    node, trail, best, visits, leaves = jax.lax.while_loop(go, outer, st)
    return best, visits, leaves


def collect(bvh: BVH, o, d, t_min, t_max, capacity: int, skip=0):
    """Every leaf whose box the ray's (t_min, t_max] meets, for primitives that all contribute
    along the ray (the influence spheres of skeletal implicit surfaces, Rouiller 2011 Sec. 4.2,
    where the field sums every primitive it is inside, so there is no nearest hit to prune by).

    The walk of :func:`nearest` (near child first, bit trail, no stack) without the best-hit
    cut-off: each leaf it reaches is written to the next of ``capacity`` slots (a select over
    the slots, not a scatter under vmap). The walk stops as soon as a leaf finds the slots full,
    so a ray costs the internal nodes above its leaves plus at most capacity + 1 leaves.
    Returns (leaves (capacity,) int32 leaf indices, -1 in unused slots, in walk order; count
    written; overflow: more leaves met than slots, the list is then not every leaf met).
    ``skip`` (may be traced): the walk's first ``skip`` leaves are passed over, not written, so
    a ray that overflowed is continued by walking it again with ``skip`` = the slots already
    taken (the walk's order is the same every time)."""
    n_leaves = bvh.lo.shape[0] // 2
    inv_d = _inv_d(d)
    lanes = jnp.arange(capacity, dtype=jnp.int32)

    def meets(lo, hi):
        t0, t1 = slab(lo, hi, o, inv_d)
        return (t0 <= t1) & (t1 >= t_min) & (t0 <= t_max) & jnp.all(lo <= hi), t0

    def body(st):
        node, trail, k, slots, over = st
        at_leaf = node >= n_leaves
        nxt, ntrail = descend(node, trail, bvh.children[jnp.where(at_leaf, 0, node)], meets)
        pn, pt = pop(node, trail)
        full = k - skip >= capacity
        slots = jnp.where(at_leaf & (lanes == k - skip), node - n_leaves, slots)
        k = k + (at_leaf & ~full).astype(jnp.int32)
        over = over | (at_leaf & full)
        node = jnp.where(at_leaf, jnp.where(full, 0, pn), nxt)
        return node, jnp.where(at_leaf, pt, ntrail), k, slots, over

    root = ray_box(bvh.lo[1], bvh.hi[1], o, inv_d, t_min, t_max)
    st = (jnp.where(root, 1, 0).astype(jnp.int32), jnp.uint32(0), jnp.int32(0), jnp.full((capacity,), -1, jnp.int32), jnp.asarray(False))
    _, _, k, slots, over = jax.lax.while_loop(lambda st: st[0] > 0, body, st)
    return slots, jnp.maximum(k - skip, 0), over


def nearest_packet(bvh: BVH, leaf_fn: Callable, leaf: int, o, d, t_min, t_max, init: Best):
    """Nearest hits of a *packet* of P rays (o, d: (P,3); t_min, t_max: (P,)) sharing one
    traversal (Wald et al. 2001's packets, with the bit trail of :func:`nearest`): the node and
    trail are scalars, every box test is done for all P rays at once, and the packet enters a
    child when any of its rays meets it, nearer child first by the smallest entry among them.
    ``leaf_fn(slots (leaf,), o, d, t_min, t_hi) -> Best`` of (P,) arrays tests every ray of the
    packet against a leaf. Each ray's t is the minimum over a superset of the leaves its own
    walk would test, so t equals :func:`nearest`'s exactly (ids too, but for exact ties).

    Why: the loop is one scalar ``while_loop`` whose body branches with a real ``lax.cond``
    (leaf or internal node) instead of a vmapped loop that runs every lane until the slowest ray
    ends; on coherent rays (primary rays in 16 x 16 screen squares, ``camera.tile_order``) the
    union of the rays' walks is short: at 1024x768 packets of 256 beat per-ray groups of 512 on
    the palm, the dancing cacti and the oasis, with identical hits (docs/choices.md#lbvh-packets).
    Incoherent rays (random directions) make the union long: use
    :func:`nearest` for those. Returns (Best of (P,) arrays, iterations of the packet's loop)."""
    n_leaves = bvh.lo.shape[0] // 2
    inv_d = _inv_d(d)
    inf = jnp.asarray(jnp.inf, o.dtype)
    one = jnp.uint32(1)

    def meets(lo, hi, t_hi):
        ta = (lo - o) * inv_d
        tb = (hi - o) * inv_d
        t0 = jnp.max(jnp.minimum(ta, tb), -1)
        t1 = jnp.min(jnp.maximum(ta, tb), -1)
        return (t0 <= t1) & (t1 >= t_min) & (t0 <= t_hi) & jnp.all(lo <= hi), t0

    def internal(st):
        node, trail, best, it = st
        row = bvh.children[node]
        hl, tl = meets(row[0:3], row[3:6], best.t)
        hr, tr = meets(row[6:9], row[9:12], best.t)
        al, ar = jnp.any(hl), jnp.any(hr)
        left_first = jnp.min(jnp.where(hl, tl, inf)) <= jnp.min(jnp.where(hr, tr, inf))
        near = jnp.where(ar & (~al | ~left_first), 2 * node + 1, 2 * node)
        pn, pt = pop(node, trail)
        met = al | ar
        return jnp.where(met, near, pn), jnp.where(met, (trail << one) | (al & ar).astype(jnp.uint32), pt), best, it + 1

    def at_leaf(st):
        node, trail, best, it = st
        slots = (node - n_leaves) * leaf + jnp.arange(leaf, dtype=jnp.int32)
        cand = leaf_fn(slots, o, d, t_min, best.t)
        better = cand.t < best.t
        best = jax.tree_util.tree_map(lambda a, b: jnp.where(better, a, b), cand, best)
        pn, pt = pop(node, trail)
        return pn, pt, best, it + 1

    def body(st):
        return jax.lax.cond(st[0] >= n_leaves, at_leaf, internal, st)

    root, _ = meets(bvh.lo[1], bvh.hi[1], t_max)
    p = o.shape[0]
    best = jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (p,)), init)
    best = best._replace(t=jnp.minimum(best.t, t_max))
    st = (jnp.where(jnp.any(root), 1, 0).astype(jnp.int32), jnp.uint32(0), best, jnp.int32(0))
    _, _, best, it = jax.lax.while_loop(lambda st: st[0] > 0, body, st)
    return best, it
