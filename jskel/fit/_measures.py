"""Measures of a skeleton against a cloud, in world units (issue 10): signed distances, how
many points the candidate culling serves exactly, and the worst shared cutting plane, all from
one compiled program (:func:`measures`) that takes the topology as data, padded to sizes
rounded up by at most 12.5 % (``_problem._bucket``), so skeletons of similar sizes share it
(a benchmark measures each fit and each peer's skeleton)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .. import checks
from ._distance import Topology, _problems, distances_of, geometry, margins_of, segments_of, topology_of
from ._problem import _bucket, normaliser_of


def _measured(joints, radii, seg: Topology, points, candidates: int):
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
#: as ``checked_distances``): one program per padded size, candidate count and point count
_checked = checks.checked(_measured, lambda j, r, seg, p, c: _problems(j, r, seg, p), static_argnums=(4,))


def measures(points, joints, radii, parents, candidates: int = 0, dtype=np.float32) -> tuple[np.ndarray, float, float | None]:
    """Signed distances of ``points`` to a skeleton's surface in world units (NumPy), the
    fraction of points whose ``candidates``-segment distance is certainly their distance over
    all segments, and the smallest shared-plane margin (None without shared planes), from one
    compiled program (in coordinates normalised by the cloud's extent; the margins are
    scale-free)."""
    seg = segments_of(joints, radii, parents, "skeleton")
    nz = normaliser_of(np.asarray(points, np.float64))
    topo = topology_of(seg, _bucket(len(seg.start)), _bucket(len(seg.cont_b)))
    pad = _bucket(len(joints)) - len(joints)  # joints in no segment (a padding segment is joint 0's)
    j = np.concatenate([nz.points(joints), np.zeros((pad, 3))])
    r = np.concatenate([np.asarray(radii, np.float64) / nz.extent, np.zeros(pad)])
    d, exact, margins = _checked(*(jnp.asarray(np.asarray(a, dtype)) for a in (j, r)), topo, jnp.asarray(np.asarray(nz.points(points), dtype)),
                                 int(candidates))
    margins = np.asarray(margins)[topo.cont]
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
