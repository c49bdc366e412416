"""Sweeps (issue 8): each metric against a hand-computed value, the harness's outputs and resume,
bad sweep files, and the trade-off being real: error falls as steps grow (relief, cells)."""

from __future__ import annotations

import csv
import math
import os
import re
from pathlib import Path

import jax
import numpy as np
import pytest

from jskel import cli
from jskel.probe.metrics import compare, depth_in_pixels, pareto_front, ssim, uv_rmse
from jskel.rays import Hit
from jskel.measure.grid import Range

ROOT = Path(__file__).resolve().parent.parent


def _hits(t, normal=None, uv=None, prim=None):
    t = np.asarray(t, np.float64)
    n = t.shape[0]
    return Hit(t, np.zeros((n, 3)), np.zeros((n, 3)) if normal is None else np.asarray(normal, float),
               np.zeros((n, 2)) if uv is None else np.asarray(uv, float), np.zeros(n, np.int32) if prim is None else np.asarray(prim))


def test_compare_metrics_on_a_hand_computed_case():
    inf = np.inf
    a = _hits([1.0, 2.0, inf, inf, 4.0], normal=[[1, 0, 0], [0, 1, 0], [0, 0, 0], [0, 0, 0], [0, 0, 1]],
              uv=[[0.99, 0.5], [0.2, 0.2], [0, 0], [0, 0], [0.5, 0.5]], prim=[3, 4, -1, -1, 7])
    b = _hits([1.5, inf, 3.0, inf, 4.0], normal=[[0, 1, 0], [0, 0, 0], [1, 0, 0], [0, 0, 0], [0, 0, 1]],
              uv=[[0.01, 0.2], [0, 0], [0, 0], [0, 0], [0.5, 0.5]], prim=[3, -1, 2, -1, 8])
    rgb = np.full((5, 3), 0.5)
    out = compare(a, b, rgb, rgb + 0.1)
    assert out["hit_miss_pct"] == pytest.approx(40.0)  # pixels 1 and 2 of 5
    assert out["pixels_hit_both"] == 2
    assert out["prim_mismatch_pct"] == pytest.approx(60.0)  # pixels 1, 2, 4
    assert out["depth_rmse"] == pytest.approx(math.sqrt(0.25 / 2))
    assert out["depth_max"] == pytest.approx(0.5)
    assert out["normal_deg_mean"] == pytest.approx(45.0)  # 90 and 0 degrees
    assert out["normal_deg_max"] == pytest.approx(90.0)
    # u wraps: 0.99 and 0.01 are 0.02 apart; v differs by 0.3; the other pixel agrees
    assert out["uv_rmse"] == pytest.approx(math.sqrt((0.02**2 + 0.3**2) / 2))
    assert out["image_rmse"] == pytest.approx(0.1)
    assert out["psnr_db"] == pytest.approx(20.0)


def test_uv_rmse_wraps_u_only():
    assert uv_rmse([[0.0, 0.95]], [[0.0, 0.05]]) == pytest.approx(0.9)  # v does not wrap
    assert uv_rmse([[0.95, 0.0]], [[0.05, 0.0]]) == pytest.approx(0.1)


def test_ssim_of_two_flat_images_is_the_luminance_term():
    """Flat images have no variance, so SSIM = (2 a b + C1) / (a^2 + b^2 + C1), C1 = (0.01 L)^2."""
    a, b = 0.5, 0.6
    c1 = 0.01**2
    got = ssim(np.full((64, 3), a), np.full((64, 3), b), (8, 8))
    assert got == pytest.approx((2 * a * b + c1) / (a * a + b * b + c1), rel=1e-9)
    assert ssim(np.full((64, 3), a), np.full((64, 3), a), (8, 8)) == pytest.approx(1.0)
    with pytest.raises(ValueError, match="ssim"):
        ssim(np.zeros((4, 3)), np.zeros((4, 3)), (2, 2))


def test_depth_error_in_pixel_footprints():
    # fov 90 degrees, 100 rows: a pixel is 2 * 10 / 100 = 0.2 high at distance 10
    out = depth_in_pixels([10.1, 10.0, np.inf, 20.0], [10.0, 10.0, 5.0, 20.8], 90.0, 100)
    # errors 0.5 px, 0 px, (miss), 0.8 / 0.416 = 1.923 px
    assert out["depth_px_max"] == pytest.approx(0.8 / (20.8 * 0.02))
    want = np.quantile([0.5, 0.0, 0.8 / (20.8 * 0.02)], 0.99)
    assert out["depth_px_p99"] == pytest.approx(want)


