"""Fitting a skeleton's joints and radii to a point cloud (issue 10).

The unknowns are the joints (J,3) and radii (J,) of a skeleton of fixed topology; the residual
of a point is its signed distance to the frusta surface (``_distance``), made robust (Huber or
Cauchy) so outliers pull linearly or less, plus ``sqrt(smoothness)`` times the second
differences of the joints along each chain. Radii stay positive by construction:
``r = min_radius + softplus(u)`` with ``u`` the free parameter.

The problem is solved in normalised coordinates (points centred on their mean and divided by
their largest extent), so tolerances, damping, the robust scale and the smoothness weight mean
the same thing for a twig and a tree; the result is mapped back to world units.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from . import _solvers
from ._config import EstimateConfig, FitFile, PointsConfig, SolverConfig
from ._distance import Segments, distances, sample_surface, segments_of


def _softplus_inv(y):
    y = np.maximum(np.asarray(y, np.float64), 1e-12)
    return np.where(y > 30, y, np.log(np.expm1(np.minimum(y, 30))))


# ----------------------------------------------------------------------------- points


def read_points(path: str | Path) -> np.ndarray:
    """(N,3) float64 points from .npy, .xyz/.txt/.csv or .ply; ValueError naming ``points.file``."""
    p = Path(path)
    if not p.exists():
        raise ValueError(f"points.file: not found (got {str(p)!r})")
    ext = p.suffix.lower()
    try:
        if ext == ".npy":
            a = np.load(p, allow_pickle=False)
        elif ext in (".xyz", ".txt", ".csv"):
            a = np.loadtxt(p, delimiter="," if ext == ".csv" else None, ndmin=2) if p.stat().st_size else np.zeros((0, 3))
        elif ext == ".ply":
            import trimesh

            g = trimesh.load(p, process=False)
            a = np.asarray(g.vertices)
        else:
            raise ValueError(f"points.file: unknown format {ext!r} (got {str(p)!r}; .npy, .xyz, .txt, .csv, .ply)")
    except ValueError:
        raise
    except Exception as e:  # noqa: BLE001 - a corrupt file: say which and why, in one line
        raise ValueError(f"points.file: cannot read {str(p)!r}: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    a = np.asarray(a, np.float64)
    if a.size == 0:
        raise ValueError(f"points.file: no points in {str(p)!r}")
    if a.ndim != 2 or a.shape[1] < 3:
        raise ValueError(f"points.file: expected (N, 3) points, got shape {a.shape} in {str(p)!r}")
    return a[:, :3]


def skeleton_arrays(sk) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(joints, radii, parents) of a ``SkeletonConfig`` (explicit or procedural), float64."""
    from ..frusta._scene import _skeleton_arrays

    j, r, p, _ = _skeleton_arrays(sk)
    return np.asarray(j, np.float64), np.asarray(r, np.float64), np.asarray(p, np.int64)


def load_points(cfg: PointsConfig, base: Path | None = None) -> tuple[np.ndarray, dict, tuple | None]:
    """The cloud (N,3) float64, facts for fit.json, and the true skeleton of synthetic points."""
    info: dict = {}
    truth = None
    if cfg.synthetic is not None:
        s = cfg.synthetic
        j, r, p = skeleton_arrays(s.skeleton)
        segments_of(j, r, p, "points.synthetic.skeleton")
        rng = np.random.default_rng(s.seed)
        pts = sample_surface(j, r, p, s.count, rng)
        length = float(np.sum(np.linalg.norm(j[p[p >= 0]] - j[p >= 0], axis=1)))
        pts = pts + rng.normal(0.0, s.noise * length, pts.shape)
        n_out = int(round(s.outliers * s.count))
        if n_out:
            lo, hi = pts.min(0), pts.max(0)
            pad = 0.2 * (hi - lo)
            idx = rng.choice(s.count, n_out, replace=False)
            pts[idx] = rng.uniform(lo - pad, hi + pad, (n_out, 3))
        info.update({"source": "synthetic", "noise_sd": s.noise * length, "outliers": n_out, "skeleton_length": length})
        truth = (j, r, p)
    else:
        f = Path(cfg.file)
        pts = read_points(f if f.is_absolute() or base is None or f.exists() else base / f)
        info["source"] = str(cfg.file)
    bad = ~np.all(np.isfinite(pts), axis=1)
    if bad.any():
        first = int(np.argmax(bad))
        if cfg.nonfinite == "reject":
            raise ValueError(f"points: {int(bad.sum())} of {len(pts)} points are NaN or inf (first at index {first}: "
                             f"{pts[first].tolist()}); set points.nonfinite: drop to drop them")
        pts = pts[~bad]
        info["dropped_nonfinite"] = int(bad.sum())
    info["points"] = int(len(pts))
    return pts, info, truth


