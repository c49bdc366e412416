"""Run in its own process (float64 is switched on here, never in the pytest workers): fuzz the
implicit and cell tracers in float32 against the same code in float64 (issue 9, item 5).

Hypothesis draws scenes and rays: for implicit models, random metaballs and a metatube under a
random rotation, a uniform scale log-uniform over 10^-2..10^3 and an offset log-uniform over
10^-2..10^5 (the tracer's step and eps scale with the model, as a user sets them); for cell
objects, a torus of cells at a random scale and centre, seen from random origins up to 10^4
sizes away, searched by the linear search and again by the voxel walk. Each example casts 256 rays in both precisions and checks: the float32 result is
float32 (no silent promotion); hit/miss agree and t agrees within 1e-3 of the scene's size plus
32 float32 ulps of the origin's distance and of t (what a float32 ray can represent) on all but
a thin band of rays (at most 2 %), and the median |dt| is a tenth of the tolerance or less.
Prints one JSON line: examples run per representation and the worst disagreeing fraction.

``JSKEL_FUZZ=long`` runs 5x the examples.
"""

import json
import os
import sys
import tempfile

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from jskel import cells, implicit  # noqa: E402
from jskel.rays import make_rays  # noqa: E402

sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
from reference import rotation  # noqa: E402  (tests/reference.py)

LONG = os.environ.get("JSKEL_FUZZ") == "long"
N = 256
worst = {k: {"examples": 0, "disagree_frac": 0.0} for k in ("implicit", "cells", "cells_walk")}
FNS = {}


def cast(rep, built, O, D, dtype):
    """First hits of float64 world rays (O, D) in ``dtype`` (one jitted batch per static)."""
    key = (rep.name, built.static, np.dtype(dtype).name)
    if key not in FNS:
        if hasattr(rep, "intersect_batch"):
            FNS[key] = jax.jit(lambda p, r: rep.intersect_batch(p, built.static, r))
        else:
            FNS[key] = jax.jit(lambda p, r: jax.vmap(lambda o, d, a, b: rep.intersect_one(p, built.static, o, d, a, b))(*r))
    rays = make_rays(O - built.anchor, D, 0.0, np.inf, dtype)
    h = FNS[key](built.params, rays)
    return np.asarray(h.t)


