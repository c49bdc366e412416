"""Relief height maps on the host (Bhagvat et al. 2009, Sec. 3-4): reading one (a named
scikit-image texture or an image file) and what a relief object costs in memory beside the
displaced triangle mesh it stands for."""

from __future__ import annotations

import numpy as np

from ..textures import finite_texels

from ._build import FrustaArrays


RELIEF_TEXTURES = ("brick", "gravel", "grass")


def load_height_map(name: str) -> np.ndarray:
    """An 8-bit height map: a scikit-image texture photograph by name, or an image file."""
    if name in RELIEF_TEXTURES:
        import skimage.data

        img = np.asarray(getattr(skimage.data, name)())
    else:
        import imageio.v3 as iio

        try:
            img = np.asarray(iio.imread(name))
        except Exception as e:  # noqa: BLE001 - any reader failure is a bad config value
            raise ValueError(f"object.relief.map: cannot read image {name!r} (or name one of {', '.join(RELIEF_TEXTURES)}): {e}") from None
    if img.ndim >= 2 and img.dtype.kind == "f":
        finite_texels(img, "object.relief.map", name)
    if img.ndim == 3:
        img = img[..., :3].mean(-1)
    if img.dtype != np.uint8:
        img = img.astype(np.float64)
        hi = img.max()
        img = np.round(255.0 * img / (hi if hi > 1.0 else 1.0))
    if img.ndim != 2 or min(img.shape) < 2:
        raise ValueError(f"object.relief.map: need a 2D image of at least 2x2 texels (got shape {img.shape})")
    return np.clip(img, 0, 255).astype(np.uint8)


def relief_memory(arr: FrustaArrays, height: np.ndarray, scale, relief_ids, dtype_bytes: int = 4) -> dict:
    """Bytes of the representation beside an equivalent displaced triangle mesh (Sec. 4).

    The mesh samples each relief segment at the height map's texel density (one vertex per
    texel of the tiled map over the segment: W * scale_u by H * scale_v), with float32
    positions (12 B) and two triangles per vertex (24 B of int32 indices).
    """
    s = arr.h.shape[0]
    per_seg = 3 + 3 + 3 + 3 + 1 + 1 + 1 + 3 + 1 + 3 + 1 + 1 + 1 + 1  # floats in FrustaParams
    frusta_b = s * per_seg * dtype_bytes
    maps_b = int(height.size)  # uint8
    hh, ww = height.shape
    verts = len(relief_ids) * (ww * float(scale[0])) * (hh * float(scale[1]))
    mesh_b = int(verts * 12 + 2 * verts * 12)
    return {"frusta_bytes": int(frusta_b), "relief_map_bytes": maps_b, "representation_bytes": int(frusta_b + maps_b),
            "mesh_vertices": int(verts), "mesh_triangles": int(2 * verts), "mesh_bytes": mesh_b}
