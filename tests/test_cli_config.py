"""The CLI end to end, and bad input: one line naming the key and value, exit 2, no compile."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from jskel import cli, executor
from jskel.config import load, validate

from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
SMALL = ["camera.width=48", "camera.height=32", "render.chunk=4096", "render.progress=false"]


def test_render_writes_every_output(tmp_path):
    out = tmp_path / "saguaro"
    rc = cli.main(["render", str(ROOT / "experiments" / "saguaro.yaml"), "--out", str(out), *sum((["--set", s] for s in SMALL), [])])
    assert rc == 0
    depth = np.load(out / "depth.npy")
    normal = np.load(out / "normal.npy")
    uv = np.load(out / "uv.npy")
    prim = np.load(out / "prim.npy")
    assert depth.shape == (32, 48) and depth.dtype == np.float32
    assert normal.shape == (32, 48, 3) and normal.dtype == np.float32
    assert uv.shape == (32, 48, 2) and uv.dtype == np.float32
    assert prim.shape == (32, 48) and prim.dtype == np.int32
    miss = ~np.isfinite(depth)
    assert np.all(np.isposinf(depth[miss])) and np.all(prim[miss] == -1)
    assert 0.02 < (~miss).mean() < 0.9
    assert prim.max() < 30
    import imageio.v3 as iio

    img = iio.imread(out / "image.png")
    assert img.shape == (32, 48, 3) and img.dtype == np.uint8
    run = json.loads((out / "run.json").read_text())
    for key in ("config", "jskel", "jax", "device", "compile_s", "render_s"):
        assert key in run
    assert run["config"]["camera"]["width"] == 48
    assert run["info"]["segments"] == 30


def test_default_experiment_is_embedded():
    exp = load(None)
    obj = exp.objects[0].shape
    assert obj.type == "frusta" and exp.camera.width > 0


def _run(tmp_path, capsys, body: str, *extra):
    p = tmp_path / "exp.yaml"
    p.write_text(body)
    rc = cli.main(["render", str(p), "--out", str(tmp_path / "o"), *extra])
    err = capsys.readouterr().err.strip().splitlines()
    return rc, err


BASE = """
object:
  type: frusta
  skeleton: {joints: [[0,0,0],[0,1,0],[0,2,0]], radii: [0.3, 0.2, 0.1], parents: [-1, 0, 1]}
