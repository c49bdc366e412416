"""A skeleton file by format (``swc``, ``nodes``, ``qsm`` or ``auto`` by extension), read and repaired."""

from __future__ import annotations

from pathlib import Path

from ._nodes import read_node_table
from ._qsm import read_qsm
from ._repair import RepairPolicy, repair
from ._swc import read_swc
from ._types import Skeleton

READERS = {"swc": read_swc, "nodes": read_node_table, "qsm": read_qsm}
EXTENSIONS = {".swc": "swc", ".csv": "nodes"}


def format_of(path, fmt: str = "auto", field: str = "skeleton.file") -> str:
    """``fmt`` itself, or for ``auto`` the format its extension names (.swc, .csv; a .txt
    named ``cylinder*``, as TreeQSM's ``save_model_text`` names its cylinder table: qsm)."""
    if fmt != "auto":
        if fmt not in READERS:
            raise ValueError(f"{field}: unknown format {fmt!r} (known: auto, {', '.join(READERS)})")
        return fmt
    ext = Path(path).suffix.lower()
    if ext == ".txt" and Path(path).name.lower().startswith("cylinder"):
        return "qsm"  # TreeQSM's save_model_text writes cylinder_<name>.txt
    if ext not in EXTENSIONS:
        raise ValueError(f"{field}: cannot tell the format from the extension of {str(path)!r} "
                         f"(known: {', '.join(EXTENSIONS)}; or give format: {' | '.join(READERS)})")
    return EXTENSIONS[ext]


def load(path, fmt: str = "auto", policy: RepairPolicy | None = None, field: str = "skeleton.file") -> tuple[Skeleton, dict]:
    """Read ``path`` in format ``fmt`` and ``repair`` it under ``policy``: (skeleton, report)."""
    reader = READERS[format_of(path, fmt, field)]
    return repair(reader(path, field), policy, field)
