"""Scene-level API of the implicit representation (re-exported by ``jskel.implicit``)."""

from __future__ import annotations

from typing import NamedTuple, final

import jax
import jax.numpy as jnp
import numpy as np

from ..interface import Built, Representation
from ..rays import Hit, Rays, masked_hit
from ..wavefront import compact_map
from ._config import ImplicitConfig as ImplicitConfig
from ..numerics import dot3, safe_div, safe_sqrt
from ._field import Displace as Displace
from ._field import Prims as Prims
from ._field import Shape as Shape
from ._field import shaped_field as shaped_field
from ._field import kernel
from ._field import field as field
from ._field import gradient as gradient
from ._field import lipschitz as lipschitz
from ._trace import OVERFLOW as OVERFLOW
from ._trace import STEP_CAP as STEP_CAP
from ._trace import Quality as Quality
from ._trace import Tuning as Tuning
from ._trace import blocks_used, cull, surface_one, trace_one


class Skin(NamedTuple):
    """Texture skinning inputs for one frame (Sec. 6.1, Alg. 3): per bone the posed segment
    (head, tail), its weight radius, and the rigid map from the posed to the rest pose."""

    head: jnp.ndarray  # (B,3)
    tail: jnp.ndarray  # (B,3)
    influence: jnp.ndarray  # (B,)
    to_rest: jnp.ndarray  # (B,3,4)


class Projector(NamedTuple):
    """K texture projectors (Sec. 6, 6.1): the local ones in config order, then the model's
    global one (region radius inf). A rest-pose point takes the first whose region holds it."""

    origin: jnp.ndarray  # (K,3)
    axis: jnp.ndarray  # (K,3) unit
    up: jnp.ndarray  # (K,3) unit, perpendicular to axis
    scale: jnp.ndarray  # (K,2)
    region_c: jnp.ndarray  # (K,3) rest-pose region centre (relative to the anchor)
    region_r: jnp.ndarray  # (K,) its radius; inf: everywhere


class ImplicitScene(NamedTuple):
    """Device arrays of an implicit model: primitives, tuning values, colour, skin, projectors and their textures, primitive ids."""

    prims: Prims
    tune: Tuning
    color: jnp.ndarray  # (3,)
    skin: Skin
    projector: Projector
    texture: jnp.ndarray  # (K,H,W,3) linear RGB per projector, zero-padded to the largest
    tex_size: jnp.ndarray  # (K,2) int32 (H, W) of each projector's texture
    prim_id: jnp.ndarray  # (N+1,) the config's index of each (Morton-sorted) primitive; -1: padding


class Static(NamedTuple):
    """Static options of an implicit model: tracer quality, projector kinds and which are textured."""

    quality: Quality
    projector: tuple[str, ...]  # planar | cylindrical | spherical per projector; () for none
    textured: tuple[bool, ...]  # per projector: it carries a texture (else the model colour)


def _pad(x, n, fill=0.0):
    pad = n - x.shape[0]
    return x if pad == 0 else np.concatenate([x, np.broadcast_to(np.asarray(fill, x.dtype), (pad,) + x.shape[1:])])


def _max_field_estimate(a, b, ra, rb) -> float:
    """max F over the skeleton (host, float64): F at every ball's centre and 9 points along
    every tube (a lower bound of the true maximum, used to reject T >= max F). Only primitives
    whose influence sphere holds a point add to F there, so the pairs come from a k-d tree over
    the spheres' centres (scipy): O(P) pairs for a model of many small primitives, where
    testing every pair is O(P^2) (the whole build took 1.0 s at 5,000 metaballs, 0.009 s now)."""
    from scipy.spatial import cKDTree

    s = np.linspace(0, 1, 9)
    ball = np.all(a == b, axis=1)
    pts = np.concatenate([a[ball], (a[~ball][:, None, :] + s[None, :, None] * (b - a)[~ball][:, None, :]).reshape(-1, 3)])
    centre = 0.5 * (a + b)
    reach = 0.5 * np.linalg.norm(b - a, axis=1) + np.maximum(ra, rb)
    pairs = cKDTree(centre).sparse_distance_matrix(cKDTree(pts), float(np.max(reach)), output_type="ndarray")
    i, j = pairs["i"], pairs["j"]
    f = np.zeros(len(pts))
    for k in range(0, len(i), 1 << 20):
        pi, pj = i[k : k + (1 << 20)], j[k : k + (1 << 20)]
        ab = (b - a)[pi]
        ax = pts[pj] - a[pi]
        den = np.sum(ab * ab, -1)
        t = np.clip(np.where(den > 0, np.sum(ax * ab, -1) / np.where(den > 0, den, 1), 0), 0, 1)
        d = ax - t[:, None] * ab
        r2 = np.sum(d * d, -1)
        R = ra[pi] + (rb - ra)[pi] * t
        q = np.where(R > 0, r2 / np.where(R > 0, R * R, 1), 1)
        f += np.bincount(pj, np.where(q < 1, (1 - q) ** 2, 0), minlength=len(pts))
    return float(np.max(f))