camera: {eye: [0, 1, 5], target: [0, 1, 0], width: 16, height: 16}
"""


@pytest.fixture
def no_compile(monkeypatch):
    def boom(*a, **k):
        raise AssertionError("compiled despite bad input")

    monkeypatch.setattr(executor, "compile_batch_fn", boom)


@pytest.mark.parametrize(
    "body, needle",
    [
        (BASE.replace("camera:", "camra: {}\ncamera:"), ["camra", "unknown key"]),
        (BASE.replace("width: 16", "width: sixteen"), ["camera.width", "sixteen"]),
        (BASE.replace("0.2, 0.1", "-0.2, 0.1"), ["object.skeleton.radii[1]", "-0.2"]),
        (BASE.replace("0.2, 0.1", ".nan, 0.1"), ["object.skeleton.radii[1]", "nan"]),
        (BASE.replace("[0,2,0]]", "[0,1,0]]"), ["object.skeleton.joints[2]", "zero-length"]),
        (BASE.replace("[-1, 0, 1]", "[2, 0, 1]"), ["object.skeleton.parents", "cycle"]),
        (BASE.replace("eye: [0, 1, 5]", "eye: [0, 6, 0]").replace("target: [0, 1, 0]", "target: [0, 1, 0], up: [0, 1, 0]"), ["camera.up", "up vector"]),
        (BASE.replace("type: frusta", "type: frustum"), ["object.type", "frustum"]),
        (BASE.replace("normals", "x") + "render: {chunk: 0}\n", ["render.chunk", "0"]),
        (BASE + "render: {chunk: big}\n", ["render.chunk", "big", "'auto'"]),  # both branches of int | 'auto', one line
        (BASE.replace("type: frusta", "type: frusta\n  kernel_block: 48"), ["object.kernel_block", "power of two", "48"]),
    ],
    ids=["unknown_key", "wrong_type", "negative_radius", "nan_radius", "zero_length", "cycle", "up_parallel", "unknown_type", "bad_range",
         "union_one_line", "kernel_block"],
)
def test_bad_input_one_line_exit_2(tmp_path, capsys, no_compile, body, needle):
    rc, err = _run(tmp_path, capsys, body)
    assert rc == 2
    assert len(err) == 1, err
    assert err[0].startswith("jskel: error: ")
    for n in needle:
        assert n in err[0], (n, err[0])
    assert "Traceback" not in err[0]


def test_every_bad_key_reported_at_once(tmp_path, capsys, no_compile):
    body = BASE.replace("width: 16", "width: -1").replace("camera:", "extra_key: 1\ncamera:")
    rc, err = _run(tmp_path, capsys, body, "--set", "render.dtype=float16")
    assert rc == 2
    joined = "\n".join(err)
    assert "camera.width" in joined and "extra_key" in joined and "render.dtype" in joined


def test_set_override_applies_and_is_validated(tmp_path, capsys, no_compile):
    rc, err = _run(tmp_path, capsys, BASE, "--set", "camera.fov_deg=200")
    assert rc == 2 and "camera.fov_deg" in err[0] and "200" in err[0]


def test_api_raises_value_error():
    import yaml

    raw = yaml.safe_load(BASE.replace("0.2, 0.1", "-0.2, 0.1"))
    with pytest.raises(ValueError, match=r"object\.skeleton\.radii\[1\]"):
        validate(raw)


def test_cli_process_exit_code(tmp_path):
    p = tmp_path / "bad.yaml"
    p.write_text(BASE.replace("width: 16", "width: 0"))
    r = subprocess.run([sys.executable, "-m", "jskel", "render", str(p), "--out", str(tmp_path / "o")], capture_output=True, text=True)
    assert r.returncode == 2
    assert r.stderr.strip().count("\n") == 0 and "camera.width" in r.stderr


def test_host_devices_are_an_explicit_call_and_a_bad_count_names_the_variable(tmp_path):
    """``import jskel`` leaves JAX's devices and ``XLA_FLAGS`` alone; ``use_host_devices`` asks
    for the count explicitly (``JSKEL_HOST_DEVICES`` or one per core), as the CLI does first
    thing; a count that is not a positive integer stops the CLI with one line naming the
    variable and the value, exit code 2."""
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JSKEL_HOST_DEVICES")}
    code = "import os, jskel, jax; print(repr(os.environ.get('XLA_FLAGS'))); print(len(jax.devices('cpu')))"
    p = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stdout.split() == ["None", "1"], p.stderr[-500:]
    code = "import jskel, jax; n = jskel.use_host_devices(); print(n, len(jax.devices('cpu')))"
    p = subprocess.run([sys.executable, "-c", code], env=dict(env, JSKEL_HOST_DEVICES="3"), capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and p.stdout.split() == ["3", "3"], p.stderr[-500:]
    for bad in ("abc", "0", "-2"):
        p = subprocess.run([sys.executable, "-m", "jskel", "render", "--out", str(tmp_path / "o")], env=dict(env, JSKEL_HOST_DEVICES=bad),
                           capture_output=True, text=True, timeout=120)
        assert p.returncode == 2
        assert p.stderr.strip() == f"jskel: error: JSKEL_HOST_DEVICES: {bad!r} is not a positive integer (XLA host devices to make)"


def test_nothing_in_the_package_imports_the_cli():
    """The CLI only parses and calls: no module of jskel (bench and sweep included) imports it."""
    import ast

    found = []
    for p in (ROOT / "jskel").rglob("*.py"):
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module is not None:
                mods = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
                if node.level == 0 and any(m == "jskel.cli" for m in mods) or node.level > 0 and "cli" in (
                        node.module.split(".")[-1], *(a.name for a in node.names)):
                    found.append(f"{p.relative_to(ROOT)}:{node.lineno}")
            elif isinstance(node, ast.Import) and any(a.name == "jskel.cli" for a in node.names):
                found.append(f"{p.relative_to(ROOT)}:{node.lineno}")
    found = [f for f in found if not f.startswith("jskel/__main__.py")]  # ``python -m jskel`` runs it
    assert found == [], found
