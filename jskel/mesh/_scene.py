"""Triangle meshes (``type: mesh``): read through trimesh, cast through the shared linear BVH.

The representation every renderer knows, here to prove the interface: it is this folder and one
registry line. Triangles are tested by :func:`jskel.mesh._triangle.triangle_t` (watertight); the BVH and its
stackless traversal are ``jskel.accel``'s (the frusta's plain segments use the same tree).
``inside`` is watertight-aware: for a closed mesh the facing of the first triangles rays from the
point meet (casts through the BVH, O(log F) each); for an open one the generalised winding number (Jacobson, Kavan and
Sorkine-Hornung 2013), the solid angles of the faces seen from the point summed over 4 pi, which
is 1 inside and 0 outside a closed mesh and a smooth in-between for open ones (``inside`` is
``w > 1/2``, O(F) per point). ``run.json`` records whether the mesh was watertight.
"""

from __future__ import annotations

from pathlib import Path
from typing import NamedTuple, final

import jax
import jax.numpy as jnp
import numpy as np

from .. import accel, checks
from ..executor import size_bucket
from ..interface import Built, Preliminary, Representation
from ..numerics import dot3, safe_div, safe_normalize
from ..rays import Hit, Rays, masked_hit
from ._config import MeshConfig
from ._triangle import cross3, triangle_t


class MeshParams(NamedTuple):
    """Device pytree: triangles' vertices relative to the anchor (kept as vertices: the
    watertight test needs shared vertices bit-equal), unit face normals, corner normals (smooth
    shading; (1, 3, 3) zeros when flat), colour, the BVH, which rows are triangles, and each
    triangle's box (the BVH's and the bins' both). The
    rows are those of a size bucket (``executor.size_bucket``, at least the F triangles), so a
    mesh of similar size shares every program; a padding row is a point at the anchor that no
    ray meets and no winding number counts (``valid`` False, out of the BVH)."""

    v0: jnp.ndarray  # (F', 3) F' = size_bucket(F)
    v1: jnp.ndarray  # (F', 3)
    v2: jnp.ndarray  # (F', 3)
    ids: jnp.ndarray  # (F', 3) int32 vertex indices (the watertight test's canonical edge order)
    normal: jnp.ndarray  # (F', 3)
    corner: jnp.ndarray  # (F', 3, 3) or (1, 3, 3)
    color: jnp.ndarray  # (3,)
    bvh: accel.BVH
    valid: jnp.ndarray  # (F',) bool: a triangle of the mesh (False: padding)
    box_lo: jnp.ndarray  # (F', 3) each triangle's box, as the BVH is built from it (lo = +inf for padding)
    box_hi: jnp.ndarray  # (F', 3) (hi = -inf for padding)


class Static(NamedTuple):
    """Static options of a mesh object: BVH leaf size, rays per traversal group, smooth
    normals, and whether the mesh is closed (``inside`` by the facing of first hits, else by
    the winding number)."""

    leaf: int
    group: int
    smooth: bool
    closed: bool = False
    packet: int = 0  # rays per shared walk (0: per-ray walks in groups of ``group``)
    bins: tuple = ()  # bins: (rays per packet, candidates and pairs per step, slots per group, walk ratio); () for walks


def read_mesh(path: str, where: str = "object.path") -> tuple[np.ndarray, np.ndarray, object]:
    """(vertices (V, 3) float64, faces (F, 3) int64, the trimesh) of the file at ``path``, with
    bit-equal vertices merged (only those);
    one ValueError listing every problem (unreadable, no faces, non-finite vertices, face
    indices out of range), each naming ``where``."""
    import trimesh

    if not Path(path).is_file():
        raise ValueError(f"{where}: no file {path!r}")
    try:
        m = trimesh.load(path, force="mesh", process=False)
    except Exception as e:  # noqa: BLE001 - any reader error, reported with the path
        raise ValueError(f"{where}: cannot read mesh {path!r}: {e}") from None
    v = np.asarray(getattr(m, "vertices", np.zeros((0, 3))), np.float64).reshape(-1, 3)
    f = np.asarray(getattr(m, "faces", np.zeros((0, 3))), np.int64).reshape(-1, 3)
    problems = []
    if f.shape[0] == 0:
        problems.append(f"{where}: {path!r} holds no triangles")
    problems += checks.nonfinite(f"{where} ({path!r}) vertices", v, "vertices")
    bad_f = np.where(np.any((f < 0) | (f >= v.shape[0]), axis=1))[0]
    problems += checks.at(f"{where} ({path!r}) faces", f"index out of [0, {v.shape[0]})", bad_f, f[bad_f], "faces")
    if problems:
        raise ValueError("\n".join(problems))
    # bit-equal vertices become one (STL stores every triangle's own three): the watertight test's
    # edge order and the closed-mesh check need shared vertices shared; nothing else is merged
    v, inverse = np.unique(v, axis=0, return_inverse=True)
    f = inverse.reshape(-1)[f]
    m = trimesh.Trimesh(vertices=v, faces=f, process=False)
    return v, f, m


