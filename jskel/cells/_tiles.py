"""Tile maps and split cells (Nürnberg 2011, Sec. 3.1.3, 3.1.6, 4.1-4.3).

A *tile map* is an (r, r, r) integer array of cell indices (0: empty space) that tiles object
space periodically. Sec. 4.1 builds it from a 3D Voronoi diagram of k seeds; here the distance
is periodic (each seed's nearest image), so the map tiles seamlessly in all six directions.

*Split cells* (Sec. 4.2-4.3): a cell that crosses a tile face appears in a tile as several
parts. Each voxel starts with its *face code* (6 bits, Fig. 4.3: bit 2a for the low face of axis
a, bit 2a+1 for the high face) and Algorithm 4.2's pass ORs in the codes of its 26 neighbours of
the same cell; repeated until nothing changes (Alg. 4.1 bounds it by r passes), every part
carries the OR of the faces it touches. Sec. 4.3 then numbers the distinct face codes of each
cell in ascending order: split index = 8 (cell - 1) + rank + 1, so a cell has 8 placeholders and
split indices run 1..8 k (0: empty space).

Whole cells (for merging memberships across tiles, Sec. 4.5, and for the ``cell`` AOV): Alg.
4.7 finds a split part's partners in neighbouring tiles from pairwise face-code comparisons.
Here the partners come from the tile map itself: ``part_links`` lists which parts touch across
the tile's faces, edges and corners, and ``part_offsets`` walks them once per cell to place every
part of a whole cell relative to its first part. A part at tile t then belongs to the whole cell
(t - offset, cell index): merging is a segment reduction over that key. It is exact when each cell
index is one connected region of the periodic tile that does not reach itself in another tile
(a cell narrower than the tile); ``part_offsets`` checks both and names the cell otherwise.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

MAX_PARTS = 8  # split placeholders per cell (Sec. 4.2: a cell split over a corner has 8 parts)

# the 26 neighbour offsets of Alg. 4.2 / 4.8
OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) != (0, 0, 0)])


def _periodic_nearest(points, seeds, chunk=1 << 16):
    """(index of the nearest seed, squared distance) under the periodic distance on [0, 1)^3."""
    best = np.empty(len(points), np.int64)
    dist = np.empty(len(points))
    for i in range(0, len(points), chunk):
        d = points[i : i + chunk, None, :] - seeds[None]
        d -= np.round(d)  # nearest periodic image
        d2 = np.sum(d * d, -1)
        best[i : i + chunk] = np.argmin(d2, 1)
        dist[i : i + chunk] = np.min(d2, 1)
    return best, dist


def voxel_centres(res: int) -> np.ndarray:
    g = (np.arange(res) + 0.5) / res
    return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)


def voronoi_tile(res: int, cells: int, seed: int = 0, attempts: int = 100) -> np.ndarray:
    """(res,)*3 uint8 tile map: a tileable 3D Voronoi diagram of ``cells`` seeds under the
    periodic distance (Sec. 4.1), cell indices 1..cells. Seed sets whose cells touch their own
    periodic image (a cell as wide as the tile: the split-cell scheme of Sec. 4.2 cannot tell
    the two apart) are drawn again from the same seeded generator, so the result stays
    reproducible; an error names the count if ``attempts`` draws all fail."""
    rng = np.random.default_rng(seed)
    centres = voxel_centres(res)
    for _ in range(attempts):
        idx, _ = _periodic_nearest(centres, rng.random((cells, 3)))
        tile = (idx + 1).astype(np.uint8).reshape(res, res, res)
        if np.unique(tile).size != cells:
            continue  # a seed owns no voxel at this resolution
        sc = split_cells(tile)
        try:
            part_offsets(sc, part_links(sc))
        except ValueError:
            continue
        return tile
    raise ValueError(f"cells.tile_map: no draw of {cells} seeds in {attempts} gave cells narrower than the tile at {res}^3 (use more cells)")


def sphere_tile(res: int, cells: int, radius: float, seed: int = 0) -> np.ndarray:
    """Spherical cells with empty space (Fig. 4.1): voxels within ``radius`` (in tile units) of
    their nearest seed take its index, the rest 0."""
    seeds = np.random.default_rng(seed).random((cells, 3))
    idx, d2 = _periodic_nearest(voxel_centres(res), seeds)
    return np.where(d2 <= radius * radius, idx + 1, 0).astype(np.uint8).reshape(res, res, res)


def initial_face_codes(res: int) -> np.ndarray:
    """Fig. 4.3: bit 2a set on the low face of axis a, bit 2a + 1 on its high face."""
    i = np.arange(res)
    code = np.zeros((res, res, res), np.uint8)
    for a in range(3):
        shape = [1, 1, 1]
        shape[a] = res
        low = (i == 0).astype(np.uint8).reshape(shape) << (2 * a)
        high = (i == res - 1).astype(np.uint8).reshape(shape) << (2 * a + 1)
        code |= low | high
    return code


def _shift(x, off, fill):
    """x shifted so that out[v] = x[v + off] (no wrap; ``fill`` outside)."""
    pad = jnp.pad(x, 1, constant_values=fill)
    r = x.shape[0]
    i, j, k = (1 + int(o) for o in off)
    return pad[i : i + r, j : j + r, k : k + r]


@jax.jit
def propagate_face_codes(tile, code):
    """Alg. 4.1 / 4.2 as array passes: OR each voxel's code with its 26 same-cell neighbours'
    (within the tile, no wrap) until nothing changes. Empty space (0) stays 0. Returns (codes,
    passes)."""
    tile = jnp.asarray(tile, jnp.int32)
    code = jnp.where(tile > 0, jnp.asarray(code, jnp.int32), 0)
    same = [(_shift(tile, o, -1) == tile) & (tile > 0) for o in OFFSETS]

    def one_pass(c):
        out = c
        for o, s in zip(OFFSETS, same):
            out = out | jnp.where(s, _shift(c, o, 0), 0)
        return out

    def body(st):
        c, _, n = st
        nc = one_pass(c)
        return nc, jnp.any(nc != c), n + 1

    c, _, n = jax.lax.while_loop(lambda st: st[1], body, (code, jnp.asarray(True), jnp.int32(0)))
    return c, n


class SplitCells(NamedTuple):
    """A tile map with its split cells (Sec. 4.2-4.3)."""

    tile: np.ndarray  # (r,r,r) uint8 cell index, 0 empty
    face: np.ndarray  # (r,r,r) uint8 face code of each voxel's part
    split: np.ndarray  # (r,r,r) uint8 split index 1..8 cells, 0 empty
    split_face: np.ndarray  # (8 cells + 1,) uint8 face code of each split index (0 unused)
    split_cell: np.ndarray  # (8 cells + 1,) int32 cell index of each split index (0 unused)
    cells: int


def split_cells(tile: np.ndarray) -> SplitCells:
    """Face codes by propagation, then Sec. 4.3's ascending split indices per cell."""
    tile = np.asarray(tile)
    cells = int(tile.max())
    face, _ = propagate_face_codes(tile, initial_face_codes(tile.shape[0]))
    face = np.asarray(face, np.uint8)
    split = np.zeros_like(tile, np.int32)
    n = MAX_PARTS * cells + 1
    split_face = np.zeros(n, np.uint8)
    split_cell = np.zeros(n, np.int32)
    occupied = tile > 0
    pairs = np.unique(tile[occupied].astype(np.int32) * 64 + face[occupied])  # sorted by cell, then code
    cell_of, code_of = pairs // 64, pairs % 64
    for c in np.unique(cell_of):  # host loop over cells (at most a few dozen), not voxels
        codes = code_of[cell_of == c]
        if len(codes) > MAX_PARTS:
            raise ValueError(f"tile map: cell {c} splits into {len(codes)} parts (at most {MAX_PARTS})")
        for rank, fc in enumerate(codes):
            s = MAX_PARTS * (c - 1) + rank + 1
            split_face[s], split_cell[s] = fc, c
    lut = np.zeros(64 * (cells + 1), np.int32)
    for s in np.nonzero(split_cell)[0]:
        lut[split_cell[s] * 64 + split_face[s]] = s
    split[occupied] = lut[tile[occupied].astype(np.int32) * 64 + face[occupied]]
    return SplitCells(tile.astype(np.uint8), face, split.astype(np.uint8 if n <= 256 else np.int32), split_face, split_cell, cells)