# ----------------------------------------------------------------------------- starts


def pca_chain(points: np.ndarray, segments: int):
    """A straight chain of ``segments`` segments along the cloud's principal axis; joints at
    the centroids of slabs across the axis, radii the median distance to the axis there."""
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    ax = vt[0]
    t = (points - c) @ ax
    lo, hi = np.percentile(t, [0.5, 99.5])
    edges = np.linspace(lo, hi, segments + 1)
    half = 0.5 * (hi - lo) / segments
    joints, radii = [], []
    for e in edges:
        sel = np.abs(t - e) <= half
        if sel.sum() < 3:
            sel = np.argsort(np.abs(t - e))[: max(3, len(t) // (4 * segments))]
        cen = points[sel].mean(0)
        cen = c + ax * e + (cen - c - ax * ((cen - c) @ ax))  # on the slab plane through e
        q = points[sel] - cen
        rad = np.linalg.norm(q - np.outer(q @ ax, ax), axis=1)
        joints.append(cen)
        radii.append(max(float(np.median(rad)), 1e-3 * (hi - lo)))
    return np.array(joints), np.array(radii), np.arange(-1, segments)


def mst_skeleton(points: np.ndarray, voxel: float, segment: float):
    """A branching skeleton: a minimum spanning tree over occupied voxels' centroids (voxel
    edge ``voxel`` x extent), rooted at one end of its longest path and simplified to joints
    at least ``segment`` x extent apart along each branch (branch points and tips kept).
    Limits: voxels must be wider than the tubes (so a centroid lies near the axis) and narrower
    than the gaps between branches (or branches fuse); noise and outliers add spurious twigs."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree, shortest_path

    ext = float(np.max(np.ptp(points, axis=0))) or 1.0
    v = voxel * ext
    keys = np.floor((points - points.min(0)) / v).astype(np.int64)
    uniq, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    cen = np.zeros((len(uniq), 3))
    np.add.at(cen, inv, points)
    cen /= counts[:, None]
    keep = counts >= 2  # lone points (outliers) make no node
    if keep.sum() < 2:
        raise ValueError(f"init.estimate.voxel: {voxel} leaves fewer than 2 occupied voxels with 2 points")
    idx = np.nonzero(keep)[0]
    cen, kk = cen[idx], uniq[idx]
    n = len(idx)
    d = np.abs(kk[:, None, :] - kk[None, :, :]).max(-1)
    ii, jj = np.nonzero((d <= 1) & (np.arange(n)[:, None] < np.arange(n)[None, :]))
    w = np.linalg.norm(cen[ii] - cen[jj], axis=1) + 1e-12
    g = coo_matrix((w, (ii, jj)), shape=(n, n)).tocsr()
    t = minimum_spanning_tree(g)
    t = t + t.T
    dist = shortest_path(t, indices=0, directed=False)
    dist = np.where(np.isfinite(dist), dist, -1)
    root = int(np.argmax(dist))  # one end of a longest path (of the component holding node 0)
    order, pred = breadth_first_order(t, root, directed=False)
    deg = np.asarray((t > 0).sum(axis=1)).reshape(-1)
    seglen = segment * ext
    keep_node = {root}
    newpar = {root: -1}
    acc = {root: 0.0}
    anchor = {root: root}
    for node in order[1:]:
        p = int(pred[node])
        a = anchor[p]
        dd = acc[p] + float(np.linalg.norm(cen[node] - cen[p]))
        if deg[node] != 2 or dd >= seglen or deg[p] > 2:
            keep_node.add(int(node))
            newpar[int(node)] = a
            anchor[int(node)] = int(node)
            acc[int(node)] = 0.0
        else:
            anchor[int(node)] = a
            acc[int(node)] = dd
    kept = [int(x) for x in order if int(x) in keep_node]
    pos = {k: i for i, k in enumerate(kept)}
    joints = cen[kept]
    parents = np.array([-1 if newpar[k] < 0 else pos[newpar[k]] for k in kept])
    # radius: median distance of each kept voxel's points from its centroid, across the local axis
    radii = np.zeros(len(kept))
    for i, k in enumerate(kept):
        sel = inv == idx[k]
        q = points[sel] - cen[k]
        nb = joints[parents[i]] if parents[i] >= 0 else (joints[np.argmax(parents == i)] if np.any(parents == i) else cen[k] + [0, 1, 0])
        ax = nb - cen[k]
        ax /= np.linalg.norm(ax) or 1.0
        radii[i] = max(float(np.median(np.linalg.norm(q - np.outer(q @ ax, ax), axis=1))) if len(q) else 0.0, 1e-3 * ext)
    return joints, radii, parents


def perturbed(joints, radii, parents, amount: float, rng: np.random.Generator):
    """Joints moved by ``amount`` x mean segment length in random directions; radii x (1 +-
    amount) with random signs."""
    if amount == 0:
        return joints.copy(), radii.copy()
    seg = np.linalg.norm(joints[parents >= 0] - joints[parents[parents >= 0]], axis=1).mean()
    d = rng.normal(size=joints.shape)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return joints + amount * seg * d, radii * (1 + amount * rng.choice([-1.0, 1.0], radii.shape))


def starting_skeleton(cfg: FitFile, points: np.ndarray, truth) -> tuple[np.ndarray, np.ndarray, np.ndarray, str]:
    init = cfg.init
    if init.skeleton is not None:
        j, r, p = skeleton_arrays(init.skeleton)
        how = "given"
    elif init.estimate is not None or truth is None:
        est = init.estimate or EstimateConfig()
        j, r, p = (pca_chain(points, est.segments) if est.method == "pca_chain" else mst_skeleton(points, est.voxel, est.segment))
        how = f"estimate:{est.method}"
    else:
        j, r, p = truth
        how = "truth"
    return j, r, p, how


# ----------------------------------------------------------------------------- the problem


class Problem(NamedTuple):
    """Static description of a fit (hashable): topology, smoothing triples, loss, solver."""

    seg: Segments
    triples: tuple
    loss: str
    scale: float
    smoothness: float
    min_radius: float


def problem_of(seg: Segments, s: SolverConfig) -> Problem:
    triples = tuple((int(seg.start[a]), int(seg.start[b]), int(seg.end[b])) for a, b in zip(seg.cont_a, seg.cont_b))
    return Problem(seg, triples, s.loss, float(s.scale), float(s.smoothness), float(s.min_radius))


def radii_of(u, pr: Problem):
    return pr.min_radius + jax.nn.softplus(u)


def unpack(x):
    """The flat parameter vector (4J,) (jaxopt's least-squares solvers want one array) as
    joints (J,3) and the radius parameters u (J,)."""
    nj = x.shape[-1] // 4
    return x[..., : 3 * nj].reshape(x.shape[:-1] + (nj, 3)), x[..., 3 * nj :]


def residuals(x, points, pr: Problem):
    """Robust point residuals (N,) and the smoothness terms, in normalised units."""
    joints, u = unpack(x)
    d = distances(joints, radii_of(u, pr), pr.seg, points)
    r = _solvers.robust_residuals(d, pr.loss, pr.scale)
    if pr.smoothness > 0 and pr.triples:
        t = np.asarray(pr.triples)
        j = joints
        sec = (j[t[:, 0]] - 2.0 * j[t[:, 1]] + j[t[:, 2]]).reshape(-1)
        r = jnp.concatenate([r, jnp.sqrt(pr.smoothness) * sec])
    return r


def loss(x, points, pr: Problem):
    r = residuals(x, points, pr)
    return 0.5 * jnp.sum(r * r)


class Normaliser(NamedTuple):
    centre: np.ndarray
    extent: float

    def points(self, p):
        return (np.asarray(p, np.float64) - self.centre) / self.extent

    def start(self, joints, radii, pr: Problem):
        j = (np.asarray(joints, np.float64) - self.centre) / self.extent
        return np.concatenate([j.reshape(-1), _softplus_inv(np.asarray(radii, np.float64) / self.extent - pr.min_radius)])

    def world(self, x, pr: Problem):
        joints, u = unpack(np.asarray(x, np.float64))
        r = np.asarray(radii_of(jnp.asarray(u), pr), np.float64) * self.extent
        return joints * self.extent + self.centre, r


def normaliser_of(points) -> Normaliser:
    c = points.mean(0)
    e = float(np.max(np.ptp(points, axis=0)))
    if not e > 0:
        raise ValueError("points: every point is at the same place (the cloud has no extent)")
    return Normaliser(c, e)


class FitResult(NamedTuple):
    joints: np.ndarray
    radii: np.ndarray
    parents: np.ndarray
    history: list  # loss after each iteration (normalised units), the start first
    iterations: int
    converged: bool
    seconds: float
    compile_s: float
    error: float  # the solver's final stopping measure
    restarts: int
    restart_losses: list


DENSE_JACOBIAN_MAX = 1 << 24  # entries (residuals x unknowns) up to which LM forms J (64 MiB in float32)


def _steppers(name, pr: Problem, s: SolverConfig, n_res: int, n_par: int):
    return _solvers.make(name, lambda x, p: residuals(x, p, pr), lambda x, p: loss(x, p, pr), s.maxiter, s.tol, s.learning_rate,
                         dense=n_res * n_par <= DENSE_JACOBIAN_MAX)


def fit_points(points: np.ndarray, joints0, radii0, parents, s: SolverConfig, dtype=np.float32, seed: int = 1,
               perturb: float = 0.0) -> FitResult:
    """Fit a skeleton of ``parents``' topology to ``points`` from (joints0, radii0): the
    stepping loop records the loss after every iteration; with ``s.restarts > 1`` that many
    starts (the given one and perturbed copies) are first solved at once under ``vmap`` and
    the best is stepped again for its loss curve (one more fit, counted in ``seconds``)."""
    seg = segments_of(joints0, radii0, parents, "init.skeleton")
    n_par = 4 * len(joints0)
    if len(points) < n_par:
        raise ValueError(f"points: {len(points)} points for {n_par} unknowns (4 per joint of {len(joints0)}); need at least as many points")
    pr = problem_of(seg, s)
    nz = normaliser_of(points)
    pts = jnp.asarray(nz.points(points), dtype)
    cast = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    step = _steppers(s.name, pr, s, len(points) + 3 * len(pr.triples), n_par)
    x0 = cast(nz.start(np.asarray(joints0, np.float64), np.asarray(radii0, np.float64), pr))
    t_all = time.perf_counter()
    restart_losses = []
    if s.restarts > 1:
        rng = np.random.default_rng(seed)
        starts = [nz.start(np.asarray(joints0), np.asarray(radii0), pr)]
        for _ in range(s.restarts - 1):
            j, r = perturbed(np.asarray(joints0, np.float64), np.asarray(radii0, np.float64), np.asarray(parents), max(perturb, 0.1), rng)
            starts.append(nz.start(j, r, pr))
        xb = cast(np.stack(starts))
        solve = jax.jit(jax.vmap(lambda x: step.run(x, pts)[0]))
        xs = solve(xb)
        ls = np.asarray(jax.jit(jax.vmap(lambda x: loss(x, pts, pr)))(xs))
        restart_losses = [float(v) for v in ls]
        best = int(np.nanargmin(ls))
        x0 = xb[best]
    lossf = jax.jit(lambda x: loss(x, pts, pr))
    t0 = time.perf_counter()
    st0 = step.init(x0, pts)
    # jaxopt's first update may change a state field's dtype (an int counter becomes a float):
    # start from the state types an update returns, so one executable serves every iteration
    shapes = jax.eval_shape(lambda x, st: step.update(x, st, pts), x0, st0)[1]
    st0 = jax.tree_util.tree_map(lambda a, sh: jnp.asarray(a, sh.dtype), st0, shapes)
    upd = jax.jit(lambda x, st: step.update(x, st, pts)).lower(x0, st0).compile()
    compile_s = time.perf_counter() - t0
    x, st = x0, st0
    history = [float(lossf(x))]
    converged = False
    it = 0
    for it in range(1, s.maxiter + 1):  # host loop over iterations: one compiled update each
        x, st = upd(x, st)
        history.append(float(lossf(x)))
        if float(step.error(st)) <= s.tol:
            converged = True
            break
    seconds = time.perf_counter() - t_all - compile_s
    if not np.all(np.isfinite(np.asarray(x))) or not np.isfinite(history[-1]):
        raise ValueError(f"solver.name: {s.name} diverged to a non-finite loss after {it} iterations (try another solver or a smaller learning_rate)")
    j, r = nz.world(x, pr)
    return FitResult(j, r, np.asarray(parents), history, it, converged, seconds, compile_s, float(step.error(st)), s.restarts, restart_losses)


def point_distances(points, joints, radii, parents, dtype=np.float32) -> np.ndarray:
    """Signed distances of ``points`` to a skeleton's surface, in world units (NumPy)."""
    seg = segments_of(joints, radii, parents, "skeleton")
    nz = normaliser_of(np.asarray(points, np.float64))
    d = distances(jnp.asarray(nz.points(joints), dtype), jnp.asarray(np.asarray(radii) / nz.extent, dtype), seg,
                  jnp.asarray(nz.points(points), dtype))
    return np.asarray(d, np.float64) * nz.extent
