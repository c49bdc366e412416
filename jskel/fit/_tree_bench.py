"""Branching synthetic truths for the fit (issue 53), ``python -m jskel bench
experiments/bench_fit_trees.yaml``: random grown trees whose tubes never touch
(:func:`grown_tree`, 5 to 500 segments) and the bracketed L-system trees of ``jskel.scenes``
(``lsystem_tree``, each junction a parent and three children, 6 to 486 segments; every row
counts its truth's :func:`crossing_pairs`), sampled on their surface with Gaussian noise and uniform outliers, started
from the points' Laplacian contraction (``_contract``) and fitted with topology edits between
rounds (``fitted_in_rounds``). Each row measures the fit against the truth it came from, in
float64 on the host:

* topology: branch points (degree >= 3) and tips in number; the true branch points matched one
  to one to the fitted ones by an assignment (a junction of three children may come out as two
  junctions of two, so the truth's are matched to the fitted ones near them): the share within
  one median true segment length (a share of the total length, as the small trees' tests
  take it, would admit any branch point of a 486-segment tree);
* joints: each fitted joint's distance to the nearest true axis (a joint on an axis is exact),
  and each true axis point's distance to the nearest fitted axis (a branch the fit lacks),
  both as fractions of the total length;
* radii: each fitted joint's radius against the true radius at its nearest axis point (the
  share within 5 %, the median relative error);
* seconds (start, fit with its compiles).
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import Field

from ..config import StrictModel
from ._config import EditsConfig, EstimateConfig, SolverConfig


class TreeBench(StrictModel):
    """``fit_trees:`` section of a bench file."""

    iterations: list[Annotated[int, Field(ge=1, le=6)]] = []
    """The L-system's iteration counts (1: 6 segments, 3: 54, 5: 486)."""
    segments: list[Annotated[int, Field(ge=1, le=5000)]] = [5, 50, 500]
    """Segment counts of random grown trees whose tubes never touch (:func:`grown_tree`)."""
    points_per_segment: Annotated[int, Field(ge=10, le=100_000)] = 100
    """Surface points sampled per true segment."""
    noise: Annotated[float, Field(ge=0.0)] = 0.003
    """Gaussian noise, world units (the trees' thinnest radius is 0.03)."""
    outliers: Annotated[float, Field(ge=0.0, le=1.0)] = 0.02
    """Fraction of uniform outliers."""
    seed: int = 0
    """Seed of the grown trees and of the first draw of the samples, their noise and the outliers."""
    draws: Annotated[int, Field(ge=1, le=100)] = 1
    """Draws of the points per truth (seeds ``seed``, ``seed + 1``, ...): the same tree sampled
    again, so a row shows whether its result holds beyond one draw (each row names its ``draw``)."""
    start: EstimateConfig = EstimateConfig(method="contraction", ball=0.01, segment=0.02, prune=2.0, max_points=40000)
    """The contraction start (``init.estimate`` of a fit file; ``method: contraction``)."""
    solver: SolverConfig = SolverConfig(name="lm", loss="huber", scale=0.002, maxiter=60, candidates=8)
    """The fit's solver."""
    edits: EditsConfig | None = EditsConfig(rounds=3)
    """Topology edits between rounds; unset: one fit."""


class TreeBenchFile(StrictModel):
    """A bench file whose ``fit_trees:`` section is the branching synthetic-tree benchmark."""

    fit_trees: TreeBench
    """The benchmark's settings."""


def _axis_gaps(a0, a1, b0, b1, samples: int = 11):
    """(S,) the least distance between the axis a0-a1 (3,) and each axis b0-b1 (S, 3), from
    ``samples`` points along each (float64; at most a sample spacing too long)."""
    t = np.linspace(0.0, 1.0, samples)
    mine = a0[None] + t[:, None] * (a1 - a0)[None]
    theirs = b0[:, None] + t[None, :, None] * (b1 - b0)[:, None]
    return np.min(np.linalg.norm(theirs[:, :, None] - mine[None, None], axis=-1), axis=(1, 2))


def crossing_pairs(j, r, p, gap: float = 0.05) -> int:
    """Pairs of segments more than a joint apart (their joints and their joints' parents all
    distinct) whose axes pass within their larger radii plus ``gap`` of each other: tubes that
    touch or cross, where the topology cannot be read from the surface."""
    p = np.asarray(p)
    kids = np.nonzero(p >= 0)[0]
    near = [{k, p[k], p[p[k]] if p[k] >= 0 else -1} - {-1} for k in kids]  # a segment's joints and their parents
    reach = np.maximum(r[kids], r[p[kids]])
    count = 0
    for a in range(len(kids) - 1):  # host loop over segments, at the bench's set-up
        apart = np.array([not (near[a] & near[b]) for b in range(a + 1, len(kids))])
        if apart.any():
            y = kids[a + 1:][apart]
            d = _axis_gaps(j[p[kids[a]]], j[kids[a]], j[p[y]], j[y])
            count += int(np.sum(d < reach[a] + reach[a + 1:][apart] + gap))
    return count


