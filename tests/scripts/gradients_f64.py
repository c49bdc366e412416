"""Run in its own process (float64 is switched on here, never in the pytest workers): check the
derivatives of hit distances against finite differences with ``jax.test_util.check_grads``
(forward and reverse mode) and print one JSON line of what was checked.

* implicit surfaces, all three tracers (march + bisection): t against the primitives' centres,
  their radii, the threshold and the ray origin (the implicit-function theorem of
  ``numerics.differentiable_root``; a bisection loop alone would give exactly zero);
* relief frusta (march + bisection in the shell): t against the shell thickness, the radii and
  the ray origin, for rays whose hit is on the relief surface itself;
* plain frusta (closed form): t against the radii, the base joint and the ray origin;
* frusta through a BVH traversal (``accel.nearest_tangent``: the walk gives the value, the
  winning segment's closed form the derivative): t against the joints and radii of a branching
  tree, through the device rebuild that makes both the segments and the BVH from them (the
  packed BVH rows are a cache of the segments, so a derivative is one of the skeleton). The
  CPU's default traversal (``bins``) by default; ``--traversals bins,packets,walks`` checks more.
"""

import argparse

import json

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from jax.test_util import check_grads  # noqa: E402

from jskel import frusta, implicit  # noqa: E402
from jskel.frusta._intersect import _segment_t, nearest_one  # noqa: E402
from jskel.frusta._relief import RELIEF, make_relief_t  # noqa: E402
from jskel.implicit._trace import cull, trace_one  # noqa: E402

checked = {}


def each_arg(f, args, eps=1e-6):
    """check_grads of f in all its arguments at once (random joint directions), both modes."""
    check_grads(jax.jit(f), args, order=1, modes=["fwd", "rev"], eps=eps)


# implicit: two balls and a tapering tube
for method in ("lipschitz", "bisection", "naive"):
    cfg = implicit.ImplicitConfig.model_validate({
        "type": "implicit", "threshold": 0.5,
        "balls": [{"center": [0, 0, 0], "radius": 1.0}, {"center": [0.8, 0.3, 0], "radius": 0.8}],
        "tubes": [{"a": [-1, -0.5, 0.2], "b": [0.5, 1.0, 0.1], "radius_a": 0.5, "radius_b": 0.3}],
        "method": method, "eps": 1e-3, "step": 0.01, "bisection": 40, "capacity": 8, "block_size": 0})
    b = implicit.build(cfg, np.float64)
    sc, q = b.params, b.static.quality
    d = jnp.array([0.05, -0.02, -1.0])

    def t_of(shift, rscale, T, o):
        p = sc.prims
        prims = p._replace(a=p.a + shift, b=p.b + shift, ra=p.ra * rscale, rb=p.rb * rscale)
        cand = cull(prims, o, d, 0.0, jnp.inf, q.capacity, q.block, q.block_capacity)
        return trace_one(cand, sc.tune._replace(threshold=T), o, d, 0.0, jnp.inf, q)[0]

    n = 0
    for xy in ([0.1, 0.2], [-0.3, -0.2]):
        o = jnp.array([xy[0], xy[1], 5.0]) - b.anchor
        args = (jnp.zeros_like(sc.prims.a), jnp.ones_like(sc.prims.ra), sc.tune.threshold, o)
        t = t_of(*args)
        assert np.isfinite(t), (method, xy)
        grads = jax.grad(t_of, argnums=(0, 1, 2, 3))(*args)
        assert all(np.all(np.isfinite(g)) for g in grads)
        assert abs(float(grads[2])) > 1e-3  # the threshold moves the surface: not the zero of a bare loop
        each_arg(t_of, args)
        n += 1
    checked[f"implicit_{method}"] = n

# relief: one cylinder with a brick height field in a shell
cfg = frusta.FrustaConfig.model_validate({
    "type": "frusta", "skeleton": {"joints": [[0, 0, 0], [0, 1.5, 0]], "radii": [0.5, 0.45], "parents": [-1, 0]},
    "relief": {"map": "brick", "thickness": 0.1, "scale": [2.0, 1.0], "steps": 256, "bisection": 40, "uv": "exact"}})
