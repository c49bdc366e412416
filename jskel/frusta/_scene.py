"""Scene-level API of the frusta representation (re-exported by ``jskel.frusta``)."""

from __future__ import annotations

from typing import NamedTuple, final

import jax
import jax.numpy as jnp
import numpy as np

from ..accel import hold, nearest_tangent
from ..interface import Built, Object, Preliminary, Representation
from ..rays import Hit, Rays
from ..textures import bilinear_wrap, load_texture
from ._build import FrustaArrays as FrustaArrays
from ._build import build_frusta as build_frusta
from ._build import cutting_planes as cutting_planes
from ._build import minor_semi_axis as minor_semi_axis
from ._config import FrustaConfig as FrustaConfig
from ._config import SkeletonConfig as SkeletonConfig
from ._intersect import FrustaParams as FrustaParams
from ._intersect import Quality as Quality
from ._intersect import inside_one as _inside_one
from ._intersect import _finish, _segment_t, nearest_batch, nearest_batch_compact, nearest_one
from ._accel import build_bvh, nearest_bins, nearest_groups, nearest_packets, winner_ts
from ._kernel import nearest_kernel
from ._relief import ReliefMaps as ReliefMaps
from ._relief import ReliefQuality as ReliefQuality
from ._relief import enters_shell, make_relief_finish, make_relief_t
from ._skeleton import topology as topology
from ._skeleton import validate_skeleton as validate_skeleton

_SIDE_BRANCH_COLOR_PATH = "object.skeleton.colors"


class Group(NamedTuple):
    """Segments cast the same way, padded to blocks, with a bounding sphere per block."""

    frusta: FrustaParams
    block_c: jnp.ndarray  # (B,3) bounding sphere centre of each block of segments
    block_r: jnp.ndarray  # (B,) its radius
    bvh: object = None  # accel.BVH over the group's segments when ``accel: bvh``


class FrustaScene(NamedTuple):
    """Device pytree: plain and relief segments (either may be None) plus shading inputs.

    Segments with relief are split from plain ones at build time, so each ray batch runs the
    analytic test only over plain segments and the relief march only over relief segments:
    compaction at build time instead of masking per segment under vmap.
    """

    plain: Group | None
    relief: Group | None
    maps: ReliefMaps | None
    colors: jnp.ndarray  # (S, 3) linear RGB per segment id
    texture: jnp.ndarray  # (H, W, 3) linear RGB, (1, 1, 3) when unused
    tex_scale: jnp.ndarray  # (2,) repeats of the texture per unit u and v


class Static(NamedTuple):
    """Static options of a frusta object (what recompiles when it changes): quality, relief options, acceleration, leaf, group and packet sizes."""

    quality: Quality  # normals and the plain group's block size
    has_texture: bool
    relief: ReliefQuality | None = None
    relief_block: int = 8
    accel: str = "blocks"  # blocks | bvh (plain segments)
    leaf: int = 4
    group: int = 512
    packet: int = 256  # bvh: rays per shared traversal (0: per-ray walks in groups of ``group``)
    traversal: str = "packets"  # bvh: bins | packets | walks | kernel (resolved from ``object.traversal``)
    kernel_block: int = 32
    kernel_warps: int = 1
    bins: tuple = (64, 128, 256, 32, 1.5)  # bins: rays per packet, candidates and pairs per step, slots per group, walk ratio


def _pad(a: np.ndarray, n: int, fill) -> np.ndarray:
    pad = n - a.shape[0]
    if pad == 0:
        return a
    tail = np.broadcast_to(np.asarray(fill, a.dtype), (pad,) + a.shape[1:])
    return np.concatenate([a, tail], axis=0)


