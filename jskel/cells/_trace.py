"""Ray tracing cell-based objects (Nürnberg 2011, Sec. 3.2, Alg. 3.1-3.3), one ray at a time.

The object is a cube of N^3 tiles of edge ``size`` from corner ``lo``. A point's membership is
found as in Sec. 3.1.6: tile index = floor((p - lo) / size), voxel = the point's place in the
tile map, split index from the split map, code from the tile's packed words (Alg. 4.5).

Linear search (Alg. 3.1 rows 6-13): samples t_k = t_0 + k h along the ray from its entry into
the object's box, h = ``step`` x tile edge (world units) divided by |d|, until a sample lies in an
INSIDE cell. (Sec. 3.2.2 scales the initial step by the angle to the basic mesh's normal so that
grazing rays keep their 3D resolution in a depth-parametrized search; a step of fixed world
length along the ray has that resolution at every angle.) then ``bisection`` halvings of the last bracket (rows 19-28) put the hit on the
cell's boundary to h / 2^bisection. Deviation: the thesis enters at the rasterized basic mesh and
discards a ray that meets an OUTSIDE cell (Fig. 3.13) because the rasterizer supplies the next
entry; here the ray enters at the box and steps on through outside cells, which finds the same
first inside cell. Empty-tile skipping (Alg. 3.2 rows 11-16): in a tile with no INSIDE part the
march jumps to the first sample t_k past the tile's exit, so the samples (and the image) are
bitwise those of the march without skipping; only fewer are evaluated. Refraction marches
inside the object (Alg. 3.3) and skips tiles whose parts are all INSIDE the same way. A part
thinner than the step lies in voxels between two samples: where a step crosses two or three
voxel faces the march looks up the voxels between (:func:`between`) and a target among them
flags the ray (``FLAG_GRAZE``; the samples and the hit stay those of Alg. 3.1).

Normals come from the normal map (Alg. 4.8) at the hit's voxel; reflection and refraction follow
the law of reflection and Snell's law, with total internal reflection where sin > 1
(``jskel.optics``, which the integrator traces a cell object's modes with).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics import safe_div, safe_normalize, safe_sqrt
from ..rays import ulp_floor
from ._membership import INSIDE, lookup

TILE_HAS_INSIDE = 1
TILE_ALL_INSIDE = 2
#: bits of ``tile_flags`` above the two flags: the pyramid levels (:func:`tile_levels`)
EMPTY_SHIFT, FULL_SHIFT, LEVEL_MASK = 2, 6, 15


class CellParams(NamedTuple):
    """Device arrays of a cell object: tile map of split cells, packed memberships, tile flags,
    normal and colour maps, placement, step, offsets, environment, ior, reflectivity, and the
    search's sample cap and bisection count (traced: a sweep over them compiles one program).
    The split-index tables hold as many rows as the W membership words have slots (16 W + 1,
    index 0 the empty space), and the split-cell count S is a value, so another cell count
    whose S fills the same words renders through the same programs (issue 27). Likewise the
    tile tables (``words``, ``tile_flags``) are padded to the size bucket of the tile count
    (``executor.size_bucket``: tiles 1-8 share a shape, then 9-16, ...) and the count N itself
    is a value; the padding tiles lie outside the object's box, so nothing reads them. The tile
    map (``split``, ``normals``) and the colour map are padded the same way to the size buckets
    of their resolutions r and c, values too (``res``, ``cres``), so maps of 17 to 32 voxels a
    side share programs; the padding voxels lie past r (c), where no point of a tile falls."""

    split: jnp.ndarray  # (R,R,R) int32 split index of the r^3 tile map, 0 empty space, R = size_bucket(r)
    words: jnp.ndarray  # (B,B,B,W) uint32 packed membership of the N^3 tiles, B = size_bucket(N)
    tile_flags: jnp.ndarray  # (B,B,B) int32 TILE_HAS_INSIDE | TILE_ALL_INSIDE, and the pyramid levels (``tile_levels``)
    normals: jnp.ndarray  # (R,R,R,3) unit normals of Alg. 4.8 (0 inside a cell)
    colors: jnp.ndarray  # (C,C,C,3) tileable linear RGB of the c^3 colour map, C = size_bucket(c)
    lo: jnp.ndarray  # (3,) object corner, relative to the anchor
    size: jnp.ndarray  # () tile edge
    step: jnp.ndarray  # () linear-search step in tiles (1/16 .. 1/512 in Sec. 5.3)
    owner_off: jnp.ndarray  # (16 W + 1, 3) int32 part offsets (whole-cell key) of split indices 0..S, then 0 rows
    split_cell: jnp.ndarray  # (16 W + 1,) int32 cell index of each split index 0..S, then 0 rows
    env: jnp.ndarray  # (H,W,3) equirectangular environment, (1,1,3): procedural sky
    ior: jnp.ndarray  # () index of refraction of the inside cells
    reflectivity: jnp.ndarray  # () mirror weight k of the reflection mode
    max_steps: jnp.ndarray  # () int32 cap on linear-search samples per ray segment
    bisection: jnp.ndarray  # () int32 halvings of the last bracket (Alg. 3.1 rows 19-28)
    slots: jnp.ndarray  # () int32 split cells S (a value: tile maps whose S fill the same W words share programs)
    tiles: jnp.ndarray  # () int32 tiles N along each axis (a value: counts in one size bucket share programs)
    res: jnp.ndarray  # () int32 tile map resolution r (a value: resolutions in one size bucket share programs)
    cres: jnp.ndarray  # () int32 colour map resolution c (likewise)


class TraceOptions(NamedTuple):
    """Static option of the linear + binary search (Alg. 3.1): tile skipping. The sample cap and
    the bisection count are values in :class:`CellParams`."""

    skip: bool = True  # empty / full tile skipping
    voxels: bool = False  # the exact voxel walk (``_voxels.walk``) instead of the linear search
    pyramid: bool = True  # the walk skips aligned blocks of 2^l tiles whole (``tile_levels``)


def tile_levels(flags: np.ndarray) -> np.ndarray:
    """The occupancy pyramid over the tiles, flattened onto them: ``flags`` (B, B, B) int32 of
    TILE_HAS_INSIDE | TILE_ALL_INSIDE, returned with two 4-bit levels added per tile. Bits
    ``EMPTY_SHIFT``: the largest l such that the aligned block of 2^l tiles a side holding the
    tile has no INSIDE part; bits ``FULL_SHIFT``: the largest l such that every tile of that
    block is INSIDE only (0 where only the tile itself is, or it is not: the flag bits say
    which). Blocks are counted on the tiles padded with empty ones to a power of two, so a block
    that reaches past the object is empty there and never full.

    Levels l = 1 .. K of an occupancy pyramid (empty / full / mixed per block, K = ceil(log2 B))
    answer "can this block be crossed in one step" with one read per level; stored per tile they
    take one read, the tile's own, which the walk makes anyway (``_voxels.walk``)."""
    b = flags.shape[0]
    k = int(np.ceil(np.log2(b))) if b > 1 else 0
    if k > LEVEL_MASK:
        raise ValueError(f"object.tiles: {b} tiles a side need {k} pyramid levels, at most {LEVEL_MASK}")
    a = np.zeros((1 << k,) * 3, np.int32)
    a[:b, :b, :b] = flags & (TILE_HAS_INSIDE | TILE_ALL_INSIDE)
    empty, full = (a & TILE_HAS_INSIDE) == 0, (a & TILE_ALL_INSIDE) != 0
    e_lvl, f_lvl = np.zeros(a.shape, np.int32), np.zeros(a.shape, np.int32)
    for lvl in range(1, k + 1):
        n = a.shape[0] >> lvl
        w = 1 << lvl
        e_blk = empty.reshape(n, w, n, w, n, w).all(axis=(1, 3, 5))
        f_blk = full.reshape(n, w, n, w, n, w).all(axis=(1, 3, 5))
        up = lambda m: np.repeat(np.repeat(np.repeat(m, w, 0), w, 1), w, 2)  # noqa: E731
        e_lvl += up(e_blk)  # a block at l empty => its sub-block at l - 1 empty: the count is the level
        f_lvl += up(f_blk)
    out = a | (e_lvl << EMPTY_SHIFT) | (f_lvl << FULL_SHIFT)
    return out[:b, :b, :b].astype(np.int32)