_build_bvh = jax.jit(accel.build, static_argnums=3)


def build(cfg: MeshConfig, dtype=np.float32) -> Built:
    """Host: read, scale and move the mesh, anchor it at its box's centre, build the BVH."""
    v, f, m = read_mesh(cfg.path)
    v = v * cfg.scale + np.asarray(cfg.offset, np.float64)
    tri = v[f]  # (F, 3, 3) float64
    lo, hi = tri.reshape(-1, 3).min(0), tri.reshape(-1, 3).max(0)
    anchor = 0.5 * (lo + hi)
    tri = tri - anchor
    closed = bool(m.is_watertight and m.is_winding_consistent)
    inward = closed and m.volume < 0
    if inward:  # wound inward: turn every face so normals point out
        f = f[:, ::-1].copy()
        tri = tri[:, ::-1]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area2 = np.linalg.norm(n, axis=1)
    n = np.where(area2[:, None] > 0, n / np.where(area2 > 0, area2, 1.0)[:, None], 0.0)
    if cfg.normals == "smooth":
        vn = np.asarray(m.vertex_normals, np.float64)[f] * (-1.0 if inward else 1.0)
    else:
        vn = np.zeros((1, 3, 3))
    # boxes widened by float32 rounding of the vertices, so the tree never culls a ray the
    # triangle test would accept
    pad = 4.0 * np.finfo(dtype).eps * (np.abs(tri).max() + 1.0)
    rows = size_bucket(f.shape[0])
    tri, ids, n = _padded(tri, rows), _padded(f.astype(np.int32), rows), _padded(n, rows)
    vn = vn if vn.shape[0] == 1 else _padded(vn, rows)
    valid = np.arange(rows) < f.shape[0]
    box_lo = np.where(valid[:, None], tri.min(1) - pad, np.inf)
    box_hi = np.where(valid[:, None], tri.max(1) + pad, -np.inf)
    bvh = _build_bvh(jnp.asarray(box_lo, dtype), jnp.asarray(box_hi, dtype), jnp.asarray(valid), cfg.leaf)
    v0, v1, v2 = (jnp.asarray(tri[:, k], dtype) for k in range(3))
    params = MeshParams(v0, v1, v2, jnp.asarray(ids), jnp.asarray(n, dtype), jnp.asarray(vn, dtype),
                        jnp.asarray(np.asarray(cfg.color, np.float64), dtype), bvh, jnp.asarray(valid),
                        jnp.asarray(box_lo, dtype), jnp.asarray(box_hi, dtype))
    info = {"triangles": int(f.shape[0]), "vertices": int(v.shape[0]), "watertight": bool(m.is_watertight), "closed": closed,
            "degenerate_triangles": int(np.sum(area2 == 0))}
    traversal = traversal_of(cfg, int(f.shape[0]))
    bins = (cfg.bin_packet, cfg.bin_candidates, cfg.bin_pairs, cfg.bin_group, cfg.bin_walk_ratio) if traversal == "bins" else ()
    static = Static(cfg.leaf, cfg.group, cfg.normals == "smooth", closed, cfg.packet if traversal == "packets" else 0, bins)
    info["traversal"] = traversal
    return Built(params, static, anchor, (lo, hi), info, primitives=int(f.shape[0]))


# from this many triangles ``auto`` picks bins on the CPU, packets below: the bins' program
# compiles longer, and on smaller meshes at the default frame size the render it saves does not
# repay that within a few frames (docs/choices.md#mesh-bins)
AUTO_BINS_TRIANGLES = 32768


