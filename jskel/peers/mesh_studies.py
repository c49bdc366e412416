"""The mesh peers' studies: the same surface as triangles cast by Embree, scored against jskel.

* :func:`marching_cubes` (Rouiller 2011's comparison): an implicit model polygonised at
  ``levels`` grid cells along its longest side;
* :func:`embree_mesh` (Bhagvat et al. 2009, Fig. 6, Table 1 "GS+R"): the relief segments as
  displaced meshes at increasing subdivision;
* :func:`embree_same_mesh`: Embree on the very triangles a mesh object casts.

Each is ``fn(exp, ref_hits, runs, rows, options)`` (``peers.study``); Embree's BVH build is
timed apart from its warm casts.
"""

from __future__ import annotations

import time

import numpy as np

from ..frusta import host_frusta
from ..textures import load_height_map
from ..implicit import expand, primitives
from ..probe.timing import median_of, warm_runs
from ..mesh import read_mesh
from ..render import camera_of
from .implicit_mesh import marching_cubes_mesh
from .relief_mesh import displaced_mesh, embree_cast
from .skeleton import EmbreeMesh
from ..probe.study import StudyOptions, match_target, scored, shape_of


def _mesh_columns(V, F) -> dict:
    return {"vertices": int(V.shape[0]), "triangles": int(F.shape[0]), "mesh_bytes": int(V.shape[0] * 12 + F.shape[0] * 12)}


def marching_cubes(exp, ref_hits, runs: int, rows: list[dict], options: StudyOptions) -> list[dict]:
    """Implicit models polygonised by marching cubes at ``options.levels`` (grid cells along the
    longest side) and cast by Embree, against the same reference."""
    cfg = expand(shape_of(exp, "peer: marching_cubes"))
    a, b, ra, rb, _, _ = primitives(cfg)
    O, D = camera_of(exp).ray_arrays()
    target = match_target(options.match, rows)
    out = []
    for n in options.levels:
        t0 = time.perf_counter()
        try:
            V, F = marching_cubes_mesh(a, b, ra, rb, cfg.threshold, n)
        except ValueError as e:  # e.g. a grid too coarse to contain the level set
            out.append({"peer": "marching_cubes+embree", "scene": exp.name, "grid": n, "error": str(e)})
            continue
        mesh_s = time.perf_counter() - t0
        t, build_s, med = embree_cast(V, F, O, D, runs)
        row = {"peer": "marching_cubes+embree", "scene": exp.name, "grid": n, **_mesh_columns(V, F),
               "polygonise_s": round(mesh_s, 4), "build_s": round(build_s, 4), "render_s_median": round(med, 4),
               "runs": runs, "rays": int(O.shape[0])}
        out.append(scored(row, t, ref_hits, target))
    return out


def embree_mesh(exp, ref_hits, runs: int, rows: list[dict], options: StudyOptions) -> list[dict]:
    """Displaced meshes of the relief segments at subdivision ``options.levels`` (16 x 2^level
    around, 4 x 2^level along), cast by Embree."""
    obj = shape_of(exp, "peer: embree_mesh")
    arrays = host_frusta(obj)[0]
    rel = obj.relief
    ids = np.arange(arrays.h.shape[0]) if rel.segments is None else np.unique(rel.segments)
    height = load_height_map(rel.map)
    O, D = camera_of(exp).ray_arrays()
    target = match_target(options.match, rows)
    out = []
    for level in options.levels:
        nu, nv = 16 * 2**level, 4 * 2**level
        V, F = displaced_mesh(arrays, ids, height, rel.scale, rel.thickness, rel.v_mode, nu, nv)
        t, build_s, med = embree_cast(V, F, O, D, runs)
        row = {"peer": "embree_mesh", "scene": exp.name, "level": level, "grid": [nu, nv], **_mesh_columns(V, F),
               "build_s": round(build_s, 4), "render_s_median": round(med, 4), "runs": runs, "rays": int(O.shape[0])}
        out.append(scored(row, t, ref_hits, target))
    return out


def embree_same_mesh(exp, ref_hits, runs: int, rows: list[dict], options: StudyOptions) -> list[dict]:
    """Embree on the very triangles a mesh object casts (read, scaled and moved as its build
    does) and the same world rays; ratios are jskel's warm cast (and render) median over
    Embree's (above 1: jskel is slower)."""
    obj = shape_of(exp, "peer: embree")
    v, f, _ = read_mesh(obj.path)
    v = v * obj.scale + np.asarray(obj.offset, np.float64)
    O, D = camera_of(exp).ray_arrays()
    em = EmbreeMesh(v, f)
    casts = warm_runs(lambda: em.cast(O, D), runs, 1).warm
    med = median_of([c[1] for c in casts])
    t, ref_t = casts[0][0], np.asarray(ref_hits.t, np.float64)
    a, b = np.isfinite(t), np.isfinite(ref_t)
    row = {"peer": "embree", "scene": exp.name, "rays": int(O.shape[0]), "triangles": int(f.shape[0]), "build_s": round(em.build_s, 4),
           "cast_s_median": med, "runs": runs, "mrays_per_s": round(O.shape[0] / med / 1e6, 3),
           "hit_miss_vs_jskel_pct": round(float(100 * np.mean(a != b)), 4)}
    if (a & b).any():
        row["depth_max_rel_vs_jskel"] = float(np.max(np.abs(t[a & b] - ref_t[a & b]) / ref_t[a & b]))
    jsk = rows[0] if rows else {}  # the first setting's row
    if jsk.get("cast_s_median"):
        row["jskel_cast_over_peer"] = round(jsk["cast_s_median"] / med, 2)
    if jsk.get("render_s_median"):
        row["jskel_over_peer"] = round(jsk["render_s_median"] / med, 2)
    # every setting's ratios, for a sweep of traversals
    row["jskel_over_peer_each"] = [{"setting": r.get("setting"), "cast": round(r["cast_s_median"] / med, 2) if r.get("cast_s_median") else None,
                                    "render": round(r["render_s_median"] / med, 2) if r.get("render_s_median") else None} for r in rows]
    return [row]
