"""Cylinder lists of tree quantitative structure models (QSMs), as TreeQSM writes them.

TreeQSM (Raumonen et al. 2013, "Fast automatic precision tree models from terrestrial laser
scanner data", Remote Sensing 5; https://github.com/InverseTampere/TreeQSM) models a tree as
cylinders with a ``radius``, a ``length``, a ``start`` point, a unit ``axis`` and a ``parent``
cylinder (MATLAB's 1-based index, 0 for none). Its text export ``src/tools/save_model_text.m``
(version 1.1.0, 17 Aug 2020; checked at commit 6630bbf) writes ``cylinder_<name>.txt``: one
cylinder a line, tab-separated ``%g`` numbers in the columns

    radius, length, start (x, y, z), axis (x, y, z), parent, extension, branch, branch_order,
    position_in_branch, mad, SurfCov, added, UnmodRadius          (17 columns)

under a header of 13 tab-separated names in which ``start_point`` and ``axis_direction`` each
stand for three columns (``radius (m)``, ``length (m)``, ``start_point``, ``axis_direction``,
``parent``, ..., ``branch_order``, ...). Version 1.0.0 wrote the same first twelve columns
without ``mad`` and ``SurfCov`` and without a header (15 columns).

:func:`read_qsm` reads

* TreeQSM's files, with or without that header: the first nine columns are radius, length,
  start, axis and parent, the twelfth (where there are twelve) the branch order;
* any table whose first line names its columns (case ignored, units in parentheses dropped;
  separated by commas, tabs or spaces): ``radius``; ``start_x start_y start_z`` (or ``sx sy sz``,
  or one ``start``/``start_point`` for three columns); then either ``axis_x axis_y axis_z`` (or
  ``ax ay az``, ``axis``/``axis_direction``) with ``length``, or ``end_x end_y end_z`` (``ex ey
  ez``, ``end``/``end_point``); ``parent``; optionally ``branch_order`` (``order``, ``bo``).

Parents are 1-based with 0 for none (TreeQSM's MATLAB convention) unless some parent is negative:
then they are 0-based with -1 for none.

Cylinders to a ``Skeleton``: cylinder i (1-based, the row of the table) ends at joint id i,
placed at ``start + length * axis`` (``axis`` normalised), with the cylinder's radius. A cylinder
continues its parent, starting at the parent's end joint, where its start lies within ``join``
(0.5) parent radii of the parent's end, or within 4 where the table has TreeQSM's ``extension``
column and the parent names it as its extension: TreeQSM fits every cylinder on its own, so
consecutive cylinders of a branch do not meet exactly (in TreeQSM's example model,
``src/results/qsm.mat``, 7471 cylinders, the gap from a parent's end to its extension's start
has median 0.62 and 99th percentile 7.9 parent radii, mostly across the axis: -2.5 to 2.3 radii
along it; 97% of the 5903 extensions lie within 4, and 5713 of the cylinders continue their
parent). Consecutive cylinders of radii r_p, r_i then render as a frustum tapering from r_p to
r_i (Bhagvat et al. 2009, Sec. 3's cones through the joints' radii), the child's start moved to
its parent's end. Any other cylinder (a root, a branch's first cylinder, which TreeQSM places on
its parent's surface part way along it, ``cylinders.m: parent_cylinder``, or an extension
beyond the gap) gets its own start joint, id N + i, radius r_i, as a root: a cylinder of its
own, touching its parent as TreeQSM's own plots draw it. Labels are the branch order (0 where
the table has none).
"""

from __future__ import annotations

import re

import numpy as np

from ..config import ConfigError
from ._swc import _read_text
from ._types import Skeleton

SHOW = 5  # rows named per problem
AXIS_TOLERANCE = 1e-3  # | |axis| - 1 | allowed (TreeQSM rounds axes to 1e-4 per component)
JOIN = 0.5  # a start within JOIN * parent radius of the parent's end continues the parent
JOIN_EXTENSION = 4.0  # ... and within 4 parent radii where the parent names it as its extension

def _header_names() -> dict:
    """Header names (lower case, units dropped) -> column keys; a tuple value spans three
    columns (TreeQSM's ``start_point``, ``axis_direction``)."""
    names = {
        "radius": "radius", "r": "radius", "rad": "radius",
        "length": "length", "len": "length",
        "parent": "parent", "parent_id": "parent", "parent_cylinder": "parent",
        "branch_order": "order", "branchorder": "order", "order": "order", "bo": "order",
        "extension": "extension", "extension_cylinder": "extension",
    }
    for key, short, aliases in (("start", "s", ("start", "start_point", "startpoint")), ("axis", "a", ("axis", "axis_direction")),
                                ("end", "e", ("end", "end_point", "endpoint"))):
        for k, c in enumerate("xyz"):
            names.update({f"{key}_{c}": f"{key}{k}", f"{key}{c}": f"{key}{k}", f"{short}{c}": f"{key}{k}"})
        names.update({a: tuple(f"{key}{k}" for k in range(3)) for a in aliases})
    return names


