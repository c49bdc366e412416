"""Skeleton -> conical frusta on the host (float64), Bhagvat et al. 2009, Sec. 2.1-2.3.

The geometry itself (axes, the cutting planes of Eq. 3-5, caps, the u-aligned frames and twist
of Sec. 2.3) is ``_geometry.frusta_fields``, the same JAX function the device rebuild and the
fit use; here NumPy evaluates its jaxpr in float64 (``jskel.compile.host_eval``: no XLA compile), traced
inside a scoped ``jax.enable_x64(True)`` (jax >= 0.8's context manager: the process-wide
``jax_enable_x64`` stays as the caller set it), on the topology padded to a power of two rows
so skeletons of similar size share one trace.

Minor-axis matching (Sec. 2.2, optional) stays a host loop over depth levels: the base radius
of a continuation is rescaled until the minor axes of the two elliptical cuts agree,
recomputing the cutting planes (``_geometry.cutting_planes``) each time.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..compile.host_eval import HostFn
from ._geometry import PLANE_KINDS, PLANE_SPLIT, cutting_planes, frusta_fields, medial_normal, padded_topology, plane_reach, segment_axes
from ._skeleton import Topology


class FrustaArrays(NamedTuple):
    """Per-segment float64 arrays (S first); the frame and planes are ``_geometry``'s."""

    c1: np.ndarray  # (S,3) base joint
    m: np.ndarray  # (S,3) unit axis
    u: np.ndarray  # (S,3) frame x
    w: np.ndarray  # (S,3) frame z (u = 0 direction)
    h: np.ndarray  # (S,) length
    r1: np.ndarray  # (S,) radius at C1
    r2: np.ndarray  # (S,) radius at C2
    nb: np.ndarray  # (S,3) bottom plane normal (n . M > 0)
    db: np.ndarray  # (S,) bottom plane offset: n . (P - C1) >= db inside
    nt: np.ndarray  # (S,3) top plane normal
    dt: np.ndarray  # (S,) top plane offset: n . (P - C1) <= dt inside
    cap_b: np.ndarray  # (S,) bool: bottom closed by a flat cap
    cap_t: np.ndarray  # (S,) bool
    u_off: np.ndarray  # (S,) u offset (turns) from the twist of the segments below
    twist: np.ndarray  # (S,) twist (turns per unit v)
    v_off: np.ndarray  # (S,) number of segments before this one along its chain (v spans segments)


def minor_semi_axis(c1, m, r1, k, n, p, nm):
    """Minor semi-axis of the ellipse cut from the cone (c1, m, r1, slope k) by plane (n, p).

    The major axis lies in the medial plane (normal ``nm``); the minor axis is along ``nm``
    through the ellipse centre. It is found as the half chord of the cut along ``nm`` through
    the centre of the major axis (Sec. 2.2).
    """
    # major axis endpoints: intersect the plane with the two side lines in the medial plane
    s = np.cross(m, nm)
    ends = []
    for sign in (+1.0, -1.0):
        base = c1 - sign * r1[:, None] * s
        dirn = m - sign * k[:, None] * s
        t = np.sum(n * (p - base), -1) / np.sum(n * dirn, -1)
        ends.append(base + t[:, None] * dirn)
    cm = 0.5 * (ends[0] + ends[1])
    y = np.sum((cm - c1) * m, -1)
    rad = cm - c1 - y[:, None] * m
    dperp2 = np.sum(rad * rad, -1)
    return np.sqrt(np.maximum((r1 + k * y) ** 2 - dperp2, 0.0))


# The host geometry's fewest rows and depth levels: every skeleton up to 32 segments and 16
# levels shares one executable (a scene's one-segment floor, column and rod and a 30-segment
# saguaro compiled two before); padding rows cost nothing to run and padding levels are never
# visited (the loop runs the skeleton's own depth)
GEOMETRY_ROWS = 32
GEOMETRY_LEVELS = 16


def _bucket(n: int) -> int:
    """The next power of two from ``n`` (at least 8): padded shapes that many skeletons share."""
    return max(8, 1 << (int(n) - 1).bit_length())


# The build runs its geometry once on a few dozen to a few thousand rows: NumPy evaluates its
# jaxpr without a compile (``jskel.compile.host_eval``), several times faster than XLA:CPU compiles it
# for a single run (docs/choices.md#host-build). Where its evaluations add up to
# ``host_eval.COMPILE_AFTER_S`` (a deep skeleton, or an animation's frames), XLA compiles it with
# its default optimisation: it then runs for every later build of those shapes, and on the
# dancing cacti the compiled geometry ran about a third faster so than at backend level 0
# without LLVM's expensive passes, for about the same compile; on the 4,176-segment neuron the
# compile took longer (docs/choices.md#host-build)
_HOST_OPTS: dict = {}
_fields_host = HostFn(frusta_fields, compiler_options=_HOST_OPTS)


