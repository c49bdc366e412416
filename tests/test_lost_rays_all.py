"""No ray lost silently, for every representation (issue 29, class 1), with hypothesis.

Each example draws an object scale over 20 decades (1e-10 .. 1e10), a translation of the object
(1e-2 .. 1e5 of its size) and 256 rays from 3 .. 1e5 sizes away (log-uniform) aimed at points of
its box grown by half (hits and misses, random directions). Every ray is either

* **decided**: it agrees with a float64 NumPy reference written here on the very float32 rays
  traced (both miss, or both hit with ``|t - t_ref| <= tol_t``), where the reference may also
  be taken on the ray moved sideways by ``delta`` (a ray that close to a silhouette, a seam or
  a corner is within tolerance of either answer); or
* **flagged**: it carries a bit of ``jskel.rays.FLAG_NAMES``.

A silent miss (no hit, no flag, the reference hits on every nearby ray) or a wrong hit fails.
Both counts go into the assertion message and are printed (``-s``).

References, float64, independent of jskel:

* frusta: a bent chain of 3 tapered segments against ``tests/reference.py`` (Bhagvat et al.
  2009, Sec. 2: the cutting planes of Eq. 3-5, the cone of Eq. 1-2, the quadratic of Eq. 10);
* implicit: one ball, whose surface (1 - r^2/R^2)^2 = T (Rouiller 2011, Sec. 3) is the sphere of
  radius R sqrt(1 - sqrt(T)): ray-sphere in closed form;
* mesh: an icosphere (80 faces), Moller-Trumbore on every face;
* relief (frusta with a height field in a shell, Bhagvat et al. 2009, Sec. 3): a collinear chain
  of 2 tapered segments under a constant height map, whose relief surface is the frustum of
  radii r + h T (closed by the same cutting planes) against ``tests/reference.py``; the march
  steps 1/64 of the shell's chord and bisects 8 times, so ``tol_t`` is the last bracket of the
  longest chord, and a chord through the relief shorter than a step may be stepped over only
  with ``graze``;
* relief on a varying map: one tapered segment under test_relief's smooth height map (bumps with
  no closed form) against that test's float64 march (4,096 samples of the shell's chord, then 40
  bisections), within one march step (a crossing stepped over carries ``graze``);
* cells: one cell that is a box of tile-map voxels (as in tests/test_spawn.py), ray-box slabs;
  the linear search (Nurnberg 2011, Sec. 3.2) steps 1/256 of the tile and bisects the step that
  crosses, so ``tol_t`` is a quarter step and ``delta`` one step (a corner chord shorter than a
  step may be stepped over); the exact voxel walk (``search: voxels``) against the same.

Implicit models of several primitives (two balls and a tapered tube that blend, Rouiller's sum of
kernels, drawn anew from each example's seed) are checked against a dense float64 march of that
sum (``tests/implicit_reference.py``: 16,384 samples of the ray's part in the influence spheres,
finer than a quarter of ``eps``, then 60 bisections); every method, fewer examples.
"""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from jskel import interface, registry
from jskel.rays import FLAG_NAMES, make_rays

import implicit_reference as iref
import reference as ref
from test_relief import _ref_march as ref_march
from test_relief import _smooth_map as smooth_map
from triangles import moller_trumbore

