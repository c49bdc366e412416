"""Topology edits between rounds of a fit (issue 53): the continuous solve keeps the skeleton's
topology, so a start with a branch too many, a joint too many or a bend too few stays wrong.
Between rounds (``edits.rounds``) the fitted skeleton is edited on the host, each edit logged:

* **prune**: a tip segment (its far joint has no child; the root counts when it has one child)
  that fewer than ``prune_points`` points are nearest to, or whose points the other segments
  explain within one robust scale as well (root mean square), is removed with its tip joint: a
  branch without support (the fit lays such a twig along another segment's surface, where it
  takes points it does not need); and a spur, a tip branch (from a tip up to the first joint
  with another child) whose tip lies within ``spur_radii`` radii of the axis of another segment
  at that joint, is removed whole: it ends inside the tube it leaves, a bump of that tube's
  surface (the 50-segment grown tree's fit kept such twigs at its thick base, their tips inside
  the trunk's tube). A test by the spur's length against the joint's radius instead also cut
  real branches of the L-system tree's crown, where the start's stubs of crossing tubes are
  short and a junction's radius swells (fewer of its branch points matched, in development
  runs of that rule, which is not kept);
* **merge**: a neck, a joint with a parent and a child whose radius is below ``neck_ratio`` of
  every neighbour's, is merged into its nearest neighbour (its other neighbours joined to that
  one): the fit hides a wrong connection inside the tubes around it by shrinking the joint
  between them, at little cost to the loss. In development runs on the 5-segment grown tree of
  ``experiments/bench_fit_trees.yaml``, fits of some draws of its points joined the side branch
  to the trunk above the true junction through such a joint, which moved the junction and left
  the radii around it far from the truth's (``fit_trees.draws`` measures it); then a segment
  shorter than ``merge_length`` x the cloud's extent, or one whose far joint has at most one
  child shorter than ``merge_radii`` times its mean radius (a frustum shorter than its width,
  whose cutting planes turn with every small move of its joints), is collapsed into its parent
  joint (its children move to the parent, placed at the midpoint); a joint with one parent and
  one child whose two segments turn by less than ``merge_angle`` degrees is removed
  (the two segments become one) where the one segment leaves their points' RMS distance
  within 5 % of the two's (``STRAIGHT``);
* **split**: a segment whose nearest points lie, root mean square, more than ``split_residual``
  robust scales (``solver.scale`` x extent) from it gets a joint at its middle: a bend or a
  branch the start did not have; the next round's fit places it.

An edit changes segments and may move a joint; no later edit of the same round uses either,
so each round's edits are independent of their order. Every comparison of distances uses
their root mean square clipped at 5 robust scales, so outliers weigh no more than that. A point's nearest segment is found on the host by its distance to each segment's cone
(|distance to the axis - radius there|), to the end's disc beyond an end and at most to the
end's plane inside: each segment as if capped at both ends, without the shared cutting
planes (a classification, not the fit's distance). Joints are renumbered breadth first from the root after every round, so parents
precede their children."""

from __future__ import annotations

import numpy as np

#: a straight joint is merged where one segment leaves its points' RMS distance within 5 % of
#: the two segments' (a joint that a true bend needs costs more: an 11-degree bend of the test
#: chain under 1 % noise came out about 20 % worse, and one scale more would have merged it)
STRAIGHT = 1.05


#: segments from which :func:`nearest_segments` scores each point's ``NEAR`` nearest segment
#: centres first (certified, else all); below it every segment
NEAR_FROM = 64
NEAR = 16


def _cone_distances(x, a, ab, ll, length, ra, rb):
    """Classification distances (module docstring) of points ``x`` (B, 1, 3) to segments given
    by their parent joint ``a`` and axis ``ab`` (..., 3), squared and plain lengths and end
    radii (...), broadcast against each other: (1, S) for every segment, (B, K) for each
    point's own candidates; float64."""
    x = x - a  # (B, S, 3)
    u = np.sum(x * ab, -1) / ll  # along the axis, 0 at a, 1 at b
    rho = np.linalg.norm(x - u[..., None] * ab, axis=-1)
    t = np.clip(u, 0.0, 1.0)
    side = np.abs(rho - (ra + t * (rb - ra)))
    y = u * length  # beyond an end: to the end's disc; inside near an end: to its plane
    before, after = np.hypot(np.maximum(rho - ra, 0.0), y), np.hypot(np.maximum(rho - rb, 0.0), y - length)
    return np.where(u < 0, before, np.where(u > 1, after, np.minimum(side, np.where(rho < ra + t * (rb - ra), np.minimum(y, length - y), np.inf))))


