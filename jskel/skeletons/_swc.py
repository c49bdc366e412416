"""SWC files in and out (Cannon et al. 1998, "An on-line archive of reconstructed hippocampal
neurons", J. Neurosci. Methods 84; the format NeuroMorpho.Org distributes and the neuron tools
(NEURON, neuTube, Vaa3D, navis, neuprint) write).

One node a line, seven whitespace-separated columns ``id type x y z radius parent``; a parent of
-1 (any negative number) makes a root; ``#`` starts a comment (whole lines, or the rest of a
line). Ids need not be sequential or sorted, a parent may come after its child, a file may hold
several roots (several trees). Types (the SWC standard; NeuroMorpho.Org's conventions): 0
undefined, 1 soma, 2 axon, 3 (basal) dendrite, 4 apical dendrite, 5 and up custom (some tools
write 5 for fork points, 6 for end points); they are kept per node as ``Skeleton.labels``.

The soma: NeuroMorpho.Org standardises it as three points (a centre and two points one soma
radius away along y, both children of the centre); other files give a single node (a sphere
of its radius) or a contour of type-1 nodes around the cell body. The reader keeps every soma
node as written; ``repair`` with ``soma: merge`` collapses each connected group of soma nodes
to one node (see ``jskel.skeletons.repair``).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ._types import TYPE_COLORS, Skeleton, resolve_parents


def _read_text(path, field: str) -> str:
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{field}: no such file (got {str(path)!r})")
    return p.read_text(encoding="utf-8", errors="replace")


def _rows(text: str, ncol: int, field: str) -> tuple[np.ndarray, np.ndarray]:
    """(line numbers (N,), values (N, ncol) float64) of the non-comment lines; every line that
    does not hold ``ncol`` numbers is named in one ValueError (the first five, and a count)."""
    nums, rows, bad = [], [], []
    for k, line in enumerate(text.splitlines(), start=1):  # host parsing of the file's lines
        words = line.split("#", 1)[0].split()
        if not words:
            continue
        try:
            vals = [float(w) for w in words]
        except ValueError:
            vals = []
        if len(vals) != ncol:
            bad.append(f"line {k}: {line.strip()[:60]!r}")
            continue
        nums.append(k)
        rows.append(vals)
    if bad:
        more = f", ... ({len(bad)} lines)" if len(bad) > 5 else ""
        raise ValueError(f"{field}: expected {ncol} numbers a line ({'; '.join(bad[:5])}{more})")
    if not rows:
        raise ValueError(f"{field}: no nodes in the file")
    return np.asarray(nums), np.asarray(rows, np.float64)


def _integers(values: np.ndarray, lines: np.ndarray, what: str, field: str) -> np.ndarray:
    """``values`` as int64; a ValueError naming the lines whose value is not an integer."""
    bad = ~np.isfinite(values) | (values != np.round(values))
    if np.any(bad):
        show = ", ".join(f"line {n}: {v!r}" for n, v in zip(lines[bad][:5], values[bad][:5]))
        raise ValueError(f"{field}: {int(bad.sum())} nodes whose {what} is not an integer ({show})")
    return values.astype(np.int64)


def read_swc(path, field: str = "skeleton.file") -> Skeleton:
    """Read an SWC file into a ``Skeleton`` (file order, original ids, types as labels).

    Nothing is repaired here: radii <= 0 or NaN, duplicate ids, parents that name no node and
    cycles stay as written, for ``repair`` to fix or report all at once. A line that is not
    seven numbers, or an id, type or parent that is not an integer, is a ValueError naming
    ``field`` and the lines.
    """
    lines, v = _rows(_read_text(path, field), 7, field)
    ids = _integers(v[:, 0], lines, "id", field)
    labels = _integers(v[:, 1], lines, "type", field)
    parent_ids = _integers(v[:, 6], lines, "parent", field)
    parent_ids = np.where(parent_ids < 0, -1, parent_ids)
    return Skeleton(v[:, 2:5].copy(), v[:, 5].copy(), resolve_parents(ids, parent_ids), labels, ids, parent_ids, lines.astype(np.int64))


def _header() -> list[str]:
    types = ", ".join(f"{k} = {n}" for k, n in zip(sorted(TYPE_COLORS), ("undefined", "soma", "axon", "basal dendrite", "apical dendrite")))
    return [
        "# SWC (Cannon et al. 1998), written by jskel",
        "# columns: id type x y z radius parent (parent -1: a root)",
        f"# types: {types}, 5 and up custom",
    ]


def write_swc(path, skeleton: Skeleton) -> Path:
    """Write ``skeleton`` as SWC: its ids, labels and parents' ids, floats in Python's shortest
    repr (reading the file back gives the same float64 values). Parents that name no node are
    written as -1 (a root). Returns the path."""
    sk = skeleton
    parent_ids = np.where(sk.parents >= 0, sk.ids[np.maximum(sk.parents, 0)], -1)
    body = [
        f"{int(i)} {int(t)} {float(x)!r} {float(y)!r} {float(z)!r} {float(r)!r} {int(q)}"
        for i, t, (x, y, z), r, q in zip(sk.ids, sk.labels, sk.joints, sk.radii, parent_ids)
    ]
    out = Path(path)
    out.write_text("\n".join(_header() + body) + "\n", encoding="utf-8")
    return out
