"""Every leaf of the shared BVH that a ray meets, found for packets of coherent rays at once
(issue 52: the frusta's packet bins offered to the implicit primitives).

:func:`jskel.accel.collect` walks the tree per ray: a vmapped ``while_loop`` that runs every
lane as long as the batch's longest walk, and on the blob slabs the largest single cost of the
exact implicit tracer's cull (8 of 20 ms on 4,096 camera rays of 5,000 blobs, a ``jax.profiler``
trace, docs/performance.md). Rouiller (2011, Sec. 4.2) culls per ray against every primitive's
sphere of influence; the field sums every primitive a ray passes through, so there is no
nearest hit to prune by and a ray's list is *every* leaf it meets.

:func:`collect_packets` finds those lists without a loop. The batch (rays in
``jskel.camera.tile_order``, consecutive rays close on screen) is cut into packets of
``packet`` rays, each bounded by the box of its origins, the box of its directions and its t
range (``_bins.packet_entry``: interval arithmetic, a superset of its rays' hits):

1. every packet is tested against every leaf box, densely (P x L box tests, elementwise work
   that XLA runs at full vector width), and its first ``listed`` leaves met are compacted
   (``first_set``, in the tree's Morton order);
2. every ray is tested against its packet's list with the slab test of :func:`collect`
   (``_lbvh.slab`` on the same floats), and its first ``capacity`` leaves met are kept.

A leaf box lies inside each of its ancestors' boxes (their bounds are the leaf bounds' min and
max, exact in floating point), and rounding is monotone, so a ray whose slab test passes a leaf
passes every ancestor's: the leaves :func:`collect` reaches are exactly those whose own test
passes, the set found here. Only the order differs (Morton order here, near child first
there), which decides which leaves a ray keeps when it meets more than ``capacity``; such a ray
is flagged either way. A packet that meets more than ``listed`` leaves (incoherent rays, or a
packet whose footprint covers much of the model) is flagged whole: its rays' lists are not
trusted, and the caller walks them per ray (``jskel.implicit._pairs``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._bins import _meets_per_packet, _pad_rows, always, fenced, first_set, pack_bits, packet_bounds
from ._lbvh import BVH, _inv_d


def collect_packets(bvh: BVH, origins, directions, t_min, t_max, capacity: int, packet: int, listed: int):
    """(leaves (N, capacity) int32 leaf indices, -1 in unused slots; count (N,) leaves met, at
    most ``listed``; over (N,): more leaves met than ``capacity``; packet_over (N,): the ray's
    packet met more than ``listed`` leaves, so the ray's list is not every leaf it meets) of
    every ray of a batch (module docstring)."""
    n = origins.shape[0]
    n_leaves = bvh.lo.shape[0] // 2
    lo, hi = bvh.lo[n_leaves:], bvh.hi[n_leaves:]
    g = min(packet, n)
    n_pad = -(-n // g) * g
    p = n_pad // g
    po, pd, pa, pb = (_pad_rows(x, n_pad).reshape((p, g) + x.shape[1:]) for x in (origins, directions, t_min, t_max))
    # the packets' bounds and the rays' 1 / d materialised once: XLA on the CPU fused their
    # reductions and divides into the box tests' loops and ran them per element (10x this
    # stage's time on 4,096 rays and 256 leaves, development profile)
    bounds, inv_d = fenced(always(pa), lambda: (packet_bounds(po, pd, pa, pb), _inv_d(pd)))
    met = _meets_per_packet(*bounds, lo, hi)[0]  # (P, L)
    k = min(listed, n_leaves)
    pos, cnt = jax.vmap(lambda m: first_set(pack_bits(m), k))(met)  # (P, K), (P,)
    pos = jnp.where(jnp.arange(k)[None, :] < cnt[:, None], jnp.minimum(pos, n_leaves - 1), n_leaves)
    lo_e = jnp.concatenate([lo, jnp.full((1, 3), jnp.inf, lo.dtype)])  # row L: empty, never met
    hi_e = jnp.concatenate([hi, jnp.full((1, 3), -jnp.inf, hi.dtype)])
    blo, bhi = lo_e[pos][:, None], hi_e[pos][:, None]  # (P, 1, K, 3)
    inv_d = inv_d[:, :, None]  # (P, G, 1, 3)
    ta = (blo - po[:, :, None]) * inv_d
    tb = (bhi - po[:, :, None]) * inv_d
    t0 = jnp.max(jnp.minimum(ta, tb), -1)  # _lbvh.slab, per ray and listed leaf: (P, G, K)
    t1 = jnp.min(jnp.maximum(ta, tb), -1)
    hit = (t0 <= t1) & (t1 >= pa[..., None]) & (t0 <= pb[..., None]) & jnp.all(blo <= bhi, -1)
    at, count = jax.vmap(jax.vmap(lambda m: first_set(pack_bits(m), capacity)))(hit)  # (P, G, C), (P, G)
    c = at.shape[-1]
    at = jnp.minimum(at, k - 1)
    leaf = jnp.take_along_axis(jnp.broadcast_to(pos[:, None], (p, g, k)), at, axis=-1)
    leaves = jnp.where(jnp.arange(c) < count[..., None], leaf, -1).reshape(n_pad, c)[:n]
    count = count.reshape(n_pad)[:n]
    packet_over = jnp.repeat(cnt > k, g)[:n]
    return leaves, count, count > capacity, packet_over
