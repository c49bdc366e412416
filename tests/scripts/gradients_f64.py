"""Run in its own process (float64 is switched on here, never in the pytest workers): check
derivatives against central differences with ``jax.test_util``'s ``check_jvp`` and
``check_vjp`` (what ``check_grads(order=1, modes=["fwd", "rev"])`` runs: forward mode, and
reverse mode as ``jax.grad`` runs it) and print one JSON line of what was checked.

Hit distances through each representation's *batch* intersection (``interface.intersect``, the
path renders and fits take), one check per (representation, mode) on 8 rays that hit, in the
object's parameters and the ray origins at once (one random direction through all of them):

* frusta: brute force (``accel: none``, the reference path) and the block scan (``accel:
  blocks``) in every float field of the segments; the BVH's
  bins, packets, per-ray walks and the Pallas kernel's walk (``traversal: kernel``, in Pallas'
  interpret mode on the CPU: the GPU's kernel body, not its Triton lowering) in every float field
  of the segments with the BVH built again from them (its packed rows are a cache of those fields); bins again in the joints and radii
  through the device rebuild (``frusta._device``) that makes both. Relief by the paper's march
  and by the exact walk (with exact v on a bent chain, and with the texels free). Loops of
  data-dependent length are never differentiated: ``accel.nearest_tangent`` differentiates the
  winner's closed form, or the relief's implicit-function derivative at the marched root
  (``numerics.differentiable_root``);
* implicit, each of the three methods: the Lipschitz march and the bisection culled through
  blocks (the tree, the Morton blocks' spheres) with room for two blocks per ray, so that rays
  along a row of balls overflow and are retraced by ``wavefront.compact_map``, whose loop over
  sub-batches has a data-dependent trip count (this path raised in reverse mode); the naive
  march with flat culling; in the primitives' centres and radii, and the threshold;
* cells, first hit (the reflection mode's cast too; also through the voxel walk, ``search:
  voxels``) and the two-sided cast of the refraction
  mode, in every float leaf: membership is discrete, so t moves only with the face of the voxel
  the ray crosses, i.e. with the origin, the object's corner ``lo`` and its tile edge ``size``;
  the other floats (normals, colours, environment, step, ior) leave t unchanged, and the check
  holds their derivative to the 0 that finite differences give;
* mesh, packets and per-ray walks, in every float leaf (t moves with the vertices of the winning
  triangle only).

Then the same batch checks under hypothesis (issue 29, class 3): the frusta tree (blocks), the
relief cylinder (the fixed march), the cell torus (first hit) and the icosphere (walks) scaled
by 1e-10 .. 1e10 and moved 1e-2 .. 1e5 of their size, their rays starting 3 .. 1e5 sizes away
(log-uniform), three drawn examples each and both ends of the range moved 1e5 sizes away with
rays from 1e5 sizes, through one compiled program per object (``keyed_program``); and the
same for the frusta tree through the BVH's bins, the implicit bisection method, the cells' voxel
walk and the mesh's packets (``SCALED_MODES``). t is checked
in units of the size (derivatives of order 1 at every scale, so the tolerances mean the same),
with steps that grow as the cube root of the rays' distance (t's rounding against curvature).
Every argument is stepped in its own unit (``leaf_scales``: s for lengths and positions, 1 for
unit vectors and ratios), and only rays whose t is smooth within the step are checked
(``smooth``: a kink of t, at a silhouette, a cutting plane, a texel or voxel edge, makes
finite differences disagree with themselves); cell hits within 1e-3 of a voxel edge are left
out besides. And four of the implicit grid's balls (the Lipschitz march, and the bisection) the
same way, each primitive moved whole as ``implicit_moved`` moves it (one program for every
example, as for the others).

And the fitting's signed point-to-frusta distance (issue 10) against joints, radii and the point.

Run only when named (``OPT_IN``; ``python tests/scripts/gradients_f64.py render_implicit``): a
whole render, camera to image, the single-object integrator's colours of a 6 x 6 image of two
blended balls in the eye's position and the balls' parameters, at every pixel that hits.
"""

import json
import sys
import tempfile
import time
import zlib
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.test_util import check_jvp, check_vjp  # noqa: E402

from jskel import registry  # noqa: E402
from jskel.interface import Object, intersect  # noqa: E402
from jskel.rays import FLAG_OVERFLOW, make_rays  # noqa: E402

TMP = Path(tempfile.mkdtemp())
checked = {}


