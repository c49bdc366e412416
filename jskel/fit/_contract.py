"""A starting skeleton whose topology comes from the points: Laplacian-based contraction (Cao,
Tagliasacchi, Olson, Zhang and Su 2010, "Point Cloud Skeletons via Laplacian-Based
Contraction", Proc. Shape Modeling International), in NumPy and SciPy.

Sec. 3 (contraction): the points P are moved to P' minimising

    || W_L L P' ||^2 + sum_i W_H,i^2 || P'_i - P_i ||^2                        (Eq. 1)

where L is a Laplacian over each point's neighbourhood: the term W_L L P' pulls every point
towards its neighbours' mean (the surface shrinks along its normals, not along the tube's
axis, where the neighbourhood is balanced), W_H keeps it near where it was. The paper builds L
from the one-ring of a local Delaunay triangulation with cotangent weights; here L is the
symmetric umbrella of the ``neighbours`` nearest points (uniform weights), a simplification
that contracts the same way on tubes sampled about evenly (the paper's Sec. 3.1 notes both).
Eq. 1 is solved through its normal equations, (W_L^2 L^T L + W_H^2) P' = W_H^2 P, one sparse
factorisation a step. Weights as Sec. 3.2, W_L growing by s_L = 3 a step up to 2048 W_L^0
and W_H,i = sqrt(A_i^0 / A_i^t) (A_i: point i's neighbourhood area, here the mean squared
distance to its neighbours) keeping points whose neighbourhood has already collapsed in place;
but W_L^0 = 1, not the paper's 10^-3 sqrt(A): the umbrella's rows are means of differences of
positions, the same units as W_H's term, so no scale enters. It stops when the mean
neighbourhood area has shrunk below 10^-6 of its start (the paper's criterion), or, as a tube's
neighbourhoods stay spread along its axis, when a step shrinks it by less than 5 % (the
surface has collapsed onto curves; that step is not kept: further steps only pull the curves'
ends in, measured on a branching tree), or once the neighbourhoods have collapsed onto curves
(``LINEAR_STOP``: the area keeps shrinking as the curves shorten), or after ``steps`` steps.

Sec. 4 (topology): the contracted points are grouped by farthest-point sampling in balls of
radius ``ball`` x extent; two groups are joined when a point of one has a neighbour (in the
original cloud's neighbourhoods) in the other. The paper collapses the resulting graph's
triangles edge by edge; here the minimum spanning tree of the group graph (weighted by the
groups' distance) is taken, pieces it leaves apart joined to the largest where they are near
(``_trees.joined_pieces``), its twigs shorter than ``prune`` balls or ending inside the tube they leave cut, branch nodes less than
two balls apart merged (:func:`merged_branches`: a junction of four branches is split into two
of three by the balls) and its chains simplified to joints ``segment`` x extent apart
(``_trees``, shared with the ``mst`` start). A joint is its group's contracted centroid (on the
medial axis); its radius the median distance of its group's original points from the local
axis (the points' local spread).

Outliers are dropped first: points whose mean distance to their ``neighbours`` nearest is over
3 times the cloud's median (statistical outlier removal). Large clouds are then reduced to
``max_points`` by a voxel grid (one representative a cell),
the contraction's cost being a sparse factorisation of that size a step; every original point
then joins the group of its nearest representative.
"""

from __future__ import annotations

import numpy as np

#: W_L's start, its growth a step (Sec. 3.2's s_L) and its cap (2048 W_L^0, Sec. 3.2)
WL_START, WL_GROWTH, WL_MAX = 1.0, 3.0, 2048.0
AREA_STOP = 1e-6  # stop when the mean neighbourhood area is below this fraction of its start
PLATEAU = 0.05  # or when a step shrinks it by less than this fraction: the surface has collapsed onto curves
#: or when the neighbourhoods are curves: the median point's neighbours spread along one direction
#: with this share of their variance (``linearity``). Past it, W_L pulls the points along the
#: curves (their ends in, branches towards their junctions) and off the tubes' axes: on the
#: grown tree of 50 segments the contracted points' median distance from the true axes is under
#: half a radius at that step and over a radius where the area's plateau stops
#: (tests/test_fit_contract.py)
LINEAR_STOP = 0.99


