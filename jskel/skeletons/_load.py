"""A skeleton file by format (``swc``, ``nodes`` or ``auto`` by extension), read and repaired."""

from __future__ import annotations

from pathlib import Path

from ._nodes import read_node_table
from ._repair import RepairPolicy, repair
from ._swc import read_swc
from ._types import Skeleton

READERS = {"swc": read_swc, "nodes": read_node_table}
EXTENSIONS = {".swc": "swc", ".csv": "nodes"}


def format_of(path, fmt: str = "auto", field: str = "skeleton.file") -> str:
    """``fmt`` itself, or for ``auto`` the format its extension names (.swc, .csv)."""
    if fmt != "auto":
        if fmt not in READERS:
            raise ValueError(f"{field}: unknown format {fmt!r} (known: auto, {', '.join(READERS)})")
        return fmt
    ext = Path(path).suffix.lower()
    if ext not in EXTENSIONS:
        raise ValueError(f"{field}: cannot tell the format from the extension of {str(path)!r} "
                         f"(known: {', '.join(EXTENSIONS)}; or give format: {' | '.join(READERS)})")
    return EXTENSIONS[ext]


def load(path, fmt: str = "auto", policy: RepairPolicy | None = None, field: str = "skeleton.file") -> tuple[Skeleton, dict]:
    """Read ``path`` in format ``fmt`` and ``repair`` it under ``policy``: (skeleton, report)."""
    reader = READERS[format_of(path, fmt, field)]
    return repair(reader(path, field), policy, field)
