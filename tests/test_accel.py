"""The linear BVH (issue 6): tree invariants, stackless pre-order, boxes that contain every hit,
and accelerated == brute force on random skeletons and the L-system tree."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import reference as ref
from conftest import CHUNK, assert_hits_agree, build_skeleton, cast, random_tree
from jskel import accel, frusta
from jskel.frusta._accel import segment_boxes
from jskel.rays import make_rays


def test_escape_walks_the_complete_tree_in_pre_order():
    for depth in range(0, 6):
        n_leaves = 1 << depth

        def pre(i):
            return [i] + ([] if i >= n_leaves else pre(2 * i) + pre(2 * i + 1))

        want = pre(1)
        got, node = [], 1
        while node:
            got.append(node)
            node = 2 * node if node < n_leaves else int(accel.escape(jnp.int32(node)))
        assert got == want
        # skipping a subtree lands on the node after it in pre-order
        for i in range(2, 2 * n_leaves):
            sub = set(pre(i))
            after = [j for j in want[want.index(i):] if j not in sub]
            assert int(accel.escape(jnp.int32(i))) == (after[0] if after else 0)


def test_tree_boxes_nest_and_order_is_a_permutation():
    rng = np.random.default_rng(0)
    p = 37
    c = rng.normal(size=(p, 3))
    half = rng.uniform(0.01, 0.3, size=(p, 3))
    valid = np.arange(p) < 33  # the last four are padding
    blo, bhi = np.float32(c - half), np.float32(c + half)
    bvh = accel.build(jnp.asarray(blo), jnp.asarray(bhi), jnp.asarray(valid), 4)
    lo, hi, order = (np.asarray(x) for x in (bvh.lo, bvh.hi, bvh.order))
    n_leaves = lo.shape[0] // 2
    assert n_leaves == 16 and sorted(order[order >= 0].tolist()) == list(range(33))
    for i in range(1, n_leaves):
        for ch in (2 * i, 2 * i + 1):
            assert np.all(lo[i] <= lo[ch]) and np.all(hi[i] >= hi[ch])
    for leaf in range(n_leaves):
        ids = order[leaf * 4 : leaf * 4 + 4]
        for k in ids[ids >= 0]:
            assert np.all(lo[n_leaves + leaf] <= blo[k]) and np.all(hi[n_leaves + leaf] >= bhi[k])


def test_collect_finds_every_leaf_the_ray_meets_and_flags_more_than_it_keeps():
    """``accel.collect`` (the walk for implicit culling) against a float64 NumPy slab test of
    every leaf box: the same leaves where the ray is clear of a box's boundary, and overflow
    exactly when more leaves are met than kept."""
    rng = np.random.default_rng(4)
    p, leaf, cap = 300, 4, 6
    c = rng.uniform(-1, 1, size=(p, 3))
    half = rng.uniform(0.02, 0.15, size=(p, 3))
    bvh = accel.build(jnp.float32(c - half), jnp.float32(c + half), jnp.ones(p, bool), leaf)
    n_leaves = bvh.lo.shape[0] // 2
    O = rng.uniform(-1, 1, size=(512, 3))
    D = rng.normal(size=(512, 3))
    D[:32, 1:] = 0.0  # axis-parallel rays: zero direction components
    walk = jax.jit(jax.vmap(lambda o, d: accel.collect(bvh, o, d, 0.0, jnp.inf, cap)))
    slots, k, over = (np.asarray(x) for x in walk(jnp.float32(O), jnp.float32(D)))
    lo, hi = np.asarray(bvh.lo, np.float64)[n_leaves:], np.asarray(bvh.hi, np.float64)[n_leaves:]
    meets, edge = numpy_leaves_met(lo, hi, O, D)  # edge: a corner, an edge or the origin on a face
    count = meets.sum(1)
    assert count.max() > cap and (count == 0).sum() > 10 and ((count > 0) & (count <= cap)).sum() > 100
    decided = ~np.any(edge, 1)
    np.testing.assert_array_equal(over[decided], count[decided] > cap)
    for i in np.nonzero(decided & ~over)[0]:
        assert sorted(slots[i][: k[i]].tolist()) == np.nonzero(meets[i])[0].tolist()
        assert np.all(slots[i][k[i]:] == -1)
    # an overflowing list continued by walking again past the slots taken (``skip``, traced):
    # the rounds together list every leaf met, each once
    again = jax.jit(jax.vmap(lambda o, d, s: accel.collect(bvh, o, d, 0.0, jnp.inf, cap, s), in_axes=(0, 0, None)))
    rows = np.nonzero(decided & over)[0]
    assert rows.size > 20
    lists, still = [slots[rows]], over[rows]
    for r in range(1, -(-int(count.max()) // cap)):
        s_r, _, o_r = (np.asarray(x) for x in again(jnp.float32(O[rows]), jnp.float32(D[rows]), jnp.int32(r * cap)))
        lists.append(np.where(still[:, None], s_r, -1))
        still = still & o_r
    assert not np.any(still)
    for j, i in enumerate(rows):
        got = np.concatenate([l_[j] for l_ in lists])
        assert sorted(got[got >= 0].tolist()) == np.nonzero(meets[i])[0].tolist()


def numpy_leaves_met(lo, hi, O, D):
    """(R, L) whether each ray (t >= 0) meets each box, and (R, L) whether it passes within
    float32's reach of a box's boundary (a corner, an edge, the origin on a face): float64 slab
    tests written here."""
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = (lo[None] - O[:, None]) / D[:, None]
        tb = (hi[None] - O[:, None]) / D[:, None]
    inside = (O[:, None] >= lo[None]) & (O[:, None] <= hi[None])
    ta = np.where(D[:, None] == 0, np.where(inside, -np.inf, np.inf), ta)  # outside a slab: entry at +inf
    tb = np.where(D[:, None] == 0, np.inf, tb)
    t0 = np.max(np.minimum(ta, tb), -1)
    t1 = np.min(np.maximum(ta, tb), -1)
    meets = (t0 <= t1) & (t1 >= 0) & np.all(lo <= hi, -1)[None]
    with np.errstate(invalid="ignore"):
        edge = ~(np.abs(t1 - t0) > 1e-4 * (1 + np.abs(t0))) | (np.abs(t1) <= 1e-4)
    return meets, edge & np.all(lo <= hi, -1)[None]  # an empty box (padding) has no boundary


@pytest.mark.parametrize("listed", [24, 48])
def test_collect_packets_finds_every_leaf_a_ray_meets_and_spills_incoherent_packets(listed):
    """``accel.collect_packets`` against float64 NumPy slab tests of every leaf box: on packets
    of coherent rays (from one eye into a narrow cone; one packet axis-parallel) every ray's
    leaves, overflow exactly when more are met than kept; a packet of random rays meets more
    leaves than its list holds and is flagged, never answered short."""
    rng = np.random.default_rng(5)
    p, leaf, cap, g = 300, 4, 12, 64
    c = rng.uniform(-1, 1, size=(p, 3))
    half = rng.uniform(0.02, 0.15, size=(p, 3))
    bvh = accel.build(jnp.float32(c - half), jnp.float32(c + half), jnp.ones(p, bool), leaf)
    n_leaves = bvh.lo.shape[0] // 2
    Os, Ds = [], []
    for k in range(6):  # coherent packets: one eye, directions within a few degrees
        eye = rng.normal(size=3)
        eye *= 2.5 / np.linalg.norm(eye)
        aim = rng.uniform(-0.6, 0.6, size=3) - eye
        d = aim / np.linalg.norm(aim) + 0.03 * rng.normal(size=(g, 3))
        Os.append(np.tile(eye, (g, 1)))
        Ds.append(d)
    Os.append(np.column_stack([np.full(g, -2.0), rng.uniform(-0.3, 0.3, (g, 2))]))  # axis-parallel: d = (1, 0, 0)
    Ds.append(np.tile([1.0, 0.0, 0.0], (g, 1)))
    Os.append(rng.uniform(-1, 1, size=(g, 3)))  # one incoherent packet
    Ds.append(rng.normal(size=(g, 3)))
    O, D = np.concatenate(Os), np.concatenate(Ds)
    fn = jax.jit(lambda o, d: accel.collect_packets(bvh, o, d, jnp.zeros(o.shape[0]), jnp.full(o.shape[0], jnp.inf), cap, g, listed))
    slots, count, over, spill = (np.asarray(x) for x in fn(jnp.float32(O), jnp.float32(D)))
    lo, hi = np.asarray(bvh.lo, np.float64)[n_leaves:], np.asarray(bvh.hi, np.float64)[n_leaves:]
    meets, edge = numpy_leaves_met(lo, hi, O, D)
    n = meets.sum(1)
    union = meets.reshape(-1, g, n_leaves).any(1).sum(1)  # leaves each packet's rays meet
    spilled = spill.reshape(-1, g)
    assert np.all(spilled == spilled[:, :1])  # a packet's rays are flagged together
    assert np.all(spilled[union > listed])  # a list too short for its packet is never trusted
    if listed == 48:  # only the random packet's list overflowed
        assert spilled[-1, 0] and not np.any(spilled[:-1])
    else:
        assert spilled[:-1, 0].sum() in range(1, 7)
    assert np.any(n[:-g] > cap) and ((n[:-g] > 0) & (n[:-g] <= cap)).sum() > 100  # both cases are tested
    decided = ~np.any(edge, 1) & ~spill
    assert decided.sum() > (300 if listed == 48 else 150)
    np.testing.assert_array_equal(over[decided], n[decided] > cap)
    for i in np.nonzero(decided & ~over)[0]:
        k = count[i]
        assert sorted(slots[i][:k].tolist()) == np.nonzero(meets[i])[0].tolist()
        assert np.all(slots[i][k:] == -1)


def test_an_any_hit_walk_answers_whether_and_stops_at_its_first_hit():
    """``accel.nearest(..., any_hit=True)`` (shadow rays) over 400 spheres: whether each ray meets
    a sphere in ``(t_min, t_max]`` equals a float64 NumPy test of every sphere (rays within 1e-4
    of a sphere's silhouette or of their window's ends left out), the hit it returns lies on a
    sphere in the window, and it tests no more leaves than the nearest-hit walk on any ray and
    fewer in all."""
    rng = np.random.default_rng(11)
    p, leaf = 400, 4
    c = rng.uniform(-1, 1, size=(p, 3))
    r = rng.uniform(0.03, 0.12, size=p)
    bvh = accel.build(jnp.float32(c - r[:, None]), jnp.float32(c + r[:, None]), jnp.ones(p, bool), leaf)
    cj, rj = jnp.float32(c), jnp.float32(r)

    def leaf_fn(slots, o, d, t_min, t_hi):
        ids = bvh.order[slots]
        i = jnp.maximum(ids, 0)
        oc = o - cj[i]
        b, q = jnp.sum(oc * d, -1), jnp.sum(oc * oc, -1) - rj[i] ** 2
        disc = b * b - q
        root = jnp.sqrt(jnp.maximum(disc, 0.0))
        t = jnp.where(-b - root > t_min, -b - root, -b + root)
        t = jnp.where((ids >= 0) & (disc >= 0) & (t > t_min) & (t <= t_hi), t, jnp.inf)
        k = jnp.argmin(t)
        return accel.Best(t[k], jnp.zeros((), t.dtype), jnp.int32(0), jnp.where(jnp.isfinite(t[k]), ids[k], -1))

    init = accel.Best(jnp.float32(jnp.inf), jnp.float32(0.0), jnp.int32(0), jnp.int32(-1))
    walks = {a: jax.jit(jax.vmap(lambda o, d, lo, hi, a=a: accel.nearest(bvh, leaf_fn, leaf, o, d, lo, hi, init, any_hit=a)))
             for a in (False, True)}
    n = 1024
    O = rng.uniform(-1.5, 1.5, size=(n, 3))
    D = rng.normal(size=(n, 3))
    D /= np.linalg.norm(D, axis=1, keepdims=True)
    t_min = rng.uniform(0.0, 0.5, n)
    t_max = np.where(rng.uniform(size=n) < 0.5, np.inf, t_min + rng.uniform(0.1, 1.5, n))
    args = (jnp.float32(O), jnp.float32(D), jnp.float32(t_min), jnp.float32(t_max))
    (near, _, near_leaves), (first, _, first_leaves) = (jax.tree_util.tree_map(np.asarray, walks[a](*args)) for a in (False, True))
    oc = O[:, None] - c[None]
    b = np.sum(oc * D[:, None], -1)
    disc = b * b - (np.sum(oc * oc, -1) - r**2)
    root = np.sqrt(np.maximum(disc, 0.0))
    roots = np.stack([-b - root, -b + root], -1)
    within = (disc[..., None] >= 0) & (roots > t_min[:, None, None]) & (roots <= t_max[:, None, None])
    truth = np.any(within, (1, 2))
    edge = np.any(np.abs(disc) < 1e-4, 1) | np.any(np.abs(roots - t_min[:, None, None]) < 1e-4, (1, 2)) | np.any(
        np.abs(roots - t_max[:, None, None]) < 1e-4, (1, 2))
    assert truth[~edge].sum() > 100 and (~truth[~edge]).sum() > 100
    # (a walk starts its best t at t_max: a hit is a primitive found)
    np.testing.assert_array_equal((first.idx >= 0)[~edge], truth[~edge])
    np.testing.assert_array_equal((near.idx >= 0)[~edge], truth[~edge])
    hit = (first.idx >= 0) & ~edge
    k = first.idx[hit]
    on = np.abs(np.linalg.norm(O[hit] + first.t[hit, None] * D[hit] - c[k], axis=1) - r[k])
    assert np.all(on < 1e-4) and np.all(first.t[hit] >= near.t[hit] - 1e-6)
    assert np.all(first_leaves <= near_leaves) and first_leaves.sum() < 0.9 * near_leaves.sum()


def _random_skeleton(rng, n):
    j, r, p = random_tree(rng, n)
    return j, r, p.tolist()


@pytest.fixture(scope="module")
def skeletons():
    rng = np.random.default_rng(5)
    out = []
    for n in (9, 40, 64):
        j, r, p = _random_skeleton(rng, n)
        out.append((j, r, p))
    return out


def test_boxes_contain_every_hit_point(skeletons):
    rng = np.random.default_rng(6)
    for j, r, p in skeletons:
        b = build_skeleton(j, r, p)
        O, D = ref.random_rays(rng, j.min(0) - 0.5, j.max(0) + 0.5, 8192, spread=1.0)
        hit = cast(b, O, D)
        f = b.params.plain.frusta
        lo, hi = (np.asarray(x, np.float64) + b.anchor for x in segment_boxes(f))
        h = np.isfinite(hit.t)
        assert h.mean() > 0.05
        sid = np.asarray(f.sid)
        row = np.array([np.nonzero(sid == s)[0][0] for s in hit.prim[h]])
        x = hit.position[h]
        assert np.all(x >= lo[row] - 1e-5) and np.all(x <= hi[row] + 1e-5)


@pytest.mark.parametrize("accel,leaf,group,packet", [("bvh", 4, 512, 0), ("bvh", 2, 16, 0), ("bvh", 4, 512, 256),
                                                     ("bvh", 2, 512, 7), ("blocks", 4, 512, 0)])
def test_bvh_and_blocks_equal_brute_force_on_random_skeletons(skeletons, accel, leaf, group, packet):
    """Per-ray walks, packets of 256 incoherent rays and a packet size that pads the chunk."""
    rng = np.random.default_rng(7)
    for j, r, p in skeletons:
        brute = build_skeleton(j, r, p)
        fast = build_skeleton(j, r, p, accel=accel, leaf=leaf, group=group, packet=packet, traversal="packets" if packet else "walks")
        assert fast.static.accel == accel
        O, D = ref.random_rays(rng, j.min(0) - 0.5, j.max(0) + 0.5, 8192, spread=1.0)
        a = cast(brute, O, D)
        b = cast(fast, O, D, culled=True)
        np.testing.assert_array_equal(a.t, b.t)  # the same float computations, pruned differently
        same = a.prim == b.prim
        assert np.all(same | (a.t == b.t))  # a differing id only on an exact tie in t
        assert same.mean() > 0.999
        np.testing.assert_array_equal(a.normal[same], b.normal[same])


def _windows(rng, n):
    """(t_min, t_max) per ray: t_min 0 or up to 2, t_max +inf for half the rays, else 0.5-4 past t_min."""
    t_min = np.where(rng.uniform(size=n) < 0.3, 0.0, rng.uniform(0.0, 2.0, n))
    return t_min, np.where(rng.uniform(size=n) < 0.5, np.inf, t_min + rng.uniform(0.5, 4.0, n))


def _assert_windowed(a, b, t_min, t_max):
    """Brute force ``a`` and a traversal ``b`` of rays with windows: every hit inside its window,
    a miss +inf (never its t_max), the same hits as brute force."""
    for h in (a, b):
        hit = np.isfinite(h.t)
        assert np.all(h.t[hit] > t_min[hit] - 1e-6) and np.all(h.t[hit] <= t_max[hit] * (1 + 1e-6))
        assert np.all(np.isposinf(h.t[~hit])) and np.all(h.prim[~hit] == -1)
    assert 0.05 < np.isfinite(a.t).mean() < 0.95 and np.isfinite(t_max[~np.isfinite(a.t)]).sum() > 50
    np.testing.assert_array_equal(np.isfinite(a.t), np.isfinite(b.t))
    hit = np.isfinite(a.t)
    np.testing.assert_allclose(b.t[hit], a.t[hit], rtol=8 * np.finfo(np.float32).eps, atol=0)


@pytest.mark.parametrize("traversal", ["walks", "packets", "bins"])
def test_a_ray_whose_window_ends_before_any_segment_misses(skeletons, traversal):
    """Random windows (t_min > 0, finite t_max) on incoherent rays: the BVH's per-ray walks and
    packets start their best t at t_max, and once returned t_max itself for a ray that met
    nothing (found by the conformance suite when ``auto`` began to pick the walks); bins hand
    their overflowing chunks to the walks (``bin_walk_ratio: 1e-6``: every chunk with a candidate)."""
    rng = np.random.default_rng(9)
    j, r, p = skeletons[1]
    brute = build_skeleton(j, r, p, accel="none")
    kw = {"bin_walk_ratio": 1e-6} if traversal == "bins" else {}
    fast = build_skeleton(j, r, p, accel="bvh", traversal=traversal, **kw)
    O, D = ref.random_rays(rng, j.min(0) - 0.5, j.max(0) + 0.5, 2048, spread=1.0)
    t_min, t_max = _windows(rng, len(O))
    _assert_windowed(cast(brute, O, D, t_min, t_max), cast(fast, O, D, t_min, t_max, culled=True), t_min, t_max)


@pytest.mark.parametrize("traversal", ["packets"])  # bins on a large scene: the oasis above
def test_bvh_equals_brute_force_on_the_lsystem_tree(traversal):
    """The 4,374-segment tree at 64 x 48 in screen-tile order; bins within float rounding (see
    test_bins_equal_brute_force_on_random_skeletons), the BVH packets bit for bit."""
    from jskel.config import load
    from jskel.camera import tile_order

    exp = load("experiments/lsystem_tree.yaml", ["camera.width=64", "camera.height=48"])
    obj = exp.objects[0].shape
    brute = frusta.build(obj.model_copy(update={"accel": "none"}))
    fast = frusta.build(obj.model_copy(update={"accel": "bvh", "traversal": traversal}))
    assert brute.static.accel == "none" and fast.static.traversal == traversal
    from jskel.render import camera_of

    O, D = camera_of(exp).ray_arrays()
    order = tile_order(64, 48, 16)
    O, D = O[order], D[order]
    a = cast(brute, O, D, culled=True)
    b = cast(fast, O, D, culled=True)
    assert np.isfinite(a.t).mean() > 0.05
    assert_hits_agree(a, b, 2e-5 if traversal == "bins" else 0.0)


def test_table_1_scene_sizes():
    from jskel.scenes import generate

    want = {"palm": 3713, "pine": 16802, "oasis": 18557, "dancing_cacti": 2158}
    for name, n in want.items():
        j, r, p, c = generate(name, 0, {})
        assert len(j) - int(np.sum(p < 0)) == n, name


def test_a_strong_change_of_taper_keeps_every_cut_an_ellipse():
    """A thin leaflet leaving a thick joint with a small bend (the palm's case): Eq. 3-5 would put
    a plane nearly through the axis and the frustum would run off along a generator; with the
    bisector fallback every hit lies next to the skeleton, and the BVH agrees with brute force."""
    from jskel.frusta._geometry import cuts_ellipse as _cuts_ellipse

    joints = [[0, 0, 0], [0, 0.16, 0.0], [0.02, 0.34, 0.0], [0.05, 0.5, 0.0]]
    radii = [0.035, 0.0113, 0.0067, 0.002]
    brute = build_skeleton(joints, radii, [-1, 0, 1, 2])
    f = brute.params.plain.frusta
    v = np.asarray(f.valid)
    m = np.asarray(f.m)[v]
    for n, (r0, r1) in ((np.asarray(f.nb)[v], (np.asarray(f.r1)[v], np.asarray(f.r2)[v])), (np.asarray(f.nt)[v], (np.asarray(f.r1)[v], np.asarray(f.r2)[v]))):
        assert np.all(_cuts_ellipse(n, m, r0, r1, np.asarray(f.h)[v]))
    rng = np.random.default_rng(9)
    O, D = ref.random_rays(rng, np.array([-0.1, -0.05, -0.1]), np.array([0.15, 0.55, 0.1]), 8192, spread=1.0)
    hit = cast(brute, O, D)
    h = np.isfinite(hit.t)
    assert h.mean() > 0.02
    assert np.all(hit.position[h, 1] > -0.05) and np.all(hit.position[h, 1] < 0.55)
    assert np.all(np.hypot(hit.position[h, 0] - 0.03, hit.position[h, 2]) < 0.1)
    fast = build_skeleton(joints, radii, [-1, 0, 1, 2], accel="bvh", traversal="walks")
    np.testing.assert_array_equal(cast(fast, O, D, culled=True).t, hit.t)
    bins = build_skeleton(joints, radii, [-1, 0, 1, 2], accel="bvh", traversal="bins", bin_group=0)  # the flat batch list
    assert_hits_agree(hit, cast(bins, O, D, culled=True), 2e-5)


# packets on the cacti (and the L-system tree below), bins on the oasis (the CPU default from 64
# segments): each traversal once on a large scene, not both on the oasis
@pytest.mark.parametrize("scene,frame,traversal", [("dancing_cacti", 12.0, "packets"), ("oasis", 0.0, "bins")])
def test_bvh_equals_block_culling_on_the_large_scenes(scene, frame, traversal):
    """The 18,557-segment oasis, and a frame of the animated cacti (the tree rebuilt from that
    frame's frusta), at low resolution in screen-tile order: the same t and ids as the block
    scan (bins: within float rounding, see test_bins_equal_brute_force_on_random_skeletons)."""
    from jskel.config import load
    from jskel.camera import tile_order
    from jskel.render import camera_of

    exp = load(f"experiments/{scene}.yaml", ["camera.width=48", "camera.height=36", f"object.frame={frame}", f"object.traversal={traversal}"])
    obj = exp.objects[0].shape
    fast = frusta.build(obj)
    blocks = frusta.build(obj.model_copy(update={"accel": "blocks"}))
    assert fast.static.accel == "bvh" and fast.static.traversal == traversal and blocks.static.accel == "blocks"
    O, D = camera_of(exp).ray_arrays()
    order = tile_order(48, 36, 16)
    a = cast(blocks, O[order], D[order], culled=True)
    b = cast(fast, O[order], D[order], culled=True)
    assert np.isfinite(a.t).mean() > 0.05
    assert_hits_agree(a, b, 2e-5 if traversal == "bins" else 0.0)


@pytest.mark.parametrize("leaf,block", [(4, 32)])  # the defaults
def test_pallas_kernel_walk_equals_brute_force_on_random_skeletons(skeletons, leaf, block):
    """The accelerator's traversal (``traversal: kernel``, a Pallas kernel; here through Pallas's
    interpreter on the CPU) on incoherent random rays: the same hit or miss for every ray, the
    same segment but on near-ties, t within a few ulps (the kernel's per-component arithmetic is
    compiled apart from the vmapped reference, so a multiply-add may round differently) and
    exactly the per-ray walk's node and leaf counts (the same walk step for step)."""
    from jskel.frusta._accel import nearest_groups
    from jskel.frusta._kernel import nearest_kernel

    rng = np.random.default_rng(8)
    j, r, p = skeletons[2]
    brute = build_skeleton(j, r, p)
    fast = build_skeleton(j, r, p, accel="bvh", leaf=leaf, traversal="kernel", kernel_block=block)
    assert fast.static.traversal == "kernel"
    O, D = ref.random_rays(rng, j.min(0) - 0.5, j.max(0) + 0.5, 2048, spread=1.0)
    # windows: half the rays end at a finite t_max, most start beyond 0 (the same program)
    t_min, t_max = _windows(rng, len(O))
    aw, bw = cast(brute, O, D, t_min, t_max), cast(fast, O, D, t_min, t_max, culled=True)
    _assert_windowed(aw, bw, t_min, t_max)
    a = cast(brute, O, D)
    b = cast(fast, O, D, culled=True)
    hit = np.isfinite(a.t)
    assert 0.1 < hit.mean() < 0.9
    np.testing.assert_array_equal(hit, np.isfinite(b.t))
    np.testing.assert_allclose(b.t[hit], a.t[hit], rtol=8 * np.finfo(np.float32).eps, atol=0)
    same = a.prim == b.prim
    with np.errstate(invalid="ignore"):  # inf - inf on the misses (their ids are both -1)
        near_tie = np.abs(a.t - b.t) <= 8 * np.finfo(np.float32).eps * np.abs(a.t)
    assert np.all(same | near_tie) and same.mean() > 0.999
    g = fast.params.plain
    rays = make_rays(np.asarray(O) - fast.anchor, D, 0.0, np.inf)
    k = nearest_kernel(g.frusta, g.bvh, leaf, *rays, block=block)
    w = nearest_groups(g.frusta, g.bvh, leaf, 512, *rays)
    np.testing.assert_array_equal(np.asarray(k[4]), np.asarray(w[4]))  # nodes visited per ray
    np.testing.assert_array_equal(np.asarray(k[5]), np.asarray(w[5]))  # leaves tested per ray


def _slab_meets(O, D, t_lo, t_hi, lo, hi):
    """float64 NumPy: (rays, boxes) whether each ray meets each box within [t_lo, t_hi]."""
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / D[:, None, :]
        a = (lo[None] - O[:, None, :]) * inv
        b = (hi[None] - O[:, None, :]) * inv
    par = D[:, None, :] == 0  # parallel: inside the slab or never
    inside = (O[:, None, :] >= lo[None]) & (O[:, None, :] <= hi[None])
    near = np.where(par, np.where(inside, -np.inf, np.inf), np.minimum(a, b)).max(-1)
    far = np.where(par, np.where(inside, np.inf, -np.inf), np.maximum(a, b)).min(-1)
    return (np.maximum(near, t_lo[:, None]) <= np.minimum(far, t_hi[:, None])) & np.all(lo <= hi, -1)[None]


def test_packet_meets_keeps_every_box_a_ray_of_the_packet_meets():
    """The interval-arithmetic packet test against float64 per-ray slab tests: never drops a
    box one of its rays meets (coherent pinhole packets, packets with spread origins, directions
    with exact zero components and sign changes, finite t ranges), never keeps an empty box, and
    rejects most boxes for a narrow packet (it is a real filter)."""
    rng = np.random.default_rng(11)
    c = rng.uniform(-4, 4, size=(400, 3))
    half = rng.uniform(0.01, 0.6, size=(400, 3))
    lo, hi = c - half, c + half
    lo[-5:], hi[-5:] = np.inf, -np.inf  # empty boxes
    kept_narrow = []
    for trial in range(24):
        kind = trial % 4
        g = 16
        O = np.broadcast_to(rng.uniform(-6, 6, 3), (g, 3)).copy()
        target = rng.uniform(-3, 3, 3)
        D = (target - O) + rng.normal(scale=0.05 if kind < 2 else 1.0, size=(g, 3))
        if kind == 1:
            O = O + rng.normal(scale=0.3, size=(g, 3))  # origins spread (secondary rays)
        if kind == 3:
            D[:, trial % 3] = 0.0  # an axis with d = 0 exactly on every ray
            D[: g // 2, (trial + 1) % 3] *= -1  # and one whose sign changes in the packet
        D /= np.linalg.norm(D, axis=1, keepdims=True)
        t_lo = np.zeros(g)
        t_hi = np.full(g, np.inf) if trial % 2 == 0 else rng.uniform(2, 12, g)
        truth = _slab_meets(O, D, t_lo, t_hi, lo, hi).any(0)
        got = np.asarray(accel.packet_meets(*(jnp.asarray(x, jnp.float32) for x in (O.min(0), O.max(0), D.min(0), D.max(0))),
                                            jnp.float32(t_lo.min()), jnp.float32(t_hi.max()), jnp.asarray(lo, jnp.float32), jnp.asarray(hi, jnp.float32)))
        assert np.all(got[truth]), trial
        assert not np.any(got[-5:])
        if kind == 0:
            kept_narrow.append(got[:-5].mean())
    assert truth.any() and max(kept_narrow) < 0.5


def test_first_set_and_order_equal_numpy():
    """The bins' compaction and block order against NumPy: ``first_set`` gives the positions of
    the first q set bits of a packed mask (``np.flatnonzero``) and their count, for empty, sparse,
    dense and full masks and fewer set bits than q; ``_order`` is a stable argsort (ties and
    infinities included, as a block's entry distances have them)."""
    from jskel.accel._bins import _order

    rng = np.random.default_rng(5)
    first = jax.jit(lambda m: accel.first_set(accel.pack_bits(m), 96))
    for density in (0.0, 0.01, 0.2, 0.9, 1.0):
        mask = rng.random(1000) < density
        pos, count = first(jnp.asarray(mask))
        truth = np.flatnonzero(mask)
        assert int(count) == truth.size, density
        k = min(96, truth.size)
        assert np.array_equal(np.asarray(pos)[:k], truth[:k]), density
    order = jax.jit(_order)
    for trial in range(4):
        e = rng.choice([0.5, 1.0, 2.0, np.inf], 128) if trial % 2 else rng.normal(size=128)
        e = e.astype(np.float32)
        assert np.array_equal(np.asarray(order(jnp.asarray(e))), np.argsort(e, kind="stable")), trial


# the default knobs (64, 128, 256, 32, 1.5) are cast on the oasis above; here the loops run many
# times per batch, and every listed batch goes to the walks
@pytest.mark.parametrize("sizes", [(8, 3, 5, 4, 1.5), (64, 128, 256, 32, 1e-6)])
def test_bins_equal_brute_force_on_random_skeletons(skeletons, sizes):
    """Candidate lists per packet (``traversal: bins``) against brute force, on incoherent rays
    (long lists) and on a pinhole camera's rays in screen tiles; (8, 3, 5, 4) runs the group,
    candidate and pair loops many times per batch; a walk ratio of 1e-6 sends every batch with a
    non-empty list to the per-ray walks (``bin_walk_ratio``; the stats count those rays). XLA fuses the two programs apart and contracts
    different products into FMAs, so t may differ by float rounding (the bench's largest depth
    difference on the cacti at 1024 x 768: 4e-5 at about 16 units, 2.5e-6 relative; the bound
    here is 2e-5 relative); hits, misses and segments agree."""
    from jskel.camera import Camera, tile_order

    rng = np.random.default_rng(8)
    packet, cands, pairs, group, ratio = sizes
    for j, r, p in skeletons:
        brute = build_skeleton(j, r, p)
        fast = build_skeleton(j, r, p, accel="bvh", traversal="bins", bin_packet=packet, bin_candidates=cands, bin_pairs=pairs, bin_group=group,
                              bin_walk_ratio=ratio)
        assert fast.static.traversal == "bins"
        O1, D1 = ref.random_rays(rng, j.min(0) - 0.5, j.max(0) + 0.5, 4096, spread=1.0)
        c = 0.5 * (j.min(0) + j.max(0))
        cam = Camera(c + np.array([0.3, 1.0, 3.0]) * np.ptp(j, 0).max(), c, np.array([0.0, 1.0, 0.0]), 45.0, 64, 64)
        O2, D2 = cam.ray_arrays()
        order = tile_order(64, 64, 16)
        O, D = np.concatenate([O1, O2[order]]), np.concatenate([D1, D2[order]])
        a = cast(brute, O, D)
        b = cast(fast, O, D, culled=True)
        assert 0.05 < np.isfinite(a.t).mean() < 0.95
        assert_hits_agree(a, b, 2e-5)
        assert (a.prim == b.prim).mean() > 0.999
    if ratio < 1e-3:  # the last skeleton's batches were walked
        from jskel import frusta
        from jskel.rays import make_rays

        assert frusta.traversal_stats(fast, make_rays(O - fast.anchor, D), chunk=CHUNK)["bin_walked_fraction"] > 0.5


@pytest.mark.parametrize("traversal", ["bins", "walks"])
def test_grazing_rays_from_far_origins_keep_their_hits(traversal):
    """Rays parallel to a cylinder's box face, 1e-7 to 1e-2 radii inside its silhouette (the
    hit lies on the face of the segment's box), from 10 to 1e4 units away: the box tests of the
    packet and of the walk keep every hit brute force finds (no hit lost to float rounding of a
    far origin against a near box)."""
    joints = [[0, 0, 0], [0, 2, 0], [0.0, 4.0, 0.0], [3, 0, 0], [3, 2, 0]]
    radii, parents = [0.5, 0.5, 0.5, 0.3, 0.3], [-1, 0, 1, -1, 3]
    brute = build_skeleton(joints, radii, parents, accel="none")
    fast = build_skeleton(joints, radii, parents, accel="bvh", traversal=traversal)
    n = 4096
    x = 0.5 * (1 - np.geomspace(1e-7, 1e-2, n))
    y = np.linspace(0.1, 3.9, n)
    for dist in (10.0, 1e3, 1e4):
        O = np.stack([x, y, np.full(n, dist)], 1)
        D = np.tile([0.0, 0.0, -1.0], (n, 1))
        a = cast(brute, O, D, culled=True)
        b = cast(fast, O, D, culled=True)
        assert np.all(np.isfinite(a.t))  # every ray is inside the silhouette
        assert_hits_agree(a, b, 2e-5 if traversal == "bins" else 0.0)
