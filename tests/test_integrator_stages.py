"""The integrator's two stages (``render._hits.nearest``): every object casts, the nearest cast
wins, and only the winner is finished (``surface``, ``albedo``), as Mitsuba's
``ray_intersect_preliminary`` / ``compute_surface_interaction``."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jskel import registry
from jskel.config import validate
from jskel.rays import make_rays
from jskel.render._hits import nearest
from jskel.render._scene import build_scene

N = 256
CENTERS = ([0.0, 0.0, 0.0], [0.6, 0.0, -3.0], [-1.0, 0.0, -6.0])  # behind one another, seen overlapping


def test_a_scene_finishes_only_each_rays_nearest_hit(monkeypatch):
    """Three implicit balls, three objects, one behind another and seen overlapping, so that
    many rays that meet a back ball have met a nearer one first: ``surface`` is called for as
    many rays (rows with a hit in its preliminary) as hit something, counted through a
    ``jax.debug.callback`` in a wrapped ``surface``; every hit is the first ball's closed-form
    sphere (the kernel's 0.5 level at rho = sqrt(1 - sqrt(0.5))) and object, object 0 where the rays meet
    it, and the nearest other ball's elsewhere (closed forms, float64)."""
    rep = registry.get("implicit")
    seen = []
    inner = type(rep).surface

    def counted(self, params, static, rays, pre):
        jax.debug.callback(lambda k: seen.append(int(k)), jnp.sum(jnp.isfinite(pre.t)))
        return inner(self, params, static, rays, pre)

    monkeypatch.setattr(type(rep), "surface", counted)
    objects = [{"shape": {"type": "implicit", "threshold": 0.5, "balls": [{"center": c, "radius": 1.0}]}} for c in CENTERS]
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
    for k, c in reversed(list(enumerate(CENTERS))):  # the nearest last: the front ball overwrites
        oc = e - c
        b = d @ oc
        disc = b**2 - (oc @ oc - rho**2)
        t = np.where(disc > 0, -b - np.sqrt(np.maximum(disc, 0.0)), np.inf)
        t_ref, k_ref = np.where(t < t_ref, t, t_ref), np.where(t < t_ref, k, k_ref)
    hits = np.isfinite(t_ref)
    assert 0.3 < hits.mean() < 0.95 and np.sum(k_ref >= 1) >= 5  # the back balls win somewhere
    np.testing.assert_array_equal(np.asarray(hit.obj), k_ref)
    np.testing.assert_allclose(np.asarray(hit.t, np.float64)[hits], t_ref[hits], atol=1e-3)
    assert sum(seen) == hits.sum(), (seen, hits.sum())
