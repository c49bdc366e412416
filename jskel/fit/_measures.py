"""Measures of a skeleton against a cloud, in world units (issue 10): signed distances, how
many points the candidate culling serves exactly, and the worst shared cutting plane."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from ._distance import checked_distances, culling_exact, plane_margins, segments_of
from ._problem import normaliser_of


def point_distances(points, joints, radii, parents, dtype=np.float32) -> np.ndarray:
    """Signed distances of ``points`` to a skeleton's surface, in world units (NumPy)."""
    seg = segments_of(joints, radii, parents, "skeleton")
    nz = normaliser_of(np.asarray(points, np.float64))
    d = checked_distances(jnp.asarray(nz.points(joints), dtype), jnp.asarray(np.asarray(radii) / nz.extent, dtype), seg,
                          jnp.asarray(nz.points(points), dtype))
    return np.asarray(d, np.float64) * nz.extent


def culling_exact_fraction(points, joints, radii, parents, candidates: int) -> float:
    """Fraction of ``points`` whose distance over their ``candidates`` nearest segments is
    certainly their distance over all segments (``culling_exact``), at this skeleton."""
    seg = segments_of(joints, radii, parents, "skeleton")
    nz = normaliser_of(np.asarray(points, np.float64))
    ok = culling_exact(jnp.asarray(nz.points(joints), jnp.float32), jnp.asarray(np.asarray(radii) / nz.extent, jnp.float32), seg,
                       jnp.asarray(nz.points(points), jnp.float32), candidates)
    return float(np.mean(np.asarray(ok)))


def plane_margin_min(joints, radii, parents) -> float | None:
    """The smallest ``plane_margins`` value of a skeleton (None without shared planes)."""
    seg = segments_of(joints, radii, parents, "skeleton")
    if not len(seg.cont_b):
        return None
    return float(np.min(np.asarray(plane_margins(jnp.asarray(joints, jnp.float32), jnp.asarray(radii, jnp.float32), seg))))