#: header names (lower case, units dropped) -> column keys
NAMES = _header_names()
OPTIONAL = ("extension", "order")  # read where every row holds them
#: TreeQSM's headerless column order (save_model_text.m, versions 1.0.0 and 1.1.0)
TREEQSM = ("radius", "length", "start0", "start1", "start2", "axis0", "axis1", "axis2", "parent",
           "extension", "branch", "order")


def _split(line: str) -> list[str]:
    if "," in line:
        return [w.strip() for w in line.split(",")]
    if "\t" in line:
        return [w.strip() for w in line.split("\t") if w.strip()]
    return line.split()


def _columns(header: list[str], field: str) -> dict[str, int]:
    """Column index of every known key named in ``header`` (three-column names expanded)."""
    where, at = {}, 0
    for name in header:
        key = NAMES.get(re.sub(r"\s*\(.*?\)\s*", "", name).strip().lower().replace(" ", "_"))
        keys = key if isinstance(key, tuple) else (key,)
        for k in keys:
            if k is not None and k not in where:
                where[k] = at
            at += 1
    need = ["radius", "start0", "start1", "start2", "parent"]
    need += ["end0", "end1", "end2"] if "end0" in where else ["axis0", "axis1", "axis2", "length"]
    missing = [k for k in need if k not in where]
    if missing:
        raise ValueError(f"{field}: the header names no column for {', '.join(missing)} (got {', '.join(header)})")
    return where


def _table(text: str, field: str) -> tuple[dict[str, int], np.ndarray, np.ndarray]:
    """(columns, line numbers (N,), values (N, C)) of the file's table; ``#`` lines skipped."""
    lines = [(k, _split(s)) for k, s in enumerate(text.splitlines(), start=1) if s.strip() and not s.lstrip().startswith("#")]
    if not lines:
        raise ValueError(f"{field}: no cylinders in the file")
    first = lines[0][1]
    try:
        [float(w) for w in first]
        where = {k: i for i, k in enumerate(TREEQSM) if k != "branch"}
    except ValueError:
        where = _columns(first, field)
        lines = lines[1:]
    optional = {k: where.pop(k) for k in OPTIONAL if k in where}
    width = max(where.values()) + 1
    bad, rows, nums = [], [], []
    for k, words in lines:  # host parsing of the file's lines
        try:
            vals = [float(w) for w in words]
        except ValueError:
            vals = []
        if len(vals) < width:
            bad.append(f"line {k}: {' '.join(words)[:60]!r}")
            continue
        nums.append(k)
        rows.append(vals)
    if bad:
        raise ValueError(f"{field}: expected at least {width} numbers a line ({'; '.join(bad[:SHOW])}"
                         f"{f', ... ({len(bad)} lines)' if len(bad) > SHOW else ''})")
    shortest = min(len(r) for r in rows)
    where.update({k: i for k, i in optional.items() if i < shortest})  # columns every row holds
    width = max(where.values()) + 1
    return where, np.asarray(nums), np.asarray([r[:width] for r in rows], np.float64)


def _listed(field: str, what: str, rows: np.ndarray, lines: np.ndarray, values) -> str:
    """``<field> <what>: <n> cylinders (row <i> (line <n>): <value>, ...)``; rows 1-based."""
    shown = ", ".join(f"row {int(i) + 1} (line {int(lines[i])}): {v}" for i, v in zip(rows[:SHOW], values[:SHOW]))
    return f"{field} {what}: {len(rows)} cylinders ({shown}{', ...' if len(rows) > SHOW else ''})"


def _geometry(where: dict[str, int], v: np.ndarray):
    """(start (N, 3), end (N, 3), radius (N,), length (N,), axis norm (N,)) of the table."""
    start = v[:, [where[f"start{k}"] for k in range(3)]]
    if "end0" in where:
        end = v[:, [where[f"end{k}"] for k in range(3)]]
        length = np.linalg.norm(end - start, axis=1)
        return start, end, v[:, where["radius"]], length, np.ones(v.shape[0])
    axis = v[:, [where[f"axis{k}"] for k in range(3)]]
    norm = np.linalg.norm(axis, axis=1)
    length = v[:, where["length"]]
    end = start + length[:, None] * axis / np.where(norm > 0, norm, 1.0)[:, None]
    return start, end, v[:, where["radius"]], length, norm


