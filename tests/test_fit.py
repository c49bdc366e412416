"""Fitting frusta to point clouds (issue 10): the distance against closed forms and the
renderer's own hits, finite gradients at hard points, recovery of a known chain, estimates,
the command and its bad input. (The float64 finite-difference check of the distance's
gradients runs in ``tests/scripts/gradients_f64.py``, see ``test_gradients.py``.)"""

from __future__ import annotations

import functools
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

import fit_truths
from fit_truths import noisy_cylinder

from jskel.cli import main
from jskel.fit import culling_exact, distances, fit_many, fit_points, load_points, mst_skeleton, pca_chain, perturbed, segments_of
from jskel.fit._config import FitFile, PointsConfig, SolverConfig
from jskel.skeletons import read_swc

from conftest import build_skeleton, cast


# one compiled distance per topology (``Segments`` hash as static) and candidate count: points
# are padded to PAD rows (copies of the last), so the tests' clouds of 2 to 4000 points share it
# instead of running the distance op by op per cloud
_distances = jax.jit(distances, static_argnums=(2, 4))
_culling_exact = jax.jit(culling_exact, static_argnums=(2, 4))
_blocked = jax.jit(distances, static_argnums=(2, 4), static_argnames=("block", "per_block"))
_culling_exact_blocked = jax.jit(culling_exact, static_argnums=(2, 4), static_argnames=("block", "per_block"))
PAD = 4096


def dist(joints, radii, seg, pts, candidates=0, fn=_distances):
    """``fn(joints, radii, seg, points, candidates)`` in float32 on ``pts`` padded to PAD rows."""
    pts = np.asarray(pts, np.float32)
    assert len(pts) <= PAD
    padded = np.pad(pts, ((0, PAD - len(pts)), (0, 0)), mode="edge")
    out = fn(jnp.asarray(joints, jnp.float32), jnp.asarray(radii, jnp.float32), seg, jnp.asarray(padded), candidates)
    return np.asarray(out)[: len(pts)]


def d32(joints, radii, parents, pts):
    return dist(joints, radii, segments_of(joints, radii, parents), pts)


def test_measures_of_a_padded_topology_are_those_of_the_capped_cylinder():
    """``fit.point_distances`` and ``_measures.measures`` take the topology as data padded to a
    bucket (19 segments in a program for 20: one padding segment far away): on a straight chain
    of 19 unit segments of radius 0.5 (a capped cylinder, its shared planes perpendicular) the
    signed distances of points around it are the closed form's, written here in float64
    (``max(rho - R, -y, y - L)`` inside, the length of the positive parts outside), every point
    is served exactly by its 4 candidates, and the smallest plane margin is 1 (``n . m`` = 1,
    no taper) from the real continuations alone."""
    from jskel.fit import point_distances
    from jskel.fit._measures import measures

    n, radius = 19, 0.5
    joints = np.stack([np.zeros(n + 1), np.arange(n + 1.0), np.zeros(n + 1)], 1)
    radii, parents = np.full(n + 1, radius), np.arange(-1, n)
    rng = np.random.default_rng(3)
    pts = np.stack([rng.uniform(-1.5, 1.5, 400), rng.uniform(-1.5, n + 1.5, 400), rng.uniform(-1.5, 1.5, 400)], 1)
    a = np.hypot(pts[:, 0], pts[:, 2]) - radius
    b = np.maximum(-pts[:, 1], pts[:, 1] - n)
    want = np.where((a <= 0) & (b <= 0), np.maximum(a, b), np.hypot(np.maximum(a, 0), np.maximum(b, 0)))
    np.testing.assert_allclose(point_distances(pts, joints, radii, parents), want, atol=2e-5 * n)
    d, exact, margin = measures(pts, joints, radii, parents, candidates=4)
    np.testing.assert_allclose(d, want, atol=2e-5 * n)
    assert exact == 1.0 and margin == pytest.approx(1.0, abs=1e-6)


def test_distance_closed_forms_on_a_cylinder_and_a_cone():
    J, R, P = [[0, 0, 0], [0, 2, 0]], [0.5, 0.5], [-1, 0]
    e = 0.1
    pts = [[0.5 + e, 1, 0], [0.5 - e, 1, 0], [0, 1, 0], [0.2, 2 + e, 0], [0.2, -e, 0.1], [0.5 + e, 2 + e, 0], [0, 3, 0]]
    want = [e, -e, -0.5, e, e, np.sqrt(2) * e, 1.0]
    np.testing.assert_allclose(d32(J, R, P, pts), want, atol=2e-6)
    # a cone r = 0.5 -> 0.25 over h = 2: distance to the generator line, (rho - r(y)) / sqrt(1 + k^2)
    k = -0.125
    rng = np.random.default_rng(0)
    y = rng.uniform(0.3, 1.7, 50)
    rho = rng.uniform(0.0, 0.8, 50)
    phi = rng.uniform(0, 2 * np.pi, 50)
    x = np.stack([rho * np.cos(phi), y, rho * np.sin(phi)], 1)
    want = (rho - (0.5 + k * y)) / np.sqrt(1 + k * k)
    # only points whose nearest surface point is on the side (not nearer a cap than the side)
    side = np.minimum(y, 2 - y) > np.abs(want) + 0.05
    np.testing.assert_allclose(d32(J, [0.5, 0.25], P, x)[side], want[side], atol=3e-6)


BENT = np.array([[0, 0, 0], [0, 1, 0], [-0.5736, 1.8192, 0], [-0.7818, 2.7975, -0.0030], [-0.7838, 3.7469, -0.3171],
                 [-0.6022, 4.6581, -0.6968]])
BENT_R = np.array([0.5, 0.46, 0.42, 0.38, 0.34, 0.3])
CHAIN = np.array([-1, 0, 1, 2, 3, 4])


