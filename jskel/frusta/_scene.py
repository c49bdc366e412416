"""The frusta representation (Bhagvat et al. 2009): its build and the interface's functions
(cast, surface, intersect, albedo, inside, traversal stats), re-exported by ``jskel.frusta``.
The skeleton and its edits are ``_edits``'s, height maps ``_maps``'s, the device packing
``_pack``'s and the choice of traversal ``_dispatch``'s."""

from __future__ import annotations

from typing import NamedTuple, final

import jax
import jax.numpy as jnp
import numpy as np

from ..accel import nearest_tangent
from ..compile.host_eval import HostFn
from ..executor import size_bucket
from ..numerics import on_device
from ..interface import Built, Object, Preliminary, Representation
from ..wavefront import compact_map
from ..rays import FLAG_GRAZE, Hit, Rays
from ..textures import bilinear_wrap, load_height_map, load_texture
from ._accel import build_bvh, nearest_groups, shell_bvh, winner_ts
from ._build import FrustaArrays, _bucket, piece_bounds
from ._config import FrustaConfig
from ._dispatch import AUTO_BVH_SEGMENTS, _plain_search, _relief_search, _stats_batch, relief_cull_of, traversal_of
from ._edits import host_frusta, skeleton_arrays
from ._export import export_mesh
from ._intersect import Quality
from ._intersect import inside_one as _inside_one
from ._intersect import _finish, _segment_t, nearest_one
from ._maps import relief_memory
from ._pack import FrustaScene, Static, make_group
from ._relief import ReliefMaps, ReliefQuality, texel_slopes
from ._relief import make_relief_finish
from ._relief_method import make_relief_t


def build(cfg: FrustaConfig, dtype=np.float32) -> Built:
    """Host-side build: validate, cut, frame, split plain/relief, pad, cast. ValueError names the field."""
    arrays, topo, info, j, r, colors = host_frusta(cfg)
    s = arrays.h.shape[0]
    rel = cfg.relief
    grow = rel.thickness if rel is not None else 0.0
    rmax = r[:, None] + grow
    lo = np.min(j - rmax, axis=0)
    hi = np.max(j + rmax, axis=0)
    anchor = 0.5 * (lo + hi)  # of the joints' box, as before the pieces' reach was bounded (same float32 offsets)
    plo, phi = piece_bounds(arrays, grow)
    lo, hi = np.minimum(lo, plo), np.maximum(hi, phi)  # a piece past a bend reaches beyond its joints' spheres
    relief_ids = _relief_ids(rel, s)
    plain, plain_block = _plain_group(cfg, arrays, np.setdiff1d(np.arange(s), relief_ids), anchor, dtype)
    relief = maps = rq = None
    relief_block = 8
    if relief_ids.size:
        relief, relief_block, maps, memory = _relief_group(cfg, arrays, relief_ids, anchor, dtype)
        info = dict(info, memory=memory)
    seg_col = np.broadcast_to(np.asarray(cfg.color, np.float64), (s, 3)) if colors is None else colors[topo.seg_end]
    seg_col = np.concatenate([seg_col, np.zeros((_bucket(s) - s, 3))])  # rows of a size bucket: one program for similar skeletons
    tex = load_texture(cfg.texture) if cfg.texture is not None else np.ones((1, 1, 3))
    tex_size = np.array(tex.shape[:2], np.int32)
    # height and width padded to size buckets: a texture of similar size shares every program
    tex = np.pad(tex, ((0, size_bucket(tex.shape[0]) - tex.shape[0]), (0, size_bucket(tex.shape[1]) - tex.shape[1]), (0, 0)))
    scene = FrustaScene(
        plain=plain,
        relief=relief,
        maps=maps,
        colors=on_device(seg_col, dtype),
        texture=on_device(tex, dtype),
        tex_scale=on_device(cfg.texture_scale, dtype),
        tex_size=on_device(tex_size),
    )
    if rel is not None:
        rq = _relief_quality(rel, arrays, relief_ids, None if maps is None else maps.height.shape)
        info = dict(info, relief_uv=rq.uv)
    static = Static(Quality(normals=cfg.normals, block=plain_block), cfg.texture is not None, rq, relief_block,
                    "none" if cfg.accel == "none" else ("bvh" if plain is not None and plain.bvh is not None else "blocks"),
                    cfg.leaf, cfg.group, cfg.packet, traversal_of(cfg, s - relief_ids.size), cfg.kernel_block, cfg.kernel_warps,
                    (cfg.bin_packet, cfg.bin_candidates, cfg.bin_pairs, cfg.bin_group, float(cfg.bin_walk_ratio)),
                    relief_cull_of(rel, relief_ids.size))
    info = dict(info, segments=int(s), joints=int(j.shape[0]), relief_segments=int(relief_ids.size),
                accel=static.accel, traversal=static.traversal if static.accel == "bvh" else None)  # what ``auto`` chose
    return Built(scene, static, anchor, (lo, hi), info, primitives=int(s), surface_tolerance=_tolerance(cfg, arrays, relief_ids, dtype))


