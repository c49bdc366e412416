"""Starting skeletons for a fit (issue 10): a straight chain along the cloud's principal axis
(:func:`pca_chain`), a branching skeleton from a spanning tree over occupied voxels
(:func:`mst_skeleton`) or from the points contracted by their Laplacian (``_contract``, issue
53), a given or the true skeleton, and perturbed copies of a start."""

from __future__ import annotations

import numpy as np

from ._config import EstimateConfig, FitFile
from ._points import skeleton_arrays
from ._trees import axis_radii, cut_twigs, largest_piece, simplified, spanning_tree_of


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
    adj = cut_twigs(largest_piece(_spanning_tree(cen, keys)), cen, prune * v)
    keep, parents = simplified(adj, cen, segment * ext)
    joints = cen[keep]
    return joints, axis_radii(points, inv, idx[keep], joints, parents, 1e-3 * ext), parents


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
    n = len(cen)
    d = np.abs(keys[:, None, :] - keys[None, :, :]).max(-1)
    ii, jj = np.nonzero((d <= 1) & (np.arange(n)[:, None] < np.arange(n)[None, :]))
    return spanning_tree_of(cen, np.column_stack([ii, jj]))


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
        if est.method == "contraction":
            from ._contract import contraction_skeleton

            j, r, p, _ = contraction_skeleton(points, est.neighbours, est.ball, est.segment, est.prune, est.max_points)
        elif est.method == "pca_chain":
            j, r, p = pca_chain(points, est.segments)
        else:
            j, r, p = mst_skeleton(points, est.voxel, est.segment, est.prune)
        how = f"estimate:{est.method}"
    else:
        j, r, p = truth
        how = "truth"
    return j, r, p, how