def morton_order(points: np.ndarray) -> np.ndarray:
    """Stable order of points (N,3) along a 30-bit Morton curve over their bounding cube (host):
    neighbours in the order are neighbours in space, so blocks of consecutive primitives have
    tight bounding spheres (``_trace.block_spheres``). One scale for all axes: a thin slab must
    not spend the curve's leading bits on its thin axis."""
    lo = points.min(0)
    ext = float(np.max(points.max(0) - lo))
    q = np.clip((points - lo) / max(ext, 1e-300) * 1023, 0, 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def expand(cfg: ImplicitConfig) -> ImplicitConfig:
    """A procedural model with a rig becomes explicit balls, tubes and bones (validated)."""
    from ._models import RIGGED

    if cfg.procedural in RIGGED:
        extra = RIGGED[cfg.procedural](cfg.seed, dict(cfg.options))
        data = cfg.model_dump()
        data.update(procedural=None, **extra)
        return ImplicitConfig.model_validate(data)
    return cfg


def primitives(cfg: ImplicitConfig, frame: float | None = None):
    """Host float64 (a, b, ra, rb) in world units at ``frame`` (default ``cfg.frame``), plus the
    rig: (heads, tails, influence, M (B,4,4) posed-from-rest) or None without bones."""
    from ._anim import apply, bone_order, pose

    frame = cfg.frame if frame is None else frame
    rig = None
    if cfg.procedural is not None:
        from ._models import MODELS

        a, b, ra, rb = MODELS[cfg.procedural](cfg.seed, dict(cfg.options))
        bone_of = -np.ones(a.shape[0], np.int64)
        groups = [("main", f"procedural[{i}]") for i in range(a.shape[0])]
    else:
        names = [bn.name for bn in cfg.bones]
        order = bone_order(names, [bn.parent for bn in cfg.bones])
        index = {n: i for i, n in enumerate(names)}
        items = [(bl.center, bl.center, bl.radius, bl.radius, bl.bone, f"balls[{i}]", bl.group) for i, bl in enumerate(cfg.balls)]
        items += [(t.a, t.b, t.radius_a, t.radius_b, t.bone, f"tubes[{i}]", t.group) for i, t in enumerate(cfg.tubes)]
        items += [(bn.head, bn.tail, bn.tube[0], bn.tube[1], bn.name, f"bones[{i}].tube", bn.group) for i, bn in enumerate(cfg.bones) if bn.tube is not None]
        for *_, bone, where, _g in items:
            if bone is not None and bone not in index:
                raise ValueError(f"object.{where}.bone: unknown bone {bone!r} (bones: {', '.join(names) or 'none'})")
        for i, (*_, where, _g) in enumerate(items):
            if items[i][2] == 0 and items[i][3] == 0:
                raise ValueError(f"object.{where}: both radii are 0")
        a = np.array([it[0] for it in items], np.float64).reshape(-1, 3)
        b = np.array([it[1] for it in items], np.float64).reshape(-1, 3)
        ra = np.array([it[2] for it in items], np.float64)
        rb = np.array([it[3] for it in items], np.float64)
        bone_of = np.array([-1 if it[4] is None else index[it[4]] for it in items], np.int64)
        groups = [(it[6], it[5]) for it in items]
        if cfg.bones:
            heads = np.array([bn.head for bn in cfg.bones], np.float64)
            tails = np.array([bn.tail for bn in cfg.bones], np.float64)
            for i in range(len(names)):
                if not np.linalg.norm(tails[i] - heads[i]) > 0:
                    raise ValueError(f"object.bones[{i}].tail: equals its head (a bone needs a length)")
            parents = [-1 if bn.parent is None else index[bn.parent] for bn in cfg.bones]
            keys = [[(k.frame, k.rotate) for k in bn.keys] for bn in cfg.bones]
            M = pose(heads, parents, order, keys, frame)
            att = bone_of >= 0
            a[att] = apply(M[bone_of[att]], a[att])
            b[att] = apply(M[bone_of[att]], b[att])
            infl = np.array([bn.influence or 0.75 * np.linalg.norm(t - h) for bn, h, t in zip(cfg.bones, heads, tails)])
            rig = (apply(M, heads), apply(M, tails), infl, M)
    off = np.asarray(cfg.offset, np.float64)
    a, b, ra, rb = a * cfg.scale + off, b * cfg.scale + off, ra * cfg.scale, rb * cfg.scale
    if rig is not None:
        S = np.eye(4) * cfg.scale
        S[3, 3] = 1.0
        S[:3, 3] = off
        Sinv = np.linalg.inv(S)
        M = S @ rig[3] @ Sinv  # the same rigid motions, in scaled world units
        rig = (rig[0] * cfg.scale + off, rig[1] * cfg.scale + off, rig[2] * cfg.scale, M)
    return a, b, ra, rb, rig, groups


def csg_shape(cfg: ImplicitConfig, groups) -> tuple[Shape, np.ndarray]:
    """Static CSG tree over group indices, and each primitive's group index."""
    disp = "none" if cfg.displace is None else cfg.displace.type
    if cfg.csg is None:
        return Shape(("group", 0), 1, disp), np.zeros(len(groups), np.int32)
    names: list[str] = []

    def conv(node):
        if node.op == "group":
            if node.group not in names:
                names.append(node.group)
            return ("group", names.index(node.group))
        return (node.op, conv(node.children[0]), conv(node.children[1]))

    tree = conv(cfg.csg)
    gid = []
    for g, where in groups:
        if g not in names:
            raise ValueError(f"object.{where}.group: group {g!r} is not in object.csg (groups there: {', '.join(names)})")
        gid.append(names.index(g))
    return Shape(tree, len(names), disp), np.asarray(gid, np.int32)


def _unit(v, path):
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v)
    if not n > 0:
        raise ValueError(f"{path}: the zero vector")
    return v / n