def _tolerance(cfg: FrustaConfig, arrays: FrustaArrays, relief_ids, dtype) -> float:
    """How far a returned hit may lie from the surface (``Built.surface_tolerance``, which
    ``jskel.spawn`` offsets secondary rays by): a side root is accepted up to 32 eps (h + r1 + r2)
    past a cutting plane (``_intersect._segment_t``'s slab slack), and a relief hit lies within
    its last bisection bracket, at most the segment's bounding diameter through the shell over
    ``steps`` 2^``bisection``. Without the slack a ray spawned along a cap at a grazing angle met
    the side's cone just past the cap's plane (``tests/test_spawn.py``)."""
    ext = arrays.h + arrays.r1 + arrays.r2
    tol = 32.0 * float(np.finfo(dtype).eps) * float(np.max(ext)) if ext.size else 0.0
    rel = cfg.relief
    if rel is not None and relief_ids.size:
        span = arrays.h[relief_ids] + 2.0 * (np.maximum(arrays.r1[relief_ids], arrays.r2[relief_ids]) + rel.thickness)
        tol = max(tol, float(np.max(span)) / rel.steps * 0.5**rel.bisection)
    return tol


def _relief_ids(rel, s: int) -> np.ndarray:
    """Sorted ids of the segments with relief (``object.relief.segments``; every segment when
    it is unset, none without ``object.relief``)."""
    if rel is None:
        return np.zeros(0, np.int64)
    if rel.segments is None:
        return np.arange(s)
    for i, sid in enumerate(rel.segments):
        if sid >= s:
            raise ValueError(f"object.relief.segments[{i}]: no segment {sid} (the skeleton has {s})")
    return np.unique(np.asarray(rel.segments, np.int64))


def _plain_group(cfg: FrustaConfig, arrays: FrustaArrays, ids, anchor, dtype):
    """(group, block size) of the plain segments ``ids`` ((None, 8) without any): with the BVH
    (``accel: bvh``, or ``auto`` from :data:`AUTO_BVH_SEGMENTS` segments) or block spheres."""
    if not ids.size:
        return None, 8
    accel = cfg.accel if cfg.accel != "auto" else ("bvh" if ids.size >= AUTO_BVH_SEGMENTS else "blocks")
    plain, block = make_group(arrays, ids, anchor, cfg.block, dtype, spheres=accel != "bvh")
    if accel == "bvh":
        plain = plain._replace(bvh=jax.tree_util.tree_map(on_device, _build_bvh_host(plain.frusta, cfg.leaf)))
    return plain, block


def _relief_group(cfg: FrustaConfig, arrays: FrustaArrays, ids, anchor, dtype):
    """(group, block size, height map, memory account) of the relief segments ``ids``: their
    block spheres bound the outer frusta of the shell (``relief.thickness``), Sec. 3-4."""
    rel = cfg.relief
    shell = np.zeros(arrays.h.shape[0])
    shell[ids] = rel.thickness
    relief, block = make_group(arrays, ids, anchor, cfg.block, dtype, shell)
    if relief_cull_of(rel, ids.size) != "blocks":
        relief = relief._replace(bvh=jax.tree_util.tree_map(on_device, _shell_bvh_host(relief.frusta, cfg.leaf)))
    height = load_height_map(rel.map)
    mip = None
    if rel.method == "exact":  # one (max, min) pair per pyramid cell: one gather reads both
        from ._relief_exact import pyramid

        mip = on_device(np.stack(pyramid(height, rel.v_mode)[:2], axis=-1))
    texels = on_device(height) if rel.storage == "uint8" else on_device(height, dtype)  # (float: 0..255, a traced leaf)
    maps = ReliefMaps(texels, on_device(rel.scale, dtype), on_device(texel_slopes(height), dtype),
                      on_device(np.int32(rel.steps)), on_device(np.int32(rel.bisection)), mip)
    return relief, block, maps, relief_memory(arrays, height, rel.scale, ids, pyramid_bytes=0 if mip is None else int(mip.size),
                                              texel_bytes=texels.dtype.itemsize)


