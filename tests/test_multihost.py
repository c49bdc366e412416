"""Several hosts (issue 6): two processes on loopback, started with the JSKEL_* variables, each
render their share and process 0 writes the gathered image, equal bit for bit to one process."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
# the saguaro with block culling: what is tested is how hosts share chunks, whatever the cast, and
# this object's render compiles in half the time of a BVH's (each of the three processes compiles)
ARGS = ["render", "experiments/saguaro.yaml", "--set", "camera.width=48", "--set", "camera.height=40", "--set", "render.chunk=256",
        "--set", "render.progress=false", "--set", "object.accel=blocks"]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_two_processes_render_the_one_process_image(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    one = subprocess.run([sys.executable, "-m", "jskel", *ARGS, "--out", str(tmp_path / "one")], cwd=ROOT, env=env,
                         capture_output=True, text=True, timeout=600)
    assert one.returncode == 0, one.stderr[-2000:]
    port = _free_port()
    procs = []
    for k in range(2):
        e = dict(env, JSKEL_COORDINATOR=f"127.0.0.1:{port}", JSKEL_NUM_PROCESSES="2", JSKEL_PROCESS_ID=str(k))
        procs.append(subprocess.Popen([sys.executable, "-m", "jskel", *ARGS, "--out", str(tmp_path / "two")], cwd=ROOT, env=e,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (o, e) in zip(procs, outs):
        assert p.returncode == 0, e[-2000:]
    import json

    run = json.loads((tmp_path / "two" / "run.json").read_text())
    assert run["processes"] == 2
    for name in ("depth", "prim", "normal", "uv"):
        a = np.load(tmp_path / "one" / f"{name}.npy")
        b = np.load(tmp_path / "two" / f"{name}.npy")
        assert np.array_equal(a, b, equal_nan=True), name
    assert (tmp_path / "one" / "image.png").read_bytes() == (tmp_path / "two" / "image.png").read_bytes()
    assert np.isfinite(np.load(tmp_path / "one" / "depth.npy")).mean() > 0.02


SWEEP = """base: {base}
set: [camera.width=32, camera.height=24, render.chunk=256, render.progress=false, object.accel=blocks]
vary: {{object.normals: [interpolated, geometric]}}
reference: [object.normals=interpolated]
metrics: [normal_deg_mean, hit_miss_pct, depth_rmse]
runs: 1
warmup: 0
"""


def test_two_processes_run_a_sweep_as_one(tmp_path):
    """A sweep under the JSKEL_* variables: both processes render every setting together and
    process 0 writes results.csv, with the errors of a one-process sweep."""
    import csv

    spec = tmp_path / "sweep.yaml"
    spec.write_text(SWEEP.format(base=ROOT / "experiments" / "saguaro.yaml"))
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    one = subprocess.run([sys.executable, "-m", "jskel", "sweep", str(spec), "--out", str(tmp_path / "one")], cwd=ROOT,
                         env=env, capture_output=True, text=True, timeout=600)
    assert one.returncode == 0, one.stderr[-2000:]
    port = _free_port()
    procs = []
    for k in range(2):
        e = dict(env, JSKEL_COORDINATOR=f"127.0.0.1:{port}", JSKEL_NUM_PROCESSES="2", JSKEL_PROCESS_ID=str(k))
        procs.append(subprocess.Popen([sys.executable, "-m", "jskel", "sweep", str(spec), "--out", str(tmp_path / "two")],
                                      cwd=ROOT, env=e, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (o, e) in zip(procs, outs):
        assert p.returncode == 0, e[-2000:]
    rows = [{r["setting"]: r for r in csv.DictReader((tmp_path / d / "results.csv").open())} for d in ("one", "two")]
    assert set(rows[0]) == set(rows[1]) and len(rows[0]) == 2
    for k in rows[0]:
        for m in ("normal_deg_mean", "hit_miss_pct", "depth_rmse", "rays"):
            assert rows[0][k][m] == rows[1][k][m], (k, m)
    assert float(rows[1]['{"object.normals": "geometric"}']["normal_deg_mean"]) > 0.1
