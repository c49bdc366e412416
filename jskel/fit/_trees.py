"""Trees over sampled nodes, shared by the starts that estimate a branching skeleton (``mst``
in ``_starts``, ``contraction`` in ``_contract``): a spanning tree's adjacency, its largest
piece, its twigs cut, its chains simplified to joints, each joint's radius from its points."""

from __future__ import annotations

import numpy as np


def spanning_tree_of(cen, pairs) -> dict:
    """Adjacency (node -> set of nodes) of the minimum spanning forest of the graph whose edges
    are ``pairs`` (E, 2) of distinct nodes, each once, weighted by the nodes' distance."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree

    n = len(cen)
    ii, jj = pairs[:, 0], pairs[:, 1]
    w = np.linalg.norm(cen[ii] - cen[jj], axis=1) + 1e-12
    t = minimum_spanning_tree(coo_matrix((w, (ii, jj)), shape=(n, n)).tocsr()).tocoo()
    adj = {i: set() for i in range(n)}
    for a, b in zip(t.row, t.col):
        adj[int(a)].add(int(b))
        adj[int(b)].add(int(a))
    return adj


def largest_piece(adj: dict) -> dict:
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


def joined_pieces(adj: dict, cen, min_nodes: int, reach: float) -> dict:
    """The largest connected piece of a forest with every other piece of at least
    ``min_nodes`` nodes joined to it by its shortest edge, where that edge is shorter than
    ``reach`` (nearest pieces first, so a piece may join through one joined before it); smaller
    or farther pieces are dropped, as :func:`largest_piece` drops them. A sampled surface
    whose neighbourhoods do not bridge a thin neck or a sparse stretch splits the graph of its
    contracted groups; keeping only the largest piece then loses the branch beyond the gap
    (a 9-group piece of a real neuron mesh in one of three subsamples), while an outlier's
    lone group stays out."""
    from scipy.spatial import cKDTree

    comp = np.full(len(adj), -1)
    pieces = []
    for s0 in range(len(adj)):
        if comp[s0] >= 0:
            continue
        members, stack = [], [s0]
        comp[s0] = len(pieces)
        while stack:
            u = stack.pop()
            members.append(u)
            for x in adj[u]:
                if comp[x] < 0:
                    comp[x] = len(pieces)
                    stack.append(x)
        pieces.append(members)
    main = max(range(len(pieces)), key=lambda k: len(pieces[k]))
    out = {u: set(adj[u]) for u in pieces[main]}
    waiting = [k for k in range(len(pieces)) if k != main and len(pieces[k]) >= min_nodes]
    while waiting:
        tree = cKDTree(cen[list(out)])
        nodes = list(out)
        best = None
        for k in waiting:  # each waiting piece's shortest edge to the joined nodes
            d, i = tree.query(cen[pieces[k]])
            j = int(np.argmin(d))
            if best is None or d[j] < best[0]:
                best = (float(d[j]), k, pieces[k][j], nodes[int(i[j])])
        dist, k, a, b = best
        if dist >= reach:
            break
        out.update({u: set(adj[u]) for u in pieces[k]})
        out[a].add(b)
        out[b].add(a)
        waiting.remove(k)
    return out


def cut_twigs(adj: dict, cen, reach: float, spread=None) -> dict:
    """Twigs cut: a leaf's path to the first branch node, when shorter than ``reach``, or, with
    ``spread`` (an array over the nodes: about the tube's radius there), when the leaf lies
    within the spread of the nearest node off its path: a twig that ends inside the tube it
    leaves is a bump of that tube's surface, not a branch (up to four rounds, as cutting one
    twig can leave another)."""
    from scipy.spatial import cKDTree

    for _ in range(4):
        cut = set()
        nodes = np.array(sorted(adj))
        tree = cKDTree(cen[nodes]) if spread is not None and len(nodes) > 1 else None
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
            if len(adj[cur]) <= 2:
                continue
            inside = False
            if tree is not None:
                k = min(len(nodes), len(path) + 1)
                dist, idx = tree.query(cen[leaf], k)
                mine = set(path)
                off = [(d, int(nodes[i])) for d, i in zip(np.atleast_1d(dist), np.atleast_1d(idx)) if int(nodes[i]) not in mine]
                inside = bool(off) and off[0][0] < spread[off[0][1]]
            if length < reach or inside:
                cut.update(path)
        if not cut:
            break
        for u in cut:
            for x in adj[u]:
                if x not in cut:
                    adj[x].discard(u)
        adj = {u: nb - cut for u, nb in adj.items() if u not in cut}
    return adj


def farthest(adj: dict, cen, src):
    """(farthest node from ``src`` along the tree, breadth-first order, predecessor of each)."""
    dist, order, par = {src: 0.0}, [src], {src: -1}
    for u in order:
        for x in adj[u]:
            if x not in dist:
                dist[x] = dist[u] + float(np.linalg.norm(cen[x] - cen[u]))
                par[x] = u
                order.append(x)
    return max(dist, key=dist.get), order, par


def simplified(adj: dict, cen, seglen: float):
    """The tree rooted at one end of its longest path, reduced to the nodes kept as joints
    (the root, branch points, tips, and a node about every ``seglen`` along a branch): their
    node ids (K,) in breadth-first order and each one's parent among them (K,), -1 at the root."""
    root, _, _ = farthest(adj, cen, next(iter(adj)))
    _, order, pred = farthest(adj, cen, root)
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


def axis_radii(points, inv, voxels, joints, parents, floor: float):
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
