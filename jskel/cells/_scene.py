"""Scene-level API of the cell representation (re-exported by ``jskel.cells``): precompute (and
cache on disk) a cell object, then trace it."""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import NamedTuple, final

import jax
import jax.numpy as jnp
import numpy as np

from .. import checks
from ..compile.policy import data_dir, prepared_dir
from ..executor import size_bucket
from ..interface import Built, Object, OwnMaterial, Representation
from ..numerics import differentiable_root, safe_normalize
from ..rays import FLAG_FLOAT_SPACING, FLAG_GRAZE, FLAG_STEP_CAP, Hit, masked_hit
from ._base import base_inside as base_inside
from ._config import CellsConfig as CellsConfig
from ._membership import INSIDE, memory_table, membership, unpack, words_for
from ._tiles import OFFSETS, SplitCells, part_links, part_offsets, sphere_tile, split_cells, validate_tile_map, voronoi_tile
from ._search import first_hit
from ._voxels import INTO
from ._trace import TILE_ALL_INSIDE, TILE_HAS_INSIDE, CellParams, TraceOptions, cell_id, tile_levels, color_at, membership_at, normal_at, starts_inside

CACHE_VERSION = 1
REFRACTED = 0.85  # the refraction mode's weight of the refracted light (0.15 local)


class Static(NamedTuple):
    """Static options of a cell object: trace options, and ``two_sided``: a ray that starts in
    an inside cell gets its exit as the hit (the refraction mode, Alg. 3.3)."""

    options: TraceOptions
    two_sided: bool = False


# ---------------------------------------------------------------- tile map, normals, colours


def tile_map_of(cfg: CellsConfig) -> np.ndarray:
    tm = cfg.tile_map
    if tm.type == "voronoi":
        return voronoi_tile(tm.resolution, tm.cells, tm.seed)
    if tm.type == "spheres":
        return sphere_tile(tm.resolution, tm.cells, tm.radius, tm.seed)
    try:
        arr = np.load(tm.path, allow_pickle=False)
    except Exception as e:  # noqa: BLE001 - any reader failure is a bad config value
        raise ValueError(f"object.tile_map.path: cannot read {tm.path!r} as a .npy array: {e}") from None
    return validate_tile_map(arr, "object.tile_map.path")


def normal_map(tile: np.ndarray) -> np.ndarray:
    """Alg. 4.8: per voxel, the normalized sum of unit vectors towards the 26 neighbours (the
    tile wraps) holding another cell index; 0 where all neighbours share the voxel's cell."""
    out = np.zeros(tile.shape + (3,))
    for o in OFFSETS:
        nb = np.roll(tile, shift=tuple(-o), axis=(0, 1, 2))
        out += (nb != tile)[..., None] * (o / np.linalg.norm(o))
    n = np.linalg.norm(out, axis=-1, keepdims=True)
    return np.where(n > 0, out / np.where(n > 0, n, 1), 0.0)


def worley_colors(tile: np.ndarray, normals: np.ndarray, seed: int) -> np.ndarray:
    """A tileable 3D colour map (Sec. 3.1.7) in the cells' own structure: one seeded colour per
    cell, darkened on the cell boundary voxels (where Alg. 4.8 gives a normal); empty space grey."""
    rng = np.random.default_rng(seed + 7919)
    hue = rng.random(int(tile.max()) + 1)
    pal = 0.35 + 0.5 * np.stack([0.5 + 0.5 * np.cos(2 * np.pi * (hue + k / 3)) for k in range(3)], -1)
    pal[0] = 0.5
    col = pal[tile.astype(np.int64)]
    edge = np.sum(normals * normals, -1) > 0
    return np.where(edge[..., None], 0.6 * col, col) ** 2.2


# ---------------------------------------------------------------- precompute + cache


class CellObject(NamedTuple):
    """Host arrays of a precomputed cell object."""

    split: np.ndarray
    split_face: np.ndarray
    split_cell: np.ndarray
    offsets: np.ndarray
    words: np.ndarray
    normals: np.ndarray
    colors: np.ndarray
    lo: np.ndarray
    size: float
    info: dict


