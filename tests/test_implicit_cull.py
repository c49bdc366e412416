"""Two-level culling of implicit primitives (Morton-sorted blocks, then primitives): exact
candidate sets against NumPy, overflow never silent, identical images, and a per-ray cost that
grows far slower than the model (XLA's own operation count, not a timing)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import reference as ref
from jskel import implicit
from jskel.implicit._cull import cull, influence_tree
from jskel.rays import make_rays
from jskel.executor import map_chunks

N_RAYS = 4096


def blob_model(n, block_size=16, **kw):
    cfg = implicit.ImplicitConfig.model_validate({"type": "implicit", "procedural": "blob_grid", "options": {"n": n},
                                                  "capacity": 64, "block_size": block_size, **kw})
    return implicit.build(cfg)


_CULL = {}


def cull_fn(q):
    key = (q.capacity, q.block, q.block_capacity, q.cull)
    if key not in _CULL:
        def f(prims, o, d):
            c = cull(prims, o, d, 0.0, jnp.inf, *key)
            return c.ids, c.overflow

        _CULL[key] = jax.jit(jax.vmap(f, in_axes=(None, 0, 0)))
    return _CULL[key]


def numpy_crossings(prims, O, D, rim=False):
    """(R,P) bool: the ray crosses the primitive's influence sphere at some t > 0 (float64);
    with ``rim``, also whether it passes within 1e-5 of the radius of the sphere's rim (where
    float32 may decide either way). Written per coordinate ((R, P) arrays, no (R, P, 3) ones)."""
    a, b = np.asarray(prims.a, np.float64), np.asarray(prims.b, np.float64)
    c = 0.5 * (a + b)
    r = 0.5 * np.linalg.norm(b - a, axis=1) + np.maximum(np.asarray(prims.ra, np.float64), np.asarray(prims.rb, np.float64))
    oc = [c[None, :, k] - O[:, k, None] for k in range(3)]
    dd = np.sum(D * D, 1)[:, None]
    tc = (oc[0] * D[:, 0, None] + oc[1] * D[:, 1, None] + oc[2] * D[:, 2, None]) / dd
    dist2 = oc[0] * oc[0] + oc[1] * oc[1] + oc[2] * oc[2] - tc * tc * dd
    half = np.sqrt(np.maximum(r[None] ** 2 - dist2, 0) / dd)
    crosses = np.asarray(prims.valid)[None] & (dist2 < r[None] ** 2) & (tc + half > 0)
    if not rim:
        return crosses
    near = np.abs(np.sqrt(np.maximum(dist2, 0)) - r[None]) < 1e-5 * r[None]
    return crosses, near | (np.abs(tc + half) < 1e-5 * r[None])


@pytest.fixture(scope="module")
def slab():
    built = blob_model(3000)
    rng = np.random.default_rng(3)
    lo, hi = np.asarray(built.bounds[0]) - built.anchor, np.asarray(built.bounds[1]) - built.anchor
    O, D = ref.random_rays(rng, lo, hi, N_RAYS, spread=0.3)
    return built, O, D


def quality(built, how, **kw):
    """The model's culling options with blocks found by ``how`` (tree: 16 kept, blocks: 32)."""
    return built.static.quality._replace(cull=how, block_capacity=16 if how == "tree" else 32, **kw)


def leaves_crossed(built, q, cross):
    """(R,) number of distinct blocks (tree leaves or Morton runs) holding a primitive whose
    influence sphere the ray crosses (``cross`` from NumPy)."""
    if q.cull == "tree":
        order = np.asarray(influence_tree(built.params.prims, q.block).order)
        group = np.full(cross.shape[1], -1)
        group[order[order >= 0]] = np.nonzero(order >= 0)[0] // q.block
    else:
        group = np.arange(cross.shape[1]) // q.block
    member = np.zeros((cross.shape[1], group.max() + 1), np.float32)  # primitive -> its block
    member[np.nonzero(group >= 0)[0], group[group >= 0]] = 1.0
    return np.sum(cross.astype(np.float32) @ member > 0, axis=1)  # (counts below 2^24: exact)


def as_mask(ids, p):
    """(R, p) bool: the primitives each ray's candidate list ``ids`` (R, K) holds (entries of
    ``p`` or more are empty slots)."""
    rows = np.repeat(np.arange(ids.shape[0]), ids.shape[1])
    keep = ids.ravel() < p
    mask = np.zeros((ids.shape[0], p), bool)
    mask[rows[keep], ids.ravel()[keep]] = True
    return mask


