"""Issue 6 beyond the tree itself: the peers' tessellation (no peer library needed), skeleton
families for the cost-against-size study, traversal work growing with log(segments), and the
memory budget that picks the chunk."""

from __future__ import annotations

import numpy as np
import pytest

import reference as ref
from conftest import build_skeleton, cast, random_tree
from jskel import frusta
from jskel.peers.skeleton import curve_points, frusta_mesh


def _tree(rng, n):
    return random_tree(rng, n, lift=0.4, length=0.7, r_max=0.25)


@pytest.mark.parametrize("level", [0, 1, 2])
def test_gs_tessellation_has_table_1_counts_and_lies_on_the_clipped_cones(level):
    """Table 1: 16 n x 4^m triangles for n segments at level m (plus fans on free ends); every
    vertex on its cone x^2 + z^2 = (r1 + k y)^2 (closed form in float64 here) and the end rings
    on the cutting planes."""
    rng = np.random.default_rng(3)
    j, r, p = _tree(rng, 12)
    arr, topo, _ = frusta.frusta_from_skeleton(j, r, p)
    s = arr.h.shape[0]
    V, F = frusta_mesh(arr, level)
    nu, nv = 8 * 2**level, 2**level
    caps = int(np.sum(arr.cap_b) + np.sum(arr.cap_t))
    assert F.shape[0] == 16 * 4**level * s + caps * nu
    assert F.min() >= 0 and F.max() < V.shape[0]
    P = V[: s * (nv + 1) * nu].reshape(s, nv + 1, nu, 3) - arr.c1[:, None, None, :]
    y = np.einsum("sabk,sk->sab", P, arr.m)
    radial = np.linalg.norm(P - y[..., None] * arr.m[:, None, None, :], axis=-1)
    want = arr.r1[:, None, None] + (arr.r2 - arr.r1)[:, None, None] / arr.h[:, None, None] * y
    np.testing.assert_allclose(radial, want, atol=1e-9)
    np.testing.assert_allclose(np.einsum("sak,sk->sa", P[:, 0], arr.nb), np.broadcast_to(arr.db[:, None], (s, nu)), atol=1e-9)
    np.testing.assert_allclose(np.einsum("sak,sk->sa", P[:, -1], arr.nt), np.broadcast_to(arr.dt[:, None], (s, nu)), atol=1e-9)
    # a triangle's vertices come from one segment (or its cap centre)
    seg = np.minimum(F // ((nv + 1) * nu), s)
    lateral = np.all(F < s * (nv + 1) * nu, axis=1)
    assert np.all(seg[lateral, 0] == seg[lateral, 1]) and np.all(seg[lateral, 1] == seg[lateral, 2])


def test_curve_points_are_one_round_cone_per_segment():
    j = np.array([[0, 0, 0], [0, 1, 0], [1, 1, 0], [0, 2, 0.0]])
    r = np.array([0.3, 0.2, 0.1, 0.15])
    pts = curve_points(j, r, np.array([-1, 0, 1, 1]))
    assert pts.shape == (3, 2, 4)
    np.testing.assert_array_equal(pts[:, 0, :3], j[[0, 1, 1]])
    np.testing.assert_array_equal(pts[:, 1, :3], j[[1, 2, 3]])
    np.testing.assert_array_equal(pts[:, :, 3], [[0.3, 0.2], [0.2, 0.1], [0.2, 0.15]])


def test_subdivided_skeleton_is_the_same_surface():
    """Splitting every segment into collinear pieces leaves the skinned surface unchanged: the
    float64 NumPy reference on the original skeleton agrees with jskel on the split one."""
    from jskel.frusta._edits import subdivide_skeleton

    rng = np.random.default_rng(11)
    j, r, p = _tree(rng, 10)
    j2, r2, p2, _ = subdivide_skeleton(j, r, p, None, 3)
    assert j2.shape[0] == 10 + 9 * 2 and np.sum(p2 >= 0) == 27
    np.testing.assert_array_equal(j2[:10], j)
    split = build_skeleton(j2, r2, p2, accel="bvh")
    O, D = ref.random_rays(rng, j.min(0) - 0.4, j.max(0) + 0.4, 8192, spread=1.0)
    got = cast(split, O, D, culled=True)
    segs = ref.segments(j, r, p)
    t_ref, _ = ref.intersect(segs, O, D)
    scale = float(np.linalg.norm(j.max(0) - j.min(0)))
    far = ref.far_from_silhouette(segs, O, D, delta=1e-3 * scale, jump=2e-2 * scale)
    hit_g, hit_w = np.isfinite(got.t), np.isfinite(t_ref)
    assert 0.05 < hit_w.mean() < 0.95
    np.testing.assert_array_equal(hit_g[far], hit_w[far])
    both = hit_g & hit_w & far
    assert np.max(np.abs(got.t[both] - t_ref[both])) <= 1e-4 * scale


def test_replicated_skeleton_tiles_the_original_box():
    from jskel.frusta._edits import replicate_skeleton

    rng = np.random.default_rng(2)
    j, r, p = _tree(rng, 7)
    j3, r3, p3, _ = replicate_skeleton(j, r, p, None, 3)
    assert j3.shape == (63, 3) and np.sum(p3 < 0) == 9
    lo, hi = j.min(0), j.max(0)
    assert np.all(j3[:, :2] >= lo[:2] - 1e-12) and np.all(j3[:, :2] <= hi[:2] + 1e-12)
    for c in range(9):  # every copy is the original scaled by 1/3 and shifted
        part = j3[7 * c : 7 * (c + 1)]
        np.testing.assert_allclose((part - part[0]) * 3, j - j[0], atol=1e-12)
        np.testing.assert_array_equal(p3[7 * c : 7 * (c + 1)], np.where(p >= 0, p + 7 * c, -1))
    np.testing.assert_allclose(r3, np.tile(r / 3, 9))


def _wall(k, width=48, height=64):
    from jskel.config import load
    from jskel.render import camera_of

    exp = load("experiments/saguaro.yaml", [f"camera.width={width}", f"camera.height={height}", "object.accel=bvh",
                                            f"object.skeleton.replicate={k}", "camera.eye=[0.1, 3.3, 9.5]",
                                            "camera.target=[0.1, 3.3, 0]", "camera.fov_deg=40"])
    built = frusta.build(exp.objects[0].shape)
    return built, camera_of(exp).rays(anchor=built.anchor)


def test_traversal_work_grows_with_log_segments_at_fixed_coverage():
    """The saguaro wall of k x k copies (30 k^2 segments, about the same pixels covered): leaves
    tested per ray stay bounded and nodes visited per ray grow at most in proportion to log2 of
    the segment count (deterministic counts of the traversal, not timings)."""
    stats = {}
    for k in (1, 4, 16):
        built, rays = _wall(k)
        stats[30 * k * k] = frusta.traversal_stats(built, rays, chunk=4096)
    leaves = [s["leaves_per_ray_mean"] for s in stats.values()]
    nodes = np.array([s["nodes_per_ray_mean"] for s in stats.values()])
    logs = np.log2(np.array(list(stats)))
    assert max(leaves) < 2.0 * max(min(leaves), 0.5), leaves
    # nodes per ray against log2(segments): bounded by a line through the origin whose slope
    # the smallest scene sets, with a margin of 1.5 (a linear growth in segments fails by far)
    assert np.all(nodes <= 1.5 * max(nodes[0] / logs[0], 1.0) * logs), (nodes, logs)
    assert nodes[-1] > nodes[0]  # the tree did deepen


def test_memory_budget_shrinks_the_chunk_and_keeps_the_image():
    from jskel.config import load
    from jskel.render import render

    # block culling: the budget is the executor's, whatever the cast (the BVH's bins compile twice as long)
    base = ["camera.width=64", "camera.height=48", "render.chunk=2048", "render.progress=false", "object.accel=blocks"]
    exp = load("experiments/saguaro.yaml", base)
    plain = render(exp)
    assert "memory_budget" not in plain.run and plain.run["peak_host_mb"] > 0
    # a budget far above the need keeps the chunk and reports what XLA says the call needs
    roomy = render(load("experiments/saguaro.yaml", base + ["render.memory_mb=65536"]))
    need = roomy.run["memory_budget"]["tries"][0]["bytes"]
    assert roomy.run["memory_budget"]["chunk"] == 2048 and 0 < need <= 65536 * 2**20
    mb = need / 3 / 2**20
    small = render(load("experiments/saguaro.yaml", base + [f"render.memory_mb={mb}"]))
    mem = small.run["memory_budget"]
    assert mem["chunk"] < 2048 and mem["tries"][-1]["bytes"] <= int(mb * 2**20) < mem["tries"][0]["bytes"]
    np.testing.assert_array_equal(small.hits.t, plain.hits.t)
    np.testing.assert_array_equal(small.hits.prim, plain.hits.prim)


def test_a_budget_below_the_scene_is_an_error_naming_the_key():
    import jax.numpy as jnp

    from jskel.rays import make_rays
    from jskel.executor import chunk_for_budget

    params = jnp.zeros((1 << 19,), jnp.float32)  # 2 MiB that no chunk size can shed
    rays = make_rays(np.zeros((64, 3)), np.tile([0.0, 0.0, 1.0], (64, 1)))
    fn = lambda p, r: r.origins * p[0]  # noqa: E731
    with pytest.raises(ValueError, match=r"render.memory_mb: 1 MiB"):
        chunk_for_budget(fn, params, rays, 64, 2**20)
    assert chunk_for_budget(fn, params, rays, 64, 2**23)[0] == 64


def test_bench_cost_against_size_writes_rows_with_traversal_counts_and_a_plot(tmp_path, capsys):
    """``jskel bench`` with a sweep and no reference times each setting and, with ``stats``,
    adds the traversal counts (checked here against a direct call) and plots them."""
    import json

    from jskel import cli

    root = __import__("pathlib").Path(__file__).resolve().parent.parent
    spec = tmp_path / "size.yaml"
    spec.write_text(
        f"width: 48\nheight: 64\nruns: 1\nwarmup: 0\nscenes: [{root / 'experiments' / 'saguaro.yaml'}]\n"
        "set: [object.accel=bvh, 'camera.eye=[0.1, 3.3, 9.5]', 'camera.target=[0.1, 3.3, 0]', camera.fov_deg=40]\n"
        "sweep: {object.skeleton.replicate: [1, 4]}\nstats: true\ncast: true\npair_test: true\n"
    )
    out = tmp_path / "size.jsonl"
    assert cli.main(["bench", str(spec), "--out", str(out)]) == 0
    rows = [json.loads(x) for x in out.read_text().splitlines()]
    assert [r["primitives"] for r in rows] == [30, 480]
    # each row says what its compile_s was (each size is a new program: compiled, or loaded from a cache)
    assert all(sum(r["programs"].values()) >= 1 for r in rows)
    assert rows[0]["run"]["command"] == f"python -m jskel bench {spec} --out {out}"  # as typed, in every row
    assert out.with_suffix(".png").exists()
    for k, r in zip((1, 4), rows):
        # both rounded (render_s to 1e-4 s, us_per_ray to 1e-4 us)
        assert r["us_per_ray"] == pytest.approx(r["render_s_median"] / r["rays"] * 1e6, abs=0.5e-4 / r["rays"] * 1e6 + 1e-4)
        assert "hit_miss_pct" not in r  # no reference, no error columns
        want = frusta.traversal_stats(*_wall(k))
        assert r["nodes_per_ray_mean"] == pytest.approx(want["nodes_per_ray_mean"], abs=1e-3)
        assert r["leaves_per_ray_mean"] == pytest.approx(want["leaves_per_ray_mean"], abs=1e-3)
        # ``pair_test``: the (ray, segment) test timed alone, and the share of the cast its tests
        # per ray would take at that rate (the row's own figures, recomputed here)
        assert r["pair_tests_timed"] == 1 << 18 and r["pair_test_ns_median"] > 0 and r["pair_test_compile_s"] > 0
        per_ray = r.get("bin_tests_per_ray_mean", r["leaf_tests_per_ray_mean"])
        assert r["pair_test_share_of_cast"] == pytest.approx(per_ray * r["rays"] * r["pair_test_ns_median"] * 1e-9 / r["cast_s_median"], abs=1e-4)
    assert "rows" not in capsys.readouterr().err


def test_a_pair_test_of_a_representation_without_one_is_named():
    """``pair_test`` on a scene whose representation times no pair test (an implicit surface):
    a ConfigError naming the key and the representation, not a row without the figure."""
    from jskel.config import ConfigError, load
    from jskel.measure.bench import pair_test_row

    root = __import__("pathlib").Path(__file__).resolve().parent.parent
    exp = load(root / "experiments" / "gecko.yaml", ["camera.width=8", "camera.height=8"])
    with pytest.raises(ConfigError, match=r"pair_test: .*'implicit'"):
        pair_test_row(exp, {})


def test_tile_order_lists_tiles_and_squares_within_them():
    from jskel.camera import tile_order

    w, h, tile = 70, 40, 16  # partial tiles on the right and bottom edges
    order = tile_order(w, h, tile)
    assert sorted(order.tolist()) == list(range(w * h))
    ys, xs = np.divmod(order, w)
    # the first 256 rays are the top-left tile, and every aligned run of 4^j rays in it a square
    assert np.all(xs[:256] < 16) and np.all(ys[:256] < 16)
    for side in (2, 4, 8, 16):
        runs = side * side
        for k in range(0, 256, runs):
            x, y = xs[k : k + runs], ys[k : k + runs]
            assert x.max() - x.min() == side - 1 and y.max() - y.min() == side - 1
    tile_of = (ys // tile) * (-(-w // tile)) + xs // tile
    assert np.all(np.diff(tile_of) >= 0)  # tile by tile


def test_tiled_rays_are_the_camera_rays_permuted_and_the_inverse_undoes_the_order():
    """``Camera.tiled_rays`` (cached directions, broadcast origin) equals the camera's rays
    permuted by ``tile_order``, value for value, for two anchors (the cache keys on the camera
    only); ``tile_inverse`` puts tile-ordered values back in row-major order."""
    from jskel.camera import Camera, permute, tile_inverse, tile_order

    cam = Camera(np.array([1.0, 2.0, 9.0]), np.array([0.2, 0.5, 0.0]), np.array([0.0, 1.0, 0.0]), 35.0, 70, 40)
    order = tile_order(70, 40, 16)
    for anchor in (np.zeros(3), np.array([1e4, -3.0, 0.5])):
        want = permute(cam.rays(anchor=anchor), order)
        got = cam.tiled_rays(16, anchor=anchor)
        for a, b in zip(want, got):
            assert a.dtype == b.dtype and a.shape == b.shape
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    inv = tile_inverse(70, 40, 16)
    np.testing.assert_array_equal(order[inv], np.arange(70 * 40))


def test_packets_share_short_walks_on_coherent_rays_and_equal_per_ray_walks():
    """Packets of 256 camera rays in 16 x 16 squares: the same t and ids as per-ray walks, and
    the shared loop runs far fewer steps than 256 separate walks would (what makes it pay)."""
    from jskel.config import load
    from jskel.camera import permute, tile_order
    from jskel.render import camera_of

    exp = load("experiments/dancing_cacti.yaml", ["camera.width=64", "camera.height=48", "object.traversal=packets"])
    obj = exp.objects[0].shape
    built = frusta.build(obj)
    assert built.static.packet == 256 and built.static.traversal == "packets"
    rays = permute(camera_of(exp).rays(anchor=built.anchor), tile_order(64, 48, 64))
    st = frusta.traversal_stats(built, rays, chunk=1024)
    per_ray_steps = st["nodes_per_ray_mean"] + st["leaves_per_ray_mean"]
    assert st["packet_steps_mean"] < 0.06 * 256 * per_ray_steps, st
    shuffled = frusta.traversal_stats(built, permute(rays, np.random.default_rng(0).permutation(64 * 48)), chunk=1024)
    assert shuffled["nodes_per_ray_mean"] == st["nodes_per_ray_mean"]  # per-ray walks ignore the order
    assert st["packet_steps_mean"] < 0.5 * shuffled["packet_steps_mean"], (st, shuffled)

    O, D = camera_of(exp).ray_arrays()
    a = cast(built, O, D, culled=True)
    b = cast(frusta.build(obj.model_copy(update={"packet": 0})), O, D, culled=True)
    assert np.isfinite(a.t).mean() > 0.2
    np.testing.assert_array_equal(a.t, b.t)
    assert np.all((a.prim == b.prim) | (a.t == b.t))


def test_chunks_per_call_equal_one_chunk_per_call(rng):
    """``map_chunks`` with several chunks per compiled call (a loop over them, the CPU's
    default on big batches) returns what one chunk per call returns, bit for bit: the block-culled
    cast of a random tree (the conftest's padded shapes), 20 chunks of 512 rays run as 3 calls of 8 (the last call's 4 padding
    chunks skipped). Chunks per call are powers of two up to the group: a few programs for
    every batch size."""
    from conftest import batch_fn, frusta_object

    from jskel.rays import make_rays
    from jskel.executor import calls_grouping, map_chunks

    assert [calls_grouping(n, 16) for n in (1, 7, 8, 9, 15, 16, 17, 75, 192)] == [1, 1, 8, 16, 16, 16, 16, 16, 16]
    assert [calls_grouping(n, 64) for n in (7, 8, 9, 17, 33, 96)] == [1, 8, 16, 32, 64, 64]
    assert calls_grouping(20, 8) == 8 and calls_grouping(100, 1) == 1 and calls_grouping(40, 48) == 48
    j, r, p = random_tree(rng, 40)
    built = build_skeleton(j, r, p, accel="blocks")
    n = 20 * 512 - 100
    O = rng.uniform(j.min(0) - 1.0, j.max(0) + 1.0, (n, 3))
    D = rng.normal(size=(n, 3)) + (j.mean(0) - O)
    rays = make_rays(O - built.anchor, D / np.linalg.norm(D, axis=1, keepdims=True))
    fn = batch_fn(True)
    one = map_chunks(fn, frusta_object(built), rays, chunk=512, progress=False).out
    many = map_chunks(fn, frusta_object(built), rays, chunk=512, progress=False, group=8).out
    assert 0.05 < np.isfinite(one.t).mean() < 0.95
    for name in ("t", "position", "normal", "uv", "prim"):
        a, b = np.asarray(getattr(one, name)), np.asarray(getattr(many, name))
        assert a.shape == b.shape and a.shape[0] == n
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("chunking", [["render.chunk=2048"], ["render.chunk=256", "render.chunks_per_call=8"]])
def test_resident_cast_gives_the_render_hits_in_tile_order(chunking):
    """``probe.cast_resident`` (rays laid out as a render lays them out and placed on the device
    before the clock, results left there: how the Mitsuba peer is timed) casts the same rays as
    a render: 3,072 saguaro rays in calls of 2,048 (one chunk a call, the second padded; or
    8 chunks of 256 a call, the second call's last 4 chunks padding), put back in pixel order,
    give the render's hit or miss and segment for every pixel and its t within float32
    rounding (the cast alone and the render with shading are compiled apart)."""
    import jax

    from jskel import registry
    from jskel.probe.cast import cast_resident, resident_rays
    from jskel.config import load
    from jskel.camera import tile_inverse
    from jskel.render import render

    exp = load("experiments/saguaro.yaml", ["camera.width=64", "camera.height=48", "render.progress=false", *chunking])
    obj = exp.objects[0].shape
    want = render(exp).hits
    built = registry.get(obj.type).build(obj, np.float32)
    res = resident_rays(exp, built)
    assert (res.layout.n, res.layout.calls, res.layout.size) == (3072, 2, 2048)  # (one device in the tests)
    assert all(isinstance(a, jax.Array) for a in jax.tree_util.tree_leaves(res.calls))
    secs, outs = cast_resident(exp, built, res)
    assert secs > 0.0 and all(isinstance(a, jax.Array) for a in jax.tree_util.tree_leaves(outs))
    t, prim = (x[tile_inverse(64, 48, exp.render.tile)] for x in res.host_outputs(outs))
    hit = np.isfinite(want.t)
    assert 0.05 < hit.mean() < 0.9  # the saguaro covers about 9 % of this frame
    np.testing.assert_array_equal(np.isfinite(t), hit)
    np.testing.assert_array_equal(prim[hit], np.asarray(want.prim)[hit])
    np.testing.assert_allclose(t[hit], np.asarray(want.t)[hit], rtol=2e-6)
