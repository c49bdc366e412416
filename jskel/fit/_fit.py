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

from .. import frusta
from ..frusta import ELLIPSE_MARGIN
from . import _normal, _solvers
from ._config import EstimateConfig, FitFile, PointsConfig, SolverConfig
from ._distance import (Segments, checked_distances, culling_exact, distances_of, geometry, margins_of,
                        plane_margins, sample_surface, segments_of)


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
    j, r, p, _ = frusta.skeleton_arrays(sk)
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


def mst_skeleton(points: np.ndarray, voxel: float, segment: float, prune: float = 3.0):
    """A branching skeleton: a minimum spanning tree over occupied voxels' centroids (voxel
    edge ``voxel`` x extent; voxels with a single point, such as lone outliers, make no node),
    twigs shorter than ``prune`` voxel edges cut off (repeatedly), rooted at one end of its
    longest path and simplified to joints about ``segment`` x extent apart along each branch
    (branch points and tips kept); each radius is the median distance of its voxel's points
    from the local axis. Limits: voxels must be wider than the tubes (so a centroid lies near
    the axis) and narrower than the gaps between branches (or branches fuse); branches shorter
    than ``prune`` voxels are lost with the twigs."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree

    ext = float(np.max(np.ptp(points, axis=0))) or 1.0
    v = voxel * ext
    keys = np.floor((points - points.min(0)) / v).astype(np.int64)
    uniq, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    cen = np.zeros((len(uniq), 3))
    np.add.at(cen, inv, points)
    cen /= counts[:, None]
    idx = np.nonzero(counts >= 2)[0]
    if len(idx) < 2:
        raise ValueError(f"init.estimate.voxel: {voxel} leaves fewer than 2 voxels holding 2 points or more")
    cen, kk = cen[idx], uniq[idx]
    n = len(idx)
    d = np.abs(kk[:, None, :] - kk[None, :, :]).max(-1)
    ii, jj = np.nonzero((d <= 1) & (np.arange(n)[:, None] < np.arange(n)[None, :]))
    w = np.linalg.norm(cen[ii] - cen[jj], axis=1) + 1e-12
    t = minimum_spanning_tree(coo_matrix((w, (ii, jj)), shape=(n, n)).tocsr()).tocoo()
    adj = {i: set() for i in range(n)}
    for a, b in zip(t.row, t.col):
        adj[int(a)].add(int(b))
        adj[int(b)].add(int(a))
    # keep the largest connected piece (a forest when voxels of two parts are not neighbours)
    seen, best = set(), []
    for s0 in range(n):
        if s0 in seen:
            continue
        comp, stack = [], [s0]
        seen.add(s0)
        while stack:
            u = stack.pop()
            comp.append(u)
            for x in adj[u] - seen:
                seen.add(x)
                stack.append(x)
        best = comp if len(comp) > len(best) else best
    alive = set(best)
    adj = {u: adj[u] & alive for u in alive}
    # cut twigs: a leaf's path to the first branch node, when shorter than prune voxels
    for _ in range(4):
        cut = set()
        for leaf in [u for u in adj if len(adj[u]) == 1]:
            path, prev, cur, length = [leaf], None, leaf, 0.0
            while True:
                nxt = [x for x in adj[cur] if x != prev]
                if len(nxt) != 1:
                    break
                length += float(np.linalg.norm(cen[nxt[0]] - cen[cur]))
                prev, cur = cur, nxt[0]
                if len(adj[cur]) != 2:
                    break
                path.append(cur)
            if len(adj[cur]) > 2 and length < prune * v:
                cut.update(path)
        if not cut:
            break
        for u in cut:
            for x in adj[u]:
                if x not in cut:
                    adj[x].discard(u)
        adj = {u: nb - cut for u, nb in adj.items() if u not in cut}

    def farthest(src):
        dist, order, par = {src: 0.0}, [src], {src: -1}
        for u in order:
            for x in adj[u]:
                if x not in dist:
                    dist[x] = dist[u] + float(np.linalg.norm(cen[x] - cen[u]))
                    par[x] = u
                    order.append(x)
        return max(dist, key=dist.get), order, par

    root, _, _ = farthest(next(iter(adj)))
    _, order, pred = farthest(root)
    deg = {u: len(adj[u]) for u in adj}
    seglen = segment * ext
    newpar, acc, anchor = {root: -1}, {root: 0.0}, {root: root}
    keep = [root]
    for node in order[1:]:
        p = pred[node]
        dd = acc[p] + float(np.linalg.norm(cen[node] - cen[p]))
        if deg[node] != 2 or dd >= seglen or deg[p] > 2:
            keep.append(node)
            newpar[node] = anchor[p]
            anchor[node], acc[node] = node, 0.0
        else:
            anchor[node], acc[node] = anchor[p], dd
    pos = {k: i for i, k in enumerate(keep)}
    joints = cen[keep]
    parents = np.array([-1 if newpar[k] < 0 else pos[newpar[k]] for k in keep])
    radii = np.zeros(len(keep))
    for i, k in enumerate(keep):
        q = points[inv == idx[k]] - cen[k]
        child = np.nonzero(parents == i)[0]
        nb = joints[parents[i]] if parents[i] >= 0 else (joints[child[0]] if len(child) else cen[k] + [0, 1, 0])
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
        j, r, p = (pca_chain(points, est.segments) if est.method == "pca_chain" else mst_skeleton(points, est.voxel, est.segment, est.prune))
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
    validity: float
    candidates: int


VALID_MARGIN = 2.0 * ELLIPSE_MARGIN  # the penalty starts where |n . m| - sin(half-angle) falls below this


def problem_of(seg: Segments, s: SolverConfig) -> Problem:
    triples = tuple((int(seg.start[a]), int(seg.start[b]), int(seg.end[b])) for a, b in zip(seg.cont_a, seg.cont_b))
    return Problem(seg, triples, s.loss, float(s.scale), float(s.smoothness), float(s.min_radius), float(s.validity), int(s.candidates))


def radii_of(u, pr: Problem):
    return pr.min_radius + jax.nn.softplus(u)


def unpack(x):
    """The flat parameter vector (4J,) (jaxopt's least-squares solvers want one array) as
    joints (J,3) and the radius parameters u (J,)."""
    nj = x.shape[-1] // 4
    return x[..., : 3 * nj].reshape(x.shape[:-1] + (nj, 3)), x[..., 3 * nj :]


def penalty_rows(joints, g, pr: Problem):
    """(K, E) penalty residuals per continuation (K = len(pr.triples)): ``sqrt(smoothness)``
    times the joints' second difference (3 rows) and the plane-validity penalty of its two
    segments (2 rows), each present when its weight is positive. A row depends only on the
    two segments' joints (``_normal`` relies on it)."""
    parts = []
    if pr.smoothness > 0 and pr.triples:
        t = np.asarray(pr.triples)
        parts.append(jnp.sqrt(pr.smoothness) * (joints[t[:, 0]] - 2.0 * joints[t[:, 1]] + joints[t[:, 2]]))
    if pr.validity > 0 and pr.triples:
        # keep every shared cutting plane cutting both its cones in ellipses (the geometry the
        # renderer and its bounds assume); an invalid plane leaves an unbounded piece that can
        # claim far outliers and so lower the loss below the truth's (see plane_margins)
        v = margins_of(g, pr.seg)
        parts.append(jnp.sqrt(pr.validity) * jnp.maximum(VALID_MARGIN - v, 0.0) / VALID_MARGIN)
    if not parts:
        return jnp.zeros((len(pr.triples), 0), joints.dtype)
    return jnp.concatenate(parts, -1)


def residuals(x, points, pr: Problem):
    """Robust point residuals (N,), then the penalty rows (:func:`penalty_rows`), in normalised units."""
    joints, u = unpack(x)
    g = geometry(joints, radii_of(u, pr), pr.seg)  # once, for the distances and the plane margins
    d = distances_of(g, pr.seg, points, pr.candidates)[0]
    r = _solvers.robust_residuals(d, pr.loss, pr.scale)
    return jnp.concatenate([r, penalty_rows(joints, g, pr).reshape(-1)])


def normal_equations(x, points, pr: Problem):
    """(r, J^T J, J^T r) of :func:`residuals` at ``x``, assembled from the problem's sparsity
    (``_normal``): no dense Jacobian, so LM and Gauss-Newton fit long chains in memory."""
    def model(x):
        joints, u = unpack(x)
        g = geometry(joints, radii_of(u, pr), pr.seg)
        return g, penalty_rows(joints, g, pr)

    return _normal.normal_equations(x, points, model, pr.seg, x.shape[-1] // 4, pr.candidates,
                                    lambda d: _solvers.robust_residuals(d, pr.loss, pr.scale))


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
    """A fitted skeleton in world units, with the loss after each iteration, iterations, whether the stopping rule was met, seconds (compile apart), the solver's final error and the restarts' losses."""

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


# Jacobian entries (residuals x unknowns) from which ``solver.jacobian: auto`` assembles the
# sparse normal equations. In the fitting benchmark (README, docs/bench_fit_*cpu.jsonl) LM took
# the same steps either way, 3.04 s dense / 1.22 s sparse at 10,000 points x 24 unknowns and
# 90.7 / 1.70 s at 10,000 x 204, and the dense form ran out of 24 GB at 10,000 x 2,004; at
# 1,000 x 24 (below the threshold) jaxopt's dense form takes 0.94 s
SPARSE_FROM = 1 << 17


def uses_sparse(s: SolverConfig, n_res: int, n_par: int) -> bool:
    """Whether LM / Gauss-Newton run on the sparse normal equations (``solver.jacobian``)."""
    if s.name not in ("lm", "gauss_newton"):
        return False
    return s.jacobian == "sparse" or (s.jacobian == "auto" and n_res * n_par >= SPARSE_FROM)


def _steppers(name, pr: Problem, s: SolverConfig, n_res: int, n_par: int):
    normal = (lambda x, p: normal_equations(x, p, pr)) if uses_sparse(s, n_res, n_par) else None
    return _solvers.make(name, lambda x, p: residuals(x, p, pr), lambda x, p: loss(x, p, pr), s.maxiter, s.tol, s.learning_rate,
                         dense=n_res * n_par <= DENSE_JACOBIAN_MAX, normal=normal)


def _typed_state(step, x0, args):
    """The solver's initial state with the dtypes an update returns (jaxopt's first update
    turns an int counter into a float), so one executable serves every iteration."""
    st0 = step.init(x0, *args)
    shapes = jax.eval_shape(lambda x, st: step.update(x, st, *args), x0, st0)[1]
    return jax.tree_util.tree_map(lambda a, sh: jnp.asarray(a, sh.dtype), st0, shapes)


# solvers whose batches run one fit after another (``lax.map``) instead of in lockstep
# (``vmap``): L-BFGS's line search is a while loop inside every iteration, and in lockstep each
# iteration waits for the batch's slowest search (CPU, 2 cores: 0.36 fits/s alone, 0.09-0.12
# fits/s in vmapped batches of 8 and 32)
SEQUENTIAL_BATCH = ("lbfgs",)


def over_batch(name: str, fn):
    """``fn`` mapped over a leading batch axis: ``vmap`` for most solvers, ``lax.map`` (one
    compiled loop, fits in turn) for those in :data:`SEQUENTIAL_BATCH`."""
    if name in SEQUENTIAL_BATCH:
        return lambda *xs: jax.lax.map(lambda a: fn(*a), xs)
    return jax.vmap(fn)


def run_to_end(step, pr: Problem, s: SolverConfig, x0, points):
    """One fit as a single ``while_loop`` with the stepping loop's stopping rule (the solver's
    criterion, or ``patience`` iterations in a row whose loss fell by less than ``ftol``);
    ``vmap`` of it fits many problems in one call. Returns (x, iterations, final loss)."""
    st0 = _typed_state(step, x0, (points,))
    l0 = loss(x0, points, pr)

    def cond(c):
        x, st, it, prev, stalled = c
        return (it < s.maxiter) & (step.error(st) > s.tol) & (stalled < s.patience)

    def body(c):
        x, st, it, prev, stalled = c
        x, st = step.update(x, st, points)
        cur = loss(x, points, pr)
        stalled = jnp.where(prev - cur <= s.ftol * jnp.abs(prev), stalled + 1, 0)
        return x, st, it + 1, cur, stalled

    x, _, it, cur, _ = jax.lax.while_loop(cond, body, (x0, st0, jnp.int32(0), l0, jnp.int32(0)))
    return x, it, cur


def fit_points(points: np.ndarray, joints0, radii0, parents, s: SolverConfig, dtype=np.float32, seed: int = 1,
               perturb: float = 0.0) -> FitResult:
    """Fit a skeleton of ``parents``' topology to ``points`` from (joints0, radii0): the
    stepping loop records the loss after every iteration; with ``s.restarts > 1`` that many
    starts (the given one and perturbed copies) are first solved in one call (:func:`over_batch`) and
    the best is stepped again for its loss curve (one more fit, counted in ``seconds``)."""
    seg = segments_of(joints0, radii0, parents, "init.skeleton")
    n_par = 4 * len(joints0)
    if len(points) < n_par:
        raise ValueError(f"points: {len(points)} points for {n_par} unknowns (4 per joint of {len(joints0)}); need at least as many points")
    pr = problem_of(seg, s)
    nz = normaliser_of(points)
    pts = jnp.asarray(nz.points(points), dtype)
    cast = lambda x: jnp.asarray(x, dtype)  # noqa: E731
    step = _steppers(s.name, pr, s, len(points) + 5 * len(pr.triples), n_par)
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
        xs, _, ls = jax.jit(over_batch(s.name, lambda x: run_to_end(step, pr, s, x, pts)))(xb)
        ls = np.asarray(ls)
        restart_losses = [float(v) for v in ls]
        best = int(np.nanargmin(ls))
        x0 = xb[best]  # stepped again from the best start, for its loss curve
    lossf = jax.jit(lambda x: loss(x, pts, pr))
    t0 = time.perf_counter()
    st0 = _typed_state(step, x0, (pts,))
    upd = jax.jit(lambda x, st: step.update(x, st, pts)).lower(x0, st0).compile()
    compile_s = time.perf_counter() - t0
    x, st = x0, st0
    history = [float(lossf(x))]
    converged = False
    it = 0
    stalled = 0
    t_loop = time.perf_counter()
    for it in range(1, s.maxiter + 1):  # host loop over iterations: one compiled update each
        x, st = upd(x, st)
        history.append(float(lossf(x)))
        if s.max_seconds is not None and time.perf_counter() - t_loop > s.max_seconds:
            break  # not converged: the time budget ran out (FitResult.converged says so)
        if float(step.error(st)) <= s.tol:
            converged = True
            break
        # the distance is piecewise smooth (which segment is nearest, rims), so the gradient
        # need not vanish at the optimum: also stop once the loss has stopped falling
        stalled = stalled + 1 if history[-2] - history[-1] <= s.ftol * abs(history[-2]) else 0
        if stalled >= s.patience:
            converged = True
            break
    seconds = time.perf_counter() - t_all - compile_s
    if not np.all(np.isfinite(np.asarray(x))) or not np.isfinite(history[-1]):
        raise ValueError(f"solver.name: {s.name} diverged to a non-finite loss after {it} iterations (try another solver or a smaller learning_rate)")
    if history[-1] > history[0]:  # a finite divergence (Gauss-Newton ran to joints of 1e25 on a 50-segment chain)
        raise ValueError(f"solver.name: {s.name} diverged: the loss rose from {history[0]:.4g} to {history[-1]:.4g} in {it} iterations "
                         "(try lm, a smaller learning_rate or more points)")
    j, r = nz.world(x, pr)
    return FitResult(j, r, np.asarray(parents), history, it, converged, seconds, compile_s, float(step.error(st)), s.restarts, restart_losses)


def fit_many(clouds, joints0, radii0, parents, s: SolverConfig, dtype=np.float32):
    """Fit one topology to B clouds at once (B, N, 3), each from its own start (B, J, 3) and
    (B, J) or one shared start: every cloud is normalised on the host, then the solver's whole
    run is mapped over the batch in one compiled call (:func:`over_batch`: in lockstep under
    ``vmap``, the batch running until its slowest fit stops, or for L-BFGS one after another).
    Returns (joints (B,J,3), radii (B,J), final losses (B,), seconds, compile seconds)."""
    clouds = np.asarray(clouds, np.float64)
    b = clouds.shape[0]
    j0 = np.broadcast_to(np.asarray(joints0, np.float64), (b,) + np.shape(joints0)[-2:])
    r0 = np.broadcast_to(np.asarray(radii0, np.float64), (b,) + np.shape(radii0)[-1:])
    seg = segments_of(j0[0], r0[0], parents, "init.skeleton")
    pr = problem_of(seg, s)
    nzs = [normaliser_of(c) for c in clouds]
    pts = jnp.asarray(np.stack([nz.points(c) for nz, c in zip(nzs, clouds)]), dtype)
    x0 = jnp.asarray(np.stack([nz.start(j, r, pr) for nz, j, r in zip(nzs, j0, r0)]), dtype)
    step = _steppers(s.name, pr, s, clouds.shape[1] + 5 * len(pr.triples), x0.shape[-1])
    solve = jax.jit(over_batch(s.name, lambda x, p: run_to_end(step, pr, s, x, p)[0]))
    t0 = time.perf_counter()
    solve = solve.lower(x0, pts).compile()
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    xs = solve(x0, pts)
    xs.block_until_ready()
    seconds = time.perf_counter() - t0
    losses = np.asarray(jax.vmap(lambda x, p: loss(x, p, pr))(xs, pts))
    out = [nz.world(x, pr) for nz, x in zip(nzs, np.asarray(xs))]
    return np.stack([o[0] for o in out]), np.stack([o[1] for o in out]), losses, seconds, compile_s


def point_distances(points, joints, radii, parents, dtype=np.float32) -> np.ndarray:
    """Signed distances of ``points`` to a skeleton's surface, in world units (NumPy)."""
    seg = segments_of(joints, radii, parents, "skeleton")
    nz = normaliser_of(np.asarray(points, np.float64))
    d = checked_distances(jnp.asarray(nz.points(joints), dtype), jnp.asarray(np.asarray(radii) / nz.extent, dtype), seg,
                          jnp.asarray(nz.points(points), dtype))
    return np.asarray(d, np.float64) * nz.extent


def culling_exact_fraction(points, joints, radii, parents, candidates: int) -> float:
    """Fraction of ``points`` whose distance over their ``candidates`` nearest segments is
    certainly their distance over all segments (``culling_exact``), at this skeleton."""
    seg = segments_of(joints, radii, parents, "skeleton")
    nz = normaliser_of(np.asarray(points, np.float64))
    ok = culling_exact(jnp.asarray(nz.points(joints), jnp.float32), jnp.asarray(np.asarray(radii) / nz.extent, jnp.float32), seg,
                       jnp.asarray(nz.points(points), jnp.float32), candidates)
    return float(np.mean(np.asarray(ok)))


def plane_margin_min(joints, radii, parents) -> float | None:
    """The smallest ``plane_margins`` value of a skeleton (None without shared planes)."""
    seg = segments_of(joints, radii, parents, "skeleton")
    if not len(seg.cont_b):
        return None
    return float(np.min(np.asarray(plane_margins(jnp.asarray(joints, jnp.float32), jnp.asarray(radii, jnp.float32), seg))))


# ----------------------------------------------------------------------------- the command


def framing_camera(joints, radii, width: int = 480, height: int = 360, fov: float = 40.0) -> dict:
    """A camera section that frames a skeleton (looking from +z, a little above and right)."""
    lo = (joints - radii[:, None]).min(0)
    hi = (joints + radii[:, None]).max(0)
    c = 0.5 * (lo + hi)
    rad = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
    d = np.array([0.5, 0.35, 1.0])
    d /= np.linalg.norm(d)
    dist = 1.15 * rad / np.tan(np.radians(fov) / 2)
    eye = c + d * dist
    return {"eye": [float(x) for x in eye], "target": [float(x) for x in c], "up": [0.0, 1.0, 0.0], "fov_deg": fov,
            "width": width, "height": height}


def residual_stats(d: np.ndarray, inlier: float) -> dict:
    a = np.abs(d)
    return {"mean_abs": float(a.mean()), "rms": float(np.sqrt(np.mean(d * d))), "median_abs": float(np.median(a)),
            "p95_abs": float(np.percentile(a, 95)), "max_abs": float(a.max()), "inlier_threshold": inlier,
            "inlier_fraction": float(np.mean(a <= inlier))}


def plot_fit(path: Path, res: FitResult, points: np.ndarray, d: np.ndarray, title: str):
    """Loss over iterations, the residual histogram, and the points (projected on the cloud's
    two principal axes) coloured by |residual| with the fitted skeleton drawn over them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(14, 4.2))
    ax[0].semilogy(np.arange(len(res.history)), res.history)
    ax[0].set_xlabel("iteration")
    ax[0].set_ylabel("loss (normalised units)")
    ax[0].set_title("loss")
    ax[1].hist(d, bins=80, color="#4477aa")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("signed distance to the fitted surface (world units)")
    ax[1].set_title("residuals")
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    pp = (points - c) @ vt[:2].T
    jj = (res.joints - c) @ vt[:2].T
    sc = ax[2].scatter(pp[:, 0], pp[:, 1], c=np.abs(d), s=2, cmap="viridis", vmax=np.percentile(np.abs(d), 95))
    for i, p in enumerate(res.parents):
        if p >= 0:
            ax[2].plot([jj[p, 0], jj[i, 0]], [jj[p, 1], jj[i, 1]], "r-", lw=1.5)
    ax[2].plot(jj[:, 0], jj[:, 1], "r.", ms=6)
    ax[2].set_aspect("equal")
    ax[2].set_title("points by |residual|, fitted skeleton (red)")
    fig.colorbar(sc, ax=ax[2], shrink=0.8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_fit(cfg: FitFile, out: Path, base: Path | None = None) -> dict:
    """Run a fit file: read or synthesise the points, start, solve; write ``fitted.yaml`` (an
    experiment ``jskel render`` renders), ``fit.json`` and ``fit.png``. Returns fit.json's dict."""
    import json

    import yaml

    dtype = np.float64 if cfg.dtype == "float64" else np.float32
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        raise ValueError("dtype: float64 needs jax_enable_x64 (the CLI's --x64 switches it on)")
    points, pinfo, truth = load_points(cfg.points, base)
    j0, r0, parents, how = starting_skeleton(cfg, points, truth)
    if cfg.init.perturb > 0:
        j0, r0 = perturbed(j0, r0, parents, cfg.init.perturb, np.random.default_rng(cfg.init.seed))
    res = fit_points(points, j0, r0, parents, cfg.solver, dtype, seed=cfg.init.seed, perturb=cfg.init.perturb)
    d = point_distances(points, res.joints, res.radii, res.parents, dtype)
    ext = float(np.max(np.ptp(points, axis=0)))
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    exp = {
        "name": f"{cfg.name}-fitted",
        "object": {"type": frusta.REPRESENTATION.name, "skeleton": {"joints": res.joints.tolist(), "radii": res.radii.tolist(),
                                                   "parents": [int(p) for p in res.parents]}},
        "camera": cfg.camera.model_dump(mode="json") if cfg.camera is not None else framing_camera(res.joints, res.radii),
    }
    (out / "fitted.yaml").write_text(f"# fitted by `jskel fit` ({cfg.solver.name}, {cfg.solver.loss} loss)\n" + yaml.safe_dump(exp, sort_keys=False))
    info = {
        "name": cfg.name,
        "solver": cfg.solver.model_dump(mode="json"),
        "start": how,
        "points": pinfo,
        "joints": len(res.joints),
        "segments": int(np.sum(res.parents >= 0)),
        "iterations": res.iterations,
        "converged": res.converged,
        "solver_error": res.error,
        "seconds": res.seconds,
        "compile_s": res.compile_s,
        "loss_start": res.history[0],
        "loss_final": res.history[-1],
        "history": res.history,
        "restarts": res.restarts,
        "restart_losses": res.restart_losses,
        "residuals": residual_stats(d, 3.0 * cfg.solver.scale * ext),
        # n . m - sin(half-angle) of the worst shared cutting plane (< 0: a piece is unbounded)
        "plane_margin_min": plane_margin_min(res.joints, res.radii, res.parents),
        "culling_exact_fraction": culling_exact_fraction(points, res.joints, res.radii, res.parents, cfg.solver.candidates),
        "dtype": cfg.dtype,
    }
    if truth is not None and len(truth[0]) == len(res.joints) and np.array_equal(truth[2], res.parents):
        length = pinfo["skeleton_length"]
        info["truth"] = {
            "joint_error_max": float(np.max(np.linalg.norm(res.joints - truth[0], axis=1))),
            "joint_error_max_of_length": float(np.max(np.linalg.norm(res.joints - truth[0], axis=1)) / length),
            "radius_error_max_rel": float(np.max(np.abs(res.radii / truth[1] - 1))),
        }
    from ..render import environment

    info.update({k: v for k, v in environment().items() if k in ("jax", "device", "jskel")})
    (out / "fit.json").write_text(json.dumps(info, indent=2) + "\n")
    plot_fit(out / "fit.png", res, points, d, f"{cfg.name}: {cfg.solver.name} ({cfg.solver.loss}), {len(points)} points, "
                                            f"{res.iterations} iterations, {res.seconds:.2f} s")
    return info