def test_pareto_front_and_ranges():
    t = [1.0, 2.0, 3.0, 2.5]
    e = [0.5, 0.2, 0.1, 0.3]  # the last is beaten by (2.0, 0.2)
    assert pareto_front(t, e).tolist() == [True, True, True, False]
    assert Range(start=8, stop=256, num=6, log=True, integer=True).values() == [8, 16, 32, 64, 128, 256]
    assert Range(start=0, stop=1, num=5).values() == [0.0, 0.25, 0.5, 0.75, 1.0]
    with pytest.raises(ValueError, match="log range"):
        Range(start=0, stop=1, num=3, log=True)


def test_one_grid_expansion_for_bench_and_sweep():
    """``grid.expand``: an explicit list as written; a mapping's cartesian product with the first
    key slowest and ranges expanded; the bench's ``sweep`` and the sweep's ``vary`` both use it."""
    from jskel.measure.bench import BenchFile
    from jskel.measure.grid import expand, overrides_of
    from jskel.measure.sweep import SweepFile

    explicit = [{}, {"a": 1}, {"a": 1}]
    assert expand(explicit) == explicit
    got = expand({"a": [1, 2], "b": Range(start=0, stop=1, num=3), "c": ["x"]})
    want = [{"a": a, "b": b, "c": "x"} for a in (1, 2) for b in (0.0, 0.5, 1.0)]
    assert got == want
    assert overrides_of({"object.steps": 8, "m": "geometric", "v": [1, 2]}) == ['object.steps=8', 'm="geometric"', "v=[1, 2]"]
    bench = BenchFile(scenes=["x.yaml"], sweep={"a": [1, 2], "b": [3, 4]})
    sweep = SweepFile(base="x.yaml", vary={"a": [1, 2], "b": [3, 4]})
    assert bench.settings() == sweep.grid() == [{"a": 1, "b": 3}, {"a": 1, "b": 4}, {"a": 2, "b": 3}, {"a": 2, "b": 4}]
    assert BenchFile(scenes=["x.yaml"]).settings() == []


def test_warm_runs_compile_apart_then_warm_up_then_time():
    """``timing.warm_runs``: the first call (the compile) is kept apart, ``warmup - 1`` more are
    untimed, then ``runs`` are timed; ``spread`` is their median, minimum and maximum."""
    from jskel.probe.timing import spread, warm_runs

    calls = []
    out = warm_runs(lambda: calls.append(len(calls)) or len(calls) - 1, runs=3, warmup=2)
    assert calls == [0, 1, 2, 3, 4] and out.first == 0 and out.warm == [2, 3, 4]
    calls.clear()
    out = warm_runs(lambda: calls.append(len(calls)) or len(calls) - 1, runs=2, warmup=0)  # the compile still comes first
    assert out.first == 0 and out.warm == [1, 2]
    s = spread([0.3, 0.1, 0.2, 0.9])
    assert (s.median, s.min, s.max) == (pytest.approx(0.25), 0.1, 0.9)


def _write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def _rows(path: Path):
    with path.open(newline="") as f:
        return list(csv.DictReader(f))


TINY = """base: {base}
set: [camera.width=32, camera.height=32, render.chunk=1024, object.accel=bvh]
vary:
  object.normals: [interpolated, geometric]
  object.packet: [0, 256]
reference: [object.normals=interpolated, object.packet=0]
metrics: [normal_deg_mean, hit_miss_pct, depth_rmse, ssim, memory_bytes]
runs: 2
warmup: 1
"""


