"""Which traversal casts a batch against a frusta object's segments, chosen by its static
options: the plain segments through the BVH (bins, the Pallas kernel, packets or per-ray walks),
by block spheres or by brute force; the relief segments by a compacted march. Also the work
counts of the chosen BVH traversal. ``_scene.cast`` wraps these searches."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ..accel import hold
from ..interface import Object
from ..rays import Rays
from ..wavefront import leaves_after, leaves_of
from ._accel import nearest_bins, nearest_groups, nearest_packets
from ._config import FrustaConfig
from ._intersect import _segment_t, nearest_batch, nearest_batch_compact, nearest_leaves_compact, nearest_one
from ._kernel import nearest_kernel
from ._pack import FrustaScene, Group, Static
from ._relief import enters_shell
from ._relief_method import make_relief_root, make_relief_t


def traversal_of(cfg: FrustaConfig, plain_segments: int) -> str:
    """``object.traversal`` resolved: ``auto`` is the Pallas kernel on an accelerator; on the
    CPU, packet candidate lists (``bins``) from :data:`AUTO_BINS_SEGMENTS` plain segments and
    per-ray walks below. On a GPU at 1024x768 the kernel beat XLA's per-ray walk over the whole
    frame several times on the palm, oasis and cacti, and the packets by far more (a ``lax.map``
    of scalar loops is bound by launches there; docs/choices.md#pallas-kernel). On the CPU bins
    beat the BVH packets on every scene of ``experiments/bench_scale_bins.yaml`` (docs/performance.md); a
    render of ``experiments/scene_cacti.yaml`` (``--set objects.1.shape.traversal=...``), whose
    shadow and reflection rays reach the cacti too, was faster with bins as well (one warm
    render each way, not a committed bench). Below the threshold the walks' program compiles
    faster and their renders are at most a few times slower (see the constant)."""
    if cfg.traversal != "auto":
        return cfg.traversal
    if jax.default_backend() != "cpu":
        return "kernel"
    return "bins" if plain_segments >= AUTO_BINS_SEGMENTS else "walks"


# from this many plain segments ``auto`` picks bins on the CPU, below it the per-ray walks, whose
# program compiles faster (the bins hold the walks, for chunks they hand back, and their own
# pair loop); the line lies between the objects on which the bins' compile is and is not earned
# back in a few frames (docs/choices.md#auto-bins-segments)
AUTO_BINS_SEGMENTS = 64

# below this many plain segments the block scan beat the BVH (docs/choices.md#auto-bins-segments)
AUTO_BVH_SEGMENTS = 16


def relief_cull_of(rel, relief_segments: int) -> str:
    """``object.relief.cull`` resolved: ``auto`` is ``tree`` from :data:`AUTO_RELIEF_TREE`
    relief segments, ``blocks`` below (and without relief). The per-ray walks beat the packets'
    lists here (faster and compiled sooner on the palm and the L-system tree): a relief ray's
    pairs cost far more than finding its leaves."""
    if rel is None:
        return "blocks"
    if rel.cull != "auto":
        return rel.cull
    return "tree" if relief_segments >= AUTO_RELIEF_TREE else "blocks"


# from this many relief segments ``auto`` culls their pairs by the BVH leaves each ray meets
# (between 18 segments, where both took the same time, and 54, where the tree was faster:
# docs/choices.md#relief-cull)
AUTO_RELIEF_TREE = 32

# BVH leaves listed per ray and round for the relief's pairs (a ray meeting more takes another round)
RELIEF_LEAVES = 32


# the exact relief traversal's persistent lanes and iterations between refills: the cast's time
# changed little from 512 to 2,048 lanes or 4 to 16 steps (docs/choices.md#exact-lanes)
EXACT_LANES = 1024
EXACT_STEPS = 8


def _plain_search(static: Static):
    """(t, s, code, idx) of a batch against the plain segments of a group, by the traversal
    ``static`` names (see :func:`cast`)."""

    def search(g: Group, rays: Rays):
        o, d, a, b = rays
        if static.accel == "bvh" and static.traversal == "bins":
            out = nearest_bins(g.frusta, g.bvh, *static.bins, o, d, a, b, leaf=static.leaf, walk_group=static.group)
        elif static.accel == "bvh" and static.traversal == "kernel":
            out = nearest_kernel(g.frusta, g.bvh, static.leaf, o, d, a, b, static.kernel_block, static.kernel_warps)
        elif static.accel == "bvh" and static.traversal == "packets" and static.packet > 0:
            out = nearest_packets(g.frusta, g.bvh, static.leaf, static.packet, o, d, a, b)
        elif static.accel == "bvh":
            out = nearest_groups(g.frusta, g.bvh, static.leaf, static.group, o, d, a, b)
        elif static.accel == "none":  # brute force: every segment for every ray (the reference)
            out = jax.vmap(lambda o_, d_, a_, b_: nearest_one(g.frusta, _segment_t, o_, d_, a_, b_, static.quality.block))(o, d, a, b)
        else:
            out = nearest_batch(g.frusta, g.block_c, g.block_r, _segment_t, o, d, a, b, static.quality.block)
        return tuple(out[:4])

    return search


def _relief_search(static: Static):
    """(t, s, code, idx, t_undecided) of a batch against the relief segments (marched only for
    the (ray, segment) pairs whose ray enters a shell; t_undecided the least t where a march
    could not exclude a crossing, ``_relief``), and its closed-form ``winner``: the winning
    segment's crossing at the s the search found, differentiated by the implicit-function
    theorem without marching again (``_relief_method.make_relief_root``)."""

    def search(sc: FrustaScene, rays: Rays):
        seg_fn = make_relief_t(sc.maps, static.relief)
        g, lanes = sc.relief, None
        cap = min(rays.origins.shape[0], 4096)
        if static.relief.method == "exact":  # its pairs take uneven numbers of iterations: persistent lanes
            from . import _relief_exact

            cap = min(cap, EXACT_LANES)
            lanes = _relief_exact.lane_fns(sc.maps, static.relief, EXACT_STEPS)
        if static.relief_cull == "blocks":
            return tuple(nearest_batch_compact(g.frusta, g.block_c, g.block_r, enters_shell, seg_fn, *rays, static.relief_block, cap,
                                               undecided=True, seg_c=g.seg_c, seg_r=g.seg_r, lanes=lanes))
        # the pairs of each ray's own leaves, RELIEF_LEAVES at a time: a ray that meets more is
        # walked again past the leaves it took (after a packet's list, from its first leaf)
        n = rays.origins.shape[0]
        walk_lanes = min(n, 1024)
        packets = static.relief_cull == "packets"

        def first():
            return leaves_of(g.bvh, rays, RELIEF_LEAVES, walk_lanes, packets)

        def after(need, r):
            return leaves_after(g.bvh, rays, need, RELIEF_LEAVES, (r - packets) * RELIEF_LEAVES, walk_lanes)

        return tuple(nearest_leaves_compact(g.frusta, g.bvh.order, static.leaf, first, after, enters_shell, seg_fn, *rays, cap,
                                            g.seg_c, g.seg_r, undecided=True, lanes=lanes))

    def winner(sc: FrustaScene, rays: Rays, out):
        t, idx = out[0], out[3]
        hit = jnp.isfinite(t)
        seg = jax.tree_util.tree_map(lambda x: x[jnp.maximum(idx, 0)], sc.relief.frusta)
        seg, o, d = hold(hit, (seg, rays.origins, rays.directions))  # (the maps are shared by every ray)
        s_root = jnp.where(hit, out[1], 0.0)
        tt, ss = jax.vmap(make_relief_root(sc.maps, static.relief))(seg, o, d, rays.t_min, rays.t_max, s_root)
        return tt, ss, None, None, None

    return search, winner


def _stats_batch(obj: Object, rays: Rays):
    """Work counts per ray of the traversal ``obj.static`` selects (one module-level function:
    the static options ride in the ``Object`` pytree, so the executor compiles once per static)."""
    static = obj.static
    g = obj.params.plain
    if static.traversal == "kernel":  # the same walk, counted by the kernel (tests/test_accel.py)
        return nearest_kernel(g.frusta, g.bvh, static.leaf, *rays, block=static.kernel_block, num_warps=static.kernel_warps)[4:]
    out = nearest_groups(g.frusta, g.bvh, static.leaf, static.group, *rays)[4:]
    if static.packet > 0 and static.traversal == "packets":
        out = out + nearest_packets(g.frusta, g.bvh, static.leaf, static.packet, *rays)[4:]
    if static.traversal == "bins":  # segment tests per ray: the batch's pairs times rays per packet
        n = rays.size
        n_list, pairs = nearest_bins(g.frusta, g.bvh, *static.bins, *rays, leaf=static.leaf, walk_group=static.group)[4]
        g_rays = min(static.bins[0], n)
        walked = pairs < 0  # a batch cast by walks (its list too long for packets): its leaves' segments
        tests = jnp.where(walked, out[1] * static.leaf, pairs * g_rays / n)
        out = out + (tests, jnp.full((n,), n_list), jnp.full((n,), walked))
    return out
