"""Relief-mapped conical frusta, Bhagvat et al. 2009 (seed 001): skeleton -> frusta -> hits.

Public API:

* :func:`build` (host) validates a skeleton and returns a :class:`jskel.interface.Built`;
* :func:`intersect_one` / :func:`intersect` ray cast it (pure, jit/vmap friendly);
* :func:`frusta_from_skeleton` is the array-level entry point for scripts and notebooks;
* ``REPRESENTATION`` is what the registry hands to the renderer.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..interface import Built
from ..rays import Hit, Rays
from ._build import FrustaArrays as FrustaArrays
from ._build import build_frusta as build_frusta
from ._build import cutting_planes as cutting_planes
from ._build import minor_semi_axis as minor_semi_axis
from ._config import FrustaConfig as FrustaConfig
from ._config import SkeletonConfig as SkeletonConfig
from ._intersect import FrustaParams as FrustaParams
from ._intersect import Quality as Quality
from ._intersect import inside_one as _inside_one
from ._intersect import intersect_batch as _intersect_batch
from ._intersect import intersect_one as _intersect_one
from ._skeleton import topology as topology
from ._skeleton import validate_skeleton as validate_skeleton

_SIDE_BRANCH_COLOR_PATH = "object.skeleton.colors"


class FrustaScene(NamedTuple):
    """Device pytree: the frusta plus what shading needs."""

    frusta: FrustaParams
    colors: jnp.ndarray  # (S_pad, 3) linear RGB per segment
    texture: jnp.ndarray  # (H, W, 3) linear RGB, (1, 1, 3) when unused
    tex_scale: jnp.ndarray  # (2,) repeats of the texture per unit u and v
    block_c: jnp.ndarray  # (B,3) bounding sphere centre of each block of segments
    block_r: jnp.ndarray  # (B,) its radius


class Static(NamedTuple):
    quality: Quality
    has_texture: bool


def _pad(a: np.ndarray, n: int, fill) -> np.ndarray:
    pad = n - a.shape[0]
    if pad == 0:
        return a
    tail = np.broadcast_to(np.asarray(fill, a.dtype), (pad,) + a.shape[1:])
    return np.concatenate([a, tail], axis=0)


def to_params(arr: FrustaArrays, anchor: np.ndarray, block: int, dtype=np.float32) -> FrustaParams:
    """Cast host arrays to a padded device ``FrustaParams`` relative to ``anchor``."""
    s = arr.h.shape[0]
    n = -(-s // block) * block
    fields = arr._asdict()
    fields["c1"] = fields["c1"] - anchor[None, :]
    out = {}
    for k, v in fields.items():
        fill = {"m": (0.0, 1.0, 0.0), "u": (1.0, 0.0, 0.0), "w": (0.0, 0.0, 1.0), "h": 1.0, "nb": (0.0, 1.0, 0.0), "nt": (0.0, 1.0, 0.0), "dt": 1.0}.get(k, 0)
        v = _pad(np.asarray(v), n, fill)
        out[k] = jnp.asarray(v, dtype=jnp.bool_ if v.dtype == bool else dtype)
    out["valid"] = jnp.asarray(np.arange(n) < s)
    return FrustaParams(**out)


def rim_points(arr: FrustaArrays, n_ang: int = 64) -> np.ndarray:
    """(S, 2*n_ang, 3) points where generators meet the two cutting planes (host, float64).

    The clipped frustum is the convex hull of its two elliptical cuts, so bounds of these points
    (grown by the chord sag 1 - cos(pi / n_ang)) bound the frustum (Sec. 2.6 uses pyramids).
    """
    ang = np.linspace(0, 2 * np.pi, n_ang, endpoint=False)
    rad = np.cos(ang)[None, :, None] * arr.u[:, None, :] + np.sin(ang)[None, :, None] * arr.w[:, None, :]
    k = (arr.r2 - arr.r1) / arr.h
    base = arr.c1[:, None, :] + arr.r1[:, None, None] * rad
    dirn = arr.m[:, None, :] + k[:, None, None] * rad
    out = []
    for n, dist in ((arr.nb, arr.db), (arr.nt, arr.dt)):
        den = np.einsum("sk,sak->sa", n, dirn)
        y = (dist[:, None] - np.einsum("sk,sak->sa", n, base - arr.c1[:, None, :])) / np.where(den == 0, 1.0, den)
        out.append(base + y[..., None] * dirn)
    return np.concatenate(out, axis=1)


def block_spheres(arr: FrustaArrays, anchor: np.ndarray, block: int):
    """Bounding sphere (centre relative to anchor, radius) of each block of segments."""
    pts = rim_points(arr) - anchor
    s = pts.shape[0]
    n = -(-s // block) * block
    sag = 1.0 - np.cos(np.pi / 64)
    rmax = np.maximum(arr.r1, arr.r2)
    cs, rs = [], []
    for i in range(0, n, block):  # host loop over blocks at build time
        p = pts[i : i + block].reshape(-1, 3)
        if p.shape[0] == 0:
            cs.append(np.zeros(3))
            rs.append(-1.0)  # padding block: no ray touches it
            continue
        lo, hi = p.min(0), p.max(0)
        c = 0.5 * (lo + hi)
        r = np.sqrt(np.max(np.sum((p - c) ** 2, -1))) + 2 * sag * float(np.max(rmax[i : i + block])) + 1e-6 * (1 + np.linalg.norm(c))
        cs.append(c)
        rs.append(r)
    return np.array(cs), np.array(rs)


def frusta_from_skeleton(joints, radii, parents, *, twist_deg=0.0, match_minor_axes=False, path="object.skeleton"):
    """Validate a skeleton and build its frusta on the host (float64). Returns (arrays, topo, info)."""
    j, r, p = validate_skeleton(joints, radii, parents, path)
    topo = topology(j, p, path)
    arrays, info = build_frusta(j, r, topo, twist_turns=twist_deg / 360.0, match_minor_axes=match_minor_axes)
    return arrays, topo, info


def _skeleton_arrays(sk: SkeletonConfig):
    if sk.procedural is not None:
        from ..scenes import generate

        j, r, p, colors = generate(sk.procedural, sk.seed, dict(sk.options))
    else:
        j = np.asarray(sk.joints, np.float64)
        r = np.asarray(sk.radii, np.float64)
        p = np.asarray(sk.parents, np.int64)
        colors = None if sk.colors is None else np.asarray(sk.colors, np.float64)
        if colors is not None and colors.shape[0] != j.shape[0]:
            raise ValueError(f"{_SIDE_BRANCH_COLOR_PATH}: has {colors.shape[0]} entries for {j.shape[0]} joints")
    j = j * sk.scale + np.asarray(sk.offset, np.float64)
    return j, r * sk.scale, p, colors


def _load_texture(path: str) -> np.ndarray:
    import imageio.v3 as iio

    try:
        img = np.asarray(iio.imread(path))
    except Exception as e:  # noqa: BLE001 - any reader failure is a bad config value
        raise ValueError(f"object.texture: cannot read image {path!r}: {e}") from None
    if img.ndim == 2:
        img = np.stack([img] * 3, -1)
    img = img[..., :3].astype(np.float64)
    img = img / (255.0 if img.max() > 1.0 else 1.0)
    return img**2.2  # sRGB-ish to linear


def build(cfg: FrustaConfig, dtype=np.float32) -> Built:
    """Host-side build: validate, cut, frame, pad, cast. Raises ValueError naming the field."""
    j, r, p, colors = _skeleton_arrays(cfg.skeleton)
    arrays, topo, info = frusta_from_skeleton(j, r, p, twist_deg=cfg.twist_deg, match_minor_axes=cfg.match_minor_axes)
    rmax = r[:, None]
    lo = np.min(j - rmax, axis=0)
    hi = np.max(j + rmax, axis=0)
    anchor = 0.5 * (lo + hi)
    # a small skeleton gets a smaller block, so a well of 8 segments is not padded to 64
    block = int(min(cfg.block, max(8, 1 << int(np.ceil(np.log2(arrays.h.shape[0]))))))
    params = to_params(arrays, anchor, block, dtype)
    s = arrays.h.shape[0]
    n = params.h.shape[0]
    if colors is None:
        seg_col = np.broadcast_to(np.asarray(cfg.color, np.float64), (s, 3))
    else:
        seg_col = colors[topo.seg_end]
    seg_col = _pad(np.asarray(seg_col, np.float64), n, 0.0)
    if cfg.texture is not None:
        tex = _load_texture(cfg.texture)
    else:
        tex = np.ones((1, 1, 3))
    bc, br = block_spheres(arrays, anchor, block)
    scene = FrustaScene(
        frusta=params,
        colors=jnp.asarray(seg_col, dtype),
        texture=jnp.asarray(tex, dtype),
        tex_scale=jnp.asarray(cfg.texture_scale, dtype),
        block_c=jnp.asarray(bc, dtype),
        block_r=jnp.asarray(br, dtype),
    )
    static = Static(Quality(normals=cfg.normals, block=block), cfg.texture is not None)
    info = dict(info, segments=int(s), joints=int(j.shape[0]), padded_segments=int(n))
    return Built(scene, static, anchor, (lo, hi), info)


def intersect_one(scene: FrustaScene, static: Static, origin, direction, t_min, t_max) -> Hit:
    """Nearest hit of one ray with the frusta of ``scene``."""
    return _intersect_one(scene.frusta, origin, direction, t_min, t_max, static.quality)


def intersect(scene: FrustaScene, static: Static, rays: Rays) -> Hit:
    """Batched :func:`intersect_one` (vmap over the ray axis)."""
    f = jax.vmap(lambda o, d, a, b: intersect_one(scene, static, o, d, a, b))
    return f(rays.origins, rays.directions, rays.t_min, rays.t_max)


def intersect_batch(scene: FrustaScene, static: Static, rays: Rays) -> Hit:
    """Like :func:`intersect`, but skips blocks of segments that no ray of the batch reaches."""
    return _intersect_batch(
        scene.frusta, scene.block_c, scene.block_r, rays.origins, rays.directions, rays.t_min, rays.t_max, static.quality
    )


def _bilinear_wrap(tex, uv):
    h, w = tex.shape[0], tex.shape[1]
    x = uv[0] * w - 0.5
    y = uv[1] * h - 0.5
    x0 = jnp.floor(x)
    y0 = jnp.floor(y)
    fx, fy = x - x0, y - y0
    x0 = x0.astype(jnp.int32)
    y0 = y0.astype(jnp.int32)

    def at(yy, xx):
        return tex[jnp.mod(yy, h), jnp.mod(xx, w)]

    return (
        (1 - fx) * (1 - fy) * at(y0, x0)
        + fx * (1 - fy) * at(y0, x0 + 1)
        + (1 - fx) * fy * at(y0 + 1, x0)
        + fx * fy * at(y0 + 1, x0 + 1)
    )


def albedo(scene: FrustaScene, static: Static, hit: Hit):
    """Base colour at one hit: the texture through (u, v) (wrapping), else the segment colour."""
    if static.has_texture:
        return _bilinear_wrap(scene.texture, hit.uv * scene.tex_scale)
    return scene.colors[jnp.maximum(hit.prim, 0)]


def inside(scene: FrustaScene, static: Static, point):
    """True when ``point`` (3,), relative to the anchor, is inside the skinned skeleton."""
    return _inside_one(scene.frusta, point)


class _Frusta:
    name = "frusta"
    Config = FrustaConfig
    build = staticmethod(build)
    intersect_one = staticmethod(intersect_one)
    intersect_batch = staticmethod(intersect_batch)
    albedo = staticmethod(albedo)
    inside = staticmethod(inside)


REPRESENTATION = _Frusta()