def _relief_quality(rel, arrays: FrustaArrays, ids, map_shape) -> ReliefQuality:
    """The relief's static march options; ``uv: auto`` takes the approximate v where every
    relief segment's two cutting planes are parallel (where the paper says it is exact), else
    the exact one."""
    uv = rel.uv
    par = np.abs(np.sum(arrays.nb[ids] * arrays.nt[ids], -1)) >= 1.0 - 1e-12
    if uv == "auto":
        uv = "approximate" if np.all(par) else "exact"
    if rel.method != "exact":
        return ReliefQuality(uv, rel.early_exit, rel.v_mode)
    from ._relief_exact import pyramid_levels

    levels = () if map_shape is None else pyramid_levels(map_shape, rel.v_mode)  # (the map loaded once, by the group)
    return ReliefQuality(uv, rel.early_exit, rel.v_mode, "exact", levels)


# the tree of a build, evaluated by NumPy (``jskel.compile.host_eval``), not compiled for a single run
# (docs/choices.md#host-build); the device rebuild of an animated frame runs the same
# ``build_bvh`` inside its program
_build_bvh_host = HostFn(build_bvh, static_argnums=(1,))
_shell_bvh_host = HostFn(shell_bvh, static_argnums=(1,))


def _nearest_hit(a: Hit, b: Hit) -> Hit:
    closer = b.t < a.t
    return jax.tree_util.tree_map(lambda x, y: jnp.where(closer.reshape(closer.shape + (1,) * (x.ndim - closer.ndim)), y, x), a, b)


def _relief_flags(out: Hit, t_undecided) -> Hit:
    """``out`` with its flags: ``FLAG_GRAZE`` where a relief march could not exclude a crossing
    before the ray's nearest hit (any finite t_undecided on a miss), Bhagvat et al. 2009 Sec. 3
    and ``_relief._step_undecided``; 0 elsewhere. Only scenes with relief carry flags."""
    return out._replace(flags=jnp.where(t_undecided < out.t, FLAG_GRAZE, 0).astype(jnp.int32))


def intersect_one(scene: FrustaScene, static: Static, origin, direction, t_min, t_max) -> Hit:
    """Nearest hit of one ray with the plain and relief frusta of ``scene`` (brute force); with
    relief its flags (:func:`_relief_flags`)."""
    hits = []
    if scene.plain is not None:
        f = scene.plain.frusta
        t, s, c, i = nearest_one(f, _segment_t, origin, direction, t_min, t_max, static.quality.block)
        hits.append(_finish(f, origin, direction, t, s, c, i, static.quality.normals))
    if scene.relief is not None:
        f = scene.relief.frusta
        seg_fn = make_relief_t(scene.maps, static.relief)
        t, s, c, i, und = nearest_one(f, seg_fn, origin, direction, t_min, t_max, static.relief_block, undecided=True)
        hits.append(make_relief_finish(scene.maps, static.relief)(f, origin, direction, t, s, c, i))
    out = hits[0]
    for h in hits[1:]:
        out = _nearest_hit(out, h)
    return out if scene.relief is None else _relief_flags(out, und)


def intersect(scene: FrustaScene, static: Static, rays: Rays) -> Hit:
    """Batched :func:`intersect_one` (vmap over the ray axis)."""
    f = jax.vmap(lambda o, d, a, b: intersect_one(scene, static, o, d, a, b))
    return f(rays.origins, rays.directions, rays.t_min, rays.t_max)


class FrustaPayload(NamedTuple):
    """What :func:`surface` needs of a preliminary hit, per ray and per group present (plain,
    relief; None where absent): each group's nearest (t, s, code, index) (``_intersect``), the
    relief's with the least t where its march could not decide, fifth (``_relief``)."""

    plain: tuple | None
    relief: tuple | None