def locate(p: CellParams, x):
    """(tile (3,) int32, in object, voxel (3,) int32) of a point relative to the anchor."""
    n, r = p.tiles, p.res
    u = (x - p.lo) / p.size
    tile = jnp.floor(u)
    inb = (tile >= 0) & (tile < n)
    inside_obj = inb[0] & inb[1] & inb[2]  # by component: under vmap a reduction over 3 is a library call
    local = u - tile
    vox = jnp.clip(jnp.floor(local * r.astype(x.dtype)), 0, r - 1).astype(jnp.int32)
    return jnp.clip(tile, 0, n - 1).astype(jnp.int32), inside_obj, vox


def membership_at(p: CellParams, x):
    """Code of the split cell at x (OUTSIDE beyond the object or in empty space)."""
    tile, ok, vox = locate(p, x)
    s = p.split[vox[0], vox[1], vox[2]]
    code = lookup(p.words[tile[0], tile[1], tile[2]], jnp.maximum(s - 1, 0))
    return jnp.where(ok & (s > 0), code, 0), tile, ok


def _min3(v):
    """min over a last axis of 3, by component (under vmap ``jnp.min`` is a library reduction on XLA:CPU)."""
    return jnp.minimum(jnp.minimum(v[..., 0], v[..., 1]), v[..., 2])


