"""Starting skeletons for a fit (issue 10): a straight chain along the cloud's principal axis
(:func:`pca_chain`), a branching skeleton from a spanning tree over occupied voxels
(:func:`mst_skeleton`), a given or the true skeleton, and perturbed copies of a start."""

from __future__ import annotations

import numpy as np

from ._config import EstimateConfig, FitFile
from ._points import skeleton_arrays


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
    ext = float(np.max(np.ptp(points, axis=0))) or 1.0
    v = voxel * ext
    cen, keys, inv, idx = _voxel_nodes(points, v)
    if len(idx) < 2:
        raise ValueError(f"init.estimate.voxel: {voxel} leaves fewer than 2 voxels holding 2 points or more")
    adj = _cut_twigs(_largest_piece(_spanning_tree(cen, keys)), cen, prune * v)
    keep, parents = _simplified(adj, cen, segment * ext)
    joints = cen[keep]
    return joints, _axis_radii(points, inv, idx[keep], joints, parents, 1e-3 * ext), parents


def _voxel_nodes(points, v: float):
    """Centroids (V,3) and integer keys (V,3) of the voxels of edge ``v`` holding 2 points or
    more, each point's voxel (N,) among all occupied voxels, and the kept voxels' indices (V,)."""
    keys = np.floor((points - points.min(0)) / v).astype(np.int64)
    uniq, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    cen = np.zeros((len(uniq), 3))
    np.add.at(cen, inv, points)
    cen /= counts[:, None]
    idx = np.nonzero(counts >= 2)[0]
    return cen[idx], uniq[idx], inv, idx


def _spanning_tree(cen, keys) -> dict:
    """Adjacency (node -> set of nodes) of the minimum spanning tree over the centroids, edges
    joining voxels that touch (faces, edges or corners), weighted by centroid distance."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree

    n = len(cen)
    d = np.abs(keys[:, None, :] - keys[None, :, :]).max(-1)
    ii, jj = np.nonzero((d <= 1) & (np.arange(n)[:, None] < np.arange(n)[None, :]))
    w = np.linalg.norm(cen[ii] - cen[jj], axis=1) + 1e-12
    t = minimum_spanning_tree(coo_matrix((w, (ii, jj)), shape=(n, n)).tocsr()).tocoo()
    adj = {i: set() for i in range(n)}
    for a, b in zip(t.row, t.col):
        adj[int(a)].add(int(b))
        adj[int(b)].add(int(a))
    return adj


def _largest_piece(adj: dict) -> dict:
    """The largest connected piece of a forest (voxels of two parts that are not neighbours)."""
    seen, best = set(), []
    for s0 in range(len(adj)):
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
    return {u: adj[u] & alive for u in alive}


def _cut_twigs(adj: dict, cen, reach: float) -> dict:
    """Twigs cut: a leaf's path to the first branch node, when shorter than ``reach`` (up to
    four rounds, as cutting one twig can leave another)."""
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
            if len(adj[cur]) > 2 and length < reach:
                cut.update(path)
        if not cut:
            break
        for u in cut:
            for x in adj[u]:
                if x not in cut:
                    adj[x].discard(u)
        adj = {u: nb - cut for u, nb in adj.items() if u not in cut}
    return adj


def _farthest(adj: dict, cen, src):
    """(farthest node from ``src`` along the tree, breadth-first order, predecessor of each)."""
    dist, order, par = {src: 0.0}, [src], {src: -1}
    for u in order:
        for x in adj[u]:
            if x not in dist:
                dist[x] = dist[u] + float(np.linalg.norm(cen[x] - cen[u]))
                par[x] = u
                order.append(x)
    return max(dist, key=dist.get), order, par


def _simplified(adj: dict, cen, seglen: float):
    """The tree rooted at one end of its longest path, reduced to the nodes kept as joints
    (the root, branch points, tips, and a node about every ``seglen`` along a branch): their
    node ids (K,) in breadth-first order and each one's parent among them (K,), -1 at the root."""
    root, _, _ = _farthest(adj, cen, next(iter(adj)))
    _, order, pred = _farthest(adj, cen, root)
    deg = {u: len(adj[u]) for u in adj}
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
    return keep, np.array([-1 if newpar[k] < 0 else pos[newpar[k]] for k in keep])


def _axis_radii(points, inv, voxels, joints, parents, floor: float):
    """Each joint's radius: the median distance of its voxel's points (``inv == voxels[i]``)
    from the axis towards its parent (or first child), at least ``floor``."""
    radii = np.zeros(len(joints))
    for i, vox in enumerate(voxels):
        q = points[inv == vox] - joints[i]
        child = np.nonzero(parents == i)[0]
        nb = joints[parents[i]] if parents[i] >= 0 else (joints[child[0]] if len(child) else joints[i] + [0, 1, 0])
        ax = nb - joints[i]
        ax /= np.linalg.norm(ax) or 1.0
        radii[i] = max(float(np.median(np.linalg.norm(q - np.outer(q @ ax, ax), axis=1))) if len(q) else 0.0, floor)
    return radii


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
    """(joints, radii, parents, how) of the fit's start: ``init.skeleton`` when given, else
    estimated from the points (``init.estimate``, or by default when there is no truth), else
    the synthetic cloud's true skeleton."""
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