def cast(scene: FrustaScene, static: Static, rays: Rays) -> Preliminary:
    """First stage: the nearest (t, segment id) of every ray, plain segments through the linear
    BVH (``accel: bvh``; packets of ``packet`` consecutive rays share a traversal, or with
    ``packet: 0`` every ray walks alone, in vmapped groups) or by skipping blocks that no ray of
    the batch reaches (``blocks``); relief marched only for the (ray, segment) pairs whose ray
    enters a shell. The payload keeps each group's (t, s, code, index) for :func:`surface`.

    t and s differentiate in both modes (``jax.grad`` too) though the traversals are loops of
    data-dependent length: ``accel.nearest_tangent`` takes their derivative from the winning
    segment's closed form (``_accel.winner_ts``; the relief's implicit-function derivative),
    and leaves the traversal alone when nothing is differentiated."""
    o = rays.origins
    plain = relief = None
    t = jnp.full(o.shape[:1], jnp.inf, o.dtype)
    prim = jnp.full(o.shape[:1], -1, jnp.int32)
    if scene.plain is not None:
        g = scene.plain
        plain = nearest_tangent(_plain_search(static), lambda g_, r, out: winner_ts(g_.frusta, r, out))(g, rays)
        t = plain[0]
        prim = jnp.where(jnp.isfinite(t), g.frusta.sid[jnp.maximum(plain[3], 0)], -1)
    if scene.relief is not None:
        g = scene.relief
        relief = nearest_tangent(*_relief_search(static))(scene, rays)
        closer = relief[0] < t  # a tie keeps the plain segment, as _nearest_hit does
        t = jnp.where(closer, relief[0], t)
        prim = jnp.where(closer, g.frusta.sid[jnp.maximum(relief[3], 0)], prim)
    return Preliminary(t, prim.astype(jnp.int32), FrustaPayload(plain, relief))


def surface(scene: FrustaScene, static: Static, rays: Rays, pre: Preliminary) -> Hit:
    """Second stage: position, normal and uv of the winning segment of each ray (Eq. 6-8; the
    relief's from its height map, Sec. 3). A batch where no ray hit a plain segment finishes
    nothing (a ``lax.cond`` on the batch; compacting the hit rays instead changed the normals
    by an ulp against ``intersect``'s program, whose equality is tested)."""
    o, d = rays.origins, rays.directions
    hits = []
    if pre.payload.plain is not None:
        g = scene.plain
        t, s, c, i = pre.payload.plain
        fin = jax.vmap(_finish, in_axes=(None, 0, 0, 0, 0, 0, 0, None))
        z = jnp.zeros_like(o)
        miss = Hit(t, z + jnp.inf, z, z[:, :2], jnp.full(i.shape, -1, jnp.int32), None)  # masked_hit's sentinels
        hits.append(jax.lax.cond(jnp.any(jnp.isfinite(t)), lambda: fin(g.frusta, o, d, t, s, c, i, static.quality.normals), lambda: miss))
    if pre.payload.relief is not None:
        # only the rays that hit a relief segment (wavefront.compact_map): the finish (exact v,
        # the angle, four height samples and a cross product) on every ray was half of an
        # intersect at one march step (docs/choices.md#relief-finish)
        rt = pre.payload.relief[0]
        one = make_relief_finish(scene.maps, static.relief)
        fin = lambda sub: jax.vmap(one, in_axes=(None, 0, 0, 0, 0, 0, 0))(scene.relief.frusta, *sub)  # noqa: E731
        z = jnp.zeros_like(o)
        miss = Hit(jnp.full_like(rt, jnp.inf), z + jnp.inf, z, z[:, :2], jnp.full(rt.shape, -1, jnp.int32), None)  # masked_hit's sentinels
        hits.append(compact_map(fin, jnp.isfinite(rt), (o, d, *pre.payload.relief[:4]), miss, min(o.shape[0], 4096)))
    out = hits[0]
    for h in hits[1:]:
        out = _nearest_hit(out, h)
    return out if pre.payload.relief is None else _relief_flags(out, pre.payload.relief[4])


def occluded(scene: FrustaScene, static: Static, rays: Rays):
    """(N,) bool: does each ray meet a segment in ``(t_min, t_max]`` (shadow rays)? Plain
    segments cast by per-ray walks (``traversal: walks``) stop at the first leaf that holds a hit
    (``accel.nearest``'s ``any_hit``); the other traversals and relief answer from
    :func:`cast`'s nearest t."""
    if scene.relief is None and scene.plain is not None and static.accel == "bvh" and static.traversal == "walks":
        g = scene.plain
        return jnp.isfinite(nearest_groups(g.frusta, g.bvh, static.leaf, static.group, *rays, any_hit=True)[0])
    return jnp.isfinite(cast(scene, static, rays).t)