def _cache_key(cfg: CellsConfig, digest: str) -> str:
    keep = cfg.model_dump(mode="json", include={"base", "tile_map", "tiles", "margin", "coarse", "color_map"})
    if cfg.tile_map.type == "file":
        keep["tile_map_bytes"] = hashlib.sha256(Path(cfg.tile_map.path).read_bytes()).hexdigest()
    if cfg.color_map != "worley":
        keep["color_bytes"] = hashlib.sha256(Path(cfg.color_map).read_bytes()).hexdigest()
    keep["digest"], keep["version"] = digest, CACHE_VERSION
    return hashlib.sha256(json.dumps(keep, sort_keys=True).encode()).hexdigest()[:24]


def precompute(cfg: CellsConfig) -> CellObject:
    """Tile map, split cells, part offsets, membership (packed), normal and colour maps; from
    the cache folder when the same inputs were computed before."""
    inside, lo, hi, digest = base_inside(cfg)
    key = _cache_key(cfg, digest)
    if cfg.cache == "auto":  # jskel's cache directory, under its one policy: made 0700, refused if others may write it
        folder = data_dir("cells")
        folder = None if folder is None else prepared_dir(folder, "cell object cache")
    else:
        folder = Path(cfg.cache) if cfg.cache else None
    path = folder / f"{key}.npz" if folder is not None else None
    if path is not None and path.exists():
        z = np.load(path, allow_pickle=False)
        info = json.loads(str(z["info"]))
        info["cache"] = "hit"
        return CellObject(z["split"], z["split_face"], z["split_cell"], z["offsets"], z["words"], z["normals"],
                          z["colors"], z["lo"], float(z["size"]), info)
    t0 = time.perf_counter()
    tile = tile_map_of(cfg)
    sc: SplitCells = split_cells(tile)
    offsets = part_offsets(sc, part_links(sc), "object.tile_map")
    slots = len(sc.split_cell) - 1
    t1 = time.perf_counter()
    extent = float(np.max(hi - lo)) * (1 + 2 * cfg.margin)
    centre = 0.5 * (lo + hi)
    corner = centre - 0.5 * extent
    size = extent / cfg.tiles
    mem = membership(sc, offsets, inside, corner, size, cfg.tiles, coarse=cfg.coarse)
    t2 = time.perf_counter()
    normals = normal_map(sc.tile)
    if cfg.color_map == "worley":
        colors = worley_colors(sc.tile, normals, cfg.tile_map.seed)
    else:
        try:
            colors = np.asarray(np.load(cfg.color_map, allow_pickle=False), np.float64)
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"object.color_map: cannot read {cfg.color_map!r} as a .npy array: {e}") from None
        if colors.ndim != 4 or colors.shape[3] != 3 or len(set(colors.shape[:3])) != 1:
            raise ValueError(f"object.color_map: a colour map must be a (c, c, c, 3) array (got shape {colors.shape})")
        bad = np.argwhere(~np.all(np.isfinite(colors), axis=3))  # every texel with a NaN or inf, by its (i, j, k)
        checks.raise_all(checks.at("object.color_map", "not finite", bad, colors[tuple(bad[:checks.SHOW].T)], "texels"))
    codes = unpack(mem.words, slots)
    info = {
        "tile_resolution": int(tile.shape[0]), "cells_per_tile": int(sc.cells), "split_cells": int(np.count_nonzero(sc.split_cell)),
        "tiles": cfg.tiles, "tile_size": size, "active_tiles": mem.active_tiles, "voxels_tested": mem.voxels_tested,
        "coarse_samples": mem.coarse_tested, "tile_map_s": t1 - t0, "membership_s": t2 - t1, "precompute_s": time.perf_counter() - t0,
        "inside_split_cells": int(np.sum(codes == INSIDE)), "intersected_split_cells": int(np.sum(codes == 2)),
        "memory_bytes": {"split_map": int(sc.split.nbytes), "membership_map": int(mem.words.nbytes),
                         "normal_map": int(np.float32(normals).nbytes), "color_map": int(np.float32(colors).nbytes)},
        "memory_table_5_1_bytes": memory_table(int(tile.shape[0]), cfg.tiles, int(colors.shape[0])),
        "cache": "miss" if path is not None else "off",
    }
    obj = CellObject(sc.split, sc.split_face, sc.split_cell, offsets, mem.words, normals, colors, corner, size, info)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_suffix(".tmp.npz")
        np.savez_compressed(tmp, **{k: v for k, v in obj._asdict().items() if k != "info"}, info=json.dumps(info))
        tmp.replace(path)
    return obj


