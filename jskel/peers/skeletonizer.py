"""Fitting real shapes against a dedicated skeletonizer (issue 53): ``python -m jskel bench
FILE`` with a ``fit_real:`` section (``experiments/bench_fit_real.yaml``).

For each real mesh that a maintained package ships (skeletor's example neuron; navis' example
neurons; both GPL-3.0, so read from the installed ``[peers]`` packages, never committed here):

* **jskel**: ``subsamples`` clouds of ``points`` points sampled on the mesh's surface (seeds
  0, 1, ...), each given the contraction start (``fit._contract``) and fitted (the fit file's
  solver, its optional ``edits``), start and fit timed, compile included;
* **skeletor**: the mesh skeletonized as skeletor's documentation does it (``pre.fix_mesh``,
  then ``skeletonize.by_wavefront`` with ``waves=1, step_size=1``; radii its own), timed;
* both measured the same way: the signed distance (``fit.point_distances``: the frusta
  surface jskel renders) from ``fresh`` points sampled anew on the mesh (a seed of their own,
  the same points for both) to the skeleton's surface: mean and median of its magnitude, the
  share of points outside, segments and branch points.

A summary row per mesh gives jskel's mean distance over skeletor's for each subsample, the
segment counts' ratio and the subsamples' spread (largest over smallest mean distance less 1,
branch points of each, and for each pair of subsamples the share of branch points they have in
common, :func:`branch_points_matched`), for the issue's stability requirement.
"""

from __future__ import annotations

import importlib.util
import time
from pathlib import Path
from typing import Annotated

import numpy as np
from pydantic import Field

from ..config import StrictModel
from ..fit import EditsConfig, EstimateConfig, SolverConfig

#: where a package keeps its example meshes, relative to the package
MESH_DIRS = {"skeletor": "data", "navis": "data/obj"}


class RealFitBench(StrictModel):
    """``fit_real:`` section of a bench file."""

    meshes: list[str] = ["skeletor:722817260", "navis:754534424"]
    """``package:name``: the example mesh ``name``.obj that the installed package ships."""
    points: Annotated[int, Field(ge=100, le=10_000_000)] = 20000
    """Points sampled on the surface for each fit."""
    fresh: Annotated[int, Field(ge=100, le=10_000_000)] = 5000
    """Points sampled anew to measure every skeleton."""
    subsamples: Annotated[int, Field(ge=1, le=100)] = 3
    """Fits from that many clouds (seeds 0, 1, ...)."""
    start: EstimateConfig = EstimateConfig(method="contraction", ball=0.003, segment=0.01, prune=2.0)
    """The contraction start."""
    solver: SolverConfig = SolverConfig(name="lm", loss="huber", scale=0.002, maxiter=60, candidates=8, outside=4.0)
    """The fit's solver."""
    edits: EditsConfig | None = None
    """Topology edits between rounds; unset: one fit."""


class RealFitBenchFile(StrictModel):
    fit_real: RealFitBench


def mesh_path(spec: str) -> Path:
    """The .obj file of ``package:name`` (ValueError naming the spec when the package is not
    installed, unknown, or has no such mesh)."""
    pkg, _, name = spec.partition(":")
    if pkg not in MESH_DIRS or not name:
        raise ValueError(f"fit_real.meshes: {spec!r} is not package:name with a package of {sorted(MESH_DIRS)}")
    found = importlib.util.find_spec(pkg)
    if found is None or not found.submodule_search_locations:
        raise ValueError(f"fit_real.meshes: {spec!r} needs {pkg} installed (pip install -e \".[peers]\")")
    path = Path(list(found.submodule_search_locations)[0]) / MESH_DIRS[pkg] / f"{name}.obj"
    if not path.is_file():
        raise ValueError(f"fit_real.meshes: {spec!r}: no {path}")
    return path


def degrees_of(parents) -> np.ndarray:
    parents = np.asarray(parents)
    return np.bincount(np.concatenate([parents[parents >= 0], np.nonzero(parents >= 0)[0]]), minlength=len(parents))


def measured(fresh, joints, radii, parents) -> dict:
    """The issue's measures of a skeleton against fresh surface points."""
    from ..fit import point_distances

    d = point_distances(fresh, joints, radii, parents)
    deg = degrees_of(parents)
    return {"segments": int(np.sum(np.asarray(parents) >= 0)), "branch_points": int(np.sum(deg >= 3)), "tips": int(np.sum(deg == 1)),
            "mean_abs": float(np.mean(np.abs(d))), "median_abs": float(np.median(np.abs(d))), "outside_share": float(np.mean(d > 0))}


