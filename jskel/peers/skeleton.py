"""Peers for whole skeletons (issue 6's benchmark): the paper's "similar quality" tessellation cast
by Embree, and Mitsuba 3's round linear curves, on the rays jskel casts.

Embree (Bhagvat et al. 2009, Sec. 4, Table 1 "GS"): before subdivision the paper rasterizes 16
triangles per conical segment, and 16 n x 4^m after m subdivisions. :func:`frusta_mesh` (``jskel.frusta``) builds
exactly that lateral surface from jskel's own frusta (the same cutting planes, so neighbouring
segments share their seam ellipse): 8 x 2^m generators around, 2^m rings along, two triangles a
quad; free ends are closed by fans (reported in the triangle count). Vertices lie on the cone, so
only the flat facets differ from the analytic surface. The tessellation is NumPy, vectorized over
segments (no loop over segments), so a per-frame rebuild is charged fairly.

Mitsuba 3 (``linearcurve``): every segment is one two-point curve (x, y, z, r at each joint),
which Mitsuba renders as a round cone closed by spheres: the same skeleton with different joints
(spheres instead of cutting planes), so agreement with jskel is reported, not assumed. Mitsuba's
LLVM variants crash with the LLVM that Dr.Jit finds by default on this workplace's CPU; pointing
``DRJIT_LIBLLVM_PATH`` at Debian's ``libLLVM-15.so.1`` (package ``libllvm15``) works, and
``scalar_rgb`` is the fallback. Animated frames update the curves' control points through
``mi.traverse`` (Mitsuba rebuilds its acceleration structure on ``update()``).
"""

from __future__ import annotations

import os
import tempfile
import time

import numpy as np

from ..frusta import frusta_mesh as frusta_mesh  # the one tessellation, shared with the mesh export

__all__ = ["EmbreeMesh", "LLVM15", "MitsubaCurves", "TABLE1_GS_LEVEL", "curve_points", "frusta_mesh"]

#: Table 1's subdivision level m for "similar quality" (GS column) per scene generator. A
#: skeleton read from a file has no generator and no Table 1 row and takes m = 1
#: (``skeleton_study``'s default), the level of the thin-branched scenes (palm, pine): 16
#: generators around leave a chord 1 - cos(pi / 16) = 1.9 % of the radius inside the cone, under
#: a pixel for a neuron's neurites (median radius 0.45 um, about 1.6 um per pixel at 1024x768).
TABLE1_GS_LEVEL = {"palm": 1, "pine": 1, "lsystem_tree": 1, "aloe": 2, "saguaro": 2, "well": 2, "oasis": 0, "dancing_cacti": 0}

LLVM15 = "/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1"


class EmbreeMesh:
    """A triangle mesh with Embree's BVH (embreex via trimesh); ``build_s`` is the BVH build."""

    def __init__(self, vertices, faces):
        import trimesh
        from trimesh.ray.ray_pyembree import RayMeshIntersector

        self.vertices, self.faces = vertices, faces
        t0 = time.perf_counter()
        mesh = trimesh.Trimesh(vertices=vertices, faces=faces, process=False)
        self.isect = RayMeshIntersector(mesh)
        self.isect.intersects_first(np.zeros((1, 3)), np.array([[0.0, 0.0, 1.0]]))  # builds the BVH
        self.build_s = time.perf_counter() - t0

    def cast(self, origins, directions):
        """Nearest-hit t (N,) (inf on a miss) and the seconds the cast took (distances excluded)."""
        t1 = time.perf_counter()
        tri = self.isect.intersects_first(origins, directions)
        cast_s = time.perf_counter() - t1
        hit = tri >= 0
        t = np.full(origins.shape[0], np.inf)
        if hit.any():
            v0 = self.vertices[self.faces[tri[hit], 0]]
            n = np.cross(self.vertices[self.faces[tri[hit], 1]] - v0, self.vertices[self.faces[tri[hit], 2]] - v0)
            t[hit] = np.sum(n * (v0 - origins[hit]), -1) / np.sum(n * directions[hit], -1)
        return t, cast_s


def _mitsuba(variant: str):
    if variant.startswith("llvm") and "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(LLVM15):
        os.environ["DRJIT_LIBLLVM_PATH"] = LLVM15
    import mitsuba as mi

    mi.set_variant(variant)
    return mi


def curve_points(joints, radii, parents):
    """(S, 2, 4) control points (x, y, z, r): one two-point curve per segment."""
    child = np.nonzero(np.asarray(parents) >= 0)[0]
    par = np.asarray(parents)[child]
    pts = np.stack([np.concatenate([joints[par], radii[par, None]], 1), np.concatenate([joints[child], radii[child, None]], 1)], 1)
    return pts


class MitsubaCurves:
    """Mitsuba 3 ``linearcurve`` scene of a skeleton; ``build_s`` covers writing the curve file,
    loading it and building Mitsuba's acceleration structure."""

    def __init__(self, joints, radii, parents, variant: str = "llvm_ad_rgb"):
        self.mi = mi = _mitsuba(variant)
        self.variant = variant
        pts = curve_points(joints, radii, parents)
        t0 = time.perf_counter()
        with tempfile.NamedTemporaryFile("w", suffix=".txt", delete=False) as f:
            f.write("\n\n".join("\n".join(" ".join(f"{x:.9g}" for x in p) for p in c) for c in pts) + "\n")
            path = f.name
        try:
            self.scene = mi.load_dict({"type": "scene", "curves": {"type": "linearcurve", "filename": path}})
        finally:
            os.unlink(path)
        self.params = mi.traverse(self.scene)
        self.build_s = time.perf_counter() - t0
        self.n_curves = pts.shape[0]

    def update(self, joints, radii, parents) -> float:
        """Move the control points to a new frame's skeleton (same topology); returns seconds
        (the update and Mitsuba's rebuild of its acceleration structure)."""
        mi = self.mi
        key = next(k for k in self.params.keys() if k.endswith("control_points"))
        pts = curve_points(joints, radii, parents).reshape(-1).astype(np.float32)
        t0 = time.perf_counter()
        self.params[key] = mi.Float(pts)
        self.params.update()
        import drjit as dr

        dr.eval(self.scene)
        dr.sync_thread()
        return time.perf_counter() - t0

    def cast(self, origins, directions):
        """Nearest-hit t (N,) (inf on a miss) and the seconds of ``ray_intersect`` (evaluated)."""
        import drjit as dr

        mi = self.mi
        o = [mi.Float(np.ascontiguousarray(origins[:, i], np.float32)) for i in range(3)]
        d = [mi.Float(np.ascontiguousarray(directions[:, i], np.float32)) for i in range(3)]
        ray = mi.Ray3f(mi.Point3f(*o), mi.Vector3f(*d))
        dr.eval(ray)
        dr.sync_thread()
        t1 = time.perf_counter()
        si = self.scene.ray_intersect(ray)
        dr.eval(si.t)
        dr.sync_thread()  # Dr.Jit launches kernels asynchronously: wait before stopping the clock
        cast_s = time.perf_counter() - t1
        t = np.array(si.t, np.float64)
        t[~np.isfinite(t)] = np.inf
        return t, cast_s