def displace_params(cfg: ImplicitConfig, anchor, dtype) -> Displace:
    """Traced displacement inputs; for an image, the bound on |grad (h o uv)| is the largest
    neighbouring-texel difference per texel size times the projector's scale (bilinear
    interpolation never exceeds its texels' finite differences)."""
    dc = cfg.displace
    z3 = np.zeros(3)
    if dc is None or dc.type == "noise":
        amp, freq = (0.0, 1.0) if dc is None else (dc.amplitude, dc.frequency)
        return Displace(jnp.asarray(amp, dtype), jnp.asarray(freq, dtype), jnp.zeros((1, 1), dtype), jnp.asarray(z3, dtype),
                        jnp.asarray([1.0, 0, 0], dtype), jnp.asarray([0, 1.0, 0], dtype), jnp.ones(2, dtype), jnp.asarray(0.0, dtype))
    from ..frusta import load_height_map

    try:
        hmap = load_height_map(dc.map).astype(np.float64) / 255.0
    except ValueError as e:
        raise ValueError(str(e).replace("object.relief.map", "object.displace.map")) from None
    pc = dc.projector
    ax = _unit(pc.axis, "object.displace.projector.axis")
    up = _unit(np.asarray(pc.up, np.float64) - np.dot(pc.up, ax) * ax, "object.displace.projector.up (it is parallel to the axis)")
    side = np.cross(ax, up)
    hh, ww = hmap.shape
    gu = np.max(np.abs(np.diff(hmap, axis=1, append=hmap[:, :1]))) * ww * pc.scale[0]
    gv = np.max(np.abs(np.diff(hmap, axis=0, append=hmap[:1, :]))) * hh * pc.scale[1]
    return Displace(jnp.asarray(dc.amplitude, dtype), jnp.asarray(1.0, dtype), jnp.asarray(hmap, dtype),
                    jnp.asarray(np.asarray(pc.origin) - anchor, dtype), jnp.asarray(side, dtype), jnp.asarray(up, dtype),
                    jnp.asarray(pc.scale, dtype), jnp.asarray(float(np.hypot(gu, gv)), dtype))


