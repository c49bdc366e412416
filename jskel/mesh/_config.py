"""The ``object`` section of a triangle-mesh experiment (``type: mesh``)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field

from ..config import RGB, StrictModel, Vec3


class MeshConfig(StrictModel):
    """A triangle mesh read from ``path`` (OBJ, PLY, STL, OFF, GLB: whatever trimesh reads),
    scaled by ``scale`` about the origin and moved by ``offset`` (world units).

    ``normals``: ``flat`` shades with each face's normal, ``smooth`` with the vertex normals
    trimesh gives (area-weighted), interpolated by the hit's barycentric coordinates.
    ``traversal``: ``packets`` (default) walks the BVH once for each packet of ``packet``
    consecutive rays (coherent camera rays in screen tiles share a walk; ``accel.nearest_packet``),
    ``walks`` walks it once per ray in vmapped groups of ``group`` rays (better for incoherent
    rays). ``leaf``: triangles per BVH leaf."""

    type: Literal["mesh"]
    path: str
    scale: Annotated[float, Field(gt=0.0)] = 1.0
    offset: Vec3 = (0.0, 0.0, 0.0)
    color: RGB = (0.7, 0.7, 0.72)
    normals: Literal["flat", "smooth"] = "flat"
    leaf: Annotated[int, Field(ge=1, le=64)] = 4
    traversal: Literal["packets", "walks"] = "packets"
    packet: Annotated[int, Field(ge=1, le=65536)] = 64
    group: Annotated[int, Field(ge=1, le=65536)] = 64
