"""Pair each notebook script ``NN_name.py`` (jupytext "percent" format: cells start at ``# %%``,
markdown cells at ``# %% [markdown]`` with ``# `` prefixed lines) with ``NN_name.ipynb``, stored
with the outputs of one run top to bottom (the documentation shows them as pages).
``python notebooks/pair.py`` rewrites every .ipynb from its script, without outputs;
``python notebooks/pair.py --execute [NN_name ...]`` also runs each (or those named) once in place (``jupyter nbconvert
--execute --inplace``, the [dev] extra installs it) at its full size. The tests check that each
stored notebook's cells are its script's and were run in order, then run the scripts' cells at
a reduced size (which is what executing the notebooks runs).

An executed notebook carries the provenance of its outputs (``jskel.measure.files.provenance``,
taken before any notebook is rewritten, so a clean checkout's commit is not marked ``+changes``;
its ``date`` when that notebook started and the ``seconds`` it ran): in its metadata as
``jskel.provenance`` and as a markdown cell (id ``provenance``, after the title) that its page shows.

The conversion is written by hand (a few lines of nbformat v4 JSON)."""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
import time
from datetime import datetime, timezone
from pathlib import Path

HERE = Path(__file__).resolve().parent
PROVENANCE = "provenance"  # id of the markdown cell that shows where the stored outputs come from


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
    for i, (kind, src) in enumerate(cells_of(text)):
        lines = src.splitlines(keepends=True)
        cell = {"cell_type": kind, "id": f"cell-{i:02d}", "metadata": {}, "source": lines}  # ids: stable across runs
        if kind == "code":
            cell.update({"execution_count": None, "outputs": []})
        out.append(cell)
    return {"cells": out, "metadata": {"kernelspec": {"display_name": "Python 3", "language": "python", "name": "python3"},
                                       "language_info": {"name": "python"}}, "nbformat": 4, "nbformat_minor": 5}


def scripts() -> list[Path]:
    return sorted(p for p in HERE.glob("[0-9][0-9]_*.py"))


def same_cells(stored: dict, text: str) -> bool:
    """Are the cells of the notebook ``stored`` (outputs and all) those of the script ``text``?"""
    want = [(c["cell_type"], "".join(c["source"])) for c in notebook(text)["cells"]]
    return [(c["cell_type"], "".join(c["source"])) for c in stored["cells"] if c.get("id") != PROVENANCE] == want


def provenance_line(p: dict) -> str:
    """Markdown: the command, date, commit, machine, devices, seconds and versions of a run."""
    versions = ", ".join(f"{k} {v}" for k, v in p["versions"].items())
    return (f"*Outputs stored from one run:* `{p['command']}`, started {p['date']} on the code of commit "
            f"`{p['commit'] or 'not recorded'}`, on {p['machine']} ({', '.join(p['devices'])}), "
            f"{p['seconds']:.0f} s; {versions}.")


def stamp(nb: Path, run: dict) -> None:
    """Store ``run`` (a provenance) in ``nb``'s metadata and as its second cell."""
    import nbformat

    book = nbformat.read(nb, as_version=4)
    book.metadata["jskel"] = {"provenance": run}
    book.cells = [c for c in book.cells if c.get("id") != PROVENANCE]
    book.cells.insert(1, nbformat.v4.new_markdown_cell(provenance_line(run), id=PROVENANCE))
    nbformat.validate(book)
    nbformat.write(book, nb)


def execute(nb: Path) -> None:
    """Run ``nb`` top to bottom in a fresh kernel and store its outputs in it (no widget state:
    a stored view shows its image). The kernel imports this checkout's jskel (first on its path)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(HERE.parent), os.environ.get("PYTHONPATH")]))}
    subprocess.run([sys.executable, "-m", "jupyter", "nbconvert", "--to", "notebook", "--execute", "--inplace",
                    "--ExecutePreprocessor.timeout=1200", "--ExecutePreprocessor.store_widget_state=False", str(nb)],
                   check=True, cwd=HERE, env=env)


def main(argv: list[str]) -> int:
    names = [a for a in argv if not a.startswith("--")]  # e.g. 04_cells: only those
    run = None
    if "--execute" in argv:
        sys.path.insert(0, str(HERE.parent))
        from jskel.measure.files import provenance

        run = provenance(shlex.join(["python", "notebooks/pair.py", *argv]))  # before a notebook is rewritten
    for py in scripts():
        if names and py.stem not in names:
            continue
        nb = py.with_suffix(".ipynb")
        nb.write_text(json.dumps(notebook(py.read_text()), indent=1, ensure_ascii=False) + "\n")
        print(f"{py.name} -> {nb.name}")
        if run is not None:
            date, t0 = datetime.now(timezone.utc).isoformat(timespec="seconds"), time.monotonic()
            execute(nb)
            stamp(nb, {**run, "date": date, "seconds": round(time.monotonic() - t0, 1)})
            print(f"  ran {nb.name}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
