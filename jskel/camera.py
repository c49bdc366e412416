"""The pinhole look-at camera and the screen-tile order of its rays.

Precision. Cameras are built on the host in float64 and expressed relative to an *anchor* (the
centre of the scene's bounds) before they are cast to the working dtype. A skeleton placed 1e4
away from the world origin is then ray cast in float32 with the precision of one placed at the
origin; only the world position of a hit (anchor + local position) is as coarse as float32 is
at 1e4.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from .rays import Rays, make_rays


class Camera(NamedTuple):
    """Pinhole look-at camera (host-side, float64).

    eye, target, up: (3,) world coordinates; fov_y_deg: vertical field of view in degrees;
    width, height: image size in pixels.
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_y_deg: float
    width: int
    height: int

    def basis(self):
        """Orthonormal camera frame ``(right, true_up, forward)``; raises if ``up`` is degenerate."""
        eye = np.asarray(self.eye, np.float64)
        fwd = np.asarray(self.target, np.float64) - eye
        n = np.linalg.norm(fwd)
        if not n > 0:
            raise ValueError(f"camera.target: equals camera.eye ({list(map(float, eye))})")
        fwd = fwd / n
        up = np.asarray(self.up, np.float64)
        right = np.cross(fwd, up)
        rn = np.linalg.norm(right)
        if not rn > 1e-6 * max(np.linalg.norm(up), 1e-300):
            raise ValueError(
                f"camera.up: {list(map(float, up))} is parallel to the viewing direction "
                f"{list(map(float, np.round(fwd, 6)))}"
            )
        right = right / rn
        true_up = np.cross(right, fwd)
        return right, true_up, fwd

    def rays(self, anchor=None, dtype=np.float32) -> Rays:
        """Primary rays through pixel centres, row-major (row 0 at the top of the image).

        anchor: (3,) world point subtracted from the origins in float64 before casting to
        ``dtype`` (see module docstring). Directions are unit length, t in (0, inf].
        """
        o, d = self.ray_arrays(anchor)
        return make_rays(o, d, 0.0, np.inf, dtype)

    def tiled_rays(self, tile: int, anchor=None, dtype=np.float32) -> Rays:
        """:meth:`rays` in :func:`tile_order`, as host (NumPy) arrays, equal value for value to
        ``permute(self.rays(anchor, dtype), tile_order(...))``. The directions, which depend
        on the camera alone, are cached (an animated frame with a fixed camera makes none);
        the origins are one point, broadcast (the anchor may move from frame to frame)."""
        d = _tiled_directions(self._key(), tile, np.dtype(dtype).name)
        eye = np.asarray(self.eye, np.float64)
        if anchor is not None:
            eye = eye - np.asarray(anchor, np.float64)
        n = d.shape[0]
        o = np.broadcast_to(eye.astype(dtype), (n, 3))
        return Rays(o, d, np.broadcast_to(np.zeros((), dtype), (n,)), np.broadcast_to(np.asarray(np.inf, dtype), (n,)))

    def _key(self) -> tuple:
        return (tuple(map(float, self.eye)), tuple(map(float, self.target)), tuple(map(float, self.up)), float(self.fov_y_deg),
                int(self.width), int(self.height))

    def ray_arrays(self, anchor=None, jitter=None) -> tuple[np.ndarray, np.ndarray]:
        """(origins, directions), both (H*W, 3) float64 NumPy, as :meth:`rays` casts them.

        jitter: None (pixel centres) or (H*W, 2) offsets in pixels (x right, y down) of each
        ray's point in its pixel, e.g. uniform in [-0.5, 0.5) for jittered anti-aliasing."""
        right, up, fwd = self.basis()
        w, h = int(self.width), int(self.height)
        tan_half = math.tan(math.radians(self.fov_y_deg) / 2.0)
        aspect = w / h
        ix, iy = np.meshgrid(np.arange(w, dtype=np.float64) + 0.5, np.arange(h, dtype=np.float64) + 0.5)
        if jitter is not None:
            j = np.asarray(jitter, np.float64).reshape(h, w, 2)
            ix, iy = ix + j[..., 0], iy + j[..., 1]
        px = (ix / w * 2.0 - 1.0) * tan_half * aspect
        py = (1.0 - iy / h * 2.0) * tan_half
        d = fwd[None, :] + px.reshape(-1, 1) * right[None, :] + py.reshape(-1, 1) * up[None, :]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        eye = np.asarray(self.eye, np.float64)
        if anchor is not None:
            eye = eye - np.asarray(anchor, np.float64)
        return np.broadcast_to(eye, d.shape).copy(), d


