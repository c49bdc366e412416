"""Relief-mapped conical frusta, Bhagvat et al. 2009 (seed 001): skeleton -> frusta -> hits.

Public API:

* :func:`build` (host) validates a skeleton and returns a :class:`jskel.interface.Built`;
* :func:`intersect_one` / :func:`intersect` ray cast it (pure, jit/vmap friendly);
* :func:`frusta_from_skeleton` is the array-level entry point for scripts and notebooks;
* :func:`frusta_mesh` tessellates frusta (Table 1's mesh), :func:`export_mesh` writes it (PLY, OBJ, glTF);
* :func:`segment_axes`, :func:`joint_planes`, :func:`cutting_planes` are the geometry (JAX,
  differentiable) that the host build, the device rebuild and the fit share;
* ``REPRESENTATION`` is what the registry hands to the renderer."""

from ._build import FrustaArrays as FrustaArrays
from ._config import FrustaConfig as FrustaConfig
from ._intersect import FrustaParams as FrustaParams
from ._scene import FrustaPayload as FrustaPayload
from ._pack import FrustaScene as FrustaScene
from ._pack import Group as Group
from ._intersect import Quality as Quality
from ..textures import RELIEF_TEXTURES as RELIEF_TEXTURES
from ._scene import REPRESENTATION as REPRESENTATION
from ._relief import ReliefMaps as ReliefMaps
from ._relief import ReliefQuality as ReliefQuality
from ._geometry import ELLIPSE_MARGIN as ELLIPSE_MARGIN
from ._geometry import PIECE_REACH as PIECE_REACH
from ._geometry import plane_reach as plane_reach
from ._build import piece_reach as piece_reach
from ._edits import ANIMATED as ANIMATED
from ._geometry import cone_sin as cone_sin
from ._geometry import joint_planes as joint_planes
from ._geometry import segment_axes as segment_axes
from ._device import rebuilder as rebuilder
from ._config import SkeletonConfig as SkeletonConfig
from ._pack import Static as Static
from ._scene import albedo as albedo
from ._pack import block_spheres as block_spheres
from ._scene import build as build
from ._build import build_frusta as build_frusta
from ._scene import cast as cast
from ._geometry import cutting_planes as cutting_planes
from ._edits import frusta_from_skeleton as frusta_from_skeleton
from ._export import export_mesh as export_mesh
from ._export import frusta_mesh as frusta_mesh
from ._export import mesh_format as mesh_format
from ._edits import host_frusta as host_frusta
from ._scene import inside as inside
from ._scene import intersect as intersect
from ._scene import intersect_batch as intersect_batch
from ._scene import intersect_one as intersect_one
from ..textures import load_height_map as load_height_map
from ._pack import make_group as make_group
from ._build import minor_semi_axis as minor_semi_axis
from ._maps import relief_memory as relief_memory
from ._pack import rim_points as rim_points
from ._edits import skeleton_arrays as skeleton_arrays
from ._scene import surface as surface
from ._pack import to_params as to_params
from ._skeleton import topology as topology
from ._scene import pair_test_seconds as pair_test_seconds
from ._scene import traversal_stats as traversal_stats
from ._skeleton import validate_skeleton as validate_skeleton

__all__ = ["ANIMATED", "ELLIPSE_MARGIN", "PIECE_REACH", "FrustaArrays", "FrustaConfig", "FrustaParams", "FrustaPayload", "FrustaScene", "Group", "Quality", "RELIEF_TEXTURES", "REPRESENTATION", "ReliefMaps", "ReliefQuality", "SkeletonConfig", "Static", "albedo", "block_spheres", "build", "build_frusta", "cast", "cone_sin", "cutting_planes", "export_mesh", "frusta_from_skeleton", "frusta_mesh", "host_frusta", "inside", "intersect", "intersect_batch", "intersect_one", "joint_planes", "load_height_map", "make_group", "mesh_format", "minor_semi_axis", "pair_test_seconds", "piece_reach", "plane_reach", "rebuilder", "relief_memory", "rim_points", "segment_axes", "skeleton_arrays", "surface", "to_params", "topology", "traversal_stats", "validate_skeleton"]
