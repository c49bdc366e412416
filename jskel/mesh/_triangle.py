"""One ray against triangles, watertight: Woop, Benthin and Wald (2013), double-sided.

The ray's frame is permuted so its dominant axis is z and sheared so it runs along +z; each
vertex, relative to the ray origin, is projected to 2D by the same shear, and the three 2D edge
functions U, V, W are products of those projected coordinates. Two triangles that share an edge
compute that edge's function from the same two projected vertices with the factors swapped, so
the two values are exact negatives: a ray through a shared edge or vertex meets at least one of
the triangles in float32 (no pinholes), which a Möller-Trumbore test with a rounded barycentric
tolerance does not guarantee. That argument needs both triangles to round the same products:
XLA on the CPU compiled the test inside the BVH walk differently from the test alone (a fused
multiply-add, by the results: a ray through a shared edge hit neither triangle in the walk and
one of them alone), so each edge function is evaluated in one canonical vertex order, the
lower vertex id first, and negated where the triangle winds the other way: the two triangles
then run the same operations on the same operands. An edge function of exactly zero counts as inside (the paper falls
back to double precision there; here both triangles accept the ray and the nearer is kept).
Vertices are therefore stored as vertices, never as a vertex and rounded edges.
"""

from __future__ import annotations

import jax.numpy as jnp

from ..numerics import dot3


def cross3(a, b):
    """Cross product over a last axis of 3, written out (see :func:`jskel.numerics.dot3`)."""
    return jnp.stack([a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
                      a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
                      a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0]], axis=-1)


def pick(a, k):
    """``a[..., k]`` for an axis index ``k`` in {0, 1, 2} (a traced scalar) by selects: exact, and
    elementwise under vmap, where an indexed read by a per-ray index becomes a gather."""
    return jnp.where(k == 0, a[..., 0], jnp.where(k == 1, a[..., 1], a[..., 2]))


def ray_frame(d):
    """(kx, ky, kz, Sx, Sy, Sz) of ray direction ``d`` (3,): kz its dominant axis, (kx, ky) the
    other two in an order that keeps the winding, and the shear taking ``d`` to +z."""
    kz = jnp.argmax(jnp.abs(d))
    kx = (kz + 1) % 3
    ky = (kx + 1) % 3
    dz = pick(d, kz)
    kx, ky = jnp.where(dz < 0, ky, kx), jnp.where(dz < 0, kx, ky)
    return kx, ky, kz, pick(d, kx) / dz, pick(d, ky) / dz, 1.0 / dz


def _edge(p, q, ip, iq):
    """2D edge function ``px qy - py qx`` of projected vertices p, q, computed with the lower
    vertex id first (module docstring): bit-identical, up to sign, in both triangles of an edge."""
    flip = iq < ip
    ax, ay = jnp.where(flip, q[0], p[0]), jnp.where(flip, q[1], p[1])
    bx, by = jnp.where(flip, p[0], q[0]), jnp.where(flip, p[1], q[1])
    e = ax * by - ay * bx
    return jnp.where(flip, -e, e)


def triangle_t(v0, v1, v2, o, d, t_min, t_max, ids=None):
    """(t, u, v) of ray ``o + t d`` against triangles with vertices v0, v1, v2 (..., 3): t in
    ``(t_min, t_max]`` or +inf; (u, v) the barycentric weights of v1 and v2 at the hit.
    ``ids`` (..., 3) int: the vertices' indices in the mesh, for the canonical edge order
    (without them, shared edges are watertight only where the compiler rounds alike).
    Broadcasts over the triangles' leading axes."""
    kx, ky, kz, sx, sy, sz = ray_frame(d)

    def project(v):
        a = v - o
        ax, ay, az = pick(a, kx), pick(a, ky), pick(a, kz)
        return ax - sx * az, ay - sy * az, sz * az

    ax, ay, az = project(v0)
    bx, by, bz = project(v1)
    cx, cy, cz = project(v2)
    if ids is None:
        ids = jnp.broadcast_to(jnp.arange(3), v0.shape)
    i0, i1, i2 = ids[..., 0], ids[..., 1], ids[..., 2]
    eu = _edge((cx, cy), (bx, by), i2, i1)  # weight of v0
    ev = _edge((ax, ay), (cx, cy), i0, i2)  # weight of v1
    ew = _edge((bx, by), (ax, ay), i1, i0)  # weight of v2
    same = ((eu >= 0) & (ev >= 0) & (ew >= 0)) | ((eu <= 0) & (ev <= 0) & (ew <= 0))
    det = eu + ev + ew
    ok = same & (det != 0)
    inv = 1.0 / jnp.where(ok, det, 1.0)
    t = (eu * az + ev * bz + ew * cz) * inv
    hit = ok & (t > t_min) & (t <= t_max)
    return jnp.where(hit, t, jnp.inf), ev * inv, ew * inv


def face_normals(v0, v1, v2):
    """Unit normals (..., 3) of triangles as their vertices wind (zero for degenerate ones)."""
    n = cross3(v1 - v0, v2 - v0)
    length2 = dot3(n, n)
    ok = length2 > 0
    return jnp.where(ok[..., None], n / jnp.sqrt(jnp.where(ok, length2, 1.0))[..., None], 0.0)