N = 256  # rays per example: one shape, one compile per representation
EPS32 = float(np.finfo(np.float32).eps)
ULPS = 4  # float32 spacings of |origin| + t allowed on top of each tolerance (the rays are rounded to float32)
T_ISO = 0.5
JOINTS = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.3, 1.8, 0.0], [0.3, 2.5, 0.4]])
RADII = np.array([0.3, 0.26, 0.2, 0.12])
PARENTS = [-1, 0, 1, 2]
R_JOINTS = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 2.0, 0.0]])
R_RADII = np.array([0.5, 0.45, 0.4])
R_LEVEL, R_THICK, R_STEPS, R_BIS = 128, 0.1, 64, 8  # the constant height (of 255), shell thickness (sizes), march
M_H, M_RADII, M_THICK = 2.0, (0.5, 0.4), 0.15  # relief_map: one segment along +y (sizes), under test_relief's smooth map
TILE = np.zeros((16, 16, 16), np.int64)
TILE[4:12, 3:13, 5:11] = 1  # the cell object's one cell: a box of voxels
_cast = jax.jit(interface.intersect)
#: each representation's other tracers, held to the same property (name:mode -> the section's overrides):
#: the frusta chain by brute force and through a BVH by each traversal (the Pallas kernel's walk in
#: Pallas' interpret mode on the CPU), the mesh's per-ray walks, the implicit block culling,
#: a cell object's two-sided refraction cast, the relief march's early exit
MODES = {"frusta:none": {"accel": "none"}, "frusta:bins": {"accel": "bvh", "traversal": "bins"},
         "frusta:packets": {"accel": "bvh", "traversal": "packets"}, "frusta:walks": {"accel": "bvh", "traversal": "walks"},
         "frusta:kernel": {"accel": "bvh", "traversal": "kernel"},
         "mesh:walks": {"traversal": "walks"}, "implicit:blocks": {"cull": "blocks"}, "cells:refraction": {"mode": "refraction"},
         "relief:early": {"relief": {"early_exit": True}}}


def _icosphere():
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=1)
    return np.asarray(m.vertices, np.float64), np.asarray(m.faces)


def _blend(s, off, seed):
    """(a, b, ra, rb) of two balls and a tapered tube within 0.6 s of ``off`` (float64, world)."""
    rng = np.random.default_rng(seed)
    a = off + rng.uniform(-0.6, 0.6, (3, 3)) * s
    b = a.copy()
    b[2] = a[2] + rng.normal(size=3) * 0.5 * s
    ra, rb = rng.uniform(0.5, 0.9, 3) * s, rng.uniform(0.5, 0.9, 3) * s
    rb[:2] = ra[:2]
    return a, b, ra, rb


def _raw(name, tmp, s, off, method="lipschitz", seed=0):
    if name == "implicit_blend":
        a, b, ra, rb = _blend(s, off, seed)
        return {"type": "implicit", "threshold": T_ISO, "step": 0.02 * s, "eps": 1e-3 * s, "method": method,
                "balls": [{"center": a[i].tolist(), "radius": ra[i]} for i in range(2)],
                "tubes": [{"a": a[2].tolist(), "b": b[2].tolist(), "radius_a": ra[2], "radius_b": rb[2]}]}
    if name == "frusta":
        return {"type": "frusta", "skeleton": {"joints": JOINTS.tolist(), "radii": RADII.tolist(), "parents": PARENTS,
                                               "scale": s, "offset": off.tolist()}}
    if name == "relief":
        import imageio.v3 as iio

        path = tmp / "level.png"
        iio.imwrite(path, np.full((8, 8), R_LEVEL, np.uint8))
        return {"type": "frusta", "skeleton": {"joints": R_JOINTS.tolist(), "radii": R_RADII.tolist(), "parents": [-1, 0, 1],
                                               "scale": s, "offset": off.tolist()},
                "relief": {"map": str(path), "thickness": R_THICK * s, "steps": R_STEPS, "bisection": R_BIS}}
    if name == "relief_map":
        import imageio.v3 as iio

        path = tmp / "smooth.png"
        iio.imwrite(path, smooth_map())
        return {"type": "frusta", "skeleton": {"joints": [[0, 0, 0], [0, M_H, 0]], "radii": list(M_RADII), "parents": [-1, 0],
                                               "scale": s, "offset": off.tolist()},
                "relief": {"map": str(path), "thickness": M_THICK * s, "steps": R_STEPS, "bisection": R_BIS, "scale": [1, 1], "uv": "exact"}}
    if name == "implicit":
        return {"type": "implicit", "threshold": T_ISO, "balls": [{"center": off.tolist(), "radius": s}],
                "step": 0.02 * s, "eps": 1e-3 * s, "method": method}
    if name == "mesh":
        import trimesh

        path = tmp / "ico.ply"
        if not path.exists():
            v, f = _icosphere()
            trimesh.Trimesh(v, f, process=False).export(path)
        return {"type": "mesh", "path": str(path), "scale": s, "offset": off.tolist(), "normals": "flat"}
    assert name == "cells", f"{name}: a new representation needs its object and reference here"
    np.save(tmp / "tile.npy", TILE)
    return {"type": "cells", "base": {"type": "sphere", "radius": s, "center": off.tolist()}, "tiles": 1,
            "steps_per_tile": 256, "tile_map": {"type": "file", "path": str(tmp / "tile.npy")}, "cache": None,
            "search": "voxels" if method == "voxels" else "linear"}