def grown_tree(segments: int, seed: int, length: float = 1.0, gap: float = 0.3):
    """(joints, radii, parents) of a random branching tree of ``segments`` segments of
    ``length`` (host, float64): each new segment leaves a joint with fewer than two children
    (so every branch point has three segments) turned 20-50 degrees from its parent's direction
    and leaning up, and is kept only where its axis passes more than the two radii plus ``gap``
    from every segment but its neighbours', and whose far end and a sibling's (a segment leaving
    the same joint) each pass as far from the other's axis: no two tubes touch but where they
    meet, and siblings part within their length, so the topology can be read from the surface (the L-system's crown at 486 segments has such pairs: the bench's
    ``crossing_pairs``). Radii taper from 0.25 by 0.85
    a generation down to 0.05."""
    rng = np.random.default_rng(seed)
    joints, parents, depth, dirs, kids = [np.zeros(3)], [-1], [0], [np.array([0.0, 1.0, 0.0])], [0]
    radius = lambda k: max(0.05, 0.25 * 0.85**k)  # noqa: E731
    tries = 0
    while len(joints) < segments + 1:
        tries += 1
        if tries > 200 * (segments + 1):
            raise ValueError(f"fit_trees.segments: no room found for {segments} segments")
        i = int(rng.integers(len(joints)))
        if kids[i] >= 2:
            continue
        axis = np.cross(dirs[i], rng.normal(size=3))
        axis /= np.linalg.norm(axis)
        a = np.radians(rng.uniform(20.0, 50.0))
        d = dirs[i] * np.cos(a) + np.cross(axis, dirs[i]) * np.sin(a) + axis * (axis @ dirs[i]) * (1 - np.cos(a))
        d = d + np.array([0.0, 0.3, 0.0])
        d /= np.linalg.norm(d)
        new = joints[i] + length * d
        rn = radius(depth[i] + 1)
        q = np.asarray(parents[1:])
        kid = np.arange(1, len(joints))
        ok = (kid != i) & (q != i) & (q != parents[i])  # not the segments at joint i
        jj = np.asarray(joints)
        if ok.any():
            dist = _axis_gaps(joints[i], new, jj[q[ok]], jj[kid[ok]])
            rr = np.maximum(np.asarray([radius(depth[k]) for k in kid[ok]]), np.asarray([radius(depth[k]) for k in q[ok]]))
            if np.any(dist <= rr + rn + gap):
                continue
        sib = kid[q == i]  # a sibling leaving joint i too: each one's far end clear of the other's tube
        if sib.size:
            rs = np.asarray([radius(depth[k]) for k in sib])
            to_theirs = _axis_gaps(new, new, jj[np.full(sib.size, i)], jj[sib])
            to_mine = np.array([_axis_gaps(jj[k], jj[k], joints[i][None], new[None])[0] for k in sib])
            if np.any(np.minimum(to_theirs, to_mine) <= rs + rn + gap):
                continue
        joints.append(new)
        parents.append(i)
        depth.append(depth[i] + 1)
        dirs.append(d)
        kids.append(0)
        kids[i] += 1
    return np.array(joints), np.array([radius(k) for k in depth]), np.array(parents)


def _degrees(parents) -> np.ndarray:
    parents = np.asarray(parents)
    return np.bincount(np.concatenate([parents[parents >= 0], np.nonzero(parents >= 0)[0]]), minlength=len(parents))


def _axis_samples(j, r, p, per: int = 50):
    """Points along every segment's axis and the radius there (float64)."""
    kids = np.nonzero(np.asarray(p) >= 0)[0]
    t = np.linspace(0.0, 1.0, per)
    a, b = j[p[kids]], j[kids]
    x = a[:, None] + t[None, :, None] * (b - a)[:, None]
    rr = r[p[kids]][:, None] + t[None] * (r[kids] - r[p[kids]])[:, None]
    return x.reshape(-1, 3), rr.reshape(-1)


