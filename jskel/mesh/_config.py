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
    """Selects this representation."""
    path: str
    """The mesh file (OBJ, PLY, STL, OFF, GLB: whatever trimesh reads)."""
    scale: Annotated[float, Field(gt=0.0)] = 1.0
    """Scale about the origin."""
    offset: Vec3 = (0.0, 0.0, 0.0)
    """Translation after ``scale``, world units."""
    color: RGB = (0.7, 0.7, 0.72)
    """Linear RGB colour of the surface."""
    normals: Literal["flat", "smooth"] = "flat"
    """Face normals, or trimesh's area-weighted vertex normals interpolated by barycentric coordinates."""
    leaf: Annotated[int, Field(ge=1, le=64)] = 4
    """Triangles per BVH leaf."""
    traversal: Literal["auto", "packets", "walks", "bins"] = "auto"
    """One BVH walk per packet of ``packet`` coherent rays, one per ray in vmapped groups of ``group``, or packet
    candidate lists (``bins``: each packet of ``bin_packet`` rays tests only the triangles whose box it may meet);
    ``auto``: bins on the CPU for large meshes, packets otherwise (``mesh.traversal_of``)."""
    packet: Annotated[int, Field(ge=1, le=65536)] = 64
    """``packets``: consecutive rays sharing one walk."""
    group: Annotated[int, Field(ge=1, le=65536)] = 64
    """``walks``: rays per vmapped group of walks (and ``bins``' walks, for the chunks it hands them)."""
    bin_packet: Annotated[int, Field(ge=1, le=65536)] = 64
    """``bins``: consecutive rays sharing one candidate list (64 and ``bin_pairs`` 256 were best or within the spread
    under AVX-512 and AVX2 alike: docs/choices.md#mesh-bins-isa)."""
    bin_candidates: Annotated[int, Field(ge=1, le=65536)] = 128
    """``bins``: triangles tested against every packet at once."""
    bin_pairs: Annotated[int, Field(ge=1, le=65536)] = 256
    """``bins``: (packet, triangle) pairs cast at once."""
    bin_group: Annotated[int, Field(ge=0, le=65536)] = 32
    """``bins``: leaf slots per BVH node tested before its triangles (0: every triangle's box)."""
    bin_walk_ratio: Annotated[float, Field(ge=0.0, le=1e6)] = 8.0
    """``bins``: a chunk whose list holds more triangles per ray than this walks instead (0: never)."""