@pytest.mark.parametrize("radii", [BENT_R, np.array([0.2, 0.6, 0.15, 0.55, 0.1, 0.4])], ids=["tapering", "zigzag"])
def test_distance_of_points_outside_matches_a_dense_sample_of_the_surface(radii):
    """Outside the chain, near and far, the distance equals the distance to 200,000 points
    sampled on the surface (host float64 build; the samples' spacing, under 0.01, bounds how
    far that reference can read long). The steep zigzag radii are where the distance to the
    infinite cone read a point up to 3.4 too near and the sampler left the outer side of each
    bend bare; both fixed (a fit on a 50-segment chain had bent segments to exploit it)."""
    from scipy.spatial import cKDTree

    from jskel.fit import sample_surface
    from jskel.frusta import frusta_from_skeleton

    rng = np.random.default_rng(0)
    tree = cKDTree(sample_surface(BENT, radii, CHAIN, 200_000, rng))
    d = rng.normal(size=(2000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x = BENT.mean(0) + d * rng.uniform(0.5, 15.0, (2000, 1))
    ref, _ = tree.query(x)
    got = d32(BENT, radii, CHAIN, x)
    a, _, _ = frusta_from_skeleton(BENT, radii, CHAIN)  # inside any piece: host float64, written here
    q = x[:, None, :] - a.c1[None]
    y = np.sum(q * a.m, -1)
    rho = np.linalg.norm(q - y[..., None] * a.m, axis=-1)
    inside = ((rho <= a.r1 + (a.r2 - a.r1) / a.h * y) & (np.sum(q * a.nb, -1) >= a.db) & (np.sum(q * a.nt, -1) <= a.dt)).any(1)
    out = (ref > 0.05) & ~inside
    assert out.sum() > 1500
    # reference reads long by at most the sample spacing; the distance in the point's own axial
    # half-plane reads long by under 1 % near tilted rims
    assert np.all(got[out] > 0)
    assert np.min(got[out] - ref[out]) > -0.01
    assert np.max((got[out] - ref[out]) / ref[out]) < 0.01


def test_distance_is_zero_where_the_renderer_hits_and_inside_near_joints():
    """The renderer's hits (its own host-built frusta and analytic intersection) lie on the
    surface the distance describes; a point on the axis at a joint is as deep as the radius."""
    b = build_skeleton(BENT, BENT_R, CHAIN)
    rng = np.random.default_rng(2)
    c = BENT.mean(0)
    d = rng.normal(size=(4000, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = c - 8 * d + rng.uniform(-1.5, 1.5, (4000, 3))
    hit = cast(b, o, d)
    ok = np.isfinite(hit.t)
    assert ok.sum() > 1000
    dist = d32(BENT, BENT_R, CHAIN, hit.position[ok])
    assert np.max(np.abs(dist)) < 3e-5 * np.ptp(BENT, axis=0).max()
    # on the axis at an interior joint: about minus the radius there (the shared plane is no surface)
    deep = d32(BENT, BENT_R, CHAIN, BENT[1:5])
    assert np.all(deep < -0.8 * BENT_R[1:5])


def test_distance_gradients_are_finite_at_hard_points():
    J = np.array([[0, 0, 0], [0, 1, 0], [0.4, 2, 0.1], [0.6, 3, 0.5]], float)
    R = np.array([0.5, 0.5, 0.3, 0.0])  # r1 == r2, then a closed tip (apex)
    P = [-1, 0, 1, 2]
    seg = segments_of(J, R, P)
    hard = np.array([[0, 0.5, 0], [0, 0, 0], J[1], J[3], J[3] + [0, 0.1, 0], [0.5, 1.0, 0.0], [0.5, 0.0, 0.0], [0, -1, 0]])

    def total(j, r, x):
        return jnp.sum(distances(j, r, seg, x))

    # compiled, as a fit runs it (XLA's fused program, not the ops one by one): a NaN in the
    # derivative raises FloatingPointError under debug_nans, and a NaN on the way that a
    # ``where`` masks in the value still reaches the gradient (0 * NaN), so it raises too.
    # (op by op the same check compiled every primitive apart: 24.1 s in the slowest-tests list
    # of ``pytest --durations`` at 75de3eb, 16.3 s compiled in ``.ci/run``'s at 3b6853c,
    # 2026-12-03, the 2-core AMD EPYC; different runs of a machine whose speed varied)
    with jax.debug_nans(True):
        g = jax.jit(jax.grad(total, argnums=(0, 1, 2)))(jnp.asarray(J, jnp.float32), jnp.asarray(R, jnp.float32), jnp.asarray(hard, jnp.float32))
    for a in g:
        assert np.all(np.isfinite(np.asarray(a)))


@pytest.fixture(scope="module")
def noisy_branch():
    pc = PointsConfig.model_validate({"synthetic": {"skeleton": {"joints": BENT.tolist(), "radii": BENT_R.tolist(),
                                                                 "parents": CHAIN.tolist()},
                                                    "count": 3000, "noise": 0.01, "outliers": 0.05, "seed": 7}})
    pts, info, _ = load_points(pc)
    assert info["outliers"] == 150 and abs(info["noise_sd"] / info["skeleton_length"] - 0.01) < 1e-12
    return pts, info["skeleton_length"]


@pytest.mark.parametrize("solver", ["lm", "lbfgs"])
def test_recovers_a_known_chain_from_noisy_points_with_outliers(noisy_branch, solver):
    """5 segments, Gaussian noise of 1 % of the chain's length, 5 % outliers, a start moved by
    10 % (joints by 10 % of a segment, radii by 10 %): joints within 2 % of the length, radii
    within 5 %. LM on the dense normal equations; jaxopt's LM (``solver.jacobian: jaxopt``, an
    implementation of its own of the same algorithm) takes the same steps to the same skeleton
    (the sparse normal equations equal the dense ones in ``test_fit_normal``, and fit in
    ``test_batched_fits_match_the_truth_for_every_cloud``). L-BFGS
    runs 2 starts in one call (the given one and a perturbed copy, in turn under lax.map) and
    keeps the best: from single starts it once stopped in a local minimum (an earlier loss); with
    4 starts all four reached the same loss to 1e-4, at twice the test's run time."""
    pts, length = noisy_branch
    j0, r0 = perturbed(BENT, BENT_R, CHAIN, 0.1, np.random.default_rng(3))
    s = SolverConfig(name=solver, loss="cauchy", scale=0.01, maxiter=300, restarts=1 if solver == "lm" else 2, jacobian="dense")
    res = fit_points(pts, j0, r0, CHAIN, s)
    assert np.max(np.linalg.norm(j0 - BENT, axis=1)) > 0.05 * length / 5  # the start is really off
    assert np.max(np.linalg.norm(res.joints - BENT, axis=1)) < 0.02 * length
    assert np.max(np.abs(res.radii / BENT_R - 1)) < 0.05
    assert res.history[-1] < res.history[0] and res.converged
    if solver == "lbfgs":
        assert len(res.restart_losses) == 2 and min(res.restart_losses) == pytest.approx(res.history[-1], rel=1e-5)
    else:
        for jac in ("jaxopt",):
            sp = fit_points(pts, j0, r0, CHAIN, s.model_copy(update={"jacobian": jac}))
            np.testing.assert_allclose(sp.history[:6], res.history[:6], rtol=1e-4)  # the same first steps
            assert abs(sp.iterations - res.iterations) <= 2 and abs(sp.history[-1] / res.history[-1] - 1) < 1e-4
            np.testing.assert_allclose(sp.joints, res.joints, atol=1e-3 * length)
            np.testing.assert_allclose(sp.radii, res.radii, rtol=1e-3)


def test_batched_fits_match_the_truth_for_every_cloud():
    """vmap over 3 clouds (noise-free, each a translated and scaled copy) fits each one, LM on
    the sparse normal equations (``solver.jacobian: sparse``)."""
    rng = np.random.default_rng(5)
    from jskel.fit import sample_surface

    base = sample_surface(BENT, BENT_R, CHAIN, 600, rng)
    shifts, scales = np.array([[0, 0, 0], [10, -3, 2], [-4, 8, 1]]), np.array([1.0, 2.0, 0.5])
    clouds = np.stack([base * s + t for s, t in zip(scales, shifts)])
    j0, r0 = perturbed(BENT, BENT_R, CHAIN, 0.05, np.random.default_rng(1))
    starts_j = np.stack([j0 * s + t for s, t in zip(scales, shifts)])
    starts_r = np.stack([r0 * s for s in scales])
    J, R, losses, secs, _ = fit_many(clouds, starts_j, starts_r, CHAIN, SolverConfig(name="lm", loss="l2", maxiter=300, tol=1e-7, jacobian="sparse"))
    for i, (s, t) in enumerate(zip(scales, shifts)):
        np.testing.assert_allclose((J[i] - t) / s, BENT, atol=0.02)
        np.testing.assert_allclose(R[i] / s, BENT_R, rtol=0.03)


def test_estimated_starts_follow_the_cloud():
    rng = np.random.default_rng(0)
    from jskel.fit import sample_surface

    # a straight tube along a tilted axis: the principal-axis chain lies on the axis
    axis = np.array([1.0, 2.0, 0.5]) / np.linalg.norm([1.0, 2.0, 0.5])
    tube = sample_surface(np.array([[0, 0, 0], 4 * axis]), np.array([0.4, 0.4]), [-1, 0], 3000, rng)
    J, R, P = pca_chain(tube, 4)
    assert len(J) == 5 and list(P) == [-1, 0, 1, 2, 3]
    off_axis = np.linalg.norm(J - np.outer(J @ axis, axis), axis=1)
    assert np.all(off_axis < 0.05) and np.all(np.abs(R[1:-1] - 0.4) < 0.04)
    # a Y: the spanning tree over coarse voxels has three tips, and joints near the axes
    Y = np.array([[0, 0, 0], [0, 2, 0], [-1.4, 3.4, 0], [1.4, 3.4, 0]])
    cloud = sample_surface(Y, np.array([0.15, 0.15, 0.1, 0.1]), [-1, 0, 1, 1], 4000, rng)
    J, R, P = mst_skeleton(cloud, voxel=0.1, segment=0.15)
    children = np.bincount(P[P >= 0], minlength=len(J))
    tips = np.sum(children == 0) + (1 if children[0] == 1 else 0)  # leaves, and the root if it is an end
    assert tips == 3
    seg_d = []
    for a, b in ((0, 1), (1, 2), (1, 3)):
        v = Y[b] - Y[a]
        t = np.clip((J - Y[a]) @ v / (v @ v), 0, 1)
        seg_d.append(np.linalg.norm(J - (Y[a] + t[:, None] * v), axis=1))
    # a voxel centroid of surface points lies inside the tube: within the radius (0.15) of an
    # axis segment, or of the branch joint on the outer side of the 45-degree bend, where the
    # surface reaches 0.15 / cos(22.5 deg) = 0.163 from both axis segments
    assert np.max(np.min(seg_d, axis=0)) < 0.15 / np.cos(np.radians(22.5)) + 1e-3


def _fit_file(tmp_path, **over):
    cfg = {"name": "t", "points": {"synthetic": {"skeleton": {"joints": BENT.tolist(), "radii": BENT_R.tolist(), "parents": CHAIN.tolist()},
                                                 "count": 3000, "noise": 0.01, "outliers": 0.05, "seed": 7}},
           "init": {"perturb": 0.1, "seed": 3}, "solver": {"name": "lm", "loss": "cauchy", "maxiter": 300}}
    cfg.update(over)
    p = tmp_path / "fit.yaml"
    p.write_text(yaml.safe_dump(cfg))
    return p


def test_fit_command_writes_a_file_jskel_renders(tmp_path, capsys):
    f = _fit_file(tmp_path)
    assert main(["fit", str(f), "--out", str(tmp_path / "out")]) == 0
    info = json.loads((tmp_path / "out" / "fit.json").read_text())
    assert info["truth"]["joint_error_max_of_length"] < 0.02 and info["truth"]["radius_error_max_rel"] < 0.05
    assert info["history"][-1] < info["history"][0] and (tmp_path / "out" / "fit.png").stat().st_size > 10_000
    assert info["plane_margin_min"] > 0.05  # every shared plane cuts ellipses, as the renderer needs
    # the programs the process handed to XLA so far (the fit's own update at least, compiled or loaded)
    assert info["programs"]["compiled"] + info["programs"]["loaded"] >= 1 and "jit(_update)" in info["programs"]["by_name"]
    fitted = tmp_path / "out" / "fitted.yaml"
    sk, swc = yaml.safe_load(fitted.read_text())["object"]["skeleton"], read_swc(tmp_path / "out" / "fitted.swc")
    np.testing.assert_array_equal(swc.joints, sk["joints"])  # the same float64 values through both files
    np.testing.assert_array_equal(swc.radii, sk["radii"])
    np.testing.assert_array_equal(swc.parents, sk["parents"])
    # fitted.ply: the surface as triangles, every vertex on one of the fitted cones (256 lateral
    # triangles a segment at level 2) or a cap's centre on an axis, checked in float64 here
    import trimesh

    mesh = trimesh.load(tmp_path / "out" / "fitted.ply", process=False)
    j, r, par = np.asarray(sk["joints"]), np.asarray(sk["radii"]), np.asarray(sk["parents"])
    child = np.nonzero(par >= 0)[0]
    a, b, r1, r2 = j[par[child]], j[child], r[par[child]], r[child]
    axis = (b - a) / np.linalg.norm(b - a, axis=1, keepdims=True)
    h = np.linalg.norm(b - a, axis=1)
    rel = mesh.vertices[:, None, :] - a[None]  # (V, S, 3)
    y = np.einsum("vsk,sk->vs", rel, axis)
    rho = np.linalg.norm(rel - y[..., None] * axis[None], axis=-1)
    on_cone = np.abs(rho - (r1 + (r2 - r1) * y / h)) < 1e-9 * (1 + np.abs(y)) + 1e-9
    within = (y > -r1 - r2) & (y < h + r1 + r2)  # between its cutting planes, which tilt at joints
    assert np.all(np.any((on_cone | (rho < 1e-9)) & within, axis=1))
    assert len(mesh.faces) >= 256 * len(child) and info["surface"]["faces"] == len(mesh.faces) and info["surface"]["file"] == "fitted.ply"
    assert main(["render", str(fitted), "--out", str(tmp_path / "render"), "--set", "camera.width=64", "--set", "camera.height=48"]) == 0
    depth = np.load(tmp_path / "render" / "depth.npy")
    assert 0.05 < np.mean(np.isfinite(depth)) < 0.95  # framed: the branch is in view, not filling it


def test_topology_edits_between_rounds_recover_the_chain(tmp_path):
    """``edits``: the start is the bent chain with a twig that no points need and a joint too
    many on its straight first segment. The first round's fit lays the twig along the chain
    (where it takes points it does not need); the edits prune it and merge the straight joint;
    the next round edits nothing, and its fit is the true chain (same joints in the same order):
    joints within 2 % of the length, radii within 5 %; each edit in fit.json."""
    twig = BENT[3] + np.array([2.2, 0.3, 0.0])
    mid = 0.5 * (BENT[0] + BENT[1])
    start_j = np.concatenate([BENT[:1], [mid], BENT[1:], [twig]])
    start_r = np.concatenate([BENT_R[:1], [0.48], BENT_R[1:], [0.2]])
    start_p = [-1, 0, 1, 2, 3, 4, 5, 4]
    f = _fit_file(tmp_path, init={"skeleton": {"joints": start_j.tolist(), "radii": start_r.tolist(), "parents": start_p}},
                  edits={"rounds": 4, "merge_angle": 6.0})
    assert main(["fit", str(f), "--out", str(tmp_path / "out")]) == 0
    info = json.loads((tmp_path / "out" / "fit.json").read_text())
    kinds = sorted((e["edit"], e["joint"]) for e in info["edits"])
    assert kinds == [("merge", 1), ("prune", 7)] and all(e["round"] == 1 for e in info["edits"]), info["edits"]
    assert info["rounds"] == 2  # the second round edited nothing
    # the time and iterations are the two rounds', not the last's; the second round's topology
    # fits the first's sizes (6 joints of 8), so it ran the first round's program: its compile
    # time is the first update's run alone (milliseconds, against the first round's seconds)
    per = info["round_fits"]
    assert [r["round"] for r in per] == [1, 2] and [r["joints"] for r in per] == [8, 6]
    assert [r["padded_joints"] for r in per] == [8, 8]
    assert per[0]["compile_s"] > 0 and per[1]["compile_s"] < 0.2 * per[0]["compile_s"]
    assert all(r["iterations"] >= 1 for r in per)
    assert info["iterations"] == per[0]["iterations"] + per[1]["iterations"]
    assert info["compile_s"] == pytest.approx(per[0]["compile_s"] + per[1]["compile_s"])
    assert info["seconds"] == pytest.approx(per[0]["seconds"] + per[1]["seconds"])
    # solver.radii_refit with edits: once, after the last round; the rounds, edits and joints as without it
    f2 = _fit_file(tmp_path, init={"skeleton": {"joints": start_j.tolist(), "radii": start_r.tolist(), "parents": start_p}},
                   edits={"rounds": 4, "merge_angle": 6.0}, solver={"name": "lm", "loss": "cauchy", "maxiter": 300, "radii_refit": True})
    assert main(["fit", str(f2), "--out", str(tmp_path / "refit")]) == 0
    refit = json.loads((tmp_path / "refit" / "fit.json").read_text())
    assert refit["edits"] == info["edits"] and refit["history"] == info["history"]
    plain_sk, refit_sk = (yaml.safe_load((tmp_path / d / "fitted.yaml").read_text())["object"]["skeleton"] for d in ("out", "refit"))
    # (the same solver's steps and loss history; the written joints' last float64 bits differed
    # between the two runs in one process, 1e-16 relative)
    np.testing.assert_allclose(refit_sk["joints"], plain_sk["joints"], rtol=1e-12, atol=1e-12)
    assert refit_sk["radii"] != plain_sk["radii"]
    assert refit["truth"]["joint_error_max_of_length"] < 0.02 and refit["truth"]["radius_error_max_rel"] < 0.05
    assert info["truth"]["joint_error_max_of_length"] < 0.02 and info["truth"]["radius_error_max_rel"] < 0.05


def _tube(rng, a, b, r, n):
    """``n`` points on the cylinder of radius ``r`` around the axis a -> b, uniform in t and angle."""
    ax = (b - a) / np.linalg.norm(b - a)
    u = np.cross(ax, [0.3, 0.1, 0.9])
    u /= np.linalg.norm(u)
    w = np.cross(ax, u)
    t, phi = rng.uniform(0, 1, n), rng.uniform(0, 2 * np.pi, n)
    return a + t[:, None] * (b - a) + r * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * w)


def test_rounds_after_the_first_take_the_later_loss(monkeypatch):
    """``edits.later_loss``: the first round fits with ``solver.loss``, every later round with
    the later loss, and ``round_fits`` says which (the fits and edits replaced by stand-ins that
    record what they were given: no program is compiled)."""
    from jskel.fit import _fit, _run, _topology
    from jskel.fit._config import EditsConfig

    seen = []

    def fit(points, joints, radii, parents, s, dtype, seed=1, perturb=0.0, sizes=None):
        seen.append(s.loss)
        return _fit.FitResult(np.asarray(joints), np.asarray(radii), np.asarray(parents), [1.0, 0.5], 1, True, 0.1, 0.2, 0.0, 1, [])

    monkeypatch.setattr(_run, "fit_points", fit)
    monkeypatch.setattr(_topology, "edited", lambda pts, j, r, p, *a, **k: (j, r, p, [{"edit": "stand-in"}]))
    pts = np.random.default_rng(0).normal(size=(50, 3))
    for later, want in ((None, ["huber"] * 3), ("geman_mcclure", ["huber", "geman_mcclure", "geman_mcclure"])):
        seen.clear()
        res, log, rounds = _run.fitted_in_rounds(SolverConfig(loss="huber"), EditsConfig(rounds=3, later_loss=later), pts, BENT, BENT_R, CHAIN, np.float32)
        assert seen == want and [r["loss"] for r in res.rounds] == want and rounds == 3
    with pytest.raises(ValueError, match="later_loss"):
        EditsConfig(later_loss="tukey")


def test_each_topology_edit_where_the_points_call_for_it():
    """``_topology.edited`` on skeletons and points written here (no fit): a tip without points
    and a tip laid along another segment are pruned, a real branch is kept; a joint on a
    straight line and a segment shorter than ``merge_length`` are merged, a 30-degree joint is
    kept; the segment that cuts a 40-degree bend of the points is split at its middle, the
    others are not. Joints come out renumbered breadth first."""
    from jskel.fit._config import EditsConfig
    from jskel.fit._topology import edited

    rng = np.random.default_rng(2)
    tube = functools.partial(_tube, rng)

    cfg = EditsConfig(prune_points=5, merge_length=0.02, merge_angle=10.0, split_residual=3.0)
    # the points: a trunk up to (0, 4.5, 0) that then bends by 60 degrees, and a branch from (0, 3, 0)
    bend_top = np.array([1.7321, 5.5, 0.0])
    pts = np.concatenate([tube(np.zeros(3), np.array([0.0, 4.5, 0.0]), 0.2, 1500), tube(np.array([0.0, 4.5, 0.0]), bend_top, 0.2, 600),
                          tube(np.array([0.0, 3.0, 0.0]), np.array([-1.5, 3.5, 0.0]), 0.15, 500)])
    joints = np.array([[0, 0, 0], [0, 1.0, 0], [0, 2.0, 0], [0, 3.0, 0], [-0.01, 3.0, 0], [-1.5, 3.5, 0], bend_top, [0, 3.5, 0],
                       [1.0, 0.9, 2.0], [0.05, 2.5, 0.0]])
    radii = np.array([0.2, 0.2, 0.2, 0.2, 0.15, 0.15, 0.2, 0.2, 0.1, 0.2])
    parents = np.array([-1, 0, 1, 2, 3, 4, 7, 3, 1, 2])
    # 1: a joint on a straight line -> merged; 4: 0.01 from its parent (< 0.02 x extent) -> merged;
    # 5: the branch's tip (its points) -> kept; 6: the segment 7 -> 6 cuts the bend -> split;
    # 8: a twig with no points -> pruned; 9: a twig inside the trunk (the trunk's points) -> pruned
    j, r, p, log = edited(pts, joints, radii, parents, cfg, 0.01 * 5.0, 5.0, 1)
    got = sorted((e["edit"], e["joint"], e.get("why", "")) for e in log)
    assert got == [("merge", 1, "straight"), ("merge", 4, "short"), ("prune", 8, ""), ("prune", 9, ""), ("split", 6, "")], log
    assert len(j) == len(joints) - 4 + 1 and p[0] == -1 and np.all(p[1:] < np.arange(1, len(p)))  # breadth first
    assert np.sum(np.bincount(p[p >= 0], minlength=len(p)) >= 2) == 1  # one branch point left, at (0, 3, 0) or its merge
    assert np.min(np.linalg.norm(j - 0.5 * (joints[7] + bend_top), axis=1)) < 1e-12  # the new joint, mid-segment
    assert not EditsConfig().final_spurs  # an option, off by default (docs/fitting.md)
    # after the last round, the spurs alone: twig 9 (inside the trunk) goes, the twig 8 without
    # points is not a spur (its tip lies far from the trunk) and stays, as does every other joint
    j, r, p, log = edited(pts, joints, radii, parents, cfg, 0.01 * 5.0, 5.0, 3, spurs_only=True)
    assert [(e["edit"], e["joint"], e["why"]) for e in log] == [("prune", 9, "spur")], log
    assert len(j) == len(joints) - 1 and {tuple(x) for x in j} == {tuple(x) for x in np.delete(joints, [9], 0)}


def test_the_radius_parameter_is_the_radius_above_a_few_softnesses():
    """``_problem.radii_of``: ``r = min_radius + s softplus(u / s)``; the start's inverse gives
    back the radius (float64), and ``dr/du`` is the logistic ``1 / (1 + exp(-u / s))``, at least
    1 - exp(-5) once ``r - min_radius`` is 5 s or more (so LM's damping moves radii as it moves
    joints); 0 < r for any u."""
    from jskel.fit._problem import RADIUS_SOFTNESS, Normaliser, problem_of, radii_of
    from jskel.fit._distance import segments_of

    joints, parents = np.array([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 2.0, 0.0]]), np.array([-1, 0, 1])
    pr = problem_of(segments_of(joints, np.full(3, 0.1), parents), SolverConfig(), 3)
    nz = Normaliser(np.zeros(3), 1.0)
    s = RADIUS_SOFTNESS
    for r in (pr.min_radius + 5 * s, 0.01, 0.3):
        u = nz.start(joints, np.full(3, r), pr)[9:]
        with jax.enable_x64(True):
            uu = jnp.asarray(u, jnp.float64)
            np.testing.assert_allclose(np.asarray(radii_of(uu, pr)), r, rtol=1e-12)
            slope = np.asarray(jax.vmap(jax.grad(lambda v: radii_of(v, pr)))(uu))
        np.testing.assert_allclose(slope, 1.0 / (1.0 + np.exp(-u / s)), rtol=1e-12)
        assert np.all(slope >= 1.0 - np.exp(-5.0) - 1e-12)
        np.testing.assert_allclose(nz.world(np.concatenate([joints.reshape(-1), u]), pr)[1], r, rtol=1e-12)
    assert np.all(np.asarray(radii_of(np.array([-50.0, -1.0, 0.0]), pr)) > 0)


def test_spurs_and_frusta_shorter_than_their_width_are_edited_away():
    """``edits.spur_radii`` and ``edits.merge_radii`` on a skeleton and points written here (no
    fit): a trunk of radius 0.3 with a 0.33-long twig from its joint at y = 2, whose tip lies
    inside the trunk's tube (0.4 of its radius from its axis) and which has points of its own
    that the trunk does not explain (so only the spur rule removes it), and a straight branch of
    radius 0.15 from y = 3 with a 0.26-long segment in its chain (under 2 x its mean radius 0.15,
    over merge_length x extent). With both rules: the spur pruned, the short segment merged; with
    both rules off, neither."""
    from jskel.fit._config import EditsConfig
    from jskel.fit._topology import edited

    tube = functools.partial(_tube, np.random.default_rng(5))

    tip = np.array([-1.5, 3.5, 0.0])
    pts = np.concatenate([tube(np.zeros(3), np.array([0.0, 4.5, 0.0]), 0.3, 3000), tube(np.array([0.0, 2.05, 0.0]), np.array([0.12, 2.3, 0.0]), 0.04, 200),
                          tube(np.array([0.0, 3.0, 0.0]), tip, 0.15, 800)])
    b1, b2 = np.array([0.0, 3.0, 0.0]) + 0.5 * (tip - [0.0, 3.0, 0.0]), np.array([0.0, 3.0, 0.0]) + (0.5 + 0.26 / np.linalg.norm(tip - [0, 3, 0])) * (tip - [0.0, 3.0, 0.0])
    joints = np.array([[0, 0, 0], [0, 2.0, 0], [0, 3.0, 0], [0, 4.5, 0], [0.12, 2.3, 0], b1, b2, tip])
    radii = np.array([0.3, 0.3, 0.3, 0.3, 0.04, 0.15, 0.15, 0.15])
    parents = np.array([-1, 0, 1, 2, 1, 2, 5, 6])
    kw = dict(prune_points=5, merge_length=0.02, merge_angle=10.0, split_residual=3.0)
    _, _, _, log = edited(pts, joints, radii, parents, EditsConfig(**kw), 0.01 * 5.0, 5.0, 1)
    got = sorted((e["edit"], e["joint"], e.get("why", "")) for e in log)
    assert got == [("merge", 6, "short"), ("prune", 4, "spur")], log
    _, _, _, log = edited(pts, joints, radii, parents, EditsConfig(**kw, spur_radii=0.0, merge_radii=0.0), 0.01 * 5.0, 5.0, 1)
    assert not [e for e in log if e.get("why") in ("spur", "short")], log


def test_a_neck_is_merged_into_its_nearest_neighbour():
    """``edits.neck_ratio`` on a skeleton and points written here (no fit): a straight tube of
    radius 0.2 along y from 0 to 3 whose chain has joints at y = 0, 1, 1.3, 2, 3, the one at
    y = 1.3 of radius 0.02 (a tenth of its neighbours'). It is merged into the joint at y = 1
    (0.3 away, against 0.7), leaving the chain 0, 1, 2, 3 with the radii 0.2; a tip as thin
    (nothing beyond it) is not a neck, and with ``neck_ratio: 0`` nothing is merged."""
    from jskel.fit._config import EditsConfig
    from jskel.fit._topology import edited

    pts = _tube(np.random.default_rng(8), np.zeros(3), np.array([0.0, 3.0, 0.0]), 0.2, 3000)
    joints = np.array([[0, 0, 0], [0, 1.0, 0], [0, 1.3, 0], [0, 2.0, 0], [0, 3.0, 0]])
    radii = np.array([0.2, 0.2, 0.02, 0.2, 0.2])
    parents = np.array([-1, 0, 1, 2, 3])
    kw = dict(prune_points=5, merge_length=0.02, merge_radii=0.0, merge_angle=0.0, split_residual=100.0)  # necks alone
    j, r, p, log = edited(pts, joints, radii, parents, EditsConfig(**kw), 0.01 * 3.0, 3.0, 1)
    assert [(e["edit"], e["joint"], e["into"], e["why"]) for e in log] == [("merge", 2, 1, "neck")], log
    np.testing.assert_array_equal(p, [-1, 0, 1, 2])
    np.testing.assert_allclose(j[:, 1], [0.0, 1.0, 2.0, 3.0])
    np.testing.assert_allclose(r, 0.2)
    _, _, _, log = edited(pts, joints, radii, parents, EditsConfig(**kw, neck_ratio=0.0), 0.01 * 3.0, 3.0, 1)
    assert log == [], log
    thin_tip = np.array([0.2, 0.2, 0.2, 0.2, 0.02])
    _, _, _, log = edited(pts, joints, thin_tip, parents, EditsConfig(**kw), 0.01 * 3.0, 3.0, 1)
    assert not [e for e in log if e.get("why") == "neck"], log


def test_one_tube_traced_twice_from_a_joint_is_zipped_and_a_real_fork_is_not():
    """``edits.zip_radii`` on skeletons and points written here (no fit): a trunk of radius 0.2
    along y from 0 to 3, whose joint at y = 1.5 has two children 0.07 apart at y = 2 (one tube
    traced twice, as fits of the grown trees kept beside their junctions), each going on up the
    trunk. One child is merged into the other (logged as a zip at the joint), the joint is left
    with one child, and the merged joint carries both continuations. A real fork, two branches
    of radius 0.1 leaving the joint 60 degrees apart, whose first joints lie 0.5 apart, is
    kept; with ``zip_radii: 0`` nothing is zipped."""
    from jskel.fit._config import EditsConfig
    from jskel.fit._topology import edited

    tube = functools.partial(_tube, np.random.default_rng(11))
    pts = tube(np.zeros(3), np.array([0.0, 3.0, 0.0]), 0.2, 3000)
    joints = np.array([[0, 0, 0], [0, 1.5, 0], [0, 2.0, 0], [0.07, 2.0, 0], [0, 3.0, 0], [0.05, 2.9, 0]])
    radii = np.full(6, 0.2)
    parents = np.array([-1, 0, 1, 1, 2, 3])
    kw = dict(prune_points=0, merge_length=0.0, merge_radii=0.0, merge_angle=0.0, split_residual=100.0, spur_radii=0.0, neck_ratio=0.0,
              zip_radii=1.0)
    assert EditsConfig().zip_radii == 0.0  # an option, off by default (docs/fitting.md)
    j, r, p, log = edited(pts, joints, radii, parents, EditsConfig(**kw), 0.01 * 3.0, 3.0, 1)
    assert [(e["edit"], e["why"], e["at"]) for e in log] == [("merge", "zip", 1)], log
    assert {e["joint"] for e in log} | {e["into"] for e in log} == {2, 3}
    kids = np.bincount(p[p >= 0], minlength=len(p))
    assert len(j) == 5 and kids[np.argmin(np.linalg.norm(j - [0, 1.5, 0], axis=1))] == 1
    assert np.max(kids) == 2  # the kept joint at y = 2 carries both continuations
    _, _, _, log = edited(pts, joints, radii, parents, EditsConfig(**{**kw, "zip_radii": 0.0}), 0.01 * 3.0, 3.0, 1)
    assert log == [], log
    # a real fork: branches 60 degrees apart, their first joints 0.5 from the joint and each other
    arm = lambda deg: np.array([0.0, 1.5, 0.0]) + 0.5 * np.array([np.sin(np.radians(deg)), np.cos(np.radians(deg)), 0.0])  # noqa: E731
    fork = np.concatenate([tube(np.zeros(3), np.array([0.0, 1.5, 0.0]), 0.2, 1500), tube(np.array([0.0, 1.5, 0.0]), arm(-30) * 2 - [0, 1.5, 0], 0.1, 800),
                           tube(np.array([0.0, 1.5, 0.0]), arm(30) * 2 - [0, 1.5, 0], 0.1, 800)])
    joints = np.array([[0, 0, 0], [0, 1.5, 0], arm(-30), arm(30), arm(-30) * 2 - [0, 1.5, 0], arm(30) * 2 - [0, 1.5, 0]])
    radii = np.array([0.2, 0.2, 0.1, 0.1, 0.1, 0.1])
    _, _, _, log = edited(fork, joints, radii, parents, EditsConfig(**kw), 0.01 * 3.0, 3.0, 1)
    assert log == [], log


def test_an_outside_weight_makes_the_radius_enclose_the_points():
    """``solver.outside``: points outside the surface weigh ``outside`` times those inside (their
    squared residuals). On a cylinder of radius 0.3 sampled with radial noise, the l2 fit's
    radius is the mean radial distance with 1 and the ``outside / (1 + outside)`` expectile with
    16, both computed here in float64 from the points (and then about 15 % of them outside, not
    half)."""
    pts, rho = noisy_cylinder()
    joints, radii, parents = np.array([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]]), np.array([0.3, 0.3]), np.array([-1, 0])
    expectile = functools.partial(fit_truths.expectile, rho)
    for w in (1.0, 16.0):
        s = SolverConfig(name="lm", loss="l2", maxiter=200, tol=1e-9, jacobian="dense", outside=w, validity=0.0)
        res = fit_points(pts, joints, radii, parents, s)
        want = expectile(w)
        np.testing.assert_allclose(res.radii.mean(), want, rtol=2e-3)  # at the expectile (the noise tapers it a little)
        np.testing.assert_allclose(res.radii, want, rtol=1e-2)
        out = np.mean(rho > res.radii.mean())
        assert abs(out - np.mean(rho > want)) < 0.03 and ((0.4 < out < 0.6) if w == 1.0 else (out < 0.2))
    sparse = fit_points(pts, joints, radii, parents, s.model_copy(update={"jacobian": "sparse"}))  # the other normal equations
    np.testing.assert_allclose(sparse.radii, res.radii, rtol=1e-4)
    # solver.radii_refit (the same compiled solver): the joints as fitted, the radii again from them
    refit = fit_points(pts, joints, radii, parents, s.model_copy(update={"radii_refit": True}))
    np.testing.assert_array_equal(refit.joints, res.joints)
    np.testing.assert_allclose(refit.radii, want, rtol=1e-2)
    assert expectile(16.0) > expectile(1.0) + 0.02  # the two fits lie more than a noise sigma apart


def test_bad_fit_input_is_one_line_and_exit_2(tmp_path, capsys):
    few = tmp_path / "few.npy"
    np.save(few, np.zeros((10, 3)) + np.arange(10)[:, None])
    nan = tmp_path / "nan.npy"
    a = np.random.default_rng(0).normal(size=(200, 3))
    a[17] = np.nan
    np.save(nan, a)
    empty = tmp_path / "empty.xyz"
    empty.write_text("")
    cases = [
        ({"points": {"file": str(few)}, "init": {"estimate": {"segments": 5}}}, "10 points for 24 unknowns"),
        ({"points": {"file": str(nan)}}, "points.file[17]: not finite (got [nan, nan, nan]); set points.nonfinite: drop"),
        ({"points": {"file": str(empty)}}, "points.file: no points in"),
        ({"points": {"file": str(tmp_path / "none.ply")}}, "points.file: not found"),
        ({"init": {"skeleton": {"joints": [[0, 0, 0], [0, 0, 0]], "radii": [1, 1], "parents": [-1, 0]}}}, "init.skeleton.joints[1]: zero-length segment"),
        ({"solver": {"name": "newton", "maxiter": 0}}, "solver.name"),
    ]
    for over, needle in cases:
        f = _fit_file(tmp_path, **over)
        assert main(["fit", str(f), "--out", str(tmp_path / "bad")]) == 2, needle
        err = capsys.readouterr().err.strip().splitlines()
        assert any(needle in line for line in err), (needle, err)
        if needle != "solver.name":
            assert len(err) == 1
    # dropping instead of rejecting: counted
    pts, info, _ = load_points(PointsConfig(file=str(nan), nonfinite="drop"))
    assert info["dropped_nonfinite"] == 1 and pts.shape == (199, 3)
    with pytest.raises(ValueError):
        FitFile.model_validate({"points": {"file": "a.npy", "synthetic": {"skeleton": {"procedural": "saguaro"}}}})


def test_bad_values_inside_jit_raise_naming_the_index():
    """checkify: a radius driven negative, joints that met, a NaN point, all only known under
    jit (traced values), raise a ValueError with the index and value, never a silent NaN;
    several at once give a line each."""
    from jskel.fit import checked_distances

    J = np.array([[0, 0, 0], [0, 1, 0], [0.3, 2, 0]], np.float32)
    R = np.array([0.3, 0.25, 0.2], np.float32)
    seg = segments_of(J, R, [-1, 0, 1])
    x = np.array([[0.5, 0.5, 0.0], [0.0, 1.5, 0.4]], np.float32)
    np.testing.assert_allclose(checked_distances(J, R, seg, x), d32(J, R, [-1, 0, 1], x), atol=1e-7)
    compiled = checked_distances.program._cache_size()
    with pytest.raises(ValueError) as e:
        checked_distances(J, np.array([0.3, -0.5, 0.2], np.float32), seg, x)
    assert e.value.lines == ["radii[1]: negative (got -0.5); 1 of 3 entries"]
    with pytest.raises(ValueError) as e:
        checked_distances(np.array([[0, 0, 0], [0, 1, 0], [0, 1, 0]], np.float32), R, seg, x)
    assert e.value.lines == ["segment_length[2]: not positive (got 0); 1 of 2 entries"]
    # every failing field at once, each with every bad entry counted (checkify alone stops at the first)
    with pytest.raises(ValueError) as e:
        checked_distances(J, np.array([np.nan, -0.5, -0.2], np.float32), seg, np.array([[0.5, 0.5, 0.0], [np.nan, 0, 0]], np.float32))
    assert e.value.lines == ["radii[0]: not finite (got nan); 1 of 3 entries",
                             "radii: 2 entries: negative (indices 1: -0.5, 2: -0.2); 2 of 3 entries",
                             "points[1]: not finite (got [nan, 0, 0]); 1 of 2 entries"]
    assert checked_distances.program._cache_size() == compiled  # new values, the same program


def test_a_diverging_solver_is_an_error_not_a_result(noisy_branch):
    """Adam with a far too large step runs the skeleton away: the loss rises, and the fit says
    so (a ValueError naming solver.name) instead of returning the finite but absurd skeleton."""
    pts, _ = noisy_branch
    with pytest.raises(ValueError, match=r"solver\.name: adam diverged"):
        fit_points(pts, BENT, BENT_R, CHAIN, SolverConfig(name="adam", loss="cauchy", learning_rate=5.0, maxiter=40))


def test_a_fit_shows_its_iterations_and_loss_as_it_runs(noisy_branch, monkeypatch):
    """The stepping loop's bar (``jskel.progress.bar``, shown where ``progress.quiet`` allows):
    one bar of ``maxiter`` steps, advanced once per iteration, its last postfix the last loss."""
    from jskel import progress

    seen = []

    class Bar:
        def __init__(self, total, desc, unit):
            self.total, self.desc, self.n, self.post = total, desc, 0, None
            seen.append(self)

        def update(self, n):
            self.n += n

        def set_postfix(self, refresh=True, **kw):
            self.post = kw

        def close(self):
            pass

    monkeypatch.setattr(progress, "bar", Bar)
    pts, _ = noisy_branch
    res = fit_points(pts, BENT, BENT_R, CHAIN, SolverConfig(name="adam", loss="cauchy", learning_rate=1e-3, maxiter=6))
    assert len(seen) == 1 and seen[0].total == 6 and seen[0].desc == "fit (adam)"
    assert seen[0].n == res.iterations and seen[0].post == {"loss": f"{res.history[-1]:.4g}"}


def test_jitted_distance_of_a_long_chain_is_zero_on_its_surface():
    """Regression: on XLA CPU (jax 0.10.2) ``jnp.sum(a * b, -1)`` dot products made the jitted
    distance of a 50-segment chain wrong (by up to 35) for points past the 655th of a batch, while
    the same ops run one by one were right; the distance now writes its dots out per component."""
    from jskel.fit._bench import bent_chain
    from jskel.fit import sample_surface

    j, r, p = bent_chain(50, 0)
    pts = sample_surface(j, r, p, 2000, np.random.default_rng(0))
    d = dist(j, r, segments_of(j, r, p), pts)  # jitted, padded to 4096 points (past the 655th)
    assert np.max(np.abs(d)) < 1e-4


def _chain_and_cloud(n_surface: int, seed: int):
    """A 50-segment bent chain (joints, radii, parents, Segments) and points about it: its
    surface with noise, as many 0.3 inside it, and 500 uniform outliers up to 3 units beyond."""
    from jskel.fit import sample_surface
    from jskel.fit._bench import bent_chain

    j, r, p = bent_chain(50, 0)
    rng = np.random.default_rng(seed)
    surf = sample_surface(j, r, p, n_surface, rng)
    inward = (j.mean(0) - surf) / np.linalg.norm(j.mean(0) - surf, axis=1, keepdims=True)
    pts = np.concatenate([surf + rng.normal(0, 0.05, surf.shape), surf + 0.3 * inward, rng.uniform(j.min(0) - 3, j.max(0) + 3, (500, 3))])
    return j, r, p, segments_of(j, r, p), pts


def test_culled_distances_equal_all_segments_where_certified():
    """Each point measured against its 8 nearest segments (by a lower bound) of a 50-segment
    chain: on and off the surface, inside, and far outliers, the culled distance equals the
    distance over all 50 segments wherever ``culling_exact`` certifies it, and it certifies
    nearly every point; the smallest lower bound never exceeds the distance over all segments."""
    j, r, p, seg, pts = _chain_and_cloud(1500, 4)
    args = (jnp.asarray(j, jnp.float32), jnp.asarray(r, jnp.float32), seg, jnp.asarray(pts, jnp.float32))
    full = dist(j, r, seg, pts)
    culled = dist(j, r, seg, pts, 8)
    ok = dist(j, r, seg, pts, 8, fn=_culling_exact)
    assert ok.mean() > 0.99
    np.testing.assert_allclose(culled[ok], full[ok], atol=1e-6)
    # the bound the choice rests on: no piece is nearer than its bound (outside points)
    from jskel.fit._distance import _lower_bounds, _reach, geometry

    g = geometry(*args[:3])
    lb = np.asarray(jax.jit(jax.vmap(lambda x: jnp.min(_lower_bounds(g, _reach(g), x))))(args[3]))
    assert np.all(lb[full > 0] <= full[full > 0] + 1e-5)


def test_block_lists_choose_what_every_point_would_and_certify_honestly():
    """Candidates chosen through blocks of 32 consecutive points sharing a list of 16 of the
    50 segments (``solver.block``), on points of the surface, inside and far outliers: in
    spatial order the distances equal those of each point choosing among all 50 segments,
    and the certificate holds as often; shuffled, every block is spread over the whole cloud,
    most points are unsure of their block's list and fall back 500 at a time (several passes),
    and the distances are again every point's own."""
    from jskel.fit._distance import spatial_order

    j, r, p, seg, pts = _chain_and_cloud(2500, 5)
    pts = pts[np.random.default_rng(5).permutation(len(pts))][:PAD]
    blocked = functools.partial(_blocked, block=32, per_block=16)
    certified = functools.partial(_culling_exact_blocked, block=32, per_block=16)
    full = dist(j, r, seg, pts)
    with pytest.raises(ValueError, match="block_candidates: 8 must exceed candidates"):
        SolverConfig(candidates=8, block_candidates=8)
    for cloud, ref in ((pts[spatial_order(pts)], full[spatial_order(pts)]), (pts, full)):
        d = dist(j, r, seg, cloud, 8, fn=blocked)
        np.testing.assert_allclose(d, dist(j, r, seg, cloud, 8), atol=1e-6)
        ok = dist(j, r, seg, cloud, 8, fn=certified)
        assert ok.mean() > 0.99
        np.testing.assert_allclose(d[ok], ref[ok], atol=1e-6)


@pytest.mark.parametrize("kind", ["l2", "huber", "cauchy", "geman_mcclure"])
def test_robust_residuals_square_to_their_loss(kind):
    """Half the square of each robust residual is its loss, written here in float64 NumPy:
    Huber's, Cauchy's scale^2/2 log(1 + x), Geman-McClure's scale^2/2 x / (1 + x) (bounded)."""
    from jskel.fit import robust_residuals

    s = 0.3
    r = np.concatenate([np.linspace(-50, 50, 401), [0.0, 1e-4, -1e-4, s, -s]])
    x = (r / s) ** 2
    want = {"l2": 0.5 * r**2, "huber": np.where(np.abs(r) <= s, 0.5 * r**2, s * np.abs(r) - 0.5 * s * s),
            "cauchy": 0.5 * s * s * np.log1p(x), "geman_mcclure": 0.5 * s * s * x / (1 + x)}[kind]
    got = np.asarray(robust_residuals(jnp.asarray(r, jnp.float32), kind, s), np.float64)
    np.testing.assert_allclose(0.5 * got**2, want, rtol=2e-5, atol=1e-9)
    assert np.all(np.sign(got) == np.sign(r))


def test_a_time_budget_stops_the_fit_and_says_so(noisy_branch):
    pts, _ = noisy_branch
    # the recovery test's solver (a program the persistent compilation cache already holds) with a budget
    s = SolverConfig(name="lm", loss="cauchy", scale=0.01, maxiter=300, restarts=1, jacobian="dense", max_seconds=1e-9)
    res = fit_points(pts, BENT, BENT_R, CHAIN, s)
    assert res.iterations == 1 and not res.converged and len(res.history) == 2
