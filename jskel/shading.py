"""Lambert + Blinn-Phong shading with directional and point lights (traced values: no
recompile), and the output transfer to 8-bit sRGB."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from .numerics import dot3, on_device, safe_div, safe_sqrt
from .rays import Hit


class Lights(NamedTuple):
    """L lights: ``direction`` (L,3) towards a directional light, ``radiance`` (L,3).
    ``position`` (L,3) and ``point`` (L,) bool, where given, make light l a point light at
    ``position[l]`` (in the rays' frame) whose radiance falls off as 1 / distance^2."""

    direction: jnp.ndarray
    radiance: jnp.ndarray
    position: jnp.ndarray | None = None
    point: jnp.ndarray | None = None


class Shading(NamedTuple):
    """Device arrays of the shading section: ambient, specular, shininess, background colour."""

    ambient: jnp.ndarray
    specular: jnp.ndarray
    shininess: jnp.ndarray
    background: jnp.ndarray  # (3,)


def lights_from_config(lights, dtype, origin=None) -> Lights:
    """Device arrays of the ``lights`` section; point-light positions are expressed relative to
    ``origin`` (the rays' frame: the anchor, or the eye for scenes) in float64 first."""
    if not lights:
        return Lights(on_device(np.zeros((1, 3)), dtype), on_device(np.zeros((1, 3)), dtype))
    d = np.array([l.direction for l in lights], np.float64)
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    rad = np.array([np.asarray(l.color) * l.intensity for l in lights], np.float64)
    point = np.array([l.type == "point" for l in lights])
    if not point.any():
        return Lights(on_device(d, dtype), on_device(rad, dtype))
    o = np.zeros(3) if origin is None else np.asarray(origin, np.float64)
    pos = np.array([np.asarray(l.position, np.float64) - o if l.type == "point" else np.zeros(3) for l in lights])
    return Lights(on_device(d, dtype), on_device(rad, dtype), on_device(pos, dtype), on_device(point))


def light_at(lights: Lights, p):
    """Per light, at point ``p`` (3,): unit direction towards it (L,3), radiance arriving
    (L,3) and the distance to it (L,) (+inf for directional lights)."""
    if lights.position is None:
        n = lights.direction.shape[0]
        return lights.direction, lights.radiance, jnp.full((n,), jnp.inf, lights.radiance.dtype)
    to = lights.position - p[None, :]
    dist2 = dot3(to, to)
    dist = jnp.sqrt(jnp.maximum(dist2, jnp.finfo(to.dtype).tiny))
    pl = lights.point
    direction = jnp.where(pl[:, None], to / dist[:, None], lights.direction)
    radiance = jnp.where(pl[:, None], lights.radiance / jnp.maximum(dist2, jnp.finfo(to.dtype).tiny)[:, None], lights.radiance)
    return direction, radiance, jnp.where(pl, dist, jnp.inf)


def shading_from_config(sh, dtype) -> Shading:
    """Device arrays of the ``shading`` section (traced: changing them never recompiles)."""
    return Shading(
        on_device(sh.ambient, dtype),
        on_device(sh.specular, dtype),
        on_device(sh.shininess, dtype),
        on_device(sh.background, dtype),
    )


def shade_one(hit: Hit, direction, base_rgb, lights: Lights, sh: Shading):
    """Linear RGB of one pixel: ambient + sum over lights of Lambert and Blinn-Phong terms.

    The shading normal is turned to face the viewer, so interpolated normals (Eq. 8 of
    Bhagvat et al.) that lean away from a grazing eye still shade the visible side.
    """
    col = shade_local(hit.position, hit.normal, direction, base_rgb, lights, sh.ambient, sh.specular, sh.shininess)
    return jnp.where(jnp.isfinite(hit.t), col, sh.background)


def _unit3(v):
    """``v / |v|`` (the zero vector stays zero), with :func:`jskel.numerics.dot3`."""
    return safe_div(v, safe_sqrt(dot3(v, v))[..., None], 0.0)


def facing(normal, direction):
    """``normal`` turned to face against ``direction`` (the side the ray arrives from)."""
    return jnp.where(dot3(normal, direction)[..., None] > 0, -normal, normal)


def shade_local(position, normal, direction, base_rgb, lights: Lights, ambient, specular, shininess, visible=None):
    """Ambient + per light Lambert + Blinn-Phong at one hit (no miss handling); ``visible``
    (L,) scales each light (shadow rays: 0 where occluded). The lights (a static number) are
    summed in a Python loop, in order."""
    d = _unit3(direction)
    n = facing(normal, d)
    v = -d
    ldir, rad, _ = light_at(lights, position)
    col = ambient * base_rgb
    for i in range(ldir.shape[0]):
        ndl = jnp.maximum(dot3(ldir[i], n), 0.0)
        ndh = jnp.maximum(dot3(_unit3(ldir[i] + v), n), 0.0)
        spec = jnp.where(ndl > 0, ndh**shininess, 0.0)
        r = rad[i] if visible is None else rad[i] * visible[i]
        col = col + r * (base_rgb * ndl + specular * spec)
    return col


def srgb_encode(x: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values in [0, 1]."""
    x = np.asarray(x, np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0.0031308), 1.0 / 2.4) - 0.055)


def encode_png(rgb: np.ndarray, gamma: float | None = None) -> np.ndarray:
    """Linear float RGB (H,W,3) -> uint8: the sRGB curve (``gamma`` None) or a power 1/gamma.
    Values are clipped to [0, 1] first; NaN (never produced on purpose) becomes 0."""
    x = np.clip(np.nan_to_num(np.asarray(rgb, np.float64), nan=0.0), 0.0, 1.0)
    x = srgb_encode(x) if gamma is None else x ** (1.0 / gamma)
    return (x * 255.0 + 0.5).astype(np.uint8)


def output_transform(shading) -> float | None:
    """The ``gamma`` argument of :func:`encode_png` for a ``shading`` section."""
    return None if shading.output == "srgb" else shading.gamma
