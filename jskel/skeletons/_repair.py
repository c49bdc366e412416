"""An explicit repair policy for skeleton files, every repair counted, every problem in one error.

Real reconstructions (NeuroMorpho.Org, CATMAID, hemibrain skeletons) carry unknown radii (0,
negative, NaN), nodes placed twice at one point, somata drawn as contours and small detached
pieces. ``repair`` applies a ``RepairPolicy`` and returns the repaired skeleton with a report:
for each repair kind the number of nodes it touched and the first ids (as in the file).

What no policy repairs is an error: duplicate ids, parents that name no node, cycles and
non-finite coordinates, plus unknown radii under ``unknown_radius: error``. ``repair`` collects
ALL of them and raises ONE ``ValueError`` (``jskel.config.ConfigError``, one line per kind)
naming the field, the count and the first ids with their values, e.g.
``skeleton.file radius: 433 nodes with radius <= 0 or not a number (ids 12: 0, 17: -1, ...)``.
"""

from __future__ import annotations

from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from ..config import ConfigError, StrictModel
from ._types import MISSING, Skeleton, nearest_kept, root_of, subset

SHOW = 5  # ids named per problem and per repair
SOMA = 1  # the SWC soma type


class RepairPolicy(StrictModel):
    """What ``repair`` does with a skeleton file (all lengths in the file's units).

    ``min_radius``: radii below it are raised to it (0: none). ``unknown_radius``: what a radius
    <= 0 or NaN becomes: ``error`` (reported), ``parent`` (the nearest ancestor's known radius;
    the median where no ancestor has one), ``median`` (of the known radii) or a number.
    ``merge_zero_length``: a node that coincides with its parent (distance <= ``merge_tolerance``,
    at least 1e-9 of the skeleton's extent, the build's own zero-length bound) is merged into it,
    its children re-parented to the parent, which keeps its radius and type.
    ``drop_fragments_below``: trees (connected pieces) of fewer nodes are dropped (0 keeps all).
    ``soma``: ``keep`` every soma node (SWC type 1) as written, or ``merge`` each connected group of
    soma nodes (a contour, NeuroMorpho.Org's three-point soma) into its topmost node, placed at
    the group's centroid with radius max(mean distance of the group from the centroid, largest
    radius in the group); children of the other group nodes re-parented to it.
    """

    min_radius: Annotated[float, Field(ge=0.0)] = 0.0
    """Radii below it are raised to it (0: none)."""
    unknown_radius: Literal["error", "parent", "median"] | Annotated[float, Field(gt=0.0)] = "parent"
    """What a radius <= 0 or NaN becomes: an error, the nearest ancestor's, the median of the known radii, or a number."""
    merge_zero_length: bool = True
    """Merge a node that coincides with its parent into it (children re-parented)."""
    merge_tolerance: Annotated[float, Field(ge=0.0)] = 0.0
    """Distance within which a node coincides with its parent (at least 1e-9 of the skeleton's extent)."""
    drop_fragments_below: Annotated[int, Field(ge=0)] = 0
    """Connected pieces of fewer nodes are dropped (0 keeps all)."""
    soma: Literal["keep", "merge"] = "keep"
    """Soma nodes (SWC type 1) kept as written, or each connected group merged into one node."""


def _value(v) -> str:
    a = np.ravel(np.asarray(v))
    if a.size == 1:
        return f"{a[0]:.6g}" if np.issubdtype(a.dtype, np.floating) else str(a[0])
    return "[" + ", ".join(f"{x:.6g}" for x in a) + "]"


def _problem(field: str, what: str, noun: str, ids, values) -> str:
    """``<field> <what>: <n> <noun> (ids <id>: <value>, ...)``, the first ``SHOW`` ids."""
    shown = ", ".join(f"{int(i)}: {_value(v)}" for i, v in zip(ids[:SHOW], values[:SHOW]))
    return f"{field} {what}: {len(ids)} {noun} (ids {shown}{', ...' if len(ids) > SHOW else ''})"


def _entry(ids) -> dict:
    return {"count": int(len(ids)), "ids": [int(i) for i in ids[:SHOW]]}


def unknown_radius(radii: np.ndarray) -> np.ndarray:
    """(J,) bool: radius <= 0 or not a number."""
    return ~(radii > 0)


def problems(sk: Skeleton, policy: RepairPolicy, field: str = "skeleton.file") -> list[str]:
    """Every problem the policy does not repair, one line per kind (empty: none)."""
    out = []
    _, first, counts = np.unique(sk.ids, return_index=True, return_counts=True)
    dup = np.setdiff1d(np.arange(sk.ids.size), first)
    if dup.size:
        times = dict(zip(sk.ids[first].tolist(), counts.tolist()))
        out.append(_problem(field, "id", "nodes repeat an id used before", sk.ids[dup], [f"{times[i]} times" for i in sk.ids[dup].tolist()]))
    miss = np.nonzero(sk.parents == MISSING)[0]
    if miss.size:
        out.append(_problem(field, "parent", "nodes name a parent id that no node has", sk.ids[miss], [f"parent {p}" for p in sk.parent_ids[miss]]))
    cyc = np.nonzero(root_of(np.where(sk.parents == MISSING, -1, sk.parents)) < 0)[0]
    if cyc.size:
        out.append(_problem(field, "parent", "nodes in or below a cycle", sk.ids[cyc], [f"parent {p}" for p in sk.parent_ids[cyc]]))
    bad = np.nonzero(~np.all(np.isfinite(sk.joints), axis=1))[0]
    if bad.size:
        out.append(_problem(field, "joints", "nodes with non-finite coordinates", sk.ids[bad], sk.joints[bad]))
    if policy.unknown_radius == "error":
        bad = np.nonzero(unknown_radius(sk.radii))[0]
        if bad.size:
            out.append(_problem(field, "radius", "nodes with radius <= 0 or not a number", sk.ids[bad], sk.radii[bad]))
    return out