def _axes_and_planes_of(joints, radii, topo, r1):
    """The axes and every row's cutting plane with the row it continues (placeholders on rows
    that continue nothing), with base radii ``r1`` (N,): ``(c1, m, h, r2, n, p, nm, kind)``."""
    c1, m, h, _, r2 = segment_axes(joints, radii, topo.start, topo.end, topo.valid)
    r1 = jnp.where(topo.valid, r1, 0.0)
    a = jnp.maximum(topo.parent, 0)
    n, p, kind = cutting_planes(c1, m[a], c1[a], r1[a], r2[a], h[a], m, r1, r2, h)
    return c1, m, h, r2, n, p, medial_normal(m[a], m)[0], kind


_axes_and_planes = HostFn(_axes_and_planes_of, compiler_options=_HOST_OPTS)


def _match_minor_axes(joints, radii, ptopo, topo: Topology, info: dict, tol: float, iters: int):
    """Sec. 2.2: base radii (N,) of the continuations rescaled, depth level by depth level, until
    the minor axes of the two elliptical cuts at each joint agree within ``tol`` (relative);
    ``info`` gets the iterations used and the mismatch left (host loop, float64)."""
    r1 = radii[np.asarray(ptopo.start)] * np.asarray(ptopo.valid)
    cont = np.nonzero(topo.parent_seg >= 0)[0]
    for lvl in np.unique(topo.depth[cont]):  # host loop over depth levels; vectorised within one
        bs = cont[topo.depth[cont] == lvl]
        a = topo.parent_seg[bs]
        for it in range(iters):
            c1, m, h, r2, n, p, nm, kind = (np.asarray(x) for x in _axes_and_planes(joints, radii, ptopo, r1))
            ba = minor_semi_axis(c1[a], m[a], r1[a], (r2[a] - r1[a]) / h[a], n[bs], p[bs], nm[bs])
            bb = minor_semi_axis(c1[bs], m[bs], r1[bs], (r2[bs] - r1[bs]) / h[bs], n[bs], p[bs], nm[bs])
            # joints without a shared plane (PLANE_SPLIT: capped ends) have no cuts to match
            mis = np.where(kind[bs] == PLANE_SPLIT, 0.0, np.abs(ba - bb) / np.maximum(ba, 1e-300))
            info["minor_axis_iterations"] = max(info["minor_axis_iterations"], it)
            if np.all(mis <= tol):
                break
            r1[bs] = r1[bs] * np.where((bb > 0) & (kind[bs] != PLANE_SPLIT), ba / np.where(bb > 0, bb, 1.0), 1.0)
        info["minor_axis_mismatch"] = max(info["minor_axis_mismatch"], float(np.max(mis)))
    return r1


def build_frusta(
    joints: np.ndarray,
    radii: np.ndarray,
    topo: Topology,
    twist_turns: float = 0.0,
    match_minor_axes: bool = False,
    match_tol: float = 1e-10,
    match_iters: int = 100,
) -> tuple[FrustaArrays, dict]:
    """Build every segment's frustum; returns (arrays, info) with info on minor-axis matching
    and the joints' plane choices (:func:`plane_counts`)."""
    s, nj = topo.seg_start.shape[0], joints.shape[0]
    n = max(GEOMETRY_ROWS, _bucket(s))
    jn = max(GEOMETRY_ROWS, _bucket(nj))
    j = np.concatenate([np.asarray(joints, np.float64), np.zeros((jn - nj, 3))])
    r = np.concatenate([np.asarray(radii, np.float64), np.zeros(jn - nj)])
    ptopo = padded_topology(topo, n, np)
    bl = ptopo.by_level
    if bl.shape[0] < GEOMETRY_LEVELS:  # levels of rows out of range (n), never visited
        ptopo = ptopo._replace(by_level=np.concatenate([bl, np.full((GEOMETRY_LEVELS - bl.shape[0], bl.shape[1]), n, np.int32)]))
    levels = np.int32(topo.depth.max() + 1)
    info = {"minor_axis_iterations": 0, "minor_axis_mismatch": 0.0}
    with jax.enable_x64(True):
        r1 = None
        if match_minor_axes:
            r1 = _match_minor_axes(j, r, ptopo, topo, info, match_tol, match_iters)
        f, kinds = _fields_host(j, r, ptopo, np.float64(twist_turns), levels, r1)
    arrays = FrustaArrays(**{name: np.array(x[:s]) for name, x in f.items()})
    info["joint_planes"] = plane_counts(np.asarray(kinds)[:s])
    return arrays, info


