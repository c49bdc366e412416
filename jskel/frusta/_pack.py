"""Packing a frusta object for the device: segments cast the same way (plain or relief) padded
to blocks, with a bounding sphere per block (Bhagvat et al. 2009, Sec. 2.6), gathered in the
scene pytree beside its static options."""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from ..executor import size_bucket
from ..numerics import on_device
from ._build import FrustaArrays
from ._intersect import FrustaParams, Quality
from ._relief import ReliefMaps, ReliefQuality


class Group(NamedTuple):
    """Segments cast the same way, padded to blocks, with a bounding sphere per block."""

    frusta: FrustaParams
    block_c: jnp.ndarray  # (B,3) bounding sphere centre of each block of segments
    block_r: jnp.ndarray  # (B,) its radius
    bvh: object = None  # plain: ``_accel.FrustaBVH`` when ``accel: bvh``; relief: an ``accel.BVH`` over the shells' boxes unless ``cull: blocks``
    seg_c: jnp.ndarray | None = None  # relief: (S,3) bounding sphere centre of each segment's outer solid
    seg_r: jnp.ndarray | None = None  # relief: (S,) its radius (-1: padding)


class FrustaScene(NamedTuple):
    """Device pytree: plain and relief segments (either may be None) plus shading inputs.

    Segments with relief are split from plain ones at build time, so each ray batch runs the
    analytic test only over plain segments and the relief march only over relief segments:
    compaction at build time instead of masking per segment under vmap.
    """

    plain: Group | None
    relief: Group | None
    maps: ReliefMaps | None
    colors: jnp.ndarray  # (S, 3) linear RGB per segment id, zero rows up to the next power of two (>= 8)
    texture: jnp.ndarray  # (H', W', 3) linear RGB padded to size buckets, (8, 8, 3) when unused
    tex_scale: jnp.ndarray  # (2,) repeats of the texture per unit u and v
    tex_size: jnp.ndarray  # (2,) int32 the texture's own (H, W): its top-left texels, the rest padding


class Static(NamedTuple):
    """Static options of a frusta object (what recompiles when it changes): quality, relief options, acceleration, leaf, group and packet sizes."""

    quality: Quality  # normals and the plain group's block size
    has_texture: bool
    relief: ReliefQuality | None = None
    relief_block: int = 8
    accel: str = "blocks"  # blocks | bvh (plain segments)
    leaf: int = 4
    group: int = 512
    packet: int = 256  # bvh: rays per shared traversal (0: per-ray walks in groups of ``group``)
    traversal: str = "packets"  # bvh: bins | packets | walks | kernel (resolved from ``object.traversal``)
    kernel_block: int = 32
    kernel_warps: int = 1
    bins: tuple = (64, 128, 256, 32, 1.5)  # bins: rays per packet, candidates and pairs per step, slots per group, walk ratio
    relief_cull: str = "blocks"  # relief: blocks | tree | packets (resolved from ``object.relief.cull``)


def _pad(a: np.ndarray, n: int, fill) -> np.ndarray:
    pad = n - a.shape[0]
    if pad == 0:
        return a
    tail = np.broadcast_to(np.asarray(fill, a.dtype), (pad,) + a.shape[1:])
    return np.concatenate([a, tail], axis=0)


def to_params(arr: FrustaArrays, anchor: np.ndarray, block: int, dtype=np.float32, ids=None, shell=None) -> FrustaParams:
    """Cast host arrays (the rows ``ids``) to a padded device ``FrustaParams`` relative to
    ``anchor``: rows of a size bucket (``executor.size_bucket``, a multiple of ``block``), so a
    skeleton of similar size shares every program; padding rows are invalid (never hit)."""
    ids = np.arange(arr.h.shape[0]) if ids is None else np.asarray(ids)
    s = ids.shape[0]
    n = size_bucket(s, block)
    fields = {k: np.asarray(v)[ids] for k, v in arr._asdict().items()}
    fields["c1"] = fields["c1"] - anchor[None, :]
    fields["shell"] = np.zeros(s) if shell is None else np.asarray(shell, np.float64)[ids]
    out = {}
    for k, v in fields.items():
        fill = {"m": (0.0, 1.0, 0.0), "u": (1.0, 0.0, 0.0), "w": (0.0, 0.0, 1.0), "h": 1.0, "nb": (0.0, 1.0, 0.0), "nt": (0.0, 1.0, 0.0), "dt": 1.0}.get(k, 0)
        v = _pad(np.asarray(v), n, fill)
        out[k] = on_device(v, bool if v.dtype == bool else dtype)
    out["valid"] = on_device(np.arange(n) < s)
    out["sid"] = on_device(_pad(ids.astype(np.int32), n, -1))
    return FrustaParams(**out)


def _block_size(cfg_block: int, count: int) -> int:
    """A small group gets a smaller block, so a well of 8 segments is not padded to 64."""
    return int(min(cfg_block, max(8, 1 << int(np.ceil(np.log2(max(count, 1)))))))


def make_group(arr: FrustaArrays, ids, anchor, cfg_block: int, dtype, shell=None, spheres: bool = True) -> tuple[Group, int]:
    """Device arrays of the segments ``ids`` (plain or relief): their padded params and block
    bounding spheres (``spheres=False``: one dummy sphere, for a group cast through the BVH,
    which never reads them: their host loop over blocks would be wasted work every frame);
    returns (group, block size used)."""
    block = _block_size(cfg_block, len(ids))
    params = to_params(arr, anchor, block, dtype, ids, shell)
    sub = FrustaArrays(*(np.asarray(v)[ids] for v in arr))
    if shell is not None:  # bound the outer frusta of the shell
        t = np.asarray(shell)[ids]
        sub = sub._replace(r1=sub.r1 + t, r2=sub.r2 + t)
    bc, br = block_spheres(sub, anchor, block) if spheres else (np.zeros((0, 3)), np.zeros(0))
    if bc.shape[0] == 0:
        bc, br = np.zeros((1, 3)), np.full(1, -1.0)
    if spheres:  # a sphere per block of the padded rows: the padding blocks' radius -1, met by no ray
        nb = params.h.shape[0] // block
        bc, br = _pad(bc, nb, 0.0), _pad(br, nb, -1.0)
    if shell is None:
        return Group(params, on_device(bc, dtype), on_device(br, dtype)), block
    # relief: a sphere per segment too, so a ray's pairs with a block are tested against its
    # segments' spheres before the costlier shell test (``_intersect.nearest_batch_compact``)
    sc, sr = block_spheres(sub, anchor, 1)
    rows = params.h.shape[0]
    return Group(params, on_device(bc, dtype), on_device(br, dtype), None,
                 on_device(_pad(sc, rows, 0.0), dtype), on_device(_pad(sr, rows, -1.0), dtype)), block


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
