"""Skeleton validation and topology (host side, NumPy float64).

A skeleton is ``joints`` (J, 3), ``radii`` (J,) and ``parents`` (J,) with -1 for a root. Every
non-root joint ``j`` closes one segment ``parents[j] -> j``; segments are numbered in increasing
order of their end joint. Branching is allowed.

Branching (Bhagvat et al. 2009 leave it open, Sec. 4.1 "Limitations"): at a joint with several
children, the child whose axis is best aligned with the incoming segment *continues* it and
shares the medial cutting plane of Eq. 3-5 with it; every other child is a *side branch*: its
base is cut by the plane through the joint perpendicular to its own axis and closed by a flat
cap. That cap lies inside the parent wherever the branch is thinner than the parent at the
joint, which is the case for trees and cacti.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from .. import checks

#: a continuation may not fold back by more than this (degrees): Eq. 3's medial plane and the
#: cutting plane through A and B degenerate as the bend approaches 180 degrees.
MAX_BEND_DEG = 179.0


class Topology(NamedTuple):
    """Segment structure of a validated skeleton (all int arrays)."""

    seg_start: np.ndarray  # (S,) joint index at the base of each segment
    seg_end: np.ndarray  # (S,) joint index at the top
    parent_seg: np.ndarray  # (S,) segment this one continues, or -1 (root or side branch)
    incoming: np.ndarray  # (J,) segment ending at each joint, or -1
    continuation: np.ndarray  # (J,) segment continuing through each joint, or -1
    depth: np.ndarray  # (S,) number of segments before this one along continuations/branches
    branch_parent: np.ndarray  # (S,) incoming segment at the base joint (also for side branches), -1 at roots


def _fmt(v) -> str:
    return "[" + ", ".join(f"{float(x):.6g}" for x in np.ravel(v)) + "]"


def validate_skeleton(joints, radii, parents, path: str = "object.skeleton"):
    """Return float64/int arrays after checking every field; raise one ValueError
    (:class:`jskel.config.ConfigError`) naming every problem: shapes first (nothing else can be
    read without them), then every bad joint value, parent index, cycle and fold-back at once
    (:func:`topology_problems`), then every degenerate segment."""
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 2 or j.shape[1] != 3 or j.shape[0] < 2:
        raise ValueError(f"{path}.joints: expected a list of at least 2 [x, y, z] points, got shape {j.shape}")
    nj = j.shape[0]
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    p_raw = np.asarray(parents).reshape(-1)
    lines = checks.count_mismatch("radii", r.shape[0], nj, "joints") + checks.count_mismatch("parents", p_raw.shape[0], nj, "joints")
    checks.raise_all([f"{path}.{x}" for x in lines])
    lines = checks.nonfinite("joints", j, "joints") + checks.nonfinite("radii", r, "joints")
    neg = np.nonzero(r < 0)[0]
    lines += checks.at("radii", "negative radius", neg, r[neg], "joints") + topology_problems(j, p_raw)
    pf = p_raw.astype(np.float64)
    if np.all((pf == np.round(pf)) & (pf >= -1) & (pf < nj) & (pf != np.arange(nj))):
        lines += _segment_problems(j, r, pf.astype(np.int64))  # the segments are known
    checks.raise_all([f"{path}.{x}" for x in lines])
    return j, r, p_raw.astype(np.int64)


def topology_problems(joints, parents) -> list[str]:
    """Every problem of a skeleton's structure, as lines relative to its path (``jskel.checks``'
    form): every parent that is not an integer, out of range or the joint itself; where the
    parents are all indices, every cycle (named by its joints, from its lowest), a skeleton of
    roots only, and every joint where the skeleton folds back by more than MAX_BEND_DEG (the
    angle and the two segments; joints or segments that are not finite or of zero length are
    left to their own checks)."""
    j = np.asarray(joints, np.float64)
    pf = np.asarray(parents, np.float64).reshape(-1)
    nj = pf.shape[0]
    whole = pf == np.round(pf)  # False at NaN
    out = whole & ((pf < -1) | (pf >= nj))
    own = whole & (pf == np.arange(nj))
    lines = checks.at("parents", "not an integer", np.nonzero(~whole)[0], pf[~whole], "joints")
    lines += checks.at("parents", f"index out of range [-1, {nj - 1}]", np.nonzero(out)[0], pf[out], "joints")
    lines += checks.at("parents", "is the joint itself", np.nonzero(own)[0], pf[own], "joints")
    if lines:
        return lines
    p = pf.astype(np.int64)
    lines = _cycles(p)
    if lines:
        return lines
    if np.all(p == -1):
        return [f"parents: every joint is a root; a skeleton needs a segment (got {nj} roots)"]
    return _fold_backs(*_continuations(j, p)[2:])


def _cycles(p: np.ndarray) -> list[str]:
    """Every cycle of the parent pointers, as ``parents[k]: parents make a cycle (got k -> ...
    -> k)`` from its lowest joint ``k``."""
    nj = p.shape[0]
    # pointer doubling: after 2^b >= nj steps a joint that reaches no root sits on a cycle
    anc = p.copy()
    for _ in range(max(1, int(nj).bit_length())):
        anc = np.where(anc >= 0, anc[np.maximum(anc, 0)], -1)
    on_cycle = np.unique(anc[anc >= 0])
    seen = np.zeros(nj, bool)
    lows, walks = [], []
    for c in on_cycle:  # one walk per cycle, over its joints only
        if seen[c]:
            continue
        cyc = [int(c)]
        while p[cyc[-1]] != c:
            cyc.append(int(p[cyc[-1]]))
        seen[cyc] = True
        k = int(np.argmin(cyc))
        cyc = cyc[k:] + cyc[:k]
        lows.append(cyc[0])
        walks.append(" -> ".join(map(str, cyc + [cyc[0]])))
    return checks.at("parents", "parents make a cycle", lows, walks, "cycles")


def _continuations(joints: np.ndarray, parents: np.ndarray):
    """(starts, ends, incoming, continuation, best): each segment's joints, the segment ending
    at each joint, the outgoing segment best aligned with it (the first such segment on a tie;
    -1 where none) and that alignment (cosine; -inf where none). Segments whose axis is not
    finite or of zero length continue nothing and are continued by nothing."""
    nj = joints.shape[0]
    ends = np.nonzero(parents >= 0)[0]
    starts = parents[ends]
    ns = ends.shape[0]
    incoming = -np.ones(nj, np.int64)
    incoming[ends] = np.arange(ns)
    with np.errstate(invalid="ignore", divide="ignore"):  # non-finite joints: their own check names them
        axis = joints[ends] - joints[starts]
        axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    continuation = -np.ones(nj, np.int64)
    best = np.full(nj, -np.inf)
    # sorted by joint, then alignment descending, then segment index
    seg = np.nonzero(incoming[starts] >= 0)[0]
    if seg.size:
        a = starts[seg]
        inc = incoming[a]
        d = axis[inc, 0] * axis[seg, 0] + axis[inc, 1] * axis[seg, 1] + axis[inc, 2] * axis[seg, 2]
        ok = np.isfinite(d)
        a, seg, d = a[ok], seg[ok], d[ok]
        order = np.lexsort((seg, -d, a))
        first = np.ones(order.size, bool)
        first[1:] = a[order][1:] != a[order][:-1]
        pick = order[first]
        best[a[pick]] = d[pick]
        continuation[a[pick]] = seg[pick]
    return starts, ends, incoming, continuation, best


def _fold_backs(incoming: np.ndarray, continuation: np.ndarray, best: np.ndarray) -> list[str]:
    """Every joint whose continuation turns back by more than MAX_BEND_DEG (Eq. 3's medial
    plane degenerates there): ``joints[i]: folds back by more than 179 degrees (got 179.5
    degrees from segment a to segment b)``, from :func:`_continuations`' last three."""
    bad = np.nonzero((continuation >= 0) & (best < np.cos(np.radians(MAX_BEND_DEG))))[0]
    ang = np.degrees(np.arccos(np.clip(best[bad], -1, 1)))
    got = [f"{a:.6g} degrees from segment {incoming[i]} to segment {continuation[i]}" for i, a in zip(bad, ang)]
    return checks.at("joints", f"folds back by more than {MAX_BEND_DEG:g} degrees", bad, got, "joints")


