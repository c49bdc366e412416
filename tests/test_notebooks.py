"""Notebooks (issues 11 and 28): every stored .ipynb holds its paired script's cells with the
outputs of one run top to bottom (the documentation shows them; ``python notebooks/pair.py
--execute`` stores them), and every notebook runs top to bottom at the reduced size CI uses
(``JSKEL_NOTEBOOK_SMALL=1``).

The cells are run in this process from the paired script, which is what executing the
notebook runs (the pairing is checked first); each notebook gets a fresh namespace."""

from __future__ import annotations

import importlib.util
import json
import re
import warnings
from datetime import datetime, timedelta
from pathlib import Path

import pytest

NB = Path(__file__).resolve().parent.parent / "notebooks"
spec = importlib.util.spec_from_file_location("nb_pair", NB / "pair.py")
pair = importlib.util.module_from_spec(spec)
spec.loader.exec_module(pair)
SCRIPTS = pair.scripts()


MAX_BYTES = 400_000  # a stored notebook, its images included


def test_every_theme_has_a_notebook_stored_with_the_outputs_of_one_run():
    names = [p.stem for p in SCRIPTS]
    assert names == ["01_frusta", "02_relief", "03_implicit", "04_cells", "05_sweeps", "06_fitting"]
    for py in SCRIPTS:
        nb = py.with_suffix(".ipynb")
        stored = json.loads(nb.read_text())
        assert pair.same_cells(stored, py.read_text()), f"{py.name}: run python notebooks/pair.py --execute"
        code = [c for c in stored["cells"] if c["cell_type"] == "code"]
        assert [c["execution_count"] for c in code] == list(range(1, len(code) + 1)), f"{nb.name}: not run once top to bottom"
        errors = [o.get("ename") for c in code for o in c["outputs"] if o["output_type"] == "error"]
        assert not errors, f"{nb.name}: stored errors {errors}"
        assert any("image/png" in o.get("data", {}) for c in code for o in c["outputs"]), f"{nb.name}: no figure stored"
        assert "widgets" not in stored["metadata"], f"{nb.name}: widget state stored (a view shows its image)"
        assert nb.stat().st_size <= MAX_BYTES, f"{nb.name}: {nb.stat().st_size} bytes (keep its figures small)"


def _when(text: str) -> datetime:
    return datetime.fromisoformat(text.replace("Z", "+00:00"))


@pytest.mark.parametrize("script", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_stored_outputs_carry_the_provenance_of_their_run(script):
    """Each stored notebook names the run whose outputs it holds (issue 28): date, commit of a clean
    checkout, machine, devices, command, seconds and versions in its metadata, and a visible cell
    after the title saying the same; the run's start and seconds enclose every cell's execution
    times that nbconvert recorded, so the provenance is that of these outputs."""
    stored = json.loads(script.with_suffix(".ipynb").read_text())
    p = stored["metadata"].get("jskel", {}).get("provenance")
    assert p is not None, f"{script.stem}: no provenance stored: run python notebooks/pair.py --execute"
    assert set(p) >= {"date", "commit", "machine", "devices", "command", "versions", "seconds"}
    assert re.fullmatch(r"[0-9a-f]{7,40}", p["commit"]), f"{script.stem}: commit {p['commit']!r} (run on a clean checkout)"
    assert p["command"].startswith("python notebooks/pair.py --execute") and p["machine"] and p["devices"]
    assert {"jskel", "jax", "jaxlib", "numpy", "python"} <= set(p["versions"])
    start, end = _when(p["date"]), _when(p["date"]) + timedelta(seconds=p["seconds"] + 1)  # date is to the second
    times = [_when(t) for c in stored["cells"] for t in c["metadata"].get("execution", {}).values()]
    code = [c for c in stored["cells"] if c["cell_type"] == "code"]
    assert len(times) >= 2 * len(code), f"{script.stem}: cells' execution times not recorded"
    assert start <= min(times) and max(times) <= end, f"{script.stem}: cells ran {min(times)}..{max(times)}, outside the run {start}..{end}"
    shown = [c for c in stored["cells"] if c.get("id") == pair.PROVENANCE]
    assert len(shown) == 1 and stored["cells"].index(shown[0]) == 1 and shown[0]["cell_type"] == "markdown"
    text = "".join(shown[0]["source"])
    for value in [p["date"], p["commit"], p["machine"], p["command"], *p["devices"], *p["versions"].values()]:
        assert value in text, f"{script.stem}: the visible provenance does not say {value!r}"


@pytest.mark.parametrize("script", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_notebook_runs_at_reduced_size(script, monkeypatch):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    monkeypatch.setenv("JSKEL_NOTEBOOK_SMALL", "1")
    monkeypatch.chdir(NB)
    src = "\n\n".join(s for kind, s in pair.cells_of(script.read_text()) if kind == "code")
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*non-interactive.*")  # plt.show() under Agg
        exec(compile(src, str(script), "exec"), {"__name__": "__notebook__"})
    plt.close("all")