def projector_arrays(cfg: ImplicitConfig, anchor, dtype):
    """Projector (K entries: local ones, then the global one), (textures (K,H,W,3), sizes
    (K,2)), the static kinds and whether each is textured."""
    from ..textures import load_texture

    entries = [(pc, pc.region.center, pc.region.radius, pc.texture or cfg.texture, f"object.projectors[{i}]")
               for i, pc in enumerate(cfg.projectors)]
    if cfg.projector is not None:
        entries.append((cfg.projector, (0.0, 0.0, 0.0), np.inf, cfg.texture, "object.projector"))
    cols = {k: [] for k in ("origin", "axis", "up", "scale", "rc", "rr")}
    images = []
    for pc, centre, radius, texture, where in entries:
        ax = _unit(pc.axis, f"{where}.axis")
        up = _unit(np.asarray(pc.up, np.float64) - np.dot(pc.up, ax) * ax, f"{where}.up (it is parallel to the axis)")
        for k, v in zip(cols, (np.asarray(pc.origin) - anchor, ax, up, pc.scale, np.asarray(centre) - anchor, radius)):
            cols[k].append(v)
        images.append(None if texture is None else load_texture(texture, "object.texture" if texture == cfg.texture else f"{where}.texture"))
    kinds = tuple(pc.type for pc, *_ in entries)
    textured = tuple(im is not None for im in images)
    if not entries:  # one unused projector keeps the shapes non-empty
        cols = {"origin": [np.zeros(3)], "axis": [[0, 1.0, 0]], "up": [[0, 0, 1.0]], "scale": [[1.0, 1]], "rc": [np.zeros(3)], "rr": [0.0]}
        images = [None]
    images = [np.ones((1, 1, 3)) if im is None else im for im in images]
    hmax, wmax = max(im.shape[0] for im in images), max(im.shape[1] for im in images)
    stack = np.zeros((len(images), hmax, wmax, 3))
    for k, im in enumerate(images):
        stack[k, : im.shape[0], : im.shape[1]] = im
    sizes = np.array([im.shape[:2] for im in images], np.int32)
    proj = Projector(*(jnp.asarray(np.asarray(cols[k], np.float64), dtype) for k in cols))
    return proj, (jnp.asarray(stack, dtype), jnp.asarray(sizes)), kinds, textured


