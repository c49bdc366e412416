"""The latency benchmark's harness (``jskel.measure.latency``), without compiling anything:
its process timing and what it reads back, its cases, and the changes it re-renders after."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np

from jskel.frusta import skeleton_arrays
from jskel.config import load as load_experiment
from jskel.measure.files import read_model
from jskel.measure.latency import LatencyFile, cases, changes, process_env, timed_process

ROOT = Path(__file__).resolve().parent.parent
SAGUARO = ROOT / "experiments" / "saguaro.yaml"


def test_a_process_is_timed_to_its_outputs_and_its_report_read(tmp_path):
    out = tmp_path / "o"
    run = {"compile_s": 1.25, "build_s": 0.5, "render_s": 0.125, "programs": {"compiled": 7, "loaded": 3, "cache_dir": None}}
    code = f"import json, os, time; os.makedirs({str(out)!r}); time.sleep(0.3); open({str(out / 'run.json')!r}, 'w').write({json.dumps(run)!r}); time.sleep(0.4)"
    row = timed_process([sys.executable, "-c", code], process_env(tmp_path / "c"), out, 60)
    assert row["compile_s"] == 1.25 and row["build_s"] == 0.5 and row["render_s"] == 0.125
    assert row["compiled"] == 7 and row["loaded"] == 3
    assert 0.3 <= row["outputs_s"] < row["wall_s"] and row["wall_s"] - row["outputs_s"] >= 0.35
    bad = timed_process([sys.executable, "-c", "import sys; sys.exit('jskel: error: camera.width: bad')"], {}, None, 60)
    assert bad["error"] == "jskel: error: camera.width: bad"


def test_a_fits_first_iteration_is_timed_from_the_process_start(tmp_path):
    """A fake fit process sleeps 0.5 s, notes the time as its first iteration's, sleeps again and
    writes fit.json: the row's ``first_iteration_s`` is those first 0.5 s (and process start-up)."""
    out = tmp_path / "o"
    fit = {"compile_s": 2.5, "seconds": 1.5, "iterations": 9, "programs": {"compiled": 3, "loaded": 1}}
    code = (f"import json, os, time; time.sleep(0.5); f = dict({fit!r}, first_iteration_at=time.time()); time.sleep(0.6); "
            f"os.makedirs({str(out)!r}); open({str(out / 'fit.json')!r}, 'w').write(json.dumps(f))")
    row = timed_process([sys.executable, "-c", code], process_env(tmp_path / "c"), out, 60)
    assert row["compile_s"] == 2.5 and row["fit_s"] == 1.5 and row["iterations"] == 9 and (row["compiled"], row["loaded"]) == (3, 1)
    assert 0.5 <= row["first_iteration_s"] <= row["outputs_s"] - 0.55


def test_each_process_gets_its_own_cache_and_no_bars(monkeypatch, tmp_path):
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", "/elsewhere")
    monkeypatch.setenv("JSKEL_CACHE", "off")
    env = process_env(tmp_path / "c")
    assert env["JSKEL_CACHE_DIR"] == str(tmp_path / "c") and env["CI"] == "1"
    assert "JAX_COMPILATION_CACHE_DIR" not in env and "JSKEL_CACHE" not in env
    spec = read_model(LatencyFile, ROOT / "experiments" / "bench_latency.yaml", []).latency
    labels = [label for label, _ in cases(spec, ROOT / "experiments" / "bench_latency.yaml", tmp_path)]
    assert labels[0] == "default" and "saguaro" in labels and labels[-2].startswith("sweep:") and labels[-1].startswith("fit:")


def test_the_rerender_changes_change_one_thing_each():
    exp = load_experiment(SAGUARO, [])
    obj = exp.objects[0].shape
    j, r, p = skeleton_arrays(obj.skeleton, obj.frame)[:3]
    got = {}
    for name, sets in changes(exp).items():
        e = load_experiment(SAGUARO, sets)
        o = e.objects[0].shape
        got[name] = (e, *skeleton_arrays(o.skeleton, o.frame)[:3])
    e0, j0, r0, p0 = got["none"]
    assert np.array_equal(j0, j) and np.array_equal(r0, r) and np.array_equal(p0, p)
    _, j1, r1, p1 = got["radius"]
    assert np.array_equal(j1, j) and np.array_equal(p1, p)
    (k,) = np.nonzero(r1 != r)[0]
    assert np.isclose(r1[k], 1.2 * r[k], rtol=1e-12)
    ec = got["camera"][0]
    assert np.allclose(np.subtract(ec.camera.eye, exp.camera.eye), [0.5, 0, 0]) and ec.camera.target == exp.camera.target
    es = got["image_size"][0]
    assert (es.camera.width, es.camera.height) == (exp.camera.width + 16, exp.camera.height + 12)
    _, j4, r4, p4 = got["segments"]
    assert len(j4) == len(j) + 1 and np.array_equal(j4[:-1], j) and p4[-1] == len(j) - 1 and np.isclose(r4[-1], 0.8 * r[-1])
    for e, *_ in got.values():
        assert e.render.progress is False


def test_a_sweeps_rows_are_summed_and_a_peers_empty_cells_skipped(tmp_path):
    """A sweep's results.csv: its settings' compile seconds and program counts summed; a peer's
    row leaves those cells empty and is skipped, not an error."""
    import csv

    from jskel.measure.latency import reported

    with (tmp_path / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["setting", "compile_s", "compiled", "loaded"])
        w.writeheader()
        w.writerows([{"setting": "a", "compile_s": 2.5, "compiled": 2, "loaded": 0},
                     {"setting": "b", "compile_s": 0.25, "compiled": 0, "loaded": 1},
                     {"setting": "peer", "compile_s": "", "compiled": "", "loaded": ""}])
    assert reported(tmp_path) == {"compiled": 2, "loaded": 1, "compile_s": 2.75}
