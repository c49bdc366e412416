"""Cell membership (Nürnberg 2011, Sec. 3.1.4-3.1.6, 4.4-4.5, Tables 4.1-4.2, Fig. 4.9, Table 5.1).

Object space is a cube of N^3 tiles; each tile holds the same split cells. A split cell of a
tile is INSIDE when all its voxels are inside the base shape, OUTSIDE when none is, else
INTERSECTED (Alg. 4.4 with Table 4.2's rules: the per-part min and max of the inside flag).
Sec. 4.5 merges the parts of one whole cell across tiles by the same rules; here a whole cell is
the key (tile - part offset, cell index) of ``_tiles.part_offsets`` and the merge is a segment
min / max over that key (``jax.ops.segment_min`` / ``segment_max``).

Voxelizing all (N r)^3 voxels is what the thesis does on the GPU slice by slice (Sec. 3.1.4); on
a CPU it is the cost to avoid. Tiles are first classified from a coarse grid of inside samples
(``coarse`` per tile edge, corners included): a tile whose 3^3 neighbourhood of tiles is sampled
all inside (or all outside) takes that membership for every part without voxel work; only the
*active* tiles (the rest) are voxelized, plus a ring of neighbours for the merge. The coarse
classification is exact when no feature of the base shape is thinner than a coarse sample
spacing (tile / coarse); ``coarse = r`` samples every voxel.

Codes (Table 4.1): 0 OUTSIDE, 1 INSIDE, 2 INTERSECTED, 3 UNSET. Fig. 4.9 packs 16 two-bit codes
per 32-bit word, 64 split cells per 128-bit tile code (Alg. 4.5): word = slot >> 4, shift =
(slot & 15) << 1, slot = split index - 1.
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..progress import bar as progress_bar
from ._base import AxisInside
from ._tiles import SplitCells

OUTSIDE, INSIDE, INTERSECTED, UNSET = 0, 1, 2, 3


def words_for(slots: int) -> int:
    """32-bit words per tile code for ``slots`` split cells (4 for the thesis' 64)."""
    return max(1, -(-2 * slots // 32))


def pack(codes) -> np.ndarray:
    """(..., S) codes in 0..3 -> (..., ceil(S/16)) uint32 words (Fig. 4.9, Alg. 4.5)."""
    codes = np.asarray(codes, np.uint32)
    s = codes.shape[-1]
    w = words_for(s)
    padded = np.full(codes.shape[:-1] + (16 * w,), UNSET, np.uint32)
    padded[..., :s] = codes
    shifts = (2 * np.arange(16, dtype=np.uint32))
    return np.bitwise_or.reduce(padded.reshape(codes.shape[:-1] + (w, 16)) << shifts, axis=-1).astype(np.uint32)


def unpack(words, slots: int) -> np.ndarray:
    """Inverse of :func:`pack`: (..., W) uint32 -> (..., slots) uint8."""
    words = np.asarray(words, np.uint32)
    shifts = (2 * np.arange(16, dtype=np.uint32))
    codes = (words[..., :, None] >> shifts) & np.uint32(3)
    return codes.reshape(words.shape[:-1] + (-1,))[..., :slots].astype(np.uint8)


def lookup(words, slot):
    """Alg. 4.5 in JAX: the code of split slot ``slot`` (0-based) in a tile's words (W,)."""
    word = jnp.take(words, slot >> 4, mode="clip")
    return ((word >> ((slot & 15) << 1).astype(jnp.uint32)) & jnp.uint32(3)).astype(jnp.int32)


def memory_table(cell_res: int, tiles: int, color_res: int = 128) -> dict:
    """Texture memory of Table 5.1 (bytes): an 8-bit cell (split) map, an RGBA8 colour map, an
    RGBA32F normal map (both at their resolutions) and 128-bit tile codes."""
    cell = cell_res**3
    color = 4 * color_res**3
    normal = 16 * cell_res**3
    member = 16 * tiles**3
    return {"cell_map": cell, "color_map": color, "normal_map": normal, "membership_map": member,
            "total": cell + color + normal + member}


class Membership(NamedTuple):
    words: np.ndarray  # (N,N,N,W) uint32 packed tile codes
    active_tiles: int  # tiles voxelized
    voxels_tested: int  # inside tests at voxel resolution
    coarse_tested: int  # inside tests of the coarse classification


def tile_axes(lo, size, tiles_idx: np.ndarray, res: int) -> tuple:
    """The world voxel-centre coordinates of the tiles at integer coordinates ``tiles_idx``
    (B, 3), one axis each, shaped to broadcast: x (B, r, 1, 1), y (B, 1, r, 1), z (B, 1, 1, r)."""
    g = (np.arange(res) + 0.5) / res
    x, y, z = (np.asarray(lo)[a] + (tiles_idx[:, a, None] + g[None, :]) * size for a in range(3))
    return x[:, :, None, None], y[:, None, :, None], z[:, None, None, :]


def tile_points(lo, size, tiles_idx: np.ndarray, res: int) -> np.ndarray:
    """World voxel centres (B, r^3, 3) of the tiles at ``tiles_idx`` (B, 3): :func:`tile_axes`
    broadcast together, x slowest."""
    axes = np.broadcast_arrays(*tile_axes(lo, size, tiles_idx, res))
    return np.stack(axes, -1).reshape(len(tiles_idx), -1, 3)


def classify_tiles(inside: Callable, lo, size: float, n: int, coarse: int):
    """(state (N,N,N) int8: 0 all outside, 1 all inside, -1 mixed at the coarse samples, and
    the number of samples)."""
    m = n * coarse + 1
    g = np.arange(m) / coarse
    flags = np.empty((m, m, m), bool)
    for i in range(m):  # slabs keep memory bounded
        pts = np.stack(np.meshgrid(g[i : i + 1], g, g, indexing="ij"), -1).reshape(-1, 3)
        flags[i] = np.asarray(inside(np.asarray(lo) + pts * size)).reshape(m, m)
    f = flags.astype(np.int8)
    # per tile: all of its (coarse + 1)^3 samples
    mins = np.ones((n, n, n), np.int8)
    maxs = np.zeros((n, n, n), np.int8)
    for a in range(coarse + 1):
        for b in range(coarse + 1):
            for c in range(coarse + 1):
                sub = f[a : a + n * coarse : coarse, b : b + n * coarse : coarse, c : c + n * coarse : coarse]
                mins = np.minimum(mins, sub)
                maxs = np.maximum(maxs, sub)
    state = np.where(mins == maxs, mins, -1).astype(np.int8)
    return state, m**3


def _dilate_not_uniform(state: np.ndarray) -> np.ndarray:
    """Active tiles: the 3^3 neighbourhood (clipped to the grid) is not one uniform value."""
    pad = np.pad(state, 1, mode="edge")
    n = state.shape[0]
    lo = np.full(state.shape, 2, np.int8)
    hi = np.full(state.shape, -2, np.int8)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                s = pad[i : i + n, j : j + n, k : k + n]
                lo = np.minimum(lo, s)
                hi = np.maximum(hi, s)
    return (lo != hi) | (state < 0)


def _ring(active: np.ndarray) -> np.ndarray:
    pad = np.pad(active, 1)
    n = active.shape[0]
    out = np.zeros_like(active)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                out |= pad[i : i + n, j : j + n, k : k + n]
    return out


@jax.jit
def _part_min_max(flags, split, slots):
    """Per tile (B, r^3) bool flags and the tile's split map (r^3,) -> min, max of the flag per
    slot (B, S), from the count of inside voxels of each slot: one (B, r^3) x (r^3, S) product
    with the slots' indicator (integer counts below 2^24, exact in float32 in any order of
    summation); min is 1 where every voxel of the slot is inside, max 1 where any is (an absent
    slot, which the caller masks, reads min 1, max 0); faster than a segment min / max over
    (tile, slot) (docs/choices.md#slot-counts)."""
    indicator = (split[:, None] == (slots[None, :] + 1)).astype(jnp.float32)
    count = jnp.dot(flags.astype(jnp.float32), indicator, precision=jax.lax.Precision.HIGHEST)
    size = jnp.sum(indicator, 0)
    return (count == size[None, :]).astype(jnp.int32), (count > 0).astype(jnp.int32)


def _measure_batch(act, i: int, batch: int, lo, size: float, res: int, inside: Callable, split_flat, slot_ids, mins, maxs):
    """Voxel-level min / max membership of the active tiles ``act[i : i + batch]`` (padded to
    ``batch`` by repeating the last, so one program serves every batch), into ``mins``/``maxs``."""
    idx = act[i : i + batch]
    pad = batch - len(idx)
    tiles = np.concatenate([idx, np.repeat(idx[-1:], pad, 0)])
    if isinstance(inside, AxisInside):  # the voxel centres as three axes that broadcast
        flags = np.asarray(inside.xyz(*tile_axes(lo, size, tiles, res))).reshape(batch, -1)
    else:
        flags = np.asarray(inside(tile_points(lo, size, tiles, res).reshape(-1, 3))).reshape(batch, -1)
    mn, mx = _part_min_max(jnp.asarray(flags), split_flat, slot_ids)
    mins[i : i + len(idx)] = np.asarray(mn)[: len(idx)]
    maxs[i : i + len(idx)] = np.asarray(mx)[: len(idx)]


def membership(sc: SplitCells, offsets: np.ndarray, inside: Callable, lo, size: float, n: int,
               coarse: int = 2, batch: int = 64, progress=None) -> Membership:
    """The packed membership map (Sec. 4.4-4.5) of the split cells ``sc`` tiled N^3 times from
    world corner ``lo`` with tile edge ``size``; ``inside(points (M,3) float64) -> (M,) bool``.
    The active tiles' voxel work (the long part) shows a progress bar on a terminal or in a
    notebook (``jskel.progress``), and calls ``progress(tiles_done)`` after each batch if given."""
    res = sc.tile.shape[0]
    slots = len(sc.split_cell) - 1  # split indices 1..S
    present = np.zeros(slots, bool)
    present[np.unique(sc.split[sc.split > 0]).astype(np.int64) - 1] = True
    state, coarse_n = classify_tiles(inside, lo, size, n, min(coarse, res))
    active = _dilate_not_uniform(state)
    work = _ring(active)
    codes_uniform = {v: np.where(present, v, UNSET).astype(np.uint8) for v in (OUTSIDE, INSIDE)}
    w = words_for(slots)
    words = np.empty((n, n, n, w), np.uint32)
    uni = np.where(state < 0, 0, state)  # non-active tiles are uniform
    for v in (OUTSIDE, INSIDE):
        words[uni == v] = pack(codes_uniform[v][None])[0]
    # voxel-level min / max for the active tiles, in batches of tiles (one compile: fixed batch)
    act = np.argwhere(active)
    split_flat = jnp.asarray(sc.split.reshape(-1).astype(np.int32))
    slot_ids = jnp.arange(slots)
    mins = np.empty((len(act), slots), np.int32)
    maxs = np.empty((len(act), slots), np.int32)
    with progress_bar(len(act), "cell membership", "tile") as bar:
        for i in range(0, len(act), batch):
            _measure_batch(act, i, batch, lo, size, res, inside, split_flat, slot_ids, mins, maxs)
            bar.update(min(batch, len(act) - i))
            if progress is not None:
                progress(min(batch, len(act) - i))
    # the merge set: active tiles (measured) and their ring (uniform values)
    ring = np.argwhere(work & ~active)
    ring_val = uni[tuple(ring.T)]
    tiles_m = np.concatenate([act, ring])
    mn_all = np.concatenate([mins, np.repeat(ring_val[:, None], slots, 1).astype(np.int32)])
    mx_all = np.concatenate([maxs, np.repeat(ring_val[:, None], slots, 1).astype(np.int32)])
    # whole-cell key of every (tile, slot): (tile - offset(slot), cell)
    cell_of = sc.split_cell[1:]
    owner = tiles_m[:, None, :] - offsets[None, 1:, :] + 2  # (M,S,3), >= 0
    m = n + 4
    key = ((owner[..., 0] * m + owner[..., 1]) * m + owner[..., 2]) * (sc.cells + 1) + cell_of[None, :]
    ok = present[None, :] & np.ones((len(tiles_m), 1), bool)
    uniq, seg = np.unique(key[ok], return_inverse=True)
    gmn = jax.ops.segment_min(jnp.asarray(mn_all[ok]), jnp.asarray(seg), num_segments=len(uniq))
    gmx = jax.ops.segment_max(jnp.asarray(mx_all[ok]), jnp.asarray(seg), num_segments=len(uniq))
    gmn, gmx = np.asarray(gmn)[seg], np.asarray(gmx)[seg]
    code = np.full((len(tiles_m), slots), UNSET, np.uint8)
    code[ok] = np.where(gmn == gmx, gmn, INTERSECTED).astype(np.uint8)
    words[tuple(tiles_m.T)] = pack(code)
    return Membership(words, int(len(act)), int(len(act) * res**3), int(coarse_n))
