"""Culling a batch of rays through the shared BVH by (ray, leaf) pairs (``method: exact``).

``_cull.cull`` gathers and tests every slot of a ray's leaf list (``block_capacity`` leaves of
``block`` primitives: 256 sphere tests a ray by default) although a camera ray meets fewer than
two leaves on average (the blob slabs: 1.8 at 5,000 blobs, ``docs/performance.md``). Here the
leaves are found as there (``accel.collect``, or with ``cull: packets`` ``accel.collect_packets``:
``wavefront.leaves_of``), and the pairs of a ray and a leaf it met are gathered into
dense sub-batches (``wavefront.compact_map``), each pair testing its leaf's primitives'
spheres of influence (Rouiller 2011, Sec. 4.2) and returning one word of hit bits; a ray then
keeps the first ``capacity`` primitives met (``accel.first_set`` over its words): in the walk's
order of its leaves (the walk's, or the tree's for packets), then the tree's (Morton) order
within a leaf. The candidates are those of ``cull(..., nearest=False)``, the ray's window (its
spheres' union) the same."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .. import accel
from ..rays import Rays
from ..wavefront import compact_map, leaves_of
from ._field import Prims
from ._cull import Candidates, _sphere_interval, _words, influence_spheres, influence_tree


def usable(block: int) -> bool:
    """Static: a leaf's hits fit one 32-bit word."""
    return 0 < block <= 32


def cull_batch(prims: Prims, rays: Rays, capacity: int, block: int, block_capacity: int, lanes: int, packets: bool = False) -> Candidates:
    """The :class:`_cull.Candidates` (leading axis N) of every ray of ``rays``, the leaves met
    found by ``wavefront.leaves_of`` (``packets``: through the packets' lists)."""
    bvh = influence_tree(prims, block)
    leaves, over = leaves_of(bvh, rays, block_capacity, lanes, packets)
    n, s = leaves.shape
    c, r = influence_spheres(prims)
    order = jnp.maximum(bvh.order, 0)  # -1 for padding and invalid primitives
    live = bvh.order >= 0
    table = jnp.stack([c[order, 0], c[order, 1], c[order, 2], jnp.where(live, r[order], -1.0)]).reshape(4, -1, block)
    ray_of = jnp.repeat(jnp.arange(n, dtype=jnp.int32), s)
    leaf = leaves.reshape(-1)

    def pairs(sub):
        i, lf = sub

        def one(i, lf):
            rows = table[:, jnp.maximum(lf, 0)]  # (4, block): this leaf's spheres
            t0, t1, hit = _sphere_interval(rows[:3].T, rows[3], rays.origins[i], rays.directions[i], rays.t_min[i], rays.t_max[i])
            hit = hit & (rows[3] >= 0)
            word = _words(hit)[0]  # block <= 32: one word
            inf = jnp.asarray(jnp.inf, t0.dtype)
            return word, jnp.min(jnp.where(hit, t0, inf)), jnp.max(jnp.where(hit, t1, -inf))

        return jax.vmap(one)(i, lf)

    inf = jnp.full((n * s,), jnp.inf, rays.t_min.dtype)
    base = (jnp.zeros((n * s,), jnp.uint32), inf, -inf)
    words, lo, hi = compact_map(pairs, leaf >= 0, (ray_of, leaf), base, lanes)
    words, lo, hi = words.reshape(n, s), lo.reshape(n, s), hi.reshape(n, s)
    count = jnp.sum(jax.lax.population_count(words).astype(jnp.int32), axis=1)
    pos = jax.vmap(lambda w: accel.first_set(w, capacity)[0])(words)  # (N, C): slot * 32 + bit
    ok = jnp.arange(capacity)[None, :] < count[:, None]
    slot, bit = jnp.minimum(pos // 32, s - 1), pos % 32
    lf = jnp.take_along_axis(leaves, slot, axis=1)
    p = prims.a.shape[0]
    gid = jnp.where(ok, bvh.order[jnp.maximum(lf, 0) * block + bit], p)
    sub = jax.tree_util.tree_map(lambda x: jnp.concatenate([x, jnp.zeros((1,) + x.shape[1:], x.dtype)])[gid], prims)
    t_lo, t_hi = jnp.min(lo, axis=1), jnp.max(hi, axis=1)
    return Candidates(sub, gid, t_lo, t_hi, count > 0, (count > capacity) | over)
