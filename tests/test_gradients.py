"""Derivatives of hit distances (issue 9): the implicit tracers' and the relief march's t
differentiate through the implicit-function theorem (a bisection loop alone gives exactly zero),
the closed-form frusta t as it is, and a BVH traversal's t through its winning segment's closed
form (in the skeleton, through the device rebuild); all checked against finite differences in float64 by
``jax.test_util.check_grads`` (forward and reverse mode) in a process of their own, since the
test workers stay in float32."""

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


def test_hit_distances_have_the_derivatives_finite_differences_give():
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    p = subprocess.run([sys.executable, str(ROOT / "tests" / "scripts" / "gradients_f64.py")], cwd=ROOT, env=env,
                       capture_output=True, text=True, timeout=900)
    assert p.returncode == 0, p.stderr[-3000:]
    checked = json.loads(p.stdout.strip().splitlines()[-1])["checked"]
    assert checked == {"implicit_lipschitz": 2, "implicit_bisection": 2, "implicit_naive": 2, "relief": 3, "frusta": 2,
                       "fit_distance_random": 6, "fit_distance_hard": 4, "cells": 2, "frusta_bins": 6}


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