def to_params(arr: FrustaArrays, anchor: np.ndarray, block: int, dtype=np.float32, ids=None, shell=None) -> FrustaParams:
    """Cast host arrays (the rows ``ids``) to a padded device ``FrustaParams`` relative to ``anchor``."""
    ids = np.arange(arr.h.shape[0]) if ids is None else np.asarray(ids)
    s = ids.shape[0]
    n = max(-(-s // block) * block, block)
    fields = {k: np.asarray(v)[ids] for k, v in arr._asdict().items()}
    fields["c1"] = fields["c1"] - anchor[None, :]
    fields["shell"] = np.zeros(s) if shell is None else np.asarray(shell, np.float64)[ids]
    out = {}
    for k, v in fields.items():
        fill = {"m": (0.0, 1.0, 0.0), "u": (1.0, 0.0, 0.0), "w": (0.0, 0.0, 1.0), "h": 1.0, "nb": (0.0, 1.0, 0.0), "nt": (0.0, 1.0, 0.0), "dt": 1.0}.get(k, 0)
        v = _pad(np.asarray(v), n, fill)
        out[k] = jnp.asarray(v, dtype=jnp.bool_ if v.dtype == bool else dtype)
    out["valid"] = jnp.asarray(np.arange(n) < s)
    out["sid"] = jnp.asarray(_pad(ids.astype(np.int32), n, -1))
    return FrustaParams(**out)


def _block_size(cfg_block: int, count: int) -> int:
    """A small group gets a smaller block, so a well of 8 segments is not padded to 64."""
    return int(min(cfg_block, max(8, 1 << int(np.ceil(np.log2(max(count, 1)))))))


def make_group(arr: FrustaArrays, ids, anchor, cfg_block: int, dtype, shell=None, spheres: bool = True) -> tuple[Group, int]:
    """Device arrays of the segments ``ids`` (plain or relief): their padded params and block
    bounding spheres (``spheres=False``: one dummy sphere, for a group cast through the BVH,
    which never reads them: their host loop over blocks would be wasted work every frame);
    returns (group, block size used)."""
    block = _block_size(cfg_block, len(ids))
    params = to_params(arr, anchor, block, dtype, ids, shell)
    sub = FrustaArrays(*(np.asarray(v)[ids] for v in arr))
    if shell is not None:  # bound the outer frusta of the shell
        t = np.asarray(shell)[ids]
        sub = sub._replace(r1=sub.r1 + t, r2=sub.r2 + t)
    bc, br = block_spheres(sub, anchor, block) if spheres else (np.zeros((0, 3)), np.zeros(0))
    if bc.shape[0] == 0:
        bc, br = np.zeros((1, 3)), np.full(1, -1.0)
    return Group(params, jnp.asarray(bc, dtype), jnp.asarray(br, dtype)), block


def rim_points(arr: FrustaArrays, n_ang: int = 64) -> np.ndarray:
    """(S, 2*n_ang, 3) points where generators meet the two cutting planes (host, float64).

    The clipped frustum is the convex hull of its two elliptical cuts, so bounds of these points
    (grown by the chord sag 1 - cos(pi / n_ang)) bound the frustum (Sec. 2.6 uses pyramids).
    """
    ang = np.linspace(0, 2 * np.pi, n_ang, endpoint=False)
    rad = np.cos(ang)[None, :, None] * arr.u[:, None, :] + np.sin(ang)[None, :, None] * arr.w[:, None, :]
    k = (arr.r2 - arr.r1) / arr.h
    base = arr.c1[:, None, :] + arr.r1[:, None, None] * rad
    dirn = arr.m[:, None, :] + k[:, None, None] * rad
    out = []
    for n, dist in ((arr.nb, arr.db), (arr.nt, arr.dt)):
        den = np.einsum("sk,sak->sa", n, dirn)
        y = (dist[:, None] - np.einsum("sk,sak->sa", n, base - arr.c1[:, None, :])) / np.where(den == 0, 1.0, den)
        out.append(base + y[..., None] * dirn)
    return np.concatenate(out, axis=1)


def block_spheres(arr: FrustaArrays, anchor: np.ndarray, block: int):
    """Bounding sphere (centre relative to anchor, radius) of each block of segments."""
    pts = rim_points(arr) - anchor
    s = pts.shape[0]
    n = -(-s // block) * block
    sag = 1.0 - np.cos(np.pi / 64)
    rmax = np.maximum(arr.r1, arr.r2)
    cs, rs = [], []
    for i in range(0, n, block):  # host loop over blocks at build time
        p = pts[i : i + block].reshape(-1, 3)
        if p.shape[0] == 0:
            cs.append(np.zeros(3))
            rs.append(-1.0)  # padding block: no ray touches it
            continue
        lo, hi = p.min(0), p.max(0)
        c = 0.5 * (lo + hi)
        r = np.sqrt(np.max(np.sum((p - c) ** 2, -1))) + 2 * sag * float(np.max(rmax[i : i + block])) + 1e-6 * (1 + np.linalg.norm(c))
        cs.append(c)
        rs.append(r)
    return np.array(cs), np.array(rs)


def frusta_from_skeleton(joints, radii, parents, *, twist_deg=0.0, match_minor_axes=False, path="object.skeleton"):
    """Validate a skeleton and build its frusta on the host (float64). Returns (arrays, topo, info)."""
    j, r, p = validate_skeleton(joints, radii, parents, path)
    topo = topology(j, p, path)
    arrays, info = build_frusta(j, r, topo, twist_turns=twist_deg / 360.0, match_minor_axes=match_minor_axes)
    return arrays, topo, info


ANIMATED = ("dancing_cacti",)


def skeleton_arrays(sk: SkeletonConfig, frame: float = 0.0):
    """(joints (J, 3), radii (J,), parents (J,), colours (J, 3) or None) of a skeleton section at
    animation ``frame``: the explicit arrays, or the procedural generator's, with ``scale``,
    ``offset``, ``subdivide`` and ``replicate`` applied (float64, world units)."""
    if sk.procedural is not None:
        from ..scenes import generate

        opts = dict(sk.options)
        if sk.procedural in ANIMATED:
            opts.setdefault("frame", frame)
        j, r, p, colors = generate(sk.procedural, sk.seed, opts)
    else:
        j = np.asarray(sk.joints, np.float64)
        r = np.asarray(sk.radii, np.float64)
        p = np.asarray(sk.parents, np.int64)
        colors = None if sk.colors is None else np.asarray(sk.colors, np.float64)
        if colors is not None and colors.shape[0] != j.shape[0]:
            raise ValueError(f"{_SIDE_BRANCH_COLOR_PATH}: has {colors.shape[0]} entries for {j.shape[0]} joints")
    j = j * sk.scale + np.asarray(sk.offset, np.float64)
    r = r * sk.scale
    if sk.subdivide > 1:
        j, r, p, colors = subdivide_skeleton(j, r, p, colors, sk.subdivide)
    if sk.replicate > 1:
        j, r, p, colors = replicate_skeleton(j, r, p, colors, sk.replicate)
    return j, r, p, colors


def replicate_skeleton(joints, radii, parents, colors, k: int):
    """k x k copies of a skeleton, each scaled by 1/k about its box's (x, y) minimum corner and
    placed on a k x k grid over the original's x-y extent (z unchanged in the mean). Copy c has
    joints ``c * J .. (c + 1) * J - 1`` with its parents shifted by ``c * J``."""
    lo, hi = joints.min(0), joints.max(0)
    ext = hi - lo
    nj = joints.shape[0]
    cells = np.stack(np.meshgrid(np.arange(k), np.arange(k), indexing="ij"), -1).reshape(-1, 2)  # (k^2, 2)
    shift = np.zeros((cells.shape[0], 3))
    shift[:, :2] = cells * ext[None, :2] / k
    centre_z = 0.5 * (lo[2] + hi[2])
    local = (joints - np.array([lo[0], lo[1], centre_z])) / k + np.array([lo[0], lo[1], centre_z])
    j = (local[None] + shift[:, None, :]).reshape(-1, 3)
    p = np.asarray(parents)
    pp = np.where(p[None, :] >= 0, p[None, :] + (np.arange(cells.shape[0]) * nj)[:, None], -1).reshape(-1)
    cols = None if colors is None else np.tile(colors, (cells.shape[0], 1))
    return j, np.tile(radii / k, cells.shape[0]), pp, cols


def subdivide_skeleton(joints, radii, parents, colors, n: int):
    """Every segment (parent -> child) split into ``n`` collinear pieces: n - 1 new joints on the
    segment, radii linearly interpolated, colours of the child. The original joints keep their
    indices; the new ones follow, ``n - 1`` per child joint in child order. Collinear joints get
    cutting planes perpendicular to the axis (Eq. 3-5's bisector), so the surface is unchanged."""
    p = np.asarray(parents)
    child = np.nonzero(p >= 0)[0]
    nj = joints.shape[0]
    if child.size == 0:
        return joints, radii, p, colors
    f = (np.arange(1, n) / n)[None, :]  # (1, n-1)
    a, b = joints[p[child]], joints[child]
    new_j = (a[:, None, :] + f[..., None] * (b - a)[:, None, :]).reshape(-1, 3)
    new_r = (radii[p[child], None] + f * (radii[child] - radii[p[child]])[:, None]).reshape(-1)
    ids = nj + np.arange(child.size * (n - 1)).reshape(child.size, n - 1)
    new_p = np.concatenate([p[child][:, None], ids[:, :-1]], axis=1).reshape(-1)
    out_p = p.copy()
    out_p[child] = ids[:, -1]
    cols = None if colors is None else np.concatenate([colors, np.repeat(colors[child], n - 1, axis=0)])
    return np.concatenate([joints, new_j]), np.concatenate([radii, new_r]), np.concatenate([out_p, new_p]), cols


RELIEF_TEXTURES = ("brick", "gravel", "grass")


def load_height_map(name: str) -> np.ndarray:
    """An 8-bit height map: a scikit-image texture photograph by name, or an image file."""
    if name in RELIEF_TEXTURES:
        import skimage.data

        img = np.asarray(getattr(skimage.data, name)())
    else:
        import imageio.v3 as iio

        try:
            img = np.asarray(iio.imread(name))
        except Exception as e:  # noqa: BLE001 - any reader failure is a bad config value
            raise ValueError(f"object.relief.map: cannot read image {name!r} (or name one of {', '.join(RELIEF_TEXTURES)}): {e}") from None
    if img.ndim == 3:
        img = img[..., :3].mean(-1)
    if img.dtype != np.uint8:
        img = img.astype(np.float64)
        hi = img.max()
        img = np.round(255.0 * img / (hi if hi > 1.0 else 1.0))
    if img.ndim != 2 or min(img.shape) < 2:
        raise ValueError(f"object.relief.map: need a 2D image of at least 2x2 texels (got shape {img.shape})")
    return np.clip(img, 0, 255).astype(np.uint8)


def relief_memory(arr: FrustaArrays, height: np.ndarray, scale, relief_ids, dtype_bytes: int = 4) -> dict:
    """Bytes of the representation beside an equivalent displaced triangle mesh (Sec. 4).

    The mesh samples each relief segment at the height map's texel density (one vertex per
    texel of the tiled map over the segment: W * scale_u by H * scale_v), with float32
    positions (12 B) and two triangles per vertex (24 B of int32 indices).
    """
    s = arr.h.shape[0]
    per_seg = 3 + 3 + 3 + 3 + 1 + 1 + 1 + 3 + 1 + 3 + 1 + 1 + 1 + 1  # floats in FrustaParams
    frusta_b = s * per_seg * dtype_bytes
    maps_b = int(height.size)  # uint8
    hh, ww = height.shape
    verts = len(relief_ids) * (ww * float(scale[0])) * (hh * float(scale[1]))
    mesh_b = int(verts * 12 + 2 * verts * 12)
    return {"frusta_bytes": int(frusta_b), "relief_map_bytes": maps_b, "representation_bytes": int(frusta_b + maps_b),
            "mesh_vertices": int(verts), "mesh_triangles": int(2 * verts), "mesh_bytes": mesh_b}


def host_frusta(cfg: FrustaConfig):
    """World-space float64 frusta of an object config: (arrays, topo, info, joints, radii, colors)."""
    j, r, p, colors = skeleton_arrays(cfg.skeleton, cfg.frame)
    arrays, topo, info = frusta_from_skeleton(j, r, p, twist_deg=cfg.twist_deg, match_minor_axes=cfg.match_minor_axes)
    return arrays, topo, info, j, r, colors


def build(cfg: FrustaConfig, dtype=np.float32) -> Built:
    """Host-side build: validate, cut, frame, split plain/relief, pad, cast. ValueError names the field."""
    arrays, topo, info, j, r, colors = host_frusta(cfg)
    s = arrays.h.shape[0]
    rel = cfg.relief
    grow = rel.thickness if rel is not None else 0.0
    rmax = r[:, None] + grow
    lo = np.min(j - rmax, axis=0)
    hi = np.max(j + rmax, axis=0)
    anchor = 0.5 * (lo + hi)
    shell = np.zeros(s)
    relief_ids = np.zeros(0, np.int64)
    if rel is not None:
        if rel.segments is None:
            relief_ids = np.arange(s)
        else:
            for i, sid in enumerate(rel.segments):
                if sid >= s:
                    raise ValueError(f"object.relief.segments[{i}]: no segment {sid} (the skeleton has {s})")
            relief_ids = np.unique(np.asarray(rel.segments, np.int64))
        shell[relief_ids] = rel.thickness
    plain_ids = np.setdiff1d(np.arange(s), relief_ids)
    plain = relief = maps = None
    plain_block = relief_block = 8
    if plain_ids.size:
        accel = cfg.accel if cfg.accel != "auto" else ("bvh" if plain_ids.size >= AUTO_BVH_SEGMENTS else "blocks")
        plain, plain_block = make_group(arrays, plain_ids, anchor, cfg.block, dtype, spheres=accel != "bvh")
        if accel == "bvh":
            plain = plain._replace(bvh=_build_bvh_jit(plain.frusta, cfg.leaf))
    if relief_ids.size:
        relief, relief_block = make_group(arrays, relief_ids, anchor, cfg.block, dtype, shell)
        height = load_height_map(rel.map)
        maps = ReliefMaps(jnp.asarray(height), jnp.asarray(rel.scale, dtype))
        info = dict(info, memory=relief_memory(arrays, height, rel.scale, relief_ids))
    seg_col = np.broadcast_to(np.asarray(cfg.color, np.float64), (s, 3)) if colors is None else colors[topo.seg_end]
    tex = load_texture(cfg.texture) if cfg.texture is not None else np.ones((1, 1, 3))
    scene = FrustaScene(
        plain=plain,
        relief=relief,
        maps=maps,
        colors=jnp.asarray(seg_col, dtype),
        texture=jnp.asarray(tex, dtype),
        tex_scale=jnp.asarray(cfg.texture_scale, dtype),
    )
    rq = None
    if rel is not None:
        uv = rel.uv
        if uv == "auto":
            par = np.abs(np.sum(arrays.nb[relief_ids] * arrays.nt[relief_ids], -1)) >= 1.0 - 1e-12
            uv = "approximate" if np.all(par) else "exact"
        rq = ReliefQuality(rel.steps, rel.bisection, uv, rel.early_exit, rel.v_mode)
        info = dict(info, relief_uv=uv)
    static = Static(Quality(normals=cfg.normals, block=plain_block), cfg.texture is not None, rq, relief_block,
                    "none" if cfg.accel == "none" else ("bvh" if plain is not None and plain.bvh is not None else "blocks"),
                    cfg.leaf, cfg.group, cfg.packet, traversal_of(cfg), cfg.kernel_block, cfg.kernel_warps,
                    (cfg.bin_packet, cfg.bin_candidates, cfg.bin_pairs, cfg.bin_group, float(cfg.bin_walk_ratio)))
    info = dict(info, segments=int(s), joints=int(j.shape[0]), relief_segments=int(relief_ids.size))
    return Built(scene, static, anchor, (lo, hi), info, primitives=int(s))


_build_bvh_jit = jax.jit(build_bvh, static_argnums=1)


def traversal_of(cfg: FrustaConfig) -> str:
    """``object.traversal`` resolved: ``auto`` is the Pallas kernel on an accelerator and packet
    candidate lists (``bins``) on the CPU. On the H100 at 1024x768 the kernel took 13-16 ms on
    the palm, oasis and cacti, XLA's per-ray walk over the whole frame 48-162 ms, and packets
    4.6-9.2 s (a ``lax.map`` of scalar loops is bound by launches there). On the 2-core CPU bins
    beat the BVH packets on every scene of ``experiments/bench_scale_bins.yaml`` (README); a
    render of ``experiments/scene_cacti.yaml`` (``--set objects.1.shape.traversal=...``), whose
    shadow and reflection rays reach the cacti too, was faster with bins as well (one warm
    render each way, not a committed bench)."""
    if cfg.traversal != "auto":
        return cfg.traversal
    if jax.default_backend() != "cpu":
        return "kernel"
    return "bins"

# below this many plain segments the block scan beat the BVH (256x192: the 8-segment well 0.11 s
# with blocks, 0.16 s with the tree; the 30-segment saguaro 0.24 s vs 0.10 s)
AUTO_BVH_SEGMENTS = 16


def _nearest_hit(a: Hit, b: Hit) -> Hit:
    closer = b.t < a.t
    return jax.tree_util.tree_map(lambda x, y: jnp.where(closer.reshape(closer.shape + (1,) * (x.ndim - closer.ndim)), y, x), a, b)


def intersect_one(scene: FrustaScene, static: Static, origin, direction, t_min, t_max) -> Hit:
    """Nearest hit of one ray with the plain and relief frusta of ``scene`` (brute force)."""
    hits = []
    if scene.plain is not None:
        f = scene.plain.frusta
        t, s, c, i = nearest_one(f, _segment_t, origin, direction, t_min, t_max, static.quality.block)
        hits.append(_finish(f, origin, direction, t, s, c, i, static.quality.normals))
    if scene.relief is not None:
        f = scene.relief.frusta
        seg_fn = make_relief_t(scene.maps, static.relief)
        t, s, c, i = nearest_one(f, seg_fn, origin, direction, t_min, t_max, static.relief_block)
        hits.append(make_relief_finish(scene.maps, static.relief)(f, origin, direction, t, s, c, i))
    out = hits[0]
    for h in hits[1:]:
        out = _nearest_hit(out, h)
    return out


def intersect(scene: FrustaScene, static: Static, rays: Rays) -> Hit:
    """Batched :func:`intersect_one` (vmap over the ray axis)."""
    f = jax.vmap(lambda o, d, a, b: intersect_one(scene, static, o, d, a, b))
    return f(rays.origins, rays.directions, rays.t_min, rays.t_max)


class FrustaPayload(NamedTuple):
    """What :func:`surface` needs of a preliminary hit, per ray and per group present (plain,
    relief; None where absent): each group's nearest (t, s, code, index) (``_intersect``)."""

    plain: tuple | None
    relief: tuple | None


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
    """(t, s, code, idx) of a batch against the relief segments (marched only for the (ray,
    segment) pairs whose ray enters a shell), and its closed-form ``winner``: the march and
    bisection of the winning segment alone, differentiated by the implicit-function theorem
    (``_relief``)."""

    def search(sc: FrustaScene, rays: Rays):
        seg_fn = make_relief_t(sc.maps, static.relief)
        g, cap = sc.relief, min(rays.origins.shape[0], 4096)
        return tuple(nearest_batch_compact(g.frusta, g.block_c, g.block_r, enters_shell, seg_fn, *rays, static.relief_block, cap))

    def winner(sc: FrustaScene, rays: Rays, out):
        t, s, code, idx = out
        hit = jnp.isfinite(t)
        seg = jax.tree_util.tree_map(lambda x: x[jnp.maximum(idx, 0)], sc.relief.frusta)
        seg, o, d = hold(hit, (seg, rays.origins, rays.directions))  # (the maps are shared by every ray)
        tt, ss, _ = jax.vmap(make_relief_t(sc.maps, static.relief))(seg, o, d, rays.t_min, rays.t_max)
        return tt, ss, None, None

    return search, winner


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
        fin = jax.vmap(make_relief_finish(scene.maps, static.relief), in_axes=(None, 0, 0, 0, 0, 0, 0))
        hits.append(fin(scene.relief.frusta, o, d, *pre.payload.relief))
    out = hits[0]
    for h in hits[1:]:
        out = _nearest_hit(out, h)
    return out


def intersect_batch(scene: FrustaScene, static: Static, rays: Rays) -> Hit:
    """Like :func:`intersect`, but skips work at the batch level: :func:`surface` of :func:`cast`."""
    return surface(scene, static, rays, cast(scene, static, rays))


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


def albedo(scene: FrustaScene, static: Static, hit: Hit):
    """Base colour at one hit: the texture through (u, v) (wrapping), else the segment colour."""
    if static.has_texture:
        return bilinear_wrap(scene.texture, hit.uv * scene.tex_scale)
    return scene.colors[jnp.maximum(hit.prim, 0)]


def inside(scene: FrustaScene, static: Static, point):
    """True when ``point`` (3,), relative to the anchor, is inside the skinned skeleton.

    For relief segments this is the inner frustum (the relief itself is not tested)."""
    groups = [g.frusta for g in (scene.plain, scene.relief) if g is not None]
    return jnp.any(jnp.stack([_inside_one(f, point) for f in groups]))


@final
class _Frusta(Representation, module=__name__):
    """The frusta representation as the registry hands it to the renderer."""

    name = "frusta"
    Config = FrustaConfig

    @staticmethod
    def exits_from_inside(cfg) -> bool:
        """Plain frusta: both roots of the cone and the caps are tested against t_min, so a
        ray from inside gets its exit (a relief shell's march searches for entries only)."""
        return cfg.relief is None


REPRESENTATION = _Frusta()