def nearest_segments(points: np.ndarray, joints: np.ndarray, radii: np.ndarray, parents: np.ndarray, block: int = 4096, alive=None):
    """(segment (N,) the child joint of each point's nearest segment, distance (N,) |axis
    distance - radius|) over every segment (blocks of points, float64); ``alive`` (J,): only
    the segments whose child joint is alive.

    From ``NEAR_FROM`` segments on, each point first scores only the ``NEAR`` segments whose
    centres lie nearest it (a k-d tree); the answer stands where every other segment's
    bounding sphere (its centre, half its length plus its larger radius) lies farther than the
    best distance found, which bounds that segment's distance from below (the classification
    distance is at least the distance to the surface, which lies in that sphere). The other
    points score every segment, so the answer is the brute force's, at a fraction of its cost
    (100,000 points and 1,000 segments: every point scored 1,000 segments before)."""
    child = np.nonzero((parents >= 0) & (True if alive is None else alive))[0]
    a, b = joints[parents[child]], joints[child]
    ra, rb = radii[parents[child]], radii[child]
    ab = b - a
    ll = np.maximum(np.sum(ab * ab, 1), 1e-300)
    length = np.sqrt(ll)
    seg, dist = np.empty(len(points), np.int64), np.empty(len(points))

    def brute(idx):
        for s in range(0, len(idx), block):
            rows = idx[s : s + block]
            d = _cone_distances(points[rows, None, :], a[None], ab[None], ll[None], length[None], ra[None], rb[None])
            k = np.argmin(d, 1)
            seg[rows], dist[rows] = child[k], d[np.arange(len(k)), k]

    if len(child) < NEAR_FROM:
        brute(np.arange(len(points)))
        return seg, dist
    from scipy.spatial import cKDTree

    centre_d, near = cKDTree(0.5 * (a + b)).query(points, k=NEAR)
    reach = float(np.max(0.5 * length + np.maximum(ra, rb)))  # the largest bounding sphere about a centre
    for s in range(0, len(points), block):
        n = near[s : s + block]
        d = _cone_distances(points[s : s + block, None, :], a[n], ab[n], ll[n], length[n], ra[n], rb[n])
        k = np.argmin(d, 1)
        rows = np.arange(len(k))
        seg[s : s + block], dist[s : s + block] = child[n[rows, k]], d[rows, k]
    # a segment outside a point's candidates has its centre at least as far as the farthest
    # candidate's, so its distance is at least that less the largest reach
    unsure = np.nonzero(centre_d[:, -1] - reach < dist)[0]
    if len(unsure):
        brute(unsure)
    return seg, dist


def _inside(x, a, b, ra, rb) -> float:
    """The distance of the point ``x`` from the axis segment a-b in radii of that segment's cone
    at the nearest axis point (below 1: inside the tube)."""
    ab = b - a
    t = float(np.clip((x - a) @ ab / max(ab @ ab, 1e-300), 0.0, 1.0))
    return float(np.linalg.norm(x - a - t * ab)) / max(ra + t * (rb - ra), 1e-300)


def breadth_first(joints, radii, parents):
    """The skeleton renumbered breadth first from its root (parents before children)."""
    root = int(np.nonzero(parents < 0)[0][0])
    kids = {i: [] for i in range(len(parents))}
    for c, p in enumerate(parents):
        if p >= 0:
            kids[int(p)].append(c)
    order = [root]
    for u in order:
        order.extend(kids[u])
    pos = {o: i for i, o in enumerate(order)}
    return joints[order], radii[order], np.array([-1 if parents[o] < 0 else pos[int(parents[o])] for o in order])