def traversal_of(cfg: MeshConfig, triangles: int) -> str:
    """``object.traversal`` resolved: ``auto`` is ``bins`` on the CPU from
    :data:`AUTO_BINS_TRIANGLES` triangles, else ``packets`` (on an accelerator too, where the
    bins' scalar loops have not been measured)."""
    if cfg.traversal != "auto":
        return cfg.traversal
    return "bins" if jax.default_backend() == "cpu" and triangles >= AUTO_BINS_TRIANGLES else "packets"


def _padded(x: np.ndarray, rows: int) -> np.ndarray:
    """``x`` with zero rows appended up to ``rows``."""
    return np.concatenate([x, np.zeros((rows - x.shape[0],) + x.shape[1:], x.dtype)])


def _leaf_best(p: MeshParams, slots, o, d, t_min, t_hi):
    """The nearest of one BVH leaf's triangles (``accel.nearest``'s ``leaf_fn``)."""
    ids = p.bvh.order[slots]
    i = jnp.maximum(ids, 0)
    t, _, _ = triangle_t(p.v0[i], p.v1[i], p.v2[i], o, d, t_min, t_hi, p.ids[i])
    t = jnp.where(ids >= 0, t, jnp.inf)
    k = jnp.argmin(t)
    return accel.Best(t[k], jnp.zeros((), t.dtype), jnp.int32(0), jnp.where(jnp.isfinite(t[k]), ids[k], -1))


def _nearest_one(p: MeshParams, static: Static, o, d, t_min, t_max, any_hit: bool = False):
    init = accel.Best(jnp.asarray(jnp.inf, o.dtype), jnp.zeros((), o.dtype), jnp.int32(0), jnp.int32(-1))
    leaf_fn = lambda s, o_, d_, a_, b_: _leaf_best(p, s, o_, d_, a_, b_)  # noqa: E731
    best, _, _ = accel.nearest(p.bvh, leaf_fn, static.leaf, o, d, t_min, t_max, init, any_hit)
    return jnp.where(best.idx >= 0, best.t, jnp.inf), best.idx  # the walk starts its best t at t_max


def _nearest_packet(p: MeshParams, static: Static, o, d, t_min, t_max):
    leaf_fn = jax.vmap(lambda slots, o_, d_, a_, b_: _leaf_best(p, slots, o_, d_, a_, b_), in_axes=(None, 0, 0, 0, 0))
    init = accel.Best(jnp.asarray(jnp.inf, o.dtype), jnp.zeros((), o.dtype), jnp.int32(0), jnp.int32(-1))
    best, _ = accel.nearest_packet(p.bvh, leaf_fn, static.leaf, o, d, t_min, t_max, init)
    return jnp.where(best.idx >= 0, best.t, jnp.inf), best.idx


def nearest_bins(p: MeshParams, static: Static, rays: Rays):
    """(t, idx) of a batch through packet candidate lists (``accel.nearest_binned``, the frusta's
    ``bins``): each packet of ``bins[0]`` consecutive rays tests, densely, only the triangles
    whose box (``box_lo``/``box_hi``, those the tree is built from, so both are conservative
    alike) one of its rays may meet, nearest first and pruned by its rays' best t; the batch's
    list is found through the tree's nodes of ``bins[3]`` leaf slots. A batch whose
    list holds more than ``bins[4]`` triangles per ray is cast by per-ray walks instead.
    Equal to brute force (ties to the lowest triangle index)."""
    packet, candidates, pairs, per, walk_ratio = static.bins
    n = rays.size

    def pair_fn(ids, o, d, a, b):  # ids (Q,), rays (Q, G, ...): t (Q, G)
        v0, v1, v2, vid = p.v0[ids], p.v1[ids], p.v2[ids], p.ids[ids]
        one = jax.vmap(lambda v0, v1, v2, i, o, d, a, b: triangle_t(v0, v1, v2, o, d, a, b, i)[0], in_axes=(None, None, None, None, 0, 0, 0, 0))
        return jax.vmap(one)(v0, v1, v2, vid, o, d, a, b)

    def walks(o, d, a, b):
        return accel.map_groups(jax.vmap(lambda *r: _nearest_one(p, static, *r)), static.group, o, d, a, b)

    groups = accel.bin_groups(p.bvh, per) if per else None
    fallback = walks if walk_ratio > 0 and int(walk_ratio * n) < p.box_lo.shape[0] else None
    t, idx, _ = accel.nearest_binned(p.box_lo, p.box_hi, pair_fn, packet, candidates, pairs, *rays, groups, fallback, int(walk_ratio * n),
                                     root=(p.bvh.lo[1], p.bvh.hi[1]))
    return t, idx


