"""Procedural scenes have the paper's segment counts; shading matches its closed form."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from jskel import frusta
from jskel.rays import Hit
from jskel.render import Lights, Shading, shade_one
from jskel.scenes import generate


@pytest.mark.parametrize("name, count", [("saguaro", 30), ("aloe", 229), ("well", 8), ("lsystem_tree", 4374)])
def test_scene_segment_counts_and_valid(name, count):
    j, r, p, c = generate(name, 0, {})
    arrays, topo, _ = frusta.frusta_from_skeleton(j, r, p)  # validates: raises on a bad skeleton
    assert arrays.h.shape[0] == count
    assert c.shape == (j.shape[0], 3)
    assert np.all(arrays.h > 0) and np.all(np.isfinite(arrays.nt)) and np.all(np.isfinite(arrays.nb))


def test_unknown_generator_option_is_named():
    with pytest.raises(ValueError, match=r"object\.skeleton\.options\.branches"):
        generate("lsystem_tree", 0, {"branches": 3})


def test_lambert_blinn_phong_closed_form():
    n = np.array([0.0, 0.0, 1.0])
    d = np.array([0.0, -0.6, -0.8])  # towards the surface
    l = np.array([0.0, 0.6, 0.8])
    albedo = np.array([0.5, 0.4, 0.3])
    hit = Hit(jnp.float32(2.0), jnp.zeros(3), jnp.asarray(n, jnp.float32), jnp.zeros(2), jnp.int32(0))
    lights = Lights(jnp.asarray([l], jnp.float32), jnp.asarray([[1.0, 0.9, 0.8]], jnp.float32))
    sh = Shading(jnp.float32(0.1), jnp.float32(0.3), jnp.float32(16.0), jnp.asarray([0.0, 0.0, 0.0], jnp.float32))
    got = np.asarray(shade_one(hit, jnp.asarray(d, jnp.float32), jnp.asarray(albedo, jnp.float32), lights, sh))
    ndl = n @ l
    hv = (l - d) / np.linalg.norm(l - d)
    want = 0.1 * albedo + np.array([1.0, 0.9, 0.8]) * (albedo * ndl + 0.3 * (n @ hv) ** 16)
    np.testing.assert_allclose(got, want, rtol=1e-5)
    miss = hit._replace(t=jnp.float32(jnp.inf))
    np.testing.assert_allclose(np.asarray(shade_one(miss, jnp.asarray(d, jnp.float32), jnp.asarray(albedo, jnp.float32), lights, sh)), 0.0)


def test_texture_through_uv(tmp_path):
    import imageio.v3 as iio

    img = np.zeros((2, 4, 3), np.uint8)
    img[:, :2] = (255, 0, 0)  # u in [0, 0.5): red
    img[:, 2:] = (0, 0, 255)  # u in [0.5, 1): blue
    path = tmp_path / "tex.png"
    iio.imwrite(path, img)
    cfg = frusta.FrustaConfig.model_validate(
        {"type": "frusta", "texture": str(path),
         "skeleton": {"joints": [[0, 0, 0], [0, 1, 0]], "radii": [0.5, 0.5], "parents": [-1, 0]}}
    )
    b = frusta.build(cfg)
    for u, want in ((0.25, (1, 0, 0)), (0.75, (0, 0, 1))):
        hit = Hit(jnp.float32(1.0), jnp.zeros(3), jnp.zeros(3), jnp.asarray([u, 0.5], jnp.float32), jnp.int32(0))
        np.testing.assert_allclose(np.asarray(frusta.albedo(b.params, b.static, hit)), want, atol=1e-6)
    bad = cfg.model_copy(update={"texture": str(tmp_path / "missing.png")})
    with pytest.raises(ValueError, match=r"object\.texture"):
        frusta.build(bad)