def _fixed_radii(sk: Skeleton, policy: RepairPolicy, field: str) -> tuple[np.ndarray, dict]:
    """Radii after ``unknown_radius`` and ``min_radius``, with their report entries."""
    r = sk.radii.copy()
    bad = unknown_radius(r)
    known = r[~bad]
    if bad.any() and known.size == 0 and not isinstance(policy.unknown_radius, float):
        raise ValueError(f"{field} radius: no node has a radius > 0 to take an unknown radius from (give a number)")
    if isinstance(policy.unknown_radius, float):
        r[bad] = policy.unknown_radius
    elif bad.any():
        median = float(np.median(known))
        src = nearest_kept(sk.parents, ~bad) if policy.unknown_radius == "parent" else -np.ones_like(sk.parents)
        r[bad] = np.where(src[bad] >= 0, sk.radii[np.maximum(src[bad], 0)], median)
    low = r < policy.min_radius
    r[low] = policy.min_radius
    return r, {"unknown_radius": _entry(sk.ids[bad]), "min_radius": _entry(sk.ids[low])}


def merge_soma(sk: Skeleton) -> tuple[Skeleton, np.ndarray]:
    """Each connected group of soma nodes into its topmost node (see ``RepairPolicy.soma``);
    returns (skeleton, ids of the nodes merged away)."""
    n = sk.ids.size
    soma = sk.labels == SOMA
    p = sk.parents
    up = np.where(soma & (p >= 0) & soma[np.maximum(p, 0)], p, np.arange(n))
    for _ in range(max(1, int(n).bit_length())):
        up = up[up]
    size = np.bincount(up[soma], minlength=n)
    centre = np.stack([np.bincount(up[soma], sk.joints[soma, k], minlength=n) for k in range(3)], 1) / np.maximum(size, 1)[:, None]
    dist = np.where(soma, np.linalg.norm(sk.joints - centre[up], axis=1), 0.0)
    mean = np.bincount(up[soma], dist[soma], minlength=n) / np.maximum(size, 1)
    rmax = np.zeros(n)
    np.maximum.at(rmax, up[soma], sk.radii[soma])
    top = soma & (up == np.arange(n)) & (size >= 2)
    joints, radii = sk.joints.copy(), sk.radii.copy()
    joints[top] = centre[top]
    radii[top] = np.maximum(mean[top], rmax[top])
    merged = soma & (up != np.arange(n))
    return subset(sk._replace(joints=joints, radii=radii), ~merged), sk.ids[merged]


def merge_zero_length(sk: Skeleton, tolerance: float) -> tuple[Skeleton, np.ndarray]:
    """Nodes within ``tolerance`` of their parent merged into it; (skeleton, merged ids)."""
    p = sk.parents
    length = np.where(p >= 0, np.linalg.norm(sk.joints - sk.joints[np.maximum(p, 0)], axis=1), np.inf)
    zero = length <= tolerance
    return subset(sk, ~zero), sk.ids[zero]


def drop_fragments(sk: Skeleton, below: int) -> tuple[Skeleton, np.ndarray]:
    """Trees of fewer than ``below`` nodes dropped; (skeleton, dropped ids)."""
    root = root_of(sk.parents)
    small = np.bincount(root, minlength=sk.ids.size)[root] < below
    return subset(sk, ~small), sk.ids[small]


def repair(sk: Skeleton, policy: RepairPolicy | None = None, field: str = "skeleton.file") -> tuple[Skeleton, dict]:
    """Apply ``policy`` (default ``RepairPolicy()``): check, fix radii, merge the soma and
    zero-length segments, drop small fragments. Returns (skeleton, report): per repair kind
    ``{"count": nodes, "ids": first ids}``. Raises one ValueError listing every problem."""
    policy = RepairPolicy() if policy is None else policy
    lines = problems(sk, policy, field)
    if lines:
        raise ConfigError(lines)
    radii, report = _fixed_radii(sk, policy, field)
    sk = sk._replace(radii=radii)
    gone = np.zeros(0, np.int64)
    if policy.soma == "merge":
        sk, gone = merge_soma(sk)
    report["soma_merged"] = _entry(gone)
    gone = np.zeros(0, np.int64)
    if policy.merge_zero_length:
        extent = float(np.max(np.ptp(sk.joints, axis=0))) if sk.ids.size else 0.0
        sk, gone = merge_zero_length(sk, max(policy.merge_tolerance, 1e-9 * extent))
    report["zero_length_merged"] = _entry(gone)
    sk, gone = drop_fragments(sk, policy.drop_fragments_below)
    report["fragments_dropped"] = _entry(gone)
    if sk.ids.size == 0:
        raise ValueError(f"{field}: no node left after repair (drop_fragments_below {policy.drop_fragments_below})")
    return sk, report