def environment_map(name: str) -> np.ndarray:
    """(1,1,3) placeholder for the procedural ``sky``, else an equirectangular image (linear)."""
    if name == "sky":
        return np.ones((1, 1, 3))
    from ..textures import load_texture

    return load_texture(name, "object.environment")


def tile_flags(words: np.ndarray, slots: int, present: np.ndarray) -> np.ndarray:
    codes = unpack(words, slots)
    has = np.any(codes == INSIDE, axis=-1)
    full = np.all((codes == INSIDE) | ~present, axis=-1)
    return (has * TILE_HAS_INSIDE + full * TILE_ALL_INSIDE).astype(np.int32)


def build(cfg: CellsConfig, dtype=np.float32) -> Built:
    """Precompute (or load from the cache) a cell object and cast it to device arrays: the
    split-cell tile map, packed memberships (Fig. 4.9), tile flags for skipping, normal and
    colour maps, environment; anchored at the centre of the object's cube."""
    obj = precompute(cfg)
    slots = len(obj.split_cell) - 1
    present = np.zeros(slots, bool)
    present[np.unique(obj.split[obj.split > 0]).astype(np.int64) - 1] = True
    extent = obj.size * cfg.tiles
    lo = np.asarray(obj.lo, np.float64)
    anchor = lo + 0.5 * extent
    rows = 16 * obj.words.shape[-1] + 1  # every slot the membership words hold, and index 0

    def slot_table(a):  # split indices 0..S, then inert rows (no split voxel holds their index)
        return jnp.asarray(np.concatenate([a, np.zeros((rows - len(a),) + a.shape[1:], a.dtype)]).astype(np.int32))

    def bucketed(a, n, dtype=None):  # n along the first three axes padded to n's size bucket (never read)
        pad = size_bucket(n) - n
        return jnp.asarray(np.pad(a, [(0, pad)] * 3 + [(0, 0)] * (a.ndim - 3)), dtype)

    res, cres = int(obj.split.shape[0]), int(obj.colors.shape[0])
    params = CellParams(
        bucketed(obj.split.astype(np.int32), res), bucketed(obj.words, cfg.tiles), bucketed(tile_levels(tile_flags(obj.words, slots, present)), cfg.tiles),
        bucketed(obj.normals, res, dtype), bucketed(obj.colors, cres, dtype), jnp.asarray(lo - anchor, dtype),
        jnp.asarray(obj.size, dtype), jnp.asarray(1.0 / cfg.steps_per_tile, dtype),
        slot_table(obj.offsets), slot_table(obj.split_cell),
        jnp.asarray(environment_map(cfg.environment), dtype), jnp.asarray(cfg.ior, dtype), jnp.asarray(cfg.reflectivity, dtype),
        jnp.asarray(cfg.max_steps, jnp.int32), jnp.asarray(cfg.bisection, jnp.int32), jnp.asarray(slots, jnp.int32),
        jnp.asarray(cfg.tiles, jnp.int32), jnp.asarray(res, jnp.int32), jnp.asarray(cres, jnp.int32),
    )
    static = Static(TraceOptions(cfg.skip, cfg.search == "voxels", cfg.pyramid), cfg.mode == "refraction")
    info = dict(obj.info)
    info["words_per_tile"] = words_for(slots)
    # the last bisection bracket's width; the voxel walk's hit lies _voxels.INTO of a voxel past the face
    voxel = float(obj.size / obj.split.shape[0])
    tol = voxel * INTO if cfg.search == "voxels" else float(obj.size / cfg.steps_per_tile * 0.5**cfg.bisection)
    # secondary rays start one voxel out of the hit cell (Alg. 3.2); refracted ones one linear
    # step through the surface, where Alg. 3.3 row 3 takes the sample that decides their side
    start = float(obj.size / cfg.steps_per_tile) if cfg.mode == "refraction" else voxel
    return Built(params, static, anchor, (lo, lo + extent), info, primitives=int(info["inside_split_cells"]), surface_tolerance=tol,
                 secondary_offset=start)