def checker(g):
    """``(run, program)``: ``run(args, rows=None, only=None)`` is ``check_jvp`` and ``check_vjp``
    of ``g(*args)`` (of its entries ``rows``; in its argument ``only`` alone), all through one
    compiled ``program(args, v, u) -> (g, J v, J^T u)``: g's value, its linearisation and that
    one's transpose (``check_grads`` of a jitted function compiles the value, the JVP and the
    two halves of the VJP apart)."""

    @jax.jit
    def both(a, v, u):
        y, lin = jax.linearize(g, *a)
        return y, lin(*v), jax.linear_transpose(lin, *a)(u)

    def run(args, rows=None, name="", only=None, eps=1e-6):
        zero = jax.tree_util.tree_map(jnp.zeros_like, args)
        shape = jax.eval_shape(g, *args)
        nothing = jnp.zeros(shape.shape, shape.dtype)
        pick = (lambda y: y) if rows is None else (lambda y: y[rows])

        def put(u):  # (an array of the program's own type: a NumPy scalar would compile again)
            u = jnp.asarray(u, shape.dtype)
            return u.reshape(shape.shape) if rows is None else nothing.at[rows].set(u)

        def whole(a):  # ``only``: the other arguments stay at args, with tangents 0
            return a if only is None else args[:only] + tuple(a) + args[only + 1:]

        def f(*a):
            return pick(both(whole(a), zero, nothing)[0])

        def f_jvp(a, v):
            y, jv, _ = both(whole(a), v if only is None else zero[:only] + tuple(v) + zero[only + 1:], nothing)
            return pick(y), pick(jv)

        def f_vjp(*a):
            def vjp(u):
                ct = both(whole(a), zero, put(u))[2]
                return ct if only is None else (ct[only],)

            return f(*a), vjp

        mine = args if only is None else (args[only],)
        check_jvp(f, f_jvp, mine, eps=eps, err_msg=name)
        check_vjp(f, f_vjp, mine, eps=eps, err_msg=name)

    return run, both


def float_leaves(params):
    """Every float leaf of ``params``, each free: (theta, theta -> params)."""
    leaves, tree = jax.tree_util.tree_flatten(params)
    floats = [i for i, a in enumerate(leaves) if jnp.issubdtype(a.dtype, jnp.floating)]

    def params_of(values):
        mixed = list(leaves)
        for i, v in zip(floats, values):
            mixed[i] = v
        return tree.unflatten(mixed)

    return [leaves[i] for i in floats], params_of


def check_batch(name, raw, origins, directions, free=lambda b, cfg: float_leaves(b.params), n=8, eps=1e-6, record=True, unit=None):
    """Forward and reverse mode of the first ``n`` hit rays' t through the batch intersection,
    in the parameters ``free(built, cfg)`` makes free and the ray origins. With ``unit`` (the
    scaled checks: the object's size s) the origins and t are in units of s and only rays whose
    t is smooth within the step (:func:`smooth`) are checked. Returns (built, rays)."""
    rep = registry.get(raw["type"])
    cfg = rep.Config.model_validate(raw)
    b = rep.build(cfg, np.float64)
    d = np.asarray(directions, float)
    rays = make_rays(np.asarray(origins) - b.anchor, d / np.linalg.norm(d, axis=1, keepdims=True), dtype=np.float64)
    theta, params_of = free(b, cfg)

    w = 1.0 if unit is None else unit

    def t_all(th, o):  # (with ``unit``, t in units of s too: derivatives of order 1 at every scale)
        return intersect(Object(params_of(th), b.static, rep.name), rays._replace(origins=o * w)).t / w

    run, both = checker(t_all)
    args = (theta, rays.origins / w)
    value = lambda a: np.asarray(both(a, *jax.tree_util.tree_map(jnp.zeros_like, (a, rays.t_min)))[0])  # noqa: E731
    ok = np.isfinite(value(args))
    if unit is not None:
        ok &= smooth(value, args, eps, name)
    rows = np.nonzero(ok)[0][:n]
    assert rows.size == n, (name, rows.size)
    run(args, rows, name, eps=eps)
    if record:
        checked[name] = n
    return b, rays


def down(n, lo, hi, z, rng, tilt=(0.03, -0.02)):
    """n rays from the plane at height z, (nearly) straight down, over [lo, hi] in x and y."""
    o = np.stack([rng.uniform(lo[0], hi[0], n), rng.uniform(lo[1], hi[1], n), np.full(n, z)], 1)
    return o, np.tile([tilt[0], tilt[1], -1.0], (n, 1))


def segment_free(b, cfg):
    """Every float field of the plain segments, the BVH built again from them (``build_bvh``:
    its packed rows are a cache of the fields, its boxes bound them)."""
    from jskel.frusta._accel import build_bvh

    leaves, params_of_leaves = float_leaves(b.params.plain.frusta)
    grp = b.params.plain

    def params_of(values):
        f = params_of_leaves(values)
        return b.params._replace(plain=grp._replace(frusta=f, bvh=build_bvh(f, b.static.leaf)))

    return leaves, params_of


