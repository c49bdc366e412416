"""Culling for the implicit tracers (Rouiller 2011, Sec. 4.2: discard the primitives whose
sphere of influence a ray misses): each ray's candidate list of static capacity, through the
shared BVH's leaves or Morton blocks first when the model is large (``_trace``'s docstring says
how and why). ``_pairs`` culls a whole batch by (ray, leaf) pairs to the same lists."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import accel
from ..numerics import dot3, line_dist2, safe_div, safe_sqrt
from ._field import Prims


def influence_spheres(prims: Prims):
    """Centre (P,3) and radius (P,) of a sphere containing each primitive's support."""
    c = 0.5 * (prims.a + prims.b)
    half = 0.5 * safe_sqrt(dot3(prims.b - prims.a, prims.b - prims.a))
    return c, half + jnp.maximum(prims.ra, prims.rb)


class Candidates(NamedTuple):
    """The culled primitives of one ray: sub (C,) with their ids (P for an empty slot)."""

    sub: Prims
    ids: jnp.ndarray
    t_lo: jnp.ndarray
    t_hi: jnp.ndarray
    any: jnp.ndarray
    overflow: jnp.ndarray


def _sphere_interval(c, r, o, d, t_min, t_max):
    """(t0, t1, crossed) of the ray o + t d against spheres (c (N,3), r (N,)), clipped to the
    ray's (t_min, t_max]."""
    dd = dot3(d, d)
    oc = c - o
    tc = safe_div(dot3(oc, d), dd, 0.0)
    dist2 = line_dist2(oc, d, tc)
    half = safe_sqrt(safe_div(r * r - dist2, dd, 0.0))  # safe: a miss or d = 0 gives no NaN derivative
    t0 = jnp.maximum(tc - half, t_min)
    t1 = jnp.minimum(tc + half, t_max)
    return t0, t1, (dist2 < r * r) & (t0 < t1)


def block_spheres(prims: Prims, block: int):
    """Bounding sphere (centre (B,3), radius (B,), any valid (B,)) of each run of ``block``
    consecutive primitives' influence spheres. Computed from the (traced) primitives, so an
    animated or fitted model is bounded afresh; under vmap over rays it is not batched."""
    c, r = influence_spheres(prims)
    nb = c.shape[0] // block
    c, r, v = c.reshape(nb, block, 3), r.reshape(nb, block), prims.valid.reshape(nb, block)
    inf = jnp.asarray(jnp.inf, c.dtype)
    lo = jnp.min(jnp.where(v[..., None], c - r[..., None], inf), axis=1)
    hi = jnp.max(jnp.where(v[..., None], c + r[..., None], -inf), axis=1)
    anyv = jnp.any(v, axis=1)
    cb = jnp.where(anyv[:, None], 0.5 * (lo + hi), 0.0)
    e = c - cb[:, None, :]
    rb = jnp.max(jnp.where(v, safe_sqrt(dot3(e, e)) + r, 0.0), axis=1)
    # rounding: grow by a few ulps of the coordinates so no member pokes out in float32
    scale = jnp.max(jnp.abs(cb), axis=1) + rb
    return cb, rb + 8 * jnp.finfo(c.dtype).eps * scale, anyv


def _nearest(hit, t0, k: int):
    """Indices of the k entries with the smallest t0 among ``hit`` (top_k: faster than
    nonzero's scatter on CPU here), and whether each chosen slot is a real hit."""
    score = jnp.where(hit, -t0, -jnp.asarray(jnp.inf, t0.dtype))
    _, idx = jax.lax.top_k(score, k)
    return idx, jnp.take(hit, idx)


def blocks_used(p: int, block: int, block_capacity: int) -> bool:
    """Static: whether culling goes through the block level (more blocks than a ray keeps)."""
    return bool(block) and p % block == 0 and p // block > block_capacity


def influence_tree(prims: Prims, block: int) -> accel.BVH:
    """The shared linear BVH (``jskel.accel.build``: Morton codes, complete tree, built in JAX
    from the traced primitives) over the influence spheres' boxes, ``block`` primitives per
    leaf. The boxes grow by a few ulps of the coordinates, as ``block_spheres`` do, so that no
    sphere the exact test finds crossed pokes out of its box in float32."""
    c, r = influence_spheres(prims)
    scale = jnp.max(jnp.abs(c), axis=1) + r
    r = r + 8 * jnp.finfo(c.dtype).eps * scale
    return accel.build(c - r[:, None], c + r[:, None], prims.valid, block)


