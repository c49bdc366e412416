"""Node tables: a CSV with one node a row and a header naming the columns, as CATMAID and navis
export skeletons (``navis.TreeNeuron.nodes.to_csv``, CATMAID's "treenode table").

Columns by header name, case and surrounding spaces ignored: the id (``id``, ``node_id``,
``treenode_id``), ``x``, ``y``, ``z``, the radius (``radius``, ``r``) and the parent
(``parent_id``, ``parent``, ``parent_treenode_id``); an SWC type column (``type``/``label``
holding integers) is kept as labels, any other column is ignored. A parent that is empty,
``None``, ``NaN`` or negative makes a root (CATMAID leaves it empty, navis writes -1). An empty
or ``None`` radius is NaN: an unknown radius for ``repair``.
"""

from __future__ import annotations

import csv
import io

import numpy as np

from ._swc import _read_text
from ._types import Skeleton, resolve_parents

#: accepted header names of each column (lower case)
COLUMNS = {
    "id": ("id", "node_id", "treenode_id"),
    "x": ("x",),
    "y": ("y",),
    "z": ("z",),
    "radius": ("radius", "r"),
    "parent": ("parent_id", "parent", "parent_treenode_id"),
}
LABEL_COLUMNS = ("type", "label")
_EMPTY = {"", "none", "nan", "null", "na"}


def _column_index(header: list[str], field: str) -> dict[str, int]:
    names = [h.strip().lower() for h in header]
    where, missing = {}, []
    for key, accepted in COLUMNS.items():
        hit = [names.index(a) for a in accepted if a in names]
        if hit:
            where[key] = hit[0]
        else:
            missing.append("/".join(accepted))
    if missing:
        raise ValueError(f"{field}: the header has no column {', '.join(missing)} (got {', '.join(header)})")
    return where


def _numbers(cells: list[str], what: str, field: str, first_line: int) -> np.ndarray:
    """A column's cells as float64 (empty/None/NaN -> NaN); a ValueError naming the rows that
    hold anything else."""
    out = np.full(len(cells), np.nan)
    bad = []
    for k, c in enumerate(cells):  # host parsing of the table's cells
        s = c.strip()
        if s.lower() in _EMPTY:
            continue
        try:
            out[k] = float(s)
        except ValueError:
            bad.append(f"line {first_line + k}: {s[:30]!r}")
    if bad:
        raise ValueError(f"{field} {what}: {len(bad)} cells are not numbers ({', '.join(bad[:5])})")
    return out


def _ints(values: np.ndarray, what: str, field: str, first_line: int, empty: int | None = None) -> np.ndarray:
    """Integral float column as int64 (NaN -> ``empty`` where given); a ValueError otherwise."""
    v = np.where(np.isnan(values), np.nan if empty is None else float(empty), values)
    bad = ~np.isfinite(v) | (v != np.round(v))
    if np.any(bad):
        rows = np.nonzero(bad)[0][:5]
        raise ValueError(f"{field} {what}: {int(bad.sum())} rows are not integers "
                         f"({', '.join(f'line {first_line + k}: {values[k]!r}' for k in rows)})")
    return v.astype(np.int64)


def read_node_table(path, field: str = "skeleton.file") -> Skeleton:
    """Read a CSV node table into a ``Skeleton`` (row order, original ids, labels from an
    integer type column or 0). Nothing is repaired (see ``read_swc``)."""
    reader = csv.reader(io.StringIO(_read_text(path, field)))
    numbered = [(reader.line_num, r) for r in reader if any(c.strip() for c in r)]  # (line, cells)
    rows = [r for _, r in numbered]
    if len(rows) < 2:
        raise ValueError(f"{field}: expected a header line and at least one node")
    header, body = rows[0], rows[1:]
    where = _column_index(header, field)
    names = [h.strip().lower() for h in header]
    short = [k + 2 for k, r in enumerate(body) if len(r) < len(header)]
    if short:
        raise ValueError(f"{field}: {len(short)} rows have fewer cells than the header (lines {', '.join(map(str, short[:5]))})")
    col = {k: _numbers([r[i] for r in body], k, field, 2) for k, i in where.items()}
    ids = _ints(col["id"], "id", field, 2)
    parent_ids = _ints(col["parent"], "parent", field, 2, empty=-1)
    parent_ids = np.where(parent_ids < 0, -1, parent_ids)
    labels = np.zeros(ids.shape[0], np.int64)
    lab = [names.index(a) for a in LABEL_COLUMNS if a in names]
    if lab:
        cells = [r[lab[0]].strip() for r in body]
        if all(c.lstrip("-").isdigit() for c in cells):  # navis' node types ("root", "slab") are not labels
            labels = np.asarray([int(c) for c in cells], np.int64)
    joints = np.stack([col["x"], col["y"], col["z"]], axis=1)
    lines = np.asarray([n for n, _ in numbered[1:]], np.int64)
    return Skeleton(joints, col["radius"], resolve_parents(ids, parent_ids), labels, ids, parent_ids, lines)
