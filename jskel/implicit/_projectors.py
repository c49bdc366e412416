"""Texture coordinates of an implicit model (Rouiller 2011, Sec. 6, 6.1, Alg. 3): planar,
cylindrical and spherical projectors applied at the rest-pose position a posed point skins
back to, their host arrays, and the image displacement that goes through a projector."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..executor import size_bucket
from ..numerics import dot3, on_device, safe_div, safe_sqrt
from ._config import ImplicitConfig
from ._field import Displace, kernel


class Skin(NamedTuple):
    """Texture skinning inputs for one frame (Sec. 6.1, Alg. 3): per bone the posed segment
    (head, tail), its weight radius, and the rigid map from the posed to the rest pose."""

    head: jnp.ndarray  # (B,3)
    tail: jnp.ndarray  # (B,3)
    influence: jnp.ndarray  # (B,)
    to_rest: jnp.ndarray  # (B,3,4)


class Projector(NamedTuple):
    """K texture projectors (Sec. 6, 6.1): the local ones in config order, then the model's
    global one (region radius inf). A rest-pose point takes the first whose region holds it."""

    origin: jnp.ndarray  # (K,3)
    axis: jnp.ndarray  # (K,3) unit
    up: jnp.ndarray  # (K,3) unit, perpendicular to axis
    scale: jnp.ndarray  # (K,2)
    region_c: jnp.ndarray  # (K,3) rest-pose region centre (relative to the anchor)
    region_r: jnp.ndarray  # (K,) its radius; inf: everywhere


def _unit(v, path):
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v)
    if not n > 0:
        raise ValueError(f"{path}: the zero vector")
    return v / n


def displace_params(cfg: ImplicitConfig, anchor, dtype) -> Displace:
    """Traced displacement inputs; for an image, the bound on |grad (h o uv)| is the largest
    neighbouring-texel difference per texel size times the projector's scale (bilinear
    interpolation never exceeds its texels' finite differences)."""
    dc = cfg.displace
    z3 = np.zeros(3)
    if dc is None or dc.type == "noise":
        amp, freq = (0.0, 1.0) if dc is None else (dc.amplitude, dc.frequency)
        return Displace(on_device(amp, dtype), on_device(freq, dtype), on_device(np.zeros((1, 1)), dtype), on_device(z3, dtype),
                        on_device([1.0, 0, 0], dtype), on_device([0, 1.0, 0], dtype), on_device(np.ones(2), dtype), on_device(0.0, dtype))
    from ..textures import load_height_map

    hmap = load_height_map(dc.map, "object.displace.map").astype(np.float64) / 255.0
    pc = dc.projector
    ax = _unit(pc.axis, "object.displace.projector.axis")
    up = _unit(np.asarray(pc.up, np.float64) - np.dot(pc.up, ax) * ax, "object.displace.projector.up (it is parallel to the axis)")
    side = np.cross(ax, up)
    hh, ww = hmap.shape
    gu = np.max(np.abs(np.diff(hmap, axis=1, append=hmap[:, :1]))) * ww * pc.scale[0]
    gv = np.max(np.abs(np.diff(hmap, axis=0, append=hmap[:1, :]))) * hh * pc.scale[1]
    return Displace(on_device(dc.amplitude, dtype), on_device(1.0, dtype), on_device(hmap, dtype),
                    on_device(np.asarray(pc.origin) - anchor, dtype), on_device(side, dtype), on_device(up, dtype),
                    on_device(pc.scale, dtype), on_device(float(np.hypot(gu, gv)), dtype))