def skeleton_free(b, cfg):
    """The joints and radii, through the device rebuild that makes the segments and the BVH."""
    from jskel.frusta import Group, host_frusta
    from jskel.frusta._device import _core_jit
    from jskel.frusta._geometry import padded_topology

    _, topo, _, joints, radii, _ = host_frusta(cfg)
    grp = b.params.plain
    dtopo = padded_topology(topo, grp.frusta.h.shape[0])

    def params_of(th):
        seg, bvh = _core_jit(th[0], th[1], 0.0, dtopo, grp.frusta, b.static.leaf, int(topo.depth.max()) + 1)
        return b.params._replace(plain=Group(seg, grp.block_c, grp.block_r, bvh))

    return (jnp.asarray(joints - b.anchor), jnp.asarray(radii)), params_of


def implicit_moved(sc, th):
    """The implicit params ``sc`` with each primitive shifted whole by ``th[0]`` (both ends),
    its radii times ``th[1]`` and the threshold ``th[2]``."""
    shift, rscale, T = th
    p = sc.prims
    prims = p._replace(a=p.a + shift, b=p.b + shift, ra=p.ra * rscale, rb=p.rb * rscale)
    return sc._replace(prims=prims, tune=sc.tune._replace(threshold=T))


def implicit_free(b, cfg):
    """A ball is a segment of length 0, whose field is not differentiable in its two ends apart:
    each primitive moves as a whole (one shift of both ends), its radii scale together, and the
    threshold moves (:func:`implicit_moved`)."""
    sc = b.params
    return (jnp.zeros_like(sc.prims.a), jnp.ones_like(sc.prims.ra), sc.tune.threshold), lambda th: implicit_moved(sc, th)


which = set(sys.argv[1].split(",")) if len(sys.argv) > 1 else None  # a subset of the checks, by name
#: checks run only when named: a whole render's derivative program (the integrator linearised
#: and transposed in float64) took ~18 s of CPU to compile (one-off, /usr/bin/time of the command
#: in the docstring less the script's start, 2-core AMD EPYC, 2026-12-02, at 9907a66),
#: more than the suite's budget leaves for one check
OPT_IN = {"render_implicit"}


#: each check's seconds, its compile included (from its ``wanted`` to the next one's, or to the
#: end), printed beside what was checked: where the suite's time in this process goes
seconds = {}
_running = [None, 0.0]


def _lap(next_name=None):
    """Close the running check's time; start ``next_name``'s."""
    now = time.perf_counter()
    if _running[0] is not None:
        seconds[_running[0]] = round(now - _running[1], 2)
    _running[:] = [next_name, now]


def wanted(name):
    """Whether to run the check ``name``; it then sets ``rng`` to a generator of its own, so a
    subset draws the same rays as the whole run."""
    global rng
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    run = name not in OPT_IN if which is None else name in which
    _lap(name if run else None)
    return run


# frusta: a branching tree of 6 segments
TREE = {"joints": [[0, 0, 0], [0, 1, 0], [0.3, 2, 0.1], [-0.4, 1.8, 0.2], [0.5, 3, 0.3], [0.1, 2.9, -0.3]],
        "radii": [0.3, 0.25, 0.2, 0.15, 0.1, 0.08], "parents": [-1, 0, 1, 1, 2, 2]}
for name, accel, trav, free in (("none", "none", "auto", None), ("blocks", "blocks", "auto", None), ("bins", "bvh", "bins", segment_free),
                                ("packets", "bvh", "packets", segment_free), ("walks", "bvh", "walks", segment_free),
                                ("kernel", "bvh", "kernel", segment_free), ("skeleton", "bvh", "bins", skeleton_free)):
    if wanted(f"frusta_{name}"):
        o, d = down(48, (-0.3, 0.0), (0.3, 2.9), 4.0, rng)
        check_batch(f"frusta_{name}", {"type": "frusta", "skeleton": TREE, "accel": accel, "traversal": trav, "packet": 4, "group": 8},
                    o, d, **({"free": free} if free else {}))

# relief: a cylinder with a brick height field in a shell
RELIEF_CYLINDER = {"joints": [[0, 0, 0], [0, 1.5, 0]], "radii": [0.5, 0.45], "parents": [-1, 0]}
RELIEF = {"map": "brick", "thickness": 0.1, "scale": [2.0, 1.0], "steps": 64, "bisection": 40, "uv": "exact"}
# (the fixed march alone: since the relief's derivative is the implicit-function theorem's at
# the root its search found, with no march of its own (``_relief.relief_root``), the early-exit
# march has the same derivative program and its forward equality is test_relief's; the exact
# walk's approximate-uv root is checked with the texels free below, its exact-v root on the
# bent chain)
if wanted("relief_fixed"):
    o, d = down(32, (-0.2, 0.3), (0.2, 1.2), 3.0, rng, (0.03, -0.05))
    check_batch("relief_fixed", {"type": "frusta", "skeleton": RELIEF_CYLINDER, "relief": {**RELIEF, "early_exit": False}}, o, d)