def rays_at(rng, lo, hi, far):
    """N rays from random points ``far`` x the box size away, aimed at random points of the box."""
    size = float(np.linalg.norm(hi - lo))
    c = 0.5 * (lo + hi)
    u = rng.normal(size=(N, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    O = c + u * far * size
    T = rng.uniform(lo, hi, (N, 3))
    D = T - O
    return O, D / np.linalg.norm(D, axis=1, keepdims=True), size


EPS32 = float(np.finfo(np.float32).eps)


def compare(t32, t64, size, name, dist):
    """``dist`` (N,): each origin's distance from the anchor. A float32 ray cannot place its
    origin closer than eps32 x dist, nor its direction closer than eps32 x t, so the tolerance is
    1e-3 of the scene's size plus 32 eps32 (dist + t). Rays through a thin band (a silhouette, or
    for cells a sliver of a cell that one sample catches and the other misses) may differ: at
    most 2 % of the rays may disagree on hit/miss or exceed the tolerance."""
    assert t32.dtype == np.float32, f"{name}: the float32 run returned {t32.dtype}"
    a, b = np.isfinite(t32), np.isfinite(t64)
    both = a & b
    tol = 1e-3 * size + 32 * EPS32 * (dist + np.where(b, t64, 0.0))
    dt = np.where(both, np.abs(t32.astype(np.float64) - np.where(b, t64, 0.0)), 0.0)
    bad = (a != b) | (dt > tol)
    frac = float(np.mean(bad))
    assert frac <= 0.02, f"{name}: {frac:.1%} of the rays disagree (hit/miss {np.mean(a != b):.1%}, |dt| over tolerance {np.mean(dt > tol):.1%})"
    if both.sum():
        assert np.median(dt[both] / tol[both]) <= 0.1, f"{name}: median |dt| / tolerance {np.median(dt[both] / tol[both]):.3g}"
    worst[name]["disagree_frac"] = max(worst[name]["disagree_frac"], frac)
    worst[name]["examples"] += 1


quaternion = st.tuples(*[st.floats(-1, 1) for _ in range(4)]).filter(lambda q: np.linalg.norm(q) > 0.1)
unit = st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda v: np.linalg.norm(v) > 0.1)
RUNS = 40 if LONG else 8


@settings(max_examples=RUNS, deadline=None, derandomize=not LONG, suppress_health_check=list(HealthCheck))
@given(seed=st.integers(0, 2**31 - 1), log_scale=st.floats(-2, 3), log_offset=st.floats(-2, 5), q=quaternion, u=unit,
       far=st.floats(1.5, 30.0))
def implicit_case(seed, log_scale, log_offset, q, u, far):
    rng = np.random.default_rng(seed)
    s = 10.0**log_scale
    off = 10.0**log_offset * np.asarray(u) / np.linalg.norm(u)
    R = rotation(q)
    c = rng.uniform(-1, 1, (4, 3)) * [1.0, 0.6, 0.6]
    pts = (c * s) @ R.T + off
    a, b = (np.array([[-0.8, -0.3, 0.1], [0.7, 0.6, -0.2]]) * s) @ R.T + off
    cfg = implicit.ImplicitConfig.model_validate({
        "type": "implicit", "threshold": 0.5, "method": "lipschitz", "eps": 1e-3 * s, "bisection": 16, "capacity": 16,
        "block_size": 0, "balls": [{"center": p.tolist(), "radius": float(rr * s)} for p, rr in zip(pts, rng.uniform(0.5, 1.0, 4))],
        "tubes": [{"a": a.tolist(), "b": b.tolist(), "radius_a": 0.5 * s, "radius_b": 0.3 * s}]})
    b32, b64 = implicit.build(cfg, np.float32), implicit.build(cfg, np.float64)
    lo, hi = b64.bounds
    O, D, size = rays_at(rng, lo, hi, far)
    compare(cast(implicit.REPRESENTATION, b32, O, D, np.float32), cast(implicit.REPRESENTATION, b64, O, D, np.float64), size, "implicit",
            np.linalg.norm(O - b64.anchor, axis=1))


CACHE = tempfile.mkdtemp()


def _cells(seed, log_scale, log_offset, u, log_far, search):
    rng = np.random.default_rng(seed)
    s = 10.0**log_scale
    centre = 10.0**log_offset * np.asarray(u) / np.linalg.norm(u)
    cfg = cells.CellsConfig.model_validate({
        "type": "cells", "base": {"type": "torus", "major": 1.0 * s, "minor": 0.45 * s, "center": centre.tolist()}, "tiles": 6,
        "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "steps_per_tile": 64, "bisection": 20,
        "search": search, "cache": CACHE})
    b32, b64 = cells.build(cfg, np.float32), cells.build(cfg, np.float64)
    lo, hi = b64.bounds
    O, D, size = rays_at(rng, np.asarray(lo), np.asarray(hi), 10.0**log_far)
    name = "cells" if search == "linear" else "cells_walk"
    compare(cast(cells.REPRESENTATION, b32, O, D, np.float32), cast(cells.REPRESENTATION, b64, O, D, np.float64), size, name,
            np.linalg.norm(O - b64.anchor, axis=1))


CELL_DRAWS = dict(seed=st.integers(0, 2**31 - 1), log_scale=st.floats(-2, 3), log_offset=st.floats(-2, 5), u=unit, log_far=st.floats(0.2, 4.0))


@settings(max_examples=RUNS, deadline=None, derandomize=not LONG, suppress_health_check=list(HealthCheck))
@given(**CELL_DRAWS)
def cells_case(seed, log_scale, log_offset, u, log_far):
    _cells(seed, log_scale, log_offset, u, log_far, "linear")


@settings(max_examples=RUNS, deadline=None, derandomize=not LONG, suppress_health_check=list(HealthCheck))
@given(**CELL_DRAWS)
def cells_walk_case(seed, log_scale, log_offset, u, log_far):
    """The voxel walk (``search: voxels``) under the same draws."""
    _cells(seed, log_scale, log_offset, u, log_far, "voxels")


if __name__ == "__main__":
    implicit_case()
    cells_case()
    cells_walk_case()
    print(json.dumps(worst))
    sys.exit(0)
