"""Lambert + Blinn-Phong shading with directional lights (traced values: no recompile)."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..numerics import safe_normalize
from ..rays import Hit


class Lights(NamedTuple):
    """L directional lights: ``direction`` (L,3) towards the light, ``radiance`` (L,3)."""

    direction: jnp.ndarray
    radiance: jnp.ndarray


class Shading(NamedTuple):
    ambient: jnp.ndarray
    specular: jnp.ndarray
    shininess: jnp.ndarray
    background: jnp.ndarray  # (3,)


def lights_from_config(lights, dtype) -> Lights:
    if not lights:
        return Lights(jnp.zeros((1, 3), dtype), jnp.zeros((1, 3), dtype))
    d = np.array([l.direction for l in lights], np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rad = np.array([np.asarray(l.color) * l.intensity for l in lights], np.float64)
    return Lights(jnp.asarray(d, dtype), jnp.asarray(rad, dtype))


def shading_from_config(sh, dtype) -> Shading:
    return Shading(
        jnp.asarray(sh.ambient, dtype),
        jnp.asarray(sh.specular, dtype),
        jnp.asarray(sh.shininess, dtype),
        jnp.asarray(sh.background, dtype),
    )


def shade_one(hit: Hit, direction, base_rgb, lights: Lights, sh: Shading):
    """Linear RGB of one pixel: ambient + sum over lights of Lambert and Blinn-Phong terms.

    The shading normal is turned to face the viewer, so interpolated normals (Eq. 8 of
    Bhagvat et al.) that lean away from a grazing eye still shade the visible side.
    """
    d = safe_normalize(direction)
    n = hit.normal
    n = jnp.where(jnp.sum(n * d) > 0, -n, n)
    v = -d
    ndl = jnp.maximum(lights.direction @ n, 0.0)  # (L,)
    hv = safe_normalize(lights.direction + v[None, :])
    ndh = jnp.maximum(hv @ n, 0.0)
    spec = jnp.where(ndl > 0, ndh**sh.shininess, 0.0)
    col = sh.ambient * base_rgb + jnp.sum(
        lights.radiance * (base_rgb[None, :] * ndl[:, None] + sh.specular * spec[:, None]), axis=0
    )
    return jnp.where(jnp.isfinite(hit.t), col, sh.background)


def encode_png(rgb: np.ndarray, gamma: float) -> np.ndarray:
    """Linear float RGB (H,W,3) -> uint8 with display gamma."""
    x = np.clip(np.nan_to_num(rgb, nan=0.0), 0.0, 1.0) ** (1.0 / gamma)
    return (x * 255.0 + 0.5).astype(np.uint8)