# ---------------------------------------------------------------- tracing


def intersect_one(p: CellParams, static: Static, origin, direction, t_min, t_max) -> Hit:
    """First hit (Alg. 3.1): t on the inside cell's boundary, Alg. 4.8 normal, uv 0, prim = the
    whole cell's global id (also written as ``cell.npy``); flags STEP_CAP where ``max_steps``
    samples ran out before the ray left the object, FLOAT_SPACING where the linear step was
    below a few ulps of t and raised to them, GRAZE where a voxel between two samples was a
    target no sample landed in (a part thinner than the step) or may be (``cells._trace.march``). With ``static.two_sided`` (refraction) a
    ray that starts in an inside cell gets its exit (Alg. 3.3): the normal and the cell are
    those of the cell it leaves (looked up at the last sample inside)."""
    m = first_hit(p, origin, direction, t_min, t_max, static.options, static.two_sided)
    x0 = origin + jnp.where(jnp.isfinite(m.t), m.t, 0.0) * direction
    # leaving: the ray started in an inside cell and searched for its exit (the search's own
    # choice, Alg. 3.3 row 3), not the membership at the hit, which lies on a cell boundary and
    # flipped there under rounding (1.3 % of a torus' cell ids changed with a translation)
    leaving = (jnp.isfinite(m.t) & starts_inside(p, origin, direction, t_min)) if static.two_sided else jnp.asarray(False)
    face, x_entered = _crossed_face(p, x0, direction)
    x_hit = jnp.where(membership_at(p, x0)[0] == INSIDE, x0, x_entered)  # x0 if it did not round out
    x_cell = jnp.where(leaving, origin + jnp.where(jnp.isfinite(m.t_out), m.t_out, 0.0) * direction, x_hit)
    # Alg. 4.8's normal, turned outward at the crossing: where a ray enters an inside cell, to
    # the side where half a voxel along it is outside while half a voxel against it is inside
    # (by the ray's direction alone, a smoothed normal at a grazing hit near an edge was turned
    # into the cell, and a secondary ray offset along it started inside: tests/test_spawn.py);
    # where that does not decide (thin parts), and in the two-sided cast of the refraction
    # mode (whose Alg. 3.3 reading orients by the ray, tests/test_cells_trace.py), by the ray
    n = normal_at(p, x_cell, direction)
    h = 0.5 * p.size / p.res.astype(p.size.dtype)
    x_probe = jnp.where(leaving, x_cell, x0)
    out_along, out_against = (membership_at(p, x_probe + k * h * n)[0] != INSIDE for k in (1.0, -1.0))
    by_ray = (jnp.sum(n * direction) > 0) != leaving
    probe = (out_along != out_against) & (not static.two_sided)
    n = jnp.where(jnp.where(probe, out_against, by_ray), -n, n)
    # derivatives (issue 9): cells are unions of tile-map voxels, so the boundary at the hit is
    # the voxel face the ray crosses there (the axis whose voxel coordinate is nearest an
    # integer), fixed in the tile frame: t(origin, direction, lo, size) is the root of
    # g(t) = e_axis . (o + t d - x_b), with x_b = lo + size u and u the hit's tile coordinates.
    # (Alg. 4.8's smoothed normal shades; it is not the geometry.) The search loop itself would
    # differentiate to zero.
    u = jax.lax.stop_gradient((x0 - p.lo) / p.size)

    def g(tt):
        return jnp.sum(face * (origin + tt * direction - (p.lo + p.size * u)))

    t = jnp.where(jnp.isfinite(m.t), differentiable_root(g, jnp.where(jnp.isfinite(m.t), m.t, 0.0)), m.t)
    x_in = origin + jnp.where(jnp.isfinite(t), t, 0.0) * direction
    cid = cell_id(p, x_cell)
    capped = (~m.found) & (m.steps >= p.max_steps)  # stopped by max_steps: counted, not silent
    flags = jnp.where(capped, FLAG_STEP_CAP, 0) | jnp.where(m.floored, FLAG_FLOAT_SPACING, 0) | jnp.where(m.stepped, FLAG_GRAZE, 0)
    return masked_hit(t, x_in, n, jnp.zeros((2,), origin.dtype), cid, flags)