def reduced(points: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(representatives (M,3), each point's representative (N,)): a voxel grid whose cells hold
    at most about ``max_points`` occupied cells, one representative a cell (its centroid)."""
    n = len(points)
    if n <= max_points:
        return points, np.arange(n)
    ext = float(np.max(np.ptp(points, axis=0)))
    v = ext / 8.0
    for _ in range(40):  # shrink the cell until enough cells are occupied
        keys = np.floor((points - points.min(0)) / v).astype(np.int64)
        uniq, inv = np.unique(keys, axis=0, return_inverse=True)
        if len(uniq) >= max_points // 2 or v < 1e-9 * ext:
            break
        v *= 0.7
    inv = inv.reshape(-1)
    cen = np.zeros((len(uniq), 3))
    np.add.at(cen, inv, points)
    cen /= np.bincount(inv, minlength=len(uniq))[:, None]
    return cen, inv


def sparse_points(points: np.ndarray, k: int, factor: float = 3.0) -> np.ndarray:
    """Whether each point is an outlier (M,): its mean distance to its ``k`` nearest points is
    more than ``factor`` times the median of that over the cloud (statistical outlier removal:
    a stray point's neighbourhood is far away, and contracting it would pull a false branch)."""
    from scipy.spatial import cKDTree

    k = min(k, len(points) - 1)
    dist, _ = cKDTree(points).query(points, k + 1)
    spread = dist[:, 1:].mean(1)
    return spread > factor * np.median(spread)


def neighbourhoods(points: np.ndarray, k: int) -> np.ndarray:
    """(M, k) indices of each point's ``k`` nearest other points."""
    from scipy.spatial import cKDTree

    k = min(k, len(points) - 1)
    _, idx = cKDTree(points).query(points, k + 1)
    return idx[:, 1:]


def umbrella(nbr: np.ndarray):
    """The symmetric umbrella Laplacian (M, M) of the neighbourhood graph: L_ij = -1/deg_i for
    each neighbour j (either way), L_ii = 1; rows sum to 0."""
    from scipy.sparse import coo_matrix, diags

    m = len(nbr)
    i = np.repeat(np.arange(m), nbr.shape[1])
    j = nbr.reshape(-1)
    a = coo_matrix((np.ones(len(i)), (i, j)), shape=(m, m)).tocsr()
    a = ((a + a.T) > 0).astype(np.float64)
    deg = np.asarray(a.sum(1)).reshape(-1)
    return diags(np.ones(m)) - diags(1.0 / deg) @ a


def _areas(p: np.ndarray, nbr: np.ndarray) -> np.ndarray:
    """Each point's neighbourhood area proxy: the mean squared distance to its neighbours."""
    return np.mean(np.sum((p[nbr] - p[:, None, :]) ** 2, -1), 1)


def contract(points: np.ndarray, nbr: np.ndarray, steps: int) -> tuple[np.ndarray, int]:
    """(contracted points (M,3), steps taken): Eq. 1 solved ``steps`` times at most with the
    weights of Sec. 3.2 (module docstring)."""
    from scipy.sparse import diags
    from scipy.sparse.linalg import splu

    lap = umbrella(nbr)
    ltl = (lap.T @ lap).tocsc()
    a0 = _areas(points, nbr)
    wl = WL_START
    p = points.copy()
    wh = np.ones(len(p))
    done, prev = 0, a0.mean()
    for done in range(1, steps + 1):
        mat = (wl * wl) * ltl + diags(wh * wh)
        step = splu(mat.tocsc()).solve((wh * wh)[:, None] * p)
        a = _areas(step, nbr)
        if done > 1 and a.mean() > (1.0 - PLATEAU) * prev:  # collapsed: further steps pull along the curves
            done -= 1
            break
        p, prev = step, a.mean()
        if a.mean() < AREA_STOP * a0.mean() or linearity(p, nbr) >= LINEAR_STOP:
            break
        wl = min(wl * WL_GROWTH, WL_MAX * WL_START)
        wh = np.sqrt(a0 / np.maximum(a, 1e-30 * a0.mean()))
        wh = np.minimum(wh, 1e4)  # a collapsed neighbourhood pins its points, within floats
    return p, done


def linearity(p: np.ndarray, nbr: np.ndarray) -> float:
    """The median over the points of the share of their neighbourhood's spread along its main
    direction (the largest eigenvalue of the neighbours' covariance over the trace): 1/3 on a
    blob, about 1/2 on a surface, 1 on a curve."""
    nb = p[nbr] - p[nbr].mean(1, keepdims=True)
    ev = np.linalg.eigvalsh(np.einsum("mki,mkj->mij", nb, nb))
    return float(np.median(ev[:, 2] / np.maximum(ev.sum(1), 1e-300)))


def groups(contracted: np.ndarray, radius: float) -> np.ndarray:
    """Each point's group (M,), by farthest-point sampling in balls of ``radius``: the first
    ungrouped point (the farthest from every group so far) claims every ungrouped point within
    ``radius`` of it."""
    from scipy.spatial import cKDTree

    m = len(contracted)
    tree = cKDTree(contracted)
    label = np.full(m, -1)
    dist = np.full(m, np.inf)
    cur, g = 0, 0
    while True:
        near = np.asarray(tree.query_ball_point(contracted[cur], radius), np.int64)
        near = near[label[near] < 0]
        label[near] = g
        label[cur] = g
        dist = np.minimum(dist, np.linalg.norm(contracted - contracted[cur], axis=1))
        dist[label >= 0] = -1.0
        g += 1
        if np.all(label >= 0):
            return label
        cur = int(np.argmax(dist))


def merged_branches(adj: dict, cen: np.ndarray, reach: float) -> tuple[dict, np.ndarray]:
    """(adjacency, centroids): a tree whose branch nodes joined by a chain shorter than
    ``reach`` are merged into one at their midpoint (with the chain). Grouping in balls splits
    a junction of four or more branches into branch nodes of three a ball or two apart; the
    paper's edge collapse (Sec. 4) removes such short edges too."""
    adj = {u: set(nb) for u, nb in adj.items()}
    cen = cen.copy()
    changed = True
    while changed:
        changed = False
        for u in list(adj):
            if u not in adj or len(adj[u]) < 3:
                continue
            for first in list(adj[u]):
                path, prev, cur = [], u, first
                length = float(np.linalg.norm(cen[first] - cen[u]))
                while len(adj[cur]) == 2:
                    nxt = next(x for x in adj[cur] if x != prev)
                    path.append(cur)
                    length += float(np.linalg.norm(cen[nxt] - cen[cur]))
                    prev, cur = cur, nxt
                if len(adj[cur]) < 3 or cur == u or length >= reach:
                    continue
                gone = set(path) | {cur}
                for w in gone:
                    for x in adj.pop(w):
                        adj.get(x, set()).discard(w)
                        if x not in gone and x != u:
                            adj[u].add(x)
                            adj[x].add(u)
                cen[u] = 0.5 * (cen[u] + cen[cur])
                changed = True
                break
    return adj, cen


#: a piece of the groups' graph that its neighbourhoods leave apart from the largest is joined
#: to it when it holds at least this many groups and lies within this many balls of it (a branch
#: beyond a sparse stretch; an outlier's few groups stay out)
PIECE_GROUPS = 3
PIECE_REACH = 6.0
#: a twig is cut when its end lies within this many times the spread of the nearest group off
#: it (the median distance of that group's points from its contracted centre: about the tube's
#: radius there): it ends inside the tube it leaves
TWIG_RADII = 1.0


def contraction_skeleton(points: np.ndarray, neighbours: int, ball: float, segment: float, prune: float, max_points: int,
                         steps: int = 20):
    """(joints, radii, parents, info) of a skeleton estimated by Laplacian contraction (module
    docstring); ``ball``, ``segment`` and ``prune`` are fractions of the cloud's extent (prune:
    of balls). info: the contraction's steps, groups and the points it ran on."""
    from ._trees import axis_radii, cut_twigs, joined_pieces, simplified, spanning_tree_of

    stray = sparse_points(points, neighbours)
    kept_points = np.nonzero(~stray)[0]
    points = points[kept_points]
    ext = float(np.max(np.ptp(points, axis=0))) or 1.0
    reps, owner = reduced(points, max_points)
    if len(reps) < 4:
        raise ValueError(f"init.estimate: {len(reps)} points to contract; need at least 4")
    nbr = neighbourhoods(reps, neighbours)
    con, taken = contract(reps, nbr, steps)
    lab = groups(con, ball * ext)
    ng = int(lab.max()) + 1
    if ng < 2:
        raise ValueError(f"init.estimate.ball: {ball} groups every contracted point in one ball; make it smaller")
    cen = np.zeros((ng, 3))
    np.add.at(cen, lab, con)
    cen /= np.bincount(lab, minlength=ng)[:, None]
    # groups joined where a point of one has a neighbour in the other
    a, b = lab[np.repeat(np.arange(len(reps)), nbr.shape[1])], lab[nbr.reshape(-1)]
    pairs = np.unique(np.sort(np.column_stack([a, b])[a != b], axis=1), axis=0)
    # each group's spread: the median distance of its points from its contracted centre
    dist = np.linalg.norm(reps - cen[lab], axis=1)
    order = np.argsort(lab, kind="stable")
    starts = np.searchsorted(lab[order], np.arange(ng))
    spread = np.array([np.median(d) if len(d) else 0.0 for d in np.split(dist[order], starts[1:])])
    # pieces of at least PIECE_GROUPS groups within PIECE_REACH balls of the rest are joined to
    # it; a twig whose end lies within TWIG_RADII times the spread of the nearest group off it (a
    # bump of the tube's surface that the contraction left, not a branch) is cut
    adj = cut_twigs(joined_pieces(spanning_tree_of(cen, pairs), cen, PIECE_GROUPS, PIECE_REACH * ball * ext), cen, prune * ball * ext,
                    TWIG_RADII * spread)
    adj, cen = merged_branches(adj, cen, 2.0 * ball * ext)
    kept, parents = simplified(adj, cen, segment * ext)
    joints = cen[kept]
    point_group = lab[owner]  # each original point's group
    radii = axis_radii(points, point_group, np.asarray(kept), joints, parents, 1e-3 * ext)
    return joints, radii, parents, {"contraction_steps": taken, "contracted_points": len(reps), "groups": ng, "outliers": int(stray.sum())}