b = frusta.build(cfg, np.float64)
scene, static = b.params, b.static
seg0 = jax.tree_util.tree_map(lambda a: a[0], scene.relief.frusta)
relief_t = make_relief_t(scene.maps, static.relief)


def rt(shell, rscale, o, d):
    seg = seg0._replace(shell=shell, r1=seg0.r1 * rscale, r2=seg0.r2 * rscale)
    return relief_t(seg, o, d, 0.0, jnp.inf)


def rt0(sh, rs, oo):
    return rt(sh, rs, oo, D_RELIEF)[0]


D_RELIEF = jnp.array([0.03, -0.05, -1.0])
rng = np.random.default_rng(3)
n = 0
for _ in range(200):
    if n == 3:
        break
    o = jnp.array([rng.uniform(-0.2, 0.2), rng.uniform(0.3, 1.2), 3.0]) - b.anchor
    t, _, code = rt(seg0.shell, 1.0, o, D_RELIEF)
    if not (np.isfinite(t) and int(code) == RELIEF):
        continue
    each_arg(rt0, (seg0.shell, jnp.asarray(1.0), o))
    n += 1
assert n == 3, n
checked["relief"] = n

# plain frusta: a bent chain, closed form
cfg = frusta.FrustaConfig.model_validate({
    "type": "frusta", "skeleton": {"joints": [[0, 0, 0], [0, 1, 0], [0.4, 1.8, 0.1]], "radii": [0.3, 0.25, 0.12],
                                   "parents": [-1, 0, 1]}})
b = frusta.build(cfg, np.float64)
f = b.params.plain.frusta


def ft(r1s, c1, o, d):
    g = f._replace(r1=f.r1 * r1s, c1=c1)
    return nearest_one(g, _segment_t, o, d, 0.0, jnp.inf, f.h.shape[0])[0]


D_FRUSTA = jnp.array([0.02, 0.01, -1.0])


def ft0(a, c, oo):
    return ft(a, c, oo, D_FRUSTA)


n = 0
for xy in ([0.05, 0.4], [0.3, 1.5]):
    o = jnp.array([xy[0], xy[1], 3.0]) - b.anchor
    assert np.isfinite(ft(1.0, f.c1, o, D_FRUSTA))
    each_arg(ft0, (jnp.asarray(1.0), f.c1, o))
    n += 1
checked["frusta"] = n

# frusta through a traversal of the BVH, differentiated in the skeleton through the device rebuild
from jskel.frusta import Group, host_frusta  # noqa: E402
from jskel.frusta._device import _core_jit  # noqa: E402
from jskel.frusta._geometry import padded_topology  # noqa: E402
from jskel.interface import Object, intersect  # noqa: E402
from jskel.rays import Rays  # noqa: E402

ap = argparse.ArgumentParser()
ap.add_argument("--traversals", default="bins")
TJ = np.array([[0, 0, 0], [0, 1, 0], [0.3, 2, 0.1], [-0.4, 1.8, 0.2], [0.5, 3, 0.3], [0.1, 2.9, -0.3]])
TR = np.array([0.3, 0.25, 0.2, 0.15, 0.1, 0.08])
TP = [-1, 0, 1, 1, 2, 2]
for trav in ap.parse_args().traversals.split(","):
    tcfg = frusta.FrustaConfig.model_validate({"type": "frusta", "skeleton": {"joints": TJ.tolist(), "radii": TR.tolist(), "parents": TP},
                                               "accel": "bvh", "traversal": trav})
    tpl = frusta.build(tcfg, np.float64)
    assert tpl.static.traversal == trav, tpl.static.traversal
    _, topo, _, _, _, _ = host_frusta(tcfg)
    grp = tpl.params.plain
    dtopo = padded_topology(topo, grp.frusta.h.shape[0])
    rng = np.random.default_rng(0)
    TO = np.stack([rng.uniform(-0.5, 0.6, 64), rng.uniform(0.0, 3.2, 64), np.full(64, 4.0)], 1) - tpl.anchor
    TD = np.tile([0.01, 0.02, -1.0], (64, 1))

    def t_tree(joints, radii):
        seg, bvh = _core_jit(joints, radii, 0.0, dtopo, grp.frusta, tpl.static.leaf, int(topo.depth.max()) + 1)
        scene = tpl.params._replace(plain=Group(seg, grp.block_c, grp.block_r, bvh))
        rays = Rays(jnp.asarray(TO), jnp.asarray(TD), jnp.zeros(64), jnp.full(64, jnp.inf))
        return intersect(Object(scene, tpl.static, "frusta"), rays).t

    args = (jnp.asarray(TJ - tpl.anchor), jnp.asarray(TR))
    hit = np.nonzero(np.isfinite(np.asarray(t_tree(*args))))[0]
    assert hit.size >= 6, hit.size
    check_grads(jax.jit(lambda j, r: t_tree(j, r)[hit[:6]]), args, order=1, modes=["fwd", "rev"], eps=1e-6)
    checked[f"frusta_{trav}"] = 6

