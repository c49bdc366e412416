"""Relief height maps on the host (Bhagvat et al. 2009, Sec. 3-4): what a relief object costs
in memory beside the displaced triangle mesh it stands for. Reading a map (a named scikit-image
texture or an image file) is ``jskel.textures.load_height_map``, shared with the implicit
surfaces' displacement."""

from __future__ import annotations

import numpy as np

from ._build import FrustaArrays




def relief_memory(arr: FrustaArrays, height: np.ndarray, scale, relief_ids, dtype_bytes: int = 4, pyramid_bytes: int = 0,
                  texel_bytes: int = 1) -> dict:
    """Bytes of the representation beside an equivalent displaced triangle mesh (Sec. 4).
    ``pyramid_bytes``: the exact tracer's min/max pyramid (``_relief_exact.pyramid``; 0 for the
    march), counted in the representation's bytes; ``texel_bytes``: 1 for the 8-bit map, the
    float type's for ``relief.storage: float``.

    The mesh samples each relief segment at the height map's texel density (one vertex per
    texel of the tiled map over the segment: W * scale_u by H * scale_v), with float32
    positions (12 B) and two triangles per vertex (24 B of int32 indices).
    """
    s = arr.h.shape[0]
    per_seg = 3 + 3 + 3 + 3 + 1 + 1 + 1 + 3 + 1 + 3 + 1 + 1 + 1 + 1  # floats in FrustaParams
    frusta_b = s * per_seg * dtype_bytes
    maps_b = int(height.size) * texel_bytes
    hh, ww = height.shape
    verts = len(relief_ids) * (ww * float(scale[0])) * (hh * float(scale[1]))
    mesh_b = int(verts * 12 + 2 * verts * 12)
    return {"frusta_bytes": int(frusta_b), "relief_map_bytes": maps_b, "pyramid_bytes": int(pyramid_bytes),
            "representation_bytes": int(frusta_b + maps_b + pyramid_bytes),
            "mesh_vertices": int(verts), "mesh_triangles": int(2 * verts), "mesh_bytes": mesh_b}
