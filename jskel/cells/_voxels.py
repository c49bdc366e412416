"""The exact search of a cell object (``search: voxels``): a walk through the tile map's voxels.

Membership is constant on a voxel of the tile map (Sec. 3.1.4: the split map assigns each voxel
one split cell, whose code the tile's words hold), so the first INSIDE point along a ray is the
entry of the first INSIDE voxel it crosses. Alg. 3.1's linear search samples the ray every
``steps_per_tile``-th of a tile and bisects the last bracket; it misses a part thinner than its
step and puts the boundary within h / 2^bisection. This walk visits every voxel the ray crosses
instead, in order (Amanatides and Woo 1987, "A fast voxel traversal algorithm for ray
tracing"), and stops at the first target: the hit is the crossed face itself, with no step to
choose, no bracket and no part stepped over. Each voxel's exit t is computed from its integer
index (no running sums, so no drift over a thousand voxels), and the index advances by one on
the axis that leaves first, so the walk ends even where rounding makes two exits equal.

Tile skipping as in Alg. 3.2 rows 11-16 and Alg. 3.3 rows 12-15: in a tile with no INSIDE part
(looking for one) or with INSIDE parts only (leaving one) the walk jumps to the tile's exit, to
the voxel there on the tile's far side; with ``pyramid`` (the default) to the exit of the
largest aligned block of 2^l tiles around it that can be skipped whole (an occupancy pyramid over
the tiles, stored per tile in the tile's flags: ``_trace.tile_levels``), so a run of empty tiles
costs a step per pyramid cell, and the one read a step makes stays the tile's own. A block's
exits are computed from its integer bounds, as a voxel's are.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._membership import INSIDE, lookup
from ._trace import EMPTY_SHIFT, FULL_SHIFT, LEVEL_MASK, TILE_ALL_INSIDE, TILE_HAS_INSIDE, CellParams, March, _min3, position_spacing, voxel_ray


#: how far past the crossed face a hit's t lies, in voxel edges
INTO = 2.0**-12
#: the float spacing of a ray's positions, in voxel edges, above which a walk is flagged
#: ``FLAG_FLOAT_SPACING`` (in float32, on an object 96 voxels wide: rays from 1e4 sizes away,
#: not from 1e3)
SPACING = 2.0**-5


def _first_axis(te):
    """One-hot (3,) bool of the axis whose exit ``te`` (3,) is smallest (ties: the lowest axis)."""
    x = (te[0] <= te[1]) & (te[0] <= te[2])
    y = ~x & (te[1] <= te[2])
    return jnp.stack([x, y, ~x & ~y])


def _code(p: CellParams, g, r):
    """(membership code, tile flags, tile) of voxel g (3,) int32 counted from the object's corner."""
    tile = g // r
    local = g - tile * r
    s = p.split[local[0], local[1], local[2]]
    code = lookup(p.words[tile[0], tile[1], tile[2]], jnp.maximum(s - 1, 0))
    return jnp.where(s > 0, code, 0), p.tile_flags[tile[0], tile[1], tile[2]], tile


