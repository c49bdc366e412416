"""Pair each notebook script ``NN_name.py`` (jupytext "percent" format: cells start at ``# %%``,
markdown cells at ``# %% [markdown]`` with ``# `` prefixed lines) with ``NN_name.ipynb``, stored
without outputs. ``python notebooks/pair.py`` rewrites every .ipynb from its script; the tests
check that each stored notebook equals its script's conversion and carries no outputs, then run
the scripts' cells (which is what executing the notebooks runs).

Written by hand (a few lines of nbformat v4 JSON) so that no notebook tooling is a dependency."""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def cells_of(text: str) -> list[tuple[str, str]]:
    """(kind, source) of each cell of a percent-format script."""
    cells, kind, buf = [], None, []
    for line in text.splitlines():
        if line.startswith("# %%"):
            if kind is not None:
                cells.append((kind, "\n".join(buf).strip("\n")))
            kind = "markdown" if "[markdown]" in line else "code"
            buf = []
            continue
        if kind is None:
            continue  # the header before the first cell (module docstring) is not a cell
        buf.append(line[2:] if kind == "markdown" and line.startswith("# ") else ("" if kind == "markdown" and line == "#" else line))
    if kind is not None:
        cells.append((kind, "\n".join(buf).strip("\n")))
    return [c for c in cells if c[1].strip()]


def notebook(text: str) -> dict:
    out = []
    for kind, src in cells_of(text):
        lines = src.splitlines(keepends=True)
        cell = {"cell_type": kind, "metadata": {}, "source": lines}
        if kind == "code":
            cell.update({"execution_count": None, "outputs": []})
        out.append(cell)
    return {"cells": out, "metadata": {"kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"},
                                       "language_info": {"name": "python"}}, "nbformat": 4, "nbformat_minor": 5}


def scripts() -> list[Path]:
    return sorted(p for p in HERE.glob("[0-9][0-9]_*.py"))


def main() -> int:
    for py in scripts():
        nb = py.with_suffix(".ipynb")
        nb.write_text(json.dumps(notebook(py.read_text()), indent=1, ensure_ascii=False) + "\n")
        print(f"{py.name} -> {nb.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
