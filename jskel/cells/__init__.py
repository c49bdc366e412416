"""Cell-based objects, Nürnberg 2011 (seed 004): tileable cell tiles (``_tiles``), membership
maps (``_membership``), a ray tracer for first hit, self-reflection and refraction (``_trace``);
``build`` precomputes (and caches) an object from a ``type: cells`` section."""

from ._scene import REPRESENTATION as REPRESENTATION
from ._scene import CellsConfig as CellsConfig
from ._scene import Static as Static
from ._scene import albedo as albedo
from ._scene import base_inside as base_inside
from ._scene import build as build
from ._scene import inside as inside
from ._scene import intersect_one as intersect_one
from ._scene import normal_map as normal_map
from ._scene import precompute as precompute
from ._scene import steps_per_ray as steps_per_ray
from ._scene import traversal_stats as traversal_stats
from ._trace import CellParams as CellParams
from ._trace import TraceOptions as TraceOptions

__all__ = ["CellParams", "CellsConfig", "REPRESENTATION", "Static", "TraceOptions", "albedo", "base_inside", "build", "inside", "intersect_one", "normal_map", "precompute", "steps_per_ray", "traversal_stats"]