def plane_counts(kinds) -> dict:
    """How many joints took each plane of ``_geometry.cutting_planes``' chain (``run.json``'s
    ``joint_planes``): Eq. 3-5's, the collinear limit, the bisector, or perpendicular planes with
    caps (no shared plane), the last two where a piece would otherwise reach beyond
    ``PIECE_REACH`` times its larger radius from its segment."""
    return {name: int(np.sum(kinds == i)) for i, name in enumerate(PLANE_KINDS)}


def piece_reach(arr: FrustaArrays) -> np.ndarray:
    """(S,) how far each frustum piece reaches from its axis segment: the larger of its two
    planes' :func:`_geometry.plane_reach` (exact: the distance is convex along the axis, so it
    peaks at a cut's axial extreme), at most ``PIECE_REACH * max(r1, r2)`` by construction.
    Evaluated eagerly in float64 (a few array operations, no compile)."""
    with jax.enable_x64(True):
        bottom = plane_reach(arr.nb, arr.db, arr.m, arr.r1, arr.r2, arr.h)
        top = plane_reach(arr.nt, arr.dt, arr.m, arr.r1, arr.r2, arr.h)
        return np.asarray(jnp.maximum(bottom, top), np.float64)


def _cut_boxes(arr: FrustaArrays, n: np.ndarray, dist: np.ndarray):
    """(lo, hi) (S, 3) boxes of the ellipses the planes ``n . (P - C1) = dist`` cut from the
    cones, in closed form: the major axis joins the cut's two points in the plane of ``m`` and
    ``n`` (the axial extremes of :func:`_geometry.plane_reach`), the minor axis is the half chord
    through its centre across that plane, ``sqrt((r1 + k y_c)^2 - rho_c^2)`` (Sec. 2.2's minor
    axis, :func:`minor_semi_axis`); an ellipse of semi-axes a, b spans ``sqrt(a_i^2 + b_i^2)``
    about its centre along axis i."""
    k = (arr.r2 - arr.r1) / arr.h
    nm = np.sum(n * arr.m, -1)
    tilt = n - nm[:, None] * arr.m
    tn = np.linalg.norm(tilt, axis=-1)
    e = np.where((tn > 1e-12)[:, None], tilt / np.maximum(tn, 1e-300)[:, None], arr.u)  # a circle: any radial direction
    ne = np.where(tn > 1e-12, tn, 0.0)
    ends = []
    for sign in (1.0, -1.0):
        y = (dist - sign * ne * arr.r1) / (nm + sign * ne * k)
        ends.append(arr.c1 + y[:, None] * arr.m + (sign * (arr.r1 + k * y))[:, None] * e)
    centre = 0.5 * (ends[0] + ends[1])
    semi_a = 0.5 * (ends[0] - ends[1])
    yc = np.sum((centre - arr.c1) * arr.m, -1)
    rho_c = np.sum((centre - arr.c1) * e, -1)
    semi_b = np.sqrt(np.maximum((arr.r1 + k * yc) ** 2 - rho_c**2, 0.0))
    b_dir = np.cross(n, semi_a / np.maximum(np.linalg.norm(semi_a, axis=-1), 1e-300)[:, None])
    half = np.sqrt(semi_a**2 + (semi_b[:, None] * b_dir) ** 2)
    return centre - half, centre + half


def piece_bounds(arr: FrustaArrays, grow: float = 0.0):
    """(lo, hi) (3,) world box of every piece: each piece is the convex hull of its two
    elliptical cuts (every generator runs straight from one to the other; a flat cap lies inside
    its cut), so the boxes of the cuts (:func:`_cut_boxes`, exact) bound it; ``grow``, a relief
    shell's thickness, takes the shell's outer frusta (radii + grow) instead."""
    if grow:
        arr = arr._replace(r1=arr.r1 + grow, r2=arr.r2 + grow)
    lo_b, hi_b = _cut_boxes(arr, arr.nb, arr.db)
    lo_t, hi_t = _cut_boxes(arr, arr.nt, arr.dt)
    return np.minimum(lo_b, lo_t).min(0), np.maximum(hi_b, hi_t).max(0)
