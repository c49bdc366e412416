"""The paper's comparison (Bhagvat et al. 2009, Fig. 6, Table 1 "GS+R"): a relief object as a
displaced triangle mesh at increasing subdivision, ray cast with Embree (embreex via trimesh).

The mesh samples each relief segment on a (nu x nv) grid of (u, v): the vertex for (u, v) lies
on the cone concentric with the frustum whose radius exceeds the inner one by h(u, v) * T, at
parameter v between the cutting planes along that cone's generator (Sec. 2.3 and 3), so a vertex
is exactly on jskel's relief surface and only the flat triangles between vertices differ.
Free ends are closed by triangle fans.
"""

from __future__ import annotations

import time

import numpy as np


def _bilinear(img, uu, vv, v_mode):
    h, w = img.shape
    x = uu * w - 0.5
    y = vv * h - 0.5
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    fx, fy = x - x0, y - y0
    xa, xb = np.mod(x0, w), np.mod(x0 + 1, w)
    if v_mode == "wrap":
        ya, yb = np.mod(y0, h), np.mod(y0 + 1, h)
    else:
        ya, yb = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    g = lambda yy, xx: img[yy, xx].astype(float)  # noqa: E731
    return ((1 - fx) * (1 - fy) * g(ya, xa) + fx * (1 - fy) * g(ya, xb) + (1 - fx) * fy * g(yb, xa) + fx * fy * g(yb, xb)) / 255.0


def displaced_mesh(arr, ids, height, scale, thickness, v_mode, nu, nv):
    """(vertices (V,3) float64 world, faces (F,3) int64) of the relief segments ``ids``."""
    verts, faces = [], []
    off = 0
    us = np.arange(nu) / nu
    vs = np.arange(nv + 1) / nv
    U, V = np.meshgrid(us, vs)  # (nv+1, nu)
    for s in ids:
        c1, m, ux, wz = arr.c1[s], arr.m[s], arr.u[s], arr.w[s]
        k = (arr.r2[s] - arr.r1[s]) / arr.h[s]
        hgt = _bilinear(height, U * scale[0], (V + arr.v_off[s]) * scale[1], v_mode)
        theta = 2 * np.pi * (U - arr.u_off[s] - V * arr.twist[s])
        radial = np.sin(theta)[..., None] * ux + np.cos(theta)[..., None] * wz
        base = c1 + (arr.r1[s] + hgt * thickness)[..., None] * radial
        g = m + k * radial
        yl = (arr.db[s] - (base - c1) @ arr.nb[s]) / (g @ arr.nb[s])
        yu = (arr.dt[s] - (base - c1) @ arr.nt[s]) / (g @ arr.nt[s])
        y = yl + V * (yu - yl)
        P = base + y[..., None] * g
        verts.append(P.reshape(-1, 3))
        i = np.arange(nv)[:, None]
        j = np.arange(nu)[None, :]
        a = off + i * nu + j
        b = off + i * nu + (j + 1) % nu
        c = a + nu
        d = b + nu
        faces.append(np.stack([a, b, d], -1).reshape(-1, 3))
        faces.append(np.stack([a, d, c], -1).reshape(-1, 3))
        off += P.shape[0] * P.shape[1]
        for capped, row, n, dist in ((arr.cap_b[s], 0, arr.nb[s], arr.db[s]), (arr.cap_t[s], nv, arr.nt[s], arr.dt[s])):
            if not capped:
                continue
            centre = c1 + m * (dist / (n @ m))
            verts.append(centre[None, :])
            ring = off - (nv + 1) * nu + row * nu + np.arange(nu)
            fan = np.stack([np.full(nu, off), ring[(np.arange(nu) + 1) % nu], ring], -1)
            faces.append(fan if row == 0 else fan[:, [0, 2, 1]])
            off += 1
    return np.concatenate(verts), np.concatenate(faces)


def embree_cast(vertices, faces, origins, directions, runs=5):
    """Nearest-hit distances with Embree through trimesh; returns (t (N,), build_s, median_s)."""
    import trimesh
    from trimesh.ray.ray_pyembree import RayMeshIntersector

    t0 = time.perf_counter()
    mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
    isect = RayMeshIntersector(mesh)
    isect.intersects_first(origins[:1], directions[:1])  # builds the BVH
    build_s = time.perf_counter() - t0
    times = []
    for _ in range(runs):
        t1 = time.perf_counter()
        tri = isect.intersects_first(origins, directions)
        times.append(time.perf_counter() - t1)
    hit = tri >= 0
    t = np.full(origins.shape[0], np.inf)
    if hit.any():
        # distance along the unit ray to the hit triangle's plane
        v0 = vertices[faces[tri[hit], 0]]
        n = np.cross(vertices[faces[tri[hit], 1]] - v0, vertices[faces[tri[hit], 2]] - v0)
        t[hit] = np.sum(n * (v0 - origins[hit]), -1) / np.sum(n * directions[hit], -1)
    return t, build_s, float(np.median(times))