def _rows(raw: np.ndarray, zero_based: bool) -> np.ndarray:
    """0-based cylinder rows (-1: none) of a parent or extension column: 1-based with 0 for
    none, or 0-based with -1 for none."""
    p = np.where(raw < 0, -1, raw) if zero_based else raw - 1
    return np.where(np.isfinite(p), p, -1).astype(np.int64)


def _joined(where: dict[str, int], v: np.ndarray, start, end, radius, join: float) -> tuple[np.ndarray, np.ndarray]:
    """(parent rows (N,), (N,) bool: the cylinder starts at its parent's end joint): its start
    lies within ``join`` parent radii of the parent's end, or within ``JOIN_EXTENSION`` where
    the parent's ``extension`` column names it."""
    raw = v[:, where["parent"]]
    zero_based = bool(np.any(raw < 0))
    parent = _rows(raw, zero_based)
    q = np.maximum(parent, 0)
    gap = np.linalg.norm(start - end[q], axis=1) / radius[q]
    extends = np.zeros(v.shape[0], bool)
    if "extension" in where:
        extends = _rows(v[:, where["extension"]], zero_based)[q] == np.arange(v.shape[0])
    return parent, (parent >= 0) & ((gap <= join) | (extends & (gap <= JOIN_EXTENSION)))


def _problems(field: str, where: dict[str, int], v: np.ndarray, lines: np.ndarray) -> list[str]:
    """Every bad cylinder, one line per kind: non-finite numbers, radius or length <= 0, axis
    not of unit length, parent not an integer, out of range or the cylinder itself."""
    n = v.shape[0]
    out = []
    finite = np.all(np.isfinite(v), axis=1)
    rows = np.nonzero(~finite)[0]
    if rows.size:
        out.append(_listed(field, "numbers", rows, lines, ["non-finite"] * rows.size))
    start, end, radius, length, norm = _geometry(where, v)
    for what, x in (("radius", radius), ("length", length)):
        rows = np.nonzero(finite & ~(x > 0))[0]
        if rows.size:
            out.append(_listed(field, what, rows, lines, [f"{x[i]:.6g} <= 0" for i in rows]))
    rows = np.nonzero(finite & (np.abs(norm - 1.0) > AXIS_TOLERANCE))[0]
    if rows.size:
        out.append(_listed(field, "axis", rows, lines, [f"length {norm[i]:.6g}, not 1" for i in rows]))
    raw = v[:, where["parent"]]
    zero_based = bool(np.any(raw < 0))
    lo, hi = (-1, n - 1) if zero_based else (0, n)
    own = np.arange(n) + (0 if zero_based else 1)
    bad = finite & ((raw != np.round(raw)) | (raw < lo) | (raw > hi) | (raw == own))
    rows = np.nonzero(bad)[0]
    if rows.size:
        base = "0-based, -1 none" if zero_based else "1-based, 0 none"
        out.append(_listed(field, f"parent ({base}, {n} cylinders)", rows, lines, [f"{raw[i]:g}" for i in rows]))
    return out


def read_qsm(path, field: str = "skeleton.file", join: float = JOIN) -> Skeleton:
    """Read a QSM cylinder table (see the module) into a ``Skeleton``: cylinder i ends at joint
    id i with its radius; it starts at its parent's end joint where its start lies within
    ``join`` x the parent's radius of it (or 4 x where the parent names it as its extension),
    else at its own root joint (id N + i, radius r_i).

    Every bad cylinder (non-finite numbers, radius or length <= 0, axis not of unit length
    within 1e-3, parent out of range) is listed in one ValueError: per kind the count and the
    first rows (1-based, as TreeQSM numbers cylinders) with their line and value."""
    where, lines, v = _table(_read_text(path, field), field)
    issues = _problems(field, where, v, lines)
    if issues:
        raise ConfigError(issues)
    n = v.shape[0]
    start, end, radius, _, _ = _geometry(where, v)
    parent, joined = _joined(where, v, start, end, radius, join)
    q = np.maximum(parent, 0)
    own = np.nonzero(~joined)[0]  # cylinders with a start joint of their own
    start_row = np.full(n, -1, np.int64)
    start_row[own] = n + np.arange(own.size)
    start_row = np.where(joined, q, start_row)
    joints = np.concatenate([end, start[own]])
    radii = np.concatenate([radius, radius[own]])
    parents = np.concatenate([start_row, np.full(own.size, -1, np.int64)])
    order = v[:, where["order"]].astype(np.int64) if "order" in where else np.zeros(n, np.int64)
    labels = np.concatenate([order, order[own]])
    ids = np.concatenate([np.arange(1, n + 1), n + 1 + own]).astype(np.int64)
    lines = np.concatenate([lines, lines[own]]).astype(np.int64)  # a joint's line: its cylinder's
    return Skeleton(joints, radii, parents, labels, ids, np.where(parents >= 0, ids[np.maximum(parents, 0)], -1), lines)