# ---------------------------------------------------------------- float64 references: (O, D) -> t (inf: miss)


def _sphere(c, rho):
    def trace(O, D):
        oc = O - c
        a = np.sum(D * D, 1)
        b = np.sum(oc * D, 1)
        q = np.sum(oc * oc, 1) - rho * rho
        disc = b * b - a * q
        sq = np.sqrt(np.maximum(disc, 0.0))
        # the near root without cancellation: q / (-b + sq) (Numerical Recipes' form)
        t = np.where(b < 0, q / np.where(b < 0, -b + sq, 1.0), np.inf)
        return np.where((disc >= 0) & (q > 0) & (t > 0), t, np.inf)
    return trace


def _triangles(v, f):
    tri = v[f]

    def trace(O, D):  # Moller-Trumbore, rays x faces
        t, u, w, det = moller_trumbore(tri, O, D)
        ok = (det != 0) & (u >= 0) & (w >= 0) & (u + w <= 1) & (t > 0)
        return np.where(ok, t, np.inf).min(1)
    return trace


def _box(lo, hi):
    def trace(O, D):
        with np.errstate(divide="ignore", invalid="ignore"):
            t1, t2 = (lo - O) / D, (hi - O) / D
        t1, t2 = np.nan_to_num(t1, nan=-np.inf), np.nan_to_num(t2, nan=np.inf)
        near, far = np.minimum(t1, t2).max(1), np.maximum(t1, t2).min(1)
        return np.where((near <= far) & (near > 0), near, np.inf)
    return trace


def _reference(name, built, s, off, seed=0):
    """(trace, tol_t, delta): the float64 surface and the tolerances that state what agreeing means."""
    if name == "implicit_blend":
        def march(O, D):  # first_root takes unit directions; the float32 rays' are not, in float64
            n = np.linalg.norm(D, axis=1)
            return iref.first_root(O, D / n[:, None], *_blend(s, off, seed), T_ISO, n=16384, batch=16)[0] / n
        return march, 4e-3 * s, 1e-3 * s
    if name == "frusta":
        segs = ref.segments(JOINTS * s + off, RADII * s, PARENTS)
        return (lambda O, D: ref.intersect(segs, O, D)[0]), 1e-4 * s, 1e-4 * s
    if name == "implicit":
        return _sphere(off, s * np.sqrt(1 - np.sqrt(T_ISO))), 4e-3 * s, 1e-3 * s
    if name == "relief":
        segs = ref.segments(R_JOINTS * s + off, (R_RADII + R_LEVEL / 255 * R_THICK) * s, [-1, 0, 1])
        chord = (2.0 + 2 * (R_RADII.max() + R_THICK)) * s  # a bound of any chord through the chain's shell
        return (lambda O, D: ref.intersect(segs, O, D)[0]), chord / R_STEPS * 0.5**R_BIS + 1e-4 * s, 1e-4 * s
    if name == "relief_map":  # test_relief's float64 march of the same map, in the segment's unit frame
        def march(O, D):  # from 10 sizes before the segment's centre (the reference's exit search reaches 100)
            n = np.linalg.norm(D, axis=1)
            Ou, Du = (O - off) / s, D / n[:, None]
            t0 = np.maximum(np.sum(([0.0, 0.5 * M_H, 0.0] - Ou) * Du, 1) - 10.0, 0.0)
            return (t0 + ref_march(smooth_map(), *M_RADII, M_H, M_THICK, Ou + t0[:, None] * Du, Du)[0]) * s / n
        chord = np.hypot(M_H, 2 * (max(M_RADII) + M_THICK)) * s  # the longest chord through the shell
        return march, chord / R_STEPS + 1e-4 * s, 1e-4 * s
    if name == "mesh":
        v, f = _icosphere()
        return _triangles(v * s + off, f), 1e-4 * s, 1e-4 * s
    vox = built.info["tile_size"] / TILE.shape[0]
    idx = np.argwhere(TILE)
    lo = np.asarray(built.bounds[0], np.float64) + vox * idx.min(0)
    hi = np.asarray(built.bounds[0], np.float64) + vox * (idx.max(0) + 1)
    step = built.info["tile_size"] / 256
    return _box(lo, hi), step / 4, step


