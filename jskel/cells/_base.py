"""A cell object's base shape (Nürnberg 2011, Sec. 3.1.4): the inside test that decides which
cells of the tiled map are kept, as a host function over world points, with the shape's box and
a digest of its inputs for the precompute's cache key. A torus or a sphere in closed form, a
watertight mesh file voxelized once, or any other representation's own ``inside``."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Callable

import jax
import numpy as np

from .. import accel
from ._config import CellsConfig


def base_inside(cfg: CellsConfig) -> tuple[Callable, np.ndarray, np.ndarray, str]:
    """(inside(points (M,3) world float64) -> (M,) bool, lo, hi, a digest of the shape's inputs)."""
    b = cfg.base
    c = np.asarray(b.center, np.float64)
    if b.type in ("torus", "sphere"):
        return _analytic_inside(b, c)
    if b.type == "voxel_mesh":
        return _mesh_voxels_inside(b, c)
    return _object_inside(b, c)


class AxisInside:
    """An inside test written over coordinates that broadcast (``xyz(x, y, z) -> bool``), and
    callable as every base shape's test is, on points (M, 3). The precompute's voxel work passes
    a batch of tiles' voxel centres as three axes, (B, r, 1, 1), (B, 1, r, 1) and (B, 1, 1, r),
    instead of the (B, r^3, 3) points: the same float64 operations on the same values, so the
    same flags, without building the points, which dominated the precompute of a large torus."""

    def __init__(self, xyz: Callable):
        self.xyz = xyz

    def __call__(self, p):
        return self.xyz(p[:, 0], p[:, 1], p[:, 2])


def _analytic_inside(b, c: np.ndarray):
    """:func:`base_inside` of a torus (about the y axis) or a sphere centred at ``c``."""
    if b.type == "torus":
        def torus(x, y, z):
            q = np.hypot(x - c[0], z - c[2]) - b.major
            return q * q + (y - c[1]) ** 2 < b.minor * b.minor

        ext = np.array([b.major + b.minor, b.minor, b.major + b.minor])
        return AxisInside(torus), c - ext, c + ext, ""

    def sphere(x, y, z):
        return (x - c[0]) ** 2 + (y - c[1]) ** 2 + (z - c[2]) ** 2 < b.radius * b.radius

    return AxisInside(sphere), c - b.radius, c + b.radius, ""


def _mesh_voxels_inside(b, c: np.ndarray):
    """:func:`base_inside` of a watertight mesh file, voxelized and filled once (Sec. 3.1.4)."""
    import trimesh

    try:
        mesh = trimesh.load(b.path, force="mesh")
    except Exception as e:  # noqa: BLE001
        raise ValueError(f"object.base.path: cannot read mesh {b.path!r}: {e}") from None
    if not mesh.is_watertight:
        raise ValueError(f"object.base.path: mesh {b.path!r} is not watertight (the inside/outside voxelization of Sec. 3.1.4 needs a closed mesh)")
    digest = hashlib.sha256(Path(b.path).read_bytes()).hexdigest()
    # voxelize once and fill the inside (surface voxels, then scipy's hole fill): no ray tests,
    # so no rtree or Embree; ``base.voxels`` voxels along the longest side
    pitch = float(np.max(mesh.extents)) / float(b.voxels)
    grid, origin = filled_voxels(np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces), pitch)

    def inside(p):
        idx = np.round((np.asarray(p, np.float64) - c) / pitch).astype(np.int64) - origin
        ok = np.all((idx >= 0) & (idx < np.array(grid.shape)), axis=1)
        idx = np.clip(idx, 0, np.array(grid.shape) - 1)
        return ok & grid[idx[:, 0], idx[:, 1], idx[:, 2]]

    return inside, mesh.bounds[0] + c, mesh.bounds[1] + c, digest