@pytest.mark.parametrize("how", ["tree", "blocks"])
def test_block_cull_finds_exactly_the_crossed_spheres(slab, how):
    built, O, D = slab
    q = quality(built, how)
    assert q.block == 16 and built.params.prims.a.shape[0] // q.block > q.block_capacity  # the block level is in use
    ids, over = cull_fn(q)(built.params.prims, np.float32(O), np.float32(D))
    ids, over = np.asarray(ids), np.asarray(over)
    cross, rim = numpy_crossings(built.params.prims, O, D, rim=True)
    count = cross.sum(1)
    assert count.max() >= 5 and (count == 0).mean() < 0.9  # the rays do cross the slab's blobs
    p = cross.shape[1]
    assert np.all(over[count > q.capacity])  # and grazing rays may cross more blocks than kept: flagged too
    assert np.all(over[leaves_crossed(built, q, cross) > q.block_capacity])
    diff = (as_mask(ids, p) ^ cross) & ~over[:, None]  # rays kept whole: candidates against crossings
    assert np.all(rim[diff]), np.argwhere(diff & ~rim)[:5]  # only spheres the ray grazes may differ
    exact = np.sum(~over & ~diff.any(1))
    assert exact >= 0.99 * np.sum(~over) and np.mean(over) < 0.1


@pytest.mark.parametrize("how", ["tree", "blocks"])
def test_block_overflow_is_flagged_never_dropped(slab, how):
    built, O, D = slab
    q = quality(built, how)._replace(block_capacity=1)
    ids, over = cull_fn(q)(built.params.prims, np.float32(O), np.float32(D))
    cross = numpy_crossings(built.params.prims, O, D)
    blocks_crossed = leaves_crossed(built, q, cross)
    over = np.asarray(over)
    assert np.sum(blocks_crossed >= 2) > 100
    assert np.all(over[blocks_crossed >= 2])  # a ray whose primitives lie in two blocks meets both blocks' bounds