def cull(prims: Prims, o, d, t_min, t_max, capacity: int, block: int = 0, block_capacity: int = 0, how: str = "tree",
         nearest: bool = True, leaves=None) -> Candidates:
    """Candidates of one ray (Sec. 4.2: discard primitives whose influence the ray misses),
    through the block level first when the model has more blocks than ``block_capacity``:
    ``how="blocks"`` tests every block sphere and keeps the ``block_capacity`` nearest met;
    ``how="tree"`` (or ``"packets"``) takes the leaves met of the shared BVH
    (:func:`influence_tree`): ``leaves = (leaves (block_capacity,), overflow)`` found for the
    whole batch (``wavefront.leaves_of``), or, where not given, by walking it for this ray
    (``accel.collect``). Either way more blocks than kept sets ``OVERFLOW``. ``nearest``: keep
    the candidates ordered by their spheres' entries (the marches); the exact tracer needs no
    order."""
    p = prims.a.shape[0]
    ids = None
    block_overflow = jnp.asarray(False)
    if how in ("tree", "packets") and blocks_used(p, block, block_capacity):
        bvh = influence_tree(prims, block)
        if leaves is None:
            leaves, _, block_overflow = accel.collect(bvh, o, d, t_min, t_max, block_capacity)
        else:
            leaves, block_overflow = leaves
        # the spheres of the leaves' primitives only, a leaf's rows contiguous in the tree's
        # order (one slice of block x 5 values per leaf, not five gathers per primitive); the
        # candidates' whole records are gathered after, C of them
        c, r = influence_spheres(prims)
        order = jnp.maximum(bvh.order, 0)  # bvh.order is -1 for padding and invalid primitives
        rows = jnp.concatenate([c, r[:, None], jnp.ones_like(r)[:, None]], 1)
        table = jnp.where((bvh.order >= 0)[:, None], rows[order], 0.0).reshape(-1, block, 5)
        got = table[jnp.maximum(leaves, 0)].reshape(-1, 5)
        ids = order.reshape(-1, block)[jnp.maximum(leaves, 0)].reshape(-1)
        ok = jnp.repeat(leaves >= 0, block) & (got[:, 4] > 0)
        return _kept(prims, ids, got[:, :3], got[:, 3], ok, o, d, t_min, t_max, capacity, block_overflow, nearest)
    elif blocks_used(p, block, block_capacity):
        cb, rb, vb = block_spheres(prims, block)
        b0, _, bhit = _sphere_interval(cb, rb, o, d, t_min, t_max)
        bhit = bhit & vb
        bidx, bok = _nearest(bhit, b0, block_capacity)
        block_overflow = jnp.sum(bhit.astype(jnp.int32)) > block_capacity
        ids = (bidx[:, None] * block + jnp.arange(block)[None, :]).reshape(-1)
        c, r = influence_spheres(prims)
        return _kept(prims, ids, c[ids], r[ids], prims.valid[ids] & jnp.repeat(bok, block), o, d, t_min, t_max, capacity, block_overflow, nearest)
    c, r = influence_spheres(prims)
    return _kept(prims, ids, c, r, prims.valid, o, d, t_min, t_max, capacity, block_overflow, nearest)


def _words(mask):
    """``accel.pack_bits`` of one ray's mask as a sum of its set bits' values (disjoint bits: the
    same words); XLA on the CPU vectorises the sum, where a shift-or reduce was a sixth of the
    cull's time (docs/choices.md#cull-words)."""
    n = mask.shape[0]
    w = jnp.pad(mask, (0, -n % 32)).reshape(-1, 32)
    return jnp.sum(jnp.where(w, jnp.uint32(1) << jnp.arange(32, dtype=jnp.uint32), jnp.uint32(0)), axis=1, dtype=jnp.uint32)


def _kept(prims: Prims, ids, c, r, valid, o, d, t_min, t_max, capacity: int, block_overflow, nearest: bool) -> Candidates:
    """The :class:`Candidates` among the primitives ``ids`` of ``prims`` (all of them where
    ``ids`` is None), whose influence spheres are (c, r) and ``valid``: those the ray crosses,
    the ``capacity`` nearest kept (by their sphere's entry), or with ``nearest`` False the
    first ``capacity`` in the primitives' order (a ray with more overflows either way)."""
    p = prims.a.shape[0]
    t0, t1, hit = _sphere_interval(c, r, o, d, t_min, t_max)
    hit = valid & hit
    count = jnp.sum(hit.astype(jnp.int32))
    n = c.shape[0]
    if nearest:
        idx, ok = _nearest(hit, t0, min(capacity, n))  # fewer entries than the capacity cannot overflow
    else:  # the first met in the tree's (Morton) order: no sort (top_k) per ray
        idx, _ = accel.first_set(_words(hit), min(capacity, n))
        ok = jnp.arange(idx.shape[0]) < count
        idx = jnp.minimum(idx, n - 1)
    gid = jnp.where(ok, idx, p) if ids is None else jnp.where(ok, ids[idx], p)
    sub = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])[gid], prims)
    inf = jnp.asarray(jnp.inf, o.dtype)
    t_lo = jnp.min(jnp.where(hit, t0, inf))
    t_hi = jnp.max(jnp.where(hit, t1, -inf))
    return Candidates(sub, gid, t_lo, t_hi, count > 0, (count > capacity) | block_overflow)
