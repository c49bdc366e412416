"""The fit's term from the surface back to the points (``solver.cover``, issue 53): samples on
every segment's cone pulled towards the nearest point of the cloud.

The points' residuals measure how far each point lies from the frusta surface, never how far
the surface lies from the points: a surface may grow where no point is at no cost. Fitted to a
chain of 1,000 segments with outliers, the free tip stretched several segments long into the
outliers, where its cap claimed them; fitted to a neuron mesh, joints beside a side branch
swelled to two or three times the tube's radius, enclosing the branch's points (wrapped at the
``outside`` weight) while most of the swollen surface lay hundreds of units from any point
(docs/fitting.md). This is the other half of a two-sided (Chamfer) distance: ``AXIAL`` x
``AROUND`` samples on each segment's cone, ``c1 + u h m + (r1 + u (r2 - r1)) (cos a e1 + sin a
e2)`` (the cone through the joints' circles, Bhagvat et al. 2009, Sec. 2.1; rings at
``u`` = 1/4 and 3/4, away from the cutting planes, the second turned half a step), each
contributing the robust distance to its nearest point, with that point chosen without
gradient (as an ICP step does) so the residual moves the sample straight towards it, less a
dead zone of :data:`DEAD_ZONE` times the points' median spacing. Without it a sample on the
true surface was pulled towards a point half a spacing away, mostly along the surface, and on
a curved surface the chord to it runs inside: on bench_fit.yaml's 5-segment chain of 1,000
points the joints moved from 1.04 % of the length off the truth to 2.52 %, with the loss below
the truth's (docs/fitting.md).

Samples off the frusta surface (signed distance to the whole skeleton beyond the robust
``scale`` either way: a junction's child cone inside its parent's tube, or a ring beyond its
own piece's cutting plane where the next segment is thinner, which sticks out of the skeleton
and would pull the radius in) are left out. That switch is abrupt, and a fit can also escape
the term by hiding a ring inside a neighbour. Each segment gets the same samples whatever its
size, so the term pulls the surface onto the points and never shrinks it for its area alone.
The samples together weigh ``cover`` times the points (each sample's squared residual
``cover N / (S M)`` times a point's; :func:`weight`).

The nearest point: the points in Morton order (``_distance.spatial_order``) in blocks of
``BLOCK`` with their boxes, computed once on the host (the points never move); each sample
measures the ``NEAREST_BLOCKS`` blocks whose boxes are nearest it. The point found is the
nearest wherever the next-nearest box lies beyond it; not certified otherwise: where more
boxes than that hold the sample (Morton blocks that straddle a cell's boundary make long,
overlapping boxes) the nearest point can be missed, and the distance is then overstated by up
to the diagonal of a box. With four blocks, 7 of the 368 samples of a ring of cones around a
noisy torus' core missed theirs by up to 0.06 (0.8 of the dead zone); with six, none did
(``tests/scripts/cover_search_time.py``; tested in ``tests/test_fit_cover.py``). The blocks
are chosen through each segment's list (:func:`nearest_points`): an evaluation costs
segments x blocks box distances plus samples x ``GROUP_BLOCKS``, not samples x blocks
(16 S x N / 32), which grew as the points x segments that the fit's candidate blocks avoid for
the points (``solver.block``).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..numerics import dot3, safe_sqrt
from ._distance import UNSURE_SHARE, Geometry, _top, redo_unsure, spatial_order

AXIAL = (0.25, 0.75)  # where the rings of samples sit along each segment's axis
AROUND = 8  # samples around each ring
SAMPLES = len(AXIAL) * AROUND  # per segment
BLOCK = 32  # points per block of the nearest-point search
NEAREST_BLOCKS = 6  # blocks each sample measures
GROUP_BLOCKS = 32  # blocks each segment's samples choose them from
DEAD_ZONE = 2.0  # no pull on a sample within this many times the points' median spacing of a point


class PointIndex(NamedTuple):
    """The cloud for the nearest-point search: its points in Morton order in blocks (NB, B, 3)
    (the last padded with its last point), each block's box (NB, 3) x 2, and the points'
    ``spacing`` () (the median distance from a point to its nearest other point: the dead zone
    of :func:`dead_zone`)."""

    blocks: jax.Array
    lo: jax.Array
    hi: jax.Array
    spacing: jax.Array


def point_index(points, block: int = BLOCK) -> PointIndex:
    """The :class:`PointIndex` of ``points`` (N, 3) (host NumPy, the fit's normalised units)."""
    p = np.asarray(points)
    p = p[spatial_order(p)]
    nb = -(-len(p) // block)
    pad = nb * block - len(p)
    if pad:
        p = np.concatenate([p, np.repeat(p[-1:], pad, 0)])
    b = p.reshape(nb, block, 3)
    from scipy.spatial import cKDTree

    q = np.asarray(points)
    spacing = DEAD_ZONE * np.median(cKDTree(q).query(q, k=2)[0][:, 1]) if len(q) > 1 else 0.0
    return PointIndex(b, b.min(1), b.max(1), np.asarray(spacing, p.dtype))


def samples(g: Geometry):
    """(S, M, 3) the :data:`SAMPLES` points on each segment's cone (module docstring). The frame
    around the axis is ``e1 = m x a / |m x a|`` with ``a`` the coordinate axis least aligned with
    ``m`` (chosen without gradient; ``|m x a|`` >= sqrt(2/3) for a unit ``m``), ``e2 = m x e1``."""
    m = g.m
    pick = jax.lax.stop_gradient(jnp.argmin(jnp.abs(m), axis=-1))
    a = jax.nn.one_hot(pick, 3, dtype=m.dtype)
    e1 = jnp.cross(m, a)
    n1 = safe_sqrt(dot3(e1, e1))
    ok = n1 > 0  # m = 0 on a segment of no length: its samples on its rings' centres, derivative 0
    e1 = jnp.where(ok[:, None], e1 / jnp.where(ok, n1, 1.0)[:, None], 0.0)
    e2 = jnp.cross(m, e1)
    out = []
    for i, u in enumerate(AXIAL):  # static loops over the rings and angles, not over segments
        r = g.r1 + u * (g.r2 - g.r1)
        c = g.c1 + (u * g.h)[:, None] * m
        for k in range(AROUND):
            ang = 2.0 * math.pi * (k + 0.5 * i) / AROUND  # Python floats: weak types, the samples keep the fit's dtype
            out.append(c + r[:, None] * (math.cos(ang) * e1 + math.sin(ang) * e2))
    return jnp.stack(out, 1)


def _box_gap2(lo, hi, b_lo, b_hi):
    """Squared distances (..., NB) between boxes [lo, hi] (..., 3) and the blocks' boxes (NB, 3)
    (0 where they overlap)."""
    gap = jnp.maximum(jnp.maximum(b_lo - hi[..., None, :], lo[..., None, :] - b_hi), 0.0)
    return dot3(gap, gap)


def nearest_points(index: PointIndex, x):
    """(G, M, 3) for samples ``x`` (G, M, 3) in groups of M near ones (a segment's samples): the
    nearest point among the :data:`NEAREST_BLOCKS` blocks whose boxes lie nearest each sample,
    without gradient.

    Each group first keeps the :data:`GROUP_BLOCKS` blocks whose boxes lie nearest the box
    around its samples (work groups x blocks, not samples x blocks), and a sample measures the
    boxes of that list. A sample lies in its group's box, so a block off the list is no nearer
    the sample than the first block off the list is to the group's box: where the farthest of
    the sample's chosen boxes lies no further than that, they are the ones it would choose
    among every block. The samples where it lies further (a group box that many blocks touch,
    or a sample far from its group's points) choose among every block, ``cap`` at a time, as
    ``_distance._candidates``' unsure points do (``_distance.redo_unsure``); so every sample's
    blocks are its own choice."""
    x = jax.lax.stop_gradient(x)
    ng, m = x.shape[:2]
    nb = index.lo.shape[0]
    kg = min(GROUP_BLOCKS, nb)
    k = min(NEAREST_BLOCKS, kg)
    g2 = _box_gap2(x.min(1), x.max(1), index.lo, index.hi)  # (G, NB)
    top = _top(-g2, min(kg + 1, nb))
    lst = top[:, :kg]
    nxt = jnp.take_along_axis(g2, top[:, kg:], 1)[:, 0] if kg < nb else jnp.full((ng,), jnp.inf, x.dtype)
    gap = _box_gap2(x, x, index.lo[lst][:, None], index.hi[lst][:, None])  # (G, M, kg)
    sel = _top(-gap, k)  # (G, M, k), nearest first
    blk = jnp.take_along_axis(lst[:, None, :], sel, 2).reshape(ng * m, k)
    sure = (jnp.take_along_axis(gap, sel[..., k - 1 :], 2)[..., 0] <= nxt[:, None]).reshape(-1)
    flat = x.reshape(-1, 3)
    q = flat.shape[0]
    cap = min(q, max(m, q // UNSURE_SHARE))
    (blk,) = redo_unsure((blk,), ~sure, cap, lambda rows: (_top(-_box_gap2(flat[rows], flat[rows], index.lo, index.hi), k),))
    pts = index.blocks[blk].reshape(q, -1, 3)  # (Q, k B, 3)
    d = pts - flat[:, None]
    near = jnp.take_along_axis(pts, jnp.argmin(dot3(d, d), -1)[:, None, None], 1)[:, 0]
    return near.reshape(ng, m, 3)


def weight(n_points: int, n_segments: int, cover: float) -> float:
    """Each sample's squared-residual weight, ``cover N / (S M)``: all the samples together weigh
    ``cover`` times the points (before samples off the surface are left out, and before the
    points' ``outside`` weight)."""
    return cover * n_points / (n_segments * SAMPLES)