@functools.lru_cache(maxsize=4)
def _tiled_directions(key: tuple, tile: int, dtype: str) -> np.ndarray:
    """Unit directions of a camera's rays in :func:`tile_order`, cast to ``dtype`` (read-only)."""
    eye, target, up, fov, w, h = key
    cam = Camera(np.asarray(eye), np.asarray(target), np.asarray(up), fov, w, h)
    d = cam.ray_arrays()[1][tile_order(w, h, tile)].astype(dtype)
    d.flags.writeable = False
    return d


def _morton2(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Interleave the bits of two non-negative int arrays (< 2^16): a 2D Z-order key."""
    def spread(v):
        v = v.astype(np.uint64) & 0xFFFF
        v = (v | (v << 8)) & 0x00FF00FF
        v = (v | (v << 4)) & 0x0F0F0F0F
        v = (v | (v << 2)) & 0x33333333
        v = (v | (v << 1)) & 0x55555555
        return v

    return spread(x) | (spread(y) << np.uint64(1))


@functools.lru_cache(maxsize=8)
def tile_order(width: int, height: int, tile: int) -> np.ndarray:
    """Permutation of row-major pixel indices that lists pixels tile by tile (tile x tile), and
    within a tile in Z-order (Morton order of the pixel's position in its tile).

    Chunks of consecutive rays are then compact on screen, which is what lets a batch-level
    test (one scalar per chunk) skip geometry that no ray of the chunk can reach; with a
    power-of-two tile, every aligned run of 4^j rays inside a tile is a 2^j x 2^j square, which
    is what packet traversal (``jskel.accel.nearest_packet``) wants of its packets.
    """
    ys, xs = np.divmod(np.arange(width * height), width)
    tiles = (ys // tile) * (-(-width // tile)) + xs // tile
    key = tiles.astype(np.uint64) * np.uint64(1 << 32) + _morton2(xs % tile, ys % tile)
    order = np.argsort(key, kind="stable")
    order.flags.writeable = False  # cached (lru_cache): shared by every caller
    return order


@functools.lru_cache(maxsize=8)
def tile_inverse(width: int, height: int, tile: int) -> np.ndarray:
    """The inverse permutation of :func:`tile_order` (cached): ``a[tile_inverse(...)]`` puts
    values computed in tile order back in row-major order."""
    order = tile_order(width, height, tile)
    inv = np.empty_like(order)
    inv[order] = np.arange(order.size)
    inv.flags.writeable = False
    return inv


def permute(rays: Rays, order: np.ndarray) -> Rays:
    """The rays in the order of the index array ``order`` (e.g. :func:`tile_order`)."""
    return Rays(*(a[order] for a in rays))


def framing(lo, hi, view, fov_y_deg: float, width: int, height: int, margin: float = 1.05):
    """(eye, target) in float64 for a camera that sees the box [lo, hi] whole: the target at
    its centre, the eye along ``view`` at the distance where the box's bounding sphere (radius
    times ``margin``) fills the narrower of the vertical and horizontal fields of view."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    centre = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-12) * margin
    half_y = math.radians(fov_y_deg) / 2
    half_x = math.atan(math.tan(half_y) * width / height)
    v = np.asarray(view, np.float64)
    return centre + radius / math.sin(min(half_x, half_y)) * v / np.linalg.norm(v), centre