def _max3(v):
    """max over a last axis of 3, by component (:func:`_min3`)."""
    return jnp.maximum(jnp.maximum(v[..., 0], v[..., 1]), v[..., 2])


def box_interval(lo, hi, o, d, inv=None):
    """Slab test: (t_enter, t_exit) of the ray against the box [lo, hi] (t_enter > t_exit: miss);
    ``inv``: 1 / d as ``safe_div(1, d, inf)`` gives it, when the caller has it already."""
    inv = safe_div(1.0, d, jnp.inf) if inv is None else inv
    ta = (lo - o) * inv
    tb = (hi - o) * inv
    # a zero direction component: inside the slab (-inf, inf) or outside it (inf, -inf)
    inslab = (o >= lo) & (o <= hi)
    t0 = jnp.where(d == 0, jnp.where(inslab, -jnp.inf, jnp.inf), jnp.minimum(ta, tb))
    t1 = jnp.where(d == 0, jnp.where(inslab, jnp.inf, -jnp.inf), jnp.maximum(ta, tb))
    return _max3(t0), _min3(t1)  # by component (numerics.dot3: a reduction over 3 under vmap is slow)


class March(NamedTuple):
    t: jnp.ndarray  # boundary t (inf: none found)
    t_out: jnp.ndarray  # the last sample on the starting side
    steps: jnp.ndarray  # samples evaluated (int32), the voxels looked up between samples included
    found: jnp.ndarray
    floored: jnp.ndarray  # the step was below a few ulps of t and raised to them (FLAG_FLOAT_SPACING)
    stepped: jnp.ndarray  # a voxel between two samples was a target the samples missed, or may be (FLAG_GRAZE)


def march(p: CellParams, o, d, t_start, t_end, want_inside, opt: TraceOptions, cut=False) -> March:
    """Linear search from t_start for the first sample whose INSIDE-ness equals ``want_inside``
    (True: Alg. 3.1 / 3.2, looking for an inside cell; False: Alg. 3.3, leaving one; a Python
    bool or a traced one per ray), then bisection. Tiles with no INSIDE part (looking for one,
    Alg. 3.2 rows 11-16) or with INSIDE parts only (leaving, Alg. 3.3 rows 12-15) are jumped
    over to the first sample past their exit (bitwise the same samples). A step below
    ``rays.ulp_floor`` of the interval's far end (where t + h would round back to t) is raised to
    it and reported in ``floored``. Voxels crossed between two samples on the starting side (a
    part thinner than the step, Sec. 5.3: :func:`between`) are looked up, a target among them
    reported in ``stepped``. ``cut``: the last sample is t_end (:func:`_clamp`)."""
    h, floored = _step(p, o, d, t_start, t_end)
    inv = safe_div(1.0, d, jnp.inf)  # once a ray, for the tiles' exits
    vr = voxel_ray(p, o, d)

    def is_target(t):
        code, tile, ok = membership_at(p, o + t * d)
        return ((code == INSIDE) == want_inside), tile, ok

    def t_at(k):  # sample k
        return jnp.minimum(t_start + k.astype(o.dtype) * h, _clamp(t_end, cut))

    def body(st):
        k, found, evals, stepped, pend, k_next, had = st
        t = t_at(k)
        # the voxels between this sample and the one before (evaluated, or in a tile a skip
        # passed over: on the starting side); pend 1, 2: this iteration looks up the pend-th
        c, mid0, mid1 = between(p, vr, o, d, t_at(k - 1), t)
        probe = pend > 0
        found_here, tile, ok = is_target(jnp.where(probe, jnp.where(pend == 2, mid1, mid0), t))
        hit = ~probe & found_here
        flags = p.tile_flags[tile[0], tile[1], tile[2]]
        # c > 3 (a step above the voxel edge): the voxels between are not looked up; where this
        # sample's tile or the one before has an INSIDE part, one may be
        has = (flags & TILE_HAS_INSIDE) != 0
        unknown = (c > 3) & (has | had)
        stepped = stepped | (probe & found_here) | (~probe & (k > 0) & ~hit & unknown)
        can_skip = ok & jnp.where(want_inside, (flags & TILE_HAS_INSIDE) == 0, (flags & TILE_ALL_INSIDE) != 0)
        if opt.skip:
            lo = p.lo + tile.astype(o.dtype) * p.size
            _, t_exit = box_interval(lo, lo + p.size, o, d, inv)
            k_exit = jnp.ceil((t_exit - t_start) / h).astype(jnp.int32)
            nk = jnp.where(~hit & can_skip, jnp.maximum(k + 1, k_exit), k + 1)
        else:
            nk = k + 1
        # after a sample that is not a hit: look up the c - 1 <= 2 voxels between, then go on
        more = jnp.where(probe, pend < jnp.minimum(c, 3) - 1, (k > 0) & ~hit & (c >= 2) & (c <= 3))
        pend = jnp.where(more, pend + 1, 0)
        k_next = jnp.where(probe, k_next, nk)
        k = jnp.where(hit | more, k, k_next)
        return k, hit, evals + 1, stepped, pend, k_next, jnp.where(probe, had, has)

    def cond(st):
        k, found, evals = st[:3]
        return (~found) & (evals < p.max_steps) & (t_at(k) <= t_end) & ((k == 0) | (t_at(k - 1) < t_end))

    false, zero = jnp.asarray(False), jnp.int32(0)
    k, found, evals, stepped, _, _, _ = jax.lax.while_loop(cond, body, (zero, false, zero, false, zero, zero, false))
    a, b = _refine(lambda t: is_target(t)[0], t_start, _clamp(t_end, cut), k, h, p.bisection)
    inf = jnp.asarray(jnp.inf, o.dtype)
    return March(jnp.where(found, b, inf), jnp.where(found, a, inf), evals, found, floored, stepped)