def edited(points, joints, radii, parents, cfg, scale: float, extent: float, round_: int, spurs_only: bool = False):
    """(joints, radii, parents, log) after one round of edits (module docstring); ``cfg`` the
    fit file's ``edits`` section, ``scale`` the robust scale in world units. The log names each
    edit, its joints (this round's numbering) and why. ``spurs_only``: the spurs' prune alone
    (after the last round, where no fit follows: removing a twig leaves the rest as fitted)."""
    joints, radii, par = np.asarray(joints, float).copy(), np.asarray(radii, float).copy(), np.asarray(parents).copy()
    seg, dist = nearest_segments(points, joints, radii, par)
    count = np.bincount(seg, minlength=len(par))

    def spread(d):
        """Root mean square of distances clipped at 5 robust scales (an outlier counts as 5)."""
        return np.sqrt(np.mean(np.minimum(d, 5.0 * scale) ** 2))
    log = []
    alive = np.ones(len(par), bool)

    def children(i):
        return [int(c) for c in np.nonzero((par == i) & alive)[0]]

    def unsupported(c):
        """Fewer than prune_points nearest points, or points that the other segments explain
        within one robust scale as well (RMS): a twig the fit has laid along another's surface."""
        if count[c] < cfg.prune_points:
            return True
        own = seg == c
        if not own.any():  # (prune_points 0) no point to compare: the count rule alone decides
            return False
        rest = alive.copy()
        rest[c] = False
        _, other = nearest_segments(points[own], joints, radii, par, alive=rest)
        return spread(other) < spread(dist[own]) + scale

    # prune: tips without support (not down to a single segment); not after the last round,
    # where a side branch the last fit left short beside a misplaced junction reads as unsupported
    for c in range(len(par)) if not spurs_only else ():
        if np.sum(alive) <= 2:
            break
        p = int(par[c])
        if p >= 0 and not children(c) and unsupported(c):
            alive[c] = False
            log.append({"round": round_, "edit": "prune", "joint": c, "parent": p, "points": int(count[c])})
    # prune: spurs, tip branches whose tip lies within spur_radii radii of another segment's
    # axis at the branch joint they leave
    for c in range(len(par)):
        if not alive[c] or par[c] < 0 or children(c):
            continue
        chain, length, b = [c], 0.0, c
        while par[b] >= 0:
            length += float(np.linalg.norm(joints[b] - joints[par[b]]))
            b = int(par[b])
            if par[b] < 0 or len(children(b)) != 1:
                break
            chain.append(b)
        if len(children(b)) < 2 or np.sum(alive) - len(chain) < 2:
            continue
        others = [k for k in children(b) if k not in chain] + ([int(par[b])] if par[b] >= 0 else [])
        depth = min(_inside(joints[c], joints[b], joints[k], radii[b], radii[k]) for k in others)
        if depth < cfg.spur_radii:
            alive[chain] = False
            log.append({"round": round_, "edit": "prune", "joint": c, "parent": b, "why": "spur", "length": length,
                        "radii_from_axis": depth, "joints": len(chain)})
    root = int(np.nonzero(par < 0)[0][0])
    kids = children(root)
    if len(kids) == 1 and np.sum(alive) > 2 and count[kids[0]] < cfg.prune_points and not spurs_only:
        alive[root], par[kids[0]] = False, -1
        log.append({"round": round_, "edit": "prune", "joint": root, "parent": -1, "points": int(count[kids[0]])})
    if spurs_only:
        return _kept(joints, radii, par, alive) + (log,)
    # merge: tiny segments, then joints where a chain goes on nearly straight and the straight
    # segment explains their points within one robust scale as well; an edit changes segments
    # (by child joint) and may move a joint, and no later edit this round uses either
    changed, moved = set(), set()
    # zip: two segments leaving one joint side by side, their far joints within zip_radii mean
    # radii of each other, are one tube traced twice; the child arm's far joint is merged into
    # the other arm's (its other neighbours joined to that one)
    for b in range(len(par)):
        if not alive[b] or cfg.zip_radii <= 0 or b in changed | moved:
            continue
        arms = children(b) + ([int(par[b])] if par[b] >= 0 else [])
        if len(arms) < 3:
            continue
        best = None
        for i, c in enumerate(arms):
            for e in arms[i + 1 :]:
                gap = float(np.linalg.norm(joints[c] - joints[e]))
                if gap < cfg.zip_radii * 0.5 * (radii[c] + radii[e]) and (best is None or gap < best[0]):
                    best = (gap, c, e)
        if best is None:
            continue
        gap, c, e = best  # c is a child of b (b's parent, if paired, comes last: e)
        if e != par[b] and len(children(c)) >= len(children(e)):
            c, e = e, c  # of two children, the one with fewer children goes into the other
        if {c, e} & (changed | moved) or any(k in changed | moved for k in children(c)):
            continue
        for k in children(c):
            par[k] = e
        alive[c] = False
        changed.update([b, c, e] + children(e))
        moved.update([c, e])
        log.append({"round": round_, "edit": "merge", "joint": c, "into": e, "why": "zip", "at": b, "gap": gap,
                    "radii_mean": float(0.5 * (radii[c] + radii[e]))})
    # necks: a joint much thinner than every neighbour, merged into the nearest of them
    for c in range(len(par)):
        p = int(par[c])
        if not alive[c] or p < 0 or c in changed or c in moved:
            continue
        near = [p] + children(c)
        if len(near) < 2 or radii[c] >= cfg.neck_ratio * min(radii[k] for k in near) or set(near) & (changed | moved):
            continue
        n = min(near, key=lambda k: float(np.linalg.norm(joints[k] - joints[c])))
        changed.update(near + [c])
        moved.update(near + [c])
        for k in children(c):
            if k != n:
                par[k] = n
        if n != p:
            par[n] = p
        alive[c] = False
        log.append({"round": round_, "edit": "merge", "joint": c, "into": n, "why": "neck", "radius": float(radii[c]),
                    "neighbours_min": float(min(radii[k] for k in near))})
    for c in range(len(par)):
        p = int(par[c])
        if not alive[c] or p < 0 or c in changed or p in moved:
            continue
        length = float(np.linalg.norm(joints[c] - joints[p]))
        # a frustum shorter than its width, unless its far joint branches (collapsing a branch
        # joint into its parent moved the 5-segment grown tree's junction off its axes, in
        # development runs of that rule)
        wide = cfg.merge_radii * 0.5 * (radii[c] + radii[p]) if len(children(c)) <= 1 else 0.0
        if length < max(cfg.merge_length * extent, wide):
            changed.update([c, p] + children(p) + children(c))
            for k in children(c):
                par[k] = p
            joints[p], radii[p] = 0.5 * (joints[p] + joints[c]), 0.5 * (radii[p] + radii[c])
            alive[c] = False
            moved.add(p)
            log.append({"round": round_, "edit": "merge", "joint": c, "into": p, "why": "short", "length": length})
    for c in range(len(par)):
        p = int(par[c])
        kids = children(c)
        if not alive[c] or p < 0 or len(kids) != 1 or {c, kids[0]} & changed or {p, c, kids[0]} & moved:
            continue
        k = kids[0]
        u, v = joints[c] - joints[p], joints[k] - joints[c]
        angle = float(np.degrees(np.arccos(np.clip(u @ v / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-300), -1.0, 1.0))))
        own = (seg == c) | (seg == k)
        if angle >= cfg.merge_angle or not own.any():
            continue
        two = spread(dist[own])
        one = spread(nearest_segments(points[own], joints[[p, k]], radii[[p, k]], np.array([-1, 0]))[1])
        if one < STRAIGHT * two + 0.1 * scale:
            par[k] = p
            alive[c] = False
            changed.update((c, k))
            log.append({"round": round_, "edit": "merge", "joint": c, "into": p, "why": "straight", "angle_deg": angle})
    # split: segments whose points stay far from them (the segment and its joints unchanged)
    new_j, new_r, new_p = [], [], []
    for c in range(len(par)):
        p = int(par[c])
        if not alive[c] or p < 0 or c in changed or {p, c} & moved or count[c] < max(2 * cfg.prune_points, 1):
            continue  # (a segment without points has no residual to split for)
        rms = float(spread(dist[seg == c]))
        if rms > cfg.split_residual * scale:
            m = len(par) + len(new_j)
            new_j.append(0.5 * (joints[p] + joints[c]))
            new_r.append(0.5 * (radii[p] + radii[c]))
            new_p.append(p)
            par[c] = m
            log.append({"round": round_, "edit": "split", "joint": c, "parent": p, "new": m, "rms": rms, "points": int(count[c])})
    if new_j:
        joints = np.concatenate([joints, np.array(new_j)])
        radii = np.concatenate([radii, np.array(new_r)])
        par = np.concatenate([par, np.array(new_p)])
        alive = np.concatenate([alive, np.ones(len(new_j), bool)])
    return _kept(joints, radii, par, alive) + (log,)


def _kept(joints, radii, par, alive) -> tuple:
    """(joints, radii, parents) of the alive joints, renumbered breadth first."""
    keep = np.nonzero(alive)[0]
    pos = {int(k): i for i, k in enumerate(keep)}
    j, r, p = joints[keep], radii[keep], np.array([-1 if par[k] < 0 else pos[int(par[k])] for k in keep])
    return breadth_first(j, r, p)