if wanted("relief_exact_texels"):  # the map's texels as traced floats (relief.storage: float), with the radii and thickness
    o, d = down(32, (-0.2, 0.3), (0.2, 1.2), 3.0, rng, (0.03, -0.05))
    check_batch("relief_exact_texels", {"type": "frusta", "skeleton": RELIEF_CYLINDER,
                                        "relief": {**RELIEF, "uv": "approximate", "method": "exact", "storage": "float"}}, o, d)
if wanted("relief_exact_bent"):  # exact v (Eq. 7) across a joint whose cutting plane tilts
    o, d = down(32, (-0.2, 0.5), (0.3, 1.2), 3.0, rng, (0.03, -0.05))
    check_batch("relief_exact_bent", {"type": "frusta", "skeleton": {"joints": [[0, 0, 0], [0, 0.8, 0], [0.3, 1.6, 0]],
                                                                       "radii": [0.5, 0.45, 0.4], "parents": [-1, 0, 1]},
                                      "relief": {**RELIEF, "uv": "exact", "method": "exact"}}, o, d)

# implicit: a 6 x 4 grid of balls. The Lipschitz march (the tree's leaves) and the bisection
# (Morton blocks) cull in blocks of 4 with two blocks kept per ray: rays along the rows meet more
# and are retraced with flat culling through wavefront.compact_map, in each block culling's
# program. The naive march culls flat (``block_size: 0``, room for every ball): its roots'
# derivatives in a program without the retrace, whose derivative the other two check (in
# float64 the retrace made this check 26 s of CPU against 7 s flat, one-off, 2026-12-03)
BALLS = [{"center": [0.9 * i, 0.9 * j, 0.0], "radius": 0.6} for i in range(6) for j in range(4)]
for method, cull in (("lipschitz", "tree"), ("bisection", "blocks"), ("naive", None), ("exact", "tree")):
    name = f"implicit_{method}"
    if not wanted(name):
        continue
    o1, d1 = down(4, (-0.2, -0.2), (0.2, 0.2), 3.0, rng)
    o1[:, :2] += 0.9 * rng.integers(0, [6, 4], (4, 2))  # near a ball's centre
    o2 = np.stack([np.full(4, -2.0), 0.9 * np.arange(4) + 0.05, np.full(4, 0.02)], 1)
    d2 = np.tile([1.0, 0.01, 0.005], (4, 1))
    culling = {"block_size": 0} if cull is None else {"cull": cull, "block_size": 4, "block_capacity": 2}
    raw = {"type": "implicit", "threshold": 0.5, "balls": BALLS, "method": method, "step": 0.01, "eps": 1e-3,
           "bisection": 40, "capacity": 24, **culling}
    b, rays = check_batch(name, raw, np.vstack([o1, o2]), np.vstack([d1, d2]), free=implicit_free)
    if cull is not None:
        rep = registry.get("implicit")
        first = jax.vmap(lambda o, d, a, c: rep.intersect_one(b.params, b.static, o, d, a, c))(*rays)
        assert np.sum((np.asarray(first.flags) & FLAG_OVERFLOW) != 0) >= 2, "no ray went through the compacted retrace"

# implicit, exact on tubes: a constant-radius tube (its three quartic pieces), a tapering one
# (the degree-8 axis piece) and a ball where they meet; rays straight down onto the axes
if wanted("implicit_exact_tubes"):
    TUBES = [{"a": [0.0, 0.0, 0.0], "b": [1.6, 0.0, 0.0], "radius_a": 0.7, "radius_b": 0.7},
             {"a": [1.6, 0.0, 0.0], "b": [2.4, 1.2, 0.0], "radius_a": 0.7, "radius_b": 0.4}]
    s = rng.uniform(0.05, 0.95, 16)
    ends = np.array([[[0.0, 0.0], [1.6, 0.0]], [[1.6, 0.0], [2.4, 1.2]]])[np.arange(16) % 2]
    xy = ends[:, 0] + s[:, None] * (ends[:, 1] - ends[:, 0]) + rng.uniform(-0.15, 0.15, (16, 2))
    o = np.concatenate([xy, np.full((16, 1), 3.0)], 1)
    raw = {"type": "implicit", "threshold": 0.5, "tubes": TUBES, "balls": [{"center": [1.6, 0.0, 0.0], "radius": 0.6}],
           "method": "exact", "eps": 1e-3, "bisection": 40}
    check_batch("implicit_exact_tubes", raw, o, np.tile([0.03, -0.02, -1.0], (16, 1)), free=implicit_free)