def test_tiny_sweep_writes_every_output_and_resumes(tmp_path, monkeypatch):
    from jskel.measure import sweep as sweep_mod

    spec = _write(tmp_path / "tiny.yaml", TINY.format(base=ROOT / "experiments" / "saguaro.yaml"))
    out = tmp_path / "out"
    assert cli.main(["sweep", str(spec), "--out", str(out)]) == 0
    rows = _rows(out / "results.csv")
    assert len(rows) == 4
    want = ["object.normals", "object.packet", "compile_s", "compiled", "loaded", "executables_loaded", "time_median_s", "time_min_s", "time_max_s", "runs", "rays",
            "rays_per_s", "normal_deg_mean", "hit_miss_pct", "depth_rmse", "ssim", "memory_bytes", "hit_fraction",
            "device", "jax", "dtype", "setting"]
    assert list(rows[0]) == want
    # the programs each setting handed to XLA (compiled, or loaded from the persistent cache)
    counts = [(int(r["compiled"]), int(r["loaded"]), int(r["executables_loaded"])) for r in rows]
    assert all(min(c) >= 0 for c in counts)
    assert sum(map(sum, counts)) >= 2, counts  # the two packet settings' programs at least (a reference's counted with its row)
    for r in rows:
        assert float(r["time_min_s"]) <= float(r["time_median_s"]) <= float(r["time_max_s"])
        assert int(r["rays"]) == 1024 and int(r["runs"]) == 2 and int(r["memory_bytes"]) > 0
        assert float(r["hit_miss_pct"]) == 0.0  # normals and packets change no hit
        geometric = r["object.normals"] == "geometric"
        assert (float(r["normal_deg_mean"]) > 0.1) == geometric
        assert (float(r["ssim"]) < 1.0) == geometric
    assert (out / "pareto.png").exists()
    report = (out / "report.md").read_text()
    assert "pareto.png" in report and report.count("\n| ") == 2 + 4  # header, rule, 4 rows
    # the report says what wrote it: the command as typed, the machine, the date and the versions
    assert f"by `python -m jskel sweep {spec} --out {out}` on {os.cpu_count()}-core " in report
    assert f"jax {jax.__version__}" in report and re.search(r"Written 20\d\d-\d\d-\d\dT", report)
    # resume: drop two rows, count the settings measured again, keep the others untouched
    with (out / "results.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=want)
        w.writeheader()
        w.writerows(rows[:2])
    calls = []
    real = sweep_mod.measure
    monkeypatch.setattr(sweep_mod, "measure", lambda *a, **k: calls.append(1) or real(*a, **k))
    assert cli.main(["sweep", str(spec), "--out", str(out)]) == 0
    again = _rows(out / "results.csv")
    assert len(calls) == 2 and len(again) == 4
    assert again[:2] == rows[:2]
    assert sorted(r["setting"] for r in again) == sorted(r["setting"] for r in rows)


# the parallel run's sweep: block culling (each worker process compiles its own programs, and the
# BVH's compile twice as long), a traced camera value varied next to a static option
PAR = """base: {base}
set: [camera.width=32, camera.height=32, render.chunk=1024, object.accel=blocks]
vary:
  object.normals: [interpolated, geometric]
  camera.fov_deg: [36, 40]
reference: [object.normals=interpolated]
metrics: [normal_deg_mean, hit_miss_pct, depth_rmse, ssim, memory_bytes]
runs: 2
warmup: 1
"""


def test_parallel_workers_measure_the_same_errors(tmp_path):
    """Two spawned worker processes measure the tiny sweep: the same settings and the same
    (deterministic) errors as one process; only the timings may differ."""
    base = ROOT / "experiments" / "saguaro.yaml"
    seq = _write(tmp_path / "seq.yaml", PAR.format(base=base))
    par = _write(tmp_path / "par.yaml", PAR.format(base=base) + "parallel: 2\n")
    assert cli.main(["sweep", str(seq), "--out", str(tmp_path / "a")]) == 0
    assert cli.main(["sweep", str(par), "--out", str(tmp_path / "b")]) == 0
    a = {r["setting"]: r for r in _rows(tmp_path / "a" / "results.csv")}
    b = {r["setting"]: r for r in _rows(tmp_path / "b" / "results.csv")}
    assert set(a) == set(b) and len(a) == 4
    for k in a:
        for m in ("normal_deg_mean", "hit_miss_pct", "depth_rmse", "ssim", "memory_bytes", "rays"):
            assert a[k][m] == b[k][m], (k, m)
    assert "2 worker processes" in (tmp_path / "b" / "report.md").read_text()


@pytest.mark.parametrize("body,needle", [
    ("vary: {object.normals: [interpolated]}\nmetrics: [depth_rmsx]", "metrics: unknown 'depth_rmsx'"),
    ("vary: {}", "settings: give 'vary'"),
    ("vary: {object.normals: [interpolated]}\nsettings: [{object.normals: geometric}]", "not both"),
    ("vary: {object.normalz: [interpolated]}", "object.normalz: unknown key"),
    ("vary: {object.packet: [-1]}", "object.packet"),
    ("vary: {object.packet: {start: 1, stop: 2}}", "num"),
])
def test_bad_sweep_files_fail_with_one_line_naming_the_key(tmp_path, capsys, body, needle):
    spec = _write(tmp_path / "bad.yaml", f"base: {ROOT / 'experiments' / 'saguaro.yaml'}\n{body}\n")
    assert cli.main(["sweep", str(spec), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert needle in err and err.startswith("jskel: error:")
    assert not (tmp_path / "o").exists()


def _falls(vals, slack=1.05):
    return all(b <= a * slack for a, b in zip(vals, vals[1:])) and vals[-1] < vals[0]


def test_relief_error_falls_as_steps_grow(tmp_path):
    """The relief march against a 512-step reference (float32 here; the committed sweep files
    use float64): depth error and hit/miss disagreement fall as the steps grow."""
    spec = _write(tmp_path / "relief.yaml", f"""base: {ROOT / 'experiments' / 'relief_column.yaml'}
set: [camera.width=48, camera.height=48, render.chunk=2304, object.relief.bisection=0]
vary: {{object.relief.steps: [4, 64]}}
reference: [object.relief.steps=512, object.relief.bisection=8]
metrics: [depth_rmse, hit_miss_pct]
runs: 1
warmup: 0
""")
    assert cli.main(["sweep", str(spec), "--out", str(tmp_path / "o")]) == 0
    rows = _rows(tmp_path / "o" / "results.csv")
    assert [int(r["object.relief.steps"]) for r in rows] == [4, 64]
    assert _falls([float(r["depth_rmse"]) for r in rows])
    assert _falls([float(r["hit_miss_pct"]) + 1e-3 for r in rows])


def test_cell_error_falls_as_steps_grow(tmp_path):
    """Cell objects: the % of pixels showing the wrong cell and the depth error fall as the
    linear-search step shrinks (reference 1/1024 of a tile), the trend of Sec. 5.3."""
    exp = _write(tmp_path / "cells.yaml", f"""name: small_torus_cells
object:
  type: cells
  base: {{type: torus, major: 1.0, minor: 0.45}}
  tile_map: {{type: voronoi, resolution: 16, cells: 8, seed: 0}}
  tiles: 6
  search: linear
  steps_per_tile: 16
  bisection: 10
  cache: {tmp_path / 'cache'}
camera: {{eye: [0.0, 2.2, 2.6], target: [0.0, 0.0, 0.0], up: [0, 1, 0], fov_deg: 45, width: 48, height: 36}}
""")
    spec = _write(tmp_path / "sweep.yaml", f"""base: {exp}
set: [render.chunk=1728]
vary: {{object.steps_per_tile: [2, 8, 32]}}
reference: [object.steps_per_tile=1024]
metrics: [prim_mismatch_pct, depth_rmse]
runs: 1
warmup: 0
""")
    assert cli.main(["sweep", str(spec), "--out", str(tmp_path / "o")]) == 0
    rows = _rows(tmp_path / "o" / "results.csv")
    assert _falls([float(r["prim_mismatch_pct"]) + 1e-3 for r in rows])
    assert _falls([float(r["depth_rmse"]) for r in rows])


def test_equal_error_picks_the_smallest_mesh_at_most_as_wrong():
    from jskel.measure.results import equal_error

    rows = [
        {"setting": "a", "depth_rmse": "0.02", "hit_miss_pct": "0.5", "time_median_s": "0.1"},
        {"setting": "b", "depth_rmse": "0.005", "hit_miss_pct": "0.1", "time_median_s": "0.3"},
        {"setting": "m0", "peer.level": "0", "triangles": "100", "depth_rmse": "0.03", "hit_miss_pct": "0.9", "time_median_s": "0.01"},
        {"setting": "m1", "peer.level": "1", "triangles": "400", "depth_rmse": "0.01", "hit_miss_pct": "0.4", "time_median_s": "0.01"},
        {"setting": "m2", "peer.level": "2", "triangles": "1600", "depth_rmse": "0.004", "hit_miss_pct": "0.2", "time_median_s": "0.02"},
    ]
    got = {e["setting"]: e["triangles"] for e in equal_error(rows, "depth_rmse")}
    # a: m1 is at most as wrong in both; b: m2's depth error passes but its hit/miss (0.2) does not
    assert got == {"a": 400, "b": None}


def test_a_peer_needs_a_reference(tmp_path, capsys):
    spec = _write(tmp_path / "p.yaml", f"base: {ROOT / 'experiments' / 'relief_column.yaml'}\n"
                  "vary: {object.relief.steps: [8]}\npeer: relief_mesh\n")
    assert cli.main(["sweep", str(spec), "--out", str(tmp_path / "o")]) == 2
    assert "peer: relief_mesh is scored against the reference" in capsys.readouterr().err


