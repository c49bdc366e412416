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
    """Return float64/int arrays after checking every field; raise ValueError naming the bad one
    (the first bad joint, in the order: shapes, joint values, parent indices, cycles, segments)."""
    j = np.asarray(joints, dtype=np.float64)
    if j.ndim != 2 or j.shape[1] != 3 or j.shape[0] < 2:
        raise ValueError(f"{path}.joints: expected a list of at least 2 [x, y, z] points, got shape {j.shape}")
    nj = j.shape[0]
    r = np.asarray(radii, dtype=np.float64).reshape(-1)
    p_raw = np.asarray(parents)
    if r.shape[0] != nj:
        raise ValueError(f"{path}.radii: has {r.shape[0]} entries for {nj} joints")
    if p_raw.reshape(-1).shape[0] != nj:
        raise ValueError(f"{path}.parents: has {p_raw.size} entries for {nj} joints")
    _check_joint_values(j, r, path)
    p = _parent_indices(p_raw, nj, path)
    _check_cycles(p, path)
    if np.all(p == -1):
        raise ValueError(f"{path}.parents: every joint is a root, so there is no segment")
    _check_segments(j, r, p, path)
    return j, r, p


def _check_joint_values(j: np.ndarray, r: np.ndarray, path: str) -> None:
    """Every joint finite, every radius finite and not negative."""
    bad = ~np.all(np.isfinite(j), axis=1) | ~np.isfinite(r) | (r < 0)
    for i in np.nonzero(bad)[0][:1]:  # vectorised test; the first bad joint named as before
        if not np.all(np.isfinite(j[i])):
            raise ValueError(f"{path}.joints[{i}]: not finite: {_fmt(j[i])}")
        if not np.isfinite(r[i]):
            raise ValueError(f"{path}.radii[{i}]: not finite: {r[i]}")
        raise ValueError(f"{path}.radii[{i}]: negative radius {r[i]:.6g}")


def _parent_indices(p_raw: np.ndarray, nj: int, path: str) -> np.ndarray:
    """The parents as int64, each an integer in [-1, nj - 1] and not the joint itself."""
    p = p_raw.reshape(-1)
    if not np.issubdtype(p.dtype, np.integer):
        pf = p.astype(np.float64)
        if not np.all(pf == np.round(pf)):
            i = int(np.argmax(pf != np.round(pf)))
            raise ValueError(f"{path}.parents[{i}]: not an integer: {p[i]}")
    p = p.astype(np.int64)
    bad = (p < -1) | (p >= nj) | (p == np.arange(nj))
    for i in np.nonzero(bad)[0][:1]:
        if p[i] < -1 or p[i] >= nj:
            raise ValueError(f"{path}.parents[{i}]: index {p[i]} out of range [-1, {nj - 1}]")
        raise ValueError(f"{path}.parents[{i}]: joint is its own parent")
    return p


def _check_cycles(p: np.ndarray, path: str) -> None:
    """Every joint reaches a root; a cycle is named by its joints."""
    nj = p.shape[0]
    # cycles: pointer doubling (every joint's 2^k-th ancestor) finds whether any joint fails to
    # reach a root in nj steps; only then the walk below names the cycle
    anc = p.copy()
    for _ in range(max(1, int(nj).bit_length())):
        anc = np.where(anc >= 0, anc[np.maximum(anc, 0)], -1)
    state = np.zeros(nj, np.int8)  # 0 unknown, 1 reaches a root
    for i in (range(nj) if np.any(anc >= 0) else ()):
        chain = []
        k = i
        while k != -1 and state[k] == 0:
            if k in chain:
                cyc = chain[chain.index(k):] + [k]
                raise ValueError(
                    f"{path}.parents[{i}]: parent index {p[i]} makes a cycle "
                    f"({' -> '.join(map(str, cyc))})"
                )
            chain.append(k)
            k = p[k]
        for c in chain:
            state[c] = 1


def _check_segments(j: np.ndarray, r: np.ndarray, p: np.ndarray, path: str) -> None:
    """Every segment longer than 1e-9 of the skeleton's extent and of radius > 0 at an end."""
    scale = float(np.max(np.ptp(j, axis=0))) or 1.0
    kids = np.nonzero(p >= 0)[0]
    lengths = np.linalg.norm(j[kids] - j[p[kids]], axis=1)
    bad = ~(lengths > 1e-9 * scale) | ((r[kids] == 0) & (r[p[kids]] == 0))
    for i in kids[bad][:1]:
        length = float(np.linalg.norm(j[i] - j[p[i]]))
        if not length > 1e-9 * scale:
            raise ValueError(
                f"{path}.joints[{i}]: zero-length segment {p[i]} -> {i} (length {length:.3g}, both at {_fmt(j[i])})"
            )
        if r[i] == 0 and r[p[i]] == 0:
            raise ValueError(f"{path}.radii[{i}]: segment {p[i]} -> {i} has radius 0 at both ends")


def topology(joints: np.ndarray, parents: np.ndarray, path: str = "object.skeleton") -> Topology:
    """Segments, continuation choice (see module docstring) and depth order."""
    nj = joints.shape[0]
    ends = np.nonzero(parents >= 0)[0]
    starts = parents[ends]
    ns = ends.shape[0]
    incoming = -np.ones(nj, np.int64)
    incoming[ends] = np.arange(ns)
    axis = joints[ends] - joints[starts]
    axis = axis / np.linalg.norm(axis, axis=1, keepdims=True)
    continuation = -np.ones(nj, np.int64)
    best = np.full(nj, -np.inf)
    # each joint continues the outgoing segment best aligned with its incoming one (the first
    # such segment on a tie): sorted by joint, then alignment descending, then segment index
    seg = np.nonzero(incoming[starts] >= 0)[0]
    if seg.size:
        a = starts[seg]
        inc = incoming[a]
        d = axis[inc, 0] * axis[seg, 0] + axis[inc, 1] * axis[seg, 1] + axis[inc, 2] * axis[seg, 2]
        order = np.lexsort((seg, -d, a))
        first = np.ones(order.size, bool)
        first[1:] = a[order][1:] != a[order][:-1]
        pick = order[first]
        keep = d[pick] > -np.inf
        best[a[pick][keep]] = d[pick][keep]
        continuation[a[pick][keep]] = seg[pick][keep]
    cos_max = np.cos(np.radians(MAX_BEND_DEG))
    for jnt in np.nonzero(continuation >= 0)[0]:
        if best[jnt] < cos_max:
            ang = np.degrees(np.arccos(np.clip(best[jnt], -1, 1)))
            raise ValueError(
                f"{path}.joints[{jnt}]: the skeleton folds back by {ang:.3f} degrees at this joint "
                f"(at most {MAX_BEND_DEG} allowed)"
            )
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