def _segment_problems(j: np.ndarray, r: np.ndarray, p: np.ndarray) -> list[str]:
    """Every segment not longer than 1e-9 of the skeleton's extent, and every one of radius 0
    at both ends, one line each (``segment p -> i``: ``jskel.skeletons.name_nodes`` adds a
    file's node ids)."""
    fin = np.all(np.isfinite(j), axis=1)
    scale = float(np.max(np.ptp(j[fin], axis=0))) if fin.sum() > 1 else 0.0
    scale = scale or 1.0
    kids = np.nonzero((p >= 0) & fin & fin[np.maximum(p, 0)])[0]
    lengths = np.linalg.norm(j[kids] - j[p[kids]], axis=1)
    zero = ~(lengths > 1e-9 * scale)
    lines = [f"joints[{i}]: zero-length segment {p[i]} -> {i} (length {h:.3g}, both at {_fmt(j[i])})"
             for i, h in zip(kids[zero], lengths[zero])]
    thin = kids[(r[kids] == 0) & (r[p[kids]] == 0)]
    return lines + [f"radii[{i}]: segment {p[i]} -> {i} has radius 0 at both ends" for i in thin]


def topology(joints: np.ndarray, parents: np.ndarray, path: str = "object.skeleton") -> Topology:
    """Segments, continuation choice (see module docstring) and depth order."""
    starts, ends, incoming, continuation, best = _continuations(joints, parents)
    ns = ends.shape[0]
    checks.raise_all([f"{path}.{x}" for x in _fold_backs(incoming, continuation, best)])  # every fold-back at once
    parent_seg = -np.ones(ns, np.int64)
    branch_parent = incoming[starts]
    cont = continuation[starts] == np.arange(ns)
    parent_seg[cont] = incoming[starts[cont]]
    depth = -np.ones(ns, np.int64)
    depth[branch_parent < 0] = 0
    while np.any(depth < 0):
        todo = depth < 0
        known = depth[branch_parent] >= 0
        upd = todo & known
        depth[upd] = depth[branch_parent[upd]] + 1
    return Topology(starts, ends, parent_seg, incoming, continuation, depth, branch_parent)