def build(cfg: ImplicitConfig, dtype=np.float32) -> Built:
    """Validate, pose at ``cfg.frame``, pad to a power of two (>= 8) so similar models share a
    compile, cast. Every frame of an animation has the same shapes: one compile."""
    cfg = expand(cfg)
    a, b, ra, rb, rig, groups = primitives(cfg)
    shape, gid = csg_shape(cfg, groups)
    nb = len(cfg.balls) if cfg.procedural is None else 0
    if cfg.method == "lipschitz":
        for i in np.nonzero(np.minimum(ra, rb) <= 0)[0]:
            which = "radius_a" if ra[i] <= 0 else "radius_b"
            where = f"tubes[{i - nb}].{which}" if i - nb < len(cfg.tubes) else f"bones[{i - nb - len(cfg.tubes)}].tube"
            raise ValueError(f"object.{where}: the lipschitz method needs both tube radii > 0 (its slope bound is 8/(3 sqrt(3) R))")
    fmax = _max_field_estimate(a, b, ra, rb)
    if not cfg.threshold < fmax:
        raise ValueError(f"object.threshold: {cfg.threshold} is not below the field's maximum (about {fmax:.4g}): no surface")
    p = a.shape[0]
    order = morton_order(0.5 * (a + b))
    a, b, ra, rb, gid = a[order], b[order], ra[order], rb[order], gid[order]
    n = max(8, 1 << int(np.ceil(np.log2(p))))
    if cfg.block_size:
        n = -(-n // cfg.block_size) * cfg.block_size
    rmax = np.maximum(ra, rb)[:, None]
    lo = np.min(np.minimum(a, b) - rmax, 0)
    hi = np.max(np.maximum(a, b) + rmax, 0)
    anchor = 0.5 * (lo + hi)
    # positions relative to the anchor are formed in float64 and only then cast: subtracting
    # after the cast kept float32's rounding of the world position (the float32/float64 fuzzer
    # found t off by 0.4 % of the model's size at 1e5 from the origin)
    prims = Prims(
        jnp.asarray(_pad(a - anchor, n), dtype), jnp.asarray(_pad(b - anchor, n), dtype),
        jnp.asarray(_pad(ra, n), dtype), jnp.asarray(_pad(rb, n), dtype),
        jnp.asarray(np.arange(n) < p),
        jnp.asarray(_pad(gid, n, 0)),
    )
    tune = Tuning(jnp.asarray(cfg.threshold, dtype), jnp.asarray(cfg.step, dtype), jnp.asarray(cfg.eps, dtype),
                  displace_params(cfg, anchor, dtype))
    if rig is None:  # one static "bone" with the identity map
        heads, tails, infl, M = np.zeros((1, 3)) + anchor, np.zeros((1, 3)) + anchor + [0, 1, 0], np.ones(1), np.eye(4)[None]
    else:
        heads, tails, infl, M = rig
    # posed -> rest for points relative to the anchor: x_rest - anchor = Minv (x + anchor) - anchor
    Minv = np.linalg.inv(M)
    to_rest = Minv[:, :3, :].copy()
    to_rest[:, :, 3] = to_rest[:, :, 3] + np.einsum("bij,j->bi", Minv[:, :3, :3], anchor) - anchor
    skin = Skin(jnp.asarray(heads - anchor, dtype), jnp.asarray(tails - anchor, dtype), jnp.asarray(infl, dtype), jnp.asarray(to_rest, dtype))
    projs, tex, kinds, textured = projector_arrays(cfg, anchor, dtype)
    prim_id = np.full(n + 1, -1, np.int32)
    prim_id[:p] = order
    scene = ImplicitScene(prims, tune, jnp.asarray(cfg.color, dtype), skin, projs, *tex, jnp.asarray(prim_id))
    q = Quality(cfg.method, cfg.steps, cfg.bisection, cfg.capacity, early_exit=cfg.early_exit, shape=shape,
                block=cfg.block_size, block_capacity=cfg.block_capacity or (16 if cfg.cull == "tree" else 32), cull=cfg.cull)
    static = Static(q, kinds, textured)
    info = {"primitives": int(p), "padded_primitives": int(n), "bones": len(cfg.bones), "frame": cfg.frame, "max_field_estimate": fmax}
    # width of the last bisection bracket: how far a returned hit may lie from F = T
    tol = float((cfg.eps if cfg.method == "lipschitz" else cfg.step) * 0.5 ** cfg.bisection)
    return Built(scene, static, anchor, (lo, hi), info, primitives=int(p), surface_tolerance=tol)


def intersect_one(scene: ImplicitScene, static: Static, origin, direction, t_min, t_max) -> Hit:
    """First hit of one ray; (u, v) from the projector applied at the rest-pose position."""
    q = static.quality
    cand = cull(scene.prims, origin, direction, t_min, t_max, q.capacity, q.block, q.block_capacity, q.cull)
    t, flags = trace_one(cand, scene.tune, origin, direction, t_min, t_max, q)
    pos, n, prim = surface_one(cand, scene.tune, origin, direction, t, q)
    prim = scene.prim_id[prim]
    uv = choose_uv(scene, static, pos)[1]
    return masked_hit(t, pos, n, uv, prim, flags)


def intersect_batch(scene: ImplicitScene, static: Static, rays: Rays, lanes: int = 256) -> Hit:
    """vmap of :func:`intersect_one`, then the rays whose culling overflowed (too many blocks
    or candidates) are traced again with flat culling (every primitive tested, no block list),
    gathered into dense sub-batches (``wavefront.compact_map``): a grazing ray through a large model
    costs P sphere tests only where it needs them. With the block level off it is the vmap."""
    q = static.quality
    hits = jax.vmap(lambda o, d, a, b: intersect_one(scene, static, o, d, a, b))(*rays)
    if not blocks_used(scene.prims.a.shape[0], q.block, q.block_capacity):
        return hits
    flat = static._replace(quality=q._replace(block=0))

    def redo(sub: Rays) -> Hit:
        return jax.vmap(lambda o, d, a, b: intersect_one(scene, flat, o, d, a, b))(*sub)

    return compact_map(redo, (hits.flags & OVERFLOW) != 0, rays, hits, lanes)


def rest_position(skin: Skin, x):
    """Alg. 3: the posed point x mapped to the rest pose, blending each bone's rigid inverse by
    weights (1 - d^2 / I^2)^2 of the distance d to the posed bone (nearest bone if none reaches)."""
    ab = skin.tail - skin.head
    s = jnp.clip(safe_div(dot3(x - skin.head, ab), dot3(ab, ab), 0.0), 0.0, 1.0)
    e = x - skin.head - s[:, None] * ab
    d2 = dot3(e, e)
    w = kernel(d2, skin.influence)
    nearest = (jnp.arange(d2.shape[0]) == jnp.argmin(d2)).astype(x.dtype)
    total = jnp.sum(w)
    w = jnp.where(total > 0, safe_div(w, total, 0.0), nearest)
    moved = jnp.einsum("bij,j->bi", skin.to_rest[:, :, :3], x) + skin.to_rest[:, :, 3]
    return jnp.sum(w[:, None] * moved, axis=0)


def choose_uv(scene: ImplicitScene, static: Static, pos):
    """(projector index, (u, v)) at a posed point: Alg. 3 maps it to the rest pose, the first
    projector whose region holds it is used (index -1 and uv 0 where none does)."""
    if not static.projector:
        return jnp.int32(-1), jnp.zeros((2,), pos.dtype)
    x = rest_position(scene.skin, pos)
    pr = scene.projector
    e = x - pr.region_c
    holds = dot3(e, e) <= pr.region_r * pr.region_r
    k = jnp.where(jnp.any(holds), jnp.argmax(holds), -1).astype(jnp.int32)
    uvs = jnp.stack([project(jax.tree_util.tree_map(lambda a, i=i: a[i], pr), x, kind) for i, kind in enumerate(static.projector)])
    return k, jnp.where(k >= 0, uvs[jnp.maximum(k, 0)], 0.0)


def project(pr: Projector, x, kind: str):
    """(u, v) of a rest-pose point (relative to the anchor) for one planar, cylindrical or
    spherical projector (Sec. 6): ``pr`` holds one projector's fields (no leading K axis)."""
    p = x - pr.origin
    side = jnp.cross(pr.axis, pr.up)
    h = dot3(p, pr.axis)
    pu, ps = dot3(p, pr.up), dot3(p, side)
    if kind == "planar":
        uv = jnp.stack([ps, pu])
    elif kind == "cylindrical":
        uv = jnp.stack([jnp.arctan2(ps, pu) / (2 * jnp.pi) + 0.5, h])
    else:  # spherical
        rho = safe_sqrt(pu * pu + ps * ps)
        uv = jnp.stack([jnp.arctan2(ps, pu) / (2 * jnp.pi) + 0.5, jnp.arctan2(rho, h) / jnp.pi])
    return uv * pr.scale


def albedo(scene: ImplicitScene, static: Static, hit: Hit):
    """The texture of the projector chosen at the hit, through the skinned projection (u and
    v wrap), else the model colour."""
    if not any(static.textured):
        return scene.color
    from ..textures import bilinear_wrap

    k, _ = choose_uv(scene, static, jnp.where(jnp.isfinite(hit.t), hit.position, 0.0))
    kk = jnp.maximum(k, 0)
    rgb = bilinear_wrap(scene.texture[kk], hit.uv, scene.tex_size[kk])
    use = (k >= 0) & jnp.asarray(static.textured)[kk]
    return jnp.where(use, rgb, scene.color)


def inside(scene: ImplicitScene, static: Static, point):
    """F > T at ``point`` (3,), relative to the anchor (CSG and displacement included)."""
    tn = scene.tune
    return shaped_field(scene.prims, point, static.quality.shape, tn.threshold, tn.disp) > tn.threshold


@final
class _Implicit(Representation, module=__name__):
    """The implicit representation as the registry hands it to the renderer."""

    name = "implicit"
    Config = ImplicitConfig


REPRESENTATION = _Implicit()