def _clamp(t_end, cut):
    """The t the march's samples are clamped to: t_end where t_max ended the window inside the
    object's box (the window is searched to its end: a part just before t_max was a silent
    miss), else none. At the box's own exit the samples stop at the last one inside, as Alg. 3.1
    steps: a last sample on the box's face made 3 of 129 outward rays spawned from a
    refraction-mode cell hit it again (``tests/test_spawn.py``'s fuzz; the cause not traced)."""
    return jnp.where(cut, t_end, jnp.inf)


def _step(p: CellParams, o, d, t_start, t_end):
    """The march's step in t (``p.step`` cell sizes over |d|), raised to ``rays.ulp_floor`` of the
    interval's far end; (step, whether it was raised)."""
    dn = safe_sqrt(jnp.sum(d * d))
    h0 = safe_div(p.step * p.size, dn, 0.0)  # d = 0: no step, no NaN
    floor = position_spacing(o, d, t_start, t_end)
    return jnp.maximum(h0, floor), floor > h0


def position_spacing(o, d, t_start, t_end):
    """``rays.ulp_floor`` of a ray's interval [t_start, t_end] (its far end; the origin's
    magnitude in units of t): the float spacing, in t, of the positions along it."""
    far = jnp.maximum(jnp.abs(t_start), jnp.where(jnp.isfinite(t_end), jnp.abs(t_end), 0.0))
    return ulp_floor(far, safe_div(jnp.max(jnp.abs(o)), safe_sqrt(jnp.sum(d * d)), 0.0))


def _refine(is_target, t_start, t_clamp, k, h, n):
    """The last linear bracket [t_(k-1), t_k] ([t_start, t_start] at k = 0) after ``n`` halvings
    (:func:`_bisect`). The march's t carries no derivative (the surface's comes from the crossed
    voxel face, ``differentiable_root``), and a loop of a traced length cannot be reversed."""
    t_in = jnp.minimum(t_start + k.astype(h.dtype) * h, t_clamp)
    t_prev = jnp.where(k > 0, jnp.minimum(t_start + (k - 1).astype(h.dtype) * h, t_clamp), t_start)
    return _bisect(is_target, *jax.lax.stop_gradient((t_prev, t_in)), n)


def _bisect(is_target, a, b, n):
    """``n`` (traced int32, 0 allowed) bisection steps of [a, b] (b a target, a not): the last
    non-target and target t."""
    def bis(_, lh):
        a, b = lh
        mid = 0.5 * (a + b)
        hit = is_target(mid)
        return jnp.where(hit, a, mid), jnp.where(hit, mid, b)

    return jax.lax.fori_loop(0, n, bis, (a, b))