def surface_points(v: np.ndarray, f: np.ndarray, spacing: float, budget: int = 1 << 22):
    """Points on every triangle of (vertices ``v``, faces ``f``), no two lattice neighbours
    farther apart than ``spacing``: triangle i is cut into k_i^2 similar triangles, k_i = its
    longest edge / spacing rounded up, and their corners are returned. This is the subdivision
    trimesh's ``voxelize_subdivide`` runs (every edge shorter than half a voxel), done in one
    vectorized pass per k instead of repeated splits of the mesh: on a 20,480-face icosphere at
    256 voxels a side that subdivision was nearly all of the precompute
    (docs/choices.md#voxel-mesh-subdivision). Yields (M, 3) arrays of
    at most about ``budget`` points (a triangle whose lattice is larger comes in bands of rows)."""
    p0, e1, e2 = v[f[:, 0]], v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]
    longest = np.sqrt(np.max([np.sum(e1 * e1, 1), np.sum(e2 * e2, 1), np.sum((e2 - e1) ** 2, 1)], axis=0))
    ks = np.maximum(np.ceil(longest / spacing).astype(np.int64), 1)
    for k in np.unique(ks):
        rows = np.nonzero(ks == k)[0]
        band = max(1, budget // (k + 1))  # lattice rows i per piece: at most k + 1 points each
        for i0 in range(0, k + 1, band):
            i = np.arange(i0, min(i0 + band, k + 1))
            ii = np.repeat(i, k + 1 - i)  # the lattice i + j <= k, rows i0 .. i0 + band
            jj = np.arange(ii.size) - np.repeat(np.cumsum(k + 1 - i) - (k + 1 - i), k + 1 - i)
            a, b = ii / k, jj / k
            step = max(1, budget // a.size)
            for s in range(0, rows.size, step):
                r = rows[s : s + step]
                yield (p0[r, None] + a[None, :, None] * e1[r, None] + b[None, :, None] * e2[r, None]).reshape(-1, 3)


def filled_voxels(v: np.ndarray, f: np.ndarray, pitch: float):
    """(grid (X, Y, Z) bool, origin (3,) int): the voxels of edge ``pitch`` (centred on
    multiples of it) that hold a point of the surface sampled at half a voxel
    (:func:`surface_points`, which keeps the surface's voxels 6-connected), with the holes they
    close filled (``scipy.ndimage.binary_fill_holes``); voxel (i, j, k) of the grid is the one
    centred at (origin + (i, j, k)) * pitch."""
    from scipy import ndimage

    used = v[np.unique(f)]  # the samples are convex combinations of these: the same box
    origin = np.round(used.min(0) / pitch).astype(np.int64)
    grid = np.zeros(np.round(used.max(0) / pitch).astype(np.int64) - origin + 1, bool)
    for p in surface_points(v, f, 0.5 * pitch):
        # (clipped: a sample one rounding past a vertex could round to the voxel past the box)
        i = np.clip(np.round(p / pitch).astype(np.int64) - origin, 0, np.array(grid.shape) - 1)
        grid[i[:, 0], i[:, 1], i[:, 2]] = True
    return ndimage.binary_fill_holes(grid), origin


def _inside_points(obj, xs):
    """(N,) bool inside test of ``obj`` (an ``interface.Object``) at points ``xs`` (N, 3), in
    groups of 4,096: an inside test that loops (a mesh's BVH walks) runs each vmapped group until
    its slowest point ends."""
    one = lambda x: obj.representation.inside(obj.params, obj.static, x)  # noqa: E731
    return accel.map_groups(jax.vmap(one), 4096, xs)


# one module-level jit: the Object's tree structure (representation, static options) keys its
# programs, so base objects of the same kind and shapes share one (a closure per build compiled anew)
_inside_jit = jax.jit(_inside_points)


def _object_inside(b, c: np.ndarray):
    """:func:`base_inside` of another representation's object (``base.object``): its own
    inside test, jitted over point batches."""
    from .. import registry

    kind = (b.object or {}).get("type")
    known = [n for n in registry.names() if n != "cells"]  # any representation's inside test but a cell object's own
    if kind not in known:
        raise ValueError(f"object.base.object.type: must be one of {', '.join(known)} (got {kind!r})")
    rep = registry.get(kind)
    try:
        ocfg = rep.Config.model_validate(b.object)
    except Exception as e:  # noqa: BLE001 - reported with its path
        first = str(e).splitlines()
        raise ValueError(f"object.base.object: {first[1] if len(first) > 1 else first[0]}") from None
    from ..interface import Object

    built = rep.build(ocfg, np.float32)
    obj = Object.of(rep, built)
    anchor = built.anchor

    def inside(p):
        out = np.empty(len(p), bool)
        for i in range(0, len(p), 1 << 18):
            q = p[i : i + (1 << 18)]
            pad = (1 << 18) - len(q)
            x = np.concatenate([q, np.repeat(q[-1:], pad, 0)]) - anchor - c
            out[i : i + len(q)] = np.asarray(_inside_jit(obj, np.float32(x)))[: len(q)]
        return out

    lo, hi = (np.asarray(v, np.float64) + c for v in built.bounds)
    return inside, lo, hi, json.dumps({"object": b.object, "files": _files_digest(b.object)}, sort_keys=True)


def _files_digest(section) -> dict:
    """SHA-256 of every file a section's strings name (a mesh, a height map, a texture), so a
    cached precompute is not reused after the file changed."""
    out = {}
    if isinstance(section, dict):
        for v in section.values():
            out.update(_files_digest(v))
    elif isinstance(section, list):
        for v in section:
            out.update(_files_digest(v))
    elif isinstance(section, str) and Path(section).is_file():
        out[section] = hashlib.sha256(Path(section).read_bytes()).hexdigest()
    return out