def projector_arrays(cfg: ImplicitConfig, anchor, dtype):
    """Projector (K entries: local ones, then the global one), (textures (K,H,W,3), sizes
    (K,2)), the static kinds and whether each is textured."""
    from ..textures import load_texture

    entries = [(pc, pc.region.center, pc.region.radius, pc.texture or cfg.texture, f"object.projectors[{i}]")
               for i, pc in enumerate(cfg.projectors)]
    if cfg.projector is not None:
        entries.append((cfg.projector, (0.0, 0.0, 0.0), np.inf, cfg.texture, "object.projector"))
    cols = {k: [] for k in ("origin", "axis", "up", "scale", "rc", "rr")}
    images = []
    for pc, centre, radius, texture, where in entries:
        ax = _unit(pc.axis, f"{where}.axis")
        up = _unit(np.asarray(pc.up, np.float64) - np.dot(pc.up, ax) * ax, f"{where}.up (it is parallel to the axis)")
        for k, v in zip(cols, (np.asarray(pc.origin) - anchor, ax, up, pc.scale, np.asarray(centre) - anchor, radius)):
            cols[k].append(v)
        images.append(None if texture is None else load_texture(texture, "object.texture" if texture == cfg.texture else f"{where}.texture"))
    kinds = tuple(pc.type for pc, *_ in entries)
    textured = tuple(im is not None for im in images)
    if not entries:  # one unused projector keeps the shapes non-empty
        cols = {"origin": [np.zeros(3)], "axis": [[0, 1.0, 0]], "up": [[0, 0, 1.0]], "scale": [[1.0, 1]], "rc": [np.zeros(3)], "rr": [0.0]}
        images = [None]
    images = [np.ones((1, 1, 3)) if im is None else im for im in images]
    # padded to size buckets (``executor.size_bucket``): a texture of similar size shares every
    # program; ``sizes`` keeps each one's own, so the padding texels are never sampled
    hmax, wmax = (size_bucket(max(im.shape[k] for im in images)) for k in (0, 1))
    stack = np.zeros((len(images), hmax, wmax, 3))
    for k, im in enumerate(images):
        stack[k, : im.shape[0], : im.shape[1]] = im
    sizes = np.array([im.shape[:2] for im in images], np.int32)
    proj = Projector(*(on_device(np.asarray(cols[k], np.float64), dtype) for k in cols))
    return proj, (on_device(stack, dtype), on_device(sizes)), kinds, textured


def rest_position(skin: Skin, x):
    """Alg. 3: the posed point x mapped to the rest pose, blending each bone's rigid inverse by
    weights (1 - d^2 / I^2)^2 of the distance d to the posed bone (nearest bone if none reaches)."""
    ab = skin.tail - skin.head
    s = jnp.clip(safe_div(dot3(x - skin.head, ab), dot3(ab, ab), 0.0), 0.0, 1.0)
    e = x - skin.head - s[:, None] * ab
    d2 = dot3(e, e)
    w = kernel(d2, skin.influence)
    nearest = (jnp.arange(d2.shape[0]) == jnp.argmin(d2)).astype(x.dtype)
    total = jnp.sum(w)
    w = jnp.where(total > 0, safe_div(w, total, 0.0), nearest)
    moved = jnp.einsum("bij,j->bi", skin.to_rest[:, :, :3], x) + skin.to_rest[:, :, 3]
    return jnp.sum(w[:, None] * moved, axis=0)


def project(pr: Projector, x, kind: str):
    """(u, v) of a rest-pose point (relative to the anchor) for one planar, cylindrical or
    spherical projector (Sec. 6): ``pr`` holds one projector's fields (no leading K axis)."""
    p = x - pr.origin
    side = jnp.cross(pr.axis, pr.up)
    h = dot3(p, pr.axis)
    pu, ps = dot3(p, pr.up), dot3(p, side)
    if kind == "planar":
        uv = jnp.stack([ps, pu])
    elif kind == "cylindrical":
        uv = jnp.stack([jnp.arctan2(ps, pu) / (2 * jnp.pi) + 0.5, h])
    else:  # spherical
        rho = safe_sqrt(pu * pu + ps * ps)
        uv = jnp.stack([jnp.arctan2(ps, pu) / (2 * jnp.pi) + 0.5, jnp.arctan2(rho, h) / jnp.pi])
    return uv * pr.scale