def intersect_batch(scene: FrustaScene, static: Static, rays: Rays) -> Hit:
    """Like :func:`intersect`, but skips work at the batch level: :func:`surface` of :func:`cast`."""
    return surface(scene, static, rays, cast(scene, static, rays))


def traversal_stats(built: Built, rays: Rays, chunk: int = 4096) -> dict:
    """Work per ray of the BVH traversal of the plain segments: mean and max internal nodes
    visited and leaves tested by each ray's own walk (deterministic counts, free of timing
    noise; issue 6's "cost per ray grows no faster than log(segments)"); with packets the
    mean steps of a packet's shared loop (nodes and leaves of the union of its rays' walks);
    with bins the segment tests per ray (each chunk's (packet, segment) pairs times the rays per
    packet, shared among the chunk's rays; a chunk cast by walks counts its rays' leaves), the
    mean length of a chunk's first list and the share of rays in walked chunks. Packets
    and bins depend on the given ray order (the render's: ``camera.tile_order``). Empty when the
    scene has no BVH."""
    from ..executor import map_chunks

    if built.static.accel != "bvh" or built.params.plain is None:
        return {}
    out = map_chunks(_stats_batch, Object(built.params, built.static, "frusta"), rays, chunk=chunk, progress=False).out
    visits, leaves = out[:2]
    stats = {"nodes_per_ray_mean": float(np.mean(visits)), "nodes_per_ray_max": int(np.max(visits)),
             "leaves_per_ray_mean": float(np.mean(leaves)), "leaves_per_ray_max": int(np.max(leaves)),
             "leaf_tests_per_ray_mean": float(np.mean(leaves)) * built.static.leaf}
    if built.static.traversal == "bins":  # per-ray shares of each batch's counts
        stats["bin_tests_per_ray_mean"] = float(np.mean(out[2]))
        stats["bin_batch_list_mean"] = float(np.mean(out[3]))
        stats["bin_walked_fraction"] = float(np.mean(out[4]))  # rays in batches cast by walks (``bin_walk_ratio``)
    elif len(out) > 2:  # packets: steps of each packet's shared loop (every ray carries its packet's)
        stats["packet_steps_mean"] = float(np.mean(out[2]))
    return stats


@jax.jit
def _pair_tests(seg, origins, directions, t_min, t_max):
    """t of every (segment, ray) pair: (S, N), segments outer, as the bins test a list."""
    return jax.vmap(jax.vmap(_segment_t, in_axes=(None, 0, 0, 0, 0)), in_axes=(0, None, None, None, None))(
        seg, origins, directions, t_min, t_max)[0]


def pair_test_seconds(built: Built, rays: Rays, segments: int = 64, ray_count: int = 4096, runs: int = 7, repeats: int = 20,
                      seed: int = 0) -> dict:
    """The (ray, segment) test alone (``_intersect._segment_t``, the innermost work of every
    traversal), timed on every pair of ``segments`` of the scene's plain segments and
    ``ray_count`` of the given rays, both drawn at random: a block whose parameters stay in
    cache, as a bin's list meets its packets' rays (the test is branch-free selects, so its cost
    does not depend on which pairs hit). Its compile apart, then the median of ``runs`` warm
    runs of ``repeats`` calls each, as nanoseconds per pair (one call takes about a
    millisecond, short enough for the machine's noise to move a median of single calls). With a row's pair tests per ray it says what share of a cast
    the tests take. Empty without plain segments."""
    import time

    if built.params.plain is None:
        return {}
    f = built.params.plain.frusta
    valid = np.nonzero(np.asarray(f.valid))[0]
    rng = np.random.default_rng(seed)
    ri, si = rng.integers(0, rays.size, ray_count), valid[rng.integers(0, len(valid), segments)]
    seg = jax.tree_util.tree_map(lambda a: jnp.asarray(np.asarray(a)[si]), f)
    args = (seg,) + tuple(jnp.asarray(np.asarray(a)[ri]) for a in (rays.origins, rays.directions, rays.t_min, rays.t_max))
    t = time.perf_counter()
    _pair_tests.lower(*args).compile()
    compile_s = time.perf_counter() - t
    _pair_tests(*args).block_until_ready()
    warm = []
    for _ in range(runs):  # host loop over timed runs
        t = time.perf_counter()
        for _ in range(repeats):
            out = _pair_tests(*args)
        out.block_until_ready()
        warm.append((time.perf_counter() - t) / repeats)
    pairs = segments * ray_count
    return {"pair_tests_timed": pairs, "pair_test_compile_s": round(compile_s, 4),
            "pair_test_ns_median": round(float(np.median(warm)) / pairs * 1e9, 3)}