# ---------------------------------------------------------------- one example


def _rays(rng, lo, hi, s):
    u = rng.normal(size=(N, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    c = 0.5 * (lo + hi)
    O = c + u * s * 10.0 ** rng.uniform(0.5, 5, (N, 1))
    D = c + (rng.uniform(size=(N, 3)) - 0.5) * 1.5 * (hi - lo) - O
    return O, D / np.linalg.norm(D, axis=1, keepdims=True)


def _sideways(D):
    a = np.cross(D, [0.3, 0.5, 0.8])
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(D, a)
    return (a, -a, b, -b)


def _agrees(got, t_hit, t, tol):
    """Both miss, or both hit within ``tol``."""
    return (~got & ~np.isfinite(t)) | (got & np.isfinite(t) & (np.abs(np.where(got, t_hit, 0) - np.where(np.isfinite(t), t, 0)) <= tol))


def _with(raw: dict, overrides: dict) -> dict:
    """``raw`` with a mode's ``overrides`` (a ``relief`` entry merged into the relief's section)."""
    out = {**raw, **{k: v for k, v in overrides.items() if k != "relief"}}
    return {**out, "relief": {**raw["relief"], **overrides["relief"]}} if "relief" in overrides else out


def _check(name, tmp, log_scale, log_shift, seed, method="lipschitz"):
    s = 10.0**log_scale
    off = s * 10.0**log_shift * np.array([0.6, -0.8, 0.3])
    name, _, mode = name.partition(":")  # "frusta:bins": the frusta under MODES["frusta:bins"]
    rep = registry.get({"implicit_blend": "implicit", "relief": "frusta", "relief_map": "frusta"}.get(name, name))
    raw = _with(_raw(name, tmp, s, off, method, seed), MODES[f"{name}:{mode}"] if mode else {})
    built = rep.build(rep.Config.model_validate(raw), np.float32)
    anchor = np.asarray(built.anchor, np.float64)
    lo, hi = (np.asarray(b, np.float64) for b in built.bounds)
    O, D = _rays(np.random.default_rng(seed), lo, hi, s)
    r = make_rays(O - anchor, D)
    hit = jax.tree_util.tree_map(np.asarray, _cast(interface.Object.of(rep, built), r))
    Or, Dr = np.asarray(r.origins, np.float64), np.asarray(r.directions, np.float64)  # the rays traced
    trace, tol_t, delta = _reference(name, built, s, off, seed)
    Ow = Or + anchor
    t_ref = trace(Ow, Dr)
    # float32's own spacing at the ray's origin and distance: the rays, the surface and t carry it
    ulps = ULPS * EPS32 * (np.linalg.norm(Or, axis=1) + np.where(np.isfinite(t_ref), t_ref, 0.0))
    tol, dl = tol_t + ulps, delta + ulps
    got = np.isfinite(hit.t)
    flag = (np.zeros(N, np.int32) if hit.flags is None else hit.flags) != 0  # closed forms carry none: all decided
    ok = _agrees(got, hit.t, t_ref, tol)
    sure_hit = got & ~flag & ok & np.isfinite(t_ref)  # agreeing on the ray itself
    for side in _sideways(Dr):  # the rays beside it, where the ray itself does not decide
        i = np.nonzero(~ok & ~flag)[0]
        if i.size:
            ok[i] |= _agrees(got[i], hit.t[i], trace(Ow[i] + dl[i, None] * side[i], Dr[i]), tol[i])
    flags = np.zeros(N, np.int32) if hit.flags is None else hit.flags
    both = got & np.isfinite(t_ref) & ~flag
    silent = ~got & ~flag & ~ok
    wrong = got & ~flag & ~ok
    counts = {"rays": N, "decided": int(np.sum(ok & ~flag)), "flagged": int(np.sum(flag)),
              "max_dt_sizes": float(np.max(np.abs(hit.t[both] - t_ref[both]), initial=0.0) / s),
              "silent_miss": int(np.sum(silent)), "wrong_hit": int(np.sum(wrong)), "ref_hits": int(np.sum(np.isfinite(t_ref))),
              "by_flag": {n: int(np.sum((flags & b) != 0)) for b, n in FLAG_NAMES.items() if np.any(flags & b)}}
    label = f"{name}{':' + mode if mode else ''} ({method}) at scale {s:.3g}, shift {10.0**log_shift:.3g} sizes, seed {seed}: {counts}"
    print(label)
    assert not np.any(silent | wrong), (label, Ow[silent | wrong][:3], Dr[silent | wrong][:3], hit.t[silent | wrong][:3],
                                        t_ref[silent | wrong][:3])
    assert counts["decided"] > 0, label
    assert np.any(sure_hit), label  # the example hits: not a suite of misses
    return counts


@pytest.fixture(params=registry.names())
def name(request):
    return request.param


@settings(max_examples=12, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(log_scale=st.floats(-10, 10), log_shift=st.floats(-2, 5), seed=st.integers(0, 2**31 - 1))
def test_every_ray_is_a_hit_within_tolerance_or_flagged(name, log_scale, log_shift, seed, tmp_path_factory):
    _check(name, tmp_path_factory.mktemp(name), log_scale, log_shift, seed)


@pytest.mark.parametrize("log_scale", [-10.0, 0.0, 10.0])
def test_the_extremes_of_scale_at_the_farthest_shift(name, log_scale, tmp_path_factory):
    """The corners hypothesis may not draw: 1e-10 and 1e10 with the object 1e5 sizes away."""
    _check(name, tmp_path_factory.mktemp(name), log_scale, 5.0, 7)


@pytest.mark.parametrize("method", ["naive", "bisection"])
@settings(max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(log_scale=st.floats(-10, 10), log_shift=st.floats(-2, 5), seed=st.integers(0, 2**31 - 1))
def test_implicit_methods_hit_within_tolerance_or_flag(method, log_scale, log_shift, seed, tmp_path_factory):
    """The implicit ball with the other two tracers: the fixed-step march and the thesis'
    bisection (Rouiller 2011, Sec. 4.2), whose start point inside is the ball's centre."""
    _check("implicit", tmp_path_factory.mktemp(method), log_scale, log_shift, seed, method)


@settings(max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(log_scale=st.floats(-10, 10), log_shift=st.floats(-2, 5), seed=st.integers(0, 2**31 - 1))
def test_the_cells_voxel_walk_hits_within_tolerance_or_flags(log_scale, log_shift, seed, tmp_path_factory):
    """The cell object through the exact voxel walk (``search: voxels``) instead of the linear
    search, against the same ray-box reference."""
    _check("cells", tmp_path_factory.mktemp("voxels"), log_scale, log_shift, seed, "voxels")


@pytest.mark.parametrize("log_scale", [-10.0, 10.0])
def test_the_cells_voxel_walk_at_the_extremes(log_scale, tmp_path_factory):
    """The walk at 1e-10 and 1e10 with the object 1e5 sizes away."""
    _check("cells", tmp_path_factory.mktemp("voxels"), log_scale, 5.0, 7, "voxels")


@pytest.mark.parametrize("method", ["lipschitz", "naive", "bisection"])
@settings(max_examples=2, deadline=None, derandomize=True, phases=[Phase.generate], suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(log_scale=st.floats(-10, 10), log_shift=st.floats(-2, 5), seed=st.integers(0, 2**31 - 1))
def test_blended_primitives_hit_within_tolerance_or_flag(method, log_scale, log_shift, seed, tmp_path_factory):
    """Two balls and a tapered tube that blend (Rouiller 2011, Sec. 3: the kernels summed),
    drawn from the seed, with each tracer: the bisection's Sec. 4.2.1 inside points are the
    centres' projections and the tube's, and a ray may pass a blend between them (Fig. 7) or
    a crossing before the one it brackets (Sec. 4.2.2): those must carry flags."""
    _check("implicit_blend", tmp_path_factory.mktemp(method), log_scale, log_shift, seed, method)


@settings(max_examples=8, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(log_scale=st.floats(-10, 10), log_shift=st.floats(-2, 5), seed=st.integers(0, 2**31 - 1))
def test_relief_hits_within_tolerance_or_flags(log_scale, log_shift, seed, tmp_path_factory):
    """Frusta with relief (a constant height map: the surface is the frustum of radii r + h T),
    through the shell's march and bisection (Bhagvat et al. 2009, Sec. 3)."""
    _check("relief", tmp_path_factory.mktemp("relief"), log_scale, log_shift, seed)


@settings(max_examples=6, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(log_scale=st.floats(-10, 10), log_shift=st.floats(-2, 5), seed=st.integers(0, 2**31 - 1))
def test_relief_on_a_varying_height_map_hits_within_tolerance_or_flags(log_scale, log_shift, seed, tmp_path_factory):
    """A tapered segment under test_relief's smooth height map (0.5 + 0.45 sin 2 pi u cos 2 pi v,
    bumps that cast no closed form), against that test's float64 march (4,096 samples of the
    shell's chord, 40 bisections; u = atan2(x, z) / 2 pi, v = y / H), within one march step:
    a crossing stepped over is missed or found late only with ``graze``."""
    _check("relief_map", tmp_path_factory.mktemp("relief_map"), log_scale, log_shift, seed)


@pytest.fixture(params=sorted(MODES))
def mode(request):
    return request.param


@settings(max_examples=4, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(log_scale=st.floats(-10, 10), log_shift=st.floats(-2, 5), seed=st.integers(0, 2**31 - 1))
def test_each_representations_other_tracers_hit_within_tolerance_or_flag(mode, log_scale, log_shift, seed, tmp_path_factory):
    """:data:`MODES`: every other tracer of a representation against the same float64 reference
    as its default, over the same 20 decades of scale and shifts to 1e5 sizes."""
    _check(mode, tmp_path_factory.mktemp(mode.replace(":", "_")), log_scale, log_shift, seed)


@pytest.mark.parametrize("log_scale", [-10.0, 10.0])
def test_relief_at_the_extremes(log_scale, tmp_path_factory):
    """The relief at 1e-10 and 1e10 with the object 1e5 sizes away."""
    _check("relief", tmp_path_factory.mktemp("relief"), log_scale, 5.0, 7)
