"""The integrator's nearest hit over a scene's objects (``render._hits.nearest``): an object
traces only the rays that cross its box before the nearest hit found so far."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jskel import registry
from jskel.config import validate
from jskel.rays import make_rays
from jskel.render._hits import nearest
from jskel.render._scene import build_scene

N = 256
CENTERS = ([0.0, 0.0, 0.0], [1.2, 0.0, -4.0], [-2.2, 0.0, -10.0])  # behind one another, seen overlapping
RADII = (1.0, 2.0, 2.0)  # each ball's box (centre +- radius) lies wholly behind the one before


@pytest.mark.parametrize("listed", [(0, 1, 2), (2, 1, 0)], ids=["front-first", "back-first"])
def test_an_object_behind_the_nearest_hit_so_far_is_not_traced(monkeypatch, listed):
    """Three implicit balls, three objects of one group (traced nearest box first whatever the
    order the file lists them in: front first, and back first), one
    behind another with their boxes apart and seen overlapping, so that many rays that meet a back
    ball have met a nearer one first: the objects' hits computed (``intersect_batch`` rows with a
    finite t, counted through a ``jax.debug.callback`` in a wrapped ``intersect_batch``) are as
    many as the rays that hit something, each ray's nearest found once; every hit is the closed-form
    sphere (the kernel's 0.5 level at rho = sqrt(1 - sqrt(0.5))) of the nearest ball it meets, and
    that ball's object (float64)."""
    rep = registry.get("implicit")
    seen = []
    inner = rep.intersect_batch  # the representation's own, bound

    def counted(params, static, rays):
        h = inner(params, static, rays)
        jax.debug.callback(lambda k: seen.append(int(k)), jnp.sum(jnp.isfinite(h.t)))
        return h

    monkeypatch.setattr(type(rep), "intersect_batch", staticmethod(counted))
    centers, radii = [CENTERS[i] for i in listed], [RADII[i] for i in listed]
    objects = [{"shape": {"type": "implicit", "threshold": 0.5, "balls": [{"center": c, "radius": r}]}} for c, r in zip(centers, radii)]
    raw = {"objects": objects, "camera": {"eye": [0, 0, 5], "target": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 30, "width": 8, "height": 8},
           "lights": [{"direction": [0.4, 0.9, 0.5], "shadows": False}]}
    params, static, eye, _, _ = build_scene(validate(raw), np.float32)
    rng = np.random.default_rng(5)
    d = rng.normal(scale=0.09, size=(N, 3)) + [0.0, 0.0, -1.0]
    d[0] = d[-1] = [0.0, 1.0, 0.0]  # the rows a partial sub-batch repeats: misses, so none is counted twice
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    e = np.asarray(eye, np.float64)
    rays = make_rays(np.zeros((N, 3)), d)
    hit = jax.jit(lambda p, r: nearest(p, static, r, jnp.ones((N,), bool)))(params, rays)
    jax.effects_barrier()
    rho = np.sqrt(1.0 - np.sqrt(0.5))
    t_ref, k_ref = np.full(N, np.inf), np.full(N, -1)
    for k, (c, r) in enumerate(zip(centers, radii)):  # the balls' spheres do not meet: nearest by t
        oc = e - c
        b = d @ oc
        disc = b**2 - (oc @ oc - (rho * r) ** 2)
        t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        t_ref, k_ref = np.where(t < t_ref, t, t_ref), np.where(t < t_ref, k, k_ref)
    hits = np.isfinite(t_ref)
    front = [listed.index(i) for i in range(3)]  # the objects' indices, front ball first
    assert 0.3 < hits.mean() < 0.95 and np.sum(k_ref == front[1]) >= 5 and np.sum(k_ref == front[2]) >= 5  # the back balls win somewhere
    behind = 0  # rays that meet a back ball behind a nearer one: what tracing every box crossed would count again
    for depth in (1, 2):
        k = front[depth]
        oc = e - np.asarray(centers[k])
        b = d @ oc
        nearer = np.isin(k_ref, front[:depth])
        behind += int(np.sum((b**2 - (oc @ oc - (rho * radii[k]) ** 2) > 0) & nearer))
    assert behind >= 5
    np.testing.assert_array_equal(np.asarray(hit.obj), k_ref)
    np.testing.assert_allclose(np.asarray(hit.t, np.float64)[hits], t_ref[hits], atol=1e-3)
    assert sum(seen) == hits.sum(), (seen, hits.sum())