def albedo(scene: FrustaScene, static: Static, hit: Hit):
    """Base colour at one hit: the texture through (u, v) (wrapping), else the segment colour."""
    if static.has_texture:
        return bilinear_wrap(scene.texture, hit.uv * scene.tex_scale, scene.tex_size)
    return scene.colors[jnp.maximum(hit.prim, 0)]


def inside(scene: FrustaScene, static: Static, point):
    """True when ``point`` (3,), relative to the anchor, is inside the skinned skeleton.

    For relief segments this is the inner frustum (the relief itself is not tested)."""
    groups = [g.frusta for g in (scene.plain, scene.relief) if g is not None]
    return jnp.any(jnp.stack([_inside_one(f, point) for f in groups]))


def traced_fields(scene: FrustaScene) -> dict:
    """What ``interface.checked_intersect`` verifies of traced frusta params, each segment by its
    skeleton segment id (``sid``; padding skipped): its base centre ``c1`` finite, its length
    ``h`` positive (joints that met), its radii at base and top ``r1``, ``r2`` not negative; a
    relief's march step count positive and its bisection count not negative."""
    out = {}
    if scene.maps is not None:
        out["relief.steps"] = (jnp.reshape(scene.maps.steps, (1,)), "positive", None, None)
        out["relief.bisection"] = (jnp.reshape(scene.maps.bisection, (1,)), "nonnegative", None, None)
    for prefix, g in (("segments", scene.plain), ("relief_segments", scene.relief)):
        if g is not None:
            f = g.frusta
            for name, kind in (("c1", "finite"), ("h", "positive"), ("r1", "nonnegative"), ("r2", "nonnegative")):
                out[f"{prefix}.{name}"] = (getattr(f, name), kind, f.valid, f.sid)
    return out


@final
class _Frusta(Representation, module=__name__):
    """The frusta representation as the registry hands it to the renderer."""

    name = "frusta"
    Config = FrustaConfig
    animated = True
    #: XLA:CPU's elemental emitters instead of its MLIR fusion emitters: render programs compile
    #: in about two thirds of the time, and run from 27 % faster to 3 % slower
    #: (docs/choices.md#elemental-emitters). Implicit and cell objects alone keep the default
    #: (theirs ran slower with it); in a scene with frusta they take the frusta's
    #: (``agreed_options``). And no YNNPACK fusions (jaxlib's default library for some
    #: elementwise and reduction fusions): the bins' per-block work ran in them several times
    #: slower than XLA's own loops, most under AVX2 (docs/choices.md#ynn-fusions)
    cpu_compiler_options = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": ""}

    @classmethod
    def compiler_options_for(cls, static):
        """The exact relief tracer's loop runs faster with the fusion emitters, for a longer
        compile (docs/choices.md#exact-relief-fusion-emitters). Set to True rather
        than left unset, so a scene whose other frusta ask for False falls back to XLA's default
        (True) instead of taking theirs."""
        if isinstance(static, Static) and static.relief is not None and static.relief.method == "exact":
            return {"xla_cpu_use_fusion_emitters": True}
        return cls.cpu_compiler_options

    @staticmethod
    def skeleton(cfg):
        """The skeleton's joints, radii and parents at the section's frame (its edits applied)."""
        return skeleton_arrays(cfg.skeleton, cfg.frame)[:3]

    @staticmethod
    def export_mesh(cfg, path, level: int = 2, field: str = "path") -> dict:
        """The frusta tessellated at ``level`` (``_export.export_mesh``)."""
        return export_mesh(path, cfg, level, field)

    @staticmethod
    def exits_from_inside(cfg) -> bool:
        """Plain frusta: both roots of the cone and the caps are tested against t_min, so a
        ray from inside gets its exit (a relief shell's march searches for entries only)."""
        return cfg.relief is None


REPRESENTATION = _Frusta()