# cells: a torus of Voronoi cells, first hit and the two-sided cast of the refraction mode, rays
# aimed at the tube
# (and the first hit again through the exact voxel walk, ``search: voxels``)
for mode, search in (("first_hit", "linear"), ("refraction", "linear"), ("first_hit", "voxels")):
    name = f"cells_{mode}" if search == "linear" else f"cells_{search}"
    if wanted(name):
        ang = rng.uniform(0, 2 * np.pi, 16)
        ring = np.stack([np.cos(ang), np.zeros(16), np.sin(ang)], 1)  # the torus' centre line (y up)
        o = 3.0 * ring + [0.1, 2.0, 0.3]
        d = ring - o  # from outside and above, aimed at the tube
        check_batch(name, {"type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45}, "tiles": 6,
                           "bisection": 40, "mode": mode, "search": search, "cache": str(TMP / "cells"),
                           "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}}, o, d)

# mesh: an icosphere, packets and walks
sphere = TMP / "sphere.ply"
import trimesh  # noqa: E402

trimesh.creation.icosphere(subdivisions=2, radius=1.0).export(sphere)
for trav in ("packets", "walks"):
    if wanted(f"mesh_{trav}"):
        o, d = down(16, (-0.7, -0.7), (0.7, 0.7), 3.0, rng)
        check_batch(f"mesh_{trav}", {"type": "mesh", "path": str(sphere), "traversal": trav}, o, d)

# a whole render (camera -> image): the integrator's colours of a 6 x 6 image of two blended
# balls (the single-object program jskel render runs: camera rays, march, normal, albedo,
# Blinn-Phong under one light) in the eye's position and the balls' centres, radii and
# threshold, at the pixels whose ray hits (away from the silhouette a colour is smooth)
if wanted("render_implicit"):
    from jskel.config import validate  # noqa: E402
    from jskel.render import camera_of, camera_rays  # noqa: E402
    from jskel.render._build import place_objects  # noqa: E402
    from jskel.render._scene import Scene, build_scene, scene_call  # noqa: E402

    exp = validate({"object": {"type": "implicit", "threshold": 0.5, "method": "lipschitz", "step": 0.01, "eps": 1e-3, "bisection": 40,
                               "balls": [{"center": [0, 0, 0], "radius": 1.0}, {"center": [0.5, 0.3, 0.1], "radius": 0.8}]},
                    "camera": {"eye": [0.4, 0.5, 3.0], "target": [0.2, 0.1, 0], "up": [0, 1, 0], "fov_deg": 25, "width": 6, "height": 6},
                    "lights": [{"direction": [0.3, 0.5, 1.0]}]})
    placed = place_objects(exp, np.float64)
    params, static, _, _, _ = build_scene(exp, np.float64, placed)
    b = placed[0].built
    rays = jax.tree_util.tree_map(jnp.asarray, camera_rays(exp, camera_of(exp), b.anchor, np.float64))  # (as device arrays: constants of a custom root)
    theta, params_of = implicit_free(b, None)

    def image(th, eye):
        return scene_call(Scene(params._replace(objects=(params_of(th),)), static), rays._replace(origins=jnp.broadcast_to(eye, rays.origins.shape)))["rgb"]

    run, both = checker(image)
    args = (theta, rays.origins[0])
    t = np.asarray(scene_call(Scene(params, static), rays)["hit"].t)
    rows = np.nonzero(np.isfinite(t))[0]
    assert 8 <= rows.size < t.size, rows.size  # hits and misses: the balls inside the image
    run(args, rows, "render_implicit")
    checked["render_implicit"] = int(rows.size)

# hypothesis over scales and shifts (issue 29, class 3): the same batch checks on objects
# scaled by 1e-3 .. 1e3 and moved 1e-2 .. 1e3 of their size, their rays with them, finite
# differences at 1e-6 of the size. One compiled program per (representation, static options,
# params tree): every drawn example has the same shapes and reuses it.
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

from jskel.rays import Rays  # noqa: E402

_PROGRAMS: dict = {}


def keyed_program(rep, static, tree, floats):
    """``both(args, fixed, v, u) -> (t, J v, J^T u)`` of the batch's t in ``args`` = (theta, the
    ray origins), with ``fixed`` = (every leaf, directions, t_min, t_max) held: theta is the
    params' float leaves ``floats`` (a tuple of leaf indices), or, with ``floats`` a function
    ``(params, theta) -> params`` (:func:`implicit_moved`), what it moves the params by. One
    jitted function per key, so new values compile nothing."""
    key = (rep.name, static, tree, floats if callable(floats) else tuple(floats))
    if key not in _PROGRAMS:
        def g(theta, o, leaves, d, a, b):
            if callable(floats):
                return intersect(Object(floats(tree.unflatten(leaves), theta), static, rep.name), Rays(o, d, a, b)).t
            mixed = list(leaves)
            for i, v in zip(floats, theta):
                mixed[i] = v
            return intersect(Object(tree.unflatten(mixed), static, rep.name), Rays(o, d, a, b)).t

        @jax.jit
        def both(args, fixed, v, u):
            y, lin = jax.linearize(lambda th, o: g(th, o, *fixed), *args)
            return y, lin(*v), jax.linear_transpose(lin, *args)(u)

        _PROGRAMS[key] = both
    return _PROGRAMS[key]


def smooth(t_of, args, h, name, tries=2):
    """(N,) bool: the rays whose t is smooth within 4 ``h`` of ``args`` along ``tries`` random
    directions of every argument: central differences at steps h and 4 h agree to 1e-6 of the
    derivative (plus 1e-6, plus t's rounding over the step). A ray within the finite-difference step of a kink of t (a silhouette,
    a cutting plane, a voxel edge) fails it and is left out of the check, which then compares
    derivatives only where finite differences can; the derivatives themselves are not used here."""
    keep = None
    r = np.random.default_rng(zlib.crc32(name.encode()))
    for _ in range(tries):
        v = jax.tree_util.tree_map(lambda a: jnp.asarray(r.normal(size=np.shape(a)), jnp.result_type(a)), args)
        at = lambda k: t_of(jax.tree_util.tree_map(lambda a, b: a + k * b, args, v))  # noqa: E731
        with np.errstate(invalid="ignore"):  # (inf - inf on misses)
            d1 = (at(h) - at(-h)) / (2 * h)
            d4 = (at(4 * h) - at(-4 * h)) / (8 * h)
            rounding = 4 * np.finfo(np.float64).eps * np.abs(at(0.0)) / h  # t's last bits, over the step
            good = np.isfinite(d1) & np.isfinite(d4) & (np.abs(d1 - d4) <= 1e-6 * (1.0 + np.abs(d1)) + rounding)
        keep = good if keep is None else keep & good
    return keep


def leaf_scales(rep, at_s, at_1):
    """Each float leaf's unit: the median ratio |x_s / x_1| over its entries that the scale
    changes, between the object built at scale s (``at_s``) and at scale 1 (``at_1``), both
    unmoved: s for lengths and positions, 1 for leaves it leaves alone (unit vectors, ratios,
    angles, colours; padding rows hold fixed placeholders and are not counted); None for a leaf
    that is 0 at both scales (a plane offset at its own joint, a twist of 0), which has no unit
    to step in and is held fixed (the checks at scale 1 step it). A finite-difference step of
    1e-6 s moved a unit vector by 1e-6 s, 0.035 at s = 3.5e4: far outside the linear range
    there; and a relief's bottom-plane offsets (0) by 1e-6 at s = 1e-3, a thousandth of the
    object."""
    a, b = (jax.tree_util.tree_leaves(rep.build(rep.Config.model_validate(r), np.float64).params) for r in (at_s, at_1))
    out = []
    for x, y in zip(a, b):
        if jnp.issubdtype(x.dtype, jnp.floating):
            x, y = np.asarray(x, np.float64).ravel(), np.asarray(y, np.float64).ravel()
            moved = np.isfinite(x) & np.isfinite(y) & (y != 0) & (x != y)
            nonzero = np.any(np.isfinite(x) & (x != 0)) or np.any(np.isfinite(y) & (y != 0))
            out.append(float(np.median(np.abs(x[moved] / y[moved]))) if moved.any() else (1.0 if nonzero else None))
    return out


def scaled_check(name, raw, origins, directions, s, units, n=8, h=1e-6, moves=None):
    """``check_jvp`` and ``check_vjp`` of the first ``n`` hit rays' t / s (so that derivatives are
    of order 1 at every scale and the checks' tolerances mean the same) in every float leaf of
    the params and the ray origins, each argument in its own unit (``units``, from
    :func:`leaf_scales`; the origins in s), at finite-difference steps of ``h`` of that unit.
    With ``moves`` (:func:`implicit_moved`) the params are not free leaf by leaf but moved by it:
    its shift in units of s, its radii's factor and threshold in 1 (``units`` unused)."""
    rep = registry.get(raw["type"])
    b = rep.build(rep.Config.model_validate(raw), np.float64)
    d = np.asarray(directions, float)
    rays = make_rays(np.asarray(origins) - b.anchor, d / np.linalg.norm(d, axis=1, keepdims=True), dtype=np.float64)
    leaves, tree = jax.tree_util.tree_flatten(b.params)
    if moves is None:
        floats = [i for i, a in enumerate(leaves) if jnp.issubdtype(a.dtype, jnp.floating)]
        floats, units = zip(*[(i, u) for i, u in zip(floats, units) if u is not None])
        program = keyed_program(rep, b.static, tree, list(floats))
        theta = [leaves[i] for i in floats]
    else:
        program = keyed_program(rep, b.static, tree, moves)
        theta, units = list(implicit_free(b, None)[0]), (s, 1.0, 1.0)
    unit = ([jnp.asarray(u, jnp.float64) for u in units], jnp.asarray(s, jnp.float64))
    scale = lambda a: jax.tree_util.tree_map(lambda x, w: x * w, a, unit)  # noqa: E731
    # arguments in units: x = unit * a, so J_a v = J_x (unit v), J_a^T u = unit (J_x^T u)
    # and t in units of s: y = t / s, J = J_t / s, J^T u = J_t^T (u / s)
    both = lambda a, fixed, v, u: (lambda y, jv, jt: (y / s, jv / s, scale(jt)))(*program(scale(a), fixed, scale(v), u / s))  # noqa: E731
    args = ([x / w for x, w in zip(theta, unit[0])], rays.origins / s)
    fixed = (leaves, rays.directions, rays.t_min, rays.t_max)
    zero = jax.tree_util.tree_map(jnp.zeros_like, args)
    nothing = jnp.zeros_like(rays.t_min)
    t = np.asarray(both(args, fixed, zero, nothing)[0]) * s
    ok = np.isfinite(t)
    if rep.name == "cells":  # t is piecewise: the crossed voxel face. Keep hits 1e-3 voxel from its edges
        vox = b.info["tile_size"] / 16
        u = (np.asarray(rays.origins) + np.where(ok, t, 0)[:, None] * np.asarray(rays.directions) - np.asarray(b.params.lo)) / vox
        near = np.sort(np.abs(u - np.round(u)), axis=1)  # the crossed face's axis first (nearest an integer)
        ok &= near[:, 1] > 1e-3
    ok &= smooth(lambda a: np.asarray(both(a, fixed, zero, nothing)[0]), args, h, name)
    rows = np.nonzero(ok)[0][:n]
    assert rows.size == n, (name, rows.size)

    def f(*a):
        return both(a, fixed, zero, nothing)[0][rows]

    def f_jvp(a, v):
        y, jv, _ = both(a, fixed, v, nothing)
        return y[rows], jv[rows]

    def f_vjp(*a):
        return f(*a), lambda u: both(a, fixed, zero, nothing.at[rows].set(u))[2]

    check_jvp(f, f_jvp, args, eps=h, err_msg=name)
    check_vjp(f, f_vjp, args, eps=h, err_msg=name)
    checked[name] = checked.get(name, 0) + 1


#: the other modes checked at scale: (the object they take, its section's overrides)
SCALED_MODES = {"fuzz_frusta_bins": ("fuzz_frusta", {"accel": "bvh", "traversal": "bins"}),
                "fuzz_implicit_bisection": ("fuzz_implicit", {"method": "bisection"}),
                "fuzz_cells_voxels": ("fuzz_cells", {"search": "voxels"}),
                "fuzz_mesh_packets": ("fuzz_mesh", {"traversal": "packets"})}


def scaled_raw(kind, s, off):
    """The object ``kind`` (``fuzz_frusta``, ``fuzz_relief``, ``fuzz_implicit``, ``fuzz_cells``, ``fuzz_mesh``, or
    one of :data:`SCALED_MODES`) at scale ``s``, moved to ``off``."""
    if kind in SCALED_MODES:
        base, overrides = SCALED_MODES[kind]
        return {**scaled_raw(base, s, off), **overrides}
    if kind == "fuzz_frusta":
        return {"type": "frusta", "skeleton": {**TREE, "scale": s, "offset": off.tolist()}, "accel": "blocks"}
    if kind == "fuzz_relief":  # the relief check's cylinder and brick shell, the fixed march
        return {"type": "frusta", "skeleton": {**RELIEF_CYLINDER, "scale": s, "offset": off.tolist()},
                "relief": {**RELIEF, "thickness": 0.1 * s, "early_exit": False}}
    if kind == "fuzz_cells":
        return {"type": "cells", "base": {"type": "torus", "major": s, "minor": 0.45 * s, "center": off.tolist()}, "tiles": 6,
                "bisection": 40, "search": "linear", "cache": str(TMP / "cells"),
                "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}}
    if kind == "fuzz_implicit":  # a 2 x 2 block of the grid's balls, the Lipschitz march
        return {"type": "implicit", "threshold": 0.5, "method": "lipschitz", "step": 0.01 * s, "eps": 1e-3 * s, "bisection": 40,
                "balls": [{"center": (np.asarray(q["center"]) * s + off).tolist(), "radius": q["radius"] * s}
                          for q in BALLS if q["center"][0] < 1.0 and q["center"][1] < 1.0]}
    return {"type": "mesh", "path": str(sphere), "traversal": "walks", "scale": s, "offset": off.tolist()}


def scaled_checks(kind):
    """Hypothesis' drawn scales, shifts and rays for the object ``kind`` (derandomized: the same
    examples in CI)."""

    @settings(max_examples=3, deadline=None, derandomize=True, database=None, suppress_health_check=list(HealthCheck))
    @given(log_scale=st.floats(-10, 10), log_shift=st.floats(-2, 5), log_back=st.floats(0, 5), seed=st.integers(0, 2**31 - 1))
    @example(log_scale=-10.0, log_shift=5.0, log_back=5.0, seed=1)  # both ends of 20 decades, 1e5 sizes away, rays from 1e5 sizes
    @example(log_scale=10.0, log_shift=5.0, log_back=5.0, seed=2)
    def one(log_scale, log_shift, log_back, seed):
        drawn.setdefault(kind, []).append(round(log_scale, 2))
        base = SCALED_MODES.get(kind, (kind,))[0]  # the object, and so the rays
        s = 10.0**log_scale
        off = s * 10.0**log_shift * np.array([0.6, -0.8, 0.3])
        r = np.random.default_rng(seed)
        if base == "fuzz_cells":  # from outside and above, aimed at the tube
            ang = r.uniform(0, 2 * np.pi, 16)
            ring = np.stack([np.cos(ang), np.zeros(16), np.sin(ang)], 1)
            o, d = 3.0 * ring + [0.1, 2.0, 0.3], -2.0 * ring - [0.1, 2.0, 0.3]
        elif base == "fuzz_frusta":
            o, d = down(48, (-0.3, 0.0), (0.3, 2.9), 4.0, r)
        elif base == "fuzz_relief":
            o, d = down(96, (-0.2, 0.3), (0.2, 1.2), 3.0, r, (0.03, -0.05))
        elif base == "fuzz_implicit":
            o, d = down(96, (-0.2, -0.2), (1.1, 1.1), 3.0, r)
        else:
            o, d = down(16, (-0.7, -0.7), (0.7, 0.7), 3.0, r)
        back = 10.0**log_back - 1.0  # the rays start this many sizes further back along their direction
        o = o - back * d / np.linalg.norm(d, axis=1, keepdims=True)
        # t's rounding grows with the distance: the step that balances it against the curvature
        h = 1e-6 * max(1.0, (1.0 + back / 4.0) ** (1.0 / 3.0))
        if base == "fuzz_implicit":  # each primitive moved whole (``implicit_moved``), one program for every example
            scaled_check(kind, scaled_raw(kind, s, off), off + s * o, d, s, None, h=h, moves=implicit_moved)
            return
        units = leaf_scales(registry.get(scaled_raw(kind, 1.0, 0 * off)["type"]), scaled_raw(kind, s, 0 * off), scaled_raw(kind, 1.0, 0 * off))
        scaled_check(kind, scaled_raw(kind, s, off), off + s * o, d, s, units, h=h)

    one()


drawn: dict = {}  # each kind's log10 scales, in the order checked (printed to stderr)
for kind in ("fuzz_frusta", "fuzz_relief", "fuzz_implicit", "fuzz_cells", "fuzz_mesh", *SCALED_MODES):
    if wanted(kind):
        scaled_checks(kind)
if drawn:
    print(json.dumps({"drawn_log_scales": drawn}), file=sys.stderr)


# fitting (issue 10): the signed point-to-frusta distance against joints, radii and the point,
# at random points and at hard ones where the distance is smooth in the argument checked
from jskel.fit import distances, segments_of  # noqa: E402


def fit_checks():
    """Random points, and hard ones: on the axis of a cylinder (smooth in the radii only), near a
    closed tip's apex, either side of a shared cutting plane."""
    FJ = np.array([[0, 0, 0], [0, 1, 0], [0.4, 2, 0.1], [0.6, 3, 0.5], [0.5, 4, 1.0]], float)
    FR = np.array([0.5, 0.5, 0.4, 0.3, 0.0])  # r1 == r2 on the first segment, a closed tip at the end
    FP = [-1, 0, 1, 2, 3]
    fseg = segments_of(FJ, FR, FP)

    def dist(j, r, x):
        return distances(j, r, fseg, x[None, :])[0]

    check_dist, dist_both = checker(dist)  # one program for every point
    n = 0
    for x in np.random.default_rng(0).uniform([-0.8, -0.3, -0.8], [1.2, 4.3, 1.6], (6, 3)):
        check_dist((jnp.asarray(FJ), jnp.asarray(FR), jnp.asarray(x)))
        n += 1
    checked["fit_distance_random"] = n
    # hard points: on the axis of the cylinder (smooth in the radii only: |radial| has a kink), near
    # the apex of the closed tip, just inside the shared cutting plane and beyond it (smooth in all)
    n = 0
    on_axis = jnp.array([0.0, 0.5, 0.0])
    args = (jnp.asarray(FJ), jnp.asarray(FR), on_axis)
    check_dist(args, only=1)  # in the radii alone
    g = dist_both(args, jax.tree_util.tree_map(jnp.zeros_like, args), jnp.ones((), args[1].dtype))[2]  # the gradient in all three
    assert all(np.all(np.isfinite(v)) for v in g)
    n += 1
    tip = FJ[4] + np.array([0.05, -0.2, 0.03])
    check_dist((jnp.asarray(FJ), jnp.asarray(FR), jnp.asarray(tip)))
    n += 1
    for side in (-1e-3, 1e-3):  # either side of the plane shared at joint 1, near the surface
        x = FJ[1] + np.array([0.47, side, 0.0])
        check_dist((jnp.asarray(FJ), jnp.asarray(FR), jnp.asarray(x)))
        n += 1
    checked["fit_distance_hard"] = n


if wanted("fit"):
    fit_checks()

_lap()
print(json.dumps({"checked": checked, "seconds": seconds}))
