"""Measures of a skeleton against a cloud, in world units (issue 10): signed distances, how
many points the candidate culling serves exactly, and the worst shared cutting plane, all from
one compiled program per topology (:func:`measures`)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import checks
from ._distance import Segments, _problems, distances_of, geometry, margins_of, segments_of
from ._problem import normaliser_of


def _measured(joints, radii, seg: Segments, points, candidates: int):
    """Distances over all segments (N,), whether each point's ``candidates`` nearest segments
    certainly give that distance (N,) (``_distance.culling_exact``), and the shared planes'
    margins (K, 2) (``_distance.plane_margins``), from one geometry."""
    g = geometry(joints, radii, seg)
    d = distances_of(g, seg, points)[0]
    if 0 < candidates < len(seg.start):
        dc, nxt = distances_of(g, seg, points, candidates)
        exact = jnp.where(dc >= 0, nxt >= dc, nxt > 0)
    else:  # every segment is a candidate: exact by construction
        exact = jnp.ones(d.shape, bool)
    return d, exact, margins_of(g, seg)


#: :func:`_measured` with its inputs checked in the same compiled program (``jskel.checks.checked``,
#: as ``checked_distances``): one program per topology, candidate count and shapes
_checked = checks.checked(_measured, lambda j, r, seg, p, c: _problems(j, r, seg, p), static_argnums=(2, 4))


def measures(points, joints, radii, parents, candidates: int = 0, dtype=np.float32) -> tuple[np.ndarray, float, float | None]:
    """Signed distances of ``points`` to a skeleton's surface in world units (NumPy), the
    fraction of points whose ``candidates``-segment distance is certainly their distance over
    all segments, and the smallest shared-plane margin (None without shared planes), from one
    compiled program (in coordinates normalised by the cloud's extent; the margins are
    scale-free)."""
    seg = segments_of(joints, radii, parents, "skeleton")
    nz = normaliser_of(np.asarray(points, np.float64))
    args = [np.asarray(a, dtype) for a in (nz.points(joints), np.asarray(radii) / nz.extent, nz.points(points))]
    d, exact, margins = _checked(jnp.asarray(args[0]), jnp.asarray(args[1]), seg, jnp.asarray(args[2]), int(candidates))
    margins = np.asarray(margins)
    return np.asarray(d, np.float64) * nz.extent, float(np.mean(np.asarray(exact))), float(margins.min()) if margins.size else None


def point_distances(points, joints, radii, parents, dtype=np.float32) -> np.ndarray:
    """Signed distances of ``points`` to a skeleton's surface, in world units (NumPy)."""
    return measures(points, joints, radii, parents, 0, dtype)[0]


def culling_exact_fraction(points, joints, radii, parents, candidates: int) -> float:
    """Fraction of ``points`` whose distance over their ``candidates`` nearest segments is
    certainly their distance over all segments (``culling_exact``), at this skeleton."""
    return measures(points, joints, radii, parents, candidates)[1]


def plane_margin_min(joints, radii, parents) -> float | None:
    """The smallest ``plane_margins`` value of a skeleton (None without shared planes)."""
    j = np.asarray(joints, np.float64)
    return measures(j, j, radii, parents)[2]
