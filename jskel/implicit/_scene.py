"""The implicit representation (Rouiller 2011): its build and the interface's functions
(intersect, albedo, inside), re-exported by ``jskel.implicit``. The primitives of a config are
``_primitives``'s, the texture projectors and skinning ``_projectors``'s, the field ``_field``'s
and the tracers ``_trace``'s."""

from __future__ import annotations

from typing import NamedTuple, final

import jax
import jax.numpy as jnp
import numpy as np

from ..executor import size_bucket
from ..interface import Built, Representation
from ..numerics import dot3, on_device
from ..rays import Hit, Rays, masked_hit
from ..wavefront import compact_map, leaves_of
from ._config import ImplicitConfig
from ._field import Prims, shaped_field
from ._primitives import csg_shape, expand, primitives
from ._projectors import Projector, Skin, displace_params, project, projector_arrays, rest_position
from ._cull import blocks_used, cull, influence_tree
from ._trace import NO_BRACKET, OVERFLOW, Quality, Tuning, certify, lipschitz_from, surface_one, trace_one


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


def _max_field_bound(a, b, ra, rb) -> float:
    """An upper bound of max F (host, float64; Rouiller Sec. 3's sum of kernels, each at most 1).
    Any point where F > 0 lies in some primitive i's influence sphere S_i (centre c_i, radius
    s_i), and there each primitive j adds at most its kernel at the distance from S_i to its
    segment, max(0, dist(c_i, seg_j) - s_i), with its largest radius; so max F <= max over i of
    that sum. Only spheres that overlap add, so the pairs come from a k-d tree over the
    spheres' centres (scipy): O(P) pairs for a model of many small primitives. A bound, not a
    sample: F sampled at primitive centres misses a maximum between them (two balls whose
    fields each stay below T at their centres but sum above it halfway)."""
    from scipy.spatial import cKDTree

    centre = 0.5 * (a + b)
    reach = 0.5 * np.linalg.norm(b - a, axis=1) + np.maximum(ra, rb)
    tree = cKDTree(centre)
    pairs = tree.sparse_distance_matrix(tree, 2 * float(np.max(reach)), output_type="ndarray")
    i, j = pairs["i"], pairs["j"]
    keep = pairs["v"] < reach[i] + reach[j]
    i, j = np.concatenate([np.arange(len(a)), i[keep & (i != j)]]), np.concatenate([np.arange(len(a)), j[keep & (i != j)]])
    f = np.zeros(len(a))
    for k in range(0, len(i), 1 << 20):
        pi, pj = i[k : k + (1 << 20)], j[k : k + (1 << 20)]  # the bound of sphere pi from primitive pj
        ab = (b - a)[pj]
        ax = centre[pi] - a[pj]
        den = np.sum(ab * ab, -1)
        t = np.clip(np.where(den > 0, np.sum(ax * ab, -1) / np.where(den > 0, den, 1), 0), 0, 1)
        r = np.maximum(np.linalg.norm(ax - t[:, None] * ab, axis=1) - reach[pi], 0.0)
        R = np.maximum(ra, rb)[pj]
        q = np.where(R > 0, r * r / np.where(R > 0, R * R, 1), 1)
        f += np.bincount(pi, np.where(q < 1, (1 - q) ** 2, 0), minlength=len(a))
    return float(np.max(f))