def walk(p: CellParams, o, d, t_start, t_end, want_inside, skip: bool, pyramid: bool = True) -> March:
    """The first voxel from ``t_start`` whose INSIDE-ness equals ``want_inside`` (a Python bool
    or a traced one), before ``t_end``: ``t`` its entry (the crossed face, or ``t_start`` if the
    ray starts in one) plus :data:`INTO` of a voxel edge, ``t_out`` the middle of the voxel
    before it (a point on the starting side), ``steps`` the voxels and tiles visited; at most
    ``p.max_steps`` of them (a ray that reaches the cap is not found: the caller flags it).
    ``floored``: the float spacing of the ray's positions is above :data:`SPACING` of a voxel (a
    ray from far away); ``stepped`` is False: no voxel is passed over."""
    # the value only: the hit's derivative is the crossed face's root (``_scene.intersect_one``)
    p, o, d, t_start, t_end = jax.lax.stop_gradient((p, o, d, t_start, t_end))
    r = p.res
    nv = p.tiles * r
    # t from the ray's entry point, not its origin: a ray from far away keeps the exits' precision
    # (its origin, 1e5 object sizes off, spans 1e8 voxels, whose float32 spacing is 8 of them)
    tq = jnp.where(jnp.isfinite(t_start), t_start, 0.0)
    vr = voxel_ray(p, o + tq * d, d)
    pos = vr.qd > 0
    inc = jnp.where(pos, 1, -1).astype(jnp.int32)
    inf = jnp.asarray(jnp.inf, o.dtype)
    g0 = jnp.clip(jnp.floor(vr.q0), 0, nv - 1).astype(jnp.int32)

    def exits(face):  # t at which the ray reaches the planes ``face`` (3,) in voxel units
        return jnp.where(vr.qd != 0, face.astype(o.dtype) - vr.q0, 1.0) * vr.inv  # inf, never NaN, where qd = 0

    def body(st):
        g, t_in, t_before, evals, found = st
        code, flags, tile = _code(p, g, r)
        hit = (code == INSIDE) == want_inside
        te = exits(g + pos)
        axis = _first_axis(te)
        g_next, t_next = g + jnp.where(axis, inc, 0), _min3(te)
        if skip:  # to the far side of the tile, or of the largest skippable block of 2^l tiles
            # around it: its exit axis one voxel on, the others where the ray is
            can = jnp.where(want_inside, (flags & TILE_HAS_INSIDE) == 0, (flags & TILE_ALL_INSIDE) != 0)
            if pyramid:
                lvl = jnp.where(want_inside, jnp.right_shift(flags, EMPTY_SHIFT), jnp.right_shift(flags, FULL_SHIFT)) & LEVEL_MASK
                span = jnp.left_shift(r, lvl)
                blk = jnp.right_shift(tile, lvl)
                lo_v = blk * span
                tt = exits((blk + pos) * span)
            else:  # the tile's own bounds, written as before the pyramid: XLA:CPU compiles the
                # pyramid's form at level 0 into a much slower walk (docs/choices.md#walk-tile-bounds)
                span, lo_v = r, tile * r
                tt = exits((tile + pos) * r)
            t_jump, t_axis = _min3(tt), _first_axis(tt)
            across = jnp.clip(jnp.floor(vr.q0 + t_jump * vr.qd).astype(jnp.int32), lo_v, lo_v + span - 1)
            g_jump = jnp.where(t_axis, jnp.where(pos, lo_v + span, lo_v - 1), across)
            g_next, t_next = jnp.where(can, g_jump, g_next), jnp.where(can, t_jump, t_next)
        t_next = jnp.maximum(t_next, t_in)
        return (jnp.where(hit, g, g_next), jnp.where(hit, t_in, t_next), jnp.where(hit, t_before, t_in),
                evals + 1, hit)

    def cond(st):
        g, t_in, _, evals, found = st
        inside = jnp.all((g >= 0) & (g < nv))
        return (~found) & inside & (evals < p.max_steps) & (t_in <= t_end - tq)

    zero = jnp.zeros((), o.dtype)
    init = (g0, zero, zero, jnp.int32(0), jnp.asarray(False))
    _, t_in, t_before, evals, found = jax.lax.while_loop(cond, body, init)
    found = found & (t_in <= t_end - tq)
    t_in, t_before = tq + t_in, tq + t_before
    # 2^-12 of a voxel past the face, into the voxel found: a point computed from t lies in it
    # (as the linear search's t is the target end of its last bracket), so the colour map,
    # whose texels may share the voxel's faces, is read on the cell's side
    qn = jnp.sqrt(jnp.sum(vr.qd * vr.qd))
    t_hit = t_in + INTO / qn
    false = jnp.asarray(False)
    return March(jnp.where(found, t_hit, inf), jnp.where(found, 0.5 * (t_before + t_in), inf), evals, found,
                 _spaced(o, d, tq, t_end, qn), false)


def _spaced(o, d, t_start, t_end, qn):
    """Whether the float spacing of the ray's positions (``_trace.position_spacing``, the floor of
    the linear search's step) is above :data:`SPACING` of a voxel (``qn``: voxels per unit of t):
    which voxel a point near a face lies in is then uncertain."""
    return position_spacing(o, d, t_start, t_end) * qn > SPACING