def _search(static: Static):
    def search(p: MeshParams, rays: Rays):
        if static.bins:
            return nearest_bins(p, static, rays)
        if static.packet > 0:
            return accel.map_groups(lambda *r: _nearest_packet(p, static, *r), static.packet, *rays)
        return accel.map_groups(jax.vmap(lambda o, d, a, b: _nearest_one(p, static, o, d, a, b)), static.group, *rays)

    return search


def winner_t(p: MeshParams, rays: Rays, out):
    """(t, None) of a batch on the planes of its winning triangles, t = n . (v0 - o) / (n . d)
    with n = (v1 - v0) x (v2 - v0): the value the watertight test finds, in a form whose
    derivative in the vertices and the ray is defined wherever the ray is not parallel to the
    face (``accel.nearest_tangent``'s ``winner``; a miss holds its tangents at 0)."""
    t, idx = out
    hit = jnp.isfinite(t)
    i = jnp.maximum(idx, 0)
    v0, v1, v2, o, d = accel.hold(hit, (p.v0[i], p.v1[i], p.v2[i], rays.origins, rays.directions))
    n = cross3(v1 - v0, v2 - v0)
    return safe_div(dot3(n, v0 - o), dot3(n, d), 0.0), None


def cast(p: MeshParams, static: Static, rays: Rays) -> Preliminary:
    """First stage: (t, triangle) of every ray through the BVH: one walk per packet of
    ``static.packet`` consecutive rays, or per ray in vmapped groups of ``static.group``
    (``accel.map_groups``); both give the nearest hit of each ray. t differentiates in both
    modes through the winning triangle's plane (:func:`winner_t`; the walk is a loop of
    data-dependent length, which ``jax.grad`` cannot reverse)."""
    t, idx = accel.nearest_tangent(_search(static), winner_t)(p, rays)
    return Preliminary(t, jnp.where(jnp.isfinite(t), idx, -1).astype(jnp.int32), None)


def occluded(p: MeshParams, static: Static, rays: Rays):
    """(N,) bool: does each ray meet a triangle in ``(t_min, t_max]`` (shadow rays)? Per-ray
    walks stop at the first leaf that holds a hit (``accel.nearest``'s ``any_hit``); packets
    and bins answer from :func:`cast`'s nearest t."""
    if static.packet > 0 or static.bins:
        return jnp.isfinite(cast(p, static, rays).t)
    one = jax.vmap(lambda o, d, a, b: _nearest_one(p, static, o, d, a, b, any_hit=True))
    return jnp.isfinite(accel.map_groups(one, static.group, *rays)[0])


def _surface_one(p: MeshParams, static: Static, o, d, t, idx) -> Hit:
    i = jnp.maximum(idx, 0)
    _, u, v = triangle_t(p.v0[i], p.v1[i], p.v2[i], o, d, -jnp.inf, jnp.inf, p.ids[i])
    if static.smooth:
        c = p.corner[i]
        n = safe_normalize((1.0 - u - v) * c[0] + u * c[1] + v * c[2])
    else:
        n = p.normal[i]
    tt = jnp.where(jnp.isfinite(t), t, 0.0)
    return masked_hit(t, o + tt * d, n, jnp.stack([u, v]), idx)


def surface(p: MeshParams, static: Static, rays: Rays, pre: Preliminary) -> Hit:
    """Second stage: position on the ray, the face (or interpolated corner) normal and the
    barycentric (u, v) of the winning triangle; normals outward as the faces wind them."""
    return jax.vmap(lambda o, d, t, i: _surface_one(p, static, o, d, t, i))(rays.origins, rays.directions, pre.t, pre.prim)


