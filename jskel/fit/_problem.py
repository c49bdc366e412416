"""The least-squares problem of a fit (issue 10), in normalised coordinates.

The unknowns are the joints (J,3) and radii (J,) of a skeleton of fixed topology; the residual
of a point is its signed distance to the frusta surface (``_distance``), made robust (Huber or
Cauchy) so outliers pull linearly or less, and weighted more outside the surface than inside
where asked (``solver.outside``: radii that enclose points sampled on a closed surface), plus ``sqrt(smoothness)`` times the second
differences of the joints along each chain and the plane-validity penalty. Radii stay positive
by construction: ``r = min_radius + s softplus(u / s)`` with ``u`` the free parameter.

The problem is solved in normalised coordinates (points centred on their mean and divided by
their largest extent), so tolerances, damping, the robust scale and the smoothness weight mean
the same thing for a twig and a tree; :class:`Normaliser` maps to and from world units.

The radius parameter is the radius itself wherever the radius is more than a few
:data:`RADIUS_SOFTNESS` (``r = min_radius + s softplus(u / s)``, ``dr/du`` = 0.99 at r = 5 s):
Levenberg-Marquardt's damping ``mu I`` then treats radii and joints on one scale. With a plain
``softplus(u)`` the radius of a tube 0.005 of the extent wide moved 0.005 for a unit of ``u``, so
its curvature in ``J^T J`` was 2.5e-5 of a joint's, and once a rejected step had raised ``mu`` the
radii stopped moving: on the 50-segment grown tree of ``experiments/bench_fit_trees.yaml`` the
fit left them where the start put them (median error 14 % against the truth).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..frusta import ELLIPSE_MARGIN
from ..numerics import norm3
from . import _cover, _normal, _solvers
from ._config import SolverConfig
from ._distance import Geometry, Segments, Topology, distances_of, geometry, margins_of, spatial_order, topology_of


def _softplus_inv(y):
    y = np.maximum(np.asarray(y, np.float64), 1e-12)
    return np.where(y > 30, y, np.log(np.expm1(np.minimum(y, 30))))


class Sizes(NamedTuple):
    """The sizes a fit's program is compiled for: joints, segments, continuations (the topology's,
    or more: padding, ``_distance.Topology``) and the colours of its sparse normal equations."""

    joints: int
    segments: int
    conts: int
    colors: int


class Problem(NamedTuple):
    """Static description of a fit (hashable): its sizes, loss and solver settings. The topology
    itself is data (:class:`Layout`), so every topology of the same sizes shares one program."""

    sizes: Sizes
    loss: str
    scale: float
    smoothness: float
    min_radius: float
    validity: float
    candidates: int
    outside: float = 1.0
    block: int = 0
    per_block: int = 0
    cover: float = 0.0


class Layout(NamedTuple):
    """A fit's topology as arrays, padded to its :class:`Sizes` (traced with the points):
    the segments and continuations (``_distance.Topology``), each continuation's smoothing
    triple (K, 3) (the continued segment's start, the shared joint, the continuing segment's
    end; padding rows 0) and the sparse normal equations' structure (``_normal.Sparsity``)."""

    seg: Topology
    triples: np.ndarray
    sparsity: _normal.Sparsity


class Data(NamedTuple):
    """A fit's data: the points (N, 3), their nearest-point index where ``solver.cover`` > 0
    (``_cover.PointIndex``, else None) and the topology (:class:`Layout`)."""

    points: jax.Array
    index: object
    layout: Layout


def sizes_of(seg: Segments, n_joints: int) -> Sizes:
    """The exact :class:`Sizes` of a topology of ``n_joints`` joints."""
    return Sizes(int(n_joints), len(seg.start), len(seg.cont_b), _normal.structure(seg, n_joints).n_colors)


