"""Triangle meshes of the frusta as rendered: one tessellation for the Embree peer and for export.

The tessellation is the paper's "similar quality" mesh (Bhagvat et al. 2009, Sec. 4, Table 1
"GS"): before subdivision 16 triangles per conical segment, 16 x 4^m after m subdivisions. It
is built from jskel's own frusta (``FrustaArrays``: the same cones and the same cutting planes
of Eq. 3-5, so neighbouring segments share their seam ellipse): nu = 8 x 2^m generators around,
2^m rings along (each generator split evenly between its two cutting planes), two triangles a
quad; free ends are closed by fans around the cap's centre on the axis. Every lateral vertex lies
on its segment's cone, so the mesh departs from the analytic surface only by its flat facets:
within r_max (1 - cos(pi / nu)) of it (r_max the largest radius the piece reaches). Relief
(Sec. 3) is not tessellated. NumPy, vectorized over segments.

:func:`export_mesh` writes that mesh, the format by the file's extension: PLY (binary, float64
vertices, written here), and through trimesh OBJ (17 significant digits), glTF binary (.glb, float32 as glTF
stores positions) or STL (float32).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._build import FrustaArrays
from ._config import FrustaConfig
from ._edits import host_frusta

#: extension -> trimesh's file type
FORMATS = {".ply": "ply", ".obj": "obj", ".glb": "glb", ".stl": "stl"}
MAX_LEVEL = 8  # 16 x 4^8 = 1M triangles a segment


def frusta_mesh(arr, level: int):
    """(vertices (V,3) float64, faces (F,3) int64) of every frustum in ``arr`` (``FrustaArrays``,
    world space): 16 x 4^level lateral triangles per segment, plus fans on capped ends.

    Layout: segment s's (2^level + 1) x (8 x 2^level) lateral vertices (ring by ring, from the
    bottom plane to the top one, generator angle 2 pi j / nu from ``u`` towards ``w``) come first,
    segment after segment; then one centre per bottom cap, then one per top cap."""
    s = arr.h.shape[0]
    nu, nv = 8 * 2**level, 2**level
    theta = 2 * np.pi * np.arange(nu) / nu
    radial = np.cos(theta)[None, :, None] * arr.u[:, None, :] + np.sin(theta)[None, :, None] * arr.w[:, None, :]  # (S,nu,3)
    k = (arr.r2 - arr.r1) / arr.h
    base = arr.c1[:, None, :] + arr.r1[:, None, None] * radial
    g = arr.m[:, None, :] + k[:, None, None] * radial  # generator direction (unit y step)

    def cut(n, d):  # parameter y where each generator meets the plane n . (P - C1) = d
        den = np.einsum("sk,sak->sa", n, g)
        return (d[:, None] - np.einsum("sk,sak->sa", n, base - arr.c1[:, None, :])) / np.where(den == 0, 1.0, den)

    yl, yu = cut(arr.nb, arr.db), cut(arr.nt, arr.dt)
    v = np.arange(nv + 1) / nv
    y = yl[:, None, :] + v[None, :, None] * (yu - yl)[:, None, :]  # (S, nv+1, nu)
    P = base[:, None] + y[..., None] * g[:, None]  # (S, nv+1, nu, 3)
    per = (nv + 1) * nu
    i = np.arange(nv)[:, None]
    j = np.arange(nu)[None, :]
    a = i * nu + j
    b = i * nu + (j + 1) % nu
    quad = np.concatenate([np.stack([a, b, b + nu], -1).reshape(-1, 3), np.stack([a, b + nu, a + nu], -1).reshape(-1, 3)])
    faces = [(quad[None] + (np.arange(s) * per)[:, None, None]).reshape(-1, 3)]
    verts = [P.reshape(-1, 3)]
    off = s * per
    for capped, row, n, dist, flip in ((arr.cap_b, 0, arr.nb, arr.db, False), (arr.cap_t, nv, arr.nt, arr.dt, True)):
        ids = np.nonzero(capped)[0]
        if ids.size == 0:
            continue
        centre = arr.c1[ids] + arr.m[ids] * (dist[ids] / np.sum(n[ids] * arr.m[ids], -1))[:, None]
        verts.append(centre)
        c = off + np.arange(ids.size)
        ring = ids[:, None] * per + row * nu + np.arange(nu)[None, :]
        fan = np.stack([np.broadcast_to(c[:, None], ring.shape), np.roll(ring, -1, axis=1), ring], -1).reshape(-1, 3)
        faces.append(fan[:, [0, 2, 1]] if flip else fan)
        off += ids.size
    return np.concatenate(verts), np.concatenate(faces).astype(np.int64)


def write_ply(path: Path, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Binary little-endian PLY with float64 vertices (trimesh's own PLY writer rounds vertices
    to float32) and int32 triangle indices."""
    head = ("ply\nformat binary_little_endian 1.0\ncomment jskel frusta tessellation\n"
            f"element vertex {vertices.shape[0]}\nproperty double x\nproperty double y\nproperty double z\n"
            f"element face {faces.shape[0]}\nproperty list uchar int vertex_indices\nend_header\n")
    tri = np.zeros(faces.shape[0], np.dtype([("n", "u1"), ("i", "<i4", (3,))]))
    tri["n"], tri["i"] = 3, faces
    with open(path, "wb") as f:
        f.write(head.encode("ascii"))
        f.write(np.ascontiguousarray(vertices, "<f8").tobytes())
        f.write(tri.tobytes())


def mesh_format(path, field: str = "path") -> str:
    """trimesh's file type for ``path``'s extension; a ValueError naming ``field`` otherwise."""
    fmt = FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise ValueError(f"{field}: cannot tell the mesh format from {str(path)!r} (known: {', '.join(FORMATS)})")
    return fmt


def export_mesh(path, source: FrustaArrays | FrustaConfig, level: int = 2, field: str = "path") -> dict:
    """Write the tessellation (``frusta_mesh`` at ``level``) of ``source`` (world-space
    ``FrustaArrays``, or a frusta object section, built on the host as the renderer builds it) to
    ``path``, in the format its extension names (.ply, .obj, .glb, .stl). Returns
    ``{"path", "format", "level", "segments", "vertices", "faces"}``. A bad extension or level is
    a ValueError naming ``field`` (or ``level``) and the value, raised before anything is built."""
    import trimesh

    out, fmt = Path(path), mesh_format(path, field)
    if not (isinstance(level, int) and 0 <= level <= MAX_LEVEL):
        raise ValueError(f"level: expected an integer 0..{MAX_LEVEL} (got {level!r})")
    arr = host_frusta(source)[0] if isinstance(source, FrustaConfig) else source
    verts, faces = frusta_mesh(arr, level)
    mesh = trimesh.Trimesh(vertices=verts, faces=faces, process=False)
    out.parent.mkdir(parents=True, exist_ok=True)
    if fmt == "ply":
        write_ply(out, verts, faces)
    elif fmt == "obj":
        out.write_text(trimesh.exchange.obj.export_obj(mesh, digits=17, include_normals=False))
    else:
        mesh.export(out, file_type=fmt)
    return {"path": str(out), "format": fmt, "level": level, "segments": int(arr.h.shape[0]),
            "vertices": int(verts.shape[0]), "faces": int(faces.shape[0])}