def skeletor_skeleton(mesh):
    """(joints, radii, parents, seconds) of skeletor's wavefront skeleton of ``mesh``; radii
    below a thousandth of the largest are raised to it (skeletor gives 0 at some tips; the
    frusta need a positive radius)."""
    import skeletor as sk

    t = time.perf_counter()
    fixed = sk.pre.fix_mesh(mesh, remove_disconnected=5, inplace=False)
    skel = sk.skeletonize.by_wavefront(fixed, waves=1, step_size=1, progress=False)
    seconds = time.perf_counter() - t
    swc = skel.swc
    pos = {int(v): i for i, v in enumerate(swc.node_id.values)}
    parents = np.array([pos.get(int(p), -1) for p in swc.parent_id.values])
    radii = swc.radius.values.astype(float)
    return swc[["x", "y", "z"]].values.astype(float), np.maximum(radii, 1e-3 * radii.max()), parents, seconds


def jskel_skeleton(points, b: RealFitBench):
    """(joints, radii, parents, timings) of the contraction start and the fit (with edits)."""
    from ..fit import contracted_and_fitted

    (_, _, p, info), (res, edits, rounds), secs = contracted_and_fitted(points, b.start, b.solver, b.edits, "fit_real")
    return res.joints, res.radii, res.parents, {**secs, "seconds": round(secs["start_s"] + secs["fit_s"], 3), "iterations": res.iterations,
                                                "rounds": rounds, "edits": len(edits), "start_segments": int(np.sum(p >= 0)), **info}


def branch_points_matched(a, b) -> float:
    """How many branch points two skeletons ``a`` and ``b`` ((joints, radii, parents) each)
    share, over the larger count: the branch points paired one to one by least total distance
    (an assignment), a pair counted where its two points lie within the two skeletons' median
    segment length. 1 where both have the same branch points, each within a segment of its mate."""
    from scipy.optimize import linear_sum_assignment

    def points_and_unit(j, p):
        p = np.asarray(p)
        seg = np.linalg.norm(j[p[p >= 0]] - j[p >= 0], axis=1)
        return j[degrees_of(p) >= 3], seg

    pa, la = points_and_unit(np.asarray(a[0], np.float64), a[2])
    pb, lb = points_and_unit(np.asarray(b[0], np.float64), b[2])
    most = max(len(pa), len(pb))
    if not len(pa) or not len(pb):
        return 1.0 if most == 0 else 0.0
    unit = float(np.median(np.concatenate([la, lb])))
    cost = np.linalg.norm(pa[:, None] - pb[None], axis=-1)
    row, col = linear_sum_assignment(cost)
    return float(np.sum(cost[row, col] <= unit)) / most


def run_real_fit_bench(b: RealFitBench, emit) -> list[dict]:
    """Run the benchmark (module docstring), calling ``emit(row)`` for each row as measured."""
    import trimesh

    rows = []

    def out(row):
        emit(row)
        rows.append(row)

    for spec in b.meshes:
        path = mesh_path(spec)
        surface = trimesh.load(path, process=False)
        base = {"source": spec, "vertices": int(len(surface.vertices)), "faces": int(len(surface.faces)), "extent": float(np.max(np.ptp(surface.vertices, axis=0)))}
        fresh = np.asarray(trimesh.sample.sample_surface(surface, b.fresh, seed=1000)[0], np.float64)
        j, r, p, sk_s = skeletor_skeleton(surface)
        peer = {**base, "system": "skeletor", "seconds": round(sk_s, 3), **measured(fresh, j, r, p)}
        out(peer)
        mine, skels = [], []
        for k in range(b.subsamples):
            pts = np.asarray(trimesh.sample.sample_surface(surface, b.points, seed=k)[0], np.float64)
            j, r, p, times = jskel_skeleton(pts, b)
            row = {**base, "system": "jskel", "subsample": k, "points": b.points, **times, **measured(fresh, j, r, p)}
            out(row)
            mine.append(row)
            skels.append((j, r, p))
        pairs = [(a, c) for a in range(len(skels)) for c in range(a + 1, len(skels))]
        means = [m["mean_abs"] for m in mine]
        out({**base, "summary": True, "jskel_over_skeletor_mean_abs": [round(m / peer["mean_abs"], 3) for m in means],
             "jskel_over_skeletor_segments": [round(m["segments"] / peer["segments"], 3) for m in mine],
             "subsample_mean_abs_spread": round(max(means) / min(means) - 1, 3), "subsample_branch_points": [m["branch_points"] for m in mine],
             "subsample_pairs": [list(q) for q in pairs],
             "subsample_branch_points_matched": [round(branch_points_matched(skels[a], skels[c]), 3) for a, c in pairs],
             "jskel_seconds": [m["seconds"] for m in mine], "skeletor_seconds": peer["seconds"]})
    return rows