def _bucket(n: int) -> int:
    """``n`` rounded up to a multiple of an eighth of the power of two at or below it (at most
    12.5 % more; exact up to 16)."""
    if n <= 16:
        return n
    q = 1 << (n.bit_length() - 4)
    return -(-n // q) * q


#: a round whose exact sizes fit in the previous round's and whose joints are at least this
#: share of its joints reuses its sizes (and so its program; :func:`round_sizes`)
REUSE = 0.6


def round_sizes(exact: Sizes, previous: Sizes | None = None) -> Sizes:
    """The sizes a round of a fit with topology edits is compiled for (``_run.fitted_in_rounds``):
    the previous round's where the topology fits in them and is not much smaller (at least
    :data:`REUSE` of its joints), so that round's program runs again; else the exact sizes
    rounded up (:func:`_bucket`; colours to a multiple of 4), so a later round can reuse them.
    Padding costs work in every iteration (the dense (4J)^2 factorisation above all), a new
    program its compile."""
    if previous is not None and all(e <= p for e, p in zip(exact, previous)) and exact.joints >= REUSE * previous.joints:
        return previous
    return Sizes(_bucket(exact.joints), _bucket(exact.segments), _bucket(exact.conts), -(-exact.colors // 4) * 4)


VALID_MARGIN = 2.0 * ELLIPSE_MARGIN  # the penalty starts where |n . m| - sin(half-angle) falls below this


def problem_of(seg: Segments, s: SolverConfig, n_joints: int | None = None, sizes: Sizes | None = None) -> Problem:
    """The :class:`Problem` of fitting topology ``seg`` (``n_joints`` joints; default one past its
    largest joint index) with solver settings ``s``, compiled for ``sizes`` (default: exact)."""
    n = int(max(np.max(seg.start), np.max(seg.end)) + 1) if n_joints is None else int(n_joints)
    sz = sizes_of(seg, n) if sizes is None else Sizes(*(int(v) for v in sizes))
    return Problem(sz, s.loss, float(s.scale), float(s.smoothness), float(s.min_radius), float(s.validity), int(s.candidates),
                   float(s.outside), int(s.block), int(s.block_candidates), float(s.cover))


def layout_of(seg: Segments, pr: Problem) -> Layout:
    """``seg``'s :class:`Layout` padded to ``pr.sizes`` (host arrays; ValueError where it does not fit)."""
    sz = pr.sizes
    st = _normal.structure(seg, sz.joints)
    if st.n_colors > sz.colors:
        raise ValueError(f"topology: {st.n_colors} colours do not fit in {sz.colors}")
    triples = np.zeros((sz.conts, 3), np.int32)
    for i, (a, b) in enumerate(zip(seg.cont_a, seg.cont_b)):
        triples[i] = (seg.start[a], seg.start[b], seg.end[b])
    return Layout(topology_of(seg, sz.segments, sz.conts), triples, _normal.sparsity_of(st, sz.joints, sz.segments, sz.conts))


def point_residuals(d, pr: Problem):
    """The robust residuals of signed distances ``d`` (positive outside), those outside the
    surface weighted by ``sqrt(outside)`` (``solver.outside``: their squares by ``outside``)."""
    r = _solvers.robust_residuals(d, pr.loss, pr.scale)
    if pr.outside == 1.0:
        return r
    return jnp.where(d > 0, math.sqrt(pr.outside), 1.0) * r


#: ``s`` of the radius parameter ``r = min_radius + s softplus(u / s)`` (normalised units: a
#: fraction of the extent); module docstring
RADIUS_SOFTNESS = 1e-3


def radii_of(u, pr: Problem):
    """The radii (J,) of the radius parameters ``u`` (J,), normalised units."""
    return pr.min_radius + RADIUS_SOFTNESS * jax.nn.softplus(u / RADIUS_SOFTNESS)


def unpack(x):
    """The flat parameter vector (4J,) (jaxopt's least-squares solvers want one array) as
    joints (J,3) and the radius parameters u (J,)."""
    nj = x.shape[-1] // 4
    return x[..., : 3 * nj].reshape(x.shape[:-1] + (nj, 3)), x[..., 3 * nj :]


def penalty_rows(joints, g, pr: Problem, lay: Layout):
    """(K, E) penalty residuals per continuation (K = ``pr.sizes.conts``; padding rows zero):
    ``sqrt(smoothness)`` times the joints' second difference (3 rows) and the plane-validity
    penalty of its two segments (2 rows), each present when its weight is positive. A row
    depends only on the two segments' joints (``_normal`` relies on it)."""
    k = pr.sizes.conts
    parts = []
    if pr.smoothness > 0 and k:
        t = lay.triples
        parts.append(jnp.sqrt(pr.smoothness) * (joints[t[:, 0]] - 2.0 * joints[t[:, 1]] + joints[t[:, 2]]))
    if pr.validity > 0 and k:
        # keep every shared cutting plane cutting both its cones in ellipses (the geometry the
        # renderer and its bounds assume); an invalid plane leaves an unbounded piece that can
        # claim far outliers and so lower the loss below the truth's (see plane_margins)
        v = margins_of(g, lay.seg)
        parts.append(jnp.sqrt(pr.validity) * jnp.maximum(VALID_MARGIN - v, 0.0) / VALID_MARGIN)
    if not parts:
        return jnp.zeros((k, 0), joints.dtype)
    return jnp.where(lay.seg.cont[:, None], jnp.concatenate(parts, -1), 0.0)


def residual_count(n_points: int, pr: Problem) -> int:
    """How many residuals :func:`residuals` gives for ``n_points`` points: the points, the cover
    samples where ``pr.cover`` > 0, and 5 penalty rows per continuation (the solver's choice of
    dense or sparse normal equations counts them)."""
    return n_points + (_cover.SAMPLES * pr.sizes.segments if pr.cover > 0 else 0) + 5 * pr.sizes.conts


def _near_and_kept(g: Geometry, index, pr: Problem, lay: Layout):
    """(S, M, 3) each cover sample's nearest point and (S, M) whether the sample counts (on the
    frusta surface within the robust scale: not inside another segment, nor beyond its own
    piece's cutting plane where the next segment is thinner, outside the skeleton; never on a
    padding segment), both without gradient (``_cover``)."""
    g = jax.lax.stop_gradient(g)
    xs = _cover.samples(g)
    flat = xs.reshape(-1, 3)
    near = _cover.nearest_points(index, xs)
    d = distances_of(g, lay.seg, flat, pr.candidates, *blocks_of(pr, flat.shape[0]))[0].reshape(xs.shape[:2])
    return near, (jnp.abs(d) <= pr.scale) & lay.seg.live[:, None]


def _cover_of(xs, near, kept, pr: Problem, lay: Layout, n_points: int, spacing):
    """The cover residuals of samples ``xs`` (..., 3) towards their ``near`` points, zero where
    not ``kept``: the distance less the points' ``spacing`` (none within it: ``_cover``'s dead zone)."""
    d = jnp.maximum(norm3(xs - near) - spacing, 0.0)
    w = jnp.sqrt(_cover.weight(n_points, jnp.sum(lay.seg.live), pr.cover)).astype(xs.dtype)  # the live segments' count
    return jnp.where(kept, w * _solvers.robust_residuals(d, pr.loss, pr.scale), 0.0)


def cover_rows(g: Geometry, index, pr: Problem, lay: Layout, n_points: int):
    """(S * M,) the residuals of the term from the surface back to the points (``solver.cover``,
    ``_cover``): each sample's robust distance to its nearest point."""
    near, kept = _near_and_kept(g, index, pr, lay)
    return _cover_of(_cover.samples(g), near, kept, pr, lay, n_points, index.spacing).reshape(-1)


def cover_segment_rows(flat, index, pr: Problem, lay: Layout, n_points: int):
    """(r (S, M), dr/dflat (S, M, 17)) of :func:`cover_rows` by segment, for the sparse normal
    equations: a sample's residual depends on its own segment's 17 numbers alone."""
    near, kept = _near_and_kept(_normal.geometry_of_flat(flat), index, pr, lay)

    def one(row, nr, kp):
        f = lambda r: _cover_of(_cover.samples(_normal.geometry_of_flat(r[None]))[0], nr, kp, pr, lay, n_points, index.spacing)  # noqa: E731
        return f(row), jax.jacfwd(f)(row)

    return jax.vmap(one)(flat, near, kept)


def _data(data: Data, pr: Problem):
    """(points, index, layout) of a fit's data; a ValueError where ``solver.cover`` needs the
    index and the data has none."""
    if pr.cover > 0 and data.index is None:
        raise ValueError("solver.cover > 0 needs the points with their nearest-point index (_fit.data_of)")
    return data.points, data.index, data.layout


def residuals(x, data: Data, pr: Problem):
    """Robust point residuals (N,), the cover rows where ``pr.cover`` > 0 (:func:`cover_rows`),
    then the penalty rows (:func:`penalty_rows`), in normalised units."""
    points, index, lay = _data(data, pr)
    joints, u = unpack(x)
    g = geometry(joints, radii_of(u, pr), lay.seg)  # once, for the distances and the plane margins
    d = distances_of(g, lay.seg, points, pr.candidates, *blocks_of(pr, points.shape[0]))[0]
    r = [point_residuals(d, pr)]
    if pr.cover > 0:
        r.append(cover_rows(g, index, pr, lay, points.shape[0]))
    return jnp.concatenate(r + [penalty_rows(joints, g, pr, lay).reshape(-1)])


def normal_equations(x, data: Data, pr: Problem):
    """(r, J^T J, J^T r) of :func:`residuals` at ``x``, assembled from the problem's sparsity
    (``_normal``): no dense Jacobian, so LM and Gauss-Newton fit long chains in memory."""
    points, index, lay = _data(data, pr)

    def model(x):
        joints, u = unpack(x)
        g = geometry(joints, radii_of(u, pr), lay.seg)
        return g, penalty_rows(joints, g, pr, lay)

    cover = (lambda flat: cover_segment_rows(flat, index, pr, lay, points.shape[0])) if pr.cover > 0 else None
    return _normal.normal_equations(x, points, model, lay.seg, lay.sparsity, pr.sizes.colors, pr.candidates,
                                    lambda d: point_residuals(d, pr), *blocks_of(pr, points.shape[0]), cover=cover)


def dense_equations(x, data: Data, pr: Problem):
    """(r, J^T J, J^T r) of :func:`residuals` at ``x`` with the dense Jacobian: the residuals
    linearized once and the linear map pushed along every unknown's unit vector under ``vmap``
    (forward mode, (P, M) for P unknowns and M residuals), so the program holds the residuals'
    forward pass once, then one batched tangent pass."""
    r, lin = jax.linearize(lambda v: residuals(v, data, pr), x)
    jt = jax.vmap(lin)(jnp.eye(x.shape[-1], dtype=x.dtype))  # (P, M): row p is dr/dx_p
    return r, jt @ jt.T, jt @ r


def loss(x, data: Data, pr: Problem):
    r = residuals(x, data, pr)
    return 0.5 * jnp.sum(r * r)


class Normaliser(NamedTuple):
    centre: np.ndarray
    extent: float

    def points(self, p):
        return (np.asarray(p, np.float64) - self.centre) / self.extent

    def start(self, joints, radii, pr: Problem):
        """The parameter vector (4 ``pr.sizes.joints``,) of a start in world units; joints past
        the start's own (padding) at the centre with radius parameter 0 (in no segment: they
        never move)."""
        j = (np.asarray(joints, np.float64) - self.centre) / self.extent
        u = RADIUS_SOFTNESS * _softplus_inv((np.asarray(radii, np.float64) / self.extent - pr.min_radius) / RADIUS_SOFTNESS)
        pad = pr.sizes.joints - len(j)
        if pad < 0:
            raise ValueError(f"init.skeleton: {len(j)} joints do not fit in the problem's {pr.sizes.joints}")
        return np.concatenate([j.reshape(-1), np.zeros(3 * pad), u, np.zeros(pad)])

    def world(self, x, pr: Problem, n_joints: int | None = None):
        """Joints and radii in world units, the first ``n_joints`` (default all; past them:
        padding) (float64 NumPy: :func:`radii_of` on the host, so no device operation compiles
        a program of its own)."""
        joints, u = unpack(np.asarray(x, np.float64))
        joints, u = joints[:n_joints], u[:n_joints]
        r = (pr.min_radius + RADIUS_SOFTNESS * np.logaddexp(u / RADIUS_SOFTNESS, 0.0)) * self.extent
        return joints * self.extent + self.centre, r


def ordered(points, pr: Problem) -> np.ndarray:
    """``points`` (host) in the order the fit reads them: along a Morton curve where the
    candidate choice goes by blocks of consecutive points (``pr.block``, more segments than a
    block's list and more points than a block; ``_distance._candidates``), else as given. The
    loss is a sum over the points, so their order changes only its rounding (but a fit's path
    can turn on that)."""
    p = np.asarray(points)
    return p[spatial_order(p)] if blocked(pr, len(p)) else p


#: points x segments from which the candidate choice goes by blocks (below it the choice over
#: every segment costs little, and the blocks' program would be compiled for nothing)
BLOCK_FROM = 1 << 20


def blocked(pr: Problem, n: int) -> bool:
    """Whether a fit of ``n`` points chooses its candidates by blocks (``solver.block``)."""
    s = pr.sizes.segments
    return pr.block > 0 and 0 < pr.candidates < pr.per_block < s and n > pr.block and n * s >= BLOCK_FROM


def blocks_of(pr: Problem, n: int) -> tuple[int, int]:
    """(block, per_block) of ``_distance.distances_of`` for ``n`` points: (0, 0) unless :func:`blocked`."""
    return (pr.block, pr.per_block) if blocked(pr, n) else (0, 0)


def normaliser_of(points) -> Normaliser:
    c = points.mean(0)
    e = float(np.max(np.ptp(points, axis=0)))
    if not e > 0:
        raise ValueError("points: every point is at the same place (the cloud has no extent)")
    return Normaliser(c, e)