def intersect_one(p: MeshParams, static: Static, origin, direction, t_min, t_max) -> Hit:
    """Nearest hit of one ray by brute force over every triangle (the reference the BVH must equal)."""
    t, _, _ = triangle_t(p.v0, p.v1, p.v2, origin, direction, t_min, t_max, p.ids)
    t = jnp.where(p.valid, t, jnp.inf)  # padding rows (a point: rounding could let one through)
    k = jnp.argmin(t)
    return _surface_one(p, static, origin, direction, t[k], jnp.where(jnp.isfinite(t[k]), k, -1).astype(jnp.int32))


def intersect_batch(p: MeshParams, static: Static, rays: Rays) -> Hit:
    """Nearest hits of a batch through the BVH: :func:`surface` of :func:`cast`."""
    return surface(p, static, rays, cast(p, static, rays))


def albedo(p: MeshParams, static: Static, hit: Hit):
    """The object's colour (``object.color``) at every hit."""
    return p.color


def winding_number(p: MeshParams, point):
    """Generalised winding number of ``point`` (3,) (relative to the anchor): sum over faces of
    the solid angle (Van Oosterom and Strackee 1983) over 4 pi."""
    a, b, c = p.v0 - point, p.v1 - point, p.v2 - point
    la, lb, lc = (jnp.sqrt(dot3(x, x)) for x in (a, b, c))
    num = dot3(a, cross3(b, c))
    den = la * lb * lc + dot3(a, b) * lc + dot3(b, c) * la + dot3(c, a) * lb
    return jnp.sum(jnp.where(p.valid, jnp.arctan2(num, den), 0.0)) / (2.0 * jnp.pi)


# generic directions (no axis, no face of a regular mesh lies along them) for the facing test
INSIDE_DIRECTIONS = ((0.8017837, 0.2672612, 0.5345225), (-0.3015113, 0.9045340, -0.3015113), (0.2182179, -0.4364358, -0.8728716))


def _faces_away(p: MeshParams, static: Static, point, direction):
    """1 where the first triangle the ray from ``point`` meets faces along the ray (its back
    is seen: the point is inside a closed, outward-wound mesh), 0 where it faces the ray or
    nothing is met."""
    t, idx = _nearest_one(p, static, point, direction, jnp.zeros((), point.dtype), jnp.asarray(jnp.inf, point.dtype))
    return (jnp.isfinite(t) & (dot3(p.normal[jnp.maximum(idx, 0)], direction) > 0)).astype(jnp.int32)


def inside(p: MeshParams, static: Static, point):
    """Closed meshes (watertight, consistently wound; outward as trimesh's volume sign says):
    the first triangle a ray from the point meets faces away from it, by majority over three
    rays in generic directions (one cast each through the BVH; a ray through an edge or a
    grazing hit may decide wrongly, three rarely all do). Open meshes: the winding number above
    1/2 (see the module docstring)."""
    if not static.closed:
        return winding_number(p, point) > 0.5
    votes = [_faces_away(p, static, point, jnp.asarray(d, point.dtype)) for d in INSIDE_DIRECTIONS]
    return (votes[0] + votes[1] + votes[2]) >= 2


def traced_fields(params: MeshParams) -> dict:
    """What ``interface.checked_intersect`` verifies of a traced mesh: every triangle's three
    vertices finite, by triangle index (padding rows skipped)."""
    return {f"triangles.v{k}": (getattr(params, f"v{k}"), "finite", params.valid, None) for k in range(3)}


@final
class _Mesh(Representation, module=__name__):
    """The mesh representation as the registry hands it to the renderer."""

    name = "mesh"
    Config = MeshConfig
    #: as the frusta's (``frusta._scene._Frusta``): mesh_torus's render program compiled faster
    #: and ran faster with them (docs/choices.md#elemental-emitters); no YNNPACK fusions, as the
    #: frusta's bins (docs/choices.md#ynn-fusions)
    cpu_compiler_options = {"xla_cpu_use_fusion_emitters": False, "xla_cpu_experimental_ynn_fusion_type": ""}

    @staticmethod
    def exits_from_inside(cfg) -> bool:
        """Triangles are tested from both sides, so a ray from inside a closed mesh meets its exit."""
        return True


REPRESENTATION = _Mesh()