def morton_order(points: np.ndarray) -> np.ndarray:
    """Stable order of points (N,3) along a 30-bit Morton curve over their bounding cube (host):
    neighbours in the order are neighbours in space, so blocks of consecutive primitives have
    tight bounding spheres (``_cull.block_spheres``). One scale for all axes: a thin slab must
    not spend the curve's leading bits on its thin axis."""
    lo = points.min(0)
    ext = float(np.max(points.max(0) - lo))
    q = np.clip((points - lo) / max(ext, 1e-300) * 1023, 0, 1023).astype(np.uint64)
    code = np.zeros(len(points), np.uint64)
    for bit in range(10):
        for axis in range(3):
            code |= ((q[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
    return np.argsort(code, kind="stable")


def build(cfg: ImplicitConfig, dtype=np.float32) -> Built:
    """Validate, pose at ``cfg.frame``, pad to a size bucket (``executor.size_bucket``, a
    multiple of the block size; padding rows invalid: no field, no hit, no id) so similar
    models share a compile, cast. Every frame of an animation has the same shapes: one compile."""
    cfg = expand(cfg)
    a, b, ra, rb, rig, groups = primitives(cfg)
    shape, gid = csg_shape(cfg, groups)
    fmax = _checked_field_max(cfg, a, b, ra, rb)
    p = a.shape[0]
    order = morton_order(0.5 * (a + b))
    a, b, ra, rb, gid = a[order], b[order], ra[order], rb[order], gid[order]
    n = size_bucket(p, cfg.block_size or 1)
    rmax = np.maximum(ra, rb)[:, None]
    lo = np.min(np.minimum(a, b) - rmax, 0)
    hi = np.max(np.maximum(a, b) + rmax, 0)
    anchor = 0.5 * (lo + hi)
    # positions relative to the anchor are formed in float64 and only then cast: subtracting
    # after the cast kept float32's rounding of the world position (the float32/float64 fuzzer
    # found t off by 0.4 % of the model's size at 1e5 from the origin)
    prims = Prims(
        on_device(_pad(a - anchor, n), dtype), on_device(_pad(b - anchor, n), dtype),
        on_device(_pad(ra, n), dtype), on_device(_pad(rb, n), dtype),
        on_device(np.arange(n) < p),
        on_device(_pad(gid, n, 0)),
    )
    tune = Tuning(on_device(cfg.threshold, dtype), on_device(cfg.step, dtype), on_device(cfg.eps, dtype),
                  displace_params(cfg, anchor, dtype), on_device(np.int32(cfg.steps)), on_device(np.int32(cfg.bisection)))
    projs, tex, kinds, textured = projector_arrays(cfg, anchor, dtype)
    prim_id = np.full(n + 1, -1, np.int32)
    prim_id[:p] = order
    scene = ImplicitScene(prims, tune, on_device(cfg.color, dtype), skin_of(rig, anchor, dtype), projs, *tex, on_device(prim_id))
    tubes = bool(np.any(a != b))
    q = Quality(cfg.method, cfg.capacity, early_exit=cfg.early_exit, shape=shape, tubes=tubes,
                degree=8 if np.any((ra != rb) & np.any(a != b, axis=1)) else 4,
                block=cfg.block_size, block_capacity=cfg.block_capacity or (32 if cfg.cull == "blocks" else 16), cull=cfg.cull)
    static = Static(q, kinds, textured)
    info = {"primitives": int(p), "padded_primitives": int(n), "bones": len(cfg.bones), "frame": cfg.frame, "max_field_bound": fmax}
    # width of the last bisection bracket: how far a returned hit may lie from F = T; the
    # bisection method's first bracket (the entry into the first sphere of influence to the
    # nearest inside point) spans at most the model's box, not a step
    size = float(np.linalg.norm(np.asarray(hi) - np.asarray(lo)))
    first = {"lipschitz": cfg.eps, "naive": cfg.step}.get(cfg.method, size)
    # exact: rounding of t, a few ulps of the model's size (the window's t is within a few sizes)
    # (CSG or displacement: the Lipschitz march's from exact's certified start)
    exact = cfg.method == "exact" and cfg.csg is None and cfg.displace is None
    first = cfg.eps if cfg.method == "exact" else first
    tol = 64 * float(np.finfo(dtype).eps) * size if exact else float(first * 0.5**cfg.bisection)
    return Built(scene, static, anchor, (lo, hi), info, primitives=int(p), surface_tolerance=tol)


def _checked_field_max(cfg: ImplicitConfig, a, b, ra, rb) -> float:
    """A bound of the field's maximum (:func:`_max_field_bound`; CSG trees of non-negative
    group fields stay below the sum, a displacement grows it by 1 + amplitude), after checking
    that the surface may exist (``threshold`` below it) and that the lipschitz method's slope bound does
    (both radii of every tube > 0). ValueError names the field."""
    nb = len(cfg.balls) if cfg.procedural is None else 0
    why = {"lipschitz": "its slope bound is 8/(3 sqrt(3) R)",
           "exact": "a tapering tube's interval is multiplied by R^4, which a zero radius leaves without digits"}
    if cfg.method in why:
        for i in np.nonzero(np.minimum(ra, rb) <= 0)[0]:
            which = "radius_a" if ra[i] <= 0 else "radius_b"
            where = f"tubes[{i - nb}].{which}" if i - nb < len(cfg.tubes) else f"bones[{i - nb - len(cfg.tubes)}].tube"
            raise ValueError(f"object.{where}: the {cfg.method} method needs both tube radii > 0 ({why[cfg.method]})")
    fmax = _max_field_bound(a, b, ra, rb) * (1.0 + (cfg.displace.amplitude if cfg.displace else 0.0))
    if not cfg.threshold < fmax:
        raise ValueError(f"object.threshold: {cfg.threshold} is not below a bound of the field's maximum ({fmax:.4g}): no surface")
    return fmax


def skin_of(rig, anchor, dtype) -> Skin:
    """Device skinning inputs of a rig (posed heads, tails, influence, M posed-from-rest), or of
    one static "bone" with the identity map when there is none; relative to the anchor. The
    bones are padded to a size bucket (``executor.size_bucket``: a rig of similar size shares
    every program) with copies of the last bone of influence 0: no weight, and never the
    nearest bone (``rest_position``'s argmin takes the first of equals, a real bone)."""
    if rig is None:  # one static "bone" with the identity map
        heads, tails, infl, M = np.zeros((1, 3)) + anchor, np.zeros((1, 3)) + anchor + [0, 1, 0], np.ones(1), np.eye(4)[None]
    else:
        heads, tails, infl, M = rig
    b, rows = len(infl), size_bucket(len(infl))
    heads, tails, M = (np.concatenate([x, np.repeat(x[-1:], rows - b, axis=0)]) for x in (heads, tails, M))
    infl = np.concatenate([np.asarray(infl, np.float64), np.zeros(rows - b)])
    # posed -> rest for points relative to the anchor: x_rest - anchor = Minv (x + anchor) - anchor
    Minv = np.linalg.inv(M)
    to_rest = Minv[:, :3, :].copy()
    to_rest[:, :, 3] = to_rest[:, :, 3] + np.einsum("bij,j->bi", Minv[:, :3, :3], anchor) - anchor
    return Skin(on_device(heads - anchor, dtype), on_device(tails - anchor, dtype), on_device(infl, dtype), on_device(to_rest, dtype))


def intersect_one(scene: ImplicitScene, static: Static, origin, direction, t_min, t_max, deferred: bool = False, leaves=None):
    """First hit of one ray; (u, v) from the projector applied at the rest-pose position.
    ``deferred`` (``bisection``): (hit, (candidates, origin, direction, Certify job)) with the
    certifying march left to :func:`intersect_batch`; (``exact``): the last is whether the ray
    is uncertified, its march left to the batch. ``leaves``: the ray's BVH leaves found for its
    batch (``wavefront.leaves_of``); unset, culling walks the tree for this ray."""
    q = static.quality
    cand = cull(scene.prims, origin, direction, t_min, t_max, q.capacity, q.block, q.block_capacity, q.cull, q.method != "exact", leaves)
    out = trace_one(cand, scene.tune, origin, direction, t_min, t_max, q, deferred)
    t, flags = out[:2]
    pos, n, prim = surface_one(cand, scene.tune, origin, direction, t, q)
    prim = scene.prim_id[prim]
    uv = choose_uv(scene, static, pos)[1]
    hit = masked_hit(t, pos, n, uv, prim, flags)
    return (hit, (cand.sub, origin, direction, out[2])) if deferred else hit


def intersect_batch(scene: ImplicitScene, static: Static, rays: Rays, lanes: int = 256) -> Hit:
    """vmap of :func:`intersect_one`, then the rays whose culling overflowed (too many blocks
    or candidates) are traced again with flat culling (every primitive tested, no block list),
    gathered into dense sub-batches (``wavefront.compact_map``): a grazing ray through a large model
    costs P sphere tests only where it needs them. With the block level off it is the vmap.
    ``bisection``'s certifying march (``_trace.certify``) runs the same way on only the rays
    whose bounds left a piece open: as a ``while_loop`` under vmap it would last as long as the
    batch's slowest ray for every ray."""
    q = static.quality
    if q.method == "exact":
        return _exact_batch(scene, static, rays, lanes)
    deferred = q.method == "bisection"

    def one(st: Static, defer: bool, leaves=None):
        return lambda *r: jax.vmap(lambda o, d, a, b, lv: intersect_one(scene, st, o, d, a, b, defer, lv))(*r, leaves)

    blocks = blocks_used(scene.prims.a.shape[0], q.block, q.block_capacity)
    leaves = None
    if q.cull == "packets" and blocks:  # every ray's leaves through its packet's list, for the batch
        leaves = leaves_of(influence_tree(scene.prims, q.block), rays, q.block_capacity, lanes, True)
    out = one(static, deferred, leaves)(*rays)
    if blocks:
        flat = static._replace(quality=q._replace(block=0))
        if not deferred:
            return compact_map(lambda sub: one(flat, False)(*sub), (out.flags & OVERFLOW) != 0, rays, out, lanes)

        def redo(sub):  # flat culling keeps another candidate count: these few rays march in place
            r, (c, o, d, j) = sub
            no = jnp.zeros_like(j.undecided)
            return one(flat, False)(*r), (c, o, d, j._replace(undecided=no, earlier=no))

        out = compact_map(redo, (out[0].flags & OVERFLOW) != 0, (rays, out[1]), out, lanes)
    if not deferred:
        return out
    hits, job = out
    job, tune = jax.lax.stop_gradient((job, scene.tune))  # flags only: nothing to differentiate

    def march(sub):
        return jax.vmap(lambda s, o, d, j: certify(s, tune, q, o, d, j))(*sub)

    need = job[3].undecided | job[3].earlier
    return hits._replace(flags=hits.flags | compact_map(march, need, job, jnp.zeros_like(hits.flags), lanes))


def _exact_batch(scene: ImplicitScene, static: Static, rays: Rays, lanes: int) -> Hit:
    """``exact``: every ray culled (by (ray, leaf) pairs through the tree, ``_pairs``), the rays
    whose block list overflowed culled again flat; the intervals of the rays with candidates
    solved in rounds over the rays still searching (``_exact.rounds``); the surface of the rays
    that hit; then, in a model with tapered tubes, the rays it could not certify (two tapered
    axis pieces on one interval) by the Lipschitz march. Each stage after culling runs on its rays only, gathered into dense
    sub-batches (``wavefront.compact_map``): on a camera's rays most miss every candidate."""
    from . import _exact, _pairs

    q = static.quality
    tune = scene.tune
    def culled(block: int):
        return jax.vmap(lambda o, d, a, b: cull(scene.prims, o, d, a, b, q.capacity, block, q.block_capacity, q.cull, False))

    blocks = blocks_used(scene.prims.a.shape[0], q.block, q.block_capacity)
    if q.cull in ("tree", "packets") and blocks and _pairs.usable(q.block):
        cand = _pairs.cull_batch(scene.prims, rays, q.capacity, q.block, q.block_capacity, lanes, q.cull == "packets")
    else:
        cand = culled(q.block)(*rays)
    if blocks:  # rays that met more blocks than kept: culled again flat, then traced with the rest
        k = max(cand.ids.shape[1], jax.eval_shape(culled(0), *rays).ids.shape[1])  # lists of either width
        n = scene.prims.a.shape[0]
        cand = compact_map(lambda sub: _widened(culled(0)(*sub), k, n), cand.overflow, rays, _widened(cand, k, n), lanes)
    plain = _exact.plain(q.shape)
    st = _exact.rounds(cand, _exact.lowered(tune, q), rays.origins, rays.directions, q, lanes)
    flags = jnp.where(cand.overflow, OVERFLOW, 0)
    t = st.t if plain else jnp.full_like(st.t, jnp.inf)  # a shaped field's hit is the march's
    if plain and q.degree == 4:  # built without tapering tubes: none to certify, unless traced radii now taper
        flags = flags | jnp.where(st.unc, NO_BRACKET, 0)
    else:  # the Lipschitz march from the certified start (_exact.march_start), t and flags only

        def marched(sub):
            c, s, o, d = jax.lax.stop_gradient(sub)  # its t is differentiated by finish below
            return jax.vmap(lambda c, s, o, d: lipschitz_from(c, tune, o, d, _exact.march_start(c, s), q))(c, s, o, d)

        need = st.unc if plain else jnp.isfinite(st.t) | st.unc
        t, own = compact_map(marched, need, (cand, st, rays.origins, rays.directions), (t, jnp.zeros_like(flags)), lanes)
        flags = flags | own
    inf = jnp.full(rays.t_min.shape, jnp.inf, rays.t_min.dtype)
    zero3 = jnp.zeros_like(rays.origins)
    miss = jax.vmap(masked_hit)(inf, zero3, zero3, zero3[:, :2], jnp.zeros_like(flags), flags)

    def done(sub):  # every hit: t differentiable (implicit-function theorem at the root), its surface
        def one(c, t, o, d, f):
            t = _exact.finish(c.sub, o, d, t, tune, q)
            pos, n, prim = surface_one(c, tune, o, d, t, q)
            return masked_hit(t, pos, n, choose_uv(scene, static, pos)[1], scene.prim_id[prim], f)

        return jax.vmap(one)(*sub)

    return compact_map(done, jnp.isfinite(t), (cand, t, rays.origins, rays.directions, flags), miss, lanes)


def _widened(cand, k: int, p: int):
    """Candidates (leading axis N) padded to ``k`` slots with empty ones (not valid, id ``p``:
    none, as culling marks them): the two cullings keep lists of min(capacity, slots they
    test) entries."""
    pad = k - cand.ids.shape[1]
    if pad == 0:
        return cand

    def widen(x, fill):
        return jnp.concatenate([x, jnp.full((x.shape[0], pad) + x.shape[2:], fill, x.dtype)], axis=1)

    sub = cand.sub._replace(**{f: widen(getattr(cand.sub, f), False if f == "valid" else 0) for f in cand.sub._fields})
    return cand._replace(sub=sub, ids=widen(cand.ids, p))


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


def traced_fields(scene: ImplicitScene) -> dict:
    """What ``interface.checked_intersect`` verifies of traced implicit params, each primitive by
    its index in the config (balls, tubes, then bones' tubes; padding skipped): its ends ``a``, ``b`` finite,
    its radii ``ra``, ``rb`` not negative, and the threshold positive."""
    p = scene.prims
    ids = scene.prim_id[: p.a.shape[0]]
    out = {f"primitives.{n}": (getattr(p, n), k, p.valid, ids) for n, k in (("a", "finite"), ("b", "finite"), ("ra", "nonnegative"), ("rb", "nonnegative"))}
    return {**out, "threshold": (jnp.reshape(scene.tune.threshold, (1,)), "positive", None, None)}


@final
class _Implicit(Representation, module=__name__):
    """The implicit representation as the registry hands it to the renderer."""

    name = "implicit"
    Config = ImplicitConfig
    animated = True  # its bones posed at ``frame`` (``_anim``)


REPRESENTATION = _Implicit()
