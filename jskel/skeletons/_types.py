"""A skeleton as read from a file: nodes in file order with their original ids and type labels.

``Skeleton`` is what every reader returns and every writer takes. Nodes keep the order of the
file; ``parents`` are row indices (-1 for a root, ``MISSING`` where the file names a parent id
that no node has), ``ids`` and ``parent_ids`` the numbers the file used, so every report and
error can name a node as the file does; ``lines`` the line of the file each node came from. ``labels`` are SWC structure types (Cannon et al. 1998;
0 where the format has none); :func:`label_colors` turns them into colours by ``TYPE_COLORS``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

#: ``parents`` value of a node whose parent id names no node of the file
MISSING = -2

#: SWC structure types (Cannon et al. 1998; NeuroMorpho.Org's standard) -> linear RGB
TYPE_COLORS = {
    0: (0.45, 0.45, 0.45),  # undefined: grey
    1: (0.80, 0.10, 0.10),  # soma: red
    2: (0.10, 0.25, 0.85),  # axon: blue
    3: (0.10, 0.60, 0.15),  # basal dendrite: green
    4: (0.70, 0.10, 0.70),  # apical dendrite: magenta
}
#: every other type (5 and up: custom, e.g. fork and end points as some tools write them): orange
CUSTOM_COLOR = (0.90, 0.55, 0.05)


class Skeleton(NamedTuple):
    """Nodes of a skeleton file, in file order (J nodes)."""

    joints: np.ndarray  # (J, 3) float64 positions, file units
    radii: np.ndarray  # (J,) float64 as in the file (may be <= 0 or NaN before ``repair``)
    parents: np.ndarray  # (J,) int64 row of the parent; -1 a root; MISSING: parent id names no node
    labels: np.ndarray  # (J,) int64 SWC type (0: undefined)
    ids: np.ndarray  # (J,) int64 node ids as in the file
    parent_ids: np.ndarray  # (J,) int64 parent ids as in the file (-1 for a root)
    lines: np.ndarray | None = None  # (J,) int64 line of the file each node was read from (None: not from a file)


def from_arrays(joints, radii, parents, labels=None, ids=None) -> Skeleton:
    """A ``Skeleton`` from index arrays (``parents`` rows, -1 roots), e.g. a fit's result:
    ids 1..J unless given, labels 0 unless given."""
    j = np.asarray(joints, np.float64).reshape(-1, 3)
    p = np.asarray(parents, np.int64).reshape(-1)
    i = np.arange(1, j.shape[0] + 1, dtype=np.int64) if ids is None else np.asarray(ids, np.int64)
    lab = np.zeros(j.shape[0], np.int64) if labels is None else np.asarray(labels, np.int64)
    return Skeleton(j, np.asarray(radii, np.float64).reshape(-1), p, lab, i, np.where(p >= 0, i[np.maximum(p, 0)], -1))


def resolve_parents(ids: np.ndarray, parent_ids: np.ndarray) -> np.ndarray:
    """Row of each parent id (the first node with that id); -1 for negative ids, ``MISSING``
    for ids no node has. Sorted search, no Python loop over nodes."""
    if ids.size == 0:
        return np.zeros(0, np.int64)
    order = np.argsort(ids, kind="stable")
    at = np.clip(np.searchsorted(ids[order], parent_ids), 0, ids.size - 1)
    rows = np.where(ids[order][at] == parent_ids, order[at], MISSING)
    return np.where(parent_ids < 0, -1, rows).astype(np.int64)


def label_colors(labels: np.ndarray) -> np.ndarray:
    """(J, 3) linear RGB of SWC types by ``TYPE_COLORS`` (``CUSTOM_COLOR`` for any other)."""
    table = np.array([TYPE_COLORS[k] for k in sorted(TYPE_COLORS)], np.float64)
    lab = np.asarray(labels, np.int64)
    known = (lab >= 0) & (lab < table.shape[0])
    return np.where(known[:, None], table[np.clip(lab, 0, table.shape[0] - 1)], np.asarray(CUSTOM_COLOR))


def nearest_kept(parents: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """For every node, the nearest ancestor (or the node itself) that is kept; -1 where none.
    Pointer doubling over the parent links: log2(J) vectorised steps."""
    n = parents.shape[0]
    up = np.where(keep, np.arange(n), np.where(parents >= 0, parents, -1))
    for _ in range(max(1, int(n).bit_length())):
        up = np.where(up >= 0, np.where(keep[np.maximum(up, 0)], up, up[np.maximum(up, 0)]), -1)
    return np.where(up >= 0, up, -1)


def subset(sk: Skeleton, keep: np.ndarray) -> Skeleton:
    """The kept nodes, in order; each kept node's parent becomes its nearest kept proper
    ancestor (the children of a dropped node are re-parented past it). ``joints`` and ``radii``
    of the kept nodes unchanged."""
    keep = np.asarray(keep, bool)
    p = sk.parents
    above = nearest_kept(p, keep)[np.maximum(p, 0)]
    new_parent = np.where(p >= 0, above, -1)
    row = np.cumsum(keep) - 1
    q = np.where(new_parent >= 0, row[np.maximum(new_parent, 0)], -1)[keep]
    ids = sk.ids[keep]
    lines = None if sk.lines is None else sk.lines[keep]
    return Skeleton(sk.joints[keep], sk.radii[keep], q, sk.labels[keep], ids, np.where(q >= 0, ids[np.maximum(q, 0)], -1), lines)


def root_of(parents: np.ndarray) -> np.ndarray:
    """Row of every node's root (pointer doubling); -1 where the chain does not end at a root
    within J steps (a cycle) or ends at a ``MISSING`` parent."""
    n = parents.shape[0]
    up = np.where(parents >= 0, parents, np.where(parents == -1, np.arange(n), -1))
    for _ in range(max(1, int(n).bit_length()) + 1):
        up = np.where(up >= 0, up[np.maximum(up, 0)], -1)
    is_root = np.zeros(n + 1, bool)
    is_root[:n] = parents == -1
    return np.where((up >= 0) & is_root[np.where(up >= 0, up, n)], up, -1)
