"""Float64 Möller-Trumbore (Möller and Trumbore 1997) for tests only, written independently of
``jskel.mesh``: every ray against every triangle at once."""

from __future__ import annotations

import numpy as np


def moller_trumbore(tri, O, D):
    """(t, u, v, det) of rays (n, 3) against triangles (f, 3, 3), each (n, f): the ray parameter,
    the barycentric coordinates of the second and third corners, and the determinant (0: the
    ray is parallel to the triangle's plane; t, u, v are then meaningless)."""
    v0, e1, e2 = tri[:, 0], tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    o, d = O[:, None, :], D[:, None, :]
    p = np.cross(d, e2)
    det = np.sum(e1 * p, -1)
    inv = 1.0 / np.where(det == 0, 1.0, det)
    s = o - v0
    u = np.sum(s * p, -1) * inv
    q = np.cross(s, e1)
    v = np.sum(d * q, -1) * inv
    t = np.sum(e2 * q, -1) * inv
    return t, u, v, det