def _crossed_face(p: CellParams, x0, direction):
    """(face, point): the tile-map voxel face a ray crosses at its hit x0 (a one-hot axis: the
    voxel coordinate nearest an integer, as the derivative takes it) and the point a quarter
    voxel past that face on the ray's side, in the voxel the ray entered. The march's t lies
    within its last bracket of the face; with the default 256 steps a tile and 10 halvings
    that is about an ulp of float32 positions, so x0 itself can fall in the voxel before the
    face, whose Alg. 4.8 normal is another cell's (docs/choices.md#crossed-face).
    Where x0 is not in an inside cell, the normal and the cell id are looked up here instead."""
    r = p.res.astype(x0.dtype)
    v = jax.lax.stop_gradient((x0 - p.lo) / p.size * r)
    face = jax.nn.one_hot(jnp.argmin(jnp.abs(v - jnp.round(v))), 3, dtype=x0.dtype)
    side = jnp.where(jnp.sum(face * direction) > 0, 0.25, -0.25)
    v_in = jnp.where(face > 0, jnp.round(v) + side, v)
    return face, p.lo + v_in * (p.size / r)


def _steps_batch(obj: Object, rays):
    """Per ray, what the primary search took: samples (``search: linear``) or voxels and
    skipped tiles (``voxels``), ``first_hit``'s own count (one module-level function: the static
    options ride in the ``Object`` pytree, so the executor compiles once per static)."""
    p, static = obj.params, obj.static

    def one(o, d, a, b):
        return first_hit(p, o, d, a, b, static.options, static.two_sided).steps

    return jax.vmap(one)(*rays)


def steps_per_ray(built: Built, rays, chunk: int = 4096) -> np.ndarray:
    """(N,) int: what the primary search took for each ray (:func:`_steps_batch`), in the rays'
    order (an image of them for camera rays in raster order)."""
    from ..executor import map_chunks

    return np.asarray(map_chunks(_steps_batch, Object(built.params, built.static, "cells"), rays, chunk=chunk, progress=False).out)


def traversal_stats(built: Built, rays, chunk: int = 4096) -> dict:
    """Steps per ray of the primary search (:func:`steps_per_ray`): mean, 99th percentile and
    max, deterministic counts beside the timings (issue 50 asks for them per search)."""
    steps = steps_per_ray(built, rays, chunk)
    return {"steps_per_ray_mean": float(np.mean(steps)), "steps_per_ray_p99": float(np.percentile(steps, 99)),
            "steps_per_ray_max": int(np.max(steps))}


def albedo(p: CellParams, static: Static, hit: Hit):
    """The cell colour map at a hit (3,) (Worley colours or a given map)."""
    return color_at(p, jnp.where(jnp.isfinite(hit.t), hit.position, 0.0))


def inside(p: CellParams, static: Static, point):
    """Whether ``point`` (3,), relative to the anchor, is in an inside cell (membership map)."""
    return membership_at(p, point)[0] == INSIDE