def compared(j, r, p, fj, fr, fp) -> dict:
    """The row's measures of the fitted skeleton (fj, fr, fp) against the truth (j, r, p)."""
    from scipy.optimize import linear_sum_assignment
    from scipy.spatial import cKDTree

    p, fp = np.asarray(p), np.asarray(fp)
    length = float(np.sum(np.linalg.norm(j[p[p >= 0]] - j[p >= 0], axis=1)))
    ax, ar = _axis_samples(j, r, p)
    fax, _ = _axis_samples(fj, fr, fp)
    d_joint, near = cKDTree(ax).query(fj)
    d_cover, _ = cKDTree(fax).query(ax)
    deg, fdeg = _degrees(p), _degrees(fp)
    tb, fb = j[deg >= 3], fj[fdeg >= 3]
    matched, offset = 0.0, None
    if len(tb) and len(fb):
        cost = np.linalg.norm(tb[:, None] - fb[None], axis=-1)
        row, col = linear_sum_assignment(cost)
        unit = float(np.median(np.linalg.norm(j[p[p >= 0]] - j[p >= 0], axis=1)))
        ok = cost[row, col] <= unit
        matched = float(np.sum(ok)) / len(tb)
        if ok.any():  # how far a matched branch point sits from the true one, in the true radius there
            offset = round(float(np.max(cost[row, col][ok] / r[deg >= 3][row[ok]])), 3)
    rel = np.abs(fr / ar[near] - 1.0)
    inner = d_joint < 0.5 * ar[near]  # joints on a true axis (a joint off every axis has no true radius)
    return {"segments": int(np.sum(p >= 0)), "fitted_segments": int(np.sum(fp >= 0)),
            "branch_points": int(np.sum(deg >= 3)), "fitted_branch_points": int(np.sum(fdeg >= 3)),
            "tips": int(np.sum(deg == 1)), "fitted_tips": int(np.sum(fdeg == 1)),
            "branch_points_matched_share": round(matched, 4),
            "branch_point_offset_max_radii": offset,
            "joint_off_axis_max_of_length": round(float(d_joint.max()) / length, 5),
            "joint_off_axis_median_of_length": round(float(np.median(d_joint)) / length, 6),
            "axis_uncovered_max_of_length": round(float(d_cover.max()) / length, 5),
            "radius_within_5pct_share": round(float(np.mean(rel[inner] <= 0.05)) if inner.any() else 0.0, 4),
            "radius_error_median_rel": round(float(np.median(rel[inner])) if inner.any() else float("nan"), 4),
            "radius_error_max_rel": round(float(np.max(rel[inner])) if inner.any() else float("nan"), 4),
            "length": round(length, 4)}


def run_tree_bench(b: TreeBench, emit) -> list[dict]:
    """Run the benchmark (module docstring), calling ``emit(row)`` for each row as measured."""
    from ..scenes import GENERATORS
    from ._points import sample_surface
    from ._run import contracted_and_fitted

    rows = []
    truths = [("lsystem", it, GENERATORS["lsystem_tree"](1, {"iterations": it})[:3]) for it in b.iterations]
    truths += [("grown", n_seg, grown_tree(n_seg, b.seed)) for n_seg in b.segments]
    for (kind, size, tree), draw in ((t, d) for t in truths for d in range(b.draws)):
        j, r, p = (np.asarray(x, np.float64) for x in tree)
        p = p.astype(np.int64)
        rng = np.random.default_rng(b.seed + draw)
        n = b.points_per_segment * int(np.sum(p >= 0))
        pts = sample_surface(j, r, p, n, rng) + rng.normal(0.0, b.noise, (n, 3))
        k = int(round(b.outliers * n))
        lo, hi = pts.min(0), pts.max(0)
        pts[rng.choice(n, k, replace=False)] = rng.uniform(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), (k, 3))
        try:
            (j0, r0, p0, _), (res, edits, rounds), secs = contracted_and_fitted(pts, b.start, b.solver, b.edits, "fit_trees")
        except ValueError as e:  # a start the points cannot fit, a diverged solver: a row that says so
            row = {"tree": kind, "size": size, "draw": draw, "crossing_pairs": crossing_pairs(j, r, p), "points": n, "error": str(e)}
            emit(row)
            rows.append(row)
            continue
        row = {"tree": kind, "size": size, "draw": draw, "crossing_pairs": crossing_pairs(j, r, p), "points": n, "noise": b.noise, "outliers": b.outliers, **compared(j, r, p, res.joints, res.radii, res.parents),
               "start": compared(j, r, p, j0, r0, p0), **secs,
               "rounds": rounds, "edits": len(edits), "fit_iterations": res.iterations}
        emit(row)
        rows.append(row)
    return rows
