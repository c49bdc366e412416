"""Run by hand (not by the suite): the stalled fit of docs/fitting.md. navis' mesh, subsample 3,
fitted as ``experiments/bench_fit_real.yaml`` does for two rounds with edits; at the third
round's start, the loss's point part along the descent direction (steps of 1e-7 to 1e-3), which
continuation's plane kind changes under a step of 1e-7, and, in float64, Eq. 3-5's ellipse
margins there under steps of 1e-10 to 1e-6.

    JSKEL_CACHE=off python tests/scripts/plane_stall.py
"""

import jax
import jax.numpy as jnp
import numpy as np
import trimesh
import yaml

from jskel.fit._contract import contraction_skeleton
from jskel.fit._distance import distances_of, geometry, segments_of
from jskel.fit._fit import data_of, fit_points, on_device
from jskel.fit._problem import blocks_of, normal_equations, normaliser_of, ordered, point_residuals, problem_of, radii_of, round_sizes, sizes_of, unpack
from jskel.fit._topology import edited
from jskel.frusta import joint_planes, segment_axes
from jskel.frusta._geometry import _meet, _unit, cone_sin, medial_normal
from jskel.numerics import dot3
from jskel.peers.skeletonizer import RealFitBenchFile, mesh_path

cfg = RealFitBenchFile.model_validate(yaml.safe_load(open("experiments/bench_fit_real.yaml"))).fit_real
mesh = trimesh.load(mesh_path("navis:754534424"), process=False)
pts = np.asarray(trimesh.sample.sample_surface(mesh, cfg.points, seed=3)[0], np.float64)
st = cfg.start
j, r, p, _ = contraction_skeleton(pts, st.neighbours, st.ball, st.segment, st.prune, st.max_points)
ext = float(np.max(np.ptp(pts, axis=0)))
sizes = None
for k in (1, 2):
    sizes = round_sizes(sizes_of(segments_of(j, r, p), len(j)), sizes)
    res = fit_points(pts, j, r, p, cfg.solver, np.float32, sizes=sizes)
    print("round", k, "joints", len(j), "iterations", res.iterations, "loss", res.history[0], "->", res.history[-1], "error", res.error)
    j, r, p, _ = edited(pts, res.joints, res.radii, res.parents, cfg.edits, cfg.solver.scale * ext, ext, k)
seg = segments_of(j, r, p)
pr = problem_of(seg, cfg.solver, len(j))
nz = normaliser_of(pts)
data = on_device(data_of(nz.points(ordered(pts, pr)), pr, np.float32, seg))
x = jnp.asarray(nz.start(j, r, pr), jnp.float32)
g = np.asarray(jax.jit(lambda x, d: normal_equations(x, d, pr))(x, data)[2], np.float64)
h = -g / np.linalg.norm(g)
print("round 3 start: |J^T r|", np.linalg.norm(g))


@jax.jit
def point_part(x, data):
    joints, u = unpack(x)
    gm = geometry(joints, radii_of(u, pr), data.layout.seg)
    d = distances_of(gm, data.layout.seg, data.points, pr.candidates, *blocks_of(pr, data.points.shape[0]))[0]
    return point_residuals(d, pr)


base = np.asarray(point_part(x, data), np.float64)
for t in (1e-7, 1e-6, 1e-5, 1e-4, 1e-3):
    q = np.asarray(point_part(x + jnp.asarray(t * h, jnp.float32), data), np.float64)
    print(f"step {t:g}: point loss change {0.5 * (q @ q - base @ base):.3g}, residuals changed by > 1e-4: {int(np.sum(np.abs(q - base) > 1e-4))}, most {np.abs(q - base).max():.3g}")


def axes(x):
    joints, u = unpack(x)
    return segment_axes(joints, radii_of(u, pr), seg.start, seg.end)


kinds = jax.jit(lambda x: joint_planes(*axes(x), seg.cont_a, seg.cont_b)[6])
k0, k1 = np.asarray(kinds(x)), np.asarray(kinds(x + jnp.asarray(1e-7 * h, jnp.float32)))
changed = np.nonzero(k0 != k1)[0]
print("plane kinds changed under a step of 1e-7:", [(int(c), int(k0[c]), int(k1[c])) for c in changed])


def margins(x, c):
    """Eq. 3-5's plane at continuation c: its ellipse margins (n . m - sin) for both segments."""
    c1, m, hh, r1, r2 = axes(x)
    a, b = seg.cont_a[c : c + 1], seg.cont_b[c : c + 1]
    jn, ma, ca, mb = c1[b], m[a], c1[a], m[b]
    nm, _ = medial_normal(ma, mb)
    e1, e2 = ma, jnp.cross(nm, ma)
    db = jnp.stack([dot3(mb, e1), dot3(mb, e2)], -1)
    ca2 = jnp.stack([dot3(ca - jn, e1), dot3(ca - jn, e2)], -1)
    sa = jnp.stack([jnp.zeros_like(hh[b]), -jnp.ones_like(hh[b])], -1)
    sb = jnp.stack([db[:, 1], -db[:, 0]], -1)
    a2, _ = _meet(ca2, db * hh[b][:, None], sa, sb, r1[a], r2[a], r1[b], r2[b], 1.0)
    b2, _ = _meet(ca2, db * hh[b][:, None], sa, sb, r1[a], r2[a], r1[b], r2[b], -1.0)
    ab = a2 - b2
    n = _unit(jnp.cross(ab[:, :1] * e1 + ab[:, 1:] * e2, nm))
    n = n * jnp.where(dot3(n, ma + mb) < 0, -1.0, 1.0)[:, None]
    return dot3(n, ma) - cone_sin(r1[a], r2[a], hh[a]), dot3(n, mb) - cone_sin(r1[b], r2[b], hh[b])


jax.config.update("jax_enable_x64", True)
x64, h64 = jnp.asarray(np.asarray(x, np.float64)), jnp.asarray(h)
for c in changed:
    for t in (0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6):
        ma, mb = margins(x64 + t * h64, int(c))
        print(f"float64, continuation {int(c)}, step {t:g}: margins {float(ma[0]):.4f} {float(mb[0]):.4f}")
