"""The float64 switch: a separate process (x64 is global in JAX, so it is not switched on here)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

HERE = Path(__file__).resolve().parent

SCRIPT = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)  # an entry point may switch it on
    import numpy as np
    import reference as ref
    from jskel import frusta
    from jskel.rays import make_rays
    from test_frusta_random import CASES, _bounds

    joints, radii, parents = CASES["bent_chain"]
    cfg = frusta.FrustaConfig.model_validate({"type": "frusta", "skeleton": {
        "joints": joints.tolist(), "radii": list(radii), "parents": list(map(int, parents)), "offset": [1e4, 0, 0]}})
    b = frusta.build(cfg, np.float64)
    assert b.params.plain.frusta.c1.dtype == np.float64
    lo, hi = _bounds(joints, np.asarray(radii))
    O, D = ref.random_rays(np.random.default_rng(5), lo, hi, 20000)
    segs = ref.segments(joints, radii, parents)
    t_ref, _ = ref.intersect(segs, O, D)
    far = ref.far_from_silhouette(segs, O, D, 1e-6, 1e-4)
    rays = make_rays(O + [1e4, 0, 0] - b.anchor, D, dtype=np.float64)
    hit = jax.jit(lambda p, r: frusta.intersect_batch(p, b.static, r))(b.params, rays)
    t = np.asarray(hit.t)
    assert t.dtype == np.float64
    assert np.all(np.isfinite(t[far]) == np.isfinite(t_ref[far]))
    both = far & np.isfinite(t_ref)
    err = np.abs(t[both] - t_ref[both]).max()
    assert err < 1e-9, err
    print("ok", err, far.mean())
    """
)


def test_float64_matches_reference_to_1e_9():
    r = subprocess.run([sys.executable, "-c", SCRIPT], cwd=HERE, capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.startswith("ok")


import pytest  # noqa: E402


@pytest.mark.parametrize("switch", [["--set", "render.dtype=float64"], ["--x64"]])
def test_cli_float64_render(tmp_path, switch):
    """The precision switch at the entry point: the key, or --x64 (issue 9)."""
    import json

    import numpy as np

    exp = HERE.parent / "experiments" / "well.yaml"
    r = subprocess.run(
        [sys.executable, "-m", "jskel", "render", str(exp), "--out", str(tmp_path), *switch,
         "--set", "camera.width=40", "--set", "camera.height=30"],
        capture_output=True, text=True, timeout=300,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    run = json.loads((tmp_path / "run.json").read_text())
    assert run["config"]["render"]["dtype"] == "float64"
    assert run["params_bytes"] > 0
    depth = np.load(tmp_path / "depth.npy")
    assert depth.dtype == np.float32 and np.isfinite(depth).any()