def camera_rays(lo, hi, width=64, height=64, tile=8):
    """A pinhole's rays over the box (lo, hi), in ``tile`` x ``tile`` squares of the image one
    after another (the order ``camera.tile_order`` gives a render's rays), written here."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    c, size = 0.5 * (lo + hi), np.linalg.norm(hi - lo)
    eye = c + size * np.array([0.3, 0.9, 0.6])
    fwd = (c - eye) / np.linalg.norm(c - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    ys, xs = np.meshgrid(np.arange(height), np.arange(width), indexing="ij")
    order = np.lexsort((((ys % tile) * tile + xs % tile).ravel(), ((ys // tile) * (width // tile) + xs // tile).ravel()))
    u, v = ((xs.ravel()[order] + 0.5) / width - 0.5), ((ys.ravel()[order] + 0.5) / height - 0.5)
    D = fwd[None] + 0.5 * u[:, None] * right[None] + 0.5 * v[:, None] * up[None]
    return np.tile(eye, (width * height, 1)), D / np.linalg.norm(D, axis=1, keepdims=True)


def test_blocks_render_the_same_image_as_flat_culling():
    """The tree (leaves walked per ray, or found through packets of rays, ``cull: packets``)
    and the block spheres trace the same hits as flat culling (every primitive tested), on a
    camera's rays in screen tiles (the packets' lists hold their leaves) and on random rays (an
    incoherent packet's list overflows, and its rays are walked)."""
    rng = np.random.default_rng(11)
    hits = []
    for bs, how in ((0, "tree"), (16, "tree"), (16, "blocks"), (16, "packets")):
        built = blob_model(1500, block_size=bs, cull=how)
        if not hits:
            lo, hi = built.bounds
            O, D = ref.random_rays(rng, np.asarray(lo), np.asarray(hi), N_RAYS, spread=0.3)
            Oc, Dc = camera_rays(lo, hi)
            O, D = np.concatenate([Oc, O]), np.concatenate([Dc, D])
        key = built.static
        fn = lambda p, r, key=key: implicit.intersect_batch(p, key, r)  # overflowing rays retraced flat
        out = map_chunks(fn, built.params, make_rays(O - built.anchor, D), chunk=N_RAYS, progress=False).out
        hits.append(out)
    flat = hits[0]
    ok = np.asarray(flat.flags) == 0
    assert ok.mean() > 0.95  # only candidate-list overflows remain (the same rays every way)
    h = np.isfinite(flat.t) & ok
    assert h.mean() > 0.1 and h[:N_RAYS].mean() > 0.1  # the camera's rays hit too
    for blocked in hits[1:]:
        np.testing.assert_array_equal(flat.flags, blocked.flags)
        np.testing.assert_array_equal(h, np.isfinite(blocked.t) & ok)
        np.testing.assert_allclose(blocked.t[h], flat.t[h], rtol=1e-6, atol=1e-6)
        np.testing.assert_array_equal(blocked.prim[ok], flat.prim[ok])  # ids of the config, not of the sorted order


def test_per_ray_culling_work_grows_much_slower_than_the_model():
    """XLA's operation count for culling 1,024 rays: 10x the primitives (512 and 5,120 rows of
    their size buckets) costs 10x flat, < 4x in blocks. (The tree's walk is a while loop, whose
    count XLA cannot know: its cost is in the bench, ``experiments/bench_implicit_cull.yaml``.)"""
    flops, rows = {}, {}
    O = np.zeros((1024, 3), np.float32)
    D = np.tile(np.float32([[0.3, -1.0, 0.2]]), (1024, 1))
    for bs in (0, 16):
        for n in (500, 5000):
            built = blob_model(n, block_size=bs, cull="blocks")
            fn = cull_fn(built.static.quality)
            ca = fn.lower(built.params.prims, O, D).compile().cost_analysis()
            ca = ca[0] if isinstance(ca, list) else ca
            flops[bs, n], rows[n] = ca["flops"], built.params.prims.a.shape[0]
    assert rows[5000] / rows[500] == 10
    assert flops[0, 5000] / flops[0, 500] > 0.95 * 10
    assert flops[16, 5000] / flops[16, 500] < 4


def test_line_distance_is_stable_for_a_far_origin():
    """The culling sphere test in float32, 1e4 away: the distance to the line is within 1e-2
    of the float64 value (a few ulps of 1e4; the |oc|^2 - tc^2 form is off by more than 0.1)."""
    from jskel.numerics import line_dist2

    rng = np.random.default_rng(5)
    d = rng.normal(size=(1000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    side = np.cross(d, rng.normal(size=(1000, 3)))
    side /= np.linalg.norm(side, axis=1, keepdims=True)
    dist = rng.uniform(0.0, 1.0, 1000)
    oc = 1e4 * d + dist[:, None] * side  # a centre 1e4 along the ray, `dist` off it
    tc = np.sum(oc * d, 1)
    got = np.sqrt(np.asarray(line_dist2(jnp.float32(oc), jnp.float32(d), jnp.float32(tc)), np.float64))
    assert np.max(np.abs(got - dist)) < 1e-2
    naive = np.sqrt(np.maximum(np.sum(np.float32(oc) ** 2, 1) - np.float32(tc) ** 2, 0))
    assert np.max(np.abs(naive - dist)) > 0.1  # what the old form gave


def test_max_field_bound_pairs_every_overlap_and_bounds_the_field():
    """The build's host check of T against max F bounds F over each primitive's influence
    sphere by every primitive's kernel at its distance from that sphere, pairing them through a
    k-d tree; summing every pair in float64 gives the same bound, and it is above F at the
    primitives and at random points between them."""
    from jskel.implicit._scene import _max_field_bound

    rng = np.random.default_rng(8)
    n = 400
    a = rng.uniform(-3, 3, size=(n, 3))
    b = np.where(rng.uniform(size=(n, 1)) < 0.5, a, a + rng.normal(scale=0.5, size=(n, 3)))  # balls and tubes
    ra, rb = rng.uniform(0.2, 0.9, n), rng.uniform(0.2, 0.9, n)
    ab = b - a
    c = 0.5 * (a + b)
    reach = 0.5 * np.linalg.norm(ab, axis=1) + np.maximum(ra, rb)

    def seg_dist(x):  # (M,3) -> (M,P) distance to every segment, and R interpolated there
        ax = x[:, None, :] - a[None]
        den = np.sum(ab * ab, -1)
        t = np.clip(np.sum(ax * ab[None], -1) / np.where(den > 0, den, 1), 0, 1)
        return np.linalg.norm(ax - t[..., None] * ab[None], axis=-1), ra[None] + (rb - ra)[None] * t

    r, _ = seg_dist(c)
    q = np.maximum(r - reach[:, None], 0) ** 2 / np.maximum(ra, rb)[None] ** 2
    want = np.max(np.sum(np.where(q < 1, (1 - q) ** 2, 0), 1))
    got = _max_field_bound(a, b, ra, rb)
    np.testing.assert_allclose(got, want, rtol=1e-12)
    x = np.concatenate([c, a + rng.normal(scale=0.3, size=(n, 3)), rng.uniform(-3.5, 3.5, size=(4000, 3))])
    r, R = seg_dist(x)
    F = np.sum(np.where(r < R, (1 - (r / R) ** 2) ** 2, 0), 1)
    assert F.max() > 1.0 and got >= F.max()  # overlapping primitives: F sums several, below the bound