# fitting (issue 10): the signed point-to-frusta distance against joints, radii and the point,
# at random points and at hard ones where the distance is smooth in the argument checked
from jskel.fit import distances, segments_of  # noqa: E402

FJ = np.array([[0, 0, 0], [0, 1, 0], [0.4, 2, 0.1], [0.6, 3, 0.5], [0.5, 4, 1.0]], float)
FR = np.array([0.5, 0.5, 0.4, 0.3, 0.0])  # r1 == r2 on the first segment, a closed tip at the end
FP = [-1, 0, 1, 2, 3]
fseg = segments_of(FJ, FR, FP)


def dist(j, r, x):
    return distances(j, r, fseg, x[None, :])[0]


rng = np.random.default_rng(0)
n = 0
for x in rng.uniform([-0.8, -0.3, -0.8], [1.2, 4.3, 1.6], (6, 3)):
    each_arg(dist, (jnp.asarray(FJ), jnp.asarray(FR), jnp.asarray(x)))
    n += 1
checked["fit_distance_random"] = n
# hard points: on the axis of the cylinder (smooth in the radii only: |radial| has a kink), near
# the apex of the closed tip, just inside the shared cutting plane and beyond it (smooth in all)
n = 0
on_axis = jnp.array([0.0, 0.5, 0.0])
check_grads(jax.jit(lambda r: dist(jnp.asarray(FJ), r, on_axis)), (jnp.asarray(FR),), order=1, modes=["fwd", "rev"], eps=1e-6)
g = jax.grad(dist, argnums=(0, 1, 2))(jnp.asarray(FJ), jnp.asarray(FR), on_axis)
assert all(np.all(np.isfinite(v)) for v in g)
n += 1
tip = FJ[4] + np.array([0.05, -0.2, 0.03])
each_arg(dist, (jnp.asarray(FJ), jnp.asarray(FR), jnp.asarray(tip)))
n += 1
for side in (-1e-3, 1e-3):  # either side of the plane shared at joint 1, near the surface
    x = FJ[1] + np.array([0.47, side, 0.0])
    each_arg(dist, (jnp.asarray(FJ), jnp.asarray(FR), jnp.asarray(x)))
    n += 1
checked["fit_distance_hard"] = n

# cells (binary search in the tile map): t against the ray origin and the object's placement
import tempfile  # noqa: E402

from jskel import cells  # noqa: E402

ccfg = cells.CellsConfig.model_validate({
    "type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45}, "tiles": 6, "bisection": 40,
    "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "cache": tempfile.mkdtemp()})
cb = cells.build(ccfg, np.float64)


def t_cells(o, lo, size, d):
    p = cb.params._replace(lo=lo, size=size)
    return cells.intersect_one(p, cb.static, o, d, 0.0, jnp.inf).t


n = 0
for o_w, aim in (([2.5, 1.5, 2.0], [1.0, 0.05, 0.02]), ([-2.5, 0.4, 0.3], [-1.0, 0.02, -0.03])):
    d_w = np.subtract(aim, o_w)  # aimed at the torus' tube
    d = jnp.asarray(d_w) / np.linalg.norm(d_w)
    o = jnp.asarray(o_w) - cb.anchor
    assert np.isfinite(t_cells(o, cb.params.lo, cb.params.size, d)), o_w
    each_arg(lambda oo, lo, sz: t_cells(oo, lo, sz, d), (o, cb.params.lo, cb.params.size))
    n += 1
checked["cells"] = n
print(json.dumps({"checked": checked}))
