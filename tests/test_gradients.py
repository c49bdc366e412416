"""Derivatives of hit distances (issues 9 and 29) through each representation's batch
intersection, the path renders and fits take: the implicit tracers' and the relief march's t
differentiate through the implicit-function theorem (a bisection loop alone gives exactly zero),
the closed-form frusta t as it is, a BVH traversal's t through its winning segment's closed form
(in the skeleton, through the device rebuild), a cell object's through the voxel face it
crosses, a mesh's through its winning triangle; every mode of every representation (and the
fitting's distance) checked against finite differences in float64, forward and reverse mode
(``jax.test_util.check_jvp`` / ``check_vjp``, what ``check_grads`` runs), in a process of its
own, since the test workers stay in float32."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parent.parent


# every check the script runs by default, with how many it makes of each
EXPECTED = {f"frusta_{m}": 8 for m in ("none", "blocks", "bins", "packets", "walks", "kernel", "skeleton")} | {
    "relief_fixed": 8, "relief_exact_bent": 8, "relief_exact_texels": 8}
EXPECTED |= {f"implicit_{m}": 8 for m in ("lipschitz", "bisection", "naive", "exact", "exact_tubes")} | {"cells_first_hit": 8, "cells_refraction": 8, "cells_voxels": 8}
EXPECTED |= {"mesh_packets": 8, "mesh_walks": 8}
# hypothesis' three examples and the two ends, at scales 1e-10 .. 1e10
EXPECTED |= {f"fuzz_{k}": 5 for k in ("frusta", "relief", "implicit", "cells", "mesh", "frusta_bins", "implicit_bisection", "cells_voxels", "mesh_packets")}
EXPECTED |= {"fit_distance_random": 6, "fit_distance_hard": 4}
#: the frusta's and the relief's checks here; the rest in test_gradients_others.py, a file of its
#: own so that the suite's two workers run the halves at once (one process took 139-347 s)
FRUSTA_HALF = [k for k in EXPECTED if k.startswith(("frusta_", "relief_", "fuzz_frusta", "fuzz_relief"))]


def run_checks(names: list[str]) -> dict:
    """Run the float64 script on the checks ``names`` (its argument: a subset by name; the
    fit's two come from ``fit``) and return what it says it checked."""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    asked = sorted({"fit" if n.startswith("fit_distance") else n for n in names})
    p = subprocess.run([sys.executable, str(ROOT / "tests" / "scripts" / "gradients_f64.py"), ",".join(asked)], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1])["checked"]


def test_hit_distances_have_the_derivatives_finite_differences_give():
    """The frusta's traversals and the relief's marches (the other representations and the
    fit: ``test_gradients_others.py``)."""
    assert run_checks(FRUSTA_HALF) == {k: EXPECTED[k] for k in FRUSTA_HALF}


def test_differentiable_root_keeps_the_value_and_gives_the_implicit_derivative():
    """g(t, p) = t^2 - p: the root sqrt(p) found by a bisection loop, whose own derivative is 0,
    gets d sqrt(p)/dp = 1 / (2 sqrt(p)) (float32 here) and the same value bit for bit."""
    from jskel.numerics import differentiable_root

    def bisect(p):
        lo, hi = jnp.float32(0.0), jnp.float32(4.0)
        for _ in range(30):
            mid = 0.5 * (lo + hi)
            lo, hi = jnp.where(mid * mid > p, lo, mid), jnp.where(mid * mid > p, mid, hi)
        return 0.5 * (lo + hi)

    def root(p):
        return differentiable_root(lambda t: t * t - p, bisect(p))

    p = jnp.float32(2.0)
    assert float(jax.grad(bisect)(p)) == 0.0  # what the loop alone gives: no error, no derivative
    assert root(p) == bisect(p)
    np.testing.assert_allclose(float(jax.grad(root)(p)), 1.0 / (2.0 * np.sqrt(2.0)), rtol=1e-5)
    np.testing.assert_allclose(float(jax.jvp(root, (p,), (jnp.float32(1.0),))[1]), 1.0 / (2.0 * np.sqrt(2.0)), rtol=1e-5)


def test_compact_map_differentiates_in_both_modes():
    """``wavefront.compact_map`` (a ``while_loop`` over sub-batches, as many as there are needed
    rows: a trip count JAX cannot reverse) under ``jax.grad`` and ``jax.jvp``: out = sin(w x) where
    needed (three sub-batches of 4), else the base cos(x); the derivatives against their closed
    forms in float64 NumPy, the value against the masked formula."""
    from jskel.wavefront import compact_map

    x = np.linspace(-1.0, 2.0, 19)
    need = np.sin(7 * x) > -0.3
    c = np.cos(3 * x) + 2.0

    def loss(w, xs):
        out = compact_map(lambda r: jnp.sin(w * r), jnp.asarray(need), xs, jnp.cos(xs), 4)
        return jnp.sum(out * c), out

    w = 1.3
    (value, out), (gw, gx) = jax.jit(jax.value_and_grad(loss, argnums=(0, 1), has_aux=True))(jnp.float32(w), jnp.asarray(x, jnp.float32))
    np.testing.assert_allclose(out, np.where(need, np.sin(w * x), np.cos(x)), rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(gw, np.sum(np.where(need, c * x * np.cos(w * x), 0.0)), rtol=1e-5)
    np.testing.assert_allclose(gx, np.where(need, c * w * np.cos(w * x), -c * np.sin(x)), rtol=1e-5, atol=1e-6)
    _, dw = jax.jvp(lambda ww: loss(ww, jnp.asarray(x, jnp.float32))[0], (jnp.float32(w),), (jnp.float32(1.0),))
    np.testing.assert_allclose(dw, gw, rtol=1e-5)