class VoxelRay(NamedTuple):
    """A ray in the tile map's voxel units (one voxel edge = 1, from the object's corner), once a ray."""

    q0: jnp.ndarray  # (3,) origin
    qd: jnp.ndarray  # (3,) direction
    inv: jnp.ndarray  # (3,) 1 / qd (inf where 0)


def voxel_ray(p: CellParams, o, d) -> VoxelRay:
    """The ray in voxel units, taken once before the march (no division at each sample)."""
    vox = p.size / p.res.astype(p.size.dtype)
    qd = d / vox
    return VoxelRay((o - p.lo) / vox, qd, safe_div(1.0, qd, jnp.inf))


def voxel_of(p: CellParams, x):
    """The tile map voxel (3,) (integers as floats) holding x, counted from the object's corner:
    :func:`locate`'s tile x r + voxel, bitwise where r is a power of two (u r and (u - tile) r
    are exact), so a sample and the voxels between it and the next agree on where a face lies."""
    return jnp.floor((x - p.lo) / p.size * p.res.astype(x.dtype))


def between(p: CellParams, vr: VoxelRay, o, d, ta, tb):
    """The voxels of the tile map that the ray passes between two samples ta < tb and no sample
    lands in (membership is constant on a voxel, Sec. 3.1.4): (c, mid0, mid1). The voxels'
    indices at the two ends (:func:`voxel_of`, as the samples were looked up) differ by c steps
    over the three axes: c <= 1, both voxels are sampled and nothing lies between; with a step
    below the voxel edge c <= 3 and the c - 1 voxels between hold the midpoints ``mid0``,
    ``mid1`` of the sorted face crossings (:func:`march` looks them up); c > 3 (a step above the
    voxel edge) is not told that way. It runs at every sample, so it is written by component
    (under vmap a reduction over 3 became a library call on XLA:CPU, as ``numerics.dot3``
    notes) and takes the face crossings in the ray's voxel frame (:func:`voxel_ray`) without
    a division."""
    va, vb = voxel_of(p, o + ta * d), voxel_of(p, o + tb * d)
    dv = jnp.abs(vb - va)
    c = (dv[0] + dv[1] + dv[2]).astype(jnp.int32)
    # the face each changing axis crosses (one step on it), at its t
    s = jnp.clip(jnp.where(va != vb, (jnp.maximum(va, vb) - vr.q0) * vr.inv, jnp.inf), ta, tb)
    s0, s2 = _min3(s), _max3(s)  # sorted by min, max and the one between (a sort costs more on a CPU)
    s1 = jnp.clip(s[0] + s[1] + s[2] - s0 - s2, s0, s2)
    return c, 0.5 * (s0 + s1), 0.5 * (s1 + s2)


def object_interval(p: CellParams, o, d, t_min, t_max):
    n = p.tiles
    t0, t1 = box_interval(p.lo, p.lo + n * p.size, o, d)
    return jnp.maximum(t0, t_min), jnp.minimum(t1, t_max)


def starts_inside(p: CellParams, o, d, t_min):
    """Alg. 3.3 row 3: does the ray start in an INSIDE cell (its first sample, at ``t_min``,
    inside the object's box and in an inside cell)? A ray from outside the box starts outside."""
    n = p.tiles
    enter, _ = box_interval(p.lo, p.lo + n * p.size, o, d)
    return (enter <= t_min) & (membership_at(p, o + t_min * d)[0] == INSIDE)


def normal_at(p: CellParams, x, d):
    """Alg. 4.8's normal at the voxel holding x (a point just inside the hit cell); -d where
    the voxel has none (deep inside a cell)."""
    _, _, vox = locate(p, x)
    nrm = p.normals[vox[0], vox[1], vox[2]]
    has = jnp.sum(nrm * nrm) > 0
    return jnp.where(has, nrm, safe_normalize(-d))


def color_at(p: CellParams, x):
    """Nearest texel of the tileable colour map at x."""
    c = p.cres
    u = (x - p.lo) / p.size
    local = u - jnp.floor(u)
    i = jnp.clip(jnp.floor(local * c.astype(x.dtype)), 0, c - 1).astype(jnp.int32)
    return p.colors[i[0], i[1], i[2]]


def cell_id(p: CellParams, x):
    """Global id of the whole cell at x: the key (tile - part offset, cell index) as one int."""
    n = p.tiles
    tile, ok, vox = locate(p, x)
    s = p.split[vox[0], vox[1], vox[2]]
    owner = tile - p.owner_off[s] + 2
    m = n + 4
    cells = p.slots // 8
    key = ((owner[0] * m + owner[1]) * m + owner[2]) * (cells + 1) + p.split_cell[s]
    return jnp.where(ok & (s > 0), key, -1).astype(jnp.int32)