def part_links(sc: SplitCells) -> np.ndarray:
    """(L, 5) int rows (p, q, dx, dy, dz): split part p of a tile touches part q of the tile at
    offset (dx, dy, dz) (26-neighbourhood across the tile's faces, edges and corners, same
    cell). Computed from the periodic tile map by one array pass per neighbour offset."""
    r = sc.tile.shape[0]
    split = sc.split.astype(np.int32)
    coords = np.indices(split.shape)
    rows = []
    for o in OFFSETS:
        crossing = [(coords[a] + o[a] < 0) * -1 + (coords[a] + o[a] >= r) * 1 for a in range(3)]
        cross = (crossing[0] != 0) | (crossing[1] != 0) | (crossing[2] != 0)
        nb = np.roll(split, shift=tuple(-o), axis=(0, 1, 2))
        ok = cross & (split > 0) & (nb > 0) & (sc.split_cell[split] == sc.split_cell[nb])
        if ok.any():
            rows.append(np.stack([split[ok], nb[ok], crossing[0][ok], crossing[1][ok], crossing[2][ok]], 1))
    if not rows:
        return np.zeros((0, 5), np.int64)
    return np.unique(np.concatenate(rows).astype(np.int64), axis=0)


def part_offsets(sc: SplitCells, links: np.ndarray, path: str = "cells.tile_map") -> np.ndarray:
    """(8 cells + 1, 3) int: the tile, relative to the cell's first part, in which each split
    part lies within one connected whole cell (a breadth-first walk over ``part_links``; host,
    over at most 8 parts per cell). A part at tile t belongs to the whole cell owned by tile
    t - offset: this replaces Alg. 4.7's pairwise face-code comparisons, which mis-assign parts
    that touch the faces of different axes (found on 8-cell Voronoi tiles). Raises when a cell
    reaches itself in another tile (it spans the tile) or is not one connected region."""
    off = np.zeros((len(sc.split_cell), 3), np.int64)
    adj: dict[int, list] = {}
    for p, q, dx, dy, dz in links:
        adj.setdefault(int(p), []).append((int(q), (int(dx), int(dy), int(dz))))
    for c in range(1, sc.cells + 1):
        parts = [int(s) for s in np.nonzero(sc.split_cell == c)[0]]
        if not parts:
            continue
        seen = {parts[0]: (0, 0, 0)}
        todo = [parts[0]]
        while todo:
            p = todo.pop()
            for q, d in adj.get(p, []):
                t = tuple(a + b for a, b in zip(seen[p], d))
                if q not in seen:
                    seen[q] = t
                    todo.append(q)
                elif seen[q] != t:
                    raise ValueError(f"{path}: cell {c} reaches itself in a neighbouring tile (it spans the tile; use smaller cells)")
        if len(seen) != len(parts):
            raise ValueError(f"{path}: cell {c} is not one connected region of the periodic tile")
        for s, t in seen.items():
            off[s] = t
    return off


def validate_tile_map(tile, path: str = "cells.tile_map") -> np.ndarray:
    """A cubic 3D integer array (2 to 512 a side) of indices 0..255 with at least one cell.
    (Whether its cells form whole cells is checked by ``part_offsets``.) Returns uint8."""
    arr = np.asarray(tile)
    if arr.ndim != 3:
        raise ValueError(f"{path}: a tile map must be a 3D array (got shape {arr.shape})")
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{path}: a tile map must hold integers (got dtype {arr.dtype})")
    if not (arr.shape[0] == arr.shape[1] == arr.shape[2]) or not 2 <= arr.shape[0] <= 512:
        raise ValueError(f"{path}: a tile map must be cubic, 2 to 512 voxels a side (got shape {arr.shape})")
    if arr.min() < 0 or arr.max() < 1 or arr.max() > 255:
        raise ValueError(f"{path}: cell indices must lie in 0..255 with at least one cell (got range {arr.min()}..{arr.max()})")
    return arr.astype(np.uint8)
