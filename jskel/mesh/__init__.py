"""Triangle meshes (OBJ, PLY, STL through trimesh), cast through the shared BVH: ``type: mesh``.

Public API: :func:`build`, :func:`cast` / :func:`surface` (the interface's two stages),
:func:`intersect_one` (brute force), :func:`inside` (winding number), :func:`read_mesh`;
``REPRESENTATION`` for the registry."""

from ._config import MeshConfig as MeshConfig
from ._scene import REPRESENTATION as REPRESENTATION
from ._scene import MeshParams as MeshParams
from ._scene import Static as Static
from ._scene import build as build
from ._scene import cast as cast
from ._scene import inside as inside
from ._scene import intersect_batch as intersect_batch
from ._scene import intersect_one as intersect_one
from ._scene import read_mesh as read_mesh
from ._scene import surface as surface
from ._scene import winding_number as winding_number
from ._triangle import triangle_t as triangle_t

__all__ = ["MeshConfig", "MeshParams", "REPRESENTATION", "Static", "build", "cast", "inside", "intersect_batch", "intersect_one",
           "read_mesh", "surface", "triangle_t", "winding_number"]
