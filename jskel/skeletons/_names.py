"""Errors about a skeleton's joints by index, renamed as the file names its nodes.

The frusta build checks a skeleton by joint index (``object.skeleton.joints[57]: ...``,
``segment 12 -> 57``). For a skeleton read from a file, and repaired, those indices are rows of
the repaired skeleton, which a user cannot find in the file; :func:`name_nodes` puts the file's
node id and line in front of the message and the ids after every segment it names.
"""

from __future__ import annotations

import re

from ._types import Skeleton


def node_name(sk: Skeleton, i: int) -> str:
    """``node id <id> (line <n>)`` of row ``i`` (the line left out where it is unknown)."""
    line = "" if sk.lines is None else f" (line {int(sk.lines[i])})"
    return f"node id {int(sk.ids[i])}{line}"


def name_nodes(message: str, sk: Skeleton, path: str = "object.skeleton", field: str = "object.skeleton.file") -> str:
    """``message`` prefixed ``<field> <node_name>: `` for the first ``<path>.<key>[i]`` it holds
    (``i`` a row of ``sk``), with ``(node ids <a> -> <b>)`` after every ``segment p -> i``;
    unchanged where it names no row of ``sk``."""
    n = sk.ids.shape[0]

    def seg(m: re.Match) -> str:
        a, b = int(m.group(1)), int(m.group(2))
        if a >= n or b >= n:
            return m.group(0)
        return f"{m.group(0)} (node ids {int(sk.ids[a])} -> {int(sk.ids[b])})"

    out = re.sub(r"segment (\d+) -> (\d+)", seg, message)
    first = re.search(re.escape(path) + r"\.\w+\[(\d+)\]", out)
    if first is None or int(first.group(1)) >= n:
        return out
    return f"{field} {node_name(sk, int(first.group(1)))}: {out}"