# ---------------------------------------------------------------- secondary rays


def environment(env: jnp.ndarray, d):
    """Radiance for an escaping direction: an equirectangular map (H,W,3), or, for the (1,1,3)
    placeholder of ``sky``, a procedural sky (horizon to zenith, dark ground)."""
    d = safe_normalize(d)  # a zero direction gives the horizon, not NaN
    if env.shape[0] == 1:
        up = jnp.clip(d[1], -1.0, 1.0)
        sky = jnp.where(up >= 0, (1 - up) * jnp.array([0.85, 0.9, 1.0]) + up * jnp.array([0.25, 0.45, 0.85]),
                        jnp.array([0.3, 0.27, 0.24]) * (1 + up) + jnp.array([0.12, 0.1, 0.08]) * (-up))
        return sky.astype(d.dtype)
    h, w = env.shape[0], env.shape[1]
    u = jnp.arctan2(d[0], -d[2]) / (2 * jnp.pi) + 0.5
    v = jnp.arccos(jnp.clip(d[1], -1.0, 1.0)) / jnp.pi
    i = jnp.clip(jnp.floor(v * h), 0, h - 1).astype(jnp.int32)
    j = jnp.clip(jnp.floor(u * w), 0, w - 1).astype(jnp.int32) % w
    return env[i, j]


def traced_fields(p: CellParams) -> dict:
    """What ``interface.checked_intersect`` verifies of a traced cell object's placement: its
    corner ``lo`` finite, its tile edge ``size``, search ``step`` and sample cap positive, its
    bisection count not negative."""
    return {"lo": (jnp.reshape(p.lo, (1, 3)), "finite", None, None), "size": (jnp.reshape(p.size, (1,)), "positive", None, None),
            "step": (jnp.reshape(p.step, (1,)), "positive", None, None),
            "max_steps": (jnp.reshape(p.max_steps, (1,)), "positive", None, None),
            "bisection": (jnp.reshape(p.bisection, (1,)), "nonnegative", None, None)}


@final
class _Cells(Representation, module=__name__):
    """The cells representation as the registry hands it to the renderer."""

    name = "cells"
    Config = CellsConfig
    own_environment = True

    @staticmethod
    def exits_from_inside(cfg) -> bool:
        """The refraction mode's cast reports a ray's exit from an inside cell (Alg. 3.3)."""
        return cfg.mode == "refraction"

    @staticmethod
    def own_material(cfg):
        """The modes as the shared integrator's material; escaping rays see the object's
        environment. Reflection (Sec. 3.2.3, Alg. 3.2): a mirror of weight ``reflectivity`` for
        ``bounces`` bounces, the last bounce's hit shaded whole. Refraction (Sec. 3.2.4, Alg.
        3.3): Snell's law at every boundary with ``ior`` (total internal reflection keeps the ray
        inside) for ``bounces`` boundary events after the first hit, each entered cell tinting
        the ray by 0.5 + 0.5 x its colour, no local light after the first hit, and after the
        last event the environment in the ray's direction: c = 0.15 local + 0.85 tint x
        environment. Zero bounces, or the first-hit mode: the default material."""
        if cfg.bounces == 0 or cfg.mode == "first_hit":
            return None
        if cfg.mode == "reflection":
            return OwnMaterial(reflectivity=cfg.reflectivity, bounces=cfg.bounces, last_local=True, asked_by=f"mode: {cfg.mode!r}")
        return OwnMaterial(transparency=REFRACTED, ior=cfg.ior, bounces=cfg.bounces, tint=True, local_once=True, last_env=True,
                           asked_by=f"mode: {cfg.mode!r}")

    @staticmethod
    def environment(p, static, direction):
        """The object's environment (``object.environment``: the procedural sky or a map)."""
        return environment(p.env, direction)

    @staticmethod
    def extra_aovs(built, hits) -> dict:
        """``cell``: the hit cell's global id (the hit's primitive), -1 on a miss."""
        return {"cell": hits.prim}


REPRESENTATION = _Cells()
